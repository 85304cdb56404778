//! [`VulkanBackend`]: the manager's [`AsBackend`] on a real Vulkan device.
//!
//! Why one file over 600 lines: the backend's state (slots, entries, retirement), its creation
//! and drop, and the `AsBackend` trait impl (thin forwards to `frame.rs`, `registry.rs`,
//! `builds.rs`, `tlas.rs`) stay together; every phase's body lives in those files
//! (`tlas_slots.rs`: which instance slot holds each record when the TLAS is updated).
//!
//! - **Frames in flight.** `frames_in_flight` slots (default 2), each with its own command
//!   buffer, TLAS, instance buffer, scratch buffer and query pools, so frame `n+1`
//!   records and builds while frame `n`'s TLAS is traced. One timeline semaphore: frame `n`
//!   signals `n + 1`; `begin_frame(n)` waits for frame `n - frames_in_flight` before reusing
//!   its slot.
//! - **Batched builds.** A frame's BLAS builds go into one vkCmdBuildAccelerationStructuresKHR;
//!   scratch is sub-allocated from the slot's scratch buffer at multiples of
//!   `minAccelerationStructureScratchOffsetAlignment`. Every BLAS's storage is a range of one
//!   device-local `BufferArena` (16 MB blocks) and every static BLAS's uploaded inputs a range
//!   of a host-visible one, so creating or freeing a BLAS makes or destroys no buffer and no
//!   allocation (those were most of `build_blases`'s host time); the rest (TLAS, slots' buffers,
//!   skinned inputs) are gpu-allocator allocations.
//! - **Build inputs.** A static BLAS keeps the vertex and index buffers it was built from (the
//!   engine-side geometry a shader reads through [`VulkanBackend::shading_geometry`]). A skinned
//!   BLAS keeps its index buffer, which updates reuse, and a ring of `frames_in_flight + 1`
//!   pose buffers: each build or refit writes the next one, so the shading reads the last pose
//!   for as long as no refit replaces it, and no buffer is written while a frame may read it.
//! - **The engine's own buffers** (`LodGeometry::Device`, `set_skinned_pose_device`): builds,
//!   sizes and refits read the device addresses directly, in the engine's position format
//!   (f32x3, f16x4, snorm16x4), stride and index type (u16, u32), with nothing uploaded or kept
//!   (`VulkanCounters::{input_upload_bytes, pose_upload_bytes}` count what CPU slices cost).
//!   Each frame starts with a barrier making earlier compute and transfer writes on the queue
//!   (the engine's skinning) visible to build input reads, and ends with one ordering its
//!   reads before the engine's next writes. A skinned BLAS posed on the GPU is judged by a
//!   compute pass after its build and each refit (`gpu_quality.rs`), read back with the
//!   frame's queries.
//! - **Retirement.** A freed BLAS (and every buffer a slot outgrew) is queued against the last
//!   frame that used it and destroyed once the timeline passes that frame.
//! - **Compaction.** Static BLASes get a compacted-size query after their build; the size is
//!   read when the frame completes; `compact_blas` allocates the copy and records it.
//! - **Oversized meshes** (more primitives than the device allows, or storage/scratch over
//!   `max_part_bytes`, default 256 MiB — the limit a mobile GPU in the seeds had) are split into
//!   parts, each its own BLAS; `build_tlas` expands an instance of the first part into one record
//!   per part, so the manager sees one BLAS. Primitive ids of a hit are then part-relative.
//! - **Measured costs.** GPU timestamps around each batch, read back when the frame completes,
//!   reported through `take_measurements`.
//! - **Memory limit.** `memory_limit` (optional) makes the backend answer OutOfDeviceMemory above
//!   that many bytes of BLAS storage and BLAS inputs (frame infrastructure is not capped), exactly as the driver's error would arrive: a way to
//!   test the manager's OOM handling on machines with plenty of memory.

mod builds;
mod frame;
mod gpu_quality;
pub(crate) mod measure;
mod registry;
mod tlas;
mod tlas_slots;

pub use tlas::TlasUpdates;
use tlas::{Parking, TlasSource};

use std::collections::VecDeque;

use rustc_hash::FxHashMap;

use crate::backend::FaultPoint;
use std::sync::Arc;

use ash::vk;

use crate::backend::vulkan::device::accel::{
    align_up, AccelStruct, AsSizes, BlasBuildInput, ScratchLayout, TriangleGeometry,
    ACCEL_STORAGE_USAGE, BUILD_INPUT_USAGE,
};
use crate::backend::vulkan::device::arena::{ArenaRange, BufferArena};
use crate::backend::vulkan::device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::device::frames::FrameCmd;
use crate::backend::vulkan::device::query::{QueryKind, QueryPool};
use crate::backend::vulkan::device::tlas_ref::TlasRef;
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};
use crate::backend::{
    AsBackend, BackendError, BackendResult, BlasBuild, BlasClass, BlasHandle, BlasRefit, BlasSizes,
    CostOp, FrameOrder, GeometryRef, Measurement, Misuse, TlasDelta, TlasHandle,
};
use crate::record::TlasInstance;

/// Creation parameters of a [`VulkanBackend`].
#[derive(Debug, Clone)]
pub struct VulkanBackendDesc {
    /// Who records and submits (default: the backend submits itself).
    pub recording: Recording,
    /// Frames in flight (>= 1; default 2).
    pub frames_in_flight: u32,
    /// For an engine that traces on another queue (no barrier orders its traces against our
    /// writes): each refit of a skinned BLAS writes one of `frames_in_flight` structures that
    /// no frame in flight traces, instead of updating it in place. Costs `frames_in_flight`
    /// times the skinned BLAS memory, which [`AsBackend::blas_sizes`] reports so that the
    /// manager's budget counts it. The TLAS is already one per frame in flight. Off by default.
    pub separate_refit_targets: bool,
    /// TLAS build flags (default PREFER_FAST_BUILD: on the H200 inside the manager's frames it
    /// builds the default fly-through's TLAS in 0.22 ms against 0.26 with PREFER_FAST_TRACE,
    /// 0.36 against 0.46 at ten times the density, and the 1080p trace costs the same; see
    /// docs/GPU.md). With [`TlasUpdates::enabled`], ALLOW_UPDATE is added.
    pub tlas_flags: vk::BuildAccelerationStructureFlagsKHR,
    /// The build preference of static BLASes (default PREFER_FAST_BUILD; ALLOW_COMPACTION is
    /// always added). On the H200 inside the default fly-through, PREFER_FAST_BUILD takes a
    /// frame's build batch from about 0.19 to 0.13 ms of fixed cost, the GPU AS p99 from 0.58
    /// to 0.46 ms and the compacted BLAS memory from 32.2 to 24.0 MB, and the 1080p trace
    /// costs the same (7.88 against 7.89–7.91 ms; docs/GPU.md). That part has no RT cores:
    /// on RTX cards and consoles PREFER_FAST_TRACE may trace faster, so measure there.
    pub static_blas_prefer: vk::BuildAccelerationStructureFlagsKHR,
    /// When the per-frame TLAS is updated in place from the last frame's instead of rebuilt.
    pub tlas_updates: TlasUpdates,
    /// Split a mesh whose BLAS storage or scratch would exceed this many bytes (default 256 MiB).
    pub max_part_bytes: u64,
    /// Refuse allocations past this many bytes with OutOfDeviceMemory (None: only the driver's
    /// own limit applies).
    pub memory_limit: Option<u64>,
    /// Deterministic retirement: frame N counts frames up to N - `frames_in_flight` as
    /// completed (the ones it waited for) and never polls the timeline for more, so what is
    /// freed when, and the bytes counted as retiring, do not depend on GPU speed. Off by
    /// default (frees as soon as the GPU is done).
    pub deterministic: bool,
}

/// Who records and submits a frame's work.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Recording {
    /// The backend submits each frame itself, signalling its own timeline (frame `n` signals
    /// `n + 1`) and waits on it before reusing a frame's slot. For simple users and the examples.
    #[default]
    OwnSubmit,
    /// The engine's frame: the backend records each frame into a secondary command buffer that
    /// the engine executes in its own (`VulkanBackend::record`), submits nothing, and learns that a
    /// frame finished from `VulkanBackend::frame_done`. Recording is the same as in own-submit
    /// mode; only who submits and who says "done" differ.
    Engine,
}

impl VulkanBackendDesc {
    /// The engine records and submits (see [`Recording::Engine`]) with `frames_in_flight`
    /// frames in flight: frame `n` reuses what frame `n - frames_in_flight` used, so that frame
    /// must be reported done first.
    pub fn engine_recorded(frames_in_flight: u32) -> Self {
        Self {
            frames_in_flight,
            recording: Recording::Engine,
            ..Self::default()
        }
    }
}

impl Default for VulkanBackendDesc {
    fn default() -> Self {
        Self {
            recording: Recording::OwnSubmit,
            frames_in_flight: 2,
            separate_refit_targets: false,
            tlas_flags: vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
            tlas_updates: TlasUpdates::default(),
            static_blas_prefer: vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
            max_part_bytes: 256 << 20,
            memory_limit: None,
            deterministic: false,
        }
    }
}

/// Timestamp queries per frame slot: a pair per timed batch, the last pair kept for the TLAS
/// (so that the frame's GPU time always includes it).
const QUERIES_PER_SLOT: u32 = 64;
/// Bytes per block of the static input arena (the default world keeps about 20 MB of inputs).
const INPUT_BLOCK_BYTES: u64 = 8 << 20;
/// Bytes per block of the BLAS storage arena (the default world keeps 30 to 40 MB of BLASes,
/// most of them tens of kilobytes).
const ACCEL_BLOCK_BYTES: u64 = 16 << 20;
const COMPACT_QUERIES_PER_SLOT: u32 = 4096;

slotmap::new_key_type! {
    /// A BLAS's key in the registry; a [`BlasHandle`] is its FFI form (`KeyData::as_ffi`), so
    /// a handle of a freed BLAS is stale (slotmap's version), never a newer BLAS.
    struct BlasKey;
}

/// The registry key of a handle.
fn key_of(h: BlasHandle) -> BlasKey {
    BlasKey::from(slotmap::KeyData::from_ffi(h.0))
}

#[derive(Debug)]
struct BlasEntry {
    parts: Vec<AccelStruct>,
    class: BlasClass,
    sizes: BlasSizes,
    /// Skinned: the index buffer that updates reuse, the poses the shading reads.
    skinned: Option<SkinnedInputs>,
    /// Static: the buffer of positions and indices it was built from (kept for shading
    /// lookups).
    static_inputs: Option<StaticInputs>,
    /// Skinned with `separate_refit_targets`: the other structures of the ring (the current
    /// one is `parts[0]`); a refit writes the oldest and makes it current.
    spares: Vec<AccelStruct>,
    /// Device addresses of the positions and indices a shader should read for this BLAS
    /// (skinned: the last pose written to its ring, or the engine's pose buffer).
    shading: (u64, u64),
    /// Whether `shading` is `[f32; 3]` positions 12 bytes apart and `u32` indices, what
    /// [`VulkanBackend::shading_geometry`] promises (not so for the engine's other formats).
    shading_plain: bool,
    compacted_size: Option<u64>,
    /// Copied by a compaction (its inputs went with the copy): it is not compacted again.
    compacted: bool,
    /// The last frame whose commands wrote or read it (its build, a refit, a compaction from
    /// it): a free waits for that frame, whatever frame the caller says last used it.
    recorded: u64,
    /// Skinned BLAS built or refitted from the engine's GPU buffer: the GPU quality pass's
    /// bookkeeping (`gpu_quality.rs`).
    gpu_quality: Option<gpu_quality::GpuQuality>,
}

/// A static BLAS's uploaded inputs: one range of the input arena (`VulkanBackend::inputs`), its
/// `[f32; 3]` positions first and its `u32` indices after them.
#[derive(Debug)]
pub(super) struct StaticInputs {
    range: ArenaRange,
    /// Bytes of positions at the range's start; the indices start at the next multiple of 16.
    positions_bytes: u64,
}

impl StaticInputs {
    /// Offset of the indices in the range.
    fn index_offset(positions_bytes: u64) -> u64 {
        positions_bytes.next_multiple_of(16)
    }
}

/// A skinned BLAS's own inputs. The positions of each build or refit go to the next buffer of
/// a ring of `frames_in_flight + 1`, owned by the BLAS (not the frame's upload arena): the
/// shading keeps reading the last pose for as long as no refit replaces it, and a buffer is
/// written again only after every frame that could read it has completed.
#[derive(Debug)]
struct SkinnedInputs {
    /// The uploaded `u32` indices (`None`: the engine's device indices).
    indices: Option<GpuBuffer>,
    /// Address and type of the indices that builds and refits read.
    index_address: u64,
    index_type: crate::mesh::IndexType,
    /// Position format of the last build (an update must use the same; another one rebuilds).
    vertex_format: crate::mesh::VertexFormat,
    /// The geometry's opaque flag at the last build (an update must keep it; another one
    /// rebuilds).
    opaque: bool,
    triangles: u32,
    vertices: u32,
    poses: Vec<GpuBuffer>,
    /// Ring position of the next write.
    next: usize,
}

impl BlasEntry {
    /// Everything the entry owns on the device: its structures (parts and refit spares) and
    /// its input buffers, to retire or destroy.
    fn into_owned(self) -> impl Iterator<Item = Retired> {
        let accels = self.parts.into_iter().chain(self.spares);
        let skinned = self.skinned.into_iter().flat_map(SkinnedInputs::buffers);
        let statics = self
            .static_inputs
            .into_iter()
            .map(|s| Retired::BlasInput(s.range));
        accels
            .map(Retired::BlasAccel)
            .chain(skinned.map(Retired::BlasBuffer))
            .chain(statics)
    }
}

impl SkinnedInputs {
    fn buffers(self) -> impl Iterator<Item = GpuBuffer> {
        self.indices.into_iter().chain(self.poses)
    }
}

#[derive(Debug)]
enum Retired {
    /// Frame infrastructure (TLAS).
    Accel(AccelStruct),
    /// Frame infrastructure (scratch, instance buffers).
    Buffer(GpuBuffer),
    /// A BLAS (counted against `memory_limit`).
    BlasAccel(AccelStruct),
    /// A BLAS input buffer (counted against `memory_limit`).
    BlasBuffer(GpuBuffer),
    /// A static BLAS's inputs in the input arena (counted against `memory_limit`).
    BlasInput(ArenaRange),
}

#[derive(Debug)]
struct Slot {
    /// Primary (own-submit) or secondary (engine-recorded) command buffer.
    cmd: vk::CommandBuffer,
    recording: bool,
    /// Engine-recorded: the engine executed this slot's commands in its own command buffer
    /// (`record`); a slot it never executed has no query results to read.
    executed: bool,
    /// Timeline value this slot's last submit signals (0: never submitted).
    submitted_value: u64,
    frame: u64,
    tlas: Option<AccelStruct>,
    tlas_capacity: u32,
    /// The build sizes of `tlas_capacity` instances with these flags: enough for any count up
    /// to it (what vkGetAccelerationStructureBuildSizesKHR promises for a maximum count), so a
    /// frame's TLAS needs no size query of its own.
    tlas_sizes: Option<(vk::BuildAccelerationStructureFlagsKHR, AsSizes)>,
    /// Instances this slot's TLAS was last built or updated with (its records and the parked
    /// ones after them).
    tlas_count: u32,
    /// The range of `instances` that holds parked records (see `TlasUpdates`).
    parked: (u32, u32),
    instances: Option<GpuBuffer>,
    /// The `build_tlas` call (`VulkanBackend::tlas_calls`) whose records `instances` holds
    /// record for record (0: unknown, or expanded with split parts).
    instances_call: u64,
    /// TLAS records of this slot's frame.
    records: u32,
    /// Primitive bases of this frame's TLAS records (see `primitive_bases`).
    bases: Option<GpuBuffer>,
    bases_address: u64,
    scratch: Option<(GpuBuffer, vk::DeviceAddress, u64)>,
    /// This frame's scratch ranges in `scratch` (the same layout as every BLAS planner's).
    scratch_used: ScratchLayout,
    timestamps: QueryPool,
    /// Timestamp pairs recorded this frame.
    timed: Vec<Timed>,
    compact_pool: QueryPool,
    /// (handle, query index) of compacted-size queries recorded this frame.
    compact_queries: Vec<(BlasHandle, u32)>,
    /// The frame's query results, copied on the GPU at the end of the frame (timestamps first,
    /// then compacted sizes at `QUERIES_PER_SLOT`), read by the host once it completed.
    results: GpuBuffer,
    /// GPU refit-quality partials of this frame (created at the first use), read by the host
    /// once it completed.
    quality: Option<GpuBuffer>,
    /// The quality dispatches recorded this frame.
    quality_jobs: Vec<gpu_quality::QualityJob>,
}

/// A timestamp pair of a frame: what it timed (op, units, items), its first query, and the BLAS
/// builds (op, triangles, BLASes) that ran beside it inside the same pair (a timestamp between
/// them would make the GPU finish one before starting the other: `Measurement::beside`).
#[derive(Debug, Clone, Copy)]
struct Timed {
    op: CostOp,
    units: u64,
    items: u32,
    first: u32,
    beside: Option<(CostOp, u64, u32)>,
}

/// The frame's BLAS builds, planned by `build_blases` and recorded with the TLAS
/// (`builds.rs`, `record_pending_builds`): beside it when no record names them.
#[derive(Debug, Default)]
struct PendingBuilds {
    /// (geometry, flags, destination, scratch address) per BLAS part.
    inputs: Vec<(
        TriangleGeometry,
        vk::BuildAccelerationStructureFlagsKHR,
        vk::AccelerationStructureKHR,
        vk::DeviceAddress,
    )>,
    /// Every part's device address, sorted: a TLAS record naming one waits for the builds.
    addresses: Vec<u64>,
    /// The timestamp's op, triangles and BLASes.
    op: Option<CostOp>,
    triangles: u64,
    blases: u32,
    /// Static single-part BLASes whose compacted size is queried after the builds.
    queries: Vec<(BlasHandle, vk::AccelerationStructureKHR)>,
    /// Compactions (source, destination, the source's bytes), recorded after the builds: beside
    /// the TLAS with them, or before it (timed each) when a record names a pending BLAS.
    compactions: Vec<(
        vk::AccelerationStructureKHR,
        vk::AccelerationStructureKHR,
        u64,
    )>,
}

impl PendingBuilds {
    /// Whether builds or compactions wait to be recorded.
    fn has_work(&self) -> bool {
        self.op.is_some() || !self.compactions.is_empty()
    }
}

/// Counters of what the backend did (for tests and stats).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct VulkanCounters {
    /// BLASes built (split parts count once).
    pub built: u64,
    /// Skinned updates recorded.
    pub refits: u64,
    /// Skinned rebuilds recorded.
    pub rebuilds: u64,
    /// Compaction copies recorded.
    pub compactions: u64,
    /// BLASes destroyed after retirement.
    pub destroyed: u64,
    /// Meshes split into several parts.
    pub split_meshes: u64,
    /// Calls answered with OutOfDeviceMemory.
    pub oom: u64,
    /// Bytes of skinned positions copied from the CPU into pose buffers (builds and refits
    /// with CPU poses; 0 for poses in the engine's GPU buffers).
    pub pose_upload_bytes: u64,
    /// Bytes of static positions and of indices copied from the CPU into input buffers (0 for
    /// device geometry).
    pub input_upload_bytes: u64,
    /// BLASes built from the engine's device addresses (static or skinned).
    pub device_geometry_builds: u64,
    /// Refit-quality ratios measured on the GPU and reported to the manager.
    pub gpu_quality_reports: u64,
    /// TLAS instance records written into the frames' instance buffers (a record unchanged
    /// since the buffer's last use is not written again; see `TlasDelta`).
    pub tlas_records_written: u64,
    /// TLAS instance records built from (split parts included).
    pub tlas_records_built: u64,
    /// TLASes built (`VK_BUILD_ACCELERATION_STRUCTURE_MODE_BUILD_KHR`).
    pub tlas_builds: u64,
    /// TLASes updated from the previous frame's (see [`TlasUpdates`]).
    pub tlas_updates: u64,
    /// With [`TlasUpdates`] on: records that took an instance slot another record held (joined
    /// the TLAS); every other record kept its slot from the frame before.
    pub tlas_slots_joined: u64,
    /// Of them, those that found no parked slot in or next to their 64 m cell (see
    /// `TlasUpdates::max_misplaced`).
    pub tlas_slots_misplaced: u64,
    /// Frames whose BLAS builds ran beside their TLAS (no record named them, so no barrier
    /// between them).
    pub builds_beside_tlas: u64,
    /// Frames whose TLAS named a BLAS built in the same frame: the builds ran first, then a
    /// barrier, then the TLAS.
    pub builds_before_tlas: u64,
    /// Compactions recorded beside the frame's TLAS (untimed, inside its timestamp pair).
    pub compactions_beside_tlas: u64,
}

/// The manager's backend on a Vulkan device. Only the thread that owns the manager uses it.
#[derive(Debug)]
pub struct VulkanBackend {
    ctx: Arc<VulkanContext>,
    desc: VulkanBackendDesc,
    pool: vk::CommandPool,
    timeline: vk::Semaphore,
    slots: Vec<Slot>,
    current: usize,
    blases: slotmap::SlotMap<BlasKey, BlasEntry>,
    /// First-part address -> other parts' addresses, for split meshes.
    /// (the parts' addresses and first primitives).
    split_parts: FxHashMap<u64, Vec<(u64, u32)>>,
    /// First-part address -> blas slot (shading lookups by instance record).
    by_address: FxHashMap<u64, BlasKey>,
    /// Freed BLASes that a frame in flight may still name (the managed frame frees after its
    /// records: an eviction for a build, a compaction's source): first-part address -> (last
    /// frame that may use it, its shading buffers), until that frame completes.
    retired_shading: FxHashMap<u64, (u64, (u64, u64))>,
    retiring: VecDeque<(u64, Retired)>,
    /// The last frame that may have named a BLAS destroyed so far: a TLAS of this frame or an
    /// earlier one may name freed memory, so its handle no longer resolves and its refs are
    /// stale (`VulkanBackend::tlas`).
    freed_through: Option<u64>,
    completed: Option<u64>,
    measurements: Vec<Measurement>,
    /// The most recent measurements (kept after `take_measurements`), newest last.
    log: VecDeque<Measurement>,
    allocated: u64,
    blas_allocated: u64,
    lost: bool,
    counters: VulkanCounters,
    expanded: Vec<TlasInstance>,
    bases: Vec<u32>,
    /// `build_tlas` calls so far, and the last calls' deltas (call, stable, changed), oldest
    /// first: what a slot's instance buffer lacks since the call it was last written at.
    tlas_calls: u64,
    tlas_history: VecDeque<(u64, usize, Vec<u32>)>,
    /// Records of the last TLAS built (split parts included).
    tlas_len: usize,
    /// The TLAS the next frame may update from (see `TlasUpdates`): none after an aborted
    /// frame or before the first build.
    tlas_source: Option<TlasSource>,
    /// The one-triangle BLAS that parked TLAS records reference (created at the first build
    /// that parks records).
    parking: Option<Parking>,
    /// With `TlasUpdates` on: which instance slot holds each record (see `tlas_slots.rs`).
    slot_keeper: tlas_slots::SlotKeeper,
    /// Triangles of the BLAS builds recorded in the current frame.
    frame_build_triangles: u64,
    /// The current frame's builds, recorded with its TLAS (or at its end).
    pending: PendingBuilds,
    /// This frame's compactions (source, copy): the copy holds the source's input buffer
    /// (the shading reads it); a frame that fails gives it back to the source, which stays.
    frame_copies: Vec<(BlasHandle, BlasHandle)>,
    /// The frame order the calls follow (what `Misuse` refuses).
    order: FrameOrder,
    /// Engine-recorded: the last frame handed to the engine (`record`); `frame_done` can
    /// report no later one.
    recorded_up_to: Option<u64>,
    /// Faults armed by `inject_fault`, each striking once.
    faults: Vec<(FaultPoint, BackendError)>,
    /// Engine-recorded: the latest frame the engine reported done.
    engine_done: Option<u64>,
    /// Sizes by (triangles, vertices, opaque, class): they depend on nothing else, and the
    /// manager asks for every queued item every frame (one driver call each, before).
    size_cache: std::cell::RefCell<FxHashMap<SizeKey, BlasSizes>>,
    /// Static BLASes' uploaded positions and indices, as ranges of a few large host-visible
    /// buffers (`device/arena.rs`).
    inputs: BufferArena,
    /// Every BLAS's storage (built, compacted, refit targets), as ranges of a few large
    /// device-local buffers: creating a BLAS allocates no buffer or memory of its own.
    accels: BufferArena,
    /// Engine-recorded: the slot ended last and not yet handed to the engine's command buffer.
    to_record: Option<usize>,
    /// The GPU refit-quality pass, created at its first use.
    quality_pipeline: Option<gpu_quality::QualityPipeline>,
    /// GPU quality ratios read from completed frames, not yet taken by the manager.
    quality_reports: Vec<(BlasHandle, f32)>,
}

/// What a BLAS's sizes depend on: triangles, vertices, opaque, class, position format, index
/// type.
type SizeKey = (u32, u32, bool, BlasClass, vk::Format, vk::IndexType);

/// The position format and index type a geometry is built with (CPU slices: f32x3, u32).
fn input_formats(g: &GeometryRef<'_>) -> (vk::Format, vk::IndexType) {
    (
        g.device_vertices.map_or(vk::Format::R32G32B32_SFLOAT, |v| {
            gpu_quality::vk_format(v.format)
        }),
        g.device_indices.map_or(vk::IndexType::UINT32, |i| {
            gpu_quality::vk_index(i.index_type)
        }),
    )
}

fn backend_err(e: VulkanError) -> BackendError {
    match e {
        VulkanError::OutOfDeviceMemory { .. } => BackendError::OutOfDeviceMemory,
        VulkanError::DeviceLost { .. } => BackendError::DeviceLost,
        other => BackendError::Vulkan(crate::backend::VulkanFailure(Arc::new(other))),
    }
}

impl VulkanBackend {
    /// Creates the backend on `ctx`.
    pub fn new(ctx: Arc<VulkanContext>, desc: VulkanBackendDesc) -> VkResult<Self> {
        let frames = desc.frames_in_flight.max(1);
        let dev = &ctx.device;
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(ctx.queue_family())
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // Each object is owned by a guard that destroys it if a later step fails.
        ctx.failpoint("backend.pool")?;
        // SAFETY: valid device and create-info; destroyed in Drop (or by the guard).
        let pool =
            unsafe { dev.create_command_pool(&pool_info, None) }.op("vkCreateCommandPool")?;
        crate::backend::vulkan::device::context::handle_created();
        let pool = scopeguard::guard(pool, |p| {
            // SAFETY: nothing recorded into its command buffers was submitted.
            unsafe { dev.destroy_command_pool(p, None) };
            crate::backend::vulkan::device::context::handle_destroyed();
        });
        ctx.set_name(*pool, "VulkanBackend command pool");
        let mut type_info = vk::SemaphoreTypeCreateInfo::default()
            .semaphore_type(vk::SemaphoreType::TIMELINE)
            .initial_value(0);
        ctx.failpoint("backend.semaphore")?;
        // SAFETY: as above.
        let timeline = unsafe {
            dev.create_semaphore(
                &vk::SemaphoreCreateInfo::default().push_next(&mut type_info),
                None,
            )
        }
        .op("vkCreateSemaphore")?;
        crate::backend::vulkan::device::context::handle_created();
        let timeline = scopeguard::guard(timeline, |t| {
            // SAFETY: never signalled or waited on.
            unsafe { dev.destroy_semaphore(t, None) };
            crate::backend::vulkan::device::context::handle_destroyed();
        });
        ctx.set_name(*timeline, "VulkanBackend frame timeline");
        ctx.failpoint("backend.command_buffers")?;
        // SAFETY: the pool was just created.
        let cmds = unsafe {
            dev.allocate_command_buffers(
                &vk::CommandBufferAllocateInfo::default()
                    .command_pool(*pool)
                    .level(if desc.recording == Recording::Engine {
                        vk::CommandBufferLevel::SECONDARY
                    } else {
                        vk::CommandBufferLevel::PRIMARY
                    })
                    .command_buffer_count(frames),
            )
        }
        .op("vkAllocateCommandBuffers")?;
        let mut slots = scopeguard::guard(Vec::with_capacity(frames as usize), |slots| {
            for s in slots {
                let s: Slot = s;
                s.timestamps.destroy(&ctx);
                s.compact_pool.destroy(&ctx);
                ctx.destroy_buffer(s.results);
            }
        });
        for (i, cmd) in cmds.into_iter().enumerate() {
            ctx.set_name(cmd, &format!("frame slot {i}"));
            let timestamps = QueryPool::new(
                &ctx,
                QueryKind::Timestamp,
                QUERIES_PER_SLOT,
                &format!("slot {i} timestamps"),
            )?;
            let compact_pool = match QueryPool::new(
                &ctx,
                QueryKind::CompactedSize,
                COMPACT_QUERIES_PER_SLOT,
                &format!("slot {i} compacted sizes"),
            ) {
                Ok(p) => p,
                Err(e) => {
                    timestamps.destroy(&ctx);
                    return Err(e);
                }
            };
            let results = match ctx.create_buffer(&BufferDesc {
                name: "slot query results",
                size: u64::from(QUERIES_PER_SLOT + COMPACT_QUERIES_PER_SLOT) * 8,
                usage: vk::BufferUsageFlags::TRANSFER_DST,
                memory: MemoryKind::Readback,
            }) {
                Ok(b) => b,
                Err(e) => {
                    timestamps.destroy(&ctx);
                    compact_pool.destroy(&ctx);
                    return Err(e);
                }
            };
            slots.push(Slot {
                cmd,
                recording: false,
                executed: false,
                submitted_value: 0,
                frame: 0,
                tlas: None,
                tlas_capacity: 0,
                tlas_sizes: None,
                tlas_count: 0,
                parked: (0, 0),
                instances_call: 0,
                records: 0,
                instances: None,
                bases: None,
                bases_address: 0,
                scratch: None,
                scratch_used: ScratchLayout::new(ctx.info().min_scratch_alignment),
                timestamps,
                timed: Vec::new(),
                compact_pool,
                compact_queries: Vec::new(),
                results,
                quality: None,
                quality_jobs: Vec::new(),
            });
        }
        let slots = scopeguard::ScopeGuard::into_inner(slots);
        let timeline = scopeguard::ScopeGuard::into_inner(timeline);
        let pool = scopeguard::ScopeGuard::into_inner(pool);
        Ok(Self {
            ctx,
            desc,
            pool,
            timeline,
            slots,
            current: 0,
            blases: slotmap::SlotMap::with_key(),
            split_parts: FxHashMap::default(),
            by_address: FxHashMap::default(),
            retired_shading: FxHashMap::default(),
            retiring: VecDeque::new(),
            freed_through: None,
            completed: None,
            measurements: Vec::new(),
            log: VecDeque::new(),
            allocated: 0,
            blas_allocated: 0,
            lost: false,
            counters: VulkanCounters::default(),
            expanded: Vec::new(),
            tlas_calls: 0,
            tlas_history: VecDeque::new(),
            tlas_len: 0,
            tlas_source: None,
            parking: None,
            slot_keeper: Default::default(),
            frame_build_triangles: 0,
            pending: PendingBuilds::default(),
            frame_copies: Vec::new(),
            order: FrameOrder::default(),
            recorded_up_to: None,
            bases: Vec::new(),
            faults: Vec::new(),
            engine_done: None,
            to_record: None,
            size_cache: Default::default(),
            inputs: BufferArena::new(
                "BLAS inputs",
                BUILD_INPUT_USAGE,
                MemoryKind::Upload,
                INPUT_BLOCK_BYTES,
            ),
            accels: BufferArena::new(
                "BLAS storage",
                ACCEL_STORAGE_USAGE,
                MemoryKind::DeviceLocal,
                ACCEL_BLOCK_BYTES,
            ),
            quality_pipeline: None,
            quality_reports: Vec::new(),
        })
    }

    /// The context.
    pub fn context(&self) -> &Arc<VulkanContext> {
        &self.ctx
    }

    /// What the backend did so far.
    pub fn counters(&self) -> VulkanCounters {
        self.counters
    }

    /// The most recent GPU measurements (up to 256, oldest first), whether or not the manager
    /// already took them.
    pub fn measurement_log(&self) -> impl Iterator<Item = &Measurement> {
        self.log.iter()
    }

    /// Live BLAS count (split parts count once).
    pub fn live_blas_count(&self) -> usize {
        self.blases.len()
    }

    /// Bytes of device memory the backend holds (AS storage, inputs, scratch, TLAS, instances).
    pub fn allocated_bytes(&self) -> u64 {
        self.allocated
    }

    /// Whether a device address from [`AsBackend::blas_address`] names a live BLAS (one not
    /// yet handed to `free_blas`).
    pub fn is_live_blas_address(&self, address: u64) -> bool {
        address != 0
            && self
                .blases
                .values()
                .any(|e| e.parts.first().is_some_and(|p| p.address == address))
    }

    /// Whether a TLAS of frame `frame` may name the BLAS at `address`: live, or freed with
    /// `frame` at most its last frame of use (not destroyed before that frame completes).
    pub fn is_blas_address_usable(&self, address: u64, frame: u64) -> bool {
        self.is_live_blas_address(address)
            || self
                .retired_shading
                .get(&address)
                .is_some_and(|&(last, _)| last >= frame)
            || self.retiring.iter().any(|(last, r)| {
                *last >= frame && matches!(r, Retired::BlasAccel(a) if a.address == address)
            })
    }

    /// Bytes of acceleration-structure storage of BLASes not yet destroyed (live and
    /// retiring; split parts included): what the manager's memory budget counts. Input
    /// buffers kept for shading are not in it (see [`VulkanBackend::blas_allocated_bytes`]).
    pub fn blas_storage_bytes(&self) -> u64 {
        let live: u64 = self
            .blases
            .values()
            .flat_map(|e| e.parts.iter().chain(&e.spares))
            .map(|a| a.size)
            .sum();
        let retiring: u64 = self
            .retiring
            .iter()
            .map(|(_, r)| match r {
                Retired::BlasAccel(a) => a.size,
                _ => 0,
            })
            .sum();
        live + retiring
    }

    /// Bytes of BLAS storage and BLAS input buffers (what `memory_limit` caps).
    pub fn blas_allocated_bytes(&self) -> u64 {
        self.blas_allocated
    }
}

impl VulkanBackend {
    /// Structures per BLAS of `class`: `frames_in_flight` for skinned ones with separate refit
    /// targets, else 1. `BlasSizes::as_bytes` counts them all.
    pub(super) fn ring_len(&self, class: BlasClass) -> u64 {
        if self.desc.separate_refit_targets && class == BlasClass::Skinned {
            u64::from(self.desc.frames_in_flight.max(2))
        } else {
            1
        }
    }
}

impl AsBackend for VulkanBackend {
    fn begin_frame(&mut self, frame: u64) -> BackendResult<()> {
        if self.lost {
            return Err(BackendError::DeviceLost);
        }
        let _s = tracing::trace_span!("begin_frame").entered();
        self.order.may_begin(frame)?;
        self.check_slot_done(frame)?;
        self.begin_frame_inner(frame).map_err(|e| {
            let e = backend_err(e);
            self.lost |= e == BackendError::DeviceLost;
            e
        })?;
        self.order.begun(frame);
        Ok(())
    }

    fn completed_frame(&self) -> Option<u64> {
        self.completed
    }

    fn blas_sizes(&self, g: &GeometryRef<'_>, class: BlasClass) -> BlasSizes {
        let (vertex_format, index_type) = input_formats(g);
        let key = (
            g.triangle_count,
            g.vertex_count,
            g.opaque,
            class,
            vertex_format,
            index_type,
        );
        if let Some(s) = self.size_cache.borrow().get(&key) {
            return *s;
        }
        let geom = TriangleGeometry {
            vertex_address: 0,
            vertex_format,
            index_type,
            vertex_stride: g.device_vertices.map_or(12, |v| v.stride),
            max_vertex: g.vertex_count.saturating_sub(1),
            index_address: 0,
            triangle_count: g.triangle_count,
            opaque: g.opaque,
        };
        let s = self.ctx.blas_sizes(&[geom], self.blas_flags(class));
        let sizes = BlasSizes {
            as_bytes: s.storage * self.ring_len(class),
            build_scratch: s.build_scratch,
            update_scratch: s.update_scratch,
        };
        self.size_cache.borrow_mut().insert(key, sizes);
        sizes
    }

    fn build_blases(&mut self, builds: &[BlasBuild<'_>]) -> BackendResult<Vec<BlasHandle>> {
        let _s = tracing::trace_span!("build_blases").entered();
        self.record_blas_builds(builds)
    }

    fn refit_blases(&mut self, refits: &[BlasRefit<'_>]) -> BackendResult<()> {
        let _s = tracing::trace_span!("refit_blases").entered();
        if !refits.is_empty() {
            self.order.may_refit()?;
        }
        self.record_refits(refits)
    }

    fn compacted_size(&mut self, blas: BlasHandle) -> Option<u64> {
        self.entry(blas)?.compacted_size
    }

    fn compact_blas(&mut self, blas: BlasHandle) -> BackendResult<BlasHandle> {
        let _s = tracing::trace_span!("compact_blas").entered();
        self.record_compaction(blas)
    }

    fn free_blas(&mut self, blas: BlasHandle, last_used_frame: u64) {
        self.retire_blas(blas, last_used_frame)
    }

    fn next_tlas(&self) -> crate::backend::NextTlas {
        self.planned_tlas()
    }

    fn blas_address(&self, blas: BlasHandle) -> u64 {
        self.entry(blas).map_or(0, |e| e.parts[0].address)
    }

    fn tlas_records(&self) -> Option<usize> {
        Some(self.tlas_len)
    }

    fn build_tlas(
        &mut self,
        instances: &[TlasInstance],
        delta: TlasDelta<'_>,
    ) -> BackendResult<TlasHandle> {
        let _s = tracing::trace_span!("build_tlas").entered();
        self.order.may_build_tlas()?;
        #[cfg(debug_assertions)]
        self.check_records(instances, delta)?;
        let tlas = self.record_tlas(instances, delta)?;
        self.order.tlas_built();
        Ok(tlas)
    }

    fn end_frame(&mut self, frame: u64) -> BackendResult<()> {
        let _s = tracing::trace_span!("end_frame").entered();
        self.order.may_end(frame)?;
        match self.end_and_submit(frame) {
            Ok(()) => {
                self.order.ended(frame);
                Ok(())
            }
            Err(e) => {
                // Not submitted: the frame is dropped (its number may begin again).
                if !self.slots[self.current].recording {
                    self.order.aborted();
                }
                Err(e)
            }
        }
    }

    fn abort_frame(&mut self) {
        // The next TLAS writes every record (the aborted call's deltas are forgotten), and is
        // a build: the aborted frame's TLAS never ran.
        self.tlas_history.clear();
        self.tlas_source = None;
        self.slot_keeper.distrust_next_delta();
        let (current, frame) = (self.current, self.slots[self.current].frame);
        if let Some(p) = self.parking.as_mut() {
            if !p.confirmed && p.built == Some((current, frame)) {
                p.built = None;
            }
        }
        self.slots.iter_mut().for_each(|s| s.instances_call = 0);
        self.pending = PendingBuilds::default();
        self.order.aborted();
        // The copies never ran: their sources keep their inputs (the caller frees the copies).
        for (source, copy) in std::mem::take(&mut self.frame_copies).into_iter().rev() {
            let inputs = self
                .blases
                .get_mut(key_of(copy))
                .and_then(|e| e.static_inputs.take());
            if let Some(e) = self.blases.get_mut(key_of(source)) {
                e.compacted = false;
            }
            match self.blases.get_mut(key_of(source)) {
                Some(e) if e.static_inputs.is_none() => e.static_inputs = inputs,
                // The source was freed in the failed frame: the copy keeps them.
                _ => {
                    if let Some(e) = self.blases.get_mut(key_of(copy)) {
                        e.static_inputs = inputs;
                    }
                }
            }
        }
        let s = &mut self.slots[self.current];
        // The command buffer is reset by the next begin_frame of this slot; the queries
        // recorded into it were never written, so nothing may wait on them.
        s.recording = false;
        s.timed.clear();
        s.compact_queries.clear();
        s.quality_jobs.clear();
    }

    fn take_measurements(&mut self) -> Vec<Measurement> {
        std::mem::take(&mut self.measurements)
    }

    fn take_refit_quality(&mut self) -> Vec<(BlasHandle, f32)> {
        std::mem::take(&mut self.quality_reports)
    }
}

/// Acceleration-structure storage of a BLAS entry (all its parts); 0 for none.
fn entry_storage_bytes(e: Option<&BlasEntry>) -> u64 {
    e.map_or(0, |e| e.parts.iter().map(|a| a.size).sum())
}

impl Drop for VulkanBackend {
    fn drop(&mut self) {
        if let Err(e) = self.ctx.wait_idle() {
            tracing::error!("VulkanBackend drop: wait idle failed: {e}");
        }
        let mut objects: Vec<Retired> = self.retiring.drain(..).map(|(_, r)| r).collect();
        for (_, e) in self.blases.drain() {
            objects.extend(e.into_owned());
        }
        for s in std::mem::take(&mut self.slots) {
            objects.extend(s.tlas.map(Retired::Accel));
            objects.extend(s.instances.map(Retired::Buffer));
            objects.extend(s.bases.map(Retired::Buffer));
            objects.extend(s.scratch.map(|(b, _, _)| Retired::Buffer(b)));
            objects.extend(s.quality.map(Retired::Buffer));
            s.timestamps.destroy(&self.ctx);
            s.compact_pool.destroy(&self.ctx);
            self.ctx.destroy_buffer(s.results);
        }
        if let Some(p) = self.parking.take() {
            objects.push(Retired::Accel(p.accel));
            objects.push(Retired::Buffer(p.input));
        }
        for o in objects {
            self.destroy(o);
        }
        self.inputs.destroy(&self.ctx);
        self.accels.destroy(&self.ctx);
        if let Some(p) = self.quality_pipeline.take() {
            p.destroy(&self.ctx);
        }
        // SAFETY: the device is idle; the pool's command buffers and the semaphore are unused.
        unsafe {
            self.ctx.device.destroy_command_pool(self.pool, None);
            self.ctx.device.destroy_semaphore(self.timeline, None);
        }
        crate::backend::vulkan::device::context::handle_destroyed();
        crate::backend::vulkan::device::context::handle_destroyed();
    }
}
