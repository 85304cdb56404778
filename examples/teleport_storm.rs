//! Teleport storm: the camera jumps to a random place of the world (seeded) every `--every`
//! frames and stays there; the managed policy streams, builds within its per-frame budget and
//! recovers. Prints, per teleport, the frames until full coverage (every unculled instance
//! within r1 shows its target LOD or finer, for good) and the build work; charts the build
//! work per frame and the instances short of their target. Runs on the real backend through
//! the shared frame driver (`rtstream::driver`), scored against the full-world ground truth.
//!
//! ```text
//! cargo run --release --example teleport_storm -- --help
//! cargo run --release --example teleport_storm -- --deterministic --json
//! ```

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;

use anyhow::Context;
use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, FrameRow};
use serde::Serialize;

/// The example's own flag.
#[derive(Debug, clap::Args)]
struct Flags {
    /// Frames between teleports.
    #[arg(long, default_value_t = 30)]
    every: u64,
}

/// One teleport's figures.
#[derive(Debug, Serialize)]
struct Teleport {
    teleport: u64,
    first_frame: u64,
    /// None: not covered when the next teleport came.
    frames_to_coverage: Option<u64>,
    builds: u64,
    build_triangles: u64,
    peak_frame_triangles: u64,
    peak_short_of_target: u32,
}

#[derive(Debug, Serialize)]
struct Summary {
    device: String,
    frames: u64,
    every: u64,
    build_budget_triangles: u64,
    teleports: Vec<Teleport>,
    covered_teleports: usize,
    frames_to_coverage_max: Option<u64>,
    frames_to_coverage_mean: Option<f64>,
    over_build_budget_frames: usize,
    #[serde(flatten)]
    figures: cli::PolicyFigures,
}

fn main() -> anyhow::Result<()> {
    let cli = cli::ExampleCli::<Flags>::start(
        "A teleport every N frames to a random place; frames to coverage and build work.",
        "out/teleport_storm",
    );
    let every = cli.own.every;
    anyhow::ensure!(every > 0, "--every must be at least 1");
    let mut config = cli.run.run_config()?;
    config.policies = vec![PolicyKind::Managed];
    config.teleport_every = Some(every);
    config.maps = 0;
    eprintln!(
        "teleport storm: {} frames, a teleport every {} frames, world {} (seed {:#x})",
        config.frames, every, config.preset.name, config.preset.seed
    );
    let report =
        cli::run_with_progress(&config, cli.output.quiet, |_| {}).context("teleport storm run")?;

    let rows = cli::managed_rows(&report.rows);
    let coverage = driver::frames_to_coverage(&report.rows, "managed", every);
    let teleports: Vec<Teleport> = rows
        .chunks(every as usize)
        .zip(&coverage)
        .enumerate()
        .map(|(k, (seg, &c))| Teleport {
            teleport: k as u64,
            first_frame: seg[0].frame,
            frames_to_coverage: c,
            builds: seg.iter().map(|r| u64::from(r.builds)).sum(),
            build_triangles: seg.iter().map(|r| r.build_primitives).sum(),
            peak_frame_triangles: seg.iter().map(|r| r.build_primitives).max().unwrap_or(0),
            peak_short_of_target: seg.iter().map(|r| r.short_of_target).max().unwrap_or(0),
        })
        .collect();
    let covered: Vec<u64> = coverage.iter().flatten().copied().collect();
    let p = &report.summary.policies[0];
    let summary = Summary {
        device: p.backend.clone(),
        frames: config.frames,
        every,
        build_budget_triangles: config.managed.build.max_primitives,
        covered_teleports: covered.len(),
        frames_to_coverage_max: covered.iter().max().copied(),
        frames_to_coverage_mean: (!covered.is_empty())
            .then(|| covered.iter().sum::<u64>() as f64 / covered.len() as f64),
        over_build_budget_frames: rows.iter().filter(|r| r.over_build_budget).count(),
        figures: p.into(),
        teleports,
    };
    print_table(&summary);
    std::fs::create_dir_all(&cli.run.out)?;
    let per_frame = |f: fn(&FrameRow) -> f64| cli::per_frame(&rows, f);
    let by_frame = charts::LineCharts::new(&cli.run.out, "frame");
    let mut files = by_frame.draw(
        "build_work",
        &format!("Teleport every {} frames: build work per frame", every),
        "triangles built",
        &[
            (
                "triangles built".into(),
                per_frame(|r| r.build_primitives as f64),
            ),
            (
                "build budget".into(),
                per_frame(|r| r.build_budget.min(u64::from(u32::MAX)) as f64),
            ),
        ],
    )?;
    files.extend(by_frame.draw(
        "coverage",
        &format!(
            "Teleport every {} frames: instances within r1 short of target",
            every
        ),
        "instances",
        &[
            ("within r1".into(), per_frame(|r| f64::from(r.within_r1))),
            (
                "short of target".into(),
                per_frame(|r| f64::from(r.short_of_target)),
            ),
        ],
    )?);
    files.extend(report.files.iter().cloned());
    cli.output
        .finish(&cli.run.out, "teleport_storm", &summary, &files)
}

fn print_table(s: &Summary) {
    println!(
        "{:>8} {:>7} {:>10} {:>7} {:>12} {:>12} {:>7}",
        "teleport", "frame", "coverage", "builds", "triangles", "peak/frame", "short"
    );
    for t in &s.teleports {
        println!(
            "{:>8} {:>7} {:>10} {:>7} {:>12} {:>12} {:>7}",
            t.teleport,
            t.first_frame,
            t.frames_to_coverage
                .map_or("not yet".to_string(), |f| format!("{f} fr")),
            t.builds,
            t.build_triangles,
            t.peak_frame_triangles,
            t.peak_short_of_target
        );
    }
    println!(
        "covered {}/{} teleports; frames to coverage max {} mean {}; build budget {} triangles, \
         frames over it {}; frames over the memory budget {}; hit mismatch {:.2}%, shadow {:.2}%; \
         validation messages {}",
        s.covered_teleports,
        s.teleports.len(),
        s.frames_to_coverage_max
            .map_or("-".into(), |v| v.to_string()),
        s.frames_to_coverage_mean
            .map_or("-".into(), |v| format!("{v:.1}")),
        s.build_budget_triangles,
        s.over_build_budget_frames,
        s.figures.over_budget_frames,
        s.figures.hit_mismatch_mean * 100.0,
        s.figures.shadow_mismatch_mean * 100.0,
        s.figures.validation_messages
    );
}
