//! A small safe compute-pipeline wrapper, so crates that borrow the context (the renderer) need
//! no `unsafe` of their own.

use std::io::Cursor;

use ash::vk;

use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::device::frames::FrameCmd;
use crate::backend::vulkan::device::pipeline::binding::{BindingKind, Bound};
use crate::backend::vulkan::device::pipeline::ring::{
    check_timer, create_layouts, destroy_pipeline, record_passes, Pass, PassTimer, Recorder,
    SetRing,
};
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

/// A compute pipeline with one descriptor set and push constants.
#[derive(Debug)]
pub struct ComputePipeline {
    /// The pipeline, its layout, bindings and push size, and how it records.
    rec: Recorder,
    set_layout: vk::DescriptorSetLayout,
    sets: SetRing,
}

impl ComputePipeline {
    /// Creates the pipeline from SPIR-V bytes (entry point `main`).
    pub fn new(
        ctx: &VulkanContext,
        name: &str,
        spirv: &[u8],
        bindings: &[BindingKind],
        push_size: u32,
    ) -> VkResult<Self> {
        let (set_layout, layout) =
            create_layouts(ctx, bindings, vk::ShaderStageFlags::COMPUTE, push_size)?;
        let mut raw = vk::Pipeline::null();
        let sets = create_compute_pipeline(ctx, layout, spirv, name).and_then(|p| {
            raw = p;
            SetRing::new(ctx, set_layout, bindings, name)
        });
        let sets = match sets {
            Ok(s) => s,
            Err(e) => {
                // SAFETY: nothing uses the pipeline (null if its creation failed) or its
                // layouts yet.
                unsafe { destroy_pipeline(ctx, raw, layout, set_layout) };
                return Err(e);
            }
        };
        ctx.set_name(raw, name);
        ctx.set_name(layout, &format!("{name} layout"));
        ctx.set_name(set_layout, &format!("{name} set layout"));
        Ok(Self {
            rec: Recorder {
                bind_point: vk::PipelineBindPoint::COMPUTE,
                pipeline: raw,
                layout,
                stage: vk::PipelineStageFlags2::COMPUTE_SHADER,
                push_stages: vk::ShaderStageFlags::COMPUTE,
                reads: vk::AccessFlags2::empty(),
                bindings: bindings.to_vec(),
                push_size,
            },
            set_layout,
            sets,
        })
    }

    /// Binds `bound`, dispatches `groups` workgroups with `push` constants, and waits.
    /// Returns the wall time in milliseconds (submit to completion).
    ///
    /// Shader writes are made visible to the host before this returns.
    pub fn dispatch(
        &mut self,
        ctx: &VulkanContext,
        bound: &[Bound<'_>],
        push: &[u8],
        groups: [u32; 3],
    ) -> VkResult<f64> {
        let pass = Pass { push, grid: groups };
        self.rec
            .run_blocking(ctx, "compute dispatch", &self.sets, bound, pass, |c, g| {
                // SAFETY: `c` is the dispatch's command buffer, recording outside a render
                // pass, with this pipeline and its set bound by `record_passes`.
                unsafe { ctx.device.cmd_dispatch(c, g[0], g[1], g[2]) }
            })
    }

    /// Records `passes` into `cmd` with one binding set `bound`: each pass sees the storage
    /// writes of the passes before it, the first sees the frame's acceleration-structure builds
    /// (recorded before it into `cmd`), and the host sees every write once the frame completed.
    /// With `timer`, writes a timestamp before the passes and one after each (queries 0..=n; the
    /// caller resets the pool before the frame and reads it after).
    ///
    /// No wait: the frame completes when `cmd`'s submission does. The bound resources must live
    /// until then.
    pub fn record(
        &mut self,
        ctx: &VulkanContext,
        cmd: &FrameCmd,
        bound: &[Bound<'_>],
        passes: &[Pass<'_>],
        timer: Option<PassTimer<'_>>,
    ) -> VkResult<()> {
        cmd.check(ctx)?;
        self.rec.check("record", bound, passes)?;
        check_timer(timer, passes.len())?;
        let set = self.sets.acquire(ctx, cmd, &self.rec.bindings, bound)?;
        let dispatch = |c: vk::CommandBuffer, g: [u32; 3]| {
            // SAFETY: `c` is the frame's command buffer, recording outside a render pass, with
            // this pipeline and its set bound by `record_passes`.
            unsafe { ctx.device.cmd_dispatch(c, g[0], g[1], g[2]) }
        };
        // SAFETY: a FrameCmd is recording outside a render pass (its constructor's contract);
        // pipeline, layout and set are valid, the set was written for this frame only; the
        // timer was checked, and reset by the caller.
        unsafe { record_passes(ctx, cmd.raw(), &self.rec, set, passes, timer, dispatch) };
        Ok(())
    }

    /// Destroys the pipeline. The caller guarantees no dispatch is pending (dispatch waits).
    pub fn destroy(self, ctx: &VulkanContext) {
        // SAFETY: no pending work uses these objects; each is destroyed once.
        unsafe { destroy_pipeline(ctx, self.rec.pipeline, self.rec.layout, self.set_layout) };
        self.sets.destroy(ctx);
    }
}

/// A compute pipeline over `layout` from SPIR-V bytes (entry point `main`); the shader module
/// lives only for the creation. The one place both compute pipelines (the renderer's passes and
/// the backend's refit-quality pass) turn SPIR-V into a pipeline.
pub(crate) fn create_compute_pipeline(
    ctx: &VulkanContext,
    layout: vk::PipelineLayout,
    spirv: &[u8],
    name: &str,
) -> VkResult<vk::Pipeline> {
    let code = ash::util::read_spv(&mut Cursor::new(spirv))
        .map_err(|e| VulkanError::Unsupported(format!("{name}: bad SPIR-V: {e}")))?;
    let dev = &ctx.device;
    // SAFETY: valid device; the create-info points to `code`, which outlives the call; the
    // module is destroyed below.
    let module = unsafe {
        dev.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&code), None)
    }
    .op("vkCreateShaderModule")?;
    let stage = vk::PipelineShaderStageCreateInfo::default()
        .stage(vk::ShaderStageFlags::COMPUTE)
        .module(module)
        .name(c"main");
    let info = [vk::ComputePipelineCreateInfo::default()
        .stage(stage)
        .layout(layout)];
    // SAFETY: `layout` is a valid pipeline layout of this device; `info` outlives the call.
    let raw = unsafe { dev.create_compute_pipelines(vk::PipelineCache::null(), &info, None) };
    // SAFETY: the module is no longer needed once the pipeline exists (or failed).
    unsafe { dev.destroy_shader_module(module, None) };
    Ok(raw.map_err(|(_, e)| VulkanError::from_vk("vkCreateComputePipelines", e))?[0])
}
