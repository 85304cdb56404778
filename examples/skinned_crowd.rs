//! Skinned crowd: hundreds of generated skinned characters (the generator's procedural
//! character, not the 8-triangle `simple_skin`) animating around a slowly walking camera, with
//! at least twice `max_refit_primitives` skinned triangles in the world. Refits stay within the
//! refit budget; rebuilds happen only when a refit's measured quality passes its bound. Charts
//! refits, rebuilds and the worst refit quality per frame (and the GPU ms the backend measured:
//! run it on an NVIDIA GPU for those). Runs on the real backend through the shared driver.
//!
//! ```text
//! cargo run --release --example skinned_crowd -- --help
//! cargo run --release --example skinned_crowd -- --characters 600 --deterministic --json
//! ```

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;

use anyhow::Context;
use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, FrameRow};
use rtstream::streaming::{Motion, WorldPreset};
use serde::Serialize;

/// The example's own flags.
#[derive(Debug, clap::Args)]
struct Flags {
    /// Generated skinned characters (spread over a 3x3-level area, 214 m; 1 to 100,000).
    #[arg(long, default_value_t = 600, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    characters: u32,
    /// Triangles refitted per frame at most (the manager's `max_refit_primitives`).
    #[arg(long)]
    max_refit_tris: Option<u64>,
}

#[derive(Debug, Serialize)]
struct Summary {
    device: String,
    frames: u64,
    skinned_instances: usize,
    skinned_triangles: u64,
    max_refit_primitives: u64,
    rebuild_quality_bound: f32,
    refits: u64,
    rebuilds: u64,
    peak_refit_primitives: u64,
    over_refit_budget_frames: usize,
    worst_refit_quality: f32,
    gpu_as_ms_p50: f64,
    gpu_as_ms_p99: f64,
    update_ms_p50: f64,
    update_ms_p99: f64,
    #[serde(flatten)]
    figures: cli::PolicyFigures,
}

fn main() -> anyhow::Result<()> {
    let cli = cli::ExampleCli::<Flags>::start(
        "Hundreds of skinned characters near the camera: refit budget, rebuilds and quality.",
        "out/skinned_crowd",
    );
    let mut config = cli.run.run_config()?;
    cli.run
        .use_preset(&mut config, WorldPreset::crowd(cli.own.characters));
    config.policies = vec![PolicyKind::Managed];
    config.maps = 0;
    // A slow walk through the middle of the crowd.
    config.path_span = (0.4, 0.6);
    if let Some(t) = cli.own.max_refit_tris {
        config.managed.build.max_refit_primitives = t;
    }
    let world =
        driver::prepare_world(&config.preset, &config.world_dir).context("generating the crowd")?;
    let skinned: Vec<_> = world
        .levels
        .iter()
        .flat_map(|l| &l.instances)
        .filter(|i| i.motion == Motion::Skinned)
        .collect();
    let skinned_triangles: u64 = skinned
        .iter()
        .map(|i| world.meshes[i.mesh.0 as usize].lods[0].triangle_count() as u64)
        .sum();
    let budget = config.managed.build.max_refit_primitives;
    eprintln!(
        "skinned crowd: {} skinned instances, {} skinned triangles at LOD 0 ({:.1}x the refit budget of {})",
        skinned.len(),
        skinned_triangles,
        skinned_triangles as f64 / budget.max(1) as f64,
        budget
    );
    let report =
        cli::run_with_progress(&config, cli.output.quiet, |_| {}).context("skinned crowd run")?;

    let rows = cli::managed_rows(&report.rows);
    let p = &report.summary.policies[0];
    let summary = Summary {
        device: p.backend.clone(),
        frames: config.frames,
        skinned_instances: skinned.len(),
        skinned_triangles,
        max_refit_primitives: budget,
        rebuild_quality_bound: config.managed.build.rebuild_quality_bound,
        refits: rows.iter().map(|r| u64::from(r.refits)).sum(),
        rebuilds: rows.iter().map(|r| u64::from(r.rebuilds)).sum(),
        peak_refit_primitives: rows.iter().map(|r| r.refit_primitives).max().unwrap_or(0),
        // One oversized item may go alone, as with builds.
        over_refit_budget_frames: rows
            .iter()
            .filter(|r| r.refit_primitives > budget && r.refits + r.rebuilds > 1)
            .count(),
        worst_refit_quality: rows
            .iter()
            .map(|r| r.worst_refit_quality)
            .fold(1.0, f32::max),
        gpu_as_ms_p50: p.gpu_as_ms_p50,
        gpu_as_ms_p99: p.gpu_as_ms_p99,
        update_ms_p50: p.update_ms_p50,
        update_ms_p99: p.update_ms_p99,
        figures: p.into(),
    };
    println!(
        "{} skinned instances, {} triangles ({:.1}x the refit budget {}); {} frames: {} refits, \
         {} rebuilds, peak {} triangles refitted in a frame, {} frames over the refit budget; \
         worst refit quality {:.2} (bound {:.2}); GPU AS ms p50 {:.3} p99 {:.3}; update ms p50 \
         {:.3} p99 {:.3}; hit mismatch {:.2}%, shadow {:.2}%; validation messages {}",
        summary.skinned_instances,
        summary.skinned_triangles,
        summary.skinned_triangles as f64 / budget.max(1) as f64,
        budget,
        summary.frames,
        summary.refits,
        summary.rebuilds,
        summary.peak_refit_primitives,
        summary.over_refit_budget_frames,
        summary.worst_refit_quality,
        summary.rebuild_quality_bound,
        summary.gpu_as_ms_p50,
        summary.gpu_as_ms_p99,
        summary.update_ms_p50,
        summary.update_ms_p99,
        summary.figures.hit_mismatch_mean * 100.0,
        summary.figures.shadow_mismatch_mean * 100.0,
        summary.figures.validation_messages
    );
    std::fs::create_dir_all(&cli.run.out)?;
    let per_frame = |f: fn(&FrameRow) -> f64| cli::per_frame(&rows, f);
    let by_frame = charts::LineCharts::new(&cli.run.out, "frame");
    let mut files = by_frame.draw(
        "refits",
        "Skinned crowd: refits and rebuilds per frame",
        "BLASes",
        &[
            ("refits".into(), per_frame(|r| f64::from(r.refits))),
            ("rebuilds".into(), per_frame(|r| f64::from(r.rebuilds))),
        ],
    )?;
    files.extend(
        by_frame.draw(
            "refit_quality",
            "Skinned crowd: worst refit quality per frame (1 = fresh build)",
            "SAH cost ratio",
            &[
                (
                    "worst refit quality".into(),
                    per_frame(|r| f64::from(r.worst_refit_quality)),
                ),
                (
                    "rebuild bound".into(),
                    per_frame(|_| 0.0)
                        .into_iter()
                        .map(|(x, _)| (x, f64::from(summary.rebuild_quality_bound)))
                        .collect(),
                ),
            ],
        )?,
    );
    files.extend(by_frame.draw(
        "gpu_ms",
        "Skinned crowd: GPU acceleration-structure ms per frame",
        "ms",
        &[("GPU AS ms".into(), per_frame(|r| r.gpu_as_ms))],
    )?);
    files.extend(report.files.iter().cloned());
    cli.output
        .finish(&cli.run.out, "skinned_crowd", &summary, &files)
}
