//! Charts for the examples: scatter plots with a Pareto front, line charts and grouped bars, as
//! PNG and SVG, drawn with plotters and the DejaVu Sans font bundled in `assets/fonts/` (so
//! nothing needs fontconfig). Included with `#[path = "support/charts.rs"] mod charts;`; not
//! every example uses every function, hence `dead_code` is allowed.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::Once;

use anyhow::Context;
use plotters::coord::Shift;
use plotters::prelude::*;

const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
const SIZE: (u32, u32) = (1000, 700);

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is ours and valid; a failure would only lose the PNG's text.
        if plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_err() {
            eprintln!("charts: the bundled font did not load; PNG text will be missing");
        }
    });
}

/// Draws with `$draw(&root, args...)` into `<stem>.png` and `<stem>.svg`; returns both paths.
macro_rules! png_and_svg {
    ($stem:expr, $draw:ident($($arg:expr),*)) => {{
        register_font();
        let (png, svg) = ($stem.with_extension("png"), $stem.with_extension("svg"));
        {
            let root = BitMapBackend::new(&png, SIZE).into_drawing_area();
            $draw(&root, $($arg),*).with_context(|| format!("drawing {}", png.display()))?;
            root.present()?;
        }
        {
            let root = SVGBackend::new(&svg, SIZE).into_drawing_area();
            $draw(&root, $($arg),*).with_context(|| format!("drawing {}", svg.display()))?;
            root.present()?;
        }
        Ok(vec![png, svg])
    }};
}

/// One point of a scatter series.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    /// Cost.
    pub x: f64,
    /// Error.
    pub y: f64,
    /// Shown next to the point (empty: none).
    pub label: String,
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Small circles.
    Sweep,
    /// A line through the points (the Pareto front).
    Front,
    /// A large filled marker (the defaults).
    Default,
    /// A filled triangle (a baseline).
    Baseline,
}

/// A named series.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text.
    pub name: String,
    /// How it is drawn.
    pub role: Role,
    /// Its points.
    pub points: Vec<Point>,
}

/// Indices of the points no other point beats on both coordinates (both minimised), by x.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    idx.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[a].1.total_cmp(&points[b].1))
    });
    let mut front = Vec::new();
    let mut best = f64::INFINITY;
    for i in idx {
        if points[i].1 < best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}

fn palette(i: usize) -> RGBColor {
    const C: [RGBColor; 8] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(23, 190, 207),
        RGBColor(188, 189, 34),
    ];
    C[i % C.len()]
}

fn range(values: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite() && (!log || *v > 0.0)) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return if log { (0.1, 10.0) } else { (0.0, 1.0) };
    }
    if log {
        (lo / 1.5, hi * 1.5)
    } else {
        let pad = ((hi - lo) * 0.08).max(hi.abs() * 0.05).max(1e-9);
        ((lo - pad).min(0.0f64.max(lo - pad)), hi + pad)
    }
}

/// Scatter chart of `series` to `<stem>.png` and `<stem>.svg`.
pub fn scatter(
    stem: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    series: &[Series],
) -> anyhow::Result<Vec<PathBuf>> {
    png_and_svg!(stem, draw_scatter(title, x_label, y_label, log_x, series))
}

fn ok(p: &Point, log_x: bool) -> bool {
    p.x.is_finite() && p.y.is_finite() && (!log_x || p.x > 0.0) && p.y >= 0.0
}

/// Every chart's frame: the title and the room for the axis labels.
fn chart_builder<'a, 'b, DB: DrawingBackend>(
    root: &'a DrawingArea<DB, Shift>,
    title: &str,
) -> ChartBuilder<'a, 'b, DB> {
    let mut builder = ChartBuilder::on(root);
    builder
        .caption(title, ("sans-serif", 22))
        .margin(20)
        .x_label_area_size(50)
        .y_label_area_size(70);
    builder
}

/// A chart's legend box, to be placed and drawn by the caller (a macro for the same reason as
/// `axes!`, defined below).
macro_rules! legend_box {
    ($chart:expr) => {
        $chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
    };
}

/// Draws a chart's grid and axis descriptions (a macro: the mesh's bounds differ between linear
/// and logarithmic axes).
macro_rules! axes {
    ($chart:expr, $x_label:expr, $y_label:expr) => {
        $chart
            .configure_mesh()
            .x_desc($x_label)
            .y_desc($y_label)
            .label_style(("sans-serif", 15))
            .axis_desc_style(("sans-serif", 17))
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?
    };
}

fn draw_scatter<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    series: &[Series],
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
    let all = || series.iter().flat_map(|s| s.points.iter());
    let (x0, x1) = range(all().filter(|p| ok(p, log_x)).map(|p| p.x), log_x);
    let ys = || all().filter(|p| ok(p, log_x) && p.y > 0.0).map(|p| p.y);
    let spread = ys().fold(0.0f64, f64::max) / ys().fold(f64::INFINITY, f64::min);
    let log_y = spread > 20.0;
    let (y0, y1) = range(all().filter(|p| ok(p, log_x)).map(|p| p.y), log_y);
    let mut builder = chart_builder(root, title);
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("{e}");
    macro_rules! body {
        ($chart:expr) => {{
            let mut chart = $chart;
            axes!(chart, x_label, y_label);
            let mut sweep_colour = 0;
            for s in series {
                let pts: Vec<&Point> = s.points.iter().filter(|p| ok(p, log_x)).collect();
                let colour = match s.role {
                    Role::Sweep => {
                        sweep_colour += 1;
                        palette(sweep_colour - 1)
                    }
                    Role::Front => RGBColor(60, 60, 60),
                    Role::Default => RGBColor(214, 39, 40),
                    Role::Baseline => RGBColor(0, 0, 0),
                };
                let style = colour.filled();
                let anno = match s.role {
                    Role::Sweep => chart
                        .draw_series(pts.iter().map(|p| Circle::new((p.x, p.y), 5, style)))
                        .map_err(|e| err(&e))?,
                    Role::Front => chart
                        .draw_series(LineSeries::new(
                            pts.iter().map(|p| (p.x, p.y)),
                            colour.stroke_width(2),
                        ))
                        .map_err(|e| err(&e))?,
                    Role::Default => chart
                        .draw_series(pts.iter().map(|p| Circle::new((p.x, p.y), 10, style)))
                        .map_err(|e| err(&e))?,
                    Role::Baseline => chart
                        .draw_series(
                            pts.iter()
                                .map(|p| TriangleMarker::new((p.x, p.y), 9, style)),
                        )
                        .map_err(|e| err(&e))?,
                };
                anno.label(s.name.as_str())
                    .legend(move |(x, y)| Circle::new((x + 8, y), 5, colour.filled()));
                chart
                    .draw_series(pts.iter().filter(|p| !p.label.is_empty()).map(|p| {
                        EmptyElement::at((p.x, p.y))
                            + Text::new(
                                p.label.clone(),
                                (9, -14),
                                ("sans-serif", 12).into_font().color(&RGBColor(70, 70, 70)),
                            )
                    }))
                    .map_err(|e| err(&e))?;
            }
            legend_box!(chart)
                .position(SeriesLabelPosition::MiddleRight)
                .draw()
                .map_err(|e| err(&e))?;
        }};
    }
    match (log_x, log_y) {
        (true, true) => body!(builder
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
            .map_err(|e| err(&e))?),
        (true, false) => body!(builder
            .build_cartesian_2d((x0..x1).log_scale(), y0..y1)
            .map_err(|e| err(&e))?),
        (false, true) => body!(builder
            .build_cartesian_2d(x0..x1, (y0..y1).log_scale())
            .map_err(|e| err(&e))?),
        (false, false) => body!(builder
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| err(&e))?),
    }
    Ok(())
}

/// Line chart of named (x, y) series to `<stem>.png` and `<stem>.svg`.
pub fn lines(
    stem: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> anyhow::Result<Vec<PathBuf>> {
    png_and_svg!(stem, draw_lines(title, x_label, y_label, series))
}

/// Line charts written to one directory, all with the same x axis (an example's charts over
/// frames, say).
pub struct LineCharts<'a> {
    /// Where they go: `<dir>/<stem>.png` and `.svg`.
    dir: &'a Path,
    /// Every chart's x axis.
    x_label: &'a str,
}

impl<'a> LineCharts<'a> {
    /// Charts in `dir` along `x_label`.
    pub fn new(dir: &'a Path, x_label: &'a str) -> Self {
        Self { dir, x_label }
    }

    /// [`lines`] to `<dir>/<stem>`.
    pub fn draw(
        &self,
        stem: &str,
        title: &str,
        y_label: &str,
        series: &[(String, Vec<(f64, f64)>)],
    ) -> anyhow::Result<Vec<PathBuf>> {
        lines(&self.dir.join(stem), title, self.x_label, y_label, series)
    }
}

fn draw_lines<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("{e}");
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let finite = |p: &&(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let all = || series.iter().flat_map(|s| s.1.iter()).filter(finite);
    let (x0, x1) = range(all().map(|p| p.0), false);
    let (y0, y1) = range(all().map(|p| p.1), false);
    let mut chart = chart_builder(root, title)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| err(&e))?;
    axes!(chart, x_label, y_label);
    for (i, (name, pts)) in series.iter().enumerate() {
        let colour = palette(i);
        chart
            .draw_series(LineSeries::new(
                pts.iter().filter(finite).copied(),
                colour.stroke_width(2),
            ))
            .map_err(|e| err(&e))?
            .label(name.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour));
    }
    legend_box!(chart).draw().map_err(|e| err(&e))?;
    Ok(())
}

/// Grouped bar chart (`groups` along x, one bar per series in each) to `<stem>.png`/`.svg`.
pub fn bars(
    stem: &Path,
    title: &str,
    y_label: &str,
    groups: &[String],
    series: &[(String, Vec<f64>)],
) -> anyhow::Result<Vec<PathBuf>> {
    png_and_svg!(stem, draw_bars(title, y_label, groups, series))
}

fn draw_bars<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    y_label: &str,
    groups: &[String],
    series: &[(String, Vec<f64>)],
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("{e}");
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let top = series
        .iter()
        .flat_map(|s| s.1.iter())
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max)
        .max(1e-9)
        * 1.15;
    let n = groups.len().max(1) as f64;
    let mut chart = chart_builder(root, title)
        .build_cartesian_2d(0.0..n, 0.0..top)
        .map_err(|e| err(&e))?;
    let labels = groups.to_vec();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(groups.len() * 2 + 1)
        .x_label_formatter(&move |x| {
            let i = x.floor() as usize;
            if (x - x.floor() - 0.5).abs() < 0.01 {
                labels.get(i).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .y_desc(y_label)
        .label_style(("sans-serif", 15))
        .axis_desc_style(("sans-serif", 17))
        .draw()
        .map_err(|e| err(&e))?;
    let k = series.len().max(1) as f64;
    for (si, (name, values)) in series.iter().enumerate() {
        let colour = palette(si);
        chart
            .draw_series(
                values
                    .iter()
                    .enumerate()
                    .filter(|(_, v)| v.is_finite())
                    .map(|(g, &v)| {
                        let x0 = g as f64 + 0.1 + 0.8 * si as f64 / k;
                        let x1 = x0 + 0.8 / k;
                        Rectangle::new([(x0, 0.0), (x1, v)], colour.filled())
                    }),
            )
            .map_err(|e| err(&e))?
            .label(name.as_str())
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 10, y + 5)], colour.filled()));
    }
    legend_box!(chart).draw().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_front_keeps_only_undominated_points() {
        let pts = [
            (1.0, 5.0),
            (2.0, 3.0),
            (3.0, 4.0),
            (4.0, 1.0),
            (f64::NAN, 0.0),
        ];
        assert_eq!(pareto_front(&pts), vec![0, 1, 3]);
    }
}
