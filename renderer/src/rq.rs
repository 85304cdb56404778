//! The ray-query renderer: a compute shader that traces a TLAS (GL_EXT_ray_query).

use std::sync::Arc;

use glam::Vec3;
use rtstream_as_manager::backend::vulkan::{
    ash::vk, BindingKind, Bound, BufferDesc, ComputePipeline, GpuBuffer, MemoryKind, VulkanContext,
};

use crate::camera::Camera;
use crate::error::{RenderError, Result};
use crate::frame::{Frame, PixelHit};

const TRACE_SPV: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/trace.comp.spv"));

/// Per-instance shading data, indexed by the instance's customIndex.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct InstanceShading {
    /// Device address of the mesh's `[f32; 3]` positions (0: shade with a view-facing normal).
    pub vertices: u64,
    /// Device address of the mesh's `u32` triangle indices (0 as above).
    pub indices: u64,
    /// Linear RGBA base colour.
    pub base_color: [f32; 4],
}

/// What to render.
#[derive(Debug, Clone, Copy)]
pub struct RenderDesc {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// The camera.
    pub camera: Camera,
    /// Direction toward the sun (need not be unit).
    pub sun_dir: Vec3,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Push {
    origin: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    forward: [f32; 4],
    sun: [f32; 4],
    size: [u32; 4],
}

/// The ray-query renderer. Borrows the manager's Vulkan context.
#[derive(Debug)]
pub struct RqRenderer {
    ctx: Arc<VulkanContext>,
    pipeline: Option<ComputePipeline>,
}

impl RqRenderer {
    /// Creates the pipeline. Fails with [`RenderError::NoRayQuery`] on devices without ray queries.
    pub fn new(ctx: Arc<VulkanContext>) -> Result<Self> {
        if !ctx.info().ray_query {
            return Err(RenderError::NoRayQuery(ctx.info().name.clone()));
        }
        let pipeline = ComputePipeline::new(
            &ctx,
            "rq trace",
            TRACE_SPV,
            &[
                BindingKind::AccelStruct,
                BindingKind::StorageBuffer,
                BindingKind::StorageBuffer,
                BindingKind::StorageBuffer,
            ],
            std::mem::size_of::<Push>() as u32,
        )?;
        Ok(Self {
            ctx,
            pipeline: Some(pipeline),
        })
    }

    /// Traces `tlas` and returns the frame. `instances[customIndex]` shades each hit.
    pub fn render(
        &mut self,
        tlas: vk::AccelerationStructureKHR,
        instances: &[InstanceShading],
        desc: &RenderDesc,
    ) -> Result<Frame> {
        let (w, h) = (desc.width, desc.height);
        if w == 0 || h == 0 || u64::from(w) * u64::from(h) > 1 << 26 {
            return Err(RenderError::InvalidRequest(format!("image size {w}x{h}")));
        }
        let pixels = u64::from(w) * u64::from(h);
        let ctx = &*self.ctx;
        let mut bufs: Vec<GpuBuffer> = Vec::with_capacity(3);
        let result = (|| {
            bufs.push(ctx.create_buffer(&BufferDesc {
                name: "rq color",
                size: pixels * 4,
                usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                memory: MemoryKind::Readback,
            })?);
            bufs.push(ctx.create_buffer(&BufferDesc {
                name: "rq hits",
                size: pixels * 16,
                usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                memory: MemoryKind::Readback,
            })?);
            let fallback = [InstanceShading {
                vertices: 0,
                indices: 0,
                base_color: [0.8; 4],
            }];
            let inst = if instances.is_empty() {
                &fallback[..]
            } else {
                instances
            };
            bufs.push(ctx.create_buffer_with_data(
                "rq instances",
                vk::BufferUsageFlags::STORAGE_BUFFER,
                bytemuck::cast_slice(inst),
            )?);
            let (r, u, f) = desc.camera.basis();
            let p = desc.camera.position;
            let s = desc.sun_dir.normalize_or(Vec3::Y);
            let push = Push {
                origin: [p.x, p.y, p.z, (desc.camera.fov_y * 0.5).tan()],
                right: [r.x, r.y, r.z, w as f32 / h as f32],
                up: [u.x, u.y, u.z, 0.0],
                forward: [f.x, f.y, f.z, 0.0],
                sun: [s.x, s.y, s.z, 0.0],
                size: [w, h, 0, 0],
            };
            let pipeline = self.pipeline.as_mut().expect("pipeline lives until drop");
            let ms = pipeline.dispatch(
                ctx,
                &[
                    Bound::AccelRaw(tlas),
                    Bound::Buffer(&bufs[0]),
                    Bound::Buffer(&bufs[1]),
                    Bound::Buffer(&bufs[2]),
                ],
                bytemuck::bytes_of(&push),
                [w.div_ceil(8), h.div_ceil(8), 1],
            )?;
            let color: Vec<[u8; 4]> =
                bytemuck::cast_slice(bufs[0].mapped().expect("readback is mapped")).to_vec();
            let hits: Vec<PixelHit> =
                bytemuck::cast_slice(bufs[1].mapped().expect("readback is mapped")).to_vec();
            Ok(Frame {
                width: w,
                height: h,
                color,
                hits,
                render_ms: ms,
            })
        })();
        for b in bufs {
            ctx.destroy_buffer(b);
        }
        result
    }
}

impl Drop for RqRenderer {
    fn drop(&mut self) {
        if let Some(p) = self.pipeline.take() {
            p.destroy(&self.ctx);
        }
    }
}
