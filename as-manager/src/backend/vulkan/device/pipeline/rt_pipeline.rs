//! A small safe ray-tracing-pipeline wrapper (VK_KHR_ray_tracing_pipeline): one raygen, one miss
//! and one triangle hit group with a closest-hit shader, a shader binding table laid out with the
//! device's handle size and alignments, and the same binding model as
//! [`ComputePipeline`](crate::backend::vulkan::ComputePipeline) (set 0, bindings in list order, push constants).
//!
//! This is the renderer's path on GPUs without VK_KHR_ray_query (the NVIDIA H100/H200 here).

use std::io::Cursor;

use ash::vk;

use crate::backend::vulkan::device::accel::align_up;
use crate::backend::vulkan::device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::device::frames::FrameCmd;
use crate::backend::vulkan::device::pipeline::binding::{BindingKind, Bound};
use crate::backend::vulkan::device::pipeline::ring::{
    check_timer, create_layouts, destroy_pipeline, record_passes, Pass, PassTimer, Recorder,
    SetRing,
};
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

/// SPIR-V of the three shaders (entry point `main` in each).
#[derive(Debug, Clone, Copy)]
pub struct RtShaders<'a> {
    /// Ray generation shader.
    pub raygen: &'a [u8],
    /// Miss shader (miss index 0).
    pub miss: &'a [u8],
    /// Closest-hit shader of the only hit group (SBT offset 0 for every instance).
    pub closest_hit: &'a [u8],
}

/// Every stage a binding or push constant of the pipeline may be read from.
const STAGES: vk::ShaderStageFlags = vk::ShaderStageFlags::from_raw(
    vk::ShaderStageFlags::RAYGEN_KHR.as_raw()
        | vk::ShaderStageFlags::MISS_KHR.as_raw()
        | vk::ShaderStageFlags::CLOSEST_HIT_KHR.as_raw(),
);

/// A ray-tracing pipeline with its shader binding table, one descriptor set and push constants.
#[derive(Debug)]
pub struct RayTracingPipeline {
    /// The pipeline (null until `finish` creates it), its layout, bindings and push size, and
    /// how it records.
    rec: Recorder,
    set_layout: vk::DescriptorSetLayout,
    /// None until `finish` creates them.
    sets: Option<SetRing>,
    sbt: GpuBuffer,
    /// raygen, miss, hit, callable (empty).
    regions: [vk::StridedDeviceAddressRegionKHR; 4],
}

impl RayTracingPipeline {
    /// Creates the pipeline and its shader binding table. Fails with
    /// [`VulkanError::Unsupported`] when the device has no VK_KHR_ray_tracing_pipeline.
    pub fn new(
        ctx: &VulkanContext,
        name: &str,
        shaders: &RtShaders<'_>,
        bindings: &[BindingKind],
        push_size: u32,
    ) -> VkResult<Self> {
        let Some(rt) = ctx.ray_tracing_pipeline() else {
            return Err(VulkanError::Unsupported(format!(
                "{name}: device {:?} has no VK_KHR_ray_tracing_pipeline",
                ctx.info().name
            )));
        };
        let read = |what: &str, bytes: &[u8]| {
            ash::util::read_spv(&mut Cursor::new(bytes))
                .map_err(|e| VulkanError::Unsupported(format!("{name}: bad {what} SPIR-V: {e}")))
        };
        let codes = [
            read("raygen", shaders.raygen)?,
            read("miss", shaders.miss)?,
            read("closest-hit", shaders.closest_hit)?,
        ];

        let mut rt_props = vk::PhysicalDeviceRayTracingPipelinePropertiesKHR::default();
        let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut rt_props);
        // SAFETY: the physical device belongs to this instance; the chain lives through the call.
        unsafe {
            ctx.instance
                .get_physical_device_properties2(ctx.physical_device, &mut props2)
        };
        let handle_size = u64::from(rt_props.shader_group_handle_size);
        let handle_align = u64::from(rt_props.shader_group_handle_alignment.max(1));
        let base_align = u64::from(rt_props.shader_group_base_alignment.max(1));
        if handle_size == 0 || rt_props.max_ray_recursion_depth == 0 {
            return Err(VulkanError::Unsupported(format!(
                "{name}: device reports shaderGroupHandleSize {handle_size}, \
                 maxRayRecursionDepth {}",
                rt_props.max_ray_recursion_depth
            )));
        }

        // Destroyed in `destroy`, or on the error paths below.
        let (set_layout, layout) = create_layouts(ctx, bindings, STAGES, push_size)?;
        // From here on, failures clean up through `partial`.
        let mut partial = Self {
            rec: Recorder {
                bind_point: vk::PipelineBindPoint::RAY_TRACING_KHR,
                pipeline: vk::Pipeline::null(),
                layout,
                stage: vk::PipelineStageFlags2::RAY_TRACING_SHADER_KHR,
                push_stages: STAGES,
                reads: vk::AccessFlags2::SHADER_BINDING_TABLE_READ_KHR,
                bindings: bindings.to_vec(),
                push_size,
            },
            set_layout,
            sets: None,
            sbt: ctx
                .create_buffer(&BufferDesc {
                    name: &format!("{name} sbt"),
                    // Room for three base-aligned regions plus the base alignment itself (the
                    // allocation's address need not be base-aligned).
                    size: 4 * align_up(align_up(handle_size, handle_align), base_align)
                        + base_align,
                    usage: vk::BufferUsageFlags::SHADER_BINDING_TABLE_KHR
                        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
                    memory: MemoryKind::Upload,
                })
                .inspect_err(|_| {
                    // SAFETY: layout and set layout are unused; there is no pipeline yet.
                    unsafe { destroy_pipeline(ctx, vk::Pipeline::null(), layout, set_layout) }
                })?,
            regions: [vk::StridedDeviceAddressRegionKHR::default(); 4],
        };
        match partial.finish(ctx, rt, name, &codes, handle_size, handle_align, base_align) {
            Ok(()) => Ok(partial),
            Err(e) => {
                partial.destroy(ctx);
                Err(e)
            }
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        ctx: &VulkanContext,
        rt: &ash::khr::ray_tracing_pipeline::Device,
        name: &str,
        codes: &[Vec<u32>; 3],
        handle_size: u64,
        handle_align: u64,
        base_align: u64,
    ) -> VkResult<()> {
        let dev = &ctx.device;
        let mut modules = Vec::with_capacity(3);
        for code in codes {
            // SAFETY: valid device; the code outlives the call; modules are destroyed below.
            match unsafe {
                dev.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(code), None)
            } {
                Ok(m) => modules.push(m),
                Err(e) => {
                    for m in modules {
                        // SAFETY: the module is unused.
                        unsafe { dev.destroy_shader_module(m, None) };
                    }
                    return Err(VulkanError::from_vk("vkCreateShaderModule", e));
                }
            }
        }
        let stages = [
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::RAYGEN_KHR)
                .module(modules[0])
                .name(c"main"),
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::MISS_KHR)
                .module(modules[1])
                .name(c"main"),
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::CLOSEST_HIT_KHR)
                .module(modules[2])
                .name(c"main"),
        ];
        let general = |i: u32| {
            vk::RayTracingShaderGroupCreateInfoKHR::default()
                .ty(vk::RayTracingShaderGroupTypeKHR::GENERAL)
                .general_shader(i)
                .closest_hit_shader(vk::SHADER_UNUSED_KHR)
                .any_hit_shader(vk::SHADER_UNUSED_KHR)
                .intersection_shader(vk::SHADER_UNUSED_KHR)
        };
        let groups = [
            general(0),
            general(1),
            vk::RayTracingShaderGroupCreateInfoKHR::default()
                .ty(vk::RayTracingShaderGroupTypeKHR::TRIANGLES_HIT_GROUP)
                .general_shader(vk::SHADER_UNUSED_KHR)
                .closest_hit_shader(2)
                .any_hit_shader(vk::SHADER_UNUSED_KHR)
                .intersection_shader(vk::SHADER_UNUSED_KHR),
        ];
        let info = [vk::RayTracingPipelineCreateInfoKHR::default()
            .stages(&stages)
            .groups(&groups)
            .max_pipeline_ray_recursion_depth(1)
            .layout(self.rec.layout)];
        // SAFETY: valid device and layout; stages, groups and modules outlive the call.
        let created = unsafe {
            rt.create_ray_tracing_pipelines(
                vk::DeferredOperationKHR::null(),
                vk::PipelineCache::null(),
                &info,
                None,
            )
        };
        for m in modules {
            // SAFETY: modules are no longer needed once the pipeline exists (or failed).
            unsafe { dev.destroy_shader_module(m, None) };
        }
        self.rec.pipeline =
            created.map_err(|(_, e)| VulkanError::from_vk("vkCreateRayTracingPipelinesKHR", e))?[0];

        // Shader binding table: raygen | miss | hit, each region base-aligned; one record each.
        let group_count = groups.len() as u32;
        // SAFETY: the pipeline was created with `group_count` groups.
        let handles = unsafe {
            rt.get_ray_tracing_shader_group_handles(
                self.rec.pipeline,
                0,
                group_count,
                (handle_size * u64::from(group_count)) as usize,
            )
        }
        .op("vkGetRayTracingShaderGroupHandlesKHR")?;
        let stride = align_up(handle_size, handle_align);
        let region_size = align_up(stride, base_align);
        let base = align_up(self.sbt.address, base_align);
        let skip = (base - self.sbt.address) as usize;
        let hs = handle_size as usize;
        for g in 0..group_count as usize {
            let at = skip + g * region_size as usize;
            self.sbt.write(at, &handles[g * hs..(g + 1) * hs]);
        }
        let region = |g: u64, stride: u64| vk::StridedDeviceAddressRegionKHR {
            device_address: base + g * region_size,
            stride,
            size: stride,
        };
        // The raygen region's size must equal its stride, and that must be base-aligned.
        self.regions = [
            region(0, region_size),
            region(1, stride),
            region(2, stride),
            vk::StridedDeviceAddressRegionKHR::default(),
        ];

        self.sets = Some(SetRing::new(
            ctx,
            self.set_layout,
            &self.rec.bindings,
            name,
        )?);
        ctx.set_name(self.rec.pipeline, name);
        ctx.set_name(self.rec.layout, &format!("{name} layout"));
        ctx.set_name(self.set_layout, &format!("{name} set layout"));
        Ok(())
    }

    /// Binds `bound`, traces `width` x `height` x 1 raygen invocations with `push` constants, and
    /// waits. Returns the wall time in milliseconds (submit to completion).
    ///
    /// Writes of earlier submissions are visible to the shaders, and the shaders' writes are
    /// visible to the host before this returns.
    pub fn trace(
        &mut self,
        ctx: &VulkanContext,
        bound: &[Bound<'_>],
        push: &[u8],
        width: u32,
        height: u32,
    ) -> VkResult<f64> {
        let Some(rt) = ctx.ray_tracing_pipeline() else {
            return Err(VulkanError::Unsupported(
                "trace without VK_KHR_ray_tracing_pipeline".into(),
            ));
        };
        let [raygen, miss, hit, callable] = &self.regions;
        let sets = self.sets.as_ref().expect("a created pipeline has its sets");
        let pass = Pass {
            push,
            grid: [width, height, 1],
        };
        self.rec
            .run_blocking(ctx, "ray tracing", sets, bound, pass, |c, g| {
                // SAFETY: `c` is the trace's command buffer, recording outside a render pass,
                // with this pipeline and its set bound by `record_passes`; the SBT is valid.
                unsafe { rt.cmd_trace_rays(c, raygen, miss, hit, callable, g[0], g[1], g[2]) }
            })
    }

    /// Records `passes` (`grid` = rays, x/y/z) into `cmd` with one binding set `bound`, as
    /// [`ComputePipeline::record`](crate::backend::vulkan::ComputePipeline::record) does for
    /// compute: ordered after earlier work on the queue, each pass after the one before, and
    /// every write visible to the host once the frame completed. No wait.
    pub fn record(
        &mut self,
        ctx: &VulkanContext,
        cmd: &FrameCmd,
        bound: &[Bound<'_>],
        passes: &[Pass<'_>],
        timer: Option<PassTimer<'_>>,
    ) -> VkResult<()> {
        let Some(rt) = ctx.ray_tracing_pipeline() else {
            return Err(VulkanError::Unsupported(
                "record without VK_KHR_ray_tracing_pipeline".into(),
            ));
        };
        cmd.check(ctx)?;
        self.rec.check("record", bound, passes)?;
        check_timer(timer, passes.len())?;
        let set = self
            .sets
            .as_mut()
            .expect("a created pipeline has its sets")
            .acquire(ctx, cmd, &self.rec.bindings, bound)?;
        let [raygen, miss, hit, callable] = &self.regions;
        let dispatch = |c: vk::CommandBuffer, g: [u32; 3]| {
            // SAFETY: `c` is the frame's command buffer, recording outside a render pass, with
            // this pipeline and its set bound by `record_passes`.
            unsafe { rt.cmd_trace_rays(c, raygen, miss, hit, callable, g[0], g[1], g[2]) }
        };
        // SAFETY: a FrameCmd is recording outside a render pass (its constructor's contract);
        // pipeline, layout and set are valid, the set was written for this frame only; the
        // timer was checked, and reset by the caller.
        unsafe { record_passes(ctx, cmd.raw(), &self.rec, set, passes, timer, dispatch) };
        Ok(())
    }

    /// Destroys the pipeline and its SBT. The caller guarantees no trace is pending (trace waits).
    pub fn destroy(self, ctx: &VulkanContext) {
        // SAFETY: no pending work uses these objects; each is destroyed once; null handles
        // (from a failed creation) are ignored by vkDestroy*.
        unsafe { destroy_pipeline(ctx, self.rec.pipeline, self.rec.layout, self.set_layout) };
        if let Some(sets) = &self.sets {
            sets.destroy(ctx);
        }
        ctx.destroy_buffer(self.sbt);
    }
}
