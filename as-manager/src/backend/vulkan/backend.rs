//! [`VulkanBackend`]: the manager's [`AsBackend`] on a real Vulkan device.
//!
//! - **Frames in flight.** `frames_in_flight` slots (default 2), each with its own command
//!   buffer, TLAS, instance buffer, scratch buffer and query pools, so frame `n+1`
//!   records and builds while frame `n`'s TLAS is traced. One timeline semaphore: frame `n`
//!   signals `n + 1`; `begin_frame(n)` waits for frame `n - frames_in_flight` before reusing
//!   its slot.
//! - **Batched builds.** A frame's BLAS builds go into one vkCmdBuildAccelerationStructuresKHR;
//!   scratch is sub-allocated from the slot's scratch buffer at multiples of
//!   `minAccelerationStructureScratchOffsetAlignment`; AS storage and buffers are sub-allocated
//!   by gpu-allocator.
//! - **Build inputs.** A static BLAS keeps the vertex and index buffers it was built from (the
//!   engine-side geometry a shader reads through [`VulkanBackend::shading_geometry`]). A skinned
//!   BLAS keeps its index buffer, which updates reuse, and a ring of `frames_in_flight + 1`
//!   pose buffers: each build or refit writes the next one, so the shading reads the last pose
//!   for as long as no refit replaces it, and no buffer is written while a frame may read it.
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

use std::collections::{HashMap, VecDeque};

use crate::backend::FaultPoint;
use std::sync::Arc;

use ash::vk;

use super::accel::{
    align_up, AccelStruct, BlasBuild as RawBuild, TriangleGeometry, BUILD_INPUT_USAGE,
};
use super::buffer::{BufferDesc, GpuBuffer, MemoryKind};
use super::context::VulkanContext;
use super::error::{VkResult, VkResultExt, VulkanError};
use super::query::{QueryKind, QueryPool};
use crate::backend::{
    AsBackend, BackendError, BackendResult, BlasBuild, BlasClass, BlasHandle, BlasRefit, BlasSizes,
    CostOp, GeometryRef, Measurement, TlasHandle,
};
use crate::record::TlasInstance;

/// Build flags of a BLAS class.
pub fn class_flags(class: BlasClass) -> vk::BuildAccelerationStructureFlagsKHR {
    match class {
        BlasClass::Static => {
            vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE
                | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION
        }
        BlasClass::Skinned => {
            vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD
                | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE
        }
    }
}

/// Creation parameters of a [`VulkanBackend`].
#[derive(Debug, Clone)]
pub struct VulkanBackendDesc {
    /// Frames in flight (>= 1; default 2).
    pub frames_in_flight: u32,
    /// TLAS build flags (default PREFER_FAST_TRACE; see docs/GPU.md for the measurement).
    pub tlas_flags: vk::BuildAccelerationStructureFlagsKHR,
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

impl Default for VulkanBackendDesc {
    fn default() -> Self {
        Self {
            frames_in_flight: 2,
            tlas_flags: vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
            max_part_bytes: 256 << 20,
            memory_limit: None,
            deterministic: false,
        }
    }
}

const QUERIES_PER_SLOT: u32 = 16;
const COMPACT_QUERIES_PER_SLOT: u32 = 4096;

#[derive(Debug)]
struct BlasEntry {
    gen: u32,
    parts: Vec<AccelStruct>,
    class: BlasClass,
    sizes: BlasSizes,
    /// Skinned: the index buffer that updates reuse, the poses the shading reads.
    skinned: Option<SkinnedInputs>,
    /// Static: the vertex and index buffers it was built from (kept for shading lookups).
    static_inputs: Option<(GpuBuffer, GpuBuffer)>,
    /// Device addresses of the positions and indices a shader should read for this BLAS
    /// (skinned: the last pose written to its ring).
    shading: (u64, u64),
    compacted_size: Option<u64>,
}

/// A skinned BLAS's own inputs. The positions of each build or refit go to the next buffer of
/// a ring of `frames_in_flight + 1`, owned by the BLAS (not the frame's upload arena): the
/// shading keeps reading the last pose for as long as no refit replaces it, and a buffer is
/// written again only after every frame that could read it has completed.
#[derive(Debug)]
struct SkinnedInputs {
    indices: GpuBuffer,
    triangles: u32,
    vertices: u32,
    poses: Vec<GpuBuffer>,
    /// Ring position of the next write.
    next: usize,
}

impl SkinnedInputs {
    fn buffers(self) -> impl Iterator<Item = GpuBuffer> {
        std::iter::once(self.indices).chain(self.poses)
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
}

#[derive(Debug)]
struct Slot {
    cmd: vk::CommandBuffer,
    recording: bool,
    /// Timeline value this slot's last submit signals (0: never submitted).
    submitted_value: u64,
    frame: u64,
    tlas: Option<AccelStruct>,
    tlas_capacity: u32,
    instances: Option<GpuBuffer>,
    /// Primitive bases of this frame's TLAS records (see `primitive_bases`).
    bases: Option<GpuBuffer>,
    bases_address: u64,
    scratch: Option<(GpuBuffer, vk::DeviceAddress, u64)>,
    scratch_used: u64,
    timestamps: QueryPool,
    /// (op, units, first query) of timestamp pairs recorded this frame.
    timed: Vec<(CostOp, u64, u32)>,
    compact_pool: QueryPool,
    /// (handle, query index) of compacted-size queries recorded this frame.
    compact_queries: Vec<(BlasHandle, u32)>,
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
    blases: Vec<Option<BlasEntry>>,
    free_slots: Vec<u32>,
    next_gen: u32,
    /// First-part address -> other parts' addresses, for split meshes.
    /// (the parts' addresses and first primitives).
    split_parts: HashMap<u64, Vec<(u64, u32)>>,
    /// First-part address -> blas slot (shading lookups by instance record).
    by_address: HashMap<u64, u32>,
    retiring: VecDeque<(u64, Retired)>,
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
    /// Faults armed by `inject_fault`, each striking once.
    faults: Vec<(FaultPoint, BackendError)>,
}

fn backend_err(e: VulkanError) -> BackendError {
    match e {
        VulkanError::OutOfDeviceMemory { .. } => BackendError::OutOfDeviceMemory,
        VulkanError::DeviceLost { .. } => BackendError::DeviceLost,
        other => BackendError::Other(other.to_string()),
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
        super::context::handle_created();
        let pool = scopeguard::guard(pool, |p| {
            // SAFETY: nothing recorded into its command buffers was submitted.
            unsafe { dev.destroy_command_pool(p, None) };
            super::context::handle_destroyed();
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
        super::context::handle_created();
        let timeline = scopeguard::guard(timeline, |t| {
            // SAFETY: never signalled or waited on.
            unsafe { dev.destroy_semaphore(t, None) };
            super::context::handle_destroyed();
        });
        ctx.set_name(*timeline, "VulkanBackend frame timeline");
        ctx.failpoint("backend.command_buffers")?;
        // SAFETY: the pool was just created.
        let cmds = unsafe {
            dev.allocate_command_buffers(
                &vk::CommandBufferAllocateInfo::default()
                    .command_pool(*pool)
                    .level(vk::CommandBufferLevel::PRIMARY)
                    .command_buffer_count(frames),
            )
        }
        .op("vkAllocateCommandBuffers")?;
        let mut slots = scopeguard::guard(Vec::with_capacity(frames as usize), |slots| {
            for s in slots {
                let s: Slot = s;
                s.timestamps.destroy(&ctx);
                s.compact_pool.destroy(&ctx);
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
            slots.push(Slot {
                cmd,
                recording: false,
                submitted_value: 0,
                frame: 0,
                tlas: None,
                tlas_capacity: 0,
                instances: None,
                bases: None,
                bases_address: 0,
                scratch: None,
                scratch_used: 0,
                timestamps,
                timed: Vec::new(),
                compact_pool,
                compact_queries: Vec::new(),
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
            blases: Vec::new(),
            free_slots: Vec::new(),
            next_gen: 1,
            split_parts: HashMap::new(),
            by_address: HashMap::new(),
            retiring: VecDeque::new(),
            completed: None,
            measurements: Vec::new(),
            log: VecDeque::new(),
            allocated: 0,
            blas_allocated: 0,
            lost: false,
            counters: VulkanCounters::default(),
            expanded: Vec::new(),
            bases: Vec::new(),
            faults: Vec::new(),
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
        self.blases.iter().filter(|b| b.is_some()).count()
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
                .iter()
                .flatten()
                .any(|e| e.parts.first().is_some_and(|p| p.address == address))
    }

    /// Bytes of acceleration-structure storage of BLASes not yet destroyed (live and
    /// retiring; split parts included): what the manager's memory budget counts. Input
    /// buffers kept for shading are not in it (see [`VulkanBackend::blas_allocated_bytes`]).
    pub fn blas_storage_bytes(&self) -> u64 {
        let live: u64 = self
            .blases
            .iter()
            .flatten()
            .flat_map(|e| &e.parts)
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

    /// The raw TLAS of a handle returned by `build_tlas`; None once its slot was reused for a
    /// later frame (`frames_in_flight` frames later): a stale handle never resolves to a newer
    /// TLAS.
    pub fn tlas(&self, handle: TlasHandle) -> Option<vk::AccelerationStructureKHR> {
        self.slot_of(handle)?.tlas.as_ref().map(|t| t.raw)
    }

    fn slot_of(&self, handle: TlasHandle) -> Option<&Slot> {
        self.slots
            .get(handle.slot() as usize)
            .filter(|s| s.frame == handle.frame())
    }

    /// Waits until every submitted frame finished (e.g. before reading a TLAS on another queue
    /// submission, or at shutdown).
    pub fn wait_idle(&mut self) -> VkResult<()> {
        let last = self
            .slots
            .iter()
            .map(|s| s.submitted_value)
            .max()
            .unwrap_or(0);
        self.wait_value(last)
    }

    fn wait_value(&self, value: u64) -> VkResult<()> {
        if value == 0 {
            return Ok(());
        }
        let sems = [self.timeline];
        let vals = [value];
        // SAFETY: the semaphore is a timeline semaphore of this device.
        unsafe {
            self.ctx.device.wait_semaphores(
                &vk::SemaphoreWaitInfo::default()
                    .semaphores(&sems)
                    .values(&vals),
                u64::MAX,
            )
        }
        .op("vkWaitSemaphores")
    }

    /// Counts `bytes` as allocated; `limited` allocations (BLAS storage and inputs, what the
    /// manager can answer by evicting) are refused past `memory_limit`.
    fn reserve(&mut self, bytes: u64, limited: bool) -> BackendResult<()> {
        if let (Some(limit), true) = (self.desc.memory_limit, limited) {
            if self.blas_allocated + bytes > limit {
                self.counters.oom += 1;
                return Err(BackendError::OutOfDeviceMemory);
            }
        }
        self.allocated += bytes;
        if limited {
            self.blas_allocated += bytes;
        }
        Ok(())
    }

    fn unreserve(&mut self, bytes: u64, limited: bool) {
        self.allocated -= bytes;
        if limited {
            self.blas_allocated -= bytes;
        }
    }

    fn create_accel(&mut self, size: u64, name: &str) -> BackendResult<AccelStruct> {
        self.reserve(size, true)?;
        self.ctx
            .create_accel(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL, size, name)
            .map_err(|e| {
                self.unreserve(size, true);
                backend_err(e)
            })
    }

    fn create_buffer(&mut self, desc: BufferDesc<'_>, limited: bool) -> BackendResult<GpuBuffer> {
        self.reserve(desc.size, limited)?;
        self.ctx.create_buffer(&desc).map_err(|e| {
            self.unreserve(desc.size, limited);
            backend_err(e)
        })
    }

    fn destroy(&mut self, r: Retired) {
        let limited = matches!(r, Retired::BlasAccel(_) | Retired::BlasBuffer(_));
        match r {
            Retired::Accel(a) | Retired::BlasAccel(a) => {
                self.unreserve(a.size, limited);
                self.ctx.destroy_accel(a);
            }
            Retired::Buffer(b) | Retired::BlasBuffer(b) => {
                self.unreserve(b.size, limited);
                self.ctx.destroy_buffer(b);
            }
        }
    }

    /// Retires an object against the frame being recorded.
    fn retire_now(&mut self, r: Retired) {
        let frame = self.slots[self.current].frame;
        self.retiring.push_back((frame, r));
    }

    fn entry(&self, h: BlasHandle) -> Option<&BlasEntry> {
        let (slot, gen) = ((h.0 & 0xffff_ffff) as usize, (h.0 >> 32) as u32);
        self.blases.get(slot)?.as_ref().filter(|e| e.gen == gen)
    }

    fn insert(&mut self, e: BlasEntry) -> BlasHandle {
        let address = e.parts[0].address;
        let slot = match self.free_slots.pop() {
            Some(s) => {
                self.blases[s as usize] = Some(e);
                s
            }
            None => {
                self.blases.push(Some(e));
                (self.blases.len() - 1) as u32
            }
        };
        let gen = self.blases[slot as usize].as_ref().map_or(0, |e| e.gen);
        self.by_address.insert(address, slot);
        BlasHandle(u64::from(slot) | (u64::from(gen) << 32))
    }

    fn take(&mut self, h: BlasHandle) -> Option<BlasEntry> {
        self.entry(h)?;
        let slot = (h.0 & 0xffff_ffff) as usize;
        self.free_slots.push(slot as u32);
        let e = self.blases[slot].take()?;
        self.by_address.remove(&e.parts[0].address);
        Some(e)
    }

    /// Device address of the primitive-base table of `tlas` (one `u32` per TLAS record, in
    /// record order: 0, or for the extra records of a split mesh's parts the part's first
    /// primitive), or 0 when no record of it is a part. A shader adds the entry of the hit's
    /// record (`gl_InstanceID`) to the hit's primitive id to get the mesh's primitive id, which
    /// [`VulkanBackend::shading_geometry`]'s index buffer is indexed by. Valid while the frame
    /// that built `tlas` is in flight.
    pub fn primitive_bases(&self, tlas: TlasHandle) -> u64 {
        self.slot_of(tlas).map_or(0, |s| s.bases_address)
    }

    /// Injected faults that have not struck yet.
    #[doc(hidden)]
    pub fn pending_faults(&self) -> usize {
        self.faults.len()
    }

    /// Disarms every injected fault.
    #[doc(hidden)]
    pub fn clear_faults(&mut self) {
        self.faults.clear();
    }

    /// Arms a fault: the next call at `at` fails with `error` and does nothing else
    /// (`DeviceLost` also marks the device lost, as a real loss would). For tests of the error
    /// paths on a real device.
    pub fn inject_fault(&mut self, at: FaultPoint, error: BackendError) {
        self.faults.push((at, error));
    }

    fn fault(&mut self, at: FaultPoint) -> BackendResult<()> {
        match self.faults.iter().position(|(p, _)| *p == at) {
            Some(i) => {
                let (_, e) = self.faults.remove(i);
                self.lost |= e == BackendError::DeviceLost;
                Err(e)
            }
            None => Ok(()),
        }
    }

    /// A new host-visible buffer holding `positions` (a skinned BLAS's pose).
    fn pose_buffer(&mut self, positions: &[[f32; 3]]) -> BackendResult<GpuBuffer> {
        let mut b = self.create_buffer(
            BufferDesc {
                name: "skinned pose",
                size: (positions.len() * 12).max(4) as u64,
                usage: BUILD_INPUT_USAGE,
                memory: MemoryKind::Upload,
            },
            true,
        )?;
        b.write(0, bytemuck::cast_slice(positions));
        Ok(b)
    }

    /// Writes a refit's pose into the next buffer of the BLAS's ring (allocating it while the
    /// ring is short) and points the shading at it; returns its device address.
    fn write_pose(&mut self, blas: BlasHandle, positions: &[[f32; 3]]) -> BackendResult<u64> {
        let ring = self.desc.frames_in_flight as usize + 1;
        let slot = (blas.0 & 0xffff_ffff) as usize;
        let short = self.blases[slot]
            .as_ref()
            .and_then(|e| e.skinned.as_ref())
            .is_some_and(|sk| sk.poses.len() < ring);
        let fresh = if short {
            Some(self.pose_buffer(positions)?)
        } else {
            None
        };
        let e = self.blases[slot]
            .as_mut()
            .ok_or_else(|| BackendError::Other(format!("refit of unknown {blas:?}")))?;
        let sk = e
            .skinned
            .as_mut()
            .ok_or_else(|| BackendError::Other("refit of a static BLAS".into()))?;
        let address = match fresh {
            Some(b) => {
                let a = b.address;
                sk.poses.push(b);
                a
            }
            None => {
                // Written `ring` refits ago: every frame that read it has completed.
                let b = &mut sk.poses[sk.next % ring];
                b.write(0, bytemuck::cast_slice(positions));
                b.address
            }
        };
        sk.next += 1;
        e.shading.0 = address;
        Ok(address)
    }

    /// The positions the shading of the BLAS at `blas_address` reads now, copied back from
    /// its host-visible buffer (tests check them against the last pose or the mesh).
    pub fn shading_positions(&self, blas_address: u64) -> Option<Vec<[f32; 3]>> {
        let slot = *self.by_address.get(&blas_address)?;
        let e = self.blases.get(slot as usize)?.as_ref()?;
        let buffers = e
            .skinned
            .iter()
            .flat_map(|sk| sk.poses.iter())
            .chain(e.static_inputs.iter().map(|(vb, _)| vb));
        let b = buffers.into_iter().find(|b| b.address == e.shading.0)?;
        let bytes = b.mapped()?;
        let n = bytes.len() / 12;
        Some(
            bytes[..n * 12]
                .chunks_exact(12)
                .map(|c| {
                    let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().expect("4 bytes"));
                    [f(0), f(4), f(8)]
                })
                .collect(),
        )
    }

    /// Device addresses of the positions (`[f32; 3]`) and `u32` indices a shader should read
    /// for the BLAS whose (first-part) device address is `blas_address` — the address in a TLAS
    /// instance record. For a skinned BLAS the positions are this frame's pose. Valid while the
    /// frame that recorded the record is in flight.
    pub fn shading_geometry(&self, blas_address: u64) -> Option<(u64, u64)> {
        let slot = *self.by_address.get(&blas_address)?;
        self.blases.get(slot as usize)?.as_ref().map(|e| e.shading)
    }

    /// Reserves `bytes` of the current slot's scratch; returns an aligned device address.
    /// The scratch buffer grows between batches (never within one recorded batch: callers
    /// reserve a batch's total first via `ensure_scratch`).
    fn ensure_scratch(&mut self, total: u64) -> BackendResult<()> {
        let s = self.current;
        let used = self.slots[s].scratch_used;
        let cap = self.slots[s].scratch.as_ref().map_or(0, |x| x.2);
        if used + total <= cap {
            return Ok(());
        }
        let align = self.ctx.info().min_scratch_alignment;
        let size = (cap * 2).max(total).max(1 << 20);
        let buf = self.create_buffer(
            BufferDesc {
                name: "frame scratch",
                size: size + align,
                usage: vk::BufferUsageFlags::STORAGE_BUFFER
                    | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
                memory: MemoryKind::DeviceLocal,
            },
            false,
        )?;
        let base = align_up(buf.address, align);
        if let Some((old, _, _)) = self.slots[s].scratch.replace((buf, base, size)) {
            // Batches already recorded this frame still use the old buffer.
            self.retire_now(Retired::Buffer(old));
        }
        self.slots[s].scratch_used = 0;
        Ok(())
    }

    fn scratch_alloc(&mut self, bytes: u64) -> vk::DeviceAddress {
        let align = self.ctx.info().min_scratch_alignment;
        let s = &mut self.slots[self.current];
        let (_, base, _) = s
            .scratch
            .as_ref()
            .expect("ensure_scratch before scratch_alloc");
        let addr = base + s.scratch_used;
        s.scratch_used += align_up(bytes, align);
        addr
    }

    fn cmd(&self) -> BackendResult<vk::CommandBuffer> {
        let s = &self.slots[self.current];
        if s.recording {
            Ok(s.cmd)
        } else {
            Err(BackendError::Other(
                "no frame is being recorded (call begin_frame)".into(),
            ))
        }
    }

    fn timestamp_begin(&mut self, op: CostOp, units: u64) -> Option<u32> {
        let timestamps = self.ctx.info().timestamps;
        let s = &mut self.slots[self.current];
        let first = s.timed.len() as u32 * 2;
        if !timestamps || first + 2 > QUERIES_PER_SLOT {
            return None;
        }
        s.timed.push((op, units, first));
        // SAFETY: the slot's command buffer is recording; the query was reset in begin_frame.
        unsafe { s.timestamps.cmd_timestamp(&self.ctx, s.cmd, first) };
        Some(first)
    }

    fn timestamp_end(&self, first: Option<u32>) {
        if let Some(first) = first {
            let s = &self.slots[self.current];
            // SAFETY: as in timestamp_begin.
            unsafe { s.timestamps.cmd_timestamp(&self.ctx, s.cmd, first + 1) };
        }
    }

    /// Splits a geometry's triangle range into parts that respect the device and size limits.
    fn parts_of(&self, g: &GeometryRef<'_>, class: BlasClass, sizes: &BlasSizes) -> u32 {
        let max_prims = self.ctx.info().max_primitive_count.max(1);
        let by_prims = u64::from(g.triangle_count).div_ceil(max_prims);
        let biggest = sizes.as_bytes.max(sizes.build_scratch);
        let by_bytes = biggest.div_ceil(self.desc.max_part_bytes.max(1));
        // Skinned meshes are refitted as one structure: never split them.
        if class == BlasClass::Skinned {
            return 1;
        }
        by_prims
            .max(by_bytes)
            .clamp(1, u64::from(g.triangle_count.max(1))) as u32
    }

    fn read_completed_slot(&mut self, slot: usize) -> VkResult<()> {
        let s = &mut self.slots[slot];
        if !s.timed.is_empty() {
            let n = s.timed.len() as u32 * 2;
            let ticks = s.timestamps.read(&self.ctx, 0, n)?;
            for &(op, units, first) in &s.timed {
                let dt = ticks[first as usize + 1].saturating_sub(ticks[first as usize]);
                let m = Measurement {
                    op,
                    units,
                    gpu_ms: s.timestamps.ticks_to_ms(dt),
                };
                self.measurements.push(m);
                if self.log.len() == 256 {
                    self.log.pop_front();
                }
                self.log.push_back(m);
            }
            s.timed.clear();
        }
        if !s.compact_queries.is_empty() {
            let n = s.compact_queries.len() as u32;
            let sizes = s.compact_pool.read(&self.ctx, 0, n)?;
            let queries = std::mem::take(&mut s.compact_queries);
            for ((h, _), size) in queries.into_iter().zip(sizes) {
                let (slot_i, gen) = ((h.0 & 0xffff_ffff) as usize, (h.0 >> 32) as u32);
                if let Some(Some(e)) = self.blases.get_mut(slot_i) {
                    if e.gen == gen {
                        e.compacted_size = Some(size);
                    }
                }
            }
        }
        Ok(())
    }

    fn begin_frame_inner(&mut self, frame: u64) -> VkResult<()> {
        let slot = (frame % self.slots.len() as u64) as usize;
        self.current = slot;
        // Wait for the frame that last used this slot, then harvest its queries.
        let value = self.slots[slot].submitted_value;
        self.wait_value(value)?;
        if value > 0 {
            let done = value - 1;
            self.completed = Some(self.completed.map_or(done, |c| c.max(done)));
            self.read_completed_slot(slot)?;
        }
        let reached = if self.desc.deterministic {
            0
        } else {
            // SAFETY: the timeline value is a plain read of our own semaphore.
            unsafe { self.ctx.device.get_semaphore_counter_value(self.timeline) }
                .op("vkGetSemaphoreCounterValue")?
        };
        if reached > 0 {
            self.completed = Some(self.completed.map_or(reached - 1, |c| c.max(reached - 1)));
        }
        while let Some((f, _)) = self.retiring.front() {
            if self.completed.is_some_and(|c| c >= *f) {
                let (_, r) = self.retiring.pop_front().expect("front exists");
                if matches!(r, Retired::BlasAccel(_)) {
                    self.counters.destroyed += 1;
                }
                self.destroy(r);
            } else {
                break;
            }
        }
        let s = &mut self.slots[slot];
        s.frame = frame;
        s.scratch_used = 0;
        s.timestamps.reset(&self.ctx);
        s.compact_pool.reset(&self.ctx);
        let dev = &self.ctx.device;
        // SAFETY: the slot's previous submission completed (waited above), so its command buffer
        // may be reset and re-recorded.
        unsafe {
            dev.reset_command_buffer(s.cmd, vk::CommandBufferResetFlags::empty())
                .op("vkResetCommandBuffer")?;
            dev.begin_command_buffer(
                s.cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .op("vkBeginCommandBuffer")?;
        }
        s.recording = true;
        // Order every earlier submission's AS writes before this frame's AS reads/writes.
        // SAFETY: the command buffer is recording.
        unsafe { self.ctx.cmd_accel_barrier(s.cmd) };
        Ok(())
    }
}

impl AsBackend for VulkanBackend {
    fn begin_frame(&mut self, frame: u64) -> BackendResult<()> {
        if self.lost {
            return Err(BackendError::DeviceLost);
        }
        self.begin_frame_inner(frame).map_err(|e| {
            let e = backend_err(e);
            self.lost |= e == BackendError::DeviceLost;
            e
        })
    }

    fn completed_frame(&self) -> Option<u64> {
        self.completed
    }

    fn blas_sizes(&self, g: &GeometryRef<'_>, class: BlasClass) -> BlasSizes {
        let geom = TriangleGeometry {
            vertex_address: 0,
            vertex_stride: 12,
            max_vertex: g.vertex_count.saturating_sub(1),
            index_address: 0,
            triangle_count: g.triangle_count,
            opaque: g.opaque,
        };
        let s = self.ctx.blas_sizes(&[geom], class_flags(class));
        BlasSizes {
            as_bytes: s.storage,
            build_scratch: s.build_scratch,
            update_scratch: s.update_scratch,
        }
    }

    fn build_blases(&mut self, builds: &[BlasBuild<'_>]) -> BackendResult<Vec<BlasHandle>> {
        self.fault(FaultPoint::BuildBlases)?;
        if builds.is_empty() {
            return Ok(Vec::new());
        }
        let cmd = self.cmd()?;
        struct Planned {
            geoms: Vec<TriangleGeometry>,
            accels: Vec<AccelStruct>,
            scratch: Vec<u64>,
            skinned: Option<SkinnedInputs>,
            inputs: Option<(GpuBuffer, GpuBuffer)>,
            shading: (u64, u64),
        }
        let mut planned: Vec<Planned> = Vec::with_capacity(builds.len());
        let align = self.ctx.info().min_scratch_alignment;
        let result: BackendResult<()> = (|| {
            for b in builds {
                let (Some(pos), Some(idx)) = (b.geometry.positions, b.geometry.indices) else {
                    return Err(BackendError::MissingGeometry);
                };
                let parts = self.parts_of(&b.geometry, b.class, &b.sizes);
                let mut ib = self.create_buffer(
                    BufferDesc {
                        name: "BLAS indices",
                        size: (idx.len() * 4).max(4) as u64,
                        usage: BUILD_INPUT_USAGE,
                        memory: MemoryKind::Upload,
                    },
                    true,
                )?;
                ib.write(0, bytemuck::cast_slice(idx));
                let iaddr = ib.address;
                let (vaddr, skinned, inputs) = if b.class == BlasClass::Skinned {
                    let pose = match self.pose_buffer(pos) {
                        Ok(pb) => pb,
                        Err(e) => {
                            self.destroy(Retired::BlasBuffer(ib));
                            return Err(e);
                        }
                    };
                    (
                        pose.address,
                        Some(SkinnedInputs {
                            indices: ib,
                            triangles: b.geometry.triangle_count,
                            vertices: b.geometry.vertex_count,
                            poses: vec![pose],
                            next: 1,
                        }),
                        None,
                    )
                } else {
                    let vb = match self.create_buffer(
                        BufferDesc {
                            name: "BLAS positions",
                            size: (pos.len() * 12).max(4) as u64,
                            usage: BUILD_INPUT_USAGE,
                            memory: MemoryKind::Upload,
                        },
                        true,
                    ) {
                        Ok(mut vb) => {
                            vb.write(0, bytemuck::cast_slice(pos));
                            vb
                        }
                        Err(e) => {
                            self.destroy(Retired::BlasBuffer(ib));
                            return Err(e);
                        }
                    };
                    (vb.address, None, Some((vb, ib)))
                };
                let p = Planned {
                    geoms: Vec::new(),
                    accels: Vec::new(),
                    scratch: Vec::new(),
                    skinned,
                    inputs,
                    shading: (vaddr, iaddr),
                };
                let tris = b.geometry.triangle_count;
                let per = tris.div_ceil(parts);
                planned.push(p);
                let p = planned.last_mut().expect("just pushed");
                for k in 0..parts {
                    let first = k * per;
                    let count = per.min(tris - first);
                    if count == 0 {
                        break;
                    }
                    let g = TriangleGeometry {
                        vertex_address: vaddr,
                        vertex_stride: 12,
                        max_vertex: b.geometry.vertex_count.saturating_sub(1),
                        index_address: iaddr + u64::from(first) * 12,
                        triangle_count: count,
                        opaque: b.geometry.opaque,
                    };
                    let s = if parts == 1 {
                        super::accel::AsSizes {
                            storage: b.sizes.as_bytes,
                            build_scratch: b.sizes.build_scratch,
                            update_scratch: b.sizes.update_scratch,
                        }
                    } else {
                        self.ctx.blas_sizes(&[g], class_flags(b.class))
                    };
                    let a = self.create_accel(s.storage, "BLAS")?;
                    p.geoms.push(g);
                    p.accels.push(a);
                    p.scratch
                        .push(align_up(s.build_scratch.max(s.update_scratch), align));
                }
            }
            let total: u64 = planned.iter().flat_map(|p| p.scratch.iter()).sum();
            self.ensure_scratch(total)
        })();
        if let Err(e) = result {
            // All or nothing: release what this call created (nothing was recorded yet).
            for p in planned {
                for a in p.accels {
                    self.destroy(Retired::BlasAccel(a));
                }
                for b in p.skinned.into_iter().flat_map(SkinnedInputs::buffers) {
                    self.destroy(Retired::BlasBuffer(b));
                }
                if let Some((vb, ib)) = p.inputs {
                    self.destroy(Retired::BlasBuffer(vb));
                    self.destroy(Retired::BlasBuffer(ib));
                }
            }
            return Err(e);
        }
        let mut raw_builds = Vec::new();
        let mut addrs = Vec::new();
        for p in &planned {
            for (g, (a, s)) in p.geoms.iter().zip(p.accels.iter().zip(&p.scratch)) {
                addrs.push((g, a.raw, *s));
            }
        }
        for (g, dst, s) in addrs {
            let scratch_address = self.scratch_alloc(s);
            raw_builds.push(RawBuild {
                geometries: std::slice::from_ref(g),
                flags: vk::BuildAccelerationStructureFlagsKHR::empty(),
                dst,
                update_from: None,
                scratch_address,
            });
        }
        // Flags per build (raw_builds was filled in plan order).
        let mut k = 0;
        for (b, p) in builds.iter().zip(&planned) {
            for _ in &p.accels {
                raw_builds[k].flags = class_flags(b.class);
                k += 1;
            }
        }
        let tris: u64 = builds
            .iter()
            .map(|b| u64::from(b.geometry.triangle_count))
            .sum();
        let op = if builds.iter().all(|b| b.class == BlasClass::Skinned) {
            CostOp::BuildSkinned
        } else {
            CostOp::BuildStatic
        };
        let t = self.timestamp_begin(op, tris);
        // SAFETY: cmd is recording; inputs are the BLASes' own buffers, retired with them after
        // the frame completes; scratch ranges are disjoint and aligned.
        unsafe { self.ctx.cmd_build_blases(cmd, &raw_builds) };
        self.timestamp_end(t);
        drop(raw_builds);
        // Compacted-size queries for static BLASes (single-part only).
        let statics: Vec<usize> = (0..builds.len())
            .filter(|&i| builds[i].class == BlasClass::Static && planned[i].accels.len() == 1)
            .collect();
        let mut handles = Vec::with_capacity(builds.len());
        let mut query_targets = Vec::new();
        for (i, (b, p)) in builds.iter().zip(planned).enumerate() {
            if p.accels.len() > 1 {
                self.counters.split_meshes += 1;
                let first = p.accels[0].address;
                let iaddr = p.shading.1;
                let parts = p.accels[1..]
                    .iter()
                    .zip(&p.geoms[1..])
                    .map(|(a, g)| (a.address, ((g.index_address - iaddr) / 12) as u32))
                    .collect();
                self.split_parts.insert(first, parts);
            }
            let gen = self.next_gen;
            self.next_gen = self.next_gen.wrapping_add(1).max(1);
            let raw0 = p.accels[0].raw;
            let h = self.insert(BlasEntry {
                gen,
                parts: p.accels,
                class: b.class,
                sizes: b.sizes,
                skinned: p.skinned,
                static_inputs: p.inputs,
                shading: p.shading,
                compacted_size: None,
            });
            if statics.contains(&i) {
                query_targets.push((h, raw0));
            }
            handles.push(h);
            self.counters.built += 1;
        }
        if !query_targets.is_empty() {
            let s = &mut self.slots[self.current];
            let room = (COMPACT_QUERIES_PER_SLOT as usize).saturating_sub(s.compact_queries.len());
            query_targets.truncate(room);
            if !query_targets.is_empty() {
                let first = s.compact_queries.len() as u32;
                let raws: Vec<_> = query_targets.iter().map(|(_, r)| *r).collect();
                // SAFETY: recording; the barrier orders the builds before the queries, which
                // were reset in begin_frame and are written once.
                unsafe {
                    self.ctx.cmd_accel_barrier(cmd);
                    s.compact_pool
                        .cmd_compacted_sizes(&self.ctx, cmd, &raws, first);
                }
                for (k, (h, _)) in query_targets.into_iter().enumerate() {
                    s.compact_queries.push((h, first + k as u32));
                }
            }
        }
        Ok(handles)
    }

    fn refit_blases(&mut self, refits: &[BlasRefit<'_>]) -> BackendResult<()> {
        self.fault(FaultPoint::RefitBlases)?;
        if refits.is_empty() {
            return Ok(());
        }
        let cmd = self.cmd()?;
        let align = self.ctx.info().min_scratch_alignment;
        let mut plan = Vec::with_capacity(refits.len());
        let mut total = 0;
        for r in refits {
            let e = self
                .entry(r.blas)
                .ok_or_else(|| BackendError::Other(format!("refit of unknown {:?}", r.blas)))?;
            let Some(SkinnedInputs {
                indices: ib,
                triangles: tris,
                vertices: verts,
                ..
            }) = &e.skinned
            else {
                return Err(BackendError::Other("refit of a static BLAS".into()));
            };
            let Some(pos) = r.geometry.positions else {
                return Err(BackendError::MissingGeometry);
            };
            if pos.len() as u32 != *verts || r.geometry.triangle_count != *tris {
                return Err(BackendError::Other(
                    "refit with a different topology".into(),
                ));
            }
            let scratch = if r.rebuild {
                e.sizes.build_scratch
            } else {
                e.sizes.update_scratch
            };
            total += align_up(scratch.max(1), align);
            plan.push((r, ib.address, *tris, *verts, e.parts[0].raw, scratch));
        }
        self.ensure_scratch(total)?;
        let mut geoms = Vec::with_capacity(plan.len());
        for (r, iaddr, tris, verts, _, _) in &plan {
            let vaddr = self.write_pose(r.blas, r.geometry.positions.expect("checked above"))?;
            geoms.push(TriangleGeometry {
                vertex_address: vaddr,
                vertex_stride: 12,
                max_vertex: verts.saturating_sub(1),
                index_address: *iaddr,
                triangle_count: *tris,
                opaque: r.geometry.opaque,
            });
        }
        let mut raw = Vec::with_capacity(plan.len());
        let mut tris_total = 0u64;
        let flags = class_flags(BlasClass::Skinned);
        for (i, (r, _, tris, _, dst, scratch)) in plan.iter().enumerate() {
            let scratch_address = self.scratch_alloc((*scratch).max(1));
            tris_total += u64::from(*tris);
            raw.push(RawBuild {
                geometries: std::slice::from_ref(&geoms[i]),
                flags,
                dst: *dst,
                update_from: (!r.rebuild).then_some(*dst),
                scratch_address,
            });
            if r.rebuild {
                self.counters.rebuilds += 1;
            } else {
                self.counters.refits += 1;
            }
        }
        let t = self.timestamp_begin(CostOp::Refit, tris_total);
        // SAFETY: recording; the barrier orders this frame's earlier builds (and previous frames'
        // traces, via begin_frame's barrier) before the updates; src == dst is allowed.
        unsafe {
            self.ctx.cmd_accel_barrier(cmd);
            self.ctx.cmd_build_blases(cmd, &raw);
        }
        self.timestamp_end(t);
        Ok(())
    }

    fn compacted_size(&mut self, blas: BlasHandle) -> Option<u64> {
        self.entry(blas)?.compacted_size
    }

    fn compact_blas(&mut self, blas: BlasHandle) -> BackendResult<BlasHandle> {
        self.fault(FaultPoint::CompactBlas)?;
        let cmd = self.cmd()?;
        let e = self
            .entry(blas)
            .ok_or_else(|| BackendError::Other(format!("compaction of unknown {blas:?}")))?;
        let size = e
            .compacted_size
            .ok_or_else(|| BackendError::Other("compacted size not known yet".into()))?;
        let (src, class, sizes, shading) = (e.parts[0].raw, e.class, e.sizes, e.shading);
        let dst = self.create_accel(size.max(256), "compacted BLAS")?;
        let t = self.timestamp_begin(CostOp::Compact, e_bytes(self.entry(blas)));
        // The compacted copy takes over the input buffers (shading reads them).
        let inputs = {
            let slot = (blas.0 & 0xffff_ffff) as usize;
            self.blases[slot]
                .as_mut()
                .and_then(|e| e.static_inputs.take())
        };
        // SAFETY: recording; the source was built in an earlier, completed frame (its size query
        // was read), and begin_frame's barrier orders it; dst is at least the compacted size.
        unsafe { self.ctx.cmd_compact(cmd, src, dst.raw) };
        self.timestamp_end(t);
        self.counters.compactions += 1;
        let gen = self.next_gen;
        self.next_gen = self.next_gen.wrapping_add(1).max(1);
        Ok(self.insert(BlasEntry {
            gen,
            parts: vec![dst],
            class,
            sizes: BlasSizes {
                as_bytes: size,
                ..sizes
            },
            skinned: None,
            static_inputs: inputs,
            shading,
            compacted_size: Some(size),
        }))
    }

    fn free_blas(&mut self, blas: BlasHandle, last_used_frame: u64) {
        let Some(e) = self.take(blas) else {
            tracing::warn!(?blas, "free of an unknown BLAS");
            return;
        };
        if e.parts.len() > 1 {
            self.split_parts.remove(&e.parts[0].address);
        }
        for a in e.parts {
            self.retiring
                .push_back((last_used_frame, Retired::BlasAccel(a)));
        }
        for b in e.skinned.into_iter().flat_map(SkinnedInputs::buffers) {
            self.retiring
                .push_back((last_used_frame, Retired::BlasBuffer(b)));
        }
        if let Some((vb, ib)) = e.static_inputs {
            self.retiring
                .push_back((last_used_frame, Retired::BlasBuffer(vb)));
            self.retiring
                .push_back((last_used_frame, Retired::BlasBuffer(ib)));
        }
        // Keep the queue ordered by frame (frees of older frames may arrive late).
        self.retiring.make_contiguous().sort_by_key(|(f, _)| *f);
    }

    fn blas_address(&self, blas: BlasHandle) -> u64 {
        self.entry(blas).map_or(0, |e| e.parts[0].address)
    }

    fn tlas_records(&self) -> Option<usize> {
        Some(self.expanded.len())
    }

    fn build_tlas(&mut self, instances: &[TlasInstance]) -> BackendResult<TlasHandle> {
        self.fault(FaultPoint::BuildTlas)?;
        let cmd = self.cmd()?;
        let mut records = std::mem::take(&mut self.expanded);
        records.clear();
        records.extend_from_slice(instances);
        let mut bases = std::mem::take(&mut self.bases);
        bases.clear();
        if !self.split_parts.is_empty() {
            for r in instances {
                if let Some(parts) = self.split_parts.get(&r.blas_address) {
                    if bases.is_empty() {
                        bases.resize(instances.len(), 0);
                    }
                    records.extend(parts.iter().map(|&(a, _)| TlasInstance {
                        blas_address: a,
                        ..*r
                    }));
                    bases.extend(parts.iter().map(|&(_, first)| first));
                }
            }
        }
        let s = self.current;
        self.slots[s].bases_address = 0;
        if !bases.is_empty() {
            let bytes = (bases.len() * 4) as u64;
            if self.slots[s].bases.as_ref().is_none_or(|b| b.size < bytes) {
                let buf = self.create_buffer(
                    BufferDesc {
                        name: "TLAS primitive bases",
                        size: bytes.next_power_of_two().max(4096),
                        usage: vk::BufferUsageFlags::STORAGE_BUFFER
                            | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
                        memory: MemoryKind::Upload,
                    },
                    false,
                )?;
                if let Some(old) = self.slots[s].bases.replace(buf) {
                    self.retire_now(Retired::Buffer(old));
                }
            }
            let b = self.slots[s].bases.as_mut().expect("allocated above");
            b.write(0, bytemuck::cast_slice(&bases));
            self.slots[s].bases_address = b.address;
        }
        self.bases = bases;
        let n = records.len().max(1) as u32;
        let bytes = u64::from(n) * 64;
        if self.slots[s]
            .instances
            .as_ref()
            .is_none_or(|b| b.size < bytes)
        {
            let size = bytes.next_power_of_two().max(64 * 1024);
            let buf = self.create_buffer(
                BufferDesc {
                    name: "TLAS instances",
                    size,
                    usage: BUILD_INPUT_USAGE,
                    memory: MemoryKind::Upload,
                },
                false,
            )?;
            if let Some(old) = self.slots[s].instances.replace(buf) {
                self.retire_now(Retired::Buffer(old));
            }
        }
        if self.slots[s].tlas_capacity < n {
            let cap = n.next_power_of_two().max(1024);
            let sizes = self.ctx.tlas_sizes(cap, self.desc.tlas_flags);
            self.reserve(sizes.storage, false)?;
            let tlas = self
                .ctx
                .create_accel(
                    vk::AccelerationStructureTypeKHR::TOP_LEVEL,
                    sizes.storage,
                    &format!("TLAS slot {s}"),
                )
                .map_err(|e| {
                    self.unreserve(sizes.storage, false);
                    backend_err(e)
                })?;
            if let Some(old) = self.slots[s].tlas.replace(tlas) {
                self.retire_now(Retired::Accel(old));
            }
            self.slots[s].tlas_capacity = cap;
        }
        let sizes = self.ctx.tlas_sizes(n, self.desc.tlas_flags);
        self.ensure_scratch(align_up(
            sizes.build_scratch,
            self.ctx.info().min_scratch_alignment,
        ))?;
        let scratch = self.scratch_alloc(sizes.build_scratch);
        let slot = &mut self.slots[s];
        let ibuf = slot.instances.as_mut().expect("allocated above");
        ibuf.write(0, bytemuck::cast_slice(&records));
        let (iaddr, tlas) = (
            ibuf.address,
            slot.tlas.as_ref().expect("allocated above").raw,
        );
        let count = records.len() as u32;
        self.expanded = records;
        let t = self.timestamp_begin(CostOp::Tlas, u64::from(count));
        // SAFETY: recording; the barrier orders this frame's BLAS builds/refits/compactions
        // before the TLAS build; every referenced BLAS is live until its retirement frame.
        unsafe {
            self.ctx.cmd_accel_barrier(cmd);
            self.ctx
                .cmd_build_tlas(cmd, tlas, None, self.desc.tlas_flags, iaddr, count, scratch);
        }
        self.timestamp_end(t);
        Ok(TlasHandle::new(s as u32, self.slots[s].frame))
    }

    fn end_frame(&mut self, frame: u64) -> BackendResult<()> {
        self.fault(FaultPoint::EndFrame)?;
        let cmd = self.cmd()?;
        let value = frame + 1;
        let r = (|| {
            // SAFETY: recording; the barrier makes the TLAS build visible to later traces.
            unsafe {
                self.ctx.cmd_accel_barrier(cmd);
                self.ctx
                    .device
                    .end_command_buffer(cmd)
                    .op("vkEndCommandBuffer")?;
            }
            let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
            let signal = [vk::SemaphoreSubmitInfo::default()
                .semaphore(self.timeline)
                .value(value)
                .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
            let submit = [vk::SubmitInfo2::default()
                .command_buffer_infos(&cmds)
                .signal_semaphore_infos(&signal)];
            self.ctx.submit(&submit)
        })();
        let s = &mut self.slots[self.current];
        s.recording = false;
        match r {
            Ok(()) => {
                s.submitted_value = value;
                Ok(())
            }
            Err(e) => {
                let e = backend_err(e);
                self.lost |= e == BackendError::DeviceLost;
                Err(e)
            }
        }
    }

    fn abort_frame(&mut self) {
        let s = &mut self.slots[self.current];
        // The command buffer is reset by the next begin_frame of this slot; the queries
        // recorded into it were never written, so nothing may wait on them.
        s.recording = false;
        s.timed.clear();
        s.compact_queries.clear();
    }

    fn take_measurements(&mut self) -> Vec<Measurement> {
        std::mem::take(&mut self.measurements)
    }
}

fn e_bytes(e: Option<&BlasEntry>) -> u64 {
    e.map_or(0, |e| e.parts.iter().map(|a| a.size).sum())
}

impl Drop for VulkanBackend {
    fn drop(&mut self) {
        if let Err(e) = self.ctx.wait_idle() {
            tracing::error!("VulkanBackend drop: wait idle failed: {e}");
        }
        let mut objects: Vec<Retired> = self.retiring.drain(..).map(|(_, r)| r).collect();
        for e in self.blases.drain(..).flatten() {
            objects.extend(e.parts.into_iter().map(Retired::BlasAccel));
            objects.extend(
                e.skinned
                    .into_iter()
                    .flat_map(SkinnedInputs::buffers)
                    .map(Retired::BlasBuffer),
            );
            if let Some((vb, ib)) = e.static_inputs {
                objects.push(Retired::BlasBuffer(vb));
                objects.push(Retired::BlasBuffer(ib));
            }
        }
        for s in std::mem::take(&mut self.slots) {
            objects.extend(s.tlas.map(Retired::Accel));
            objects.extend(s.instances.map(Retired::Buffer));
            objects.extend(s.bases.map(Retired::Buffer));
            objects.extend(s.scratch.map(|(b, _, _)| Retired::Buffer(b)));
            s.timestamps.destroy(&self.ctx);
            s.compact_pool.destroy(&self.ctx);
        }
        for o in objects {
            self.destroy(o);
        }
        // SAFETY: the device is idle; the pool's command buffers and the semaphore are unused.
        unsafe {
            self.ctx.device.destroy_command_pool(self.pool, None);
            self.ctx.device.destroy_semaphore(self.timeline, None);
        }
        super::context::handle_destroyed();
        super::context::handle_destroyed();
    }
}
