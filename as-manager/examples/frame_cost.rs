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
//! `update` µs, landmark looks, landmark waits, BLAS builds, releases, TLAS records.

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
}

fn main() {
    let args = Args::parse();
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
    for f in 300..300 + args.frames {
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
    }
    if let Ok(path) = std::env::var("FRAME_COST_DUMP") {
        // One line a frame: µs, landmark looks, landmark waits, builds, releases, TLAS records.
        let text: String = (0..times.len())
            .map(|i| {
                let (t, l, w, b) = (times[i], looks[i], waits[i], &other[i]);
                format!("{t:.1} {l} {w} {} {} {}\n", b.0, b.1, b.2)
            })
            .collect();
        std::fs::write(path, text).unwrap();
    }
    let t = Samples::new(times);
    let cpu = Samples::new(cpu);
    let (l, w) = (Samples::new(looks), Samples::new(waits));
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
}
