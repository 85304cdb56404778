//! The renderer: primary visibility, sun shadows (hard or soft) and ambient occlusion, traced
//! through either a ray-query compute shader or a ray-tracing pipeline. Both run the same pass
//! code (`shaders/passes.glsl`); only the two trace functions differ.

use std::sync::Arc;

use glam::Vec3;
use rtstream_as_manager::backend::vulkan::{
    ash::vk, BindingKind, Bound, BufferDesc, ComputePipeline, GpuBuffer, MemoryKind,
    RayTracingPipeline, RtShaders, TlasRef, VulkanContext,
};

use crate::camera::Camera;
use crate::error::{RenderError, Result};
use crate::frame::{Frame, PassStats, PixelHit};

const TRACE_COMP: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/trace.comp.spv"));
const TRACE_RGEN: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/trace.rgen.spv"));
const TRACE_RMISS: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/trace.rmiss.spv"));
const TRACE_RCHIT: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/trace.rchit.spv"));

/// Descriptor bindings of both paths: TLAS, colour, hits, instances, surface, light.
pub(crate) const BINDINGS: [BindingKind; 6] = [
    BindingKind::AccelStruct,
    BindingKind::StorageBuffer,
    BindingKind::StorageBuffer,
    BindingKind::StorageBuffer,
    BindingKind::StorageBuffer,
    BindingKind::StorageBuffer,
];

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

impl InstanceShading {
    /// An entry shaded by its colour alone, with a view-facing normal (no geometry to read):
    /// what a table holds for instances whose mesh buffers it does not know.
    pub const fn colour_only(base_color: [f32; 4]) -> Self {
        Self {
            vertices: 0,
            indices: 0,
            base_color,
        }
    }
}

/// The shading table of a frame given no instances: one grey, view-facing entry, so the
/// shaders always have a table to read.
const NO_INSTANCES: [InstanceShading; 1] = [InstanceShading::colour_only([0.8; 4])];

/// `instances`, or the one-entry fallback table when there are none.
pub(crate) fn shading_table(instances: &[InstanceShading]) -> &[InstanceShading] {
    if instances.is_empty() {
        &NO_INSTANCES
    } else {
        instances
    }
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
    /// Angular radius of the sun disk in radians; 0 gives hard shadows (one ray per pixel).
    pub sun_radius: f32,
    /// Shadow rays per pixel toward the sun disk when `sun_radius > 0` (R2 low-discrepancy
    /// points, rotated per pixel).
    pub shadow_samples: u32,
    /// Ambient-occlusion rays per pixel (cosine-weighted); 0 turns the AO pass off.
    pub ao_samples: u32,
    /// Length of the ambient-occlusion rays (world units).
    pub ao_radius: f32,
    /// Seed of the per-pixel sample rotation (vary it per frame to accumulate).
    pub seed: u32,
    /// Device address of the TLAS's primitive-base table (one `u32` per record: the first
    /// primitive of a split mesh's part), or 0 when no record is a part. From
    /// `VulkanBackend::primitive_bases`; without it, hits on parts after the first report
    /// part-relative primitives and shade the wrong triangles.
    pub primitive_bases: u64,
}

impl RenderDesc {
    /// A `width` x `height` frame of `camera` with the default lighting: a sun from above and
    /// to the side, hard shadows, one AO ray of length 1.
    pub fn new(width: u32, height: u32, camera: Camera) -> Self {
        Self {
            width,
            height,
            camera,
            sun_dir: Vec3::new(0.4, 1.0, 0.3),
            sun_radius: 0.0,
            shadow_samples: 1,
            ao_samples: 1,
            ao_radius: 1.0,
            seed: 0,
            primitive_bases: 0,
        }
    }
}

/// Which tracing path a [`Renderer`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RenderPath {
    /// Compute shader with GL_EXT_ray_query (lavapipe, most GPUs).
    RayQuery,
    /// Ray-tracing pipeline (raygen + miss + closest-hit), for devices without ray queries.
    RayTracingPipeline,
}

impl RenderPath {
    /// The path for a device: ray queries when available, else the ray-tracing pipeline.
    pub fn for_device(ctx: &VulkanContext) -> Result<Self> {
        let info = ctx.info();
        Self::choose(info.ray_query, info.ray_tracing_pipeline)
            .ok_or_else(|| RenderError::NoRayTracing(info.name.clone()))
    }

    /// The choice behind [`for_device`](Self::for_device), from the two extension flags.
    pub fn choose(ray_query: bool, ray_tracing_pipeline: bool) -> Option<Self> {
        if ray_query {
            Some(Self::RayQuery)
        } else if ray_tracing_pipeline {
            Some(Self::RayTracingPipeline)
        } else {
            None
        }
    }
}

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct Push {
    origin: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    forward: [f32; 4],
    sun: [f32; 4],
    pub(crate) size: [u32; 4],
    extra: [u32; 4],
}

#[derive(Debug)]
pub(crate) enum Tracer {
    Query(ComputePipeline),
    Pipeline(RayTracingPipeline),
}

/// The renderer. Borrows the manager's Vulkan context; traces any TLAS handed to
/// [`render`](Self::render).
#[derive(Debug)]
pub struct Renderer {
    pub(crate) ctx: Arc<VulkanContext>,
    pub(crate) tracer: Option<Tracer>,
    /// Per-frame resources of recorded frames ([`record`](Self::record)).
    pub(crate) slots: Vec<crate::slot::RenderSlot>,
    /// The shading table's versions as recorded (`record_update`).
    pub(crate) chain: crate::shading::TableChain,
    /// Shading entries the last recorded frame wrote.
    pub(crate) table_written: usize,
    /// Shading entries each recorded frame's instance buffer holds at least
    /// ([`reserve_shading`](Self::reserve_shading)).
    pub(crate) reserved_entries: usize,
}

impl Renderer {
    /// Creates the renderer on the device's best path ([`RenderPath::for_device`]).
    pub fn new(ctx: Arc<VulkanContext>) -> Result<Self> {
        let path = RenderPath::for_device(&ctx)?;
        Self::with_path(ctx, path)
    }

    /// Creates the renderer on a chosen path (e.g. to test the ray-tracing pipeline on a device
    /// that also has ray queries).
    pub fn with_path(ctx: Arc<VulkanContext>, path: RenderPath) -> Result<Self> {
        let push = std::mem::size_of::<Push>() as u32;
        let tracer = match path {
            RenderPath::RayQuery => {
                if !ctx.info().ray_query {
                    return Err(RenderError::NoRayQuery(ctx.info().name.clone()));
                }
                Tracer::Query(ComputePipeline::new(
                    &ctx, "rq trace", TRACE_COMP, &BINDINGS, push,
                )?)
            }
            RenderPath::RayTracingPipeline => {
                if !ctx.info().ray_tracing_pipeline {
                    return Err(RenderError::NoRayTracing(ctx.info().name.clone()));
                }
                Tracer::Pipeline(RayTracingPipeline::new(
                    &ctx,
                    "rt trace",
                    &RtShaders {
                        raygen: TRACE_RGEN,
                        miss: TRACE_RMISS,
                        closest_hit: TRACE_RCHIT,
                    },
                    &BINDINGS,
                    push,
                )?)
            }
        };
        Ok(Self {
            ctx,
            tracer: Some(tracer),
            slots: Vec::new(),
            chain: Default::default(),
            table_written: 0,
            reserved_entries: 0,
        })
    }

    /// The path this renderer traces with.
    pub fn path(&self) -> RenderPath {
        match self.tracer {
            Some(Tracer::Pipeline(_)) => RenderPath::RayTracingPipeline,
            _ => RenderPath::RayQuery,
        }
    }

    /// Traces `tlas` and returns the frame. `instances[customIndex]` shades each hit (a hit
    /// whose customIndex is out of range is shaded magenta with a view-facing normal).
    ///
    /// Fails with [`RenderError::InvalidRequest`] when `tlas` is not live on the renderer's
    /// device: destroyed, another device's, or stale (its TLAS was destroyed or built again,
    /// and a newer TLAS or build now has that handle value; see [`TlasRef`]).
    ///
    /// Runs three passes, each its own submission so each can be timed: primary, shadow, AO +
    /// shading.
    pub fn render(
        &mut self,
        tlas: TlasRef,
        instances: &[InstanceShading],
        desc: &RenderDesc,
    ) -> Result<Frame> {
        validate(desc)?;
        check_tlas(&self.ctx, tlas)?;
        let (w, h) = (desc.width, desc.height);
        let pixels = u64::from(w) * u64::from(h);
        let ctx = &*self.ctx;
        let mut bufs: Vec<GpuBuffer> = Vec::with_capacity(5);
        let result = (|| {
            for (name, bytes_per_pixel) in [
                ("render color", 4),
                ("render hits", 16),
                ("render surface", 16),
                ("render light", 16),
            ] {
                bufs.push(ctx.create_buffer(&BufferDesc {
                    name,
                    size: pixels * bytes_per_pixel,
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                    memory: MemoryKind::Readback,
                })?);
            }
            bufs.push(ctx.create_buffer_with_data(
                "render instances",
                vk::BufferUsageFlags::STORAGE_BUFFER,
                bytemuck::cast_slice(shading_table(instances)),
            )?);
            let mut push = push_constants(desc);
            let bound = [
                Bound::AccelRaw(tlas.raw()),
                Bound::Buffer(&bufs[0]),
                Bound::Buffer(&bufs[1]),
                Bound::Buffer(&bufs[4]),
                Bound::Buffer(&bufs[2]),
                Bound::Buffer(&bufs[3]),
            ];
            let mut ms = [0.0f64; 3];
            for (pass, ms) in ms.iter_mut().enumerate() {
                push.size[2] = pass as u32;
                *ms = match self.tracer.as_mut().expect("tracer lives until drop") {
                    Tracer::Query(p) => p.dispatch(
                        ctx,
                        &bound,
                        bytemuck::bytes_of(&push),
                        [w.div_ceil(8), h.div_ceil(8), 1],
                    )?,
                    Tracer::Pipeline(p) => p.trace(ctx, &bound, bytemuck::bytes_of(&push), w, h)?,
                };
            }
            Ok(read_frame(
                w,
                h,
                [&bufs[0], &bufs[1], &bufs[2], &bufs[3]],
                ms,
            ))
        })();
        for b in bufs {
            ctx.destroy_buffer(b);
        }
        result
    }
}

/// A frame from the passes' readback buffers (colour, hits, surface, light) and the passes'
/// milliseconds.
pub(crate) fn read_frame(w: u32, h: u32, bufs: [&GpuBuffer; 4], ms: [f64; 3]) -> Frame {
    let pixels = u64::from(w) * u64::from(h);
    let n = pixels as usize;
    let color: Vec<[u8; 4]> =
        bytemuck::cast_slice(bufs[0].mapped().expect("readback is mapped"))[..n].to_vec();
    let hits: Vec<PixelHit> =
        bytemuck::cast_slice(bufs[1].mapped().expect("readback is mapped"))[..n].to_vec();
    let surf: &[[f32; 4]] = &bytemuck::cast_slice(bufs[2].mapped().expect("mapped"))[..n];
    let light: &[[f32; 4]] = &bytemuck::cast_slice(bufs[3].mapped().expect("mapped"))[..n];
    let normals = surf.iter().map(|n| [n[0], n[1], n[2]]).collect();
    let sun_visibility = light.iter().map(|l| l[0]).collect();
    let ambient = light.iter().map(|l| l[1]).collect();
    let shadow_rays = light.iter().map(|l| l[2] as u64).sum();
    let ao_rays = light
        .iter()
        .zip(&hits)
        .filter(|(_, h)| h.is_hit())
        .map(|(l, _)| l[3] as u64)
        .sum();
    Frame {
        width: w,
        height: h,
        color,
        hits,
        sun_visibility,
        ambient,
        normals,
        render_ms: ms.iter().sum(),
        passes: PassStats {
            primary_ms: ms[0],
            shadow_ms: ms[1],
            ao_shade_ms: ms[2],
            primary_rays: pixels,
            shadow_rays,
            ao_rays,
        },
    }
}

/// The most shadow or AO samples a pixel a request may ask for.
pub const MAX_SAMPLES: u32 = 1024;

/// The most pixels an image may have.
pub const MAX_PIXELS: u64 = 1 << 26;

/// The most pixels an image side may have: 65,535 workgroups of 8 pixels (every device's
/// minimum dispatch limit).
pub const MAX_SIDE: u32 = 65_535 * 8;

/// Whether the renderer takes an image of `width` x `height` pixels: at least 1x1, at most
/// [`MAX_SIDE`] a side and [`MAX_PIXELS`] in all (`InvalidRequest` otherwise). What every
/// render and record checks; callers may check a size up front with it.
pub fn check_size(width: u32, height: u32) -> Result<()> {
    let (w, h) = (width, height);
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE || u64::from(w) * u64::from(h) > MAX_PIXELS
    {
        return Err(RenderError::InvalidRequest(format!(
            "image size {w}x{h}: 1x1 to {MAX_SIDE} pixels a side, at most {MAX_PIXELS} pixels"
        )));
    }
    Ok(())
}

/// Checks what a render request asks for.
pub(crate) fn validate(desc: &RenderDesc) -> Result<()> {
    check_size(desc.width, desc.height)?;
    let c = &desc.camera;
    let finite = c.position.is_finite() && c.forward.is_finite() && c.up.is_finite();
    if !(finite && c.fov_y > 0.0 && c.fov_y < std::f32::consts::PI) {
        return Err(RenderError::InvalidRequest(format!("camera {c:?}")));
    }
    if desc.shadow_samples > MAX_SAMPLES || desc.ao_samples > MAX_SAMPLES {
        return Err(RenderError::InvalidRequest(format!(
            "{} shadow / {} AO samples a pixel (at most {MAX_SAMPLES})",
            desc.shadow_samples, desc.ao_samples
        )));
    }
    let sun_ok = (0.0..1.0).contains(&desc.sun_radius);
    let ao_ok = desc.ao_radius.is_finite() && desc.ao_radius > 0.0;
    if !(sun_ok && ao_ok) {
        return Err(RenderError::InvalidRequest(format!(
            "sun radius {} / AO radius {}",
            desc.sun_radius, desc.ao_radius
        )));
    }
    Ok(())
}

/// The passes' push constants (pass index 0 in `size[2]`).
pub(crate) fn push_constants(desc: &RenderDesc) -> Push {
    let (w, h) = (desc.width, desc.height);
    let (r, u, f) = desc.camera.basis();
    let p = desc.camera.position;
    let s = desc.sun_dir.normalize_or(Vec3::Y);
    Push {
        origin: [p.x, p.y, p.z, (desc.camera.fov_y * 0.5).tan()],
        right: [r.x, r.y, r.z, w as f32 / h as f32],
        up: [u.x, u.y, u.z, desc.ao_radius],
        forward: [f.x, f.y, f.z, desc.sun_radius],
        sun: [s.x, s.y, s.z, 0.0],
        size: [w, h, 0, desc.shadow_samples.max(1)],
        extra: [
            desc.ao_samples,
            desc.seed,
            desc.primitive_bases as u32,
            (desc.primitive_bases >> 32) as u32,
        ],
    }
}

impl Drop for Renderer {
    fn drop(&mut self) {
        // Frames recorded into an engine's command buffers may still run: the slots, the
        // pipeline and its descriptors go once the device has finished them.
        if let Err(e) = self.ctx.wait_idle() {
            tracing::warn!(error = %e, "Renderer drop: waiting for the device failed");
        }
        for s in std::mem::take(&mut self.slots) {
            s.destroy(&self.ctx);
        }
        match self.tracer.take() {
            Some(Tracer::Query(p)) => p.destroy(&self.ctx),
            Some(Tracer::Pipeline(p)) => p.destroy(&self.ctx),
            None => {}
        }
    }
}

/// Refuses a TLAS ref that is not live on `ctx`: destroyed or another device's (tracing one
/// reads freed memory), or stale (it would trace a newer TLAS that has its handle value, or
/// a later build of its slot). The message names the case.
pub(crate) fn check_tlas(ctx: &VulkanContext, tlas: TlasRef) -> Result<()> {
    if ctx.is_live_tlas(tlas) {
        return Ok(());
    }
    let (raw, serial) = (tlas.raw(), tlas.serial());
    let why = match ctx.live_tlas_serial(raw) {
        None if raw == vk::AccelerationStructureKHR::null() => "the null handle".to_string(),
        None => format!(
            "TLAS {raw:?} (serial {serial}) is not a live top-level acceleration structure of \
             this device: destroyed, or another device's"
        ),
        // Serials are process-wide and a live TLAS's only grows: a newer serial than the live
        // one of that handle value was never this device's.
        Some(live) if live < serial => format!(
            "TLAS {raw:?} (serial {serial}) is another device's: this device's TLAS with that \
             handle value is serial {live}"
        ),
        Some(live) => format!(
            "TLAS {raw:?} (serial {serial}) is stale: it was destroyed or built again since, \
             and a newer TLAS or build (serial {live}) now has that handle value"
        ),
    };
    Err(RenderError::InvalidRequest(why))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ray_queries_win_and_the_pipeline_is_the_fallback() {
        assert_eq!(RenderPath::choose(true, true), Some(RenderPath::RayQuery));
        assert_eq!(RenderPath::choose(true, false), Some(RenderPath::RayQuery));
        // The NVIDIA H100/H200 here: acceleration structures and RT pipelines, no ray queries.
        assert_eq!(
            RenderPath::choose(false, true),
            Some(RenderPath::RayTracingPipeline)
        );
        assert_eq!(RenderPath::choose(false, false), None);
    }

    #[test]
    fn push_constants_fit_the_guaranteed_128_bytes() {
        assert!(std::mem::size_of::<Push>() <= 128);
    }
}
