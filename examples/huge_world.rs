//! Huge worlds, in two parts, each against the default world in the same run:
//! - `model`: the 1,000,000-instance synthetic world on the model backend (no GPU): the
//!   manager's per-frame `update` p50/p99 against the 104k-instance default;
//! - `stream`: the 1.76M-instance `large_world` preset, baked to disk and streamed from it into
//!   the managed policy on the real Vulkan backend through the shared driver, along a path
//!   that crosses the map: per-frame `update` p50/p99 against the default world's, and the
//!   process's resident memory and open files sampled along the way (they must stay flat).
//!
//! The manager's flags (`--r1`, `--r2`, `--budget-mb`, culling, LOD, build budget) apply to
//! both parts.
//!
//! ```text
//! cargo run --release --example huge_world -- --help
//! cargo run --release --example huge_world -- --part model --json
//! cargo run --release --example huge_world -- --part stream --frames 600 --json
//! ```

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;

use anyhow::Context;
use clap::ValueEnum;
use rtstream::as_manager::backend::model::ModelBackend;
use rtstream::as_manager::synth::{SynthParams, SynthWorld};
use rtstream::as_manager::{AsManager, Config, FrameInput, PolicyKind};
use rtstream::streaming::WorldPreset;
use rtstream::{driver, stats};
use serde::Serialize;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Part {
    /// 1M synthetic instances on the model backend.
    Model,
    /// The 1.76M-instance large world streamed from disk on the real backend.
    Stream,
    /// Both.
    Both,
}

/// The example's own flags.
#[derive(Debug, clap::Args)]
struct Flags {
    /// Which part to run.
    #[arg(long, value_enum, default_value_t = Part::Both)]
    part: Part,
    /// Frames of the model part (after 300 warm-up frames; 1 to 1,000,000).
    #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    model_frames: u64,
    /// Runs of each part, alternating the default and the huge world; the ratios reported are
    /// the medians over the pairs (the machine's noise is of the size of the differences).
    #[arg(long, default_value_t = 1)]
    repeat: u32,
    /// Walk both worlds' paths in the same number of frames (the large world's camera then moves
    /// 4x as far per frame). By default the large world gets frames in proportion to its size,
    /// so that both cameras move at the same speed and only the world's size differs.
    #[arg(long)]
    equal_frames: bool,
    /// Sample resident memory and open files every this many frames (stream part).
    #[arg(long, default_value_t = 30)]
    sample_every: u64,
}

/// Per-frame update time of one world.
#[derive(Debug, Serialize)]
struct WorldRun {
    world: String,
    instances: usize,
    update_ms: stats::Summary,
}

/// Resident memory and open files along the stream part's path.
#[derive(Debug, Serialize)]
struct Sample {
    frame: u64,
    rss_mib: f64,
    open_files: usize,
    levels_loaded: usize,
}

#[derive(Debug, Serialize)]
struct StreamRun {
    world: String,
    instances: usize,
    update_ms: stats::Summary,
    /// Frames of the path, and the camera's mean speed along it (metres per frame).
    frames: u64,
    m_per_frame: f64,
    samples: Vec<Sample>,
    /// Largest over smallest resident memory after the first tenth of the path.
    rss_ratio: f64,
    open_files_min: usize,
    open_files_max: usize,
    over_budget_frames: u64,
    validation_messages: u64,
}

#[derive(Debug, Default, Serialize)]
struct Summary {
    model: Vec<WorldRun>,
    /// p50 and p99 of the 1M world over the default's (median over the repeated pairs), and
    /// every pair's ratios.
    model_ratios: Vec<(f64, f64)>,
    model_ratio_p50: Option<f64>,
    model_ratio_p99: Option<f64>,
    stream: Vec<StreamRun>,
    stream_ratios: Vec<(f64, f64)>,
    stream_ratio_p50: Option<f64>,
    stream_ratio_p99: Option<f64>,
    over_budget_frames: u64,
    validation_messages: u64,
}

fn main() -> anyhow::Result<()> {
    let cli = cli::ExampleCli::<Flags>::start(
        "The 1M-instance and 1.76M-instance worlds against the default one.",
        "out/huge_world",
    );
    let own = &cli.own;
    // The run's configuration, checked before either part runs (a bad flag, r1 above r2 say,
    // is an error whichever part is asked for). The model part takes its manager
    // configuration (radii, culling, LOD, budgets).
    let base = cli.run.run_config()?;
    let mut s = Summary::default();
    if matches!(own.part, Part::Model | Part::Both) {
        for k in 0..own.repeat.max(1) {
            for (name, params) in [
                ("default (104k)", SynthParams::default_world()),
                ("million", SynthParams::million()),
            ] {
                eprintln!("model backend: {name} (run {})", k + 1);
                s.model.push(model_run(
                    name,
                    params,
                    base.managed.clone(),
                    own.model_frames,
                )?);
            }
            let n = s.model.len();
            let (a, b) = (&s.model[n - 2].update_ms, &s.model[n - 1].update_ms);
            s.model_ratios.push((b.p50 / a.p50, b.p99 / a.p99));
        }
        (s.model_ratio_p50, s.model_ratio_p99) = median_ratios(&s.model_ratios);
    }
    if matches!(own.part, Part::Stream | Part::Both) {
        let pairs = (0..own.repeat.max(1))
            .flat_map(|_| [WorldPreset::default_world(), WorldPreset::large_world()]);
        for (i, preset) in pairs.enumerate() {
            let mut c = base.clone();
            cli.run.use_preset(&mut c, preset);
            if cli.run.world.is_some() {
                // One --world cannot hold both worlds.
                c.world_dir = format!("out/world-{}-{:x}", c.preset.name, c.preset.seed).into();
            }
            if !own.equal_frames {
                // The path crosses the map's diagonal in `frames` frames: scale the frames with
                // the map so that the camera moves as many metres per frame in both worlds.
                let scale = c.preset.size_m / WorldPreset::default_world().size_m;
                c.frames = (base.frames as f32 * scale).round() as u64;
            }
            c.policies = vec![PolicyKind::Managed];
            c.eval_every = 0;
            c.maps = 0;
            c.out_dir = None;
            eprintln!("streamed from disk: {}", c.preset.name);
            let mut r = stream_run(&c, own.sample_every, cli.output.quiet)?;
            if own.repeat > 1 {
                r.world = format!("{} #{}", r.world, i / 2 + 1);
            }
            s.over_budget_frames += r.over_budget_frames;
            s.validation_messages += r.validation_messages;
            s.stream.push(r);
            if i % 2 == 1 {
                let n = s.stream.len();
                let (a, b) = (&s.stream[n - 2].update_ms, &s.stream[n - 1].update_ms);
                s.stream_ratios.push((b.p50 / a.p50, b.p99 / a.p99));
            }
        }
        (s.stream_ratio_p50, s.stream_ratio_p99) = median_ratios(&s.stream_ratios);
    }
    print_table(&s);
    std::fs::create_dir_all(&cli.run.out)?;
    let mut files = Vec::new();
    if !s.stream.is_empty() {
        let series = |f: fn(&Sample) -> f64| -> Vec<(String, Vec<(f64, f64)>)> {
            s.stream
                .iter()
                .map(|r| {
                    (
                        r.world.clone(),
                        r.samples.iter().map(|x| (x.frame as f64, f(x))).collect(),
                    )
                })
                .collect()
        };
        let by_frame = charts::LineCharts::new(&cli.run.out, "frame");
        files = by_frame.draw(
            "rss",
            "Resident memory along a path across the map",
            "MiB",
            &series(|x| x.rss_mib),
        )?;
        files.extend(by_frame.draw(
            "open_files",
            "Open files along a path across the map",
            "file descriptors",
            &series(|x| x.open_files as f64),
        )?);
    }
    cli.output.finish(&cli.run.out, "huge_world", &s, &files)
}

/// Medians of the pairs' p50 and p99 ratios.
fn median_ratios(pairs: &[(f64, f64)]) -> (Option<f64>, Option<f64>) {
    let median = |f: fn(&(f64, f64)) -> f64| {
        (!pairs.is_empty()).then(|| stats::Summary::of(pairs.iter().map(f)).p50)
    };
    (median(|p| p.0), median(|p| p.1))
}

/// The manager configured by `config` on the model backend over `params`'s world, camera on
/// the synthetic loop.
fn model_run(
    name: &str,
    params: SynthParams,
    config: Config,
    frames: u64,
) -> anyhow::Result<WorldRun> {
    let world = SynthWorld::generate(params);
    let manager = AsManager::new(config, ModelBackend::lavapipe())?;
    world.populate(&manager)?;
    let mut manager = manager;
    let mut times = Vec::with_capacity(frames as usize);
    for frame in 0..300 + frames {
        let cams = [world.camera_on_path(frame, 0.5)];
        let t = std::time::Instant::now();
        manager.update(FrameInput {
            frame,
            cameras: &cams,
        })?;
        if frame >= 300 {
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok(WorldRun {
        world: name.into(),
        instances: world.instances.len(),
        update_ms: stats::Summary::of(times),
    })
}

/// Resident set size of this process in MiB (Linux; 0 elsewhere).
fn rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.split_whitespace().next()?.parse::<f64>().ok())
        })
        .map_or(0.0, |kib| kib / 1024.0)
}

/// Open file descriptors of this process (Linux; 0 elsewhere).
fn open_files() -> usize {
    std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count())
}

fn stream_run(c: &driver::RunConfig, every: u64, quiet: bool) -> anyhow::Result<StreamRun> {
    let world = driver::prepare_world(&c.preset, &c.world_dir)
        .with_context(|| format!("generating and baking {}", c.preset.name))?;
    let instances = world.instance_count();
    drop(world);
    let mut samples = Vec::new();
    let (mut travelled, mut last) = (0.0f64, None::<glam::Vec3>);
    let report = cli::run_with_progress(c, quiet, |p| {
        if let Some(l) = last {
            travelled += f64::from(l.distance(p.camera));
        }
        last = Some(p.camera);
        if p.frame % every.max(1) == 0 {
            samples.push(Sample {
                frame: p.frame,
                rss_mib: rss_mib(),
                open_files: open_files(),
                levels_loaded: p.levels_loaded,
            });
        }
    })
    .with_context(|| format!("streaming {}", c.preset.name))?;
    let p = &report.summary.policies[0];
    let times = cli::managed_rows(&report.rows)
        .into_iter()
        .map(|r| r.update_ms);
    let later: Vec<&Sample> = samples.iter().skip(samples.len() / 10).collect();
    let rss_min = later
        .iter()
        .map(|x| x.rss_mib)
        .fold(f64::INFINITY, f64::min);
    let rss_max = later.iter().map(|x| x.rss_mib).fold(0.0, f64::max);
    Ok(StreamRun {
        world: c.preset.name.clone(),
        instances,
        update_ms: stats::Summary::of(times),
        frames: c.frames,
        m_per_frame: travelled / c.frames.saturating_sub(1).max(1) as f64,
        rss_ratio: if rss_min > 0.0 {
            rss_max / rss_min
        } else {
            0.0
        },
        open_files_min: later.iter().map(|x| x.open_files).min().unwrap_or(0),
        open_files_max: later.iter().map(|x| x.open_files).max().unwrap_or(0),
        samples,
        over_budget_frames: p.over_budget_frames,
        validation_messages: p.validation_messages,
    })
}

fn print_table(s: &Summary) {
    if !s.model.is_empty() {
        println!("model backend: per-frame update (ms)");
        println!(
            "{:<16} {:>10} {:>9} {:>9}",
            "world", "instances", "p50", "p99"
        );
        for r in &s.model {
            println!(
                "{:<16} {:>10} {:>9.3} {:>9.3}",
                r.world, r.instances, r.update_ms.p50, r.update_ms.p99
            );
        }
        println!(
            "million / default: p50 {:.2}x, p99 {:.2}x (median of {} pairs; target at most 1.2x)",
            s.model_ratio_p50.unwrap_or(0.0),
            s.model_ratio_p99.unwrap_or(0.0),
            s.model_ratios.len()
        );
    }
    if !s.stream.is_empty() {
        println!("streamed from disk, real backend: per-frame update (ms), memory, open files");
        println!(
            "{:<10} {:>10} {:>7} {:>7} {:>9} {:>9} {:>10} {:>12} {:>5} {:>5}",
            "world",
            "instances",
            "frames",
            "m/frame",
            "p50",
            "p99",
            "RSS ratio",
            "open files",
            "over",
            "valid"
        );
        for r in &s.stream {
            println!(
                "{:<10} {:>10} {:>7} {:>7.1} {:>9.3} {:>9.3} {:>10.3} {:>5}..{:<6} {:>5} {:>5}",
                r.world,
                r.instances,
                r.frames,
                r.m_per_frame,
                r.update_ms.p50,
                r.update_ms.p99,
                r.rss_ratio,
                r.open_files_min,
                r.open_files_max,
                r.over_budget_frames,
                r.validation_messages
            );
        }
        println!(
            "large / default: p50 {:.2}x, p99 {:.2}x (median of {} pairs; target at most 1.2x)",
            s.stream_ratio_p50.unwrap_or(0.0),
            s.stream_ratio_p99.unwrap_or(0.0),
            s.stream_ratios.len()
        );
    }
}
