//! Triangle geometry on the GPU: validated upload of positions and indices.

use crate::backend::vulkan::device::accel::{TriangleGeometry, BUILD_INPUT_USAGE};
use crate::backend::vulkan::device::buffer::GpuBuffer;
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::{VkResult, VulkanError};

/// A triangle mesh to upload (borrowed data for [`GpuGeometry::upload`] and a static scene);
/// not the manager's `MeshDesc`, which registers a LOD chain.
#[derive(Debug, Clone, Copy)]
pub struct SceneMesh<'a> {
    /// Debug name.
    pub name: &'a str,
    /// Positions.
    pub positions: &'a [[f32; 3]],
    /// Triangle-list indices into `positions`.
    pub indices: &'a [u32],
    /// Opaque material (the BLAS geometry gets the OPAQUE flag).
    pub opaque: bool,
}

/// Vertex and index buffers of one mesh, and their description as a BLAS geometry.
#[derive(Debug)]
pub struct GpuGeometry {
    /// Positions (`[f32; 3]`, tightly packed), host-visible, with a device address.
    pub vertices: GpuBuffer,
    /// `u32` triangle-list indices, with a device address.
    pub indices: GpuBuffer,
    /// The geometry as BLAS builds see it.
    pub geometry: TriangleGeometry,
}

impl GpuGeometry {
    /// Validates (non-empty triangle list, indices in range, finite positions) and uploads.
    pub fn upload(ctx: &VulkanContext, m: &SceneMesh<'_>) -> VkResult<Self> {
        let bad = |why: String| {
            Err(VulkanError::Unsupported(format!(
                "mesh {:?}: {why}",
                m.name
            )))
        };
        if m.indices.is_empty() || m.indices.len() % 3 != 0 {
            return bad(format!(
                "{} indices is not a non-empty triangle list",
                m.indices.len()
            ));
        }
        let max_vertex = m.positions.len().saturating_sub(1) as u32;
        if let Some(i) = m.indices.iter().find(|&&i| i as usize >= m.positions.len()) {
            return bad(format!(
                "index {i} out of range ({} vertices)",
                m.positions.len()
            ));
        }
        if m.positions.iter().any(|p| !p.iter().all(|c| c.is_finite())) {
            return bad("non-finite position".into());
        }
        let vertices = ctx.create_buffer_with_data(
            &format!("{} vertices", m.name),
            BUILD_INPUT_USAGE,
            bytemuck::cast_slice(m.positions),
        )?;
        let indices = match ctx.create_buffer_with_data(
            &format!("{} indices", m.name),
            BUILD_INPUT_USAGE,
            bytemuck::cast_slice(m.indices),
        ) {
            Ok(b) => b,
            Err(e) => {
                ctx.destroy_buffer(vertices);
                return Err(e);
            }
        };
        let geometry = TriangleGeometry {
            vertex_address: vertices.address,
            vertex_format: ash::vk::Format::R32G32B32_SFLOAT,
            index_type: ash::vk::IndexType::UINT32,
            vertex_stride: 12,
            max_vertex,
            index_address: indices.address,
            triangle_count: (m.indices.len() / 3) as u32,
            opaque: m.opaque,
        };
        Ok(Self {
            vertices,
            indices,
            geometry,
        })
    }

    /// Overwrites the positions (same vertex count), e.g. with a new skinned pose. The caller
    /// guarantees no pending GPU work reads the buffer.
    ///
    /// # Panics
    /// If the vertex count differs (a broken contract).
    pub fn write_positions(&mut self, positions: &[[f32; 3]]) {
        assert_eq!(
            positions.len() as u64 * 12,
            self.vertices.size,
            "write_positions with a different vertex count"
        );
        self.vertices.write(0, bytemuck::cast_slice(positions));
    }

    /// Triangle count.
    pub fn triangle_count(&self) -> u32 {
        self.geometry.triangle_count
    }

    /// Destroys the buffers. The caller guarantees the GPU no longer reads them.
    pub fn destroy(self, ctx: &VulkanContext) {
        ctx.destroy_buffer(self.vertices);
        ctx.destroy_buffer(self.indices);
    }
}
