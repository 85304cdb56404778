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

/// The geometry of one LOD: real data, or only its counts (the model backend needs no data).
#[derive(Debug, Clone)]
pub enum LodGeometry {
    /// Vertex and index data, shared (`Arc`) with the engine.
    Data(Arc<dyn MeshData>),
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
            LodGeometry::Counts { triangles, .. } => *triangles,
        }
    }

    /// Number of vertices.
    pub fn vertices(&self) -> u32 {
        match self {
            LodGeometry::Data(d) => d.positions().len() as u32,
            LodGeometry::Counts { vertices, .. } => *vertices,
        }
    }

    /// The data, if registered with data.
    pub fn data(&self) -> Option<&dyn MeshData> {
        match self {
            LodGeometry::Data(d) => Some(&**d),
            LodGeometry::Counts { .. } => None,
        }
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
