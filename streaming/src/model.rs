//! The world model: ids, bounds, instances, levels, meshes and their LOD chains.
//!
//! These are the plain data types that the generator produces, the baker writes, the loader reads
//! back and the events hand out. Instances are kept small (one `Mat4` plus bounds and a few ids,
//! 128 bytes) so that a 100k-instance world description stays far below 256 bytes per instance;
//! mesh geometry lives apart, behind `Arc`s, and is shared by every instance of the mesh.

use std::sync::Arc;

use glam::{Mat4, Vec3};

use crate::skeleton::Skeleton;

/// Identifies a mesh (a LOD chain) in the world's mesh library.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct WorldMeshId(pub u32);

/// Identifies a streaming level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct LevelId(pub u32);

/// Identifies an instance; unique over the whole world (not only within its level).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct WorldInstanceId(pub u32);

/// Axis-aligned box, `min <= max` on every axis for a non-empty box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    /// Smallest corner.
    pub min: Vec3,
    /// Largest corner.
    pub max: Vec3,
}

impl Aabb {
    /// The empty box (`min = +inf`, `max = -inf`): the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

    /// Bounds of a point set; [`Aabb::EMPTY`] for no points.
    pub fn from_points(points: &[[f32; 3]]) -> Aabb {
        points.iter().fold(Aabb::EMPTY, |b, p| Aabb {
            min: b.min.min(Vec3::from(*p)),
            max: b.max.max(Vec3::from(*p)),
        })
    }

    /// The smallest box holding both.
    pub fn union(self, other: Aabb) -> Aabb {
        Aabb {
            min: self.min.min(other.min),
            max: self.max.max(other.max),
        }
    }

    /// Centre point.
    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Whether `min <= max` on every axis.
    pub fn is_valid(&self) -> bool {
        self.min.cmple(self.max).all() && self.min.is_finite() && self.max.is_finite()
    }

    /// The box enclosing this box after an affine transform.
    ///
    /// ```
    /// use rtstream_streaming::Aabb;
    /// use glam::{Mat4, Vec3};
    /// let b = Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) };
    /// let t = b.transformed(&Mat4::from_translation(Vec3::new(10.0, 0.0, 0.0)));
    /// assert_eq!(t.min, Vec3::new(9.0, -1.0, -1.0));
    /// ```
    pub fn transformed(&self, m: &Mat4) -> Aabb {
        let c = m.transform_point3(self.center());
        let e = (self.max - self.min) * 0.5;
        let ext = Vec3::new(
            m.x_axis.x.abs() * e.x + m.y_axis.x.abs() * e.y + m.z_axis.x.abs() * e.z,
            m.x_axis.y.abs() * e.x + m.y_axis.y.abs() * e.y + m.z_axis.y.abs() * e.z,
            m.x_axis.z.abs() * e.x + m.y_axis.z.abs() * e.y + m.z_axis.z.abs() * e.z,
        );
        Aabb {
            min: c - ext,
            max: c + ext,
        }
    }

    /// Distance in the XZ plane (ground plane) from `p` to the box; 0 inside.
    pub fn distance_xz(&self, p: Vec3) -> f32 {
        let dx = (self.min.x - p.x).max(p.x - self.max.x).max(0.0);
        let dz = (self.min.z - p.z).max(p.z - self.max.z).max(0.0);
        (dx * dx + dz * dz).sqrt()
    }

    /// Euclidean distance from `p` to the box; 0 inside.
    pub fn distance(&self, p: Vec3) -> f32 {
        (self.min - p).max(p - self.max).max(Vec3::ZERO).length()
    }
}

/// Bounding sphere.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sphere {
    /// Centre.
    pub center: Vec3,
    /// Radius (>= 0).
    pub radius: f32,
}

/// What an instance's material does to rays. Only [`MaterialClass::Opaque`] geometry is eligible
/// for a BLAS (as in the shipped game): masked, transparent and world-position-offset materials
/// would need any-hit shaders or per-frame deformation the BLAS cannot follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum MaterialClass {
    /// Fully opaque.
    Opaque = 0,
    /// Alpha-tested (foliage cards, fences).
    AlphaMasked = 1,
    /// Alpha-blended (glass, water).
    Transparent = 2,
    /// Vertex shader moves the surface (wind on grass/trees).
    WorldPositionOffset = 3,
}

impl MaterialClass {
    /// Whether an instance with this material may get a BLAS.
    pub fn blas_eligible(self) -> bool {
        self == MaterialClass::Opaque
    }

    pub(crate) fn from_u8(v: u8) -> Option<MaterialClass> {
        Some(match v {
            0 => MaterialClass::Opaque,
            1 => MaterialClass::AlphaMasked,
            2 => MaterialClass::Transparent,
            3 => MaterialClass::WorldPositionOffset,
            _ => return None,
        })
    }
}

/// Whether an instance's vertices move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Motion {
    /// Rigid: shares the (mesh, LOD) BLAS with every other instance.
    Static = 0,
    /// Skinned: deformed every frame by [`crate::skin`]; owns its BLAS and refits it.
    Skinned = 1,
}

/// A placement of a mesh in the world (128 bytes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Instance {
    /// Local-to-world transform. Meshes are authored in metres, so LOD errors scale with the
    /// transform's largest axis scale ([`Instance::max_scale`]).
    pub transform: Mat4,
    /// World-space bounds.
    pub aabb: Aabb,
    /// World-space bounding sphere.
    pub sphere: Sphere,
    /// World-unique id.
    pub id: WorldInstanceId,
    /// The mesh it places.
    pub mesh: WorldMeshId,
    /// Material class (only opaque is BLAS-eligible).
    pub material: MaterialClass,
    /// Static or skinned.
    pub motion: Motion,
}

impl Instance {
    /// Builds an instance and derives its world bounds from the mesh's local bounds.
    pub fn new(
        id: WorldInstanceId,
        mesh: WorldMeshId,
        transform: Mat4,
        local_bounds: &Aabb,
        material: MaterialClass,
        motion: Motion,
    ) -> Instance {
        let aabb = local_bounds.transformed(&transform);
        let local_r = (local_bounds.max - local_bounds.min).length() * 0.5;
        let scale = max_axis_scale(&transform);
        Instance {
            transform,
            aabb,
            sphere: Sphere {
                center: transform.transform_point3(local_bounds.center()),
                radius: local_r * scale,
            },
            id,
            mesh,
            material,
            motion,
        }
    }

    /// Largest axis scale of the transform (multiplies the mesh's LOD errors).
    pub fn max_scale(&self) -> f32 {
        max_axis_scale(&self.transform)
    }
}

pub(crate) fn max_axis_scale(m: &Mat4) -> f32 {
    m.x_axis
        .truncate()
        .length()
        .max(m.y_axis.truncate().length())
        .max(m.z_axis.truncate().length())
}

/// A streaming level: one cell of the world grid and the instances placed in it.
#[derive(Debug, Clone, PartialEq)]
pub struct Level {
    /// Its id (also its file name stem once baked).
    pub id: LevelId,
    /// Grid cell (x, z).
    pub cell: [i32; 2],
    /// Union of its instances' bounds (and the cell's ground rectangle).
    pub bounds: Aabb,
    /// What it places.
    pub instances: Vec<Instance>,
}

/// Per-vertex skinning data of one LOD, plus the skeleton and animation it refers to.
#[derive(Debug, Clone, PartialEq)]
pub struct SkinWeights {
    /// Up to four joint indices per vertex (into `skeleton.joints`).
    pub joints: Vec<[u16; 4]>,
    /// Matching weights, normalised to sum to 1.
    pub weights: Vec<[f32; 4]>,
    /// The skeleton and its animation (shared by every LOD of the mesh).
    pub skeleton: Arc<Skeleton>,
}

/// One level of detail of a mesh: its own compact vertex and index buffers.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshLod {
    /// Vertex positions in mesh space (metres).
    pub positions: Vec<[f32; 3]>,
    /// Triangle list; every index is `< positions.len()`.
    pub indices: Vec<u32>,
    /// Geometric error against LOD0 in mesh-space metres (0 for LOD0), as reported by
    /// meshoptimizer and accumulated along the chain; multiply by [`Instance::max_scale`].
    pub error: f32,
    /// Skinning data for skinned meshes.
    pub skin: Option<SkinWeights>,
}

impl MeshLod {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Approximate CPU bytes held (what the mesh memory budget counts).
    pub fn byte_size(&self) -> usize {
        let skin = self
            .skin
            .as_ref()
            .map_or(0, |s| s.joints.len() * 8 + s.weights.len() * 16);
        self.positions.len() * 12 + self.indices.len() * 4 + skin
    }
}

/// A mesh: its LOD chain, LOD0 finest. Every LOD has at most ~half the triangles of the previous.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Its id (index in the mesh library).
    pub id: WorldMeshId,
    /// Human-readable name (source file and mesh name, or generator archetype).
    pub name: String,
    /// Mesh-space bounds of LOD0.
    pub bounds: Aabb,
    /// LOD0 first.
    pub lods: Vec<Arc<MeshLod>>,
}

impl Mesh {
    /// Whether the mesh carries skinning data.
    pub fn is_skinned(&self) -> bool {
        self.lods.first().is_some_and(|l| l.skin.is_some())
    }
}
