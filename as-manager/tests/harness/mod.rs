//! The state-machine harness of the property tests, generic over the backend: the model
//! backend in `as-manager/tests/properties.rs` (10,000 sequences), the Vulkan backend on
//! lavapipe with frames in flight and validation on in `tests/vulkan_properties.rs`.
#![allow(dead_code)]

use std::sync::Arc;

use super::rtm::backend::model::ModelBackend;
use super::rtm::backend::vulkan::VulkanBackend;
use super::rtm::backend::{self, AsBackend, BackendError, FaultPoint};
use super::rtm::synth::{counts_chain, grid_geometry};
use super::rtm::*;
use glam::{Affine3A, Vec3};
use proptest::prelude::*;

use super::rtm;

mod scene;
#[allow(unused_imports)]
pub use scene::{one_lod, one_lod_mesh, place, update_from};

/// What the harness asks a backend beyond [`AsBackend`].
pub trait Probe: AsBackend {
    /// Meshes with real geometry (the Vulkan backend builds what it is given) or counts only.
    const NEEDS_DATA: bool;
    /// BLASes freed or destroyed while a frame used them, as the backend saw it (the Vulkan
    /// backend leaves this to the synchronization validation layer: 0 here).
    fn lifetime_violations(&self) -> u64;
    /// Whether frame `frame`'s TLAS may name the BLAS at `address`: live, or freed after that
    /// frame's records (the managed frame's evictions and compactions) and kept until it
    /// completes.
    fn is_usable_address(&self, address: u64, frame: u64) -> bool;
    /// Bytes of BLAS storage not yet destroyed (retiring included).
    fn blas_allocated(&self) -> u64;
    /// Live BLASes.
    fn live_blases(&self) -> usize;
    /// Arms a fault.
    fn arm(&mut self, at: FaultPoint, error: BackendError);
    /// Whether an armed fault has not struck yet.
    fn armed(&self) -> bool;
    /// Disarms every fault.
    fn disarm(&mut self);
}

/// The [`Probe`] methods both backends answer with an inherent method of the same name and
/// meaning (a macro: the two backends are different types with no shared trait for these).
macro_rules! probe_by_same_name {
    () => {
        fn live_blases(&self) -> usize {
            self.live_blas_count()
        }
        fn arm(&mut self, at: FaultPoint, error: BackendError) {
            self.inject_fault(at, error);
        }
    };
}

impl Probe for ModelBackend {
    const NEEDS_DATA: bool = false;
    fn lifetime_violations(&self) -> u64 {
        self.counters().lifetime_violations
    }
    fn is_usable_address(&self, address: u64, _frame: u64) -> bool {
        // Kept until destroyed; a use after its last frame counts in `lifetime_violations`.
        ModelBackend::is_live_address(self, address)
    }
    fn blas_allocated(&self) -> u64 {
        self.allocated_bytes()
    }
    probe_by_same_name!();
    fn armed(&self) -> bool {
        !self.faults.is_empty()
    }
    fn disarm(&mut self) {
        self.faults.clear();
    }
}

impl Probe for VulkanBackend {
    const NEEDS_DATA: bool = true;
    fn lifetime_violations(&self) -> u64 {
        0
    }
    fn is_usable_address(&self, address: u64, frame: u64) -> bool {
        self.is_blas_address_usable(address, frame)
    }
    fn blas_allocated(&self) -> u64 {
        // AS storage only: the static BLASes' input buffers kept for shading lookups are
        // device memory outside the BLAS budget (the property test found that comparing
        // them against it fails; an engine shades from its own vertex buffers).
        self.blas_storage_bytes()
    }
    probe_by_same_name!();
    fn armed(&self) -> bool {
        self.pending_faults() > 0
    }
    fn disarm(&mut self) {
        self.clear_faults();
    }
}

#[derive(Debug, Clone)]
pub enum Op {
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
    /// The next allocation of a build, refit or compaction (`point` 0, 1, 2) runs out of
    /// device memory: the manager caps its budget, evicts, and retries later; the frame itself
    /// succeeds.
    Oom {
        point: usize,
    },
    /// The next backend call at `point` fails (device lost when `lost`).
    Fault {
        point: usize,
        lost: bool,
    },
}

pub const POINTS: [backend::FaultPoint; 5] = [
    backend::FaultPoint::BuildBlases,
    backend::FaultPoint::RefitBlases,
    backend::FaultPoint::CompactBlas,
    backend::FaultPoint::BuildTlas,
    backend::FaultPoint::EndFrame,
];

pub fn op() -> impl Strategy<Value = Op> {
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
        1 => (0..3usize).prop_map(|point| Op::Oom { point }),
    ]
}

pub fn config() -> impl Strategy<Value = Config> {
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
            let mut c = shrunk_config(r1, r1 + extra);
            c.residency.create_threshold = create;
            c.residency.release_threshold = release;
            c.residency.min_resident_frames = min_life;
            c.build.max_primitives = prims;
            c.memory.blas_bytes = bytes;
            c
        })
}

/// The configuration [`config`] draws from, at the values its cases shrink to: radii `r1` and
/// `r2`, thresholds and minimum residency 0, 32 m cells, 1,000 triangles and 5 ms of builds a
/// frame, a 500 KB BLAS budget (the regression tests found by the property tests).
pub fn shrunk_config(r1: f32, r2: f32) -> Config {
    let mut c = Config {
        residency: ResidencyConfig {
            r1,
            r2,
            create_threshold: 0,
            release_threshold: 0,
            min_resident_frames: 0,
            cell_size: 32.0,
        },
        ..Config::default()
    };
    c.build.max_primitives = 1000;
    c.build.max_gpu_ms = 5.0;
    c.memory.blas_bytes = 500_000;
    c
}

pub struct Harness<B: Probe> {
    pub m: AsManager<B>,
    pub meshes: Vec<Option<MeshId>>,
    /// Ids of unregistered meshes.
    pub dead: Vec<MeshId>,
    /// The device was lost: every later update must say so.
    pub lost: bool,
    /// Frames that failed by an injected fault and were retried.
    pub retried: u32,
    pub skinned: Vec<bool>,
    pub instances: Vec<(InstanceId, usize)>,
    pub cam: Vec3,
    pub frame: u64,
    /// Updates since the memory budget was last cut.
    pub budget_cut_at: Option<u32>,
    /// Injected out-of-memory faults, and the frames that reported one (`oom_events`).
    pub ooms_armed: u32,
    pub ooms_seen: u64,
    /// BLAS builds and TLAS instances over all successful frames.
    pub builds: u64,
    pub tlas_instances: u64,
}

impl<B: Probe> Harness<B> {
    pub fn new(config: Config, backend: B) -> Self {
        let m = AsManager::new(config, backend).unwrap();
        let mut meshes = Vec::new();
        let mut skinned = Vec::new();
        for i in 0..10 {
            let desc = if i >= 8 {
                MeshDesc::new(
                    format!("skinned{i}"),
                    MeshKind::Skinned,
                    1.5,
                    one_lod(grid_geometry(8, 2.0)),
                )
            } else {
                MeshDesc::new(
                    format!("m{i}"),
                    MeshKind::Static,
                    0.5 + i as f32,
                    chain(500 << (i % 6), 4, 0.01, B::NEEDS_DATA),
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
            builds: 0,
            tlas_instances: 0,
            ooms_armed: 0,
            ooms_seen: 0,
        }
    }

    pub fn frame(&mut self) -> Result<(), TestCaseError> {
        let cams = [Viewpoint::new(self.cam, Vec3::Z)];
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
        let run = |m: &mut AsManager<B>| {
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
        self.builds += s.builds as u64;
        self.ooms_seen += u64::from(s.oom_events);
        self.tlas_instances += s.tlas_instances as u64;
        self.m.check_invariants().map_err(TestCaseError::fail)?;
        prop_assert_eq!(
            self.m.backend().lifetime_violations(),
            0,
            "frame {}: a BLAS freed or destroyed while a frame used it",
            f
        );
        // TLAS references only live, built BLASes.
        for a in addrs {
            prop_assert!(
                self.m.backend().is_usable_address(a, f),
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
            prop_assert!(self.m.backend().blas_allocated() <= cfg.memory.blas_bytes);
        }
        prop_assert!(s.blas_bytes <= cfg.memory.blas_bytes || !settled);
        Ok(())
    }

    /// The end of a sequence: disarms every fault, unregisters every mesh and runs four
    /// frames; unless the device was lost, no BLAS and no byte of BLAS memory is left.
    pub fn drain(&mut self) -> Result<(), TestCaseError> {
        self.m.backend_mut().disarm();
        for i in 0..self.meshes.len() {
            self.apply(Op::Unregister { mesh: i })?;
        }
        self.apply(Op::Frames { n: 4 })?;
        if !self.lost {
            prop_assert_eq!(self.m.backend().live_blases(), 0);
            prop_assert_eq!(self.m.memory_in_use(), 0);
        }
        Ok(())
    }

    pub fn apply(&mut self, op: Op) -> Result<(), TestCaseError> {
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
                let cams = [Viewpoint::new(self.cam, Vec3::Z)];
                let r = self.m.update(FrameInput {
                    frame: self.frame - 1,
                    cameras: &cams,
                });
                let refused = self.frame - 1;
                let refused_as_such = matches!(
                    r,
                    Err(AsError::FrameNotIncreasing { frame, last }) if frame == refused && last >= refused
                );
                prop_assert!(
                    refused_as_such,
                    "frame {} not refused as not increasing",
                    refused
                );
                prop_assert_eq!(self.m.stats(), &before, "a refused frame changes nothing");
            }
            Op::SkipFrames { n } => {
                self.frame += n;
                self.frame()?;
            }
            Op::Oom { point } if !self.lost && !self.m.backend().armed() => {
                self.m
                    .backend_mut()
                    .arm(POINTS[point], backend::BackendError::OutOfDeviceMemory);
                self.ooms_armed += 1;
            }
            Op::Fault { point, lost } if !self.lost && !self.m.backend().armed() => {
                let e = if lost {
                    backend::BackendError::DeviceLost
                } else {
                    backend::BackendError::Other("injected".into())
                };
                self.m.backend_mut().arm(POINTS[point], e);
            }
            _ => {}
        }
        Ok(())
    }
}

/// A LOD chain of about `tris0` triangles halving per LOD: counts only, or grids of real
/// geometry when the backend builds what it is given.
pub fn chain(tris0: u32, lods: usize, err1: f32, data: bool) -> Vec<LodDesc> {
    let mut c = counts_chain(tris0, lods, err1);
    if data {
        for l in &mut c {
            let n = ((l.geometry.triangles() / 2) as f32).sqrt().max(2.0) as u32;
            l.geometry = LodGeometry::Data(grid_geometry(n, 2.0));
        }
    }
    c
}
