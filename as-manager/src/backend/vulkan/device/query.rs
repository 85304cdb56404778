//! Query pools: GPU timestamps (measured costs) and compacted AS sizes (compaction).

use std::sync::atomic::{AtomicU32, Ordering};

use ash::vk;

use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::{VkResult, VkResultExt};

/// What a [`QueryPool`] measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QueryKind {
    /// GPU timestamps (ticks; see [`QueryPool::ticks_to_ms`]).
    Timestamp,
    /// Compacted sizes of acceleration structures built with ALLOW_COMPACTION (bytes).
    CompactedSize,
}

/// A query pool. Destroy it with [`QueryPool::destroy`].
#[derive(Debug)]
pub struct QueryPool {
    /// The `vk::QueryPool` handle.
    pub raw: vk::QueryPool,
    /// Number of queries.
    pub count: u32,
    kind: QueryKind,
    period_ns: f64,
    /// One past the highest query recorded since the last reset: a reset covers only those
    /// (a slot's pool of 4,096 compaction queries sees a handful a frame).
    written: AtomicU32,
}

impl QueryPool {
    /// Creates a pool of `count` queries, reset and ready to be written.
    pub fn new(ctx: &VulkanContext, kind: QueryKind, count: u32, name: &str) -> VkResult<Self> {
        let ty = match kind {
            QueryKind::Timestamp => vk::QueryType::TIMESTAMP,
            QueryKind::CompactedSize => vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR,
        };
        let info = vk::QueryPoolCreateInfo::default()
            .query_type(ty)
            .query_count(count.max(1));
        ctx.failpoint("query_pool")?;
        // SAFETY: the device is valid; info is well-formed.
        let raw = unsafe { ctx.device.create_query_pool(&info, None) }.op("vkCreateQueryPool")?;
        crate::backend::vulkan::device::context::handle_created();
        ctx.set_name(raw, name);
        let pool = Self {
            raw,
            count: count.max(1),
            kind,
            period_ns: f64::from(ctx.info().timestamp_period_ns),
            written: AtomicU32::new(0),
        };
        // SAFETY: the pool is new: no GPU work uses it.
        unsafe { ctx.device.reset_query_pool(pool.raw, 0, pool.count) };
        Ok(pool)
    }

    /// Resets from the host every query recorded since the last reset (hostQueryReset is
    /// enabled by the context); the others were not written since theirs. The caller
    /// guarantees no pending GPU work uses the pool.
    pub fn reset(&self, ctx: &VulkanContext) {
        let n = self.written.swap(0, Ordering::Relaxed).min(self.count);
        if n > 0 {
            // SAFETY: by contract the pool is not in use by pending work.
            unsafe { ctx.device.reset_query_pool(self.raw, 0, n) };
        }
    }

    /// Notes that queries below `end` are recorded (for [`QueryPool::reset`]).
    fn mark_written(&self, end: u32) {
        self.written.fetch_max(end, Ordering::Relaxed);
    }

    /// Records a timestamp after all previous commands complete.
    ///
    /// # Safety
    /// `cmd` is recording; query `index` is reset and not written since.
    pub unsafe fn cmd_timestamp(&self, ctx: &VulkanContext, cmd: vk::CommandBuffer, index: u32) {
        debug_assert_eq!(self.kind, QueryKind::Timestamp);
        self.mark_written(index + 1);
        // SAFETY: guaranteed by the caller.
        unsafe {
            ctx.device.cmd_write_timestamp2(
                cmd,
                vk::PipelineStageFlags2::ALL_COMMANDS,
                self.raw,
                index,
            )
        };
    }

    /// Records queries of the compacted sizes of `accels`, starting at query `first`.
    ///
    /// # Safety
    /// `cmd` is recording; the structures were built with ALLOW_COMPACTION and their builds are
    /// ordered before this command by a barrier; the queries are reset.
    pub unsafe fn cmd_compacted_sizes(
        &self,
        ctx: &VulkanContext,
        cmd: vk::CommandBuffer,
        accels: &[vk::AccelerationStructureKHR],
        first: u32,
    ) {
        debug_assert_eq!(self.kind, QueryKind::CompactedSize);
        self.mark_written(first + accels.len() as u32);
        // SAFETY: guaranteed by the caller.
        unsafe {
            ctx.accel.cmd_write_acceleration_structures_properties(
                cmd,
                accels,
                vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR,
                self.raw,
                first,
            )
        };
    }

    /// Reads `n` results starting at `first`, waiting for them to be available.
    pub fn read(&self, ctx: &VulkanContext, first: u32, n: u32) -> VkResult<Vec<u64>> {
        let mut out = vec![0u64; n as usize];
        if n == 0 {
            return Ok(out);
        }
        // SAFETY: the range is within the pool; WAIT makes the call block until results exist.
        unsafe {
            ctx.device.get_query_pool_results(
                self.raw,
                first,
                &mut out,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .op("vkGetQueryPoolResults")?;
        Ok(out)
    }

    /// Records a copy of results `first..first + n` into `dst` at byte `offset`, waiting on
    /// the GPU for them to be written, and makes the copy visible to the host once the
    /// submission completes: a u64 each, or with `availability` 16 bytes each, the result and
    /// then its availability word (non-zero once the GPU wrote the result, so a caller that
    /// zeroed `dst` can tell whether the copy ran). Reading results this way needs no host
    /// query call, which some drivers (lavapipe) implement as "wait for the whole queue", and
    /// which would hang behind a later submission that waits for the host.
    ///
    /// # Safety
    /// `cmd` is recording outside a render pass; the queries were reset and are written by
    /// commands recorded before this one; `dst` has room and lives until the copy completed.
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn cmd_copy_results(
        &self,
        ctx: &VulkanContext,
        cmd: vk::CommandBuffer,
        first: u32,
        n: u32,
        dst: &crate::backend::vulkan::device::buffer::GpuBuffer,
        offset: u64,
        availability: bool,
    ) {
        if n == 0 {
            return;
        }
        let (stride, flags) = if availability {
            (
                16,
                vk::QueryResultFlags::TYPE_64
                    | vk::QueryResultFlags::WAIT
                    | vk::QueryResultFlags::WITH_AVAILABILITY,
            )
        } else {
            (
                8,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        };
        debug_assert!(offset + u64::from(n) * stride <= dst.size);
        let before = [vk::MemoryBarrier2::default()
            .src_stage_mask(vk::PipelineStageFlags2::COPY | vk::PipelineStageFlags2::HOST)
            .src_access_mask(vk::AccessFlags2::TRANSFER_WRITE | vk::AccessFlags2::HOST_READ)
            .dst_stage_mask(vk::PipelineStageFlags2::COPY)
            .dst_access_mask(vk::AccessFlags2::TRANSFER_WRITE)];
        let after = [vk::MemoryBarrier2::default()
            .src_stage_mask(vk::PipelineStageFlags2::COPY)
            .src_access_mask(vk::AccessFlags2::TRANSFER_WRITE)
            .dst_stage_mask(vk::PipelineStageFlags2::HOST)
            .dst_access_mask(vk::AccessFlags2::HOST_READ)];
        // SAFETY: guaranteed by the caller.
        unsafe {
            ctx.cmd_memory_barriers(cmd, &before);
            ctx.device.cmd_copy_query_pool_results(
                cmd, self.raw, first, n, dst.raw, offset, stride, flags,
            );
            ctx.cmd_memory_barriers(cmd, &after);
        }
    }

    /// Converts a tick difference to milliseconds.
    pub fn ticks_to_ms(&self, ticks: u64) -> f64 {
        ticks as f64 * self.period_ns * 1e-6
    }

    /// Destroys the pool. The caller guarantees no pending GPU work uses it.
    pub fn destroy(self, ctx: &VulkanContext) {
        // SAFETY: by contract the pool is not in use.
        unsafe { ctx.device.destroy_query_pool(self.raw, None) };
        crate::backend::vulkan::device::context::handle_destroyed();
    }
}

impl VulkanContext {
    /// Records a compacting copy of `src` into `dst` (sized from a compacted-size query).
    ///
    /// # Safety
    /// `cmd` is recording; `src` was built with ALLOW_COMPACTION and its build is ordered before
    /// this command; `dst` is at least the queried compacted size.
    pub unsafe fn cmd_compact(
        &self,
        cmd: vk::CommandBuffer,
        src: vk::AccelerationStructureKHR,
        dst: vk::AccelerationStructureKHR,
    ) {
        let info = vk::CopyAccelerationStructureInfoKHR::default()
            .src(src)
            .dst(dst)
            .mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
        // SAFETY: guaranteed by the caller.
        unsafe { self.accel.cmd_copy_acceleration_structure(cmd, &info) };
    }
}
