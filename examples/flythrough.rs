//! The main job: the open-world fly-through. The 4 km world is generated (and baked to disk
//! once), streamed by loader threads as a raster engine would (1,000 m), and fed to every policy
//! — `managed` (ours), `naive` and `seed` — each on its own Vulkan backend on the same device.
//! Every `--eval-every` frames each policy's TLAS is rendered and scored against the full-world
//! ground truth. Prints a side-by-side table; writes a per-frame CSV, `summary.json`, top-down
//! maps and each policy's worst frame (managed | reference | difference) to `--out`.
//!
//! ```text
//! cargo run --release --example flythrough -- --help
//! cargo run --release --example flythrough -- --deterministic --json
//! ```

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;
#[path = "support/profile.rs"]
mod profile;

use anyhow::Context;
use clap::Parser;
use rtstream::driver::RunReport;

/// The open-world fly-through: every policy on the real backend, scored against the full world.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    #[command(flatten)]
    run: cli::RunArgs,
    #[command(flatten)]
    output: cli::OutputArgs,
    /// Time `update`'s phases (the manager's and the backend's tracing spans), print the
    /// per-phase table and write the spans' self times to this file as folded stacks (for
    /// `inferno-flamegraph`).
    #[arg(long, value_name = "FILE")]
    profile: Option<std::path::PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let profiler = cli.profile.as_ref().map(|_| profile::PhaseProfile::new());
    let profile_data = profiler.as_ref().map(profile::PhaseProfile::data);
    cli::init_tracing_with(profiler);
    let config = cli.run.run_config()?;
    eprintln!(
        "fly-through: {} world (seed {:#x}), {} frames, stream radius {} m, {}; out: {}",
        config.preset.name,
        config.preset.seed,
        config.frames,
        config.stream.load_radius,
        if config.deterministic {
            "deterministic"
        } else {
            "real time"
        },
        cli.run.out.display()
    );
    let report = cli::run_with_progress(&config, cli.output.quiet, |_| {})
        .context("the fly-through failed")?;
    print_table(&report);
    if report.summary.evaluated_frames > 0 {
        let bands: Vec<String> = report.summary.bands.to_vec();
        let series: Vec<(String, Vec<f64>)> = report
            .summary
            .policies
            .iter()
            .map(|p| {
                (
                    p.policy.to_string(),
                    p.mismatch_by_band
                        .iter()
                        .map(|b| b.hit_mismatch_mean * 100.0)
                        .collect(),
                )
            })
            .collect();
        for f in charts::bars(
            &cli.run.out.join("error_by_band"),
            "where the error lives: hit mismatch by distance band (full-world ground truth)",
            "hit mismatch, % of all pixels",
            &bands,
            &series,
        )? {
            println!("wrote {}", f.display());
        }
    }
    if let (Some(path), Some(data)) = (&cli.profile, profile_data) {
        let data = data.lock();
        data.print();
        std::fs::write(path, data.folded())
            .with_context(|| format!("writing {}", path.display()))?;
        println!("wrote {} (folded stacks, µs)", path.display());
        // The first 60 frames stream the world in; the slowest frames after them, and what
        // made them slow (phases 0.1 ms or more over their median).
        println!("slowest frames from frame 60 (phases at least 0.1 ms over their median, ms):");
        for (frame, ms, over) in data.slowest(5, 60, 4, 0.1) {
            let phases: Vec<String> = over.iter().map(|(p, d)| format!("{p} +{d:.2}")).collect();
            println!("  frame {frame}: {ms:.2}  {}", phases.join(", "));
        }
        // `spans.folded` → `spans.frames.csv`; any other name gets `.frames.csv` appended (a
        // dot in it is not an extension to replace: `p0.5` and `p0` wrote the same file).
        let frames = if path.extension().is_some_and(|e| e == "folded") {
            path.with_extension("frames.csv")
        } else {
            let mut name = path.as_os_str().to_owned();
            name.push(".frames.csv");
            std::path::PathBuf::from(name)
        };
        std::fs::write(&frames, data.frames_csv(4))
            .with_context(|| format!("writing {}", frames.display()))?;
        println!("wrote {} (phase ms per frame)", frames.display());
    }
    if cli.output.json {
        println!("{}", report.json());
    }
    Ok(())
}

fn print_table(r: &RunReport) {
    let s = &r.summary;
    println!(
        "{} frames on {} in {:.0} s; {} scored at {}x{} against the full world ({} opaque instances, {} in never-loaded levels)",
        s.frames,
        s.device,
        s.seconds,
        s.evaluated_frames,
        s.size[0],
        s.size[1],
        s.reference.instances,
        s.reference.never_loaded_instances
    );
    // The policy column fits the longest name (`managed-tlas-update`).
    let w = s
        .policies
        .iter()
        .map(|p| p.policy.len())
        .max()
        .unwrap_or(0)
        .max(12);
    println!(
        "{:<w$} {:>9} {:>9} {:>7} {:>13} {:>8} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9} {:>9} {:>5}",
        "policy",
        "peak MB",
        "p95 MB",
        "TLAS",
        "far field",
        "upd p50",
        "upd p99",
        "gpu p50",
        "gpu p99",
        "hit mean",
        "hit p95",
        "shd mean",
        "shd p95",
        "over"
    );
    let pct = |v: f64| {
        if s.evaluated_frames == 0 {
            "-".to_string()
        } else {
            format!("{:.2}%", v * 100.0)
        }
    };
    for p in &s.policies {
        println!(
            "{:<w$} {:>9.1} {:>9.1} {:>7} {:>13} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>9} {:>9} {:>9} {:>9} {:>5}",
            p.policy,
            p.peak_blas_bytes as f64 / 1e6,
            p.p95_blas_bytes as f64 / 1e6,
            p.peak_tlas_instances,
            if p.peak_proxy_instances > 0 {
                format!(
                    "{} / {:.1} MB",
                    p.peak_proxy_instances,
                    p.peak_proxy_blas_bytes as f64 / 1e6
                )
            } else {
                "off".to_string()
            },
            p.update_ms_p50,
            p.update_ms_p99,
            p.gpu_as_ms_p50,
            p.gpu_as_ms_p99,
            pct(p.hit_mismatch_mean),
            pct(p.hit_mismatch_p95),
            pct(p.shadow_mismatch_mean),
            pct(p.shadow_mismatch_p95),
            p.over_budget_frames
        );
    }
    if s.evaluated_frames > 0 {
        println!("hit mismatch by distance band (share of all pixels):");
    }
    for p in s.policies.iter().filter(|_| s.evaluated_frames > 0) {
        let bands: Vec<String> = p
            .mismatch_by_band
            .iter()
            .map(|b| format!("{} {:.2}%", b.band, b.hit_mismatch_mean * 100.0))
            .collect();
        let all = p.error_all_geometry.as_ref().map_or(String::new(), |e| {
            format!("; vs all geometry {:.2}%", e.hit_mismatch.mean * 100.0)
        });
        println!("  {:<w$} {}{all}", p.policy, bands.join(", "));
    }
    println!(
        "what the peak holds, MB (BLASes): in the TLAS / requested, not in it / an LOD left, \
         kept / kept, nothing near / skinned; proxies held, of them in the TLAS"
    );
    for p in &s.policies {
        let Some(m) = &p.peak_memory_split else {
            continue;
        };
        let mb = |x: &rtstream::as_manager::SplitPart| {
            format!("{:.1} ({})", x.bytes as f64 / 1e6, x.count)
        };
        println!(
            "  {:<w$} frame {}: {} / {} / {} / {} / {}; proxies {}, {}",
            p.policy,
            m.frame,
            mb(&m.in_tlas),
            mb(&m.requested),
            mb(&m.superseded),
            mb(&m.kept),
            mb(&m.skinned),
            mb(&m.proxies),
            mb(&m.proxies_in_tlas)
        );
    }
    if let Some(t) = &s.frame_timing {
        println!(
            "frame timing ({}, {} frames in flight, {}x{}): frame p50 {:.2} / p99 {:.2} ms, \
             render passes p50 {:.2} / p99 {:.2} ms, update p50 {:.3} / p99 {:.3} ms, \
             frame / passes {:.2}",
            t.mode,
            t.frames_in_flight,
            t.size[0],
            t.size[1],
            t.frame_ms.p50,
            t.frame_ms.p99,
            t.passes_ms.p50,
            t.passes_ms.p99,
            t.update_ms.p50,
            t.update_ms.p99,
            t.frame_over_passes_p50
        );
    }
    let cpu: Vec<String> = s
        .policies
        .iter()
        .map(|p| {
            format!(
                "{} {:.2} / {:.2}",
                p.policy, p.update_cpu_ms_p50, p.update_cpu_ms_p99
            )
        })
        .collect();
    println!(
        "update's CPU time on its thread, ms p50 / p99 (wall time less waits for the core): {}",
        cpu.join("; ")
    );
    for p in s.policies.iter().filter(|p| p.peak_landmark_instances > 0) {
        println!(
            "  {:<w$} landmarks: peak {} records, {:.0} / {:.0} candidates looked at per frame (p50 / p99)",
            p.policy, p.peak_landmark_instances, p.landmarks_examined_p50, p.landmarks_examined_p99
        );
    }
    let copied: Vec<String> = s
        .policies
        .iter()
        .map(|p| {
            format!(
                "{} {:.2} MB, {:.1} %",
                p.policy,
                p.geometry_upload_mb_per_frame,
                p.tlas_records_written_share * 100.0
            )
        })
        .collect();
    println!(
        "per frame, new geometry copied by update and TLAS records written of those built: {}",
        copied.join("; ")
    );
    let tlas: Vec<String> = s
        .policies
        .iter()
        .map(|p| {
            format!(
                "{} {:.3} / {:.3} ms, {:.0} % updated",
                p.policy,
                p.gpu_tlas_ms_p50,
                p.gpu_tlas_ms_p99,
                p.tlas_update_share * 100.0
            )
        })
        .collect();
    println!(
        "TLAS GPU ms p50 / p99 and frames updating the last frame's TLAS: {}",
        tlas.join("; ")
    );
    if s.frame_timing.is_none() {
        // Measured on the H200: without a render a frame, its SM clock sat at 345 MHz
        // between the frames' short bursts of work (docs/GPU.md).
        println!(
            "(GPU ms without renders every frame: a GPU that idles between frames may run at \
             its idle clock; add --render-every 1 --size 1920x1080 for a game's load)"
        );
    }
    println!("validation messages: {}", s.validation_messages);
    for f in &r.files {
        println!("wrote {}", f.display());
    }
}
