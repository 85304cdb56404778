//! Property tests: random sequences of API calls, camera moves, teleports, budget changes,
//! rejected inputs (NaN, infinite and huge transforms, dead meshes, repeated frame numbers),
//! skipped frames and backend faults hold the invariants of ARCHITECTURE.md after every frame:
//! the memory and build budgets, a TLAS of live built BLASes only, no BLAS freed or destroyed
//! while a frame uses it (the model backend checks lifetimes), a failed frame rolled back and
//! retried under the same number, a lost device reported by every later update, and a
//! rejected input answered with a typed error that changes nothing.

use std::sync::Arc;

use glam::{Affine3A, Vec3};
use proptest::prelude::*;
use rtstream_as_manager::backend::model::ModelBackend;
use rtstream_as_manager::synth::{counts_chain, grid_geometry};
use rtstream_as_manager::*;

#[derive(Debug, Clone)]
enum Op {
    Add {
        mesh: usize,
        n: usize,
        x: f32,
        z: f32,
    },
    Remove {
        k: usize,
    },
    Move {
        k: usize,
        x: f32,
        z: f32,
    },
    Walk {
        dx: f32,
        dz: f32,
        frames: u64,
    },
    Teleport {
        x: f32,
        z: f32,
    },
    MemoryBudget {
        bytes: u64,
    },
    BuildBudget {
        prims: u64,
    },
    Deform {
        k: usize,
    },
    Unregister {
        mesh: usize,
    },
    Frames {
        n: u64,
    },
    /// A transform with NaN, infinite or huge values.
    BadTransform {
        k: usize,
        v: f32,
    },
    /// An instance of an unregistered mesh.
    DeadMesh {
        mesh: usize,
    },
    /// The same frame number again.
    RepeatFrame,
    /// Frame numbers jump ahead.
    SkipFrames {
        n: u64,
    },
    /// The next backend call at `point` fails (device lost when `lost`).
    Fault {
        point: usize,
        lost: bool,
    },
}

const POINTS: [backend::FaultPoint; 5] = [
    backend::FaultPoint::BuildBlases,
    backend::FaultPoint::RefitBlases,
    backend::FaultPoint::CompactBlas,
    backend::FaultPoint::BuildTlas,
    backend::FaultPoint::EndFrame,
];

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        3 => (0..10usize, 1..40usize, -300f32..300.0, -300f32..300.0).prop_map(|(mesh, n, x, z)| Op::Add { mesh, n, x, z }),
        1 => (0..1000usize).prop_map(|k| Op::Remove { k }),
        1 => (0..1000usize, -300f32..300.0, -300f32..300.0).prop_map(|(k, x, z)| Op::Move { k, x, z }),
        4 => (-8f32..8.0, -8f32..8.0, 1..20u64).prop_map(|(dx, dz, frames)| Op::Walk { dx, dz, frames }),
        1 => (-400f32..400.0, -400f32..400.0).prop_map(|(x, z)| Op::Teleport { x, z }),
        1 => (200_000u64..20_000_000).prop_map(|bytes| Op::MemoryBudget { bytes }),
        1 => (1_000u64..100_000).prop_map(|prims| Op::BuildBudget { prims }),
        1 => (0..1000usize).prop_map(|k| Op::Deform { k }),
        1 => (0..10usize).prop_map(|mesh| Op::Unregister { mesh }),
        2 => (1..10u64).prop_map(|n| Op::Frames { n }),
        1 => (0..1000usize, prop_oneof![Just(f32::NAN), Just(f32::INFINITY), Just(f32::NEG_INFINITY), Just(1e30f32), Just(-3e38f32)])
            .prop_map(|(k, v)| Op::BadTransform { k, v }),
        1 => (0..10usize).prop_map(|mesh| Op::DeadMesh { mesh }),
        1 => Just(Op::RepeatFrame),
        1 => (1..1000u64).prop_map(|n| Op::SkipFrames { n }),
        1 => (0..5usize, prop::bool::weighted(0.15)).prop_map(|(point, lost)| Op::Fault { point, lost }),
    ]
}

fn config() -> impl Strategy<Value = Config> {
    (
        20f32..150.0,
        0f32..80.0,
        0u32..4,
        0u32..12,
        0u32..10,
        1_000u64..60_000,
        500_000u64..10_000_000,
    )
        .prop_map(|(r1, extra, create, release, min_life, prims, bytes)| {
            let mut c = Config::default();
            c.residency.r1 = r1;
            c.residency.r2 = r1 + extra;
            c.residency.create_threshold = create;
            c.residency.release_threshold = release;
            c.residency.min_resident_frames = min_life;
            c.residency.cell_size = 32.0;
            c.build.max_primitives = prims;
            c.build.max_gpu_ms = 5.0;
            c.memory.blas_bytes = bytes;
            c
        })
}

struct Harness {
    m: AsManager<ModelBackend>,
    meshes: Vec<Option<MeshId>>,
    /// Ids of unregistered meshes.
    dead: Vec<MeshId>,
    /// The device was lost: every later update must say so.
    lost: bool,
    /// Frames that failed by an injected fault and were retried.
    retried: u32,
    skinned: Vec<bool>,
    instances: Vec<(InstanceId, usize)>,
    cam: Vec3,
    frame: u64,
    /// Updates since the memory budget was last cut.
    budget_cut_at: Option<u32>,
}

impl Harness {
    fn new(config: Config) -> Self {
        let m = AsManager::new(config, ModelBackend::lavapipe()).unwrap();
        let mut meshes = Vec::new();
        let mut skinned = Vec::new();
        for i in 0..10 {
            let desc = if i >= 8 {
                MeshDesc::new(
                    format!("skinned{i}"),
                    MeshKind::Skinned,
                    1.5,
                    vec![LodDesc {
                        geometry: LodGeometry::Data(grid_geometry(8, 2.0)),
                        geometric_error: 0.0,
                    }],
                )
            } else {
                MeshDesc::new(
                    format!("m{i}"),
                    MeshKind::Static,
                    0.5 + i as f32,
                    counts_chain(500 << (i % 6), 4, 0.01),
                )
            };
            skinned.push(i >= 8);
            meshes.push(Some(m.register_mesh(desc).unwrap()));
        }
        Self {
            m,
            meshes,
            dead: Vec::new(),
            lost: false,
            retried: 0,
            skinned,
            instances: Vec::new(),
            cam: Vec3::ZERO,
            frame: 0,
            budget_cut_at: None,
        }
    }

    fn frame(&mut self) -> Result<(), TestCaseError> {
        let cams = [Camera::new(self.cam, Vec3::Z)];
        let f = self.frame;
        self.frame += 1;
        let cfg = self.m.config().clone();
        if self.lost {
            let e = self
                .m
                .update(FrameInput {
                    frame: f,
                    cameras: &cams,
                })
                .err();
            prop_assert_eq!(e, Some(AsError::Backend(backend::BackendError::DeviceLost)));
            return Ok(());
        }
        // (stats, TLAS record addresses) of a successful update.
        let run = |m: &mut AsManager<ModelBackend>| {
            m.update(FrameInput {
                frame: f,
                cameras: &cams,
            })
            .map(|o| {
                let addrs: Vec<u64> = o.instances.iter().map(|r| r.blas_address).collect();
                (o.stats.clone(), addrs)
            })
        };
        let (s, addrs) = match run(&mut self.m) {
            Ok(done) => done,
            Err(AsError::Backend(backend::BackendError::DeviceLost)) => {
                self.lost = true;
                self.m.check_invariants().map_err(TestCaseError::fail)?;
                return Ok(());
            }
            Err(AsError::Backend(backend::BackendError::Other(m))) if m == "injected" => {
                // Rolled back: the invariants hold and the same frame number succeeds.
                self.m.check_invariants().map_err(TestCaseError::fail)?;
                self.retried += 1;
                run(&mut self.m).map_err(|e| TestCaseError::fail(format!("retry of {f}: {e}")))?
            }
            Err(e) => return Err(TestCaseError::fail(format!("frame {f}: {e}"))),
        };
        self.m.check_invariants().map_err(TestCaseError::fail)?;
        prop_assert_eq!(
            self.m.backend().counters().lifetime_violations,
            0,
            "frame {}: a BLAS freed or destroyed while a frame used it",
            f
        );
        // TLAS references only live, built BLASes.
        for a in addrs {
            prop_assert!(
                self.m.backend().is_live_address(a),
                "frame {f}: dead BLAS in TLAS"
            );
        }
        // Build budget, except one oversized item alone.
        prop_assert!(
            s.build_primitives <= cfg.build.max_primitives
                || (s.oversized_admitted && s.builds == 1),
            "frame {f}: {} prims over budget {}",
            s.build_primitives,
            cfg.build.max_primitives
        );
        // Memory budget (after a budget cut, freed bytes still in flight drain within the
        // backend's frames in flight).
        // Counted in updates: skipped frame numbers do not give the cut time to drain.
        if let Some(n) = self.budget_cut_at.as_mut() {
            *n += 1;
        }
        let settled = self.budget_cut_at.is_none_or(|n| n > 3);
        if settled {
            prop_assert!(
                s.memory_in_use() <= cfg.memory.blas_bytes,
                "frame {f}: {} > {}",
                s.memory_in_use(),
                cfg.memory.blas_bytes
            );
            prop_assert!(self.m.backend().allocated_bytes() <= cfg.memory.blas_bytes);
        }
        prop_assert!(s.blas_bytes <= cfg.memory.blas_bytes || !settled);
        Ok(())
    }

    fn apply(&mut self, op: Op) -> Result<(), TestCaseError> {
        match op {
            Op::Add { mesh, n, x, z } => {
                if let Some(id) = self.meshes[mesh] {
                    for i in 0..n {
                        let t = Affine3A::from_translation(Vec3::new(
                            x + (i % 7) as f32 * 3.0,
                            0.0,
                            z + (i / 7) as f32 * 3.0,
                        ));
                        let iid = self.m.add_instance(InstanceDesc::new(id, t)).unwrap();
                        self.instances.push((iid, mesh));
                    }
                }
            }
            Op::Remove { k } if !self.instances.is_empty() => {
                let (id, _) = self.instances.swap_remove(k % self.instances.len());
                self.m.remove_instance(id).unwrap();
            }
            Op::Move { k, x, z } if !self.instances.is_empty() => {
                let (id, _) = self.instances[k % self.instances.len()];
                self.m
                    .set_transform(id, Affine3A::from_translation(Vec3::new(x, 0.0, z)))
                    .unwrap();
            }
            Op::Walk { dx, dz, frames } => {
                for _ in 0..frames {
                    self.cam += Vec3::new(dx, 0.0, dz);
                    self.frame()?;
                }
            }
            Op::Teleport { x, z } => {
                self.cam = Vec3::new(x, 2.0, z);
                self.frame()?;
            }
            Op::MemoryBudget { bytes } => {
                let mut c = self.m.config().clone();
                if bytes < c.memory.blas_bytes {
                    self.budget_cut_at = Some(0);
                }
                c.memory.blas_bytes = bytes;
                self.m.set_config(c).unwrap();
            }
            Op::BuildBudget { prims } => {
                let mut c = self.m.config().clone();
                c.build.max_primitives = prims;
                self.m.set_config(c).unwrap();
            }
            Op::Deform { k } => {
                let sk: Vec<InstanceId> = self
                    .instances
                    .iter()
                    .filter(|(_, m)| self.skinned[*m])
                    .map(|(i, _)| *i)
                    .collect();
                if !sk.is_empty() {
                    let id = sk[k % sk.len()];
                    let g = grid_geometry(8, 2.0);
                    let t = k as f32 * 0.37;
                    let p: Vec<[f32; 3]> = g
                        .positions
                        .iter()
                        .map(|v| [v[0] * (1.0 + t.sin()), (v[0] * 5.0 + t).sin() * t, v[2]])
                        .collect();
                    self.m.set_skinned_pose(id, Arc::new(p)).unwrap();
                }
            }
            Op::Unregister { mesh } => {
                if let Some(id) = self.meshes[mesh].take() {
                    self.m.unregister_mesh(id).unwrap();
                    self.dead.push(id);
                    self.instances.retain(|(_, m)| *m != mesh);
                }
            }
            Op::Frames { n } => {
                for _ in 0..n {
                    self.frame()?;
                }
            }
            Op::BadTransform { k, v } if !self.instances.is_empty() => {
                let (id, _) = self.instances[k % self.instances.len()];
                // Apply what is pending first, so the next frame sees only this call.
                self.frame()?;
                let before = self.m.stats().instances;
                let t = Affine3A::from_translation(Vec3::new(v, 0.0, 1.0));
                let r = self.m.set_transform(id, t);
                if v.is_finite() {
                    prop_assert!(r.is_ok(), "a huge finite transform is accepted: {:?}", r);
                } else {
                    prop_assert_eq!(r, Err(AsError::InvalidTransform));
                }
                self.frame()?;
                if !self.lost {
                    prop_assert_eq!(
                        self.m.stats().instances,
                        before,
                        "a rejected transform changes nothing"
                    );
                }
            }
            Op::DeadMesh { mesh } if !self.dead.is_empty() => {
                let id = self.dead[mesh % self.dead.len()];
                let r = self
                    .m
                    .add_instance(InstanceDesc::new(id, Affine3A::IDENTITY));
                prop_assert_eq!(r.err(), Some(AsError::UnknownMesh(id)));
            }
            Op::RepeatFrame if self.frame > 0 && !self.lost => {
                let before = self.m.stats().clone();
                let cams = [Camera::new(self.cam, Vec3::Z)];
                let r = self.m.update(FrameInput {
                    frame: self.frame - 1,
                    cameras: &cams,
                });
                prop_assert!(matches!(r, Err(AsError::InvalidConfig(_))));
                prop_assert_eq!(self.m.stats(), &before, "a refused frame changes nothing");
            }
            Op::SkipFrames { n } => {
                self.frame += n;
                self.frame()?;
            }
            Op::Fault { point, lost } if !self.lost && self.m.backend().faults.is_empty() => {
                let e = if lost {
                    backend::BackendError::DeviceLost
                } else {
                    backend::BackendError::Other("injected".into())
                };
                self.m.backend_mut().inject_fault(POINTS[point], e);
            }
            _ => {}
        }
        Ok(())
    }
}

proptest! {
    // 10,000 sequences in the suite (PROPTEST_CASES overrides it, e.g. for longer runs).
    #![proptest_config(ProptestConfig {
        cases: std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(10_000),
        ..ProptestConfig::default()
    })]

    #[test]
    fn invariants_hold_over_random_sequences(cfg in config(), ops in prop::collection::vec(op(), 1..60)) {
        let mut h = Harness::new(cfg);
        for o in ops {
            h.apply(o)?;
        }
        // A fault armed but never reached must not strike the drain.
        h.m.backend_mut().faults.clear();
        // drain: every registered thing can be unregistered and everything retires
        for i in 0..h.meshes.len() {
            h.apply(Op::Unregister { mesh: i })?;
        }
        h.apply(Op::Frames { n: 4 })?;
        if !h.lost {
            prop_assert_eq!(h.m.backend().live_blas_count(), 0);
            prop_assert_eq!(h.m.memory_in_use(), 0);
        }
        // A lost device: the manager drops cleanly (this scope's end).
    }

    /// A camera oscillating across r1 by less than (r2 - r1) / 2 builds once and never
    /// releases; with any r1/r2 and thresholds, create/destroy stays below one per
    /// `min_resident_frames`.
    #[test]
    fn no_thrashing_at_r1(r1 in 20f32..200.0, extra in 0f32..50.0, create in 0u32..4, release in 0u32..10, amp in 0.1f32..10.0) {
        let mut c = Config::default();
        c.residency.r1 = r1;
        c.residency.r2 = r1 + extra;
        c.residency.create_threshold = create;
        c.residency.release_threshold = release;
        c.cull.mode = CullMode::Off;
        let min_life = c.residency.min_resident_frames as u64;
        let mut m = AsManager::new(c, ModelBackend::lavapipe()).unwrap();
        let mesh = m.register_mesh(MeshDesc::new("rock", MeshKind::Static, 1.0, counts_chain(1000, 1, 0.0))).unwrap();
        m.add_instance(InstanceDesc::new(mesh, Affine3A::IDENTITY)).unwrap();
        let (mut builds, mut releases) = (0u64, 0u64);
        let frames = 240u64;
        for f in 0..frames {
            let d = 1.0 + r1 + if f % 2 == 0 { amp } else { -amp };
            let cams = [Camera::new(Vec3::new(d, 0.0, 0.0), -Vec3::X)];
            let s = m.update(FrameInput { frame: f, cameras: &cams }).unwrap().stats.clone();
            builds += s.builds as u64;
            releases += s.releases as u64;
        }
        if extra > 2.0 * amp {
            prop_assert!(builds <= 1 && releases == 0, "builds {builds} releases {releases}");
        }
        prop_assert!(builds + releases <= 2 * (frames / (min_life + 1) + 1), "builds {builds} releases {releases}");
    }
}

/// The fault path of the harness runs: a fault at each point fails one frame, which is rolled
/// back and retried; a lost device is reported by every later update.
#[test]
fn injected_faults_are_retried_and_a_lost_device_stays_lost() {
    let mut c = Config::default();
    c.residency.create_threshold = 0;
    c.build.min_compaction_saving = 0.0;
    let mut h = Harness::new(c);
    h.apply(Op::Add {
        mesh: 8,
        n: 3,
        x: 0.0,
        z: 5.0,
    })
    .unwrap();
    h.apply(Op::Add {
        mesh: 2,
        n: 20,
        x: 0.0,
        z: 10.0,
    })
    .unwrap();
    h.apply(Op::Frames { n: 3 }).unwrap();
    for (point, at) in POINTS.iter().enumerate() {
        h.apply(Op::Fault { point, lost: false }).unwrap();
        for k in 0..30 {
            // New instances (builds) and a new pose (refits) every frame.
            h.apply(Op::Add {
                mesh: k % 8,
                n: 1,
                x: (point * 30 + k) as f32,
                z: 8.0,
            })
            .unwrap();
            h.apply(Op::Deform { k }).unwrap();
            h.apply(Op::Frames { n: 1 }).unwrap();
            if h.m.backend().faults.is_empty() {
                break;
            }
        }
        assert!(h.m.backend().faults.is_empty(), "{at:?} never struck");
    }
    assert_eq!(h.retried as usize, POINTS.len());
    h.apply(Op::Fault {
        point: 3,
        lost: true,
    })
    .unwrap();
    h.apply(Op::Frames { n: 3 }).unwrap();
    assert!(h.lost);
}
