//! Mesh registration: LOD chains of static or skinned triangle geometry.

use std::sync::Arc;

use crate::{AsError, Result};

/// Triangle geometry of one LOD: positions and a triangle list (3 indices per triangle).
#[derive(Debug, Clone, PartialEq)]
pub struct GeometryData {
    /// Vertex positions in mesh space.
    pub positions: Vec<[f32; 3]>,
    /// Triangle list, 3 indices per triangle.
    pub indices: Vec<u32>,
}

/// Vertex and index data the manager reads (to build, refit and measure): [`GeometryData`],
/// or the engine's own type, shared behind an `Arc` without a copy (the facade's bridge hands
/// streaming's resident LODs over this way).
pub trait MeshData: Send + Sync + std::fmt::Debug {
    /// Vertex positions in mesh space.
    fn positions(&self) -> &[[f32; 3]];
    /// Triangle list, 3 indices per triangle.
    fn indices(&self) -> &[u32];
}

impl MeshData for GeometryData {
    fn positions(&self) -> &[[f32; 3]] {
        &self.positions
    }
    fn indices(&self) -> &[u32] {
        &self.indices
    }
}

/// Vertex position format of [`DeviceVertices`]: the formats every Vulkan device supports as
/// acceleration-structure build input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VertexFormat {
    /// `R32G32B32_SFLOAT`: three `f32` (12 bytes).
    F32x3,
    /// `R16G16B16A16_SFLOAT`: four `f16`, the fourth ignored (8 bytes).
    F16x4,
    /// `R16G16B16A16_SNORM`: four `i16` mapped to [-1, 1], the fourth ignored (8 bytes).
    /// Positions are in [-1, 1] mesh space; the instance transform carries the dequantisation
    /// (scale and offset), and the mesh's bounds are in that same [-1, 1] space.
    Snorm16x4,
}

impl VertexFormat {
    /// Bytes of one position.
    pub const fn size(self) -> u64 {
        match self {
            VertexFormat::F32x3 => 12,
            VertexFormat::F16x4 | VertexFormat::Snorm16x4 => 8,
        }
    }

    /// Bytes of one component (the alignment of the address and the stride).
    pub const fn component_size(self) -> u64 {
        match self {
            VertexFormat::F32x3 => 4,
            VertexFormat::F16x4 | VertexFormat::Snorm16x4 => 2,
        }
    }
}

/// Index type of [`DeviceIndices`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum IndexType {
    /// `u16` indices.
    U16,
    /// `u32` indices.
    U32,
}

impl IndexType {
    /// Bytes of one index.
    pub const fn size(self) -> u64 {
        match self {
            IndexType::U16 => 2,
            IndexType::U32 => 4,
        }
    }
}

/// Positions in a buffer the engine owns, by device address.
///
/// The engine's contract (the backend does not check it, the GPU would read garbage or fault):
/// - the buffer was created with `SHADER_DEVICE_ADDRESS` and
///   `ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR` usage (and `STORAGE_BUFFER`, which the
///   Vulkan backend's refit-quality pass reads it through), its memory allocated with
///   `MemoryAllocateFlags::DEVICE_ADDRESS`, and is readable in whole 4-byte words (its size
///   rounded up to 4: the quality pass reads 16-bit data by the word);
/// - `count` positions, `stride` bytes apart, lie inside it from `address` on;
/// - it stays alive, and unchanged while it is a static mesh's, until the mesh is unregistered
///   and every frame that used it completed (`frame_done` / the backend's timeline).
///
/// A skinned pose ([`crate::AsManager::set_skinned_pose_device`]) is written by the engine on
/// the GPU (e.g. a skinning compute pass) on the same queue before the backend's frame work; the
/// backend's frame starts with the barrier that makes those writes visible to the refit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DeviceVertices {
    /// Device address of the first position (`vkGetBufferDeviceAddress` plus an offset).
    pub address: u64,
    /// Bytes between consecutive positions (>= the format's size, a multiple of its component).
    pub stride: u64,
    /// Position format.
    pub format: VertexFormat,
    /// Number of positions (the highest index referenced is `count - 1` at most).
    pub count: u32,
}

/// A triangle list in a buffer the engine owns, by device address (same contract as
/// [`DeviceVertices`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DeviceIndices {
    /// Device address of the first index, aligned to the index size.
    pub address: u64,
    /// `u16` or `u32`.
    pub index_type: IndexType,
}

/// One LOD's geometry in the engine's own GPU buffers: built, sized and refitted from these
/// addresses with no upload and no CPU copy. See [`DeviceVertices`] for the contract.
///
/// ```
/// use rtstream_as_manager::{DeviceGeometry, DeviceIndices, DeviceVertices, IndexType, VertexFormat};
/// let g = DeviceGeometry {
///     vertices: DeviceVertices { address: 0x1_0000, stride: 16, format: VertexFormat::Snorm16x4, count: 4 },
///     indices: DeviceIndices { address: 0x2_0000, index_type: IndexType::U16 },
///     triangle_count: 2,
/// };
/// assert!(g.validate().is_ok());
/// let odd = DeviceGeometry { indices: DeviceIndices { address: 0x2_0001, ..g.indices }, ..g };
/// assert!(odd.validate().is_err());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DeviceGeometry {
    /// Positions.
    pub vertices: DeviceVertices,
    /// Triangle-list indices (`3 * triangle_count` of them).
    pub indices: DeviceIndices,
    /// Triangles.
    pub triangle_count: u32,
}

/// Why a [`DeviceGeometry`] or [`DeviceVertices`] is unusable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DeviceGeometryError {
    /// A device address is 0.
    #[error("{0} address is 0")]
    NullAddress(&'static str),
    /// An address or stride is not a multiple of what the format needs.
    #[error("{what} {value:#x} is not a multiple of {align}")]
    Misaligned {
        /// Which value.
        what: &'static str,
        /// The value.
        value: u64,
        /// The alignment it needs.
        align: u64,
    },
    /// The stride is smaller than one position.
    #[error("vertex stride {stride} is smaller than the format's {size} bytes")]
    StrideTooSmall {
        /// The stride.
        stride: u64,
        /// The format's size.
        size: u64,
    },
    /// No vertices or no triangles.
    #[error("no vertices or no triangles")]
    Empty,
}

impl DeviceVertices {
    /// Checks the address, alignment and stride (not what lies at the address).
    pub fn validate(&self) -> std::result::Result<(), DeviceGeometryError> {
        let align = self.format.component_size();
        if self.address == 0 {
            return Err(DeviceGeometryError::NullAddress("vertex"));
        }
        if self.count == 0 {
            return Err(DeviceGeometryError::Empty);
        }
        if self.address % align != 0 {
            return Err(DeviceGeometryError::Misaligned {
                what: "vertex address",
                value: self.address,
                align,
            });
        }
        if self.stride % align != 0 {
            return Err(DeviceGeometryError::Misaligned {
                what: "vertex stride",
                value: self.stride,
                align,
            });
        }
        if self.stride < self.format.size() {
            return Err(DeviceGeometryError::StrideTooSmall {
                stride: self.stride,
                size: self.format.size(),
            });
        }
        Ok(())
    }
}

impl DeviceGeometry {
    /// Checks addresses, alignments and the stride (not what lies at the addresses).
    pub fn validate(&self) -> std::result::Result<(), DeviceGeometryError> {
        self.vertices.validate()?;
        if self.triangle_count == 0 {
            return Err(DeviceGeometryError::Empty);
        }
        self.indices.validate()
    }
}

impl DeviceIndices {
    /// Checks the address and its alignment to the index size (not what lies there).
    pub fn validate(&self) -> std::result::Result<(), DeviceGeometryError> {
        let (a, size) = (self.address, self.index_type.size());
        if a == 0 {
            return Err(DeviceGeometryError::NullAddress("index"));
        }
        if a % size != 0 {
            return Err(DeviceGeometryError::Misaligned {
                what: "index address",
                value: a,
                align: size,
            });
        }
        Ok(())
    }
}

/// The geometry of one LOD: real data, or only its counts (the model backend needs no data).
#[derive(Debug, Clone)]
pub enum LodGeometry {
    /// Vertex and index data, shared (`Arc`) with the engine.
    Data(Arc<dyn MeshData>),
    /// The engine's own GPU buffers, by device address (no upload, no CPU copy; see
    /// [`DeviceGeometry`] for the contract). The model backend uses only the counts.
    Device(DeviceGeometry),
    /// Counts only: enough for sizes, costs and policy, not for a real GPU build.
    Counts {
        /// Vertex count.
        vertices: u32,
        /// Triangle count.
        triangles: u32,
    },
}

impl LodGeometry {
    /// Number of triangles.
    pub fn triangles(&self) -> u32 {
        match self {
            LodGeometry::Data(d) => (d.indices().len() / 3) as u32,
            LodGeometry::Device(g) => g.triangle_count,
            LodGeometry::Counts { triangles, .. } => *triangles,
        }
    }

    /// Number of vertices.
    pub fn vertices(&self) -> u32 {
        match self {
            LodGeometry::Data(d) => d.positions().len() as u32,
            LodGeometry::Device(g) => g.vertices.count,
            LodGeometry::Counts { vertices, .. } => *vertices,
        }
    }

    /// The CPU data, if registered with data.
    pub fn data(&self) -> Option<&dyn MeshData> {
        match self {
            LodGeometry::Data(d) => Some(&**d),
            LodGeometry::Device(_) | LodGeometry::Counts { .. } => None,
        }
    }

    /// The engine's GPU buffers, if registered by device address.
    pub fn device(&self) -> Option<&DeviceGeometry> {
        match self {
            LodGeometry::Device(g) => Some(g),
            LodGeometry::Data(_) | LodGeometry::Counts { .. } => None,
        }
    }

    /// Whether a real backend can build it: CPU data or device addresses (not counts only).
    pub fn is_buildable(&self) -> bool {
        !matches!(self, LodGeometry::Counts { .. })
    }
}

/// One level of detail: geometry plus its geometric error (world units, in mesh space) against
/// the finest LOD. LOD 0 is the finest and usually has error 0.
#[derive(Debug, Clone)]
pub struct LodDesc {
    /// The LOD's triangles.
    pub geometry: LodGeometry,
    /// Maximum deviation from the finest LOD, in mesh-space units.
    pub geometric_error: f32,
}

/// Static meshes share one BLAS per LOD across instances; skinned instances own theirs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MeshKind {
    /// Rigid geometry: PREFER_FAST_TRACE + ALLOW_COMPACTION, shared per (mesh, LOD).
    Static,
    /// Deforming geometry: PREFER_FAST_BUILD + ALLOW_UPDATE, one BLAS per instance, refitted.
    Skinned,
}

/// Parameters to register a mesh.
///
/// ```
/// use rtstream_as_manager::{LodDesc, LodGeometry, MeshDesc, MeshKind};
/// let desc = MeshDesc::new("rock", MeshKind::Static, 2.0, vec![
///     LodDesc { geometry: LodGeometry::Counts { vertices: 600, triangles: 1000 }, geometric_error: 0.0 },
///     LodDesc { geometry: LodGeometry::Counts { vertices: 300, triangles: 500 }, geometric_error: 0.05 },
/// ]);
/// assert!(desc.validate().is_ok());
/// ```
#[derive(Debug, Clone)]
pub struct MeshDesc {
    /// Debug name.
    pub name: String,
    /// Static or skinned.
    pub kind: MeshKind,
    /// LOD chain, finest first; geometric errors must not decrease.
    pub lods: Vec<LodDesc>,
    /// Bounding-sphere centre in mesh space.
    pub bounds_center: [f32; 3],
    /// Bounding-sphere radius in mesh space (> 0).
    pub bounds_radius: f32,
    /// Opaque geometry gets FORCE_OPAQUE on its instances.
    pub opaque: bool,
}

impl MeshDesc {
    /// A mesh centred at the origin with the given bounding radius, opaque.
    pub fn new(name: impl Into<String>, kind: MeshKind, radius: f32, lods: Vec<LodDesc>) -> Self {
        Self {
            name: name.into(),
            kind,
            lods,
            bounds_center: [0.0; 3],
            bounds_radius: radius,
            opaque: true,
        }
    }

    /// Checks the chain: at least one LOD, at most [`MAX_LODS`], triangles > 0, indices in range,
    /// finite data, non-decreasing errors, positive finite radius.
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| AsError::InvalidMesh {
            name: self.name.clone(),
            reason,
        };
        if self.lods.is_empty() || self.lods.len() > MAX_LODS {
            return Err(bad(format!(
                "needs 1..={MAX_LODS} LODs, has {}",
                self.lods.len()
            )));
        }
        if !(self.bounds_radius.is_finite()
            && self.bounds_radius > 0.0
            && self.bounds_center.iter().all(|v| v.is_finite()))
        {
            return Err(bad("bounds must be finite with radius > 0".into()));
        }
        let mut prev = f32::NEG_INFINITY;
        for (i, lod) in self.lods.iter().enumerate() {
            if !(lod.geometric_error.is_finite() && lod.geometric_error >= 0.0) {
                return Err(bad(format!(
                    "LOD {i}: geometric error must be finite and >= 0"
                )));
            }
            if lod.geometric_error < prev {
                return Err(bad(format!("LOD {i}: geometric error decreases")));
            }
            prev = lod.geometric_error;
            if lod.geometry.triangles() == 0 || lod.geometry.vertices() == 0 {
                return Err(bad(format!("LOD {i}: no triangles")));
            }
            if let LodGeometry::Device(g) = &lod.geometry {
                g.validate()
                    .map_err(|e| bad(format!("LOD {i}: device geometry: {e}")))?;
            }
            if let LodGeometry::Data(d) = &lod.geometry {
                let (positions, indices) = (d.positions(), d.indices());
                if indices.len() % 3 != 0 {
                    return Err(bad(format!("LOD {i}: index count not a multiple of 3")));
                }
                let n = positions.len() as u32;
                if indices.iter().any(|&ix| ix >= n) {
                    return Err(bad(format!("LOD {i}: index out of range")));
                }
                if !positions.iter().flatten().all(|v| v.is_finite()) {
                    return Err(bad(format!("LOD {i}: non-finite position")));
                }
            }
        }
        Ok(())
    }
}

/// Most LODs a chain may have.
pub const MAX_LODS: usize = 8;
