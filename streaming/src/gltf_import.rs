//! glTF 2.0 import: triangle meshes and the scene's node instances, validated.
//!
//! Every primitive of a glTF mesh in TRIANGLES mode is merged into one indexed triangle list (they
//! share the mesh's transform, so one BLAS per mesh suffices). Other primitive modes are skipped
//! with a warning. Non-finite positions, out-of-range indices and cyclic node graphs are errors
//! that name the file; nothing is passed on half-checked.

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};

use crate::error::{Result, StreamingError};

/// Deepest node nesting accepted; deeper graphs are reported as invalid (they are almost surely
/// cycles, which the glTF spec forbids but broken files contain).
const MAX_NODE_DEPTH: usize = 64;

/// One triangle mesh: positions, optional per-vertex normals, and a triangle list.
#[derive(Debug, Clone, PartialEq)]
pub struct TriMesh {
    /// The glTF mesh name, or `mesh<index>` when it has none.
    pub name: String,
    /// Vertex positions in the mesh's local space.
    pub positions: Vec<[f32; 3]>,
    /// Per-vertex normals; empty when the file has none for some primitive.
    pub normals: Vec<[f32; 3]>,
    /// Triangle list; every index is `< positions.len()`.
    pub indices: Vec<u32>,
    /// Linear base colour of the first primitive's material (white when none).
    pub base_color: [f32; 4],
}

impl TriMesh {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Axis-aligned bounds in local space as (min, max). Empty meshes give (+inf, -inf).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(Vec3::from(*p)), hi.max(Vec3::from(*p))),
        )
    }
}

/// A placement of a mesh in the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeshInstance {
    /// Index into [`GltfScene::meshes`].
    pub mesh: usize,
    /// Local-to-world transform (all ancestor node transforms applied).
    pub transform: Mat4,
}

/// The triangle meshes of a glTF file and the instances its default scene places.
#[derive(Debug, Clone, PartialEq)]
pub struct GltfScene {
    /// The file it came from.
    pub path: PathBuf,
    /// One entry per glTF mesh that has at least one triangle; glTF mesh indices are remapped.
    pub meshes: Vec<TriMesh>,
    /// Node instances of the default scene (or the first scene, or every root node).
    pub instances: Vec<MeshInstance>,
}

impl GltfScene {
    /// Total triangles over all instances (what a flat scene would hold).
    pub fn instanced_triangle_count(&self) -> usize {
        self.instances
            .iter()
            .map(|i| self.meshes[i.mesh].triangle_count())
            .sum()
    }
}

/// Loads a `.gltf` or `.glb` file (external buffers are resolved relative to it).
///
/// ```no_run
/// let scene = rtstream_streaming::load_gltf("/usr/share/assimp/models/glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb")?;
/// assert!(!scene.instances.is_empty());
/// # Ok::<(), rtstream_streaming::StreamingError>(())
/// ```
pub fn load_gltf(path: impl AsRef<Path>) -> Result<GltfScene> {
    let path = path.as_ref();
    let (doc, buffers, _images) = gltf::import(path).map_err(|source| StreamingError::Gltf {
        path: path.to_owned(),
        source,
    })?;

    // glTF mesh index -> our mesh index (None: the mesh had no triangles).
    let mut remap = Vec::with_capacity(doc.meshes().len());
    let mut meshes = Vec::new();
    for mesh in doc.meshes() {
        match read_mesh(path, &mesh, &buffers)? {
            Some(m) => {
                remap.push(Some(meshes.len()));
                meshes.push(m);
            }
            None => remap.push(None),
        }
    }

    let roots: Vec<gltf::Node> = match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => scene.nodes().collect(),
        None => {
            // No scene: every node that is nobody's child is a root.
            let mut is_child = vec![false; doc.nodes().len()];
            for n in doc.nodes() {
                for c in n.children() {
                    is_child[c.index()] = true;
                }
            }
            doc.nodes().filter(|n| !is_child[n.index()]).collect()
        }
    };

    let mut instances = Vec::new();
    let mut stack: Vec<(gltf::Node, Mat4, usize)> =
        roots.into_iter().map(|n| (n, Mat4::IDENTITY, 0)).collect();
    while let Some((node, parent, depth)) = stack.pop() {
        if depth > MAX_NODE_DEPTH {
            return Err(StreamingError::InvalidScene {
                path: path.to_owned(),
                reason: format!("nodes nest deeper than {MAX_NODE_DEPTH} levels (a cycle?)"),
            });
        }
        let local = Mat4::from_cols_array_2d(&node.transform().matrix());
        let world = parent * local;
        if !world.is_finite() {
            return Err(StreamingError::InvalidScene {
                path: path.to_owned(),
                reason: format!("node {} has a non-finite transform", node.index()),
            });
        }
        if let Some(m) = node.mesh().and_then(|m| remap[m.index()]) {
            instances.push(MeshInstance {
                mesh: m,
                transform: world,
            });
        }
        for child in node.children() {
            stack.push((child, world, depth + 1));
        }
    }
    // The stack visits children in reverse; sort for a stable, file-order-like result.
    instances.sort_by_key(|i| i.mesh);

    Ok(GltfScene {
        path: path.to_owned(),
        meshes,
        instances,
    })
}

fn read_mesh(
    path: &Path,
    mesh: &gltf::Mesh,
    buffers: &[gltf::buffer::Data],
) -> Result<Option<TriMesh>> {
    let name = mesh
        .name()
        .map(str::to_owned)
        .unwrap_or_else(|| format!("mesh{}", mesh.index()));
    let invalid = |reason: String| StreamingError::InvalidMesh {
        path: path.to_owned(),
        mesh: name.clone(),
        reason,
    };
    let mut out = TriMesh {
        name: name.clone(),
        positions: Vec::new(),
        normals: Vec::new(),
        indices: Vec::new(),
        base_color: [1.0; 4],
    };
    let mut all_have_normals = true;
    let mut first = true;
    for prim in mesh.primitives() {
        if prim.mode() != gltf::mesh::Mode::Triangles {
            tracing::warn!(file = %path.display(), mesh = %name, mode = ?prim.mode(), "skipping non-triangle primitive");
            continue;
        }
        let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
        let positions: Vec<[f32; 3]> = reader
            .read_positions()
            .ok_or_else(|| invalid(format!("primitive {} has no POSITION", prim.index())))?
            .collect();
        if let Some(bad) = positions
            .iter()
            .position(|p| !p.iter().all(|c| c.is_finite()))
        {
            return Err(invalid(format!("vertex {bad} has a non-finite position")));
        }
        let base = u32::try_from(out.positions.len())
            .map_err(|_| invalid("more than 2^32 vertices".into()))?;
        let count = positions.len() as u64;
        let indices: Vec<u32> = match reader.read_indices() {
            Some(ix) => ix.into_u32().collect(),
            None => (0..count as u32).collect(),
        };
        if indices.len() % 3 != 0 {
            return Err(invalid(format!(
                "primitive {}: {} indices is not a multiple of 3",
                prim.index(),
                indices.len()
            )));
        }
        if let Some(bad) = indices.iter().find(|&&i| u64::from(i) >= count) {
            return Err(invalid(format!(
                "primitive {}: index {bad} out of range ({count} vertices)",
                prim.index()
            )));
        }
        match reader.read_normals() {
            Some(n) if all_have_normals => out.normals.extend(n),
            _ => all_have_normals = false,
        }
        if first {
            out.base_color = prim.material().pbr_metallic_roughness().base_color_factor();
            first = false;
        }
        out.indices.extend(indices.into_iter().map(|i| i + base));
        out.positions.extend(positions);
    }
    if !all_have_normals || out.normals.len() != out.positions.len() {
        out.normals.clear();
    }
    Ok((!out.indices.is_empty()).then_some(out))
}
