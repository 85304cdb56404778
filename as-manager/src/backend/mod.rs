//! Backends: where BLAS/TLAS are really built.
//!
//! The manager decides *what* to build, refit, compact and free; an [`AsBackend`] does it. The
//! trait is narrow on purpose: a Vulkan backend (`vulkan`, feature `vulkan`) records it into
//! command buffers, the [`model::ModelBackend`] only accounts sizes and costs.
//!
//! # Contract, in frame order
//! One frame is `begin_frame(n)`, then any of `blas_sizes`, `build_blases`, `refit_blases`,
//! `compacted_size`/`compact_blas`, `free_blas`, then `build_tlas` (once), then `end_frame(n)`.
//! The manager makes one batched `build_blases` and one `refit_blases` call a frame, refits
//! first. An engine driving a backend directly gets [`BackendError::Misuse`] for a call out of
//! this order (a frame number that does not increase, `begin_frame` while a frame records,
//! `end_frame` of another frame, a second `build_tlas`, a refit after it), for a handle that is
//! not live, one BLAS twice in a refit call, a second compaction of one original or one of a
//! BLAS made this frame, and unusable geometry (checked before anything is allocated); the
//! Vulkan backend also refuses, in debug builds, a TLAS record naming no live BLAS. A refit of
//! a BLAS built this frame runs after its build; a free waits for the frame whose commands
//! last used the BLAS, whatever frame it names.
//! - Sizes: [`AsBackend::blas_sizes`] answers like `vkGetAccelerationStructureBuildSizesKHR`
//!   for a geometry and class before anything is allocated; the manager budgets with it.
//! - Builds/refits recorded in frame `n` are visible to frame `n`'s TLAS (the backend puts the
//!   barrier between them). A BLAS handle may go into frame `n`'s instance records as soon as
//!   `build_blases` returned it.
//! - [`AsBackend::free_blas`] says "no TLAS after `last_used_frame` references it"; the backend
//!   destroys it once the GPU finished that frame (timeline value). The manager keeps counting
//!   its bytes until [`AsBackend::completed_frame`] passes `last_used_frame`.
//! - Compaction: after a static build, [`AsBackend::compacted_size`] returns `Some` once the
//!   size query is readable (frames later on a GPU). [`AsBackend::compact_blas`] allocates the
//!   compacted copy and records the copy; the manager then frees the original with `free_blas`.
//!   Both copies count against the memory budget until the original is retired.
//! - Measured GPU costs arrive late (timestamps of finished frames) through
//!   [`AsBackend::take_measurements`]; the manager refines its cost model with them.
//! - [`AsBackend::next_tlas`], asked after `begin_frame(n)` and before the frame's builds are
//!   chosen, says how frame `n`'s TLAS will be made (built, or updated in place); the manager
//!   sets aside that cost in its GPU budget. A backend that says `Update` may still build
//!   (more records than its last build holds), but one that says `Rebuild` builds.
//! - Oversized meshes: a backend that splits a geometry (primitive count, scratch size or a
//!   configured cap) still answers with one [`BlasSizes`] (summed) and one [`BlasHandle`];
//!   if the parts are separate BLASes it expands each record that carries that handle's
//!   address into one record per part in [`AsBackend::build_tlas`].
//! - Errors: [`BackendError::OutOfDeviceMemory`] fails the whole call and leaves nothing
//!   allocated; the manager evicts, shrinks its effective budget and retries on a later frame.
//!   [`BackendError::DeviceLost`] is returned to the caller of `update`.

use crate::record::TlasInstance;

mod calibration;
pub mod model;

#[cfg(feature = "vulkan")]
pub mod vulkan;

/// A backend's BLAS (opaque; the Vulkan backend maps it to its slot of `vk::AccelerationStructureKHR`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BlasHandle(pub u64);

/// The frame's TLAS as the backend built it: the backend's slot and the frame it was built
/// for. A handle kept past its frame's reuse of the slot resolves to nothing, never to a newer
/// TLAS (`VulkanBackend::tlas` checks the frame).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct TlasHandle {
    slot: u32,
    frame: u64,
}

impl TlasHandle {
    /// The handle of slot `slot`'s TLAS built for `frame`.
    pub fn new(slot: u32, frame: u64) -> Self {
        Self { slot, frame }
    }

    /// The backend's slot.
    pub fn slot(self) -> u32 {
        self.slot
    }

    /// The frame the TLAS was built for.
    pub fn frame(self) -> u64 {
        self.frame
    }
}

/// Build flags per class.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BlasClass {
    /// PREFER_FAST_TRACE | ALLOW_COMPACTION.
    Static,
    /// PREFER_FAST_BUILD | ALLOW_UPDATE.
    Skinned,
}

/// One triangle geometry to size or build. Positions come from `positions` (CPU, copied by the
/// backend) or `device_vertices` (the engine's GPU buffer, read in place), indices from
/// `indices` or `device_indices`; all are `None` when the mesh was registered with counts only
/// (enough for the model backend; a Vulkan backend returns [`BackendError::MissingGeometry`]).
#[derive(Debug, Clone, Copy)]
pub struct GeometryRef<'a> {
    /// Vertex count (= `positions.len()` when present).
    pub vertex_count: u32,
    /// Triangle count (= `indices.len() / 3` when present).
    pub triangle_count: u32,
    /// `[f32; 3]` positions (R32G32B32_SFLOAT, stride 12).
    pub positions: Option<&'a [[f32; 3]]>,
    /// `u32` triangle-list indices.
    pub indices: Option<&'a [u32]>,
    /// Positions in the engine's GPU buffer ([`crate::LodGeometry::Device`] or a pose from
    /// `set_skinned_pose_device`); `positions` is `None` when set.
    pub device_vertices: Option<crate::mesh::DeviceVertices>,
    /// Indices in the engine's GPU buffer ([`crate::LodGeometry::Device`]); `indices` is `None`
    /// when set.
    pub device_indices: Option<crate::mesh::DeviceIndices>,
    /// Sets VK_GEOMETRY_OPAQUE_BIT_KHR.
    pub opaque: bool,
}

/// What `vkGetAccelerationStructureBuildSizesKHR` reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BlasSizes {
    /// accelerationStructureSize.
    pub as_bytes: u64,
    /// buildScratchSize.
    pub build_scratch: u64,
    /// updateScratchSize (0 for a class without ALLOW_UPDATE).
    pub update_scratch: u64,
}

/// One BLAS to build in this frame's batch.
#[derive(Debug, Clone, Copy)]
pub struct BlasBuild<'a> {
    /// The geometry.
    pub geometry: GeometryRef<'a>,
    /// Flags.
    pub class: BlasClass,
    /// Sizes from [`AsBackend::blas_sizes`] for the same geometry and class.
    pub sizes: BlasSizes,
}

/// Refit (UPDATE mode, src = dst) or rebuild in place of a skinned BLAS.
#[derive(Debug, Clone, Copy)]
pub struct BlasRefit<'a> {
    /// The skinned BLAS.
    pub blas: BlasHandle,
    /// Its topology with this frame's positions (`None` with counts-only meshes).
    pub geometry: GeometryRef<'a>,
    /// `true`: full rebuild into the same storage (refits degraded it); `false`: update.
    pub rebuild: bool,
}

/// Kind of a measured GPU operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CostOp {
    /// Static BLAS build.
    BuildStatic,
    /// Skinned BLAS build or rebuild.
    BuildSkinned,
    /// Skinned refit.
    Refit,
    /// Compaction copy (`units` = source bytes).
    Compact,
    /// TLAS build (`units` = instances).
    Tlas,
    /// TLAS update in place from the previous frame's (`units` = instances).
    TlasUpdate,
}

/// A GPU timing the backend measured (timestamps), for a batch of `units` (triangles, bytes or
/// instances, see [`CostOp`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// What was timed.
    pub op: CostOp,
    /// Triangles, bytes or instances in the timed batch.
    pub units: u64,
    /// BLASes (builds, refits, compactions) or TLAS records in the timed batch.
    pub items: u32,
    /// Measured GPU milliseconds.
    pub gpu_ms: f64,
    /// Timed together with the frame's BLAS builds, which ran beside it (a TLAS that names
    /// none of them, no barrier between; a timestamp between them would serialize them): the
    /// TLAS's `gpu_ms` covers both, and the builds, reported just before it, are 0. The
    /// frame's measurements still add up to its acceleration-structure time; the cost model
    /// learns the TLAS from frames without builds, and builds from such a pair only when
    /// they clearly outlast the TLAS.
    pub beside: bool,
}

/// Backend failures the manager reacts to.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum BackendError {
    /// VK_ERROR_OUT_OF_DEVICE_MEMORY (or host memory) on an allocation; nothing was allocated.
    #[error("out of device memory")]
    OutOfDeviceMemory,
    /// VK_ERROR_DEVICE_LOST: fatal for this backend.
    #[error("device lost")]
    DeviceLost,
    /// A real build needs vertex/index data but the mesh was registered with counts only.
    #[error("geometry data missing (mesh registered with counts only)")]
    MissingGeometry,
    /// The engine records the frames (`VulkanBackend` in engine-recorded mode) and frame
    /// `frame` needs the slot of frame `waiting_for`, which the engine has not reported done
    /// (`frame_done`): more frames in flight than the backend was created with. Nothing was
    /// recorded; report the frame done and call again.
    #[error("frame {frame} needs frame {waiting_for} to be done (report it with frame_done)")]
    FrameInFlight {
        /// The frame the call was for.
        frame: u64,
        /// The earlier frame that holds the slot, not yet reported done.
        waiting_for: u64,
    },
    /// Engine-recorded mode: frame `frame` was ended but never handed to the engine's command
    /// buffer (`VulkanBackend::record`); a later frame would depend on builds that never ran.
    #[error("frame {frame} was not recorded into the engine's command buffer (call record)")]
    FrameNotRecorded {
        /// The frame that was ended but not recorded.
        frame: u64,
    },
    /// The Vulkan backend's own error, kept typed (any `VulkanError` other than out of memory
    /// or device lost, which have their variants above): match on `.0.error()`.
    #[cfg(feature = "vulkan")]
    #[error(transparent)]
    Vulkan(VulkanFailure),
    /// The caller broke the backend's contract (a call out of the frame's order, a handle or
    /// address that is not live, unusable geometry): nothing of the call was recorded or
    /// allocated, and the frame can go on (or be aborted). The manager never makes these; an
    /// engine driving the backend directly may.
    #[error(transparent)]
    Misuse(#[from] Misuse),
    /// Anything else, with the backend's words.
    #[error("{0}")]
    Other(String),
}

/// The frame order a backend's calls must follow (the module docs): both backends refuse
/// what breaks it with the same [`Misuse`].
#[derive(Debug, Default, Clone)]
pub(crate) struct FrameOrder {
    /// The frame being recorded.
    recording: Option<u64>,
    /// The last frame ended: frame numbers increase (an aborted frame's may be begun again).
    last_ended: Option<u64>,
    /// The frame being recorded has its TLAS (one a frame; refits go before it).
    tlas_built: bool,
}

impl FrameOrder {
    /// Whether frame `frame` may begin.
    pub(crate) fn may_begin(&self, frame: u64) -> Result<(), Misuse> {
        if let Some(f) = self.recording {
            return Err(Misuse::StillRecording { frame: f });
        }
        if frame == u64::MAX {
            return Err(Misuse::FrameNumberTooLarge(frame));
        }
        match self.last_ended.filter(|&l| frame <= l) {
            Some(last) => Err(Misuse::FrameNotIncreasing { frame, last }),
            None => Ok(()),
        }
    }

    /// Frame `frame` began.
    pub(crate) fn begun(&mut self, frame: u64) {
        self.recording = Some(frame);
        self.tlas_built = false;
    }

    /// The frame being recorded.
    pub(crate) fn recording(&self) -> Result<u64, Misuse> {
        self.recording.ok_or(Misuse::NotRecording)
    }

    /// Whether the frame's TLAS may be built now.
    pub(crate) fn may_build_tlas(&self) -> Result<(), Misuse> {
        self.recording()?;
        if self.tlas_built {
            return Err(Misuse::TlasAlreadyBuilt);
        }
        Ok(())
    }

    /// The frame's TLAS was recorded.
    pub(crate) fn tlas_built(&mut self) {
        self.tlas_built = true;
    }

    /// Whether refits may be recorded now.
    pub(crate) fn may_refit(&self) -> Result<(), Misuse> {
        self.recording()?;
        if self.tlas_built {
            return Err(Misuse::RefitAfterTlas);
        }
        Ok(())
    }

    /// Whether `end_frame(frame)` ends the frame being recorded.
    pub(crate) fn may_end(&self, frame: u64) -> Result<(), Misuse> {
        let recording = self.recording()?;
        if frame != recording {
            return Err(Misuse::WrongFrame { frame, recording });
        }
        Ok(())
    }

    /// Frame `frame` ended (submitted).
    pub(crate) fn ended(&mut self, frame: u64) {
        self.recording = None;
        self.tlas_built = false;
        self.last_ended = Some(frame);
    }

    /// The frame being recorded was dropped (failed, aborted): its number may begin again.
    pub(crate) fn aborted(&mut self) {
        self.recording = None;
        self.tlas_built = false;
    }
}

/// What a [`BackendError::Misuse`] refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum Misuse {
    /// A call that records work outside `begin_frame` .. `end_frame`.
    #[error("no frame is being recorded (call begin_frame)")]
    NotRecording,
    /// `begin_frame` while frame `frame` is still being recorded.
    #[error("frame {frame} is still being recorded (end or abort it first)")]
    StillRecording {
        /// The frame being recorded.
        frame: u64,
    },
    /// `begin_frame(frame)` after frame `last` was ended: frame numbers increase (a frame
    /// that failed and was aborted may be begun again with its number).
    #[error("frame {frame} after frame {last}: frame numbers increase")]
    FrameNotIncreasing {
        /// The frame asked for.
        frame: u64,
        /// The last frame ended.
        last: u64,
    },
    /// `begin_frame(u64::MAX)`: the largest frame number is `u64::MAX - 1` (a timeline
    /// semaphore signals `frame + 1`).
    #[error("frame {0}: the largest frame number is u64::MAX - 1")]
    FrameNumberTooLarge(u64),
    /// `end_frame(frame)` while another frame is being recorded.
    #[error("end_frame({frame}) while frame {recording} is being recorded")]
    WrongFrame {
        /// The frame named.
        frame: u64,
        /// The frame being recorded.
        recording: u64,
    },
    /// A second `build_tlas` in one frame.
    #[error("the frame's TLAS is already built (one build_tlas a frame)")]
    TlasAlreadyBuilt,
    /// A refit after the frame's `build_tlas`: the TLAS was built over the old bounds.
    #[error("refits go before the frame's TLAS")]
    RefitAfterTlas,
    /// A handle that names no live BLAS of this backend (freed, or another backend's).
    #[error("{0:?} is not a live BLAS of this backend")]
    UnknownBlas(BlasHandle),
    /// One BLAS twice in one `refit_blases` call.
    #[error("{0:?} is refitted twice in one call")]
    DuplicateRefit(BlasHandle),
    /// A refit of a static BLAS (only skinned BLASes are built for updates).
    #[error("{0:?} is static: only skinned BLASes are refitted")]
    NotSkinned(BlasHandle),
    /// A refit with another vertex or triangle count than the build.
    #[error("refit of {0:?} with another vertex or triangle count than its build")]
    TopologyChanged(BlasHandle),
    /// A refit in another vertex format or opacity than the BLAS's build (a rebuild in place)
    /// whose new inputs need more storage than the BLAS has: free it and build it anew.
    #[error(
        "refit of {blas:?} in other inputs needs {needs} bytes of storage, more than its {has}"
    )]
    RefitOutgrowsStorage {
        /// The BLAS.
        blas: BlasHandle,
        /// The storage the new inputs need (the driver's size).
        needs: u64,
        /// The storage the BLAS has.
        has: u64,
    },
    /// A compaction before the BLAS's compacted size was read (frames after its build).
    #[error("{0:?}'s compacted size is not known yet")]
    CompactedSizeUnknown(BlasHandle),
    /// A second compaction of one original (free it once its copy is made).
    #[error("{0:?} was compacted already")]
    AlreadyCompacted(BlasHandle),
    /// A compaction of a BLAS whose own build or copy is recorded in this frame.
    #[error("{0:?} is made in this frame: compact it in a later one")]
    CompactionOfPending(BlasHandle),
    /// A TLAS record naming an address that is no live BLAS (checked in debug builds).
    #[error("TLAS record {index} names {address:#x}, which is no live BLAS")]
    UnknownBlasAddress {
        /// The record's index in the call.
        index: usize,
        /// The address it names.
        address: u64,
    },
    /// Geometry a build cannot use (no triangles, counts beyond the slices, an index past
    /// the vertices).
    #[error("unusable geometry: {0}")]
    InvalidGeometry(&'static str),
    /// The engine's device geometry is unusable (a null or misaligned address, a stride
    /// shorter than a position).
    #[error("unusable device geometry: {0}")]
    DeviceGeometry(crate::mesh::DeviceGeometryError),
}

/// A [`vulkan::VulkanError`] inside a [`BackendError`], shared so that the error stays `Clone`.
/// Two are equal when they are the same failure (the same allocation), not merely alike.
#[cfg(feature = "vulkan")]
#[derive(Debug, Clone)]
pub struct VulkanFailure(pub std::sync::Arc<vulkan::VulkanError>);

#[cfg(feature = "vulkan")]
impl VulkanFailure {
    /// The Vulkan error.
    pub fn error(&self) -> &vulkan::VulkanError {
        &self.0
    }
}

#[cfg(feature = "vulkan")]
impl PartialEq for VulkanFailure {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.0, &other.0)
    }
}

#[cfg(feature = "vulkan")]
impl Eq for VulkanFailure {}

#[cfg(feature = "vulkan")]
impl std::fmt::Display for VulkanFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

#[cfg(feature = "vulkan")]
impl std::error::Error for VulkanFailure {
    // Transparent: the Vulkan error's own text and source.
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        std::error::Error::source(&*self.0)
    }
}

/// Where a fault injected into a backend (tests of the error paths:
/// `VulkanBackend::inject_fault`, [`model::ModelBackend::inject_fault`]) strikes: at the start
/// of that call, which then does nothing else.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultPoint {
    /// `build_blases`.
    BuildBlases,
    /// `refit_blases`.
    RefitBlases,
    /// `compact_blas`.
    CompactBlas,
    /// `build_tlas` (after the frame's builds were recorded).
    BuildTlas,
    /// `end_frame` (before the submission).
    EndFrame,
}

/// `Result` for backend calls.
pub type BackendResult<T> = std::result::Result<T, BackendError>;

/// Which of a TLAS's records equal the previous `build_tlas` call's record at the same index:
/// every index below `stable` that `changed` does not list. The manager keeps the far field's
/// landmarks at the front of its records and lists what joined, left or changed, so a backend
/// can write the records that changed instead of all of them. [`TlasDelta::ALL`] promises
/// nothing (everything may have changed).
#[derive(Debug, Clone, Copy, Default)]
pub struct TlasDelta<'a> {
    /// Records below this index are unchanged unless listed in `changed`.
    pub stable: usize,
    /// Indices below `stable` whose record changed (any order; repeats and indices at or past
    /// `stable` are allowed and mean nothing more).
    pub changed: &'a [u32],
}

impl TlasDelta<'_> {
    /// Nothing is known to be unchanged.
    pub const ALL: TlasDelta<'static> = TlasDelta {
        stable: 0,
        changed: &[],
    };
}

/// How a backend will make the next frame's TLAS, as far as it knows before the frame's builds
/// ([`AsBackend::next_tlas`]): the manager's GPU budget sets aside what that costs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum NextTlas {
    /// Every frame builds its TLAS (updates in place off).
    #[default]
    BuildEveryFrame,
    /// An update in place of the last frame's TLAS (unless the frame's records outgrow it).
    Update,
    /// A build after updates: the tree is due to be rebuilt. A backend that updates in place
    /// rebuilds in a frame that builds few BLAS triangles, so the manager admits builds in
    /// such a frame only within its budget (no build is forced through for progress: the
    /// frames that follow update).
    Rebuild,
}

/// What the manager needs from a GPU (or a model of one). See the module docs for the frame
/// contract. Only the thread that owns the manager calls it.
pub trait AsBackend: Send {
    /// Starts frame `frame` (waits for the frame-in-flight slot it reuses; retires what the
    /// GPU has finished with).
    fn begin_frame(&mut self, frame: u64) -> BackendResult<()>;
    /// The newest frame whose GPU work has completed, if any.
    fn completed_frame(&self) -> Option<u64>;
    /// Whether builds and refits need vertex/index data (`true` for a real GPU). When it does,
    /// the manager only targets LODs whose geometry is registered as [`crate::LodGeometry::Data`]
    /// or [`crate::LodGeometry::Device`] (see `Registrar::set_lod_geometry`), falling back to
    /// the nearest LOD that has data.
    fn needs_geometry(&self) -> bool {
        true
    }
    /// Sizes of a BLAS for this geometry and class, before building.
    fn blas_sizes(&self, geometry: &GeometryRef<'_>, class: BlasClass) -> BlasSizes;
    /// Records one batched build of `builds`; returns their handles in order. All or nothing.
    /// The frame's TLAS may name them (the builds then finish before it); when it names none
    /// (the managed policy builds after its records), a backend may run them beside the TLAS
    /// (the Vulkan backend does: no barrier between them; `CostModel::beside_tlas`).
    fn build_blases(&mut self, builds: &[BlasBuild<'_>]) -> BackendResult<Vec<BlasHandle>>;
    /// Records one batch of skinned refits/rebuilds (in place).
    fn refit_blases(&mut self, refits: &[BlasRefit<'_>]) -> BackendResult<()>;
    /// The compacted size of a static BLAS once its post-build query is readable.
    fn compacted_size(&mut self, blas: BlasHandle) -> Option<u64>;
    /// Allocates the compacted copy of `blas` and records the copy; returns the new handle.
    /// The caller frees the original with [`AsBackend::free_blas`].
    fn compact_blas(&mut self, blas: BlasHandle) -> BackendResult<BlasHandle>;
    /// No TLAS after `last_used_frame` references `blas`: destroy it once the GPU is done.
    /// The Vulkan backend also waits for the last frame whose own commands used it (its
    /// build, a refit, a compaction from it), so the original of a copy recorded this frame
    /// may be freed at once.
    fn free_blas(&mut self, blas: BlasHandle, last_used_frame: u64);
    /// The BLAS device address for `accelerationStructureReference`.
    fn blas_address(&self, blas: BlasHandle) -> u64;
    /// Records the frame's TLAS build from its 64-byte instance records. `delta` says which
    /// records equal the previous call's (a backend may write only the others; see
    /// [`TlasDelta`]).
    fn build_tlas(
        &mut self,
        instances: &[TlasInstance],
        delta: TlasDelta<'_>,
    ) -> BackendResult<TlasHandle>;
    /// How the next frame's TLAS will be made (see [`NextTlas`]); asked before the frame's
    /// builds are chosen.
    fn next_tlas(&self) -> NextTlas {
        NextTlas::BuildEveryFrame
    }
    /// Records in the last TLAS built, where the backend adds its own (a mesh split into
    /// parts has one record per part); `None`: exactly the instances given.
    fn tlas_records(&self) -> Option<usize> {
        None
    }
    /// Submits frame `frame`.
    fn end_frame(&mut self, frame: u64) -> BackendResult<()>;
    /// Discards the frame being recorded after a failure: nothing recorded since
    /// `begin_frame` is ever submitted, its queries are forgotten, and the next `begin_frame`
    /// (the same frame number included) starts clean. Objects created in it stay until freed.
    fn abort_frame(&mut self) {}
    /// GPU timings measured since the last call (from completed frames).
    fn take_measurements(&mut self) -> Vec<Measurement>;
    /// Refit-quality ratios of skinned BLASes posed on the GPU (`device_vertices` in a
    /// [`BlasRefit`]), measured on the GPU since the last call, oldest first: the metric of
    /// `crate::quality` after a refit over the same metric after the BLAS's last build
    /// (1.0 = as good as built). They arrive frames late (read once the frame completed); a
    /// ratio measured before the BLAS's latest rebuild is never reported. Backends without
    /// such a pass report nothing.
    fn take_refit_quality(&mut self) -> Vec<(BlasHandle, f32)> {
        Vec::new()
    }
}
