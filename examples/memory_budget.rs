//! Memory budget sweep: the managed policy over the same path with BLAS budgets from well below
//! to above what r1 asks for (default 1, 2, 4, 8, 16, 32, 64 MB, and no budget to show the
//! need). The budget is never exceeded; LOD fallbacks, evictions and refused builds show in the
//! table; the image degrades gracefully, scored against the full-world ground truth. Runs on
//! the real backend through the shared frame driver and sweep code (as `tradeoff` does).
//!
//! ```text
//! cargo run --release --example memory_budget -- --help
//! cargo run --release --example memory_budget -- --deterministic --json
//! ```

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;
#[path = "support/sweep.rs"]
mod sweep;

use serde::Serialize;

/// The example's own flag.
#[derive(Debug, clap::Args)]
struct Flags {
    /// Budgets to sweep, MB (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])]
    budgets_mb: Vec<f64>,
}

/// One budget's figures.
#[derive(Debug, Serialize)]
struct Point {
    /// None: no budget (what the policy asks for).
    budget_mb: Option<f64>,
    peak_blas_mb: f64,
    evictions: u64,
    lod_fallback_frames: usize,
    memory_refused_frames: usize,
    short_of_target_mean: f64,
    tlas_instances_mean: f64,
    #[serde(flatten)]
    figures: cli::PolicyFigures,
}

#[derive(Debug, Serialize)]
struct Summary {
    #[serde(flatten)]
    totals: sweep::Totals,
    points: Vec<Point>,
}

fn main() -> anyhow::Result<()> {
    let cli = cli::ExampleCli::<Flags>::start(
        "The managed policy under BLAS budgets below and above what r1 asks for.",
        "out/memory_budget",
    );
    anyhow::ensure!(
        cli.own.budgets_mb.iter().all(|b| b.is_finite() && *b > 0.0),
        "every budget must be a positive number of MB"
    );
    let base = sweep::managed_base(&cli.run)?;
    let mut budgets: Vec<Option<f64>> = vec![None];
    budgets.extend(cli.own.budgets_mb.iter().map(|&b| Some(b)));
    let points = sweep::points(&base, &budgets, |c, b| {
        c.managed.memory.blas_bytes = b.map_or(1 << 50, |mb| (mb * 1024.0 * 1024.0) as u64);
        b.map_or("no budget".into(), |mb| format!("{mb} MB"))
    });
    let ctx = sweep::context(&base)?;
    let reports = sweep::run_points(&ctx, &points, cli.output.quiet)?;
    let mut out = Vec::new();
    for (b, r) in budgets.iter().zip(&reports) {
        let p = &r.summary.policies[0];
        let rows = cli::managed_rows(&r.rows);
        out.push(Point {
            budget_mb: *b,
            peak_blas_mb: p.peak_blas_bytes as f64 / (1 << 20) as f64,
            evictions: rows.iter().map(|x| u64::from(x.evictions)).sum(),
            lod_fallback_frames: rows.iter().filter(|x| x.lod_fallbacks > 0).count(),
            memory_refused_frames: rows.iter().filter(|x| x.memory_refused > 0).count(),
            short_of_target_mean: cli::mean(&rows, |x| f64::from(x.short_of_target)),
            tlas_instances_mean: cli::mean(&rows, |x| f64::from(x.tlas_instances)),
            figures: p.into(),
        });
    }
    let summary = Summary {
        totals: sweep::Totals::of(&ctx, &base, &reports),
        points: out,
    };
    print_table(&summary);
    std::fs::create_dir_all(&cli.run.out)?;
    let budgeted: Vec<&Point> = summary
        .points
        .iter()
        .filter(|p| p.budget_mb.is_some())
        .collect();
    let series = |f: fn(&Point) -> f64| -> Vec<(f64, f64)> {
        budgeted
            .iter()
            .map(|p| (p.budget_mb.unwrap_or(0.0).log2(), f(p)))
            .collect()
    };
    let by_budget = charts::LineCharts::new(&cli.run.out, "log2(budget / MB)");
    let mut files = by_budget.draw(
        "error_vs_budget",
        "BLAS budget against image error (full-world ground truth)",
        "mismatched pixels, %",
        &[
            (
                "hit mismatch".into(),
                series(|p| p.figures.hit_mismatch_mean * 100.0),
            ),
            (
                "shadow mismatch".into(),
                series(|p| p.figures.shadow_mismatch_mean * 100.0),
            ),
        ],
    )?;
    files.extend(by_budget.draw(
        "memory_vs_budget",
        "BLAS budget against peak BLAS memory",
        "MB",
        &[
            ("peak BLAS MB".into(), series(|p| p.peak_blas_mb)),
            ("budget".into(), series(|p| p.budget_mb.unwrap_or(0.0))),
        ],
    )?);
    cli.output
        .finish(&cli.run.out, "memory_budget", &summary, &files)
}

fn print_table(s: &Summary) {
    println!(
        "{:>9} {:>9} {:>5} {:>9} {:>9} {:>8} {:>8} {:>9} {:>8} {:>8}",
        "budget",
        "peak MB",
        "over",
        "evictions",
        "fallback",
        "refused",
        "short",
        "TLAS inst",
        "hit %",
        "shadow %"
    );
    for p in &s.points {
        println!(
            "{:>9} {:>9.2} {:>5} {:>9} {:>9} {:>8} {:>8.1} {:>9.0} {:>8.2} {:>8.2}",
            p.budget_mb.map_or("none".into(), |b| format!("{b} MB")),
            p.peak_blas_mb,
            p.figures.over_budget_frames,
            p.evictions,
            p.lod_fallback_frames,
            p.memory_refused_frames,
            p.short_of_target_mean,
            p.tlas_instances_mean,
            p.figures.hit_mismatch_mean * 100.0,
            p.figures.shadow_mismatch_mean * 100.0
        );
    }
    println!(
        "frames over budget {} (all points); validation messages {}",
        s.totals.over_budget_frames, s.totals.validation_messages
    );
}
