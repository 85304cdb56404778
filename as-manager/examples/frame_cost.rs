//! Quick frame-cost probe on the synthetic worlds (no criterion): mean and median `update`
//! time over a camera path, plus the frame statistics.
//!
//! `cargo run --release -p rtstream-as-manager --no-default-features --example frame_cost -- [--million] [--cams N] [--cell-size M] [--far] [--keep-angle DEG] [--frames N] [--speed M] [--instances N] [--no-incremental-detail] [--evict-mb N] [--json]`
//!
//! `--json` prints one JSON object instead (the run's parameters, `update`'s median, mean and
//! percentiles in µs, wall and the calling thread's CPU time, the landmark looks and waits a
//! frame), for scripts that sweep speeds or
//! worlds (`docs/PROFILE.md`, "What the far field costs with camera speed").
//!
//! With `FRAME_COST_DUMP=path`, every measured frame's figures go to `path`, one line a frame:
//! `update` µs, landmark looks, landmark waits, BLAS builds, releases, TLAS records; with
//! `--phases`, a header line (`# update_us ...`) names them and each phase's µs follows.

use std::time::Instant;

use clap::Parser;

use rtstream_as_manager::backend::model::ModelBackend;
use rtstream_as_manager::synth::{SynthParams, SynthWorld};
use rtstream_as_manager::{AsManager, Config, FrameInput, Viewpoint};
use rtstream_stats::Samples;

/// `update`'s per-frame cost on a synthetic world, on the model backend.
#[derive(Debug, Parser)]
struct Args {
    /// The 1,000,000-instance world (default: the 104,366-instance one).
    #[arg(long)]
    million: bool,
    /// Cameras (a squad within 60 m of the lead camera).
    #[arg(long, default_value_t = 1)]
    cams: usize,
    /// The residency grid's cell size, metres (default: the configuration's).
    #[arg(long)]
    cell_size: Option<f32>,
    /// The far field on, as the bench's `managed_far` (a group tree of the default world's
    /// level blocks, proxies, landmarks); off: the near field alone.
    #[arg(long)]
    far: bool,
    /// The far field's keep angle, degrees (0: no landmarks; default: the configuration's).
    /// The landmark set still looks at the near leaves' detail beyond r2 at any angle (about
    /// 7.8 looks a frame on the default world) unless `--no-incremental-detail`.
    #[arg(long)]
    keep_angle: Option<f32>,
    /// Frames measured after the 300 warm-up frames.
    #[arg(long, default_value_t = 3000)]
    frames: u64,
    /// Camera speed, metres a frame (the bench's 0.5; the fly-through moves 8.2).
    #[arg(long, default_value_t = 0.5)]
    speed: f32,
    /// Print one JSON object (parameters and figures) instead of the text report.
    #[arg(long)]
    json: bool,
    /// The near leaves' detail beyond r2 visited by the residency pass every frame instead of
    /// kept by the landmark set (`FarFieldConfig::incremental_detail: false`).
    #[arg(long)]
    no_incremental_detail: bool,
    /// Writes this many MB between frames (outside the timing), as an engine's other work
    /// and a renderer do: `update` then starts with cold caches.
    #[arg(long, default_value_t = 0)]
    evict_mb: usize,
    /// Instances in the world (default: the world's own; e.g. 1100000 on the default world's
    /// 4 km map for 10x density).
    #[arg(long)]
    instances: Option<usize>,
    /// Times the manager's phases (its `tracing` spans) in every measured frame and reports
    /// each one's median and mean, µs (two clock reads a span: about 20 spans a frame).
    #[arg(long)]
    phases: bool,
}

/// Per frame, the wall time of each span by name (µs), summed over its entries.
#[derive(Default)]
struct PhaseTimes(parking_lot::Mutex<std::collections::BTreeMap<&'static str, f64>>);

/// A `tracing` layer adding each span's time between enter and exit into `PhaseTimes`.
struct PhaseLayer(std::sync::Arc<PhaseTimes>);

/// When the span was last entered (kept in the span's extensions).
struct Entered(Instant);

impl<S> tracing_subscriber::Layer<S> for PhaseLayer
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    fn on_enter(&self, id: &tracing::span::Id, ctx: tracing_subscriber::layer::Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            span.extensions_mut().replace(Entered(Instant::now()));
        }
    }

    fn on_exit(&self, id: &tracing::span::Id, ctx: tracing_subscriber::layer::Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        let Some(Entered(t)) = span.extensions_mut().remove::<Entered>() else {
            return;
        };
        let us = t.elapsed().as_secs_f64() * 1e6;
        *self.0 .0.lock().entry(span.name()).or_default() += us;
    }
}

fn main() {
    let args = Args::parse();
    let phase_times = args.phases.then(|| {
        use tracing_subscriber::layer::SubscriberExt;
        let times = std::sync::Arc::new(PhaseTimes::default());
        let subscriber = tracing_subscriber::registry().with(PhaseLayer(times.clone()));
        tracing::subscriber::set_global_default(subscriber).expect("the only subscriber");
        times
    });
    let params = if args.million {
        SynthParams::million()
    } else {
        SynthParams::default_world()
    };
    let params = SynthParams {
        instances: args.instances.unwrap_or(params.instances),
        ..params
    };
    let cams = args.cams;
    let instances = params.instances;
    let world = SynthWorld::generate(params);
    let mut config = Config::default();
    if let Some(c) = args.cell_size {
        config.residency.cell_size = c;
    }
    config.far_field.enabled = args.far;
    config.far_field.incremental_detail = !args.no_incremental_detail;
    if let Some(a) = args.keep_angle {
        config.far_field.keep_angle = a.to_radians();
    }
    let mut m = AsManager::new(config, ModelBackend::lavapipe()).unwrap();
    if args.far {
        // The default world's level blocks: 2x2 levels of 71 m, four depths (as the bench).
        world.populate_with_groups(&m, 143.0, 4).unwrap();
    } else {
        world.populate(&m).unwrap();
    }
    let cameras = |f: u64| -> Vec<Viewpoint> {
        let lead = world.camera_on_path(f, args.speed);
        let off = [
            glam::Vec3::ZERO,
            glam::Vec3::new(40.0, 0.0, 0.0),
            glam::Vec3::new(0.0, 0.0, 40.0),
            glam::Vec3::new(-30.0, 0.0, -30.0),
        ];
        (0..cams)
            .map(|i| Viewpoint::new(lead.position + off[i % 4], lead.forward))
            .collect()
    };
    for f in 0..300 {
        m.update(FrameInput {
            frame: f,
            cameras: &cameras(f),
        })
        .unwrap();
    }
    let (mut times, mut cpu) = (Vec::new(), Vec::new());
    let (mut looks, mut waits, mut other) = (Vec::new(), Vec::new(), Vec::new());
    let mut caches = rtstream_as_manager::synth::CacheEvictor::new(args.evict_mb);
    let mut phases: std::collections::BTreeMap<&'static str, Vec<f64>> = Default::default();
    if let Some(p) = &phase_times {
        p.0.lock().clear();
    }
    for (n, f) in (300..300 + args.frames).enumerate() {
        let c = cameras(f);
        caches.evict();
        let t = Instant::now();
        let thread = cpu_time::ThreadTime::now();
        m.update(FrameInput {
            frame: f,
            cameras: &c,
        })
        .unwrap();
        times.push(t.elapsed().as_secs_f64() * 1e6);
        cpu.push(thread.elapsed().as_secs_f64() * 1e6);
        let st = m.stats();
        looks.push(st.landmarks_examined as f64);
        waits.push(st.landmarks_waited as f64);
        other.push((st.builds, st.releases, st.tlas_instances));
        if let Some(p) = &phase_times {
            // A phase that did not run this frame counts 0 (every phase has a sample a frame).
            for (name, us) in std::mem::take(&mut *p.0.lock()) {
                phases.entry(name).or_insert_with(|| vec![0.0; n]).push(us);
            }
            for v in phases.values_mut() {
                v.resize(n + 1, 0.0);
            }
        }
    }

    let phases: Vec<(&str, Vec<f64>)> = phases.into_iter().collect();
    if let Ok(path) = std::env::var("FRAME_COST_DUMP") {
        // One line a frame: µs, landmark looks, landmark waits, builds, releases, TLAS records,
        // then (with `--phases`) each phase's µs in the order of the header line.
        let mut text = String::new();
        if !phases.is_empty() {
            let names: Vec<&str> = phases.iter().map(|(n, _)| *n).collect();
            text += &format!(
                "# update_us landmark_looks landmark_waits blas_builds releases tlas_records {}\n",
                names.join(" ")
            );
        }
        for i in 0..times.len() {
            let (t, l, w, b) = (times[i], looks[i], waits[i], &other[i]);
            text += &format!("{t:.1} {l} {w} {} {} {}", b.0, b.1, b.2);
            for (_, v) in &phases {
                text += &format!(" {:.2}", v[i]);
            }
            text.push('\n');
        }
        std::fs::write(path, text).unwrap();
    }
    let t = Samples::new(times);
    let cpu = Samples::new(cpu);
    let (l, w) = (Samples::new(looks), Samples::new(waits));
    let phases: Vec<(&str, Samples)> = phases
        .into_iter()
        .map(|(name, v)| (name, Samples::new(v)))
        .collect();
    if args.json {
        let out = serde_json::json!({
            "world": if args.million { "million" } else { "default" },
            "far_field": args.far,
            "cameras": cams,
            "speed_m_per_frame": args.speed,
            "frames": args.frames,
            "update_us": {
                "median": t.median(),
                "mean": t.mean(),
                "p10": t.percentile(0.1),
                "p90": t.percentile(0.9),
                "p99": t.percentile(0.99),
                "max": t.max(),
            },
            "update_thread_cpu_us": {
                "median": cpu.median(),
                "mean": cpu.mean(),
                "p99": cpu.percentile(0.99),
            },
            "instances": instances,
            "landmark_looks_per_frame": { "mean": l.mean(), "median": l.median() },
            "landmark_waits_per_frame": { "mean": w.mean(), "median": w.median() },
            "phases_us": phases
                .iter()
                .map(|(name, s)| (name.to_string(), serde_json::json!({
                    "median": s.median(),
                    "mean": s.mean(),
                    "p99": s.percentile(0.99),
                })))
                .collect::<serde_json::Map<_, _>>(),
        });
        println!("{out}");
        return;
    }
    println!(
        "median {:.1} us, mean {:.1} us, p10 {:.1} p90 {:.1} p99 {:.1} max {:.1} us",
        t.median(),
        t.mean(),
        t.percentile(0.1),
        t.percentile(0.9),
        t.percentile(0.99),
        t.max()
    );
    println!(
        "the calling thread's CPU time: median {:.1} us, mean {:.1} us, p99 {:.1} us",
        cpu.median(),
        cpu.mean(),
        cpu.percentile(0.99)
    );
    println!("{:?}", m.stats());
    println!(
        "landmark looks per frame: mean {:.1}, median {:.1}; waits: mean {:.1}, median {:.1}",
        l.mean(),
        l.median(),
        w.mean(),
        w.median()
    );
    for (name, s) in &phases {
        println!(
            "phase {name:>14}: median {:.1} us, mean {:.1} us, p99 {:.1} us",
            s.median(),
            s.mean(),
            s.percentile(0.99)
        );
    }
}
