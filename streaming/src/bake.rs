//! Baking a generated world to disk and reading its manifest back.
//!
//! Layout of a baked world directory:
//! - `world.rtw`: the manifest — level table (id, cell, bounds, file) and the mesh library index
//!   (per mesh: name, bounds, and per LOD: offset and length in `meshes.rtm`, triangles, bytes,
//!   error). Framed and checksummed like every other file.
//! - `meshes.rtm`: the mesh library, the concatenation of framed, individually checksummed LOD
//!   chunks, so a loader reads one LOD of one mesh with one seek.
//! - `levels/<id>.rtl`: one framed level file per level.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::error::{FormatError, Result, StreamingError};
use crate::format::{self, Reader, Writer, MANIFEST_MAGIC};
use crate::generate::GeneratedWorld;
use crate::model::{Aabb, LevelId, MeshLod, WorldMeshId};

/// File name of the manifest inside a baked world directory.
pub const MANIFEST_FILE: &str = "world.rtw";
/// File name of the mesh library.
pub const MESH_LIBRARY_FILE: &str = "meshes.rtm";

/// Where one LOD chunk lies in the mesh library, and what it holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LodEntry {
    /// Byte offset in the mesh library.
    pub offset: u64,
    /// Chunk length in bytes (header included).
    pub len: u64,
    /// Triangles.
    pub triangles: u32,
    /// CPU bytes once loaded (what the mesh budget counts).
    pub bytes: u32,
    /// Geometric error in mesh-space metres.
    pub error: f32,
}

/// A mesh in the library index.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshEntry {
    /// Its id.
    pub id: WorldMeshId,
    /// Name.
    pub name: String,
    /// Mesh-space bounds.
    pub bounds: Aabb,
    /// LOD0 first.
    pub lods: Vec<LodEntry>,
}

/// A level in the manifest.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelEntry {
    /// Its id.
    pub id: LevelId,
    /// Grid cell.
    pub cell: [i32; 2],
    /// World bounds.
    pub bounds: Aabb,
    /// File, relative to the world directory.
    pub file: String,
}

/// The manifest of a baked world.
#[derive(Debug, Clone, PartialEq)]
pub struct Manifest {
    /// Map bounds.
    pub extent: Aabb,
    /// Levels, indexed by id.
    pub levels: Vec<LevelEntry>,
    /// Meshes, indexed by id.
    pub meshes: Vec<MeshEntry>,
}

/// What baking wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BakeReport {
    /// Level files written.
    pub level_files: usize,
    /// Bytes over all level files.
    pub level_bytes: u64,
    /// Bytes of the mesh library.
    pub mesh_library_bytes: u64,
    /// The far-field proxies written to [`crate::proxy::PROXY_FILE`].
    pub proxies: crate::proxy::ProxyReport,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StreamingError + '_ {
    move |source| StreamingError::Io {
        path: path.to_owned(),
        source,
    }
}

/// Writes a generated world to `dir` (created if needed).
///
/// ```no_run
/// use rtstream_streaming::{bake, generate, WorldPreset};
/// let world = generate(&WorldPreset::small(4, 1))?;
/// bake(&world, "/tmp/rtstream-world")?;
/// # Ok::<(), rtstream_streaming::StreamingError>(())
/// ```
pub fn bake(world: &GeneratedWorld, dir: impl AsRef<Path>) -> Result<BakeReport> {
    let dir = dir.as_ref();
    let _span = tracing::info_span!("bake", dir = %dir.display()).entered();
    let level_dir = dir.join("levels");
    std::fs::create_dir_all(&level_dir).map_err(io(&level_dir))?;

    let mut lib = Vec::new();
    let mut meshes = Vec::with_capacity(world.meshes.len());
    // A LOD shared by several meshes (a district's copies share the library mesh's) is
    // written once; their index entries name the same chunk, which names the first of them.
    let mut written: std::collections::HashMap<(*const MeshLod, usize), LodEntry> =
        std::collections::HashMap::new();
    for m in &world.meshes {
        let mut lods = Vec::with_capacity(m.lods.len());
        for (k, g) in m.lods.iter().enumerate() {
            if let Some(&e) = written.get(&(Arc::as_ptr(g), k)) {
                lods.push(e);
                continue;
            }
            let chunk = format::encode_lod(m.id, k, g);
            let e = LodEntry {
                offset: lib.len() as u64,
                len: chunk.len() as u64,
                triangles: g.triangle_count() as u32,
                bytes: g.byte_size() as u32,
                error: g.error,
            };
            written.insert((Arc::as_ptr(g), k), e);
            lods.push(e);
            lib.extend_from_slice(&chunk);
        }
        meshes.push(MeshEntry {
            id: m.id,
            name: m.name.clone(),
            bounds: m.bounds,
            lods,
        });
    }
    let lib_path = dir.join(MESH_LIBRARY_FILE);
    std::fs::write(&lib_path, &lib).map_err(io(&lib_path))?;

    let mut levels = Vec::with_capacity(world.levels.len());
    let mut level_bytes = 0u64;
    for l in &world.levels {
        let file = format!("levels/{:06}.rtl", l.id.0);
        let bytes = format::encode_level(l);
        let path = dir.join(&file);
        std::fs::write(&path, &bytes).map_err(io(&path))?;
        level_bytes += bytes.len() as u64;
        levels.push(LevelEntry {
            id: l.id,
            cell: l.cell,
            bounds: l.bounds,
            file,
        });
    }
    let manifest = Manifest {
        extent: world.extent,
        levels,
        meshes,
    };
    let (proxies, mut proxy_report) =
        crate::proxy::build_proxies(world, &crate::proxy::ProxyConfig::default());
    let bytes = crate::proxy::encode_proxies(&proxies);
    proxy_report.file_bytes = bytes.len() as u64;
    let proxy_path = dir.join(crate::proxy::PROXY_FILE);
    std::fs::write(&proxy_path, &bytes).map_err(io(&proxy_path))?;
    let path = dir.join(MANIFEST_FILE);
    std::fs::write(&path, encode_manifest(&manifest)).map_err(io(&path))?;
    Ok(BakeReport {
        level_files: world.levels.len(),
        level_bytes,
        mesh_library_bytes: lib.len() as u64,
        proxies: proxy_report,
    })
}

fn encode_manifest(m: &Manifest) -> Vec<u8> {
    let mut w = Writer::default();
    w.aabb(&m.extent);
    w.u32(m.levels.len() as u32);
    for l in &m.levels {
        w.u32(l.id.0);
        w.i32(l.cell[0]);
        w.i32(l.cell[1]);
        w.aabb(&l.bounds);
        w.str(&l.file);
    }
    w.u32(m.meshes.len() as u32);
    for mesh in &m.meshes {
        w.u32(mesh.id.0);
        w.str(&mesh.name);
        w.aabb(&mesh.bounds);
        w.u32(mesh.lods.len() as u32);
        for e in &mesh.lods {
            w.u64(e.offset);
            w.u64(e.len);
            w.u32(e.triangles);
            w.u32(e.bytes);
            w.f32(e.error);
        }
    }
    format::frame(MANIFEST_MAGIC, &w.0)
}

/// Reads and validates a baked world's manifest.
pub fn read_manifest(dir: impl AsRef<Path>) -> Result<Manifest> {
    let path = dir.as_ref().join(MANIFEST_FILE);
    let bytes = std::fs::read(&path).map_err(io(&path))?;
    decode_manifest(&bytes).map_err(|reason| StreamingError::Format { path, reason })
}

pub(crate) fn decode_manifest(bytes: &[u8]) -> std::result::Result<Manifest, FormatError> {
    let mut r = Reader::new(format::unframe(MANIFEST_MAGIC, bytes)?);
    let bad = |s: String| FormatError::Inconsistent(s);
    // Entry `k` of a table (`what`) starts with its id, which must be `k`.
    let id_of = |r: &mut Reader<'_>, what: &str, k: usize| {
        let id = r.u32()?;
        if id as usize != k {
            return Err(bad(format!("{what} {k} has id {id}")));
        }
        Ok(id)
    };
    let extent = r.aabb()?;
    let nl = r.count(4 + 8 + 24 + 4)?;
    let mut levels = Vec::with_capacity(nl);
    for k in 0..nl {
        let id = LevelId(id_of(&mut r, "level", k)?);
        let cell = [r.i32()?, r.i32()?];
        let bounds = r.aabb()?;
        let file = r.str()?;
        if file.contains("..") || Path::new(&file).is_absolute() {
            return Err(bad(format!(
                "level file {file:?} escapes the world directory"
            )));
        }
        levels.push(LevelEntry {
            id,
            cell,
            bounds,
            file,
        });
    }
    let nm = r.count(4 + 4 + 24 + 4)?;
    let mut meshes = Vec::with_capacity(nm);
    for k in 0..nm {
        let id = WorldMeshId(id_of(&mut r, "mesh", k)?);
        let name = r.str()?;
        let bounds = r.aabb()?;
        let n = r.count(28)?;
        if n == 0 || n > 255 {
            return Err(bad(format!("mesh {k} has {n} LODs")));
        }
        let mut lods = Vec::with_capacity(n);
        for _ in 0..n {
            lods.push(LodEntry {
                offset: r.u64()?,
                len: r.u64()?,
                triangles: r.u32()?,
                bytes: r.u32()?,
                error: r.f32()?,
            });
        }
        meshes.push(MeshEntry {
            id,
            name,
            bounds,
            lods,
        });
    }
    if r.remaining() != 0 {
        return Err(bad(format!("{} unread bytes", r.remaining())));
    }
    Ok(Manifest {
        extent,
        levels,
        meshes,
    })
}

impl Manifest {
    /// Path of a level's file.
    pub fn level_path(&self, dir: &Path, level: LevelId) -> Option<PathBuf> {
        self.levels.get(level.0 as usize).map(|l| dir.join(&l.file))
    }
}
