//! The speed–accuracy trade-off: sweeps the managed policy's culling angle, culling distance,
//! r1/r2, LOD pixel error, memory budget, far-field cut, far keep angle, release threshold and the far field's children built ahead over the same
//! deterministic path, scores every point against the full-world ground truth, and charts
//! error against memory, TLAS instances, GPU ms and `update` ms with the Pareto front, the
//! defaults, `naive` and `seed` marked.
//!
//! Every point of the managed policy, the default one included, runs alone on its backend, so
//! their `update` times compare; the baselines run together in a run of their own.
//!
//! ```text
//! cargo run --release --example tradeoff -- [--frames 600] [--eval-every 20] [--size 320x180]
//!     [--render-every 1] [--out out/tradeoff] [--only angle,distance,radii,lod,budget,far,keep,release,ahead]
//!     [--json]
//! ```
//! Writes `points.csv`, `points.json` and `error_vs_{memory,tlas,gpu,update}.{png,svg}` to
//! `--out`. With `--render-every 1` every frame is rendered (a game's GPU load: the GPU keeps
//! its clocks, so its AS times are a frame's), at `--size`, which is also the scoring size.

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;
#[path = "support/sweep.rs"]
mod sweep;

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use rtstream::as_manager::backend::vulkan::{ContextDesc, VulkanContext};
use rtstream::as_manager::{Config, PolicyKind};
use rtstream::driver::{PolicySummary, RunConfig};
use serde::Serialize;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Knob {
    /// Culling angle (0, 0.25, 0.5, 1, 2, 4 degrees).
    Angle,
    /// Culling distance (100, 150, 200, 250, 300 m).
    Distance,
    /// r1/r2 (100/150, 150/200, 200/250, 300/350 m).
    Radii,
    /// LOD pixel error (0.5, 1, 2, 4 px).
    Lod,
    /// Memory budget (4, 8, 16, 32, 64 MB).
    Budget,
    /// Far-field cut: proxy error in pixels (6, 12, 24, 48) or off.
    Far,
    /// Far keep angle: landmarks beyond r2 stay in the TLAS (off, 0.25, 0.5, 1, 2, 4 degrees).
    Keep,
    /// Release threshold: frames a BLAS nothing keeps stays built (0, 2, 4, 8, 15, 30, 60).
    Release,
    /// The far field's children built ahead: share of the proxy pixel error above which a
    /// wanted node's children are built too (0.25, 0.5, 0.75, 1 = none).
    Ahead,
}

/// Sweeps the managed policy's knobs over one path and charts error against cost.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    #[command(flatten)]
    run: cli::RunArgs,
    /// Knobs to sweep (default: all).
    #[arg(long, value_enum, value_delimiter = ',')]
    only: Vec<Knob>,
    /// Print the points as one JSON object on the last line of stdout.
    #[arg(long)]
    json: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// One point of the sweep.
#[derive(Debug, Clone, Serialize)]
struct SweepPoint {
    knob: &'static str,
    value: String,
    is_default: bool,
    #[serde(flatten)]
    figures: PolicySummary,
}

/// A sweep point: its label and how it changes the default configuration.
type Point = (String, Box<dyn Fn(&mut Config)>);

fn points(knob: Knob) -> Vec<Point> {
    fn p(v: String, f: impl Fn(&mut Config) + 'static) -> Point {
        (v, Box::new(f))
    }
    /// The angle knobs' points: 0 to 4 degrees, set in radians by `set`.
    fn angles(set: fn(&mut Config, f32)) -> Vec<Point> {
        [0.0f32, 0.25, 0.5, 1.0, 2.0, 4.0]
            .into_iter()
            .map(|a| p(format!("{a}deg"), move |c| set(c, a.to_radians())))
            .collect()
    }
    match knob {
        Knob::Angle => angles(|c, a| c.cull.min_angle = a),
        Knob::Distance => [100.0f32, 150.0, 200.0, 250.0, 300.0]
            .into_iter()
            .map(|d| p(format!("{d}m"), move |c| c.cull.far_distance = d))
            .collect(),
        Knob::Radii => [
            (100.0f32, 150.0f32),
            (150.0, 200.0),
            (200.0, 250.0),
            (300.0, 350.0),
        ]
        .into_iter()
        .map(|(a, b)| {
            p(format!("{a}/{b}m"), move |c| {
                c.residency.r1 = a;
                c.residency.r2 = b;
            })
        })
        .collect(),
        Knob::Lod => [0.5f32, 1.0, 2.0, 4.0]
            .into_iter()
            .map(|px| p(format!("{px}px"), move |c| c.lod.max_pixel_error = px))
            .collect(),
        Knob::Budget => [4u64, 8, 16, 32, 64]
            .into_iter()
            .map(|mb| p(format!("{mb}MB"), move |c| c.memory.blas_bytes = mb << 20))
            .collect(),
        Knob::Far => {
            let mut v: Vec<_> = [6.0f32, 12.0, 24.0, 48.0]
                .into_iter()
                .map(|px| p(format!("{px}px"), move |c| c.far_field.max_pixel_error = px))
                .collect();
            v.push(p("off".into(), |c| c.far_field.enabled = false));
            v
        }
        Knob::Keep => angles(|c, a| c.far_field.keep_angle = a),
        Knob::Release => [0u32, 2, 4, 8, 15, 30, 60]
            .into_iter()
            .map(|n| p(format!("{n}fr"), move |c| c.residency.release_threshold = n))
            .collect(),
        Knob::Ahead => [0.25f32, 0.5, 0.75, 1.0]
            .into_iter()
            .map(|a| p(format!("{a}"), move |c| c.far_field.refine_ahead = a))
            .collect(),
    }
}

fn knob_name(k: Knob) -> &'static str {
    match k {
        Knob::Angle => "cull_angle",
        Knob::Distance => "cull_distance",
        Knob::Radii => "r1_r2",
        Knob::Lod => "lod_px",
        Knob::Budget => "budget",
        Knob::Far => "far_field",
        Knob::Keep => "far_keep_angle",
        Knob::Release => "release_frames",
        Knob::Ahead => "refine_ahead",
    }
}

fn main() -> anyhow::Result<()> {
    cli::init_tracing();
    let mut cli = Cli::parse();
    if cli.run.out.as_path() == std::path::Path::new("out/flythrough") {
        cli.run.out = PathBuf::from("out/tradeoff");
    }
    let knobs = if cli.only.is_empty() {
        vec![
            Knob::Angle,
            Knob::Distance,
            Knob::Radii,
            Knob::Lod,
            Knob::Budget,
            Knob::Far,
            Knob::Keep,
            Knob::Release,
            Knob::Ahead,
        ]
    } else {
        cli.only.clone()
    };
    let mut base = cli.run.run_config()?;
    base.deterministic = true;
    base.all_geometry_reference = false;
    base.maps = 0;
    let out = cli.run.out.clone();
    base.out_dir = None;
    let ctx = Arc::new(VulkanContext::new(&ContextDesc::default())?);
    let default_config = base.managed.clone();

    // The baselines in a run of their own, then the default point and every other point of
    // the managed policy, each alone (policies side by side share the CPU's caches, which
    // would make the default's `update` slower than the points it is compared with).
    let mut baseline_run = base.clone();
    baseline_run.policies.retain(|&p| p != PolicyKind::Managed);
    let mut alone = base.clone();
    alone.policies = vec![PolicyKind::Managed];
    let mut runs: Vec<(String, RunConfig)> = Vec::new();
    let mut meta = Vec::new();
    if !baseline_run.policies.is_empty() {
        runs.push(("baselines".into(), baseline_run));
        meta.push(("baseline", "-".to_string(), false));
    }
    runs.push(("defaults".into(), alone));
    meta.push(("default", "default".to_string(), true));
    for &k in &knobs {
        for (value, set) in points(k) {
            let mut c = base.clone();
            set(&mut c.managed);
            if c.managed == default_config {
                continue; // the default run covers it
            }
            c.policies = vec![PolicyKind::Managed];
            c.managed
                .validate()
                .with_context(|| format!("{} = {value}", knob_name(k)))?;
            runs.push((format!("{} = {value}", knob_name(k)), c));
            meta.push((knob_name(k), value, false));
        }
    }
    let reports = sweep::run_points(&ctx, &runs, cli.quiet)?;
    let mut sweep = Vec::new();
    let mut baselines = Vec::new();
    for (report, (knob, value, is_default)) in reports.into_iter().zip(meta) {
        for p in report.summary.policies {
            if p.policy == "managed" {
                sweep.push(SweepPoint {
                    knob,
                    value: value.clone(),
                    is_default,
                    figures: p,
                });
            } else {
                baselines.push(p);
            }
        }
    }
    let validation = ctx.validation_log().failure_count();
    print_table(&sweep, &baselines);
    std::fs::create_dir_all(&out)?;
    write_csv(&out.join("points.csv"), &sweep, &baselines)?;
    let json = serde_json::json!({
        "frames": base.frames,
        "seed": base.preset.seed,
        "device": ctx.info().name,
        "points": sweep,
        "baselines": baselines,
        "validation_messages": validation,
    });
    std::fs::write(
        out.join("points.json"),
        serde_json::to_string_pretty(&json)?,
    )?;
    for f in draw_charts(&out, &sweep, &baselines)? {
        println!("wrote {}", f.display());
    }
    if cli.json {
        println!("{json}");
    }
    Ok(())
}

fn print_table(sweep: &[SweepPoint], baselines: &[PolicySummary]) {
    println!(
        "{:<14} {:>9} {:>9} {:>9} {:>7} {:>8} {:>8} {:>9} {:>9} {:>9} {:>5}",
        "knob",
        "value",
        "peak MB",
        "p95 MB",
        "TLAS",
        "upd p50",
        "gpu p99",
        "hit mean",
        "hit p95",
        "shd mean",
        "front"
    );
    let front = front_of(sweep, |p| p.figures.peak_blas_bytes as f64);
    let row = |knob: &str, value: &str, p: &PolicySummary, on_front: bool| {
        println!(
            "{:<14} {:>9} {:>9.1} {:>9.1} {:>7} {:>8.2} {:>8.2} {:>8.2}% {:>8.2}% {:>8.2}% {:>5}",
            knob,
            value,
            p.peak_blas_bytes as f64 / 1e6,
            p.p95_blas_bytes as f64 / 1e6,
            p.peak_tlas_instances,
            p.update_ms_p50,
            p.gpu_as_ms_p99,
            p.hit_mismatch_mean * 100.0,
            p.hit_mismatch_p95 * 100.0,
            p.shadow_mismatch_mean * 100.0,
            if on_front { "*" } else { "" }
        )
    };
    for (i, s) in sweep.iter().enumerate() {
        row(s.knob, &s.value, &s.figures, front.contains(&i));
    }
    for b in baselines {
        row(b.policy, "-", b, false);
    }
    println!("front: Pareto front of mean hit mismatch against peak BLAS bytes");
}

fn front_of(sweep: &[SweepPoint], cost: impl Fn(&SweepPoint) -> f64) -> Vec<usize> {
    let pts: Vec<(f64, f64)> = sweep
        .iter()
        .map(|p| (cost(p), p.figures.hit_mismatch_mean))
        .collect();
    charts::pareto_front(&pts)
}

fn write_csv(
    path: &std::path::Path,
    sweep: &[SweepPoint],
    baselines: &[PolicySummary],
) -> anyhow::Result<()> {
    #[derive(Serialize)]
    struct Row<'a> {
        knob: &'a str,
        value: &'a str,
        policy: &'a str,
        peak_blas_bytes: u64,
        p95_blas_bytes: u64,
        peak_tlas_instances: u32,
        p95_tlas_instances: u32,
        update_ms_p50: f64,
        update_ms_p99: f64,
        gpu_as_ms_p50: f64,
        gpu_as_ms_p99: f64,
        hit_mismatch_mean: f64,
        hit_mismatch_p95: f64,
        shadow_mismatch_mean: f64,
        shadow_mismatch_p95: f64,
        over_budget_frames: u64,
    }
    let row = |knob: &'static str, value: &'static str, p: &PolicySummary| Row {
        knob,
        value,
        policy: p.policy,
        peak_blas_bytes: p.peak_blas_bytes,
        p95_blas_bytes: p.p95_blas_bytes,
        peak_tlas_instances: p.peak_tlas_instances,
        p95_tlas_instances: p.p95_tlas_instances,
        update_ms_p50: p.update_ms_p50,
        update_ms_p99: p.update_ms_p99,
        gpu_as_ms_p50: p.gpu_as_ms_p50,
        gpu_as_ms_p99: p.gpu_as_ms_p99,
        hit_mismatch_mean: p.hit_mismatch_mean,
        hit_mismatch_p95: p.hit_mismatch_p95,
        shadow_mismatch_mean: p.shadow_mismatch_mean,
        shadow_mismatch_p95: p.shadow_mismatch_p95,
        over_budget_frames: p.over_budget_frames,
    };
    let mut w = csv::Writer::from_path(path)?;
    for s in sweep {
        let mut r = row(s.knob, "", &s.figures);
        r.value = &s.value;
        w.serialize(r)?;
    }
    for b in baselines {
        w.serialize(row("baseline", "", b))?;
    }
    w.flush()?;
    Ok(())
}

fn draw_charts(
    out: &std::path::Path,
    sweep: &[SweepPoint],
    baselines: &[PolicySummary],
) -> anyhow::Result<Vec<PathBuf>> {
    type Cost = fn(&PolicySummary) -> f64;
    let axes: [(&str, &str, Cost, bool); 4] = [
        (
            "error_vs_memory",
            "peak BLAS MB",
            |p| p.peak_blas_bytes as f64 / 1e6,
            true,
        ),
        (
            "error_vs_tlas",
            "peak TLAS instances",
            |p| f64::from(p.peak_tlas_instances),
            true,
        ),
        ("error_vs_gpu", "GPU AS ms p99", |p| p.gpu_as_ms_p99, false),
        (
            "error_vs_update",
            "update ms p50",
            |p| p.update_ms_p50,
            false,
        ),
    ];
    let mut files = Vec::new();
    for (stem, x_label, cost, log_x) in axes {
        let label = |s: &SweepPoint| format!("{} {}", s.knob.replace('_', " "), s.value);
        let pt = |p: &PolicySummary, l: String| charts::Point {
            x: cost(p),
            y: p.hit_mismatch_mean * 100.0,
            label: l,
        };
        let front = front_of(sweep, |s| cost(&s.figures));
        let mut series: Vec<charts::Series> = Vec::new();
        let knobs = [
            "cull_angle",
            "cull_distance",
            "r1_r2",
            "lod_px",
            "budget",
            "far_field",
            "far_keep_angle",
        ];
        for k in knobs {
            let pts: Vec<charts::Point> = sweep
                .iter()
                .filter(|s| s.knob == k)
                .map(|s| pt(&s.figures, s.value.clone()))
                .collect();
            if !pts.is_empty() {
                series.push(charts::Series {
                    name: k.replace('_', " "),
                    role: charts::Role::Sweep,
                    points: pts,
                });
            }
        }
        series.push(charts::Series {
            name: "Pareto front".into(),
            role: charts::Role::Front,
            points: front
                .iter()
                .map(|&i| pt(&sweep[i].figures, String::new()))
                .collect(),
        });
        series.push(charts::Series {
            name: "default".into(),
            role: charts::Role::Default,
            points: sweep
                .iter()
                .filter(|s| s.is_default)
                .map(|s| pt(&s.figures, label(s)))
                .collect(),
        });
        for b in baselines {
            series.push(charts::Series {
                name: b.policy.into(),
                role: charts::Role::Baseline,
                points: vec![pt(b, b.policy.into())],
            });
        }
        files.extend(charts::scatter(
            &out.join(stem),
            &format!("mean geometric hit mismatch vs {x_label} (full-world ground truth)"),
            x_label,
            "hit mismatch, % of pixels",
            log_x,
            &series,
        )?);
    }
    Ok(files)
}
