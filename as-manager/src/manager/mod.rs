//! `AsManager`: the engine-facing API and the frame loop.
//!
//! Why one file over 600 lines: the frame's phases already live in the submodules below; what stays
//! here is the public surface engines read together — the frame types (`FrameStats` alone is ~80
//! lines of documented fields) and `AsManager`'s methods, most of them thin forwards to the
//! registrar — plus `update`, which sequences the phases. Splitting the types from the loop that
//! defines them would not make either shorter to read.

mod apply;
mod baseline;
mod far;
mod journal;
mod landmarks;
mod managed;
mod memory;
mod registrar;
mod schedule;
mod split;
mod state;

use std::collections::VecDeque;

use glam::{Affine3A, Vec3};

pub use registrar::{GroupDesc, InstanceDesc, Registrar};
pub use split::{MemorySplit, SplitPart};
use state::{EntryKey, EntryState, Tables};

use crate::backend::model::CostModel;
use crate::backend::{AsBackend, CostOp, TlasHandle};
use crate::config::{Config, PolicyKind};
use crate::cull::InstanceCuller;
use crate::lod::LodSelector;
use crate::record::TlasInstance;
use crate::spatial::{GridIndex, GridLoc};
use crate::{AsError, InstanceId, Result};

/// Where the manager measures from: residency, LOD and culling use `position`; `forward` (unit)
/// only raises the build priority of what it looks at. One per camera; the renderer's pinhole
/// `Camera` carries more (up vector, field of view).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Viewpoint {
    /// World position.
    pub position: Vec3,
    /// View direction (unit length, or zero for "all around").
    pub forward: Vec3,
}

impl Viewpoint {
    /// A viewpoint at `position` looking along `forward`.
    pub fn new(position: Vec3, forward: Vec3) -> Self {
        Self { position, forward }
    }
}

/// One frame's input. Frame numbers must increase.
#[derive(Debug, Clone, Copy)]
pub struct FrameInput<'a> {
    /// Frame number (the backend's timeline value).
    pub frame: u64,
    /// Cameras (any number; all share the one TLAS).
    pub cameras: &'a [Viewpoint],
}

/// What one `update` did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameStats {
    /// Frame number.
    pub frame: u64,
    /// Registry commands applied.
    pub commands_applied: u32,
    /// Live instances.
    pub instances: u32,
    /// Registered meshes (far-field proxies included).
    pub meshes: u32,
    /// Instances examined this frame (near the cameras for `Managed`).
    pub instances_visited: u32,
    /// Instances in the TLAS.
    pub tlas_instances: u32,
    /// Instances with a built BLAS but culled.
    pub culled: u32,
    /// Built BLASes.
    pub blas_count: u32,
    /// Bytes of built BLASes.
    pub blas_bytes: u64,
    /// Bytes of freed BLASes the GPU may still use (counted against the budget).
    pub retiring_bytes: u64,
    /// The budget in force (after any OOM back-off).
    pub memory_budget: u64,
    /// BLASes created (built) this frame.
    pub builds: u32,
    /// Triangles built this frame.
    pub build_primitives: u64,
    /// Estimated GPU ms of this frame's builds.
    pub build_estimated_ms: f32,
    /// Estimated GPU ms of all of this frame's acceleration-structure work (builds, refits,
    /// compactions and the TLAS), what `BuildBudget::max_gpu_ms` bounds.
    pub as_estimated_ms: f32,
    /// An item larger than the whole build budget was admitted alone.
    pub oversized_admitted: bool,
    /// Items still waiting in the build queue.
    pub queued: u32,
    /// BLASes released (residency) this frame.
    pub releases: u32,
    /// BLASes evicted (memory) this frame.
    pub evictions: u32,
    /// LOD fallbacks (memory) this frame.
    pub lod_fallbacks: u32,
    /// Builds refused this frame for memory: the coarsest LOD did not fit and nothing less
    /// important was left to evict. Non-zero on every frame when the budget is below the
    /// smallest coarsest-LOD BLAS near the camera: nothing is shown there, nothing fails.
    pub memory_refused: u32,
    /// Unculled instances within r1 of a camera (managed policy).
    pub within_r1: u32,
    /// Of those, instances that show a coarser LOD than their target, or nothing, while
    /// their target builds (0: full coverage; see the teleport stability test).
    pub short_of_target: u32,
    /// Compactions recorded this frame.
    pub compactions: u32,
    /// Skinned refits this frame.
    pub refits: u32,
    /// Skinned rebuilds (refit quality degraded) this frame.
    pub rebuilds: u32,
    /// Triangles refitted or rebuilt this frame.
    pub refit_primitives: u64,
    /// Worst measured refit quality ratio among this frame's refits (1.0 = as built).
    pub worst_refit_quality: f32,
    /// OOM answers from the backend this frame.
    pub oom_events: u32,
    /// Far-field proxy records in the TLAS.
    pub proxy_instances: u32,
    /// Far-field landmark records in the TLAS (see `FarFieldConfig::keep_angle`).
    pub landmark_instances: u32,
    /// Records of near leaves' detail beyond r2 that the landmark set keeps
    /// (`FarFieldConfig::incremental_detail`).
    pub far_detail_instances: u32,
    /// Landmark candidates looked at this frame (the landmarks are kept incrementally: a
    /// candidate is looked at only when the cameras may have crossed one of its thresholds).
    pub landmarks_examined: u32,
    /// Landmark candidates due by camera travel whose distance was still inside the band of
    /// their last look: they only waited again, without a look.
    pub landmarks_waited: u32,
    /// Bytes of the proxies' BLASes in the TLAS.
    pub proxy_blas_bytes: u64,
    /// Proxy BLASes evicted (memory) this frame: near detail goes first, proxies last.
    pub proxies_evicted: u32,
    /// Leaf groups whose detail a proxy stands for this frame.
    pub far_groups_covered: u32,
    /// GPU ms measured by the backend and received this frame.
    pub measured_gpu_ms: f64,
    /// Of `measured_gpu_ms`, the TLAS builds and updates.
    pub measured_tlas_ms: f64,
    /// Image error of this frame against a reference frame, when the caller evaluated it (see
    /// [`AsManager::record_evaluation`]; the renderer's `FrameMetrics` converts into it).
    pub evaluation: Option<ImageError>,
}

/// Image error of a managed frame against its reference (every instance, finest LOD, no culling).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ImageError {
    /// Share of pixels whose primary-hit instance differs.
    pub primary_mismatch: f64,
    /// Share of pixels whose shadow bit differs.
    pub shadow_mismatch: f64,
    /// RMSE of the RGB channels in [0, 1].
    pub color_rmse: f64,
    /// PSNR in dB (infinite for identical colours).
    pub psnr_db: f64,
}

impl FrameStats {
    /// Bytes counted against the budget.
    pub fn memory_in_use(&self) -> u64 {
        self.blas_bytes + self.retiring_bytes
    }
}

/// The result of `update`.
#[derive(Debug, Clone, Copy)]
pub struct FrameOutput<'a> {
    /// The backend's TLAS for this frame.
    pub tlas: TlasHandle,
    /// The instance records it was built from.
    pub instances: &'a [TlasInstance],
    /// Statistics.
    pub stats: &'a FrameStats,
    /// Which of `instances` stand as they stood in the previous successful `update`'s
    /// records (see [`RecordChanges`]).
    pub changes: RecordChanges<'a>,
}

/// Which records of an `update` equal the records of the previous successful `update` at the
/// same index: every index below `stable` that `changed` does not list. The far field's
/// landmarks keep their records at the front of the list from frame to frame, so a reader
/// that keeps something per record (a renderer's shading table, a copy of the TLAS
/// records) can look at the listed records and those from `stable` on instead of every
/// record. Compare `since` with the frame of the records you saw last: on any other frame
/// (you skipped an update, or `since` is `None`), look at every record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RecordChanges<'a> {
    /// The frame of these records.
    pub frame: u64,
    /// The frame of the records they are compared with: the previous successful `update`
    /// (`None`: the first, or the first after a failed one, which dropped its records).
    pub since: Option<u64>,
    /// Records below this index are unchanged unless listed in `changed`.
    pub stable: usize,
    /// Indices below `stable` whose record changed, in increasing order, without repeats.
    pub changed: &'a [u32],
}

impl RecordChanges<'_> {
    /// Whether `changed` is as described (increasing, below `stable`); a reader given
    /// changes it did not get from the manager checks this first.
    pub fn is_well_formed(&self) -> bool {
        self.changed.windows(2).all(|w| w[0] < w[1])
            && self
                .changed
                .last()
                .is_none_or(|&i| (i as usize) < self.stable)
    }

    /// Whether `records` at `i` may differ from the records of frame `since`.
    pub fn may_differ(&self, i: usize) -> bool {
        i >= self.stable || self.changed.binary_search(&(i as u32)).is_ok()
    }
}

#[derive(Debug, Clone, Copy)]
pub(crate) struct Visit {
    pub loc: GridLoc,
    /// Distance from the nearest camera to the centre.
    pub center_dist: f32,
    /// Beyond r2, visited because its far-field group is near (angle culling only).
    pub beyond_r2: bool,
    /// Some LOD of its mesh has data or a BLAS (`MeshState::with_data`). One that has none is
    /// not ready: nothing shown, culled as if new, and it holds its leaf's proxy whatever its
    /// angle (the hand-over waits for it).
    pub ready: bool,
}

/// Whether the landmark set also keeps the near leaves' detail beyond r2
/// (`FarFieldConfig::incremental_detail`).
fn detail_kept(c: &Config) -> bool {
    let f = &c.far_field;
    c.policy == PolicyKind::Managed && f.enabled && f.incremental_detail
}

/// Radius from which an instance may be a far-field landmark (infinite: none).
fn landmark_radius(c: &Config) -> f32 {
    let f = &c.far_field;
    if c.policy == PolicyKind::Managed && f.enabled && f.keep_angle > 0.0 {
        c.residency.r2 * f.keep_angle.tan()
    } else {
        f32::INFINITY
    }
}

/// The BLAS/TLAS manager. See the crate docs for the frame pipeline.
///
/// ```
/// use std::sync::Arc;
/// use glam::{Affine3A, Vec3};
/// use rtstream_as_manager::*;
/// use rtstream_as_manager::backend::model::ModelBackend;
///
/// let mut m = AsManager::new(Config::default(), ModelBackend::lavapipe()).unwrap();
/// let mesh = m.register_mesh(MeshDesc::new("crate", MeshKind::Static, 1.0, vec![LodDesc {
///     geometry: LodGeometry::Counts { vertices: 24, triangles: 12 }, geometric_error: 0.0 }])).unwrap();
/// m.add_instance(InstanceDesc::new(mesh, Affine3A::from_translation(Vec3::new(0.0, 0.0, 20.0)))).unwrap();
/// let cam = [Viewpoint::new(Vec3::ZERO, Vec3::Z)];
/// let mut n = 0;
/// for frame in 0..4 {
///     n = m.update(FrameInput { frame, cameras: &cam }).unwrap().instances.len();
/// }
/// assert_eq!(n, 1);
/// ```
#[derive(Debug)]
pub struct AsManager<B: AsBackend> {
    config: Config,
    backend: B,
    registrar: Registrar,
    tables: Tables,
    grid: GridIndex<state::InstanceHot>,
    lod: LodSelector,
    culler: InstanceCuller,
    costs: CostModel,
    /// The online fits that refine `costs`.
    cost_fits: crate::backend::model::CostFits,
    /// The far-field group tree.
    far: far::FarField,
    /// The far-field landmarks, kept incrementally (their records lead `records`).
    landmarks: landmarks::Landmarks,
    /// Leaf group of each `tlas_list` entry, for the far field.
    tlas_groups: Vec<Option<u32>>,
    /// Entries of `tlas_list` whose leaf is on the far side of the hand-over (covered only
    /// through an ancestor's proxy): with none, and no near leaf handing over, nothing in the
    /// list can be covered and `far_select` leaves it as it is.
    tlas_far_leaf_entries: u32,
    /// Near far-field leaves reaching beyond r2 (XZ boxes), for the residency query.
    near_boxes: Vec<[f32; 4]>,
    /// The same leaves' slots, when the landmark set keeps their detail.
    near_leaves_beyond: Vec<u32>,
    /// GPU ms set aside this frame for the TLAS and refits (see `schedule_builds`).
    gpu_reserved_ms: f64,
    /// Last frame's TLAS instances and refitted triangles.
    prev_tlas_instances: u32,
    prev_refit_prims: u64,
    /// The GPU ms this frame's builds may take, and whether they run beside the TLAS
    /// (`reserve_gpu`).
    build_room_ms: f64,
    builds_beside: bool,
    /// The TLAS's share of `gpu_reserved_ms`.
    reserved_tlas_ms: f64,
    /// Estimated GPU ms of this frame's compactions.
    compaction_estimated_ms: f64,
    visits: Vec<Visit>,
    cam_pos: Vec<Vec3>,
    cam_fwd: Vec<Vec3>,
    tlas_list: Vec<(u32, u64)>,
    /// Per instance slot: its record with `blas_address` 0 (transform, customIndex, mask, SBT
    /// offset, flags), apart from the grid so that a grid entry is one cache line.
    templates: Vec<TlasInstance>,
    records: Vec<TlasInstance>,
    /// The last successful update's record changes (`RecordChanges`), sorted, and its frame
    /// and the frame before it (`None` after a failed update, which drops the records).
    output_changed: Vec<u32>,
    output_stable: usize,
    output_frame: Option<u64>,
    output_since: Option<u64>,
    /// Built static entries waiting for compaction (stale keys are skipped).
    compact_pending: Vec<EntryKey>,
    retiring: VecDeque<(u64, u64)>,
    retiring_bytes: u64,
    live_bytes: u64,
    built_count: u32,
    oom_cap: Option<u64>,
    oom_frame: u64,
    floors: Vec<u32>,
    live_instances: u32,
    /// Applied instances naming each group slot: an unregistered group's slot is recycled
    /// only once none does (they keep its index, and would join a new group there).
    group_members: Vec<u32>,
    /// Group slots to recycle at the end of `apply_commands`.
    dead_groups: Vec<u32>,
    live_meshes: u32,
    last_frame: Option<u64>,
    frame: u64,
    stats: FrameStats,
    /// The GPU timings the backend handed over this frame (see `gpu_measurements`).
    measured: Vec<crate::backend::Measurement>,
    /// What this frame changed that a failure must undo.
    journal: journal::FrameJournal,
}

impl<B: AsBackend> AsManager<B> {
    /// A manager with a validated `config` driving `backend`.
    pub fn new(config: Config, backend: B) -> Result<Self> {
        config.validate()?;
        let mut landmarks = landmarks::Landmarks::default();
        landmarks.set_min_radius(landmark_radius(&config));
        landmarks.set_detail(detail_kept(&config));
        Ok(Self {
            grid: GridIndex::new(config.residency.cell_size),
            landmarks,
            lod: LodSelector::new(&config.lod),
            culler: InstanceCuller::new(&config.cull),
            costs: config.cost_prior,
            cost_fits: Default::default(),
            far: far::FarField::default(),
            tlas_groups: Vec::new(),
            tlas_far_leaf_entries: 0,
            near_boxes: Vec::new(),
            near_leaves_beyond: Vec::new(),
            gpu_reserved_ms: 0.0,
            prev_tlas_instances: 0,
            prev_refit_prims: 0,
            build_room_ms: 0.0,
            builds_beside: false,
            reserved_tlas_ms: 0.0,
            compaction_estimated_ms: 0.0,
            config,
            backend,
            registrar: Registrar::default(),
            tables: Tables::default(),
            visits: Vec::new(),
            cam_pos: Vec::new(),
            cam_fwd: Vec::new(),
            tlas_list: Vec::new(),
            templates: Vec::new(),
            records: Vec::new(),
            output_changed: Vec::new(),
            output_stable: 0,
            output_frame: None,
            output_since: None,
            compact_pending: Vec::new(),
            retiring: VecDeque::new(),
            retiring_bytes: 0,
            live_bytes: 0,
            built_count: 0,
            oom_cap: None,
            oom_frame: 0,
            floors: Vec::new(),
            live_instances: 0,
            group_members: Vec::new(),
            dead_groups: Vec::new(),
            live_meshes: 0,
            last_frame: None,
            frame: 0,
            stats: FrameStats::default(),
            measured: Vec::new(),
            journal: journal::FrameJournal::default(),
        })
    }

    /// A thread-safe handle for registration from loader threads.
    pub fn registrar(&self) -> Registrar {
        self.registrar.clone()
    }

    /// See [`Registrar::register_mesh`].
    pub fn register_mesh(&self, desc: crate::MeshDesc) -> Result<crate::MeshId> {
        self.registrar.register_mesh(desc)
    }

    /// See [`Registrar::set_lod_geometry`].
    pub fn set_lod_geometry(
        &self,
        mesh: crate::MeshId,
        lod: usize,
        geometry: crate::LodGeometry,
    ) -> Result<()> {
        self.registrar.set_lod_geometry(mesh, lod, geometry)
    }

    /// See [`Registrar::set_lod`].
    pub fn set_lod(&self, mesh: crate::MeshId, lod: usize, desc: crate::LodDesc) -> Result<()> {
        self.registrar.set_lod(mesh, lod, desc)
    }

    /// Triangles and geometric error of each LOD of `mesh` as the policy uses them now (once
    /// the registration was applied by an `update`).
    pub fn mesh_lods(&self, mesh: crate::MeshId) -> Option<Vec<(u32, f32)>> {
        let m = self.tables.meshes.get(mesh.index as usize)?.as_ref()?;
        let n = m.nlods as usize;
        Some(
            m.lod_tris[..n]
                .iter()
                .copied()
                .zip(m.errors[..n].iter().copied())
                .collect(),
        )
    }

    /// See [`Registrar::unregister_mesh`].
    pub fn unregister_mesh(&self, id: crate::MeshId) -> Result<()> {
        self.registrar.unregister_mesh(id)
    }

    /// See [`Registrar::register_group`].
    pub fn register_group(&self, desc: GroupDesc) -> Result<crate::GroupId> {
        self.registrar.register_group(desc)
    }

    /// See [`Registrar::set_group_proxy`].
    pub fn set_group_proxy(
        &self,
        group: crate::GroupId,
        proxy: Option<(crate::MeshId, f32)>,
    ) -> Result<()> {
        self.registrar.set_group_proxy(group, proxy)
    }

    /// See [`Registrar::unregister_group`].
    pub fn unregister_group(&self, group: crate::GroupId) -> Result<()> {
        self.registrar.unregister_group(group)
    }

    /// See [`Registrar::add_instance`].
    pub fn add_instance(&self, desc: InstanceDesc) -> Result<InstanceId> {
        self.registrar.add_instance(desc)
    }

    /// See [`Registrar::set_transform`].
    pub fn set_transform(&self, id: InstanceId, transform: Affine3A) -> Result<()> {
        self.registrar.set_transform(id, transform)
    }

    /// See [`Registrar::remove_instance`].
    pub fn remove_instance(&self, id: InstanceId) -> Result<()> {
        self.registrar.remove_instance(id)
    }

    /// See [`Registrar::set_skinned_pose`].
    pub fn set_skinned_pose(
        &self,
        id: InstanceId,
        positions: std::sync::Arc<Vec<[f32; 3]>>,
    ) -> Result<()> {
        self.registrar.set_skinned_pose(id, positions)
    }

    /// See [`Registrar::set_skinned_pose_device`].
    pub fn set_skinned_pose_device(
        &self,
        id: InstanceId,
        positions: crate::mesh::DeviceVertices,
    ) -> Result<()> {
        self.registrar.set_skinned_pose_device(id, positions)
    }

    /// See [`Registrar::mark_deformed`].
    pub fn mark_deformed(&self, id: InstanceId) -> Result<()> {
        self.registrar.mark_deformed(id)
    }

    /// The configuration.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Replaces the configuration (validated); budgets apply from the next `update` (an
    /// over-budget state is evicted at once; freed bytes still in flight drain within the
    /// backend's frames in flight).
    pub fn set_config(&mut self, config: Config) -> Result<()> {
        config.validate()?;
        if config.policy != self.config.policy {
            return Err(AsError::InvalidConfig(
                "policy cannot change on a live manager".into(),
            ));
        }
        if config.residency.cell_size != self.config.residency.cell_size {
            let mut grid = GridIndex::new(config.residency.cell_size);
            for (slot, inst) in self.tables.instances.iter().enumerate() {
                if let (Some(inst), Some(grid_entry)) = (inst, self.grid.get(slot as u32)) {
                    grid.insert(slot as u32, inst.center, inst.radius, grid_entry.data);
                }
            }
            self.grid = grid;
        }
        // Whatever a landmark decision reads: every candidate is looked at again.
        let landmarks_read = |c: &Config| {
            (
                landmark_radius(c),
                c.residency.r2,
                c.far_field.far_radius,
                c.far_field.keep_range,
                c.lod.clone(),
                c.cull.clone(),
            )
        };
        let retrack = landmark_radius(&config) != self.landmarks.min_radius()
            || detail_kept(&config) != self.landmarks.detail();
        if retrack || landmarks_read(&config) != landmarks_read(&self.config) {
            self.records.clear();
            // The last output's records are gone: the next is compared with none.
            self.output_frame = None;
            self.landmarks.write_back_detail(&mut self.grid, self.frame);
            self.landmarks.invalidate();
        }
        self.lod = LodSelector::new(&config.lod);
        self.culler = InstanceCuller::new(&config.cull);
        self.config = config;
        if retrack {
            self.track_landmark_candidates();
        }
        Ok(())
    }

    /// The backend.
    pub fn backend(&self) -> &B {
        &self.backend
    }

    /// The backend, mutably (e.g. to inject failures in tests).
    pub fn backend_mut(&mut self) -> &mut B {
        &mut self.backend
    }

    /// The cost model as refined by measurements so far.
    pub fn cost_model(&self) -> &CostModel {
        &self.costs
    }

    /// Attaches the image error of the last frame (rendered and compared by the caller, since
    /// the manager renders nothing) to its [`FrameStats`].
    pub fn record_evaluation(&mut self, error: ImageError) {
        self.stats.evaluation = Some(error);
    }

    /// The last frame's statistics.
    pub fn stats(&self) -> &FrameStats {
        &self.stats
    }

    /// The GPU timings the backend reported during the last `update`, one per timed batch
    /// (builds, refits, each compaction, the TLAS). They belong to an earlier frame: the
    /// backend reads a frame's timestamps once that frame completed. `FrameStats`'s
    /// `measured_gpu_ms` is their sum.
    pub fn gpu_measurements(&self) -> &[crate::backend::Measurement] {
        &self.measured
    }

    /// The LOD an instance is targeting (skinned poses are for this LOD), once applied; `None`
    /// for an instance not applied yet, removed, or named by a stale id (its slot reused).
    pub fn instance_lod(&self, id: InstanceId) -> Option<usize> {
        self.tables
            .instances
            .get(id.index as usize)?
            .as_ref()
            .filter(|s| s.generation == id.generation)?;
        let hot = self.grid.get(id.index)?.data;
        Some(match hot.own.and_then(|k| self.tables.entries.get(k)) {
            Some(own) => own.lod as usize,
            None => hot.lod_target as usize,
        })
    }

    /// Checks internal consistency (for tests): byte accounting matches the built entries,
    /// every built entry has a handle, no two live entries hold the same static (mesh, LOD),
    /// every mesh's LOD table points at live entries of that mesh and LOD.
    // Hidden: a test fixture (tests outside the crate call it every frame), not product API.
    #[doc(hidden)]
    pub fn check_invariants(&self) -> std::result::Result<(), String> {
        self.landmarks.check(&self.records)?;
        let mut bytes = 0;
        let mut built = 0;
        let mut seen = std::collections::HashSet::new();
        if self.tables.active.len() != self.tables.entries.len() {
            return Err(format!(
                "{} active entries, {} live",
                self.tables.active.len(),
                self.tables.entries.len()
            ));
        }
        for (i, &key) in self.tables.active.iter().enumerate() {
            let Some(e) = self.tables.entries.get(key) else {
                return Err(format!("dropped entry {key:?} in the active list"));
            };
            if e.active_index as usize != i {
                return Err(format!(
                    "entry {key:?} is at {i} in the active list, not {}",
                    e.active_index
                ));
            }
            if e.state == EntryState::Built {
                if e.handle.is_none() {
                    return Err(format!("built entry {key:?} without a handle"));
                }
                bytes += e.bytes;
                built += 1;
            } else if e.handle.is_some() {
                return Err(format!("unbuilt entry {key:?} holds a handle"));
            }
            if e.owner.is_none() && !seen.insert((e.mesh, e.lod)) {
                return Err(format!(
                    "two live entries for static mesh {} LOD {}",
                    e.mesh, e.lod
                ));
            }
        }
        if bytes != self.live_bytes || built != self.built_count {
            return Err(format!(
                "accounting: {bytes} B / {built} built vs {} B / {}",
                self.live_bytes, self.built_count
            ));
        }
        for (i, m) in self.tables.meshes.iter().enumerate() {
            let Some(m) = m else { continue };
            for (lod, key) in m.lod_entry.iter().enumerate() {
                let Some(key) = *key else { continue };
                let ok = self.tables.entries.get(key).is_some_and(|e| {
                    e.mesh == i as u32 && e.lod as usize == lod && e.owner.is_none()
                });
                if !ok {
                    return Err(format!("mesh {i} LOD {lod} points at a wrong entry"));
                }
            }
        }
        Ok(())
    }

    /// Bytes counted against the memory budget now (built + retiring).
    pub fn memory_in_use(&self) -> u64 {
        self.live_bytes + self.retiring_bytes
    }

    pub(crate) fn budget(&self) -> u64 {
        let b = self.config.memory.blas_bytes;
        self.oom_cap.map_or(b, |c| c.min(b))
    }

    /// Runs one frame: applies queued registrations, then residency, LOD, scheduling, memory,
    /// culling and assembly, then records the backend work and the TLAS build.
    ///
    /// Frame numbers increase from call to call (gaps are fine) and stop at `u64::MAX - 1`;
    /// cameras must be finite. A refused frame changes nothing.
    pub fn update(&mut self, input: FrameInput<'_>) -> Result<FrameOutput<'_>> {
        let frame = input.frame;
        if let Some(last) = self.last_frame.filter(|&l| frame <= l) {
            return Err(AsError::FrameNotIncreasing { frame, last });
        }
        if frame == u64::MAX {
            return Err(AsError::FrameNumberTooLarge(frame));
        }
        if input
            .cameras
            .iter()
            .any(|c| !c.position.is_finite() || !c.forward.is_finite())
        {
            return Err(AsError::InvalidTransform);
        }
        let _span = tracing::debug_span!("update", frame).entered();
        self.frame = frame;
        // Last frame's TLAS and refit amounts predict this frame's (the GPU budget sets them
        // aside before admitting builds).
        self.prev_tlas_instances = self.stats.tlas_instances;
        self.prev_refit_prims = self.stats.refit_primitives;
        self.stats = FrameStats {
            frame,
            worst_refit_quality: 1.0,
            ..FrameStats::default()
        };
        self.compaction_estimated_ms = 0.0;
        self.gpu_reserved_ms = 0.0;
        self.reserved_tlas_ms = 0.0;
        self.builds_beside = false;
        self.backend.begin_frame(frame)?;
        self.journal.clear();
        let tlas = match self.frame_body(input) {
            Ok(tlas) => tlas,
            Err(e) => {
                tracing::warn!(frame, error = %e, "frame failed; rolled back");
                self.rollback_frame();
                // The records are gone: the next output is compared with none.
                self.output_frame = None;
                self.output_since = None;
                return Err(e);
            }
        };
        // Only a submitted frame counts: a failed frame's number may be retried.
        self.last_frame = Some(frame);
        self.output_since = self.output_frame;
        self.output_frame = Some(frame);
        self.commit_frame();
        self.stats.instances = self.live_instances;
        self.stats.meshes = self.live_meshes;
        // The real TLAS: a backend may add records (split meshes' parts).
        self.stats.tlas_instances =
            self.backend.tlas_records().unwrap_or(self.records.len()) as u32;
        let refit_ms = if self.stats.refits > 0 {
            self.costs
                .estimate_batch(CostOp::Refit, self.stats.refit_primitives)
        } else {
            0.0
        };
        let tlas_ms = self
            .costs
            .estimate_batch(CostOp::Tlas, self.records.len() as u64);
        let build_ms = self.stats.build_estimated_ms as f64;
        // Beside the TLAS, the frame's compactions run with its builds.
        let as_ms = schedule::tlas_with_work_ms(
            &self.costs,
            self.builds_beside,
            tlas_ms,
            build_ms + self.compaction_estimated_ms,
        );
        self.stats.as_estimated_ms = (as_ms + refit_ms) as f32;
        self.stats.blas_count = self.built_count;
        self.stats.blas_bytes = self.live_bytes;
        self.stats.retiring_bytes = self.retiring_bytes;
        self.stats.memory_budget = self.budget();
        Ok(FrameOutput {
            tlas,
            instances: &self.records,
            stats: &self.stats,
            changes: self
                .record_changes()
                .expect("a frame that succeeded has its output"),
        })
    }

    /// The records of the last successful `update` (its `FrameOutput::instances`; empty
    /// before the first and after a failed one).
    pub fn records(&self) -> &[TlasInstance] {
        if self.output_frame.is_some() {
            &self.records
        } else {
            &[]
        }
    }

    /// The last successful `update`'s [`RecordChanges`] (`None` before the first and after a
    /// failed one).
    pub fn record_changes(&self) -> Option<RecordChanges<'_>> {
        Some(RecordChanges {
            frame: self.output_frame?,
            since: self.output_since,
            stable: self.output_stable,
            changed: &self.output_changed,
        })
    }

    /// The frame between `begin_frame` and a successful `end_frame`. An error leaves the frame
    /// to `rollback_frame` (see `journal.rs`).
    fn frame_body(&mut self, input: FrameInput<'_>) -> Result<TlasHandle> {
        let frame = input.frame;
        self.drain_retiring();
        self.refine_costs();
        self.recover_oom_cap();
        {
            let _s = tracing::trace_span!("apply").entered();
            self.apply_commands();
        }
        self.cam_pos.clear();
        self.cam_fwd.clear();
        for c in input.cameras {
            self.cam_pos.push(c.position);
            self.cam_fwd.push(c.forward);
        }
        match self.config.policy {
            PolicyKind::Managed => self.managed_frame()?,
            PolicyKind::Naive => self.naive_frame()?,
            PolicyKind::SeedR1R2 => self.seed_frame()?,
        }
        let _s = tracing::trace_span!("record").entered();
        let delta = crate::backend::TlasDelta {
            stable: self.landmarks.len(),
            changed: &self.landmarks.changed,
        };
        let tlas = self.backend.build_tlas(&self.records, delta)?;
        // Kept for the frame's output (`RecordChanges`), sorted and without repeats.
        std::mem::swap(&mut self.output_changed, &mut self.landmarks.changed);
        self.landmarks.changed.clear();
        self.output_stable = self.landmarks.len();
        self.output_changed.sort_unstable();
        self.output_changed.dedup();
        let stable = self.output_stable as u32;
        let listed = self.output_changed.partition_point(|&i| i < stable);
        self.output_changed.truncate(listed);
        self.backend.end_frame(frame)?;
        Ok(tlas)
    }

    /// After an OOM the budget is capped; every 300 quiet frames the cap grows by a quarter of
    /// the way back to the configured budget (at least 10%), until it is back (the device may
    /// have freed memory elsewhere). Growing by 10% of the cap alone left a cap set low by a
    /// transient OOM far below the budget for thousands of frames (found by the OOM test).
    fn recover_oom_cap(&mut self) {
        if let Some(cap) = self.oom_cap {
            if self.frame.saturating_sub(self.oom_frame) >= 300 {
                self.oom_frame = self.frame;
                let budget = self.config.memory.blas_bytes;
                let grown = cap + (budget.saturating_sub(cap) / 4).max(cap / 10) + 1;
                self.oom_cap = (grown < self.config.memory.blas_bytes).then_some(grown);
            }
        }
    }

    fn drain_retiring(&mut self) {
        let done = self.backend.completed_frame();
        while let Some(&(last, bytes)) = self.retiring.front() {
            if done.is_some_and(|d| d >= last) {
                self.retiring.pop_front();
                self.retiring_bytes -= bytes;
            } else {
                break;
            }
        }
    }

    /// Measured GPU timings into the cost model: per kind of batch, an online fit of its
    /// fixed cost and its cost per unit (`OpFit`), unless the model is frozen.
    fn refine_costs(&mut self) {
        self.measured = self.backend.take_measurements();
        // Builds timed with the TLAS beside them (reported at 0 just before it).
        let mut beside_builds: Option<(CostOp, u64)> = None;
        for &m in &self.measured {
            self.stats.measured_gpu_ms += m.gpu_ms;
            let tlas = matches!(m.op, CostOp::Tlas | CostOp::TlasUpdate);
            if tlas {
                self.stats.measured_tlas_ms += m.gpu_ms;
            }
            if self.config.freeze_cost_model {
                continue;
            }
            if !m.beside {
                self.cost_fits
                    .learn(&mut self.costs, m.op, m.units, m.gpu_ms);
                continue;
            }
            if !tlas {
                // Compactions beside the TLAS are not learned (their copies hide under it);
                // builds may be (below).
                if m.op != CostOp::Compact {
                    beside_builds = Some((m.op, m.units));
                }
                continue;
            }
            // The pair's time is the longer of the TLAS and the builds plus `beside_tlas` of
            // the shorter: builds that clearly outlast the TLAS's estimate give their own
            // time; otherwise the pair says little about either (the TLAS is learned on
            // frames without builds).
            if let Some((op, units)) = beside_builds.take() {
                let t = self.costs.estimate_batch(m.op, m.units);
                let share = self.costs.beside_tlas.clamp(0.0, 1.0);
                if m.gpu_ms > t * (1.0 + share) * 1.25 {
                    let own = m.gpu_ms - share * t;
                    self.cost_fits.learn(&mut self.costs, op, units, own);
                }
            } else {
                // Only compactions beside it: a few copies of small BLASes, which add
                // `beside_tlas` of their time to the TLAS's. The pair is learned as the TLAS
                // (a slight overestimate), so that the TLAS is still learned on the frames
                // that compact (most frames that do not build).
                self.cost_fits
                    .learn(&mut self.costs, m.op, m.units, m.gpu_ms);
            }
        }
    }

    /// Indexes every live instance again as a landmark candidate (or not) under the
    /// configuration's radius: a pass over the instances, on configuration changes only.
    fn track_landmark_candidates(&mut self) {
        self.landmarks.clear();
        self.landmarks.set_min_radius(landmark_radius(&self.config));
        self.landmarks.set_detail(detail_kept(&self.config));
        if !self.landmarks.is_active() {
            return;
        }
        for (slot, inst) in self.tables.instances.iter().enumerate() {
            let Some(inst) = inst else { continue };
            let is_static = self
                .tables
                .meshes
                .get(inst.mesh as usize)
                .and_then(|m| m.as_ref())
                .is_some_and(|m| m.kind == crate::MeshKind::Static);
            let Some(hot) = self.grid.get(slot as u32).map(|g| g.data) else {
                continue;
            };
            let sphere = landmarks::CandSphere {
                center: inst.center,
                radius: inst.radius,
                mesh: inst.mesh,
                scale: hot.scale,
            };
            self.landmarks
                .track(slot as u32, sphere, is_static, hot.group);
        }
    }

    /// Frees a built entry's handle (retired after this frame) and drops the entry.
    pub(crate) fn release_entry(&mut self, key: EntryKey) {
        let frame = self.frame;
        self.tables.blas_changed(key, frame);
        let e = &mut self.tables.entries[key];
        if let Some(handle) = e.handle.take() {
            e.address = 0;
            self.backend.free_blas(handle, frame);
            self.live_bytes -= e.bytes;
            self.retiring.push_back((frame, e.bytes));
            self.retiring_bytes += e.bytes;
            self.built_count -= 1;
            tracing::trace!(entry = ?key, bytes = e.bytes, "blas released");
        }
        e.state = EntryState::Idle;
        e.bytes = 0;
        self.tables.drop_entry(key);
    }
}

#[cfg(test)]
mod detail_tests;
#[cfg(test)]
mod far_tests;
#[cfg(test)]
mod landmark_tests;
#[cfg(test)]
mod lod_geometry_tests;
#[cfg(test)]
mod tests;
