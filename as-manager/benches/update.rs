//! `update` cost on the synthetic worlds: Managed vs the SeedR1R2 and Naive baselines, one and
//! four cameras, the default world and the 1M-instance world at the same density; and the
//! residency query itself: the manager's hash grid vs an rstar R*-tree (the peer design).
//! `update/default/managed(_far)/1cam_cold` time the same frames with the caches cold (64 MB
//! written between frames, not timed).
//!
//! Run: `cargo bench -p rtstream-as-manager --no-default-features --bench update`
//! (pin to one core with `taskset -c 0` for the single-core figure).

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use glam::Vec3;
use rstar::primitives::GeomWithData;
use rstar::RTree;
use rtstream_as_manager::backend::model::ModelBackend;
use rtstream_as_manager::spatial::GridIndex;
use rtstream_as_manager::synth::{SynthParams, SynthWorld};
use rtstream_as_manager::{AsManager, Config, FrameInput, PolicyKind, Viewpoint};
use rtstream_stats::Samples;

/// Camera speed along the path: 0.5 m per frame (30 m/s at 60 fps).
const SPEED: f32 = 0.5;
/// Frames run before measuring, so residency is in its steady state.
const WARMUP_FRAMES: u64 = 300;

/// Four cameras: a squad around the lead camera (split-screen co-op / nearby probes), within
/// 60 m of it. `n == 5` means four cameras spread ~1 km apart (informative: nothing shared).
fn cameras(world: &SynthWorld, frame: u64, n: usize) -> Vec<Viewpoint> {
    let lead = world.camera_on_path(frame, SPEED);
    if n == 5 {
        let spread = [
            Vec3::ZERO,
            Vec3::new(1000.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, 1000.0),
            Vec3::new(-1000.0, 0.0, -500.0),
        ];
        return spread
            .iter()
            .map(|o| Viewpoint::new(lead.position + *o, lead.forward))
            .collect();
    }
    let offsets = [
        Vec3::ZERO,
        Vec3::new(40.0, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 40.0),
        Vec3::new(-30.0, 0.0, -30.0),
    ];
    (0..n)
        .map(|i| Viewpoint::new(lead.position + offsets[i % 4], lead.forward))
        .collect()
}

struct Run {
    world: SynthWorld,
    manager: AsManager<ModelBackend>,
    frame: u64,
    cams: usize,
}

impl Run {
    /// `far`: the far field on with its default configuration (a group tree over the world,
    /// proxies and landmarks); off: the near field alone.
    fn new(world: &SynthWorld, policy: PolicyKind, cams: usize, far: bool) -> Self {
        let mut config = Config {
            policy,
            ..Config::default()
        };
        config.far_field.enabled = far;
        let manager = AsManager::new(config, ModelBackend::lavapipe()).unwrap();
        if far {
            // The default world's level blocks: 2x2 levels of 71 m, four depths.
            world.populate_with_groups(&manager, 143.0, 4).unwrap();
        } else {
            world.populate(&manager).unwrap();
        }
        let mut r = Run {
            world: world.clone(),
            manager,
            frame: 0,
            cams,
        };
        for _ in 0..WARMUP_FRAMES {
            r.step();
        }
        r
    }

    /// Times `n` single frames and prints median / p90 / mean: criterion's figures are means
    /// of batches and on this shared 2-core machine include preemptions by other processes.
    fn per_frame(&mut self, label: &str, n: usize) {
        let t = Samples::new((0..n).map(|_| {
            let s = std::time::Instant::now();
            black_box(self.step());
            s.elapsed().as_secs_f64() * 1e6
        }));
        eprintln!(
            "[{label}] per-frame over {n} frames: median {:.1} us, p90 {:.1} us, mean {:.1} us",
            t.median(),
            t.percentile(0.9),
            t.mean()
        );
    }

    fn step(&mut self) -> usize {
        let cams = cameras(&self.world, self.frame, self.cams);
        let out = self
            .manager
            .update(FrameInput {
                frame: self.frame,
                cameras: &cams,
            })
            .unwrap();
        self.frame += 1;
        out.instances.len()
    }
}

fn config(c: &mut Criterion) -> &mut Criterion {
    c
}

fn bench_update(c: &mut Criterion) {
    let default = SynthWorld::generate(SynthParams::default_world());
    let million = SynthWorld::generate(SynthParams::million());
    let (default, million) = (&default, &million);
    let mut g = config(c).benchmark_group("update");
    g.sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    for (wname, world) in [("default", default), ("million", million)] {
        for (pname, policy, far) in [
            ("managed", PolicyKind::Managed, false),
            ("managed_far", PolicyKind::Managed, true),
            ("seed_r1r2", PolicyKind::SeedR1R2, false),
        ] {
            for cams in [1usize, 4, 5] {
                if (wname == "million" && cams != 1)
                    || (policy != PolicyKind::Managed && cams == 5)
                    || (far && cams != 1)
                {
                    continue;
                }
                // Built lazily: a filtered-out benchmark costs no setup.
                let mut run: Option<Run> = None;
                let cam_label = if cams == 5 {
                    "4cam_spread".to_string()
                } else {
                    format!("{cams}cam")
                };
                let id = BenchmarkId::new(format!("{wname}/{pname}"), &cam_label);
                g.bench_function(id, |b| {
                    let run = run.get_or_insert_with(|| {
                        let mut r = Run::new(world, policy, cams, far);
                        let n = if policy == PolicyKind::Managed { 2000 } else if wname == "million" { 30 } else { 200 };
                        r.per_frame(&format!("{wname}/{pname}/{cam_label}"), n);
                        let s = r.manager.stats().clone();
                        eprintln!(
                            "[{wname}/{pname}/{cam_label}] instances {} visited {} (landmark candidates {}) tlas {} (proxies {}, landmarks {}) blas {} bytes {:.1} MiB",
                            s.instances,
                            s.instances_visited,
                            s.landmarks_examined,
                            s.tlas_instances,
                            s.proxy_instances,
                            s.landmark_instances,
                            s.blas_count,
                            s.memory_in_use() as f64 / (1 << 20) as f64
                        );
                        r
                    });
                    b.iter(|| black_box(run.step()))
                });
            }
        }
    }
    // The same frames with the caches cold: 64 MB written before each (not timed), as an
    // engine's other work and its renderer do between two calls of `update`
    // (`docs/PROFILE.md`, "Cold caches"). The far field's share of a cold frame is what an
    // engine pays; the warm figures above are what the code's own work costs.
    let mut caches = rtstream_as_manager::synth::CacheEvictor::new(64);
    for (pname, far) in [("managed", false), ("managed_far", true)] {
        let mut run: Option<Run> = None;
        let id = BenchmarkId::new(format!("default/{pname}"), "1cam_cold");
        g.bench_function(id, |b| {
            let run = run.get_or_insert_with(|| Run::new(default, PolicyKind::Managed, 1, far));
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    caches.evict();
                    let t = std::time::Instant::now();
                    black_box(run.step());
                    total += t.elapsed();
                }
                total
            })
        });
    }
    let mut naive: Option<Run> = None;
    g.bench_function(BenchmarkId::new("default/naive", "1cam"), |b| {
        let run = naive.get_or_insert_with(|| Run::new(default, PolicyKind::Naive, 1, false));
        b.iter(|| black_box(run.step()))
    });
    g.finish();
}

/// The residency query alone: instances within r2 of the camera, exact sphere test.
fn bench_query(c: &mut Criterion) {
    let world = SynthWorld::generate(SynthParams::default_world());
    let cfg = Config::default();
    let r2 = cfg.residency.r2;
    let spheres: Vec<(Vec3, f32)> = world
        .instances
        .iter()
        .map(|(m, t)| {
            let d = &world.meshes[*m];
            let s = t.matrix3.x_axis.length();
            (
                t.transform_point3(Vec3::from(d.bounds_center)),
                d.bounds_radius * s,
            )
        })
        .collect();
    let max_r = spheres.iter().map(|s| s.1).fold(0.0f32, f32::max);
    let mut grid = GridIndex::<()>::new(cfg.residency.cell_size);
    for (i, (c, r)) in spheres.iter().enumerate() {
        grid.insert(i as u32, *c, *r, ());
    }
    let tree: RTree<GeomWithData<[f32; 3], u32>> = RTree::bulk_load(
        spheres
            .iter()
            .enumerate()
            .map(|(i, (c, _))| GeomWithData::new(c.to_array(), i as u32))
            .collect(),
    );
    let mut g = c.benchmark_group("residency_query");
    g.sample_size(30)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2));
    let mut frame = 0u64;
    let mut out: Vec<(u32, f32)> = Vec::with_capacity(4096);
    g.bench_function("grid", |b| {
        b.iter(|| {
            let cam = world.camera_on_path(frame, SPEED).position;
            frame += 1;
            out.clear();
            grid.query(&[cam], r2, |_, e| {
                let d = (cam.distance(Vec3::from(e.center)) - e.radius).max(0.0);
                if d <= r2 {
                    out.push((e.slot, d));
                }
            });
            black_box(out.len())
        })
    });
    let mut frame = 0u64;
    g.bench_function("rstar", |b| {
        b.iter(|| {
            let cam = world.camera_on_path(frame, SPEED).position;
            frame += 1;
            out.clear();
            let reach = r2 + max_r;
            for p in tree.locate_within_distance(cam.to_array(), reach * reach) {
                let (c, r) = spheres[p.data as usize];
                let d = (cam.distance(c) - r).max(0.0);
                if d <= r2 {
                    out.push((p.data, d));
                }
            }
            black_box(out.len())
        })
    });
    g.finish();
}

criterion_group!(benches, bench_query, bench_update);
criterion_main!(benches);
