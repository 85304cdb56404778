//! glTF 2.0 import: triangle meshes and the scene's node instances, validated.
//!
//! Every primitive of a glTF mesh in TRIANGLES mode is merged into one indexed triangle list (they
//! share the mesh's transform, so one BLAS per mesh suffices). Other primitive modes are skipped
//! with a warning. Non-finite positions, out-of-range indices and cyclic node graphs are errors
//! that name the file; nothing is passed on half-checked.
//!
//! Materials map to a [`MaterialClass`] (glTF alpha mode OPAQUE/MASK/BLEND; the first primitive's
//! material decides). Skins (JOINTS_0/WEIGHTS_0, the skin's joints and inverse bind matrices) and
//! the file's first animation become a [`Skeleton`] attached to the mesh as [`SkinWeights`];
//! joints are re-ordered parent-before-child and every index and key is validated.
//!
//! Why one file over 600 lines: it is the one place that reads glTF documents, and its
//! validation (header, JSON, accessors), mesh reading and skin/animation import share the checked
//! document and the file name every error carries; the skeleton type itself lives in `skeleton.rs`.

use std::path::{Path, PathBuf};

use std::sync::Arc;

use glam::{Mat4, Quat, Vec3, Vec4};

use crate::error::{Result, StreamingError};
use crate::model::{MaterialClass, SkinWeights};
use crate::skeleton::{Channel, ChannelPath, Joint, Skeleton};

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
    /// Material class from the first primitive's alpha mode.
    pub material: MaterialClass,
    /// Skinning data, when a node skins this mesh and every primitive has JOINTS_0/WEIGHTS_0.
    pub skin: Option<SkinWeights>,
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
    /// Local-to-world transform (all ancestor node transforms applied). For a skinned mesh the
    /// skeleton places the vertices, so this is the identity (glTF ignores the node transform).
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
    let bytes = std::fs::read(path).map_err(|e| gltf_error(path, gltf::Error::Io(e)))?;
    let base = path.parent().unwrap_or_else(|| Path::new("./"));
    import(path, &bytes, Some(base))
}

/// Loads a `.glb` or a `.gltf` whose buffers are embedded (data URIs) from memory; `name`
/// stands for the path in errors. The same checks as [`load_gltf`]; a buffer that names an
/// external file is an error.
pub fn load_gltf_slice(bytes: &[u8], name: &str) -> Result<GltfScene> {
    import(Path::new(name), bytes, None)
}

fn gltf_error(path: &Path, source: gltf::Error) -> StreamingError {
    StreamingError::Gltf {
        path: path.to_owned(),
        source,
    }
}

/// Parses the document and its buffers, never its images (rtstream uses none, and the gltf
/// crate's image decoding panics on malformed images). The raw checks run first: the gltf
/// crate panics on some inputs its own validation should refuse (found by fuzzing).
fn import(path: &Path, bytes: &[u8], base: Option<&Path>) -> Result<GltfScene> {
    if bytes.starts_with(b"glTF") {
        check_glb_header(path, bytes)?;
        let glb = gltf::binary::Glb::from_slice(bytes).map_err(|e| gltf_error(path, e))?;
        check_json(path, &glb.json)?;
    } else {
        check_json(path, bytes)?;
    }
    let gltf::Gltf { document, blob } =
        gltf::Gltf::from_slice(bytes).map_err(|e| gltf_error(path, e))?;
    let buffers = gltf::import_buffers(&document, base, blob).map_err(|e| gltf_error(path, e))?;
    scene_from(path, &document, &buffers)
}

/// Meshes, skins and instances of an imported document.
fn scene_from(
    path: &Path,
    doc: &gltf::Document,
    buffers: &[gltf::buffer::Data],
) -> Result<GltfScene> {
    // glTF mesh index -> our mesh index (None: the mesh had no triangles).
    let mut remap = Vec::with_capacity(doc.meshes().len());
    let mut meshes = Vec::new();
    let mut raw_skins = Vec::new();
    for mesh in doc.meshes() {
        match read_mesh(path, &mesh, buffers)? {
            Some((m, raw)) => {
                remap.push(Some(meshes.len()));
                meshes.push(m);
                raw_skins.push(raw);
            }
            None => remap.push(None),
        }
    }
    attach_skins(path, doc, buffers, &remap, &mut meshes, raw_skins)?;

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
            let skinned = meshes[m].skin.is_some();
            instances.push(MeshInstance {
                mesh: m,
                transform: if skinned { Mat4::IDENTITY } else { world },
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

/// Per-vertex joints and weights read from the primitives (None when some primitive lacks them).
type RawSkin = Option<(Vec<[u16; 4]>, Vec<[f32; 4]>)>;

/// What the gltf crate's readers accept, checked before reading: on anything else they hit
/// `unreachable!` or a debug assertion, or subtract past zero (fuzzed files with float indices,
/// a VEC2 position, a stride shorter than the element and an empty accessor did). Sparse
/// accessors are refused outright.
fn check_accessor(
    a: &gltf::Accessor<'_>,
    what: &str,
    types: &[gltf::accessor::DataType],
    dims: &[gltf::accessor::Dimensions],
) -> std::result::Result<(), String> {
    let i = a.index();
    if a.sparse().is_some() {
        return Err(format!(
            "accessor {i} ({what}): sparse accessors are not supported"
        ));
    }
    if a.count() == 0 {
        return Err(format!("accessor {i} ({what}): count is 0"));
    }
    let (t, d) = (a.data_type(), a.dimensions());
    if !types.contains(&t) || !dims.contains(&d) {
        return Err(format!("accessor {i} ({what}): {t:?} {d:?} is not allowed"));
    }
    match a.view().and_then(|v| v.stride()) {
        Some(stride) if stride < a.size() => Err(format!(
            "accessor {i} ({what}): stride {stride} is shorter than its {}-byte element",
            a.size()
        )),
        _ => Ok(()),
    }
}

/// [`check_accessor`] on every accessor of a primitive, by semantic.
fn check_accessors(prim: &gltf::Primitive<'_>) -> std::result::Result<(), String> {
    use gltf::accessor::DataType::{F32, U16, U32, U8};
    use gltf::accessor::Dimensions::{Scalar, Vec2, Vec3, Vec4};
    use gltf::Semantic;
    if let Some(a) = prim.indices() {
        check_accessor(&a, "indices", &[U8, U16, U32], &[Scalar])?;
    }
    for (sem, a) in prim.attributes() {
        let (types, dims): (&[_], &[_]) = match sem {
            Semantic::Positions | Semantic::Normals => (&[F32], &[Vec3]),
            Semantic::Tangents => (&[F32], &[Vec4]),
            Semantic::Joints(_) => (&[U8, U16], &[Vec4]),
            Semantic::Weights(_) => (&[U8, U16, F32], &[Vec4]),
            Semantic::TexCoords(_) => (&[U8, U16, F32], &[Vec2]),
            Semantic::Colors(_) => (&[U8, U16, F32], &[Vec3, Vec4]),
        };
        check_accessor(&a, &format!("{sem:?}"), types, dims)?;
    }
    Ok(())
}

/// A GLB header whose total length is below the header's own 12 bytes makes the gltf crate
/// subtract past zero.
fn check_glb_header(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(len) = bytes.get(8..12) {
        let len = u32::from_le_bytes(len.try_into().expect("four bytes"));
        if len < 12 {
            return Err(StreamingError::Schema {
                path: path.to_owned(),
                reason: format!("GLB header length {len} is below the header's 12 bytes"),
            });
        }
    }
    Ok(())
}

/// Checks on the raw JSON that the gltf crate skips or panics on:
/// - the schema requires every `extensions` value to be an object of objects, and the parser
///   ignores unknown extensions (wrongTypes/badExtension.gltf);
/// - a primitive's `POSITION` must name an existing accessor: the crate's validation indexes
///   the accessor list with it before checking (found by fuzzing).
fn check_json(path: &Path, json: &[u8]) -> Result<()> {
    // The crate skips unknown members without checking their UTF-8; read them lossily so these
    // checks see the document it sees.
    let text = String::from_utf8_lossy(json);
    let Ok(value) = serde_json::from_str::<serde_json::Value>(&text) else {
        return Ok(()); // Reported by gltf::Gltf::from_slice.
    };
    let schema = |reason: String| StreamingError::Schema {
        path: path.to_owned(),
        reason,
    };
    let accessors = value
        .get("accessors")
        .and_then(|a| a.as_array())
        .map_or(0, Vec::len);
    let meshes = value.get("meshes").and_then(|m| m.as_array());
    for (m, mesh) in meshes.into_iter().flatten().enumerate() {
        let prims = mesh.get("primitives").and_then(|p| p.as_array());
        for (p, prim) in prims.into_iter().flatten().enumerate() {
            let attrs = prim.get("attributes").and_then(|a| a.as_object());
            for (name, idx) in attrs.into_iter().flatten() {
                if idx.as_u64().is_some_and(|i| i >= accessors as u64) {
                    return Err(schema(format!(
                        "meshes[{m}].primitives[{p}].attributes.{name} = {idx}: only {accessors} accessors"
                    )));
                }
            }
        }
    }
    let mut stack = vec![(String::from("$"), &value)];
    while let Some((at, v)) = stack.pop() {
        match v {
            serde_json::Value::Object(map) => {
                for (k, child) in map {
                    let here = format!("{at}.{k}");
                    if k == "extensions" {
                        let serde_json::Value::Object(exts) = child else {
                            return Err(schema(format!("{here} is not an object")));
                        };
                        if let Some((name, _)) = exts.iter().find(|(_, e)| !e.is_object()) {
                            return Err(schema(format!("{here}.{name} is not an object")));
                        }
                    }
                    stack.push((here, child));
                }
            }
            serde_json::Value::Array(items) => {
                for (i, child) in items.iter().enumerate() {
                    stack.push((format!("{at}[{i}]"), child));
                }
            }
            _ => {}
        }
    }
    Ok(())
}

fn read_mesh(
    path: &Path,
    mesh: &gltf::Mesh,
    buffers: &[gltf::buffer::Data],
) -> Result<Option<(TriMesh, RawSkin)>> {
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
        material: MaterialClass::Opaque,
        skin: None,
    };
    let mut raw_joints: Vec<[u16; 4]> = Vec::new();
    let mut raw_weights: Vec<[f32; 4]> = Vec::new();
    let mut all_have_skin = true;
    let mut all_have_normals = true;
    let mut first = true;
    for prim in mesh.primitives() {
        if prim.mode() != gltf::mesh::Mode::Triangles {
            tracing::warn!(file = %path.display(), mesh = %name, mode = ?prim.mode(), "skipping non-triangle primitive");
            continue;
        }
        check_accessors(&prim).map_err(invalid)?;
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
        match (reader.read_joints(0), reader.read_weights(0)) {
            (Some(j), Some(w)) if all_have_skin => {
                let j: Vec<[u16; 4]> = j.into_u16().collect();
                let w: Vec<[f32; 4]> = w.into_f32().collect();
                if j.len() != positions.len() || w.len() != positions.len() {
                    return Err(invalid(format!(
                        "primitive {}: {} joints / {} weights for {} vertices",
                        prim.index(),
                        j.len(),
                        w.len(),
                        positions.len()
                    )));
                }
                raw_joints.extend(j);
                raw_weights.extend(w);
            }
            _ => all_have_skin = false,
        }
        if first {
            let material = prim.material();
            out.base_color = material.pbr_metallic_roughness().base_color_factor();
            out.material = match material.alpha_mode() {
                gltf::material::AlphaMode::Opaque => MaterialClass::Opaque,
                gltf::material::AlphaMode::Mask => MaterialClass::AlphaMasked,
                gltf::material::AlphaMode::Blend => MaterialClass::Transparent,
            };
            first = false;
        }
        out.indices.extend(indices.into_iter().map(|i| i + base));
        out.positions.extend(positions);
    }
    if !all_have_normals || out.normals.len() != out.positions.len() {
        out.normals.clear();
    }
    let raw = (all_have_skin && raw_joints.len() == out.positions.len())
        .then_some((raw_joints, raw_weights));
    Ok((!out.indices.is_empty()).then_some((out, raw)))
}

/// Builds a [`Skeleton`] for every skinned node's mesh and attaches it with the mesh's weights.
fn attach_skins(
    path: &Path,
    doc: &gltf::Document,
    buffers: &[gltf::buffer::Data],
    remap: &[Option<usize>],
    meshes: &mut [TriMesh],
    mut raw: Vec<RawSkin>,
) -> Result<()> {
    let mut parent = vec![None; doc.nodes().len()];
    for n in doc.nodes() {
        for c in n.children() {
            parent[c.index()] = Some(n.index());
        }
    }
    for node in doc.nodes() {
        let (Some(skin), Some(mesh)) = (node.skin(), node.mesh()) else {
            continue;
        };
        let Some(m) = remap[mesh.index()] else {
            continue;
        };
        if meshes[m].skin.is_some() {
            continue;
        }
        let Some((joints, weights)) = raw[m].take() else {
            tracing::warn!(file = %path.display(), mesh = %meshes[m].name, "skinned node's mesh lacks JOINTS_0/WEIGHTS_0; treated as static");
            continue;
        };
        let invalid = |reason: String| StreamingError::InvalidMesh {
            path: path.to_owned(),
            mesh: meshes[m].name.clone(),
            reason,
        };
        let skeleton = read_skeleton(doc, buffers, &skin, &parent).map_err(&invalid)?;
        let order = skeleton.1;
        let skeleton = skeleton.0;
        let n = skeleton.joints.len();
        let mut jw = Vec::with_capacity(joints.len());
        let mut ww = Vec::with_capacity(weights.len());
        for (v, (j, w)) in joints.iter().zip(&weights).enumerate() {
            if !w.iter().all(|x| x.is_finite() && *x >= 0.0) {
                return Err(invalid(format!("vertex {v} has an invalid skin weight")));
            }
            let sum: f32 = w.iter().sum();
            let mut out_j = [0u16; 4];
            for k in 0..4 {
                let ji = usize::from(j[k]);
                if ji >= n {
                    if w[k] > 0.0 {
                        return Err(invalid(format!("vertex {v} uses joint {ji} of {n}")));
                    }
                } else {
                    out_j[k] = order[ji];
                }
            }
            jw.push(out_j);
            ww.push(if sum > 0.0 {
                w.map(|x| x / sum)
            } else {
                [1.0, 0.0, 0.0, 0.0]
            });
        }
        meshes[m].skin = Some(SkinWeights {
            joints: jw,
            weights: ww,
            skeleton: Arc::new(skeleton),
        });
    }
    Ok(())
}

/// Reads a skin's joints (re-ordered parent-before-child) and the file's first animation.
/// Returns the skeleton and the map from the skin's joint order to the skeleton's.
fn read_skeleton(
    doc: &gltf::Document,
    buffers: &[gltf::buffer::Data],
    skin: &gltf::Skin,
    parent: &[Option<usize>],
) -> std::result::Result<(Skeleton, Vec<u16>), String> {
    let nodes: Vec<gltf::Node> = skin.joints().collect();
    if nodes.is_empty() || nodes.len() > usize::from(u16::MAX) {
        return Err(format!("skin {} has {} joints", skin.index(), nodes.len()));
    }
    let joint_of = |node: usize| nodes.iter().position(|n| n.index() == node);
    let depth = |mut node: usize| {
        let mut d = 0;
        while let Some(p) = parent[node] {
            node = p;
            d += 1;
            if d > MAX_NODE_DEPTH {
                break;
            }
        }
        d
    };
    let mut sorted: Vec<usize> = (0..nodes.len()).collect();
    sorted.sort_by_key(|&i| depth(nodes[i].index()));
    let mut order = vec![0u16; nodes.len()];
    for (new, &old) in sorted.iter().enumerate() {
        order[old] = new as u16;
    }
    use gltf::accessor::DataType::{F32, I16, I8, U16, U8};
    use gltf::accessor::Dimensions as D;
    if let Some(a) = skin.inverse_bind_matrices() {
        check_accessor(&a, "inverse bind matrices", &[F32], &[D::Mat4])?;
    }
    let reader = skin.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let ibm: Vec<Mat4> = match reader.read_inverse_bind_matrices() {
        Some(it) => it.map(|m| Mat4::from_cols_array_2d(&m)).collect(),
        None => vec![Mat4::IDENTITY; nodes.len()],
    };
    if ibm.len() < nodes.len() {
        return Err(format!(
            "{} inverse bind matrices for {} joints",
            ibm.len(),
            nodes.len()
        ));
    }
    let mut root = Mat4::IDENTITY;
    let mut joints = Vec::with_capacity(nodes.len());
    for &old in &sorted {
        let node = &nodes[old];
        // Nearest ancestor that is a joint.
        let mut p = parent[node.index()];
        let mut steps = 0;
        while let Some(pi) = p {
            if joint_of(pi).is_some() || steps > MAX_NODE_DEPTH {
                break;
            }
            p = parent[pi];
            steps += 1;
        }
        let parent_joint = p.and_then(joint_of).map(|j| order[j]);
        if parent_joint.is_none() && joints.is_empty() {
            // Non-joint ancestors of the first root joint place the whole skeleton.
            let mut a = parent[node.index()];
            let mut steps = 0;
            while let Some(ai) = a {
                if let Some(n) = doc.nodes().nth(ai) {
                    root = Mat4::from_cols_array_2d(&n.transform().matrix()) * root;
                }
                a = parent[ai];
                steps += 1;
                if steps > MAX_NODE_DEPTH {
                    return Err("joint ancestry too deep (a cycle?)".into());
                }
            }
        }
        let (t, r, s) = node.transform().decomposed();
        joints.push(Joint {
            parent: parent_joint,
            translation: Vec3::from(t),
            rotation: Quat::from_array(r),
            scale: Vec3::from(s),
            inverse_bind: ibm[old],
        });
    }
    let mut channels = Vec::new();
    let mut duration = 0.0f32;
    if let Some(anim) = doc.animations().next() {
        for ch in anim.channels() {
            let Some(j) = joint_of(ch.target().node().index()) else {
                continue;
            };
            let sampler = ch.sampler();
            check_accessor(&sampler.input(), "animation input", &[F32], &[D::Scalar])?;
            let (types, dims): (&[_], &[_]) = match ch.target().property() {
                gltf::animation::Property::Rotation => (&[F32, I8, U8, I16, U16], &[D::Vec4]),
                gltf::animation::Property::MorphTargetWeights => {
                    (&[F32, I8, U8, I16, U16], &[D::Scalar])
                }
                _ => (&[F32], &[D::Vec3]),
            };
            check_accessor(&sampler.output(), "animation output", types, dims)?;
            let r = ch.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
            let Some(times) = r.read_inputs().map(|i| i.collect::<Vec<f32>>()) else {
                return Err(format!("animation channel {} has no input", ch.index()));
            };
            use gltf::animation::util::ReadOutputs;
            let (path, mut values): (ChannelPath, Vec<Vec4>) = match r.read_outputs() {
                Some(ReadOutputs::Translations(t)) => (
                    ChannelPath::Translation,
                    t.map(|v| Vec3::from(v).extend(0.0)).collect(),
                ),
                Some(ReadOutputs::Scales(t)) => (
                    ChannelPath::Scale,
                    t.map(|v| Vec3::from(v).extend(0.0)).collect(),
                ),
                Some(ReadOutputs::Rotations(q)) => (
                    ChannelPath::Rotation,
                    q.into_f32().map(Vec4::from).collect(),
                ),
                Some(ReadOutputs::MorphTargetWeights(_)) => continue,
                None => return Err(format!("animation channel {} has no output", ch.index())),
            };
            if ch.sampler().interpolation() == gltf::animation::Interpolation::CubicSpline {
                // (in-tangent, value, out-tangent) triplets: keep the values.
                values = values.chunks(3).filter_map(|c| c.get(1).copied()).collect();
            }
            duration = duration.max(times.last().copied().unwrap_or(0.0));
            channels.push(Channel {
                joint: order[j],
                path,
                times,
                values,
            });
        }
    }
    let skeleton = Skeleton {
        joints,
        root,
        channels,
        duration,
    };
    skeleton.validate()?;
    Ok((skeleton, order))
}
