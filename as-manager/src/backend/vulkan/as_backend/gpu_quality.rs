//! Refit quality of skinned BLASes posed on the GPU, measured on the GPU.
//!
//! A skinned BLAS refitted from the engine's buffer (`set_skinned_pose_device`) has no CPU
//! positions to judge it by. After its build and after each refit, a compute pass
//! (`shaders/refit_quality.comp`) reads the same positions the build read and writes the
//! metric of `crate::quality` (leaf boxes of 4 triangles, node boxes of 8 leaves, summed areas,
//! root box) as per-workgroup partials into the frame slot's readback buffer. When the frame
//! has completed, `read_quality` finishes the sums on the host: the metric after the build is
//! kept, and each refit's metric over it is reported through `take_refit_quality` (late by
//! the frames in flight, like compacted sizes).
//!
//! The triangle order is the index buffer's (fixed at build time; quality.rs sorts by Morton
//! code on the CPU, which needs the positions on the CPU). Meshes from asset pipelines are in
//! a spatially coherent order; what the ratio measures, boxes of triangles that were together
//! at the build growing apart, is the same.

use crate::backend::vulkan::device::pipeline::compute::create_compute_pipeline;

use super::*;
use crate::mesh::{DeviceVertices, IndexType, VertexFormat};

/// Workgroups (partials) per measured BLAS at most; each loops over its share of nodes.
pub(super) const GROUPS_PER_BLAS: u32 = 64;
/// Measured BLASes per frame at most (the readback buffer's capacity); the rest of a frame's
/// refits go unmeasured that frame.
pub(super) const MEASURED_PER_SLOT: u32 = 64;
/// Floats per partial.
const PARTIAL_FLOATS: u64 = 8;
/// Bytes of a slot's quality readback buffer.
pub(super) const QUALITY_BYTES: u64 =
    (GROUPS_PER_BLAS as u64) * (MEASURED_PER_SLOT as u64) * PARTIAL_FLOATS * 4;
/// Push constants: three addresses and four words.
const PUSH_BYTES: u32 = 40;

const SPIRV: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/refit_quality.comp.spv"));

/// The compute pipeline (push constants only, no descriptors), created at the first use.
#[derive(Debug)]
pub(super) struct QualityPipeline {
    raw: vk::Pipeline,
    layout: vk::PipelineLayout,
}

/// What a quality dispatch measured: after a build (the reference) or after a refit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Measured {
    Build,
    Refit,
}

/// A dispatch recorded in a slot, read when its frame completed.
#[derive(Debug, Clone, Copy)]
pub(super) struct QualityJob {
    pub blas: BlasHandle,
    /// The BLAS's build generation when recorded (a refit measured before a later rebuild
    /// is dropped).
    pub build_gen: u32,
    pub kind: Measured,
    /// First partial in the slot's buffer.
    pub first: u32,
    pub groups: u32,
}

/// A skinned BLAS's GPU quality bookkeeping.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct GpuQuality {
    /// Incremented by each build and rebuild.
    pub build_gen: u32,
    /// The metric measured after the build of `build_gen`, once read.
    pub built_metric: Option<f32>,
}

impl QualityPipeline {
    fn new(ctx: &VulkanContext) -> VkResult<Self> {
        let dev = &ctx.device;
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(vk::ShaderStageFlags::COMPUTE)
            .size(PUSH_BYTES)];
        // SAFETY: valid device; the create-info points to locals that outlive the call;
        // destroyed in `destroy` (or below on failure).
        let layout = unsafe {
            dev.create_pipeline_layout(
                &vk::PipelineLayoutCreateInfo::default().push_constant_ranges(&ranges),
                None,
            )
        }
        .op("vkCreatePipelineLayout")?;
        let raw = match create_compute_pipeline(ctx, layout, SPIRV, "refit quality") {
            Ok(p) => p,
            Err(e) => {
                // SAFETY: nothing uses the layout.
                unsafe { dev.destroy_pipeline_layout(layout, None) };
                return Err(e);
            }
        };
        ctx.set_name(raw, "refit quality");
        ctx.set_name(layout, "refit quality layout");
        Ok(Self { raw, layout })
    }

    /// Destroys the pipeline; no recorded dispatch may still be pending.
    pub(super) fn destroy(self, ctx: &VulkanContext) {
        // SAFETY: the caller waited for the device (backend drop); each object is destroyed once.
        unsafe {
            ctx.device.destroy_pipeline(self.raw, None);
            ctx.device.destroy_pipeline_layout(self.layout, None);
        }
    }
}

fn format_code(f: VertexFormat) -> u32 {
    match f {
        VertexFormat::F32x3 => 0,
        VertexFormat::F16x4 => 1,
        VertexFormat::Snorm16x4 => 2,
    }
}

/// The Vulkan format of a position format.
pub(super) fn vk_format(f: VertexFormat) -> vk::Format {
    match f {
        VertexFormat::F32x3 => vk::Format::R32G32B32_SFLOAT,
        VertexFormat::F16x4 => vk::Format::R16G16B16A16_SFLOAT,
        VertexFormat::Snorm16x4 => vk::Format::R16G16B16A16_SNORM,
    }
}

/// The Vulkan index type.
pub(super) fn vk_index(t: IndexType) -> vk::IndexType {
    match t {
        IndexType::U16 => vk::IndexType::UINT16,
        IndexType::U32 => vk::IndexType::UINT32,
    }
}

/// Where a measured BLAS's inputs are.
#[derive(Debug, Clone, Copy)]
pub(super) struct QualityInputs {
    pub vertices: DeviceVertices,
    pub index_address: u64,
    pub index_type: IndexType,
    pub triangles: u32,
}

impl VulkanBackend {
    /// [`record_quality`](Self::record_quality), advisory: a failure (no memory for the
    /// readback buffer, no pipeline) leaves the BLAS unmeasured this time and is logged.
    pub(super) fn measure_quality(
        &mut self,
        blas: BlasHandle,
        kind: Measured,
        inputs: QualityInputs,
    ) {
        if let Err(e) = self.record_quality(blas, kind, inputs) {
            tracing::warn!(?blas, "refit quality not measured: {e}");
        }
    }

    /// Records the quality pass of `blas` over `inputs` (after its build or refit, recorded
    /// before this into the frame). Does nothing when the slot's buffer is full this frame.
    pub(super) fn record_quality(
        &mut self,
        blas: BlasHandle,
        kind: Measured,
        inputs: QualityInputs,
    ) -> BackendResult<()> {
        let cmd = self.cmd()?;
        let Some(build_gen) = self
            .entry(blas)
            .and_then(|e| e.gpu_quality)
            .map(|q| q.build_gen)
        else {
            return Ok(());
        };
        if self.slots[self.current].quality_jobs.len() as u32 >= MEASURED_PER_SLOT {
            return Ok(());
        }
        if self.quality_pipeline.is_none() {
            self.quality_pipeline = Some(QualityPipeline::new(&self.ctx).map_err(backend_err)?);
        }
        if self.slots[self.current].quality.is_none() {
            let b = self.create_buffer(
                BufferDesc {
                    name: "slot refit quality partials",
                    size: QUALITY_BYTES,
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER
                        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
                    memory: MemoryKind::Readback,
                },
                false,
            )?;
            self.slots[self.current].quality = Some(b);
        }
        let nodes = inputs.triangles.div_ceil(32);
        let groups = nodes.clamp(1, GROUPS_PER_BLAS);
        let s = &mut self.slots[self.current];
        let first = s.quality_jobs.len() as u32 * GROUPS_PER_BLAS;
        let out = s.quality.as_ref().expect("created above").address
            + u64::from(first) * PARTIAL_FLOATS * 4;
        s.quality_jobs.push(QualityJob {
            blas,
            build_gen,
            kind,
            first,
            groups,
        });
        let mut push = Vec::with_capacity(PUSH_BYTES as usize);
        push.extend_from_slice(&inputs.vertices.address.to_le_bytes());
        push.extend_from_slice(&inputs.index_address.to_le_bytes());
        push.extend_from_slice(&out.to_le_bytes());
        push.extend_from_slice(&(inputs.vertices.stride as u32).to_le_bytes());
        push.extend_from_slice(&format_code(inputs.vertices.format).to_le_bytes());
        let it: u32 = match inputs.index_type {
            IndexType::U16 => 0,
            IndexType::U32 => 1,
        };
        push.extend_from_slice(&it.to_le_bytes());
        push.extend_from_slice(&inputs.triangles.to_le_bytes());
        let p = self.quality_pipeline.as_ref().expect("created above");
        // SAFETY: recording outside a render pass; the pipeline and its layout live until the
        // backend drops (after a device wait); the shader reads the inputs the build just read
        // (the engine keeps them alive for the frame) and writes its own range of the slot's
        // readback buffer, which the host reads only after the frame completed. The frame
        // start's barrier orders earlier writes of the inputs and of this buffer before it.
        unsafe {
            let dev = &self.ctx.device;
            dev.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, p.raw);
            dev.cmd_push_constants(cmd, p.layout, vk::ShaderStageFlags::COMPUTE, 0, &push);
            dev.cmd_dispatch(cmd, groups, 1, 1);
        }
        Ok(())
    }

    /// Finishes the quality partials of a completed slot: records build metrics, reports
    /// refit ratios.
    pub(super) fn read_quality(&mut self, slot: usize) {
        let jobs = std::mem::take(&mut self.slots[slot].quality_jobs);
        if jobs.is_empty() {
            return;
        }
        let metrics: Vec<f32> = {
            let Some(buf) = self.slots[slot].quality.as_ref() else {
                return;
            };
            let floats: &[f32] = bytemuck::cast_slice(buf.mapped().expect("readback is mapped"));
            jobs.iter()
                .map(|j| {
                    let mut sum = 0.0f64;
                    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
                    for g in 0..j.groups {
                        let at = ((j.first + g) as u64 * PARTIAL_FLOATS) as usize;
                        let p = &floats[at..at + PARTIAL_FLOATS as usize];
                        sum += f64::from(p[0]);
                        for k in 0..3 {
                            lo[k] = lo[k].min(p[1 + k]);
                            hi[k] = hi[k].max(p[4 + k]);
                        }
                    }
                    let d = [0, 1, 2].map(|k| f64::from((hi[k] - lo[k]).max(0.0)));
                    let root = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]);
                    if root > 0.0 {
                        (sum / root) as f32
                    } else {
                        0.0
                    }
                })
                .collect()
        };
        for (j, m) in jobs.into_iter().zip(metrics) {
            let Some(e) = self.blases.get_mut(key_of(j.blas)) else {
                continue;
            };
            let Some(q) = e.gpu_quality.as_mut() else {
                continue;
            };
            if q.build_gen != j.build_gen {
                continue; // measured before a later rebuild
            }
            match j.kind {
                Measured::Build => q.built_metric = Some(m),
                Measured::Refit => {
                    if let Some(b) = q.built_metric {
                        let ratio = if b > 0.0 { m / b } else { 1.0 };
                        self.quality_reports.push((j.blas, ratio));
                        self.counters.gpu_quality_reports += 1;
                    }
                }
            }
        }
    }
}
