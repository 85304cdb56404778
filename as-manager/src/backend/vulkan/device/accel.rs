//! Acceleration structures: size queries, batched BLAS builds and TLAS builds, barriers.
//! Creating and destroying them is `accel_object.rs`.

use ash::vk;

pub use crate::backend::vulkan::device::accel_object::{
    AccelStorage, AccelStruct, ACCEL_STORAGE_USAGE,
};
use crate::backend::vulkan::device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::VkResult;
use crate::backend::BlasClass;

/// Usage of buffers read by acceleration-structure builds (vertices, indices, instances).
pub const BUILD_INPUT_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR.as_raw()
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::STORAGE_BUFFER.as_raw(),
);

/// Build flags of a BLAS of `class` with the backend's default preference for static ones
/// (see [`VulkanBackendDesc::static_blas_prefer`]): static BLASes PREFER_FAST_BUILD with
/// ALLOW_COMPACTION, skinned ones PREFER_FAST_BUILD with ALLOW_UPDATE.
///
/// [`VulkanBackendDesc::static_blas_prefer`]: crate::backend::vulkan::VulkanBackendDesc::static_blas_prefer
pub fn class_flags(class: BlasClass) -> vk::BuildAccelerationStructureFlagsKHR {
    flags_for(
        class,
        vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
    )
}

/// Build flags of a BLAS of `class`, static ones preferring `static_prefer`.
pub(crate) fn flags_for(
    class: BlasClass,
    static_prefer: vk::BuildAccelerationStructureFlagsKHR,
) -> vk::BuildAccelerationStructureFlagsKHR {
    match class {
        BlasClass::Static => {
            static_prefer | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION
        }
        BlasClass::Skinned => {
            vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD
                | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE
        }
    }
}

/// Rounds `v` up to a multiple of `align` (a power of two or any positive number).
pub fn align_up(v: u64, align: u64) -> u64 {
    v.div_ceil(align) * align
}

/// Scratch ranges laid out in one buffer: each at an offset aligned to the device's
/// `minAccelerationStructureScratchOffsetAlignment`, disjoint, so the builds of one batch need
/// no barrier between them. The one layout of every BLAS planner: [`BlasBatch`] (the static
/// scene, the benchmarks, compaction) and the backend's per-frame scratch arena.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ScratchLayout {
    align: u64,
    offsets: Vec<u64>,
    total: u64,
}

impl ScratchLayout {
    /// An empty layout for `align`-aligned offsets.
    pub fn new(align: u64) -> Self {
        Self {
            align: align.max(1),
            offsets: Vec::new(),
            total: 0,
        }
    }

    /// Adds a range of `bytes` (at least 1) and returns its offset.
    pub fn push(&mut self, bytes: u64) -> u64 {
        let at = self.total;
        self.offsets.push(at);
        self.total += align_up(bytes.max(1), self.align);
        at
    }

    /// Offsets, in push order.
    pub fn offsets(&self) -> &[u64] {
        &self.offsets
    }

    /// Bytes the layout spans.
    pub fn total(&self) -> u64 {
        self.total
    }

    /// Forgets every range (the arena's next frame).
    pub fn clear(&mut self) {
        self.offsets.clear();
        self.total = 0;
    }
}

/// BLAS builds planned together for one batched build: each geometry list's sizes and its
/// destination, and its scratch range in one [`ScratchLayout`]. Made by
/// [`VulkanContext::plan_blas_batch`] (all or nothing), turned into build inputs by
/// [`BlasBatch::inputs`].
#[derive(Debug)]
pub struct BlasBatch {
    /// The destinations, one per geometry list.
    pub accels: Vec<AccelStruct>,
    /// Their sizes.
    pub sizes: Vec<AsSizes>,
    /// Their scratch ranges (build scratch).
    pub scratch: ScratchLayout,
}

impl BlasBatch {
    /// The batch's build inputs over `geoms` (the lists it was planned for), with its scratch
    /// ranges in the buffer at `scratch_base`.
    pub fn inputs<'a>(
        &self,
        geoms: &[&'a [TriangleGeometry]],
        flags: vk::BuildAccelerationStructureFlagsKHR,
        scratch_base: vk::DeviceAddress,
    ) -> Vec<BlasBuildInput<'a>> {
        geoms
            .iter()
            .zip(&self.accels)
            .zip(self.scratch.offsets())
            .map(|((g, a), off)| BlasBuildInput {
                geometries: g,
                flags,
                dst: a.raw,
                update_from: None,
                scratch_address: scratch_base + off,
            })
            .collect()
    }

    /// Destroys the destinations (none was built, or the GPU is done with them).
    pub fn destroy(self, ctx: &VulkanContext) {
        for a in self.accels {
            ctx.destroy_accel(a);
        }
    }
}

/// One triangle geometry of a BLAS, by device address.
#[derive(Debug, Clone, Copy)]
pub struct TriangleGeometry {
    /// Address of the positions, `vertex_stride` apart.
    pub vertex_address: vk::DeviceAddress,
    /// Position format (`R32G32B32_SFLOAT`, `R16G16B16A16_SFLOAT` or `R16G16B16A16_SNORM`).
    pub vertex_format: vk::Format,
    /// Bytes between consecutive positions.
    pub vertex_stride: u64,
    /// Highest vertex index referenced.
    pub max_vertex: u32,
    /// Address of the triangle-list indices.
    pub index_address: vk::DeviceAddress,
    /// `UINT32` or `UINT16`.
    pub index_type: vk::IndexType,
    /// Number of triangles.
    pub triangle_count: u32,
    /// Mark the geometry opaque (no any-hit; what the seeds recommend for opaque materials).
    pub opaque: bool,
}

/// Sizes reported by vkGetAccelerationStructureBuildSizesKHR.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AsSizes {
    /// Bytes of acceleration-structure storage.
    pub storage: u64,
    /// Scratch bytes for a build.
    pub build_scratch: u64,
    /// Scratch bytes for an update (refit).
    pub update_scratch: u64,
}

fn triangles(g: &TriangleGeometry) -> vk::AccelerationStructureGeometryKHR<'static> {
    let data = vk::AccelerationStructureGeometryTrianglesDataKHR::default()
        .vertex_format(g.vertex_format)
        .vertex_data(vk::DeviceOrHostAddressConstKHR {
            device_address: g.vertex_address,
        })
        .vertex_stride(g.vertex_stride)
        .max_vertex(g.max_vertex)
        .index_type(g.index_type)
        .index_data(vk::DeviceOrHostAddressConstKHR {
            device_address: g.index_address,
        });
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::TRIANGLES)
        .geometry(vk::AccelerationStructureGeometryDataKHR { triangles: data })
        .flags(if g.opaque {
            vk::GeometryFlagsKHR::OPAQUE
        } else {
            vk::GeometryFlagsKHR::NO_DUPLICATE_ANY_HIT_INVOCATION
        })
}

fn instances_geometry(address: vk::DeviceAddress) -> vk::AccelerationStructureGeometryKHR<'static> {
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .geometry(vk::AccelerationStructureGeometryDataKHR {
            instances: vk::AccelerationStructureGeometryInstancesDataKHR::default()
                .array_of_pointers(false)
                .data(vk::DeviceOrHostAddressConstKHR {
                    device_address: address,
                }),
        })
}

/// One BLAS build (or refit) to record at the device level: handles and addresses. The backend
/// trait's [`crate::backend::BlasBuild`] is what the manager asks for; this is what gets recorded.
#[derive(Debug, Clone, Copy)]
pub struct BlasBuildInput<'a> {
    /// The geometries (one BLAS can hold several).
    pub geometries: &'a [TriangleGeometry],
    /// Build flags.
    pub flags: vk::BuildAccelerationStructureFlagsKHR,
    /// Destination.
    pub dst: vk::AccelerationStructureKHR,
    /// `Some(src)` for an update (refit; src may equal dst), `None` for a build.
    pub update_from: Option<vk::AccelerationStructureKHR>,
    /// Scratch address (a multiple of `minAccelerationStructureScratchOffsetAlignment`).
    pub scratch_address: vk::DeviceAddress,
}

/// A TLAS build to record beside BLAS builds in one call
/// ([`VulkanContext::cmd_build_blases_with_tlas`]).
#[derive(Debug, Clone, Copy)]
pub struct TlasBuildInput {
    /// Destination.
    pub dst: vk::AccelerationStructureKHR,
    /// Build flags.
    pub flags: vk::BuildAccelerationStructureFlagsKHR,
    /// The 64-byte instance records.
    pub instances_address: vk::DeviceAddress,
    /// How many records.
    pub instance_count: u32,
    /// Scratch address (aligned as a BLAS's).
    pub scratch_address: vk::DeviceAddress,
}

impl VulkanContext {
    /// Sizes of a BLAS over `geometries` with `flags`.
    pub fn blas_sizes(
        &self,
        geometries: &[TriangleGeometry],
        flags: vk::BuildAccelerationStructureFlagsKHR,
    ) -> AsSizes {
        let geoms: Vec<_> = geometries.iter().map(triangles).collect();
        let counts: Vec<u32> = geometries.iter().map(|g| g.triangle_count).collect();
        let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
            .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
            .flags(flags)
            .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
            .geometries(&geoms);
        self.sizes(&info, &counts)
    }

    /// Sizes of a TLAS over `instance_count` instances with `flags`.
    pub fn tlas_sizes(
        &self,
        instance_count: u32,
        flags: vk::BuildAccelerationStructureFlagsKHR,
    ) -> AsSizes {
        let geoms = [instances_geometry(0)];
        let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
            .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL)
            .flags(flags)
            .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
            .geometries(&geoms);
        self.sizes(&info, &[instance_count])
    }

    fn sizes(
        &self,
        info: &vk::AccelerationStructureBuildGeometryInfoKHR<'_>,
        counts: &[u32],
    ) -> AsSizes {
        let mut out = vk::AccelerationStructureBuildSizesInfoKHR::default();
        // SAFETY: info's geometry array and counts have the same length and live through the call.
        unsafe {
            self.accel.get_acceleration_structure_build_sizes(
                vk::AccelerationStructureBuildTypeKHR::DEVICE,
                info,
                counts,
                &mut out,
            )
        };
        AsSizes {
            storage: out.acceleration_structure_size,
            build_scratch: out.build_scratch_size,
            update_scratch: out.update_scratch_size,
        }
    }

    /// Plans one batched build of a BLAS per geometry list with `flags`: sizes each, creates
    /// its destination (named by `name(i)`) and lays out the scratch. All or nothing: on an
    /// error the destinations created so far are destroyed.
    pub fn plan_blas_batch(
        &self,
        geoms: &[&[TriangleGeometry]],
        flags: vk::BuildAccelerationStructureFlagsKHR,
        name: impl Fn(usize) -> String,
    ) -> VkResult<BlasBatch> {
        let mut batch = BlasBatch {
            accels: Vec::with_capacity(geoms.len()),
            sizes: Vec::with_capacity(geoms.len()),
            scratch: ScratchLayout::new(self.info().min_scratch_alignment),
        };
        for (i, g) in geoms.iter().enumerate() {
            let s = self.blas_sizes(g, flags);
            match self.create_accel(
                vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
                s.storage,
                &name(i),
            ) {
                Ok(a) => {
                    batch.accels.push(a);
                    batch.sizes.push(s);
                    batch.scratch.push(s.build_scratch);
                }
                Err(e) => {
                    batch.destroy(self);
                    return Err(e);
                }
            }
        }
        Ok(batch)
    }

    /// Records every BLAS build of `builds` in ONE vkCmdBuildAccelerationStructuresKHR.
    ///
    /// # Safety
    /// `cmd` is recording; every address and handle in `builds` is valid until the command
    /// completes, and the scratch ranges do not overlap.
    pub unsafe fn cmd_build_blases(&self, cmd: vk::CommandBuffer, builds: &[BlasBuildInput<'_>]) {
        // SAFETY: guaranteed by the caller.
        unsafe { self.cmd_build_blases_with_tlas(cmd, builds, None) }
    }

    /// Records the BLAS builds of `builds` and, when given, a TLAS build in ONE
    /// vkCmdBuildAccelerationStructuresKHR: the call implies no order between its builds, so
    /// the TLAS must reference none of the BLASes built beside it (they enter a later TLAS).
    ///
    /// # Safety
    /// As [`Self::cmd_build_blases`]; the TLAS's records reference BLASes built before this
    /// command, none of `builds`, and its scratch range overlaps none of theirs.
    pub unsafe fn cmd_build_blases_with_tlas(
        &self,
        cmd: vk::CommandBuffer,
        builds: &[BlasBuildInput<'_>],
        tlas: Option<&TlasBuildInput>,
    ) {
        if builds.is_empty() && tlas.is_none() {
            return;
        }
        let tlas_geoms = [instances_geometry(tlas.map_or(0, |t| t.instances_address))];
        let tlas_range = [vk::AccelerationStructureBuildRangeInfoKHR::default()
            .primitive_count(tlas.map_or(0, |t| t.instance_count))];
        let geoms: Vec<Vec<vk::AccelerationStructureGeometryKHR<'static>>> = builds
            .iter()
            .map(|b| b.geometries.iter().map(triangles).collect())
            .collect();
        let mut infos: Vec<_> = builds
            .iter()
            .zip(&geoms)
            .map(|(b, g)| {
                let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
                    .ty(vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL)
                    .flags(b.flags)
                    .dst_acceleration_structure(b.dst)
                    .geometries(g)
                    .scratch_data(vk::DeviceOrHostAddressKHR {
                        device_address: b.scratch_address,
                    });
                match b.update_from {
                    Some(src) => info
                        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
                        .src_acceleration_structure(src),
                    None => info.mode(vk::BuildAccelerationStructureModeKHR::BUILD),
                }
            })
            .collect();
        let ranges: Vec<Vec<vk::AccelerationStructureBuildRangeInfoKHR>> = builds
            .iter()
            .map(|b| {
                b.geometries
                    .iter()
                    .map(|g| {
                        vk::AccelerationStructureBuildRangeInfoKHR::default()
                            .primitive_count(g.triangle_count)
                    })
                    .collect()
            })
            .collect();
        let mut range_refs: Vec<&[vk::AccelerationStructureBuildRangeInfoKHR]> =
            ranges.iter().map(Vec::as_slice).collect();
        if let Some(t) = tlas {
            infos.push(
                vk::AccelerationStructureBuildGeometryInfoKHR::default()
                    .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL)
                    .flags(t.flags)
                    .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
                    .dst_acceleration_structure(t.dst)
                    .geometries(&tlas_geoms)
                    .scratch_data(vk::DeviceOrHostAddressKHR {
                        device_address: t.scratch_address,
                    }),
            );
            range_refs.push(&tlas_range);
        }
        // SAFETY: guaranteed by the caller; infos and ranges are parallel arrays.
        unsafe {
            self.accel
                .cmd_build_acceleration_structures(cmd, &infos, &range_refs)
        };
    }

    /// Records a TLAS build (or update) over `instance_count` records at `instances_address`.
    /// `dst` gets a new serial: [`TlasRef`](super::tlas_ref::TlasRef)s of its earlier contents
    /// are stale from now on (take a new one with [`VulkanContext::tlas_ref`]).
    ///
    /// # Safety
    /// As [`Self::cmd_build_blases`]; the instance buffer holds `instance_count` 64-byte records
    /// whose BLAS references are built before this command executes.
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn cmd_build_tlas(
        &self,
        cmd: vk::CommandBuffer,
        dst: vk::AccelerationStructureKHR,
        update_from: Option<vk::AccelerationStructureKHR>,
        flags: vk::BuildAccelerationStructureFlagsKHR,
        instances_address: vk::DeviceAddress,
        instance_count: u32,
        scratch_address: vk::DeviceAddress,
    ) {
        self.tlas_rebuilt(dst);
        let geoms = [instances_geometry(instances_address)];
        let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
            .ty(vk::AccelerationStructureTypeKHR::TOP_LEVEL)
            .flags(flags)
            .dst_acceleration_structure(dst)
            .geometries(&geoms)
            .scratch_data(vk::DeviceOrHostAddressKHR {
                device_address: scratch_address,
            });
        let info = match update_from {
            Some(src) => info
                .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
                .src_acceleration_structure(src),
            None => info.mode(vk::BuildAccelerationStructureModeKHR::BUILD),
        };
        let range = [
            vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(instance_count)
        ];
        // SAFETY: guaranteed by the caller.
        unsafe {
            self.accel
                .cmd_build_acceleration_structures(cmd, &[info], &[&range[..]])
        };
    }

    /// The shader stages that may read an acceleration structure on this device: compute
    /// (ray queries) and, when the extension is enabled, ray-tracing shaders.
    pub(crate) fn as_reader_stages(&self) -> vk::PipelineStageFlags2 {
        let mut s = vk::PipelineStageFlags2::COMPUTE_SHADER;
        if self.info().ray_tracing_pipeline {
            s |= vk::PipelineStageFlags2::RAY_TRACING_SHADER_KHR;
        }
        if self.info().ray_query {
            s |= vk::PipelineStageFlags2::FRAGMENT_SHADER;
        }
        s
    }

    /// Records one pipeline barrier made of the global memory barriers `barriers`.
    ///
    /// # Safety
    /// `cmd` is a command buffer of this device, recording, outside a render pass.
    pub(crate) unsafe fn cmd_memory_barriers(
        &self,
        cmd: vk::CommandBuffer,
        barriers: &[vk::MemoryBarrier2<'_>],
    ) {
        // SAFETY: cmd is recording outside a render pass (caller).
        unsafe {
            self.device.cmd_pipeline_barrier2(
                cmd,
                &vk::DependencyInfo::default().memory_barriers(barriers),
            )
        };
    }

    /// Records a barrier between acceleration-structure work and everything around it on the
    /// queue: AS writes (builds, refits, compaction copies) are visible to later AS builds and
    /// shader reads, and a later in-place write (a refit, the in-place TLAS rebuild) waits for
    /// earlier shader reads of the same structure (a trace of a frame still in flight on this
    /// queue: its source scope covers the ray-query and ray-tracing stages, not only builds).
    ///
    /// # Safety
    /// `cmd` is recording.
    pub unsafe fn cmd_accel_barrier(&self, cmd: vk::CommandBuffer) {
        let readers = self.as_reader_stages();
        let barrier = [vk::MemoryBarrier2::default()
            .src_stage_mask(vk::PipelineStageFlags2::ACCELERATION_STRUCTURE_BUILD_KHR | readers)
            .src_access_mask(vk::AccessFlags2::ACCELERATION_STRUCTURE_WRITE_KHR)
            .dst_stage_mask(vk::PipelineStageFlags2::ACCELERATION_STRUCTURE_BUILD_KHR | readers)
            .dst_access_mask(
                vk::AccessFlags2::ACCELERATION_STRUCTURE_READ_KHR
                    | vk::AccessFlags2::ACCELERATION_STRUCTURE_WRITE_KHR,
            )];
        // SAFETY: cmd is recording (caller).
        unsafe { self.cmd_memory_barriers(cmd, &barrier) };
    }

    /// Records the barrier a frame starts with, for build inputs the engine writes on the GPU:
    /// compute-shader and transfer writes recorded or submitted earlier on this queue (e.g. the
    /// engine's skinning pass writing a pose buffer, an upload of static geometry) are made
    /// visible to acceleration-structure build input reads and to compute-shader reads and
    /// writes (the refit-quality pass, which also rewrites its readback buffer every
    /// `frames_in_flight` frames).
    ///
    /// # Safety
    /// `cmd` is a command buffer of this device, recording, outside a render pass.
    pub unsafe fn cmd_build_input_barrier(&self, cmd: vk::CommandBuffer) {
        let barrier = [vk::MemoryBarrier2::default()
            .src_stage_mask(
                vk::PipelineStageFlags2::COMPUTE_SHADER | vk::PipelineStageFlags2::ALL_TRANSFER,
            )
            .src_access_mask(vk::AccessFlags2::SHADER_WRITE | vk::AccessFlags2::TRANSFER_WRITE)
            .dst_stage_mask(
                vk::PipelineStageFlags2::ACCELERATION_STRUCTURE_BUILD_KHR
                    | vk::PipelineStageFlags2::COMPUTE_SHADER,
            )
            .dst_access_mask(
                vk::AccessFlags2::SHADER_READ
                    | vk::AccessFlags2::SHADER_STORAGE_READ
                    | vk::AccessFlags2::SHADER_WRITE,
            )];
        // SAFETY: cmd is recording outside a render pass (caller).
        unsafe { self.cmd_memory_barriers(cmd, &barrier) };
    }

    /// Records the barrier a frame ends with, for build inputs the engine rewrites: this
    /// frame's reads of them (builds, refits, the refit-quality pass) happen before later
    /// compute-shader and transfer writes on this queue (the engine's next skinning pass), and
    /// the quality pass's writes are visible to the host once the frame completed.
    ///
    /// # Safety
    /// `cmd` is a command buffer of this device, recording, outside a render pass.
    pub unsafe fn cmd_build_input_release(&self, cmd: vk::CommandBuffer) {
        let barrier = [
            vk::MemoryBarrier2::default()
                .src_stage_mask(
                    vk::PipelineStageFlags2::ACCELERATION_STRUCTURE_BUILD_KHR
                        | vk::PipelineStageFlags2::COMPUTE_SHADER,
                )
                .dst_stage_mask(
                    vk::PipelineStageFlags2::COMPUTE_SHADER | vk::PipelineStageFlags2::ALL_TRANSFER,
                ),
            vk::MemoryBarrier2::default()
                .src_stage_mask(vk::PipelineStageFlags2::COMPUTE_SHADER)
                .src_access_mask(vk::AccessFlags2::SHADER_WRITE)
                .dst_stage_mask(vk::PipelineStageFlags2::HOST)
                .dst_access_mask(vk::AccessFlags2::HOST_READ),
        ];
        // SAFETY: cmd is recording outside a render pass (caller).
        unsafe { self.cmd_memory_barriers(cmd, &barrier) };
    }

    /// Creates a device-local scratch buffer of at least `bytes` usable from an address aligned to
    /// `minAccelerationStructureScratchOffsetAlignment`; returns it and that aligned base address.
    pub fn create_scratch(
        &self,
        name: &str,
        bytes: u64,
    ) -> VkResult<(GpuBuffer, vk::DeviceAddress)> {
        let align = self.info().min_scratch_alignment;
        let buffer = self.create_buffer(&BufferDesc {
            name,
            size: bytes.max(1) + align,
            usage: vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
            memory: MemoryKind::DeviceLocal,
        })?;
        let base = align_up(buffer.address, align);
        Ok((buffer, base))
    }
}
