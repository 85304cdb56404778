//! What both pipeline wrappers (compute and ray tracing) share: their layouts, their
//! descriptor sets for recorded frames (one set per frame in flight, up to [`RECORDED_SETS`],
//! plus one for the blocking calls that wait for their own submission), and how a call's passes
//! are checked, recorded and, for the blocking calls, submitted and waited for.

use std::time::Instant;

use ash::vk;

use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::device::frames::FrameCmd;
use crate::backend::vulkan::device::pipeline::binding::{
    descriptor_type, write_descriptor_set, BindingKind, Bound,
};
use crate::backend::vulkan::device::query::QueryPool;
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

/// A pipeline's descriptor-set layout (set 0: `bindings` in list order, seen by `stages`) and
/// its pipeline layout (that set, and `push_size` bytes of push constants for `stages`). On
/// failure nothing created here is left alive.
pub(crate) fn create_layouts(
    ctx: &VulkanContext,
    bindings: &[BindingKind],
    stages: vk::ShaderStageFlags,
    push_size: u32,
) -> VkResult<(vk::DescriptorSetLayout, vk::PipelineLayout)> {
    let dev = &ctx.device;
    let layout_bindings: Vec<_> = bindings
        .iter()
        .enumerate()
        .map(|(i, k)| {
            vk::DescriptorSetLayoutBinding::default()
                .binding(i as u32)
                .descriptor_type(descriptor_type(*k))
                .descriptor_count(1)
                .stage_flags(stages)
        })
        .collect();
    // SAFETY: `dev` is a valid device; every create-info points to locals that outlive the
    // call; the caller destroys the layouts (`destroy_pipeline`), or the error path below does.
    let set_layout = unsafe {
        dev.create_descriptor_set_layout(
            &vk::DescriptorSetLayoutCreateInfo::default().bindings(&layout_bindings),
            None,
        )
    }
    .op("vkCreateDescriptorSetLayout")?;
    let ranges = [vk::PushConstantRange::default()
        .stage_flags(stages)
        .size(push_size)];
    let set_layouts = [set_layout];
    let mut pl_info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
    if push_size > 0 {
        pl_info = pl_info.push_constant_ranges(&ranges);
    }
    // SAFETY: as above.
    match unsafe { dev.create_pipeline_layout(&pl_info, None) } {
        Ok(layout) => Ok((set_layout, layout)),
        Err(e) => {
            // SAFETY: the set layout is unused.
            unsafe { dev.destroy_descriptor_set_layout(set_layout, None) };
            Err(VulkanError::from_vk("vkCreatePipelineLayout", e))
        }
    }
}

/// Destroys a pipeline and its layouts. Null handles (a pipeline whose creation failed) are
/// ignored, as `vkDestroy*` ignores them.
///
/// # Safety
/// No pending work uses these objects, and each is destroyed once.
pub(crate) unsafe fn destroy_pipeline(
    ctx: &VulkanContext,
    pipeline: vk::Pipeline,
    layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
) {
    // SAFETY: guaranteed by the caller.
    unsafe {
        ctx.device.destroy_pipeline(pipeline, None);
        ctx.device.destroy_pipeline_layout(layout, None);
        ctx.device.destroy_descriptor_set_layout(set_layout, None);
    }
}

/// Frames in flight a pipeline's recorded passes support: frame `n` writes the set frame
/// `n - RECORDED_SETS` used, which must have completed by then.
pub const RECORDED_SETS: u32 = 4;

/// One dispatch (or trace) of a recorded frame: push constants and the grid (workgroups for
/// a compute pipeline, rays for a ray-tracing pipeline).
#[derive(Debug, Clone, Copy)]
pub struct Pass<'a> {
    /// Push constants (the pipeline's push size).
    pub push: &'a [u8],
    /// Workgroups (compute) or rays (ray tracing), x/y/z.
    pub grid: [u32; 3],
}

/// Timestamps of a recorded frame's passes: one before the passes and one after each, in
/// `queries` (reset by the caller before the frame), copied on the GPU into `results` at the
/// end of the passes, to read with [`read_timer`] once the frame completed.
///
/// Each timestamp is copied with its availability (two u64: the value, then a word that is
/// non-zero once the GPU wrote it). A caller that zeroes `results` before recording can tell
/// a frame whose commands ran to the end from one never submitted, or still on the GPU: its
/// availability words stay zero.
#[derive(Debug, Clone, Copy)]
pub struct PassTimer<'a> {
    /// A timestamp pool with at least passes + 1 queries.
    pub queries: &'a QueryPool,
    /// A host-visible buffer (TRANSFER_DST) with room for two u64 per query.
    pub results: &'a crate::backend::vulkan::device::buffer::GpuBuffer,
}

/// The first `n` timestamps a [`PassTimer`] copied into `results`, if the GPU wrote every one
/// of them (their availability words are non-zero); `None` otherwise, or if the buffer is not
/// host-visible or too short.
pub fn read_timer(
    results: &crate::backend::vulkan::device::buffer::GpuBuffer,
    n: usize,
) -> Option<Vec<u64>> {
    let words: &[u64] = bytemuck::try_cast_slice(results.mapped()?.get(..n * 16)?).ok()?;
    let pairs = words.chunks_exact(2);
    pairs
        .map(|p| (p[1] != 0).then_some(p[0]))
        .collect::<Option<Vec<u64>>>()
}

/// The descriptor pool and sets of a pipeline.
#[derive(Debug)]
pub(crate) struct SetRing {
    pool: vk::DescriptorPool,
    /// `RECORDED_SETS` sets for recorded frames, then the blocking calls' set.
    sets: Vec<vk::DescriptorSet>,
    /// Frame each recorded set was last written for.
    frames: Vec<Option<u64>>,
}

impl SetRing {
    pub(crate) fn new(
        ctx: &VulkanContext,
        set_layout: vk::DescriptorSetLayout,
        bindings: &[BindingKind],
        name: &str,
    ) -> VkResult<Self> {
        let count = RECORDED_SETS + 1;
        let mut sizes: Vec<vk::DescriptorPoolSize> = Vec::new();
        for k in bindings {
            let ty = descriptor_type(*k);
            match sizes.iter_mut().find(|s| s.ty == ty) {
                Some(s) => s.descriptor_count += count,
                None => sizes.push(vk::DescriptorPoolSize {
                    ty,
                    descriptor_count: count,
                }),
            }
        }
        let dev = &ctx.device;
        // SAFETY: valid device; the create-info points to locals; destroyed in `destroy`.
        let pool = unsafe {
            dev.create_descriptor_pool(
                &vk::DescriptorPoolCreateInfo::default()
                    .max_sets(count)
                    .pool_sizes(&sizes),
                None,
            )
        }
        .op("vkCreateDescriptorPool")?;
        let layouts = vec![set_layout; count as usize];
        // SAFETY: the pool has room for `count` sets of this layout.
        let sets = unsafe {
            dev.allocate_descriptor_sets(
                &vk::DescriptorSetAllocateInfo::default()
                    .descriptor_pool(pool)
                    .set_layouts(&layouts),
            )
        };
        let sets = match sets {
            Ok(s) => s,
            Err(e) => {
                // SAFETY: the pool is unused.
                unsafe { dev.destroy_descriptor_pool(pool, None) };
                return Err(VulkanError::from_vk("vkAllocateDescriptorSets", e));
            }
        };
        ctx.set_name(pool, &format!("{name} descriptor pool"));
        for (i, s) in sets.iter().enumerate() {
            ctx.set_name(*s, &format!("{name} set {i}"));
        }
        Ok(Self {
            pool,
            frames: vec![None; RECORDED_SETS as usize],
            sets,
        })
    }

    /// The set of the blocking calls (each waits for its submission, so it is never in use).
    pub(crate) fn blocking(&self) -> vk::DescriptorSet {
        self.sets[RECORDED_SETS as usize]
    }

    /// The set for `cmd`'s frame, written with `bound`. Fails, writing nothing, when the frame
    /// that used it last has not completed, or when the frame already recorded with it.
    pub(crate) fn acquire(
        &mut self,
        ctx: &VulkanContext,
        cmd: &FrameCmd,
        bindings: &[BindingKind],
        bound: &[Bound<'_>],
    ) -> VkResult<vk::DescriptorSet> {
        let i = (cmd.frame() % u64::from(RECORDED_SETS)) as usize;
        if let Some(f) = self.frames[i] {
            if f >= cmd.frame() {
                return Err(VulkanError::Unsupported(format!(
                    "frame {} records this pipeline after frame {f}: once per frame, in order \
                     (several passes go into one record call)",
                    cmd.frame()
                )));
            }
            if !cmd.is_done(f) {
                return Err(VulkanError::Unsupported(format!(
                    "frame {} needs frame {f} to be done: more than {RECORDED_SETS} frames in \
                     flight",
                    cmd.frame()
                )));
            }
        }
        // The set's last frame completed: no pending work uses it.
        write_descriptor_set(ctx, self.sets[i], bindings, bound)?;
        self.frames[i] = Some(cmd.frame());
        Ok(self.sets[i])
    }

    pub(crate) fn destroy(&self, ctx: &VulkanContext) {
        // SAFETY: the caller guarantees no pending work uses the sets; the pool is ours.
        unsafe { ctx.device.destroy_descriptor_pool(self.pool, None) };
    }
}

/// Checks a recorded frame's timer: one timestamp before the passes and one after each.
pub(crate) fn check_timer(timer: Option<PassTimer<'_>>, passes: usize) -> VkResult<()> {
    match timer {
        Some(t)
            if (t.queries.count as usize) < passes + 1
                || t.results.size < (passes as u64 + 1) * 16
                || t.results.mapped().is_none() =>
        {
            Err(VulkanError::Unsupported(format!(
                "a timer for {passes} passes needs {} queries and a host-visible buffer of {} \
                 bytes",
                passes + 1,
                (passes + 1) * 16
            )))
        }
        _ => Ok(()),
    }
}

/// Records the timer's copy of its `passes + 1` timestamps (after the passes).
///
/// # Safety
/// `cmd` is recording outside a render pass, after the timestamps were written.
pub(crate) unsafe fn copy_timer(
    ctx: &VulkanContext,
    cmd: vk::CommandBuffer,
    timer: Option<PassTimer<'_>>,
    passes: usize,
) {
    if let Some(t) = timer {
        // SAFETY: guaranteed by the caller; `check_timer` checked the sizes.
        unsafe {
            t.queries
                .cmd_copy_results(ctx, cmd, 0, passes as u32 + 1, t.results, 0, true)
        };
    }
}

/// A pipeline as both wrappers hold it, and how it records: what `record_passes` binds, which
/// stage its shaders run in, and the bindings and push size every call must match.
#[derive(Debug)]
pub(crate) struct Recorder {
    pub(crate) bind_point: vk::PipelineBindPoint,
    pub(crate) pipeline: vk::Pipeline,
    pub(crate) layout: vk::PipelineLayout,
    /// The shaders' pipeline stage (compute, or ray tracing).
    pub(crate) stage: vk::PipelineStageFlags2,
    /// Stages of the push-constant range.
    pub(crate) push_stages: vk::ShaderStageFlags,
    /// What the first pass reads besides storage buffers (the SBT for ray tracing).
    pub(crate) reads: vk::AccessFlags2,
    /// The pipeline's bindings, in binding order.
    pub(crate) bindings: Vec<BindingKind>,
    /// The pipeline's push-constant bytes.
    pub(crate) push_size: u32,
}

impl Recorder {
    /// Checks a call's bindings and push sizes against the pipeline's (`what` names the call
    /// in the error).
    pub(crate) fn check(
        &self,
        what: &str,
        bound: &[Bound<'_>],
        passes: &[Pass<'_>],
    ) -> VkResult<()> {
        if bound.len() != self.bindings.len()
            || passes.iter().any(|p| p.push.len() as u32 != self.push_size)
        {
            return Err(VulkanError::Unsupported(format!(
                "{what} with {} bindings and push constants of {:?} bytes; the pipeline has {} \
                 bindings and {} push bytes",
                bound.len(),
                passes.iter().map(|p| p.push.len()).collect::<Vec<_>>(),
                self.bindings.len(),
                self.push_size
            )));
        }
        Ok(())
    }

    /// The blocking calls (`ComputePipeline::dispatch`, `RayTracingPipeline::trace`): checks
    /// and binds `bound` in the blocking set of `sets`, records `pass` as `record_passes` does
    /// (after earlier work on the queue, its writes visible to the host), submits it and waits.
    /// `dispatch` records the pass's grid; `what` names the call. Returns the wall time in
    /// milliseconds (submit to completion).
    pub(crate) fn run_blocking(
        &self,
        ctx: &VulkanContext,
        what: &str,
        sets: &SetRing,
        bound: &[Bound<'_>],
        pass: Pass<'_>,
        dispatch: impl FnMut(vk::CommandBuffer, [u32; 3]),
    ) -> VkResult<f64> {
        let passes = [pass];
        self.check(what, bound, &passes)?;
        // Every blocking call waits for completion before returning, so the set is not in use.
        let set = sets.blocking();
        write_descriptor_set(ctx, set, &self.bindings, bound)?;
        let start = Instant::now();
        ctx.submit_and_wait(what, |_, cmd| {
            // SAFETY: cmd is recording, outside a render pass; pipeline, layout and set are
            // valid and the set is not in use (see above); no timer. The bound resources live
            // until the wait returns (they are borrowed for this call).
            unsafe { record_passes(ctx, cmd, self, set, &passes, None, dispatch) }
        })?;
        Ok(start.elapsed().as_secs_f64() * 1e3)
    }
}

/// Records `passes` with `set` bound: ordered after earlier work on the queue, each pass after
/// the one before, every write visible to the host once the frame completed, and the timer's
/// timestamps around the passes. `dispatch` records one pass's grid.
///
/// # Safety
/// `cmd` is recording outside a render pass; the recorder's pipeline, layout and `set` are
/// valid and `set` is not in use by other pending work; the timer was checked (`check_timer`)
/// and reset.
pub(crate) unsafe fn record_passes(
    ctx: &VulkanContext,
    cmd: vk::CommandBuffer,
    r: &Recorder,
    set: vk::DescriptorSet,
    passes: &[Pass<'_>],
    timer: Option<PassTimer<'_>>,
    mut dispatch: impl FnMut(vk::CommandBuffer, [u32; 3]),
) {
    let storage = vk::AccessFlags2::SHADER_STORAGE_READ | vk::AccessFlags2::SHADER_STORAGE_WRITE;
    // Earlier frames on this queue (the slot's last use of the same buffers) before this
    // frame's writes; the frame's AS builds are covered by the backend's own barrier.
    let before = [vk::MemoryBarrier2::default()
        .src_stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
        .src_access_mask(vk::AccessFlags2::MEMORY_READ | vk::AccessFlags2::MEMORY_WRITE)
        .dst_stage_mask(r.stage)
        .dst_access_mask(storage | vk::AccessFlags2::ACCELERATION_STRUCTURE_READ_KHR | r.reads)];
    let between = [vk::MemoryBarrier2::default()
        .src_stage_mask(r.stage)
        .src_access_mask(vk::AccessFlags2::SHADER_STORAGE_WRITE)
        .dst_stage_mask(r.stage)
        .dst_access_mask(storage)];
    let to_host = [vk::MemoryBarrier2::default()
        .src_stage_mask(r.stage)
        .src_access_mask(vk::AccessFlags2::SHADER_STORAGE_WRITE)
        .dst_stage_mask(vk::PipelineStageFlags2::HOST)
        .dst_access_mask(vk::AccessFlags2::HOST_READ)];
    let dev = &ctx.device;
    let barrier = |b: &[vk::MemoryBarrier2<'_>]| {
        // SAFETY: guaranteed by the caller (cmd is recording outside a render pass).
        unsafe { ctx.cmd_memory_barriers(cmd, b) }
    };
    barrier(&before);
    // SAFETY: guaranteed by the caller.
    unsafe {
        dev.cmd_bind_pipeline(cmd, r.bind_point, r.pipeline);
        dev.cmd_bind_descriptor_sets(cmd, r.bind_point, r.layout, 0, &[set], &[]);
        if let Some(t) = timer {
            t.queries.cmd_timestamp(ctx, cmd, 0);
        }
    }
    for (i, p) in passes.iter().enumerate() {
        if i > 0 {
            barrier(&between);
        }
        if !p.push.is_empty() {
            // SAFETY: guaranteed by the caller; the push size was checked.
            unsafe { dev.cmd_push_constants(cmd, r.layout, r.push_stages, 0, p.push) };
        }
        dispatch(cmd, p.grid);
        if let Some(t) = timer {
            // SAFETY: the timer has room for a timestamp after each pass (checked).
            unsafe { t.queries.cmd_timestamp(ctx, cmd, i as u32 + 1) };
        }
    }
    barrier(&to_host);
    // SAFETY: guaranteed by the caller.
    unsafe { copy_timer(ctx, cmd, timer, passes.len()) };
}
