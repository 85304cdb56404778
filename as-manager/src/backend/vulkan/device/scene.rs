//! A static scene: every mesh's BLAS built in one batch, and a TLAS over given instances.
//!
//! This is the "build everything" path on the device layer: the thin slice, and the renderer's
//! reference scenes (`renderer::TracedScene`: every instance, finest LOD, no culling). The
//! managed path goes through the manager's backend trait.

use std::time::Instant;

use ash::vk;

use crate::backend::vulkan::device::accel::{
    class_flags, AccelStruct, TriangleGeometry, BUILD_INPUT_USAGE,
};
use crate::backend::vulkan::device::buffer::GpuBuffer;
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::device::geometry::{GpuGeometry, SceneMesh};
use crate::backend::vulkan::device::tlas_ref::TlasRef;
use crate::backend::vulkan::error::{caller_index, VkResult, VulkanError};
use crate::backend::BlasClass;
use crate::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};

/// A placement of a mesh in a [`StaticScene`] (its TLAS record); not the manager's
/// `InstanceDesc`, which registers a managed instance.
#[derive(Debug, Clone, Copy)]
pub struct StaticInstance {
    /// Index into the scene's meshes.
    pub mesh: u32,
    /// Column-major object-to-world transform.
    pub transform: [f32; 16],
    /// customIndex (24 bits): what shaders use to find per-instance data.
    pub custom_index: u32,
    /// Visibility mask.
    pub mask: u8,
}

/// A mesh on the GPU: its buffers and its BLAS.
#[derive(Debug)]
pub struct GpuMesh {
    /// Vertex and index buffers.
    pub geometry: GpuGeometry,
    /// The BLAS.
    pub blas: AccelStruct,
}

/// Sizes and time of a static scene build.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SceneBuildStats {
    /// BLAS count.
    pub blas_count: u32,
    /// Triangles over all BLASes.
    pub triangles: u64,
    /// Sum of BLAS storage sizes (vkGetAccelerationStructureBuildSizesKHR).
    pub blas_bytes: u64,
    /// Sum of BLAS build scratch sizes.
    pub blas_scratch_bytes: u64,
    /// TLAS storage size.
    pub tlas_bytes: u64,
    /// TLAS build scratch size.
    pub tlas_scratch_bytes: u64,
    /// Wall time of the whole build (upload, BLAS batch, TLAS), milliseconds.
    pub build_ms: f64,
}

/// Every mesh with its BLAS, and a TLAS over the instances.
#[derive(Debug)]
pub struct StaticScene {
    /// The meshes, in the order given.
    pub meshes: Vec<GpuMesh>,
    /// The TLAS (trace it through [`StaticScene::tlas_ref`]).
    pub tlas: AccelStruct,
    /// The ref of `tlas` as built here.
    tlas_ref: TlasRef,
    instance_buffer: GpuBuffer,
    /// What the build took.
    pub stats: SceneBuildStats,
}

impl StaticScene {
    /// Uploads the meshes, builds all BLASes in one command (the backend's static flags,
    /// [`class_flags`]`(BlasClass::Static)`; opaque where marked) and a PREFER_FAST_TRACE TLAS
    /// over `instances` (opaque instances get FORCE_OPAQUE).
    pub fn build(
        ctx: &VulkanContext,
        meshes: &[SceneMesh<'_>],
        instances: &[StaticInstance],
    ) -> VkResult<Self> {
        Self::build_with_tlas_flags(
            ctx,
            meshes,
            instances,
            vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
        )
    }

    /// As [`StaticScene::build`], with the TLAS built with `tlas_flags`.
    pub fn build_with_tlas_flags(
        ctx: &VulkanContext,
        meshes: &[SceneMesh<'_>],
        instances: &[StaticInstance],
        tlas_flags: vk::BuildAccelerationStructureFlagsKHR,
    ) -> VkResult<Self> {
        let start = Instant::now();
        let mut built: Vec<GpuMesh> = Vec::with_capacity(meshes.len());
        let result = Self::build_inner(ctx, meshes, instances, tlas_flags, &mut built);
        match result {
            Ok((tlas, instance_buffer, mut stats)) => {
                stats.build_ms = start.elapsed().as_secs_f64() * 1e3;
                tracing::debug!(?stats, "static scene built");
                // Created TOP_LEVEL on `ctx` and built just now: a broken invariant otherwise.
                let tlas_ref = ctx
                    .tlas_ref(&tlas)
                    .expect("a static scene's TLAS is a live TLAS of its context");
                Ok(Self {
                    meshes: built,
                    tlas,
                    tlas_ref,
                    instance_buffer,
                    stats,
                })
            }
            Err(e) => {
                for m in built {
                    destroy_mesh(ctx, m);
                }
                Err(e)
            }
        }
    }

    fn build_inner(
        ctx: &VulkanContext,
        meshes: &[SceneMesh<'_>],
        instances: &[StaticInstance],
        tlas_flags: vk::BuildAccelerationStructureFlagsKHR,
        built: &mut Vec<GpuMesh>,
    ) -> VkResult<(AccelStruct, GpuBuffer, SceneBuildStats)> {
        let flags = class_flags(BlasClass::Static);
        let mut stats = SceneBuildStats::default();
        let mut uploaded: Vec<GpuGeometry> = Vec::with_capacity(meshes.len());
        for m in meshes {
            match GpuGeometry::upload(ctx, m) {
                Ok(g) => uploaded.push(g),
                Err(e) => {
                    uploaded.into_iter().for_each(|g| g.destroy(ctx));
                    return Err(e);
                }
            }
        }
        let geoms: Vec<TriangleGeometry> = uploaded.iter().map(|g| g.geometry).collect();
        let lists: Vec<&[TriangleGeometry]> = geoms.iter().map(std::slice::from_ref).collect();
        let mut batch =
            match ctx.plan_blas_batch(&lists, flags, |i| format!("{} BLAS", meshes[i].name)) {
                Ok(b) => b,
                Err(e) => {
                    uploaded.into_iter().for_each(|g| g.destroy(ctx));
                    return Err(e);
                }
            };
        for (g, sizes) in geoms.iter().zip(&batch.sizes) {
            stats.blas_count += 1;
            stats.triangles += u64::from(g.triangle_count);
            stats.blas_bytes += sizes.storage;
            stats.blas_scratch_bytes += sizes.build_scratch;
        }
        // Scratch offsets from 0; the buffer's base is added once it exists (with the TLAS's
        // range at the end of the same layout).
        let mut builds = batch.inputs(&lists, flags, 0);
        let mut scratch_layout = std::mem::take(&mut batch.scratch);
        built.extend(
            uploaded
                .into_iter()
                .zip(std::mem::take(&mut batch.accels))
                .map(|(geometry, blas)| GpuMesh { geometry, blas }),
        );

        let mut records = Vec::with_capacity(instances.len());
        for (i, inst) in instances.iter().enumerate() {
            let mesh = caller_index(built, inst.mesh as usize, |n| {
                format!("instance {i} names mesh {} of {n}", inst.mesh)
            })?;
            if !inst.transform.iter().all(|v| v.is_finite()) {
                return Err(VulkanError::Unsupported(format!(
                    "instance {i} has a non-finite transform"
                )));
            }
            let opaque = meshes[inst.mesh as usize].opaque;
            let transform = glam::Affine3A::from_mat4(glam::Mat4::from_cols_array(&inst.transform));
            records.push(TlasInstance::new(
                &transform,
                inst.custom_index,
                inst.mask,
                0,
                if opaque { INSTANCE_FORCE_OPAQUE } else { 0 },
                mesh.blas.address,
            ));
        }
        let tlas_sizes = ctx.tlas_sizes(records.len() as u32, tlas_flags);
        stats.tlas_bytes = tlas_sizes.storage;
        stats.tlas_scratch_bytes = tlas_sizes.build_scratch;
        let instance_buffer = ctx.create_buffer_with_data(
            "static scene instances",
            BUILD_INPUT_USAGE,
            bytemuck::cast_slice(&records),
        )?;
        let tlas = match ctx.create_accel(
            vk::AccelerationStructureTypeKHR::TOP_LEVEL,
            tlas_sizes.storage,
            "static scene TLAS",
        ) {
            Ok(t) => t,
            Err(e) => {
                ctx.destroy_buffer(instance_buffer);
                return Err(e);
            }
        };
        let tlas_scratch_offset = scratch_layout.push(tlas_sizes.build_scratch);
        let (scratch, base) =
            match ctx.create_scratch("static scene scratch", scratch_layout.total()) {
                Ok(s) => s,
                Err(e) => {
                    ctx.destroy_accel(tlas);
                    ctx.destroy_buffer(instance_buffer);
                    return Err(e);
                }
            };
        for b in &mut builds {
            b.scratch_address += base;
        }
        let recorded = ctx.submit_and_wait("static scene build", |_, cmd| {
            // SAFETY: every buffer referenced lives until submit_and_wait returns; scratch ranges
            // are disjoint and aligned; the barrier orders BLAS writes before the TLAS build.
            unsafe {
                ctx.cmd_build_blases(cmd, &builds);
                ctx.cmd_accel_barrier(cmd);
                ctx.cmd_build_tlas(
                    cmd,
                    tlas.raw,
                    None,
                    tlas_flags,
                    instance_buffer.address,
                    records.len() as u32,
                    base + tlas_scratch_offset,
                );
                ctx.cmd_accel_barrier(cmd);
            }
        });
        ctx.destroy_buffer(scratch);
        if let Err(e) = recorded {
            ctx.destroy_accel(tlas);
            ctx.destroy_buffer(instance_buffer);
            return Err(e);
        }
        Ok((tlas, instance_buffer, stats))
    }

    /// The scene's TLAS as the renderer traces it. Stale once the scene is destroyed, or once
    /// `tlas` is built again by someone else (then take [`VulkanContext::tlas_ref`] of it).
    pub fn tlas_ref(&self) -> TlasRef {
        self.tlas_ref
    }

    /// Destroys every GPU object of the scene. The caller guarantees the GPU is done with it.
    pub fn destroy(self, ctx: &VulkanContext) {
        for m in self.meshes {
            destroy_mesh(ctx, m);
        }
        ctx.destroy_accel(self.tlas);
        ctx.destroy_buffer(self.instance_buffer);
    }
}

fn destroy_mesh(ctx: &VulkanContext, m: GpuMesh) {
    ctx.destroy_accel(m.blas);
    m.geometry.destroy(ctx);
}
