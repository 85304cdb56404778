//! The baked world's binary format: framing, checksums and (de)serialisation of levels, mesh
//! LODs and the manifest.
//!
//! Every file (and every mesh-LOD chunk inside the mesh library) is framed as
//! `magic[4] | version u32 | payload_len u64 | xxh3_64(payload) u64 | payload`, little-endian.
//! Readers check magic, version, length and checksum before decoding, then validate what they
//! decode (finite numbers, indices and ids in range), so a flipped byte or a truncated file is a
//! [`FormatError`], never a panic or a huge allocation.
//!
//! Version 2 (this one) writes the bulk arrays (level columns, positions, indices, skin joints
//! and weights, key frames) as their raw little-endian bytes with `bytemuck` casts, and reads them
//! back with one copy into an aligned `Vec` (the payload inside a file buffer has no alignment
//! guarantee: an aligned slice is cast and copied, an unaligned one is copied byte-wise by
//! `pod_collect_to_vec`); the checks on what was decoded run over the whole array afterwards.
//! A level holds its instances as columns (ids, meshes, 3x4 transforms, materials, motions) and a
//! LOD chunk has a header of 4-byte fields, so that every array starts 4-byte aligned within the
//! payload. Version 1 (element-by-element, FNV-1a) files are rejected with
//! [`FormatError::Version`]; re-bake them. The format is little-endian and the casts assume a
//! little-endian host: big-endian targets do not compile.

use std::sync::Arc;

use bytemuck::{AnyBitPattern, NoUninit};
use glam::{Mat4, Quat, Vec3, Vec4};
use xxhash_rust::xxh3::xxh3_64;

use crate::error::FormatError;
use crate::model::{
    Aabb, Instance, Level, LevelId, MaterialClass, MeshLod, Motion, SkinWeights, WorldInstanceId,
    WorldMeshId,
};
use crate::skeleton::{Channel, ChannelPath, Joint, Skeleton};

#[cfg(target_endian = "big")]
compile_error!("the baked format is read and written with little-endian bytemuck casts");

/// Format version written and accepted (see the module docs for what changed from 1).
pub const VERSION: u32 = 2;
/// Magic of a level file.
pub const LEVEL_MAGIC: [u8; 4] = *b"RTSL";
/// Magic of a mesh-LOD chunk.
pub const LOD_MAGIC: [u8; 4] = *b"RTSC";
/// Magic of the manifest (level table + mesh library index).
pub const MANIFEST_MAGIC: [u8; 4] = *b"RTSW";
/// Header bytes before every payload.
pub const HEADER_LEN: usize = 24;

type FResult<T> = std::result::Result<T, FormatError>;

/// The payload checksum: xxh3-64 (seed 0).
pub fn checksum(payload: &[u8]) -> u64 {
    xxh3_64(payload)
}

/// Frames a payload with magic, version, length and checksum.
pub fn frame(magic: [u8; 4], payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend_from_slice(&magic);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&checksum(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// Checks a framed buffer and returns its payload.
pub fn unframe(magic: [u8; 4], bytes: &[u8]) -> FResult<&[u8]> {
    let mut r = Reader::new(bytes);
    let found: [u8; 4] = r.array()?;
    if found != magic {
        return Err(FormatError::BadMagic {
            expected: magic,
            found,
        });
    }
    let version = r.u32()?;
    if version != VERSION {
        return Err(FormatError::Version {
            found: version,
            supported: VERSION,
        });
    }
    let len = r.u64()?;
    let expected = r.u64()?;
    let len =
        usize::try_from(len).map_err(|_| FormatError::Inconsistent("payload too long".into()))?;
    let payload = r.bytes(len)?;
    if r.remaining() != 0 {
        return Err(FormatError::Inconsistent(format!(
            "{} trailing bytes after the payload",
            r.remaining()
        )));
    }
    let actual = checksum(payload);
    if actual != expected {
        return Err(FormatError::Checksum { expected, actual });
    }
    Ok(payload)
}

/// Little-endian writer.
#[derive(Debug, Default)]
pub(crate) struct Writer(pub Vec<u8>);

impl Writer {
    pub fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    pub fn u16(&mut self, v: u16) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i32(&mut self, v: i32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f32s(&mut self, v: &[f32]) {
        for &x in v {
            self.f32(x);
        }
    }
    pub fn vec3(&mut self, v: Vec3) {
        self.f32s(&v.to_array());
    }
    pub fn aabb(&mut self, b: &Aabb) {
        self.vec3(b.min);
        self.vec3(b.max);
    }
    pub fn str(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.0.extend_from_slice(s.as_bytes());
    }
    /// A bulk array as its raw (little-endian) bytes, in one copy.
    pub fn pod<T: NoUninit>(&mut self, v: &[T]) {
        self.0.extend_from_slice(bytemuck::cast_slice(v));
    }
}

/// Little-endian reader whose every read is bounds-checked.
#[derive(Debug)]
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Reader { bytes, pos: 0 }
    }
    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }
    pub fn bytes(&mut self, n: usize) -> FResult<&'a [u8]> {
        if self.remaining() < n {
            return Err(FormatError::Truncated {
                offset: self.pos,
                needed: n,
                available: self.remaining(),
            });
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    pub fn array<const N: usize>(&mut self) -> FResult<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.bytes(N)?);
        Ok(a)
    }
    pub fn u8(&mut self) -> FResult<u8> {
        Ok(self.array::<1>()?[0])
    }
    pub fn u16(&mut self) -> FResult<u16> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    pub fn u32(&mut self) -> FResult<u32> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    pub fn i32(&mut self) -> FResult<i32> {
        Ok(i32::from_le_bytes(self.array()?))
    }
    pub fn u64(&mut self) -> FResult<u64> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    /// A finite f32.
    pub fn f32(&mut self) -> FResult<f32> {
        let v = f32::from_le_bytes(self.array()?);
        if !v.is_finite() {
            return Err(FormatError::Inconsistent(format!(
                "non-finite number at offset {}",
                self.pos - 4
            )));
        }
        Ok(v)
    }
    pub fn vec3(&mut self) -> FResult<Vec3> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }
    pub fn vec4(&mut self) -> FResult<Vec4> {
        Ok(Vec4::new(
            self.f32()?,
            self.f32()?,
            self.f32()?,
            self.f32()?,
        ))
    }
    /// Bounds: finite with min <= max, or exactly [`Aabb::EMPTY`] (what the writer writes for
    /// nothing: an empty world's extent, a proxy node without opaque static content).
    pub fn aabb(&mut self) -> FResult<Aabb> {
        let start = self.pos;
        let raw: [u8; 24] = self.array()?;
        let f: [f32; 6] =
            std::array::from_fn(|i| f32::from_le_bytes(raw[4 * i..4 * i + 4].try_into().unwrap()));
        let e = Aabb::EMPTY;
        if f[..3] == e.min.to_array() && f[3..] == e.max.to_array() {
            return Ok(Aabb::EMPTY);
        }
        self.pos = start;
        let b = Aabb {
            min: self.vec3()?,
            max: self.vec3()?,
        };
        if !b.is_valid() {
            return Err(FormatError::Inconsistent("bounds with min > max".into()));
        }
        Ok(b)
    }
    /// A count of items of `item_size` bytes each that must fit in what is left.
    pub fn count(&mut self, item_size: usize) -> FResult<usize> {
        let n = self.u32()? as usize;
        let needed = n.saturating_mul(item_size);
        if needed > self.remaining() {
            return Err(FormatError::Truncated {
                offset: self.pos,
                needed,
                available: self.remaining(),
            });
        }
        Ok(n)
    }
    pub fn str(&mut self) -> FResult<String> {
        let n = self.count(1)?;
        String::from_utf8(self.bytes(n)?.to_vec())
            .map_err(|_| FormatError::Inconsistent("name is not UTF-8".into()))
    }
    /// `n` items of a plain-data type, copied out of the payload into an aligned `Vec`. The
    /// bounds are checked before anything is allocated.
    pub fn pod<T: NoUninit + AnyBitPattern>(&mut self, n: usize) -> FResult<Vec<T>> {
        let len = n
            .checked_mul(std::mem::size_of::<T>())
            .ok_or(FormatError::Truncated {
                offset: self.pos,
                needed: usize::MAX,
                available: self.remaining(),
            })?;
        let bytes = self.bytes(len)?;
        Ok(match bytemuck::try_cast_slice::<u8, T>(bytes) {
            Ok(aligned) => aligned.to_vec(),
            Err(_) => bytemuck::pod_collect_to_vec(bytes),
        })
    }
    /// `n` items of `T`, which is `f32` or an array of `f32`, every number finite.
    pub fn finite<T: NoUninit + AnyBitPattern>(&mut self, n: usize) -> FResult<Vec<T>> {
        let start = self.pos;
        let v: Vec<T> = self.pod(n)?;
        let floats: &[f32] = bytemuck::cast_slice(&v);
        if let Some(k) = floats.iter().position(|x| !x.is_finite()) {
            return Err(FormatError::Inconsistent(format!(
                "non-finite number at offset {}",
                start + 4 * k
            )));
        }
        Ok(v)
    }
}

/// Encodes a level: its header, then its instances as columns: ids, meshes, 3x4 affine
/// transforms (column-major, the implied last row dropped), material classes, motions (58 bytes
/// per instance). World bounds are re-derived from the mesh bounds on load.
pub fn encode_level(level: &Level) -> Vec<u8> {
    let inst = &level.instances;
    let mut w = Writer(Vec::with_capacity(40 + 58 * inst.len()));
    w.u32(level.id.0);
    w.i32(level.cell[0]);
    w.i32(level.cell[1]);
    w.aabb(&level.bounds);
    w.u32(inst.len() as u32);
    w.pod(&inst.iter().map(|i| i.id.0).collect::<Vec<u32>>());
    w.pod(&inst.iter().map(|i| i.mesh.0).collect::<Vec<u32>>());
    let affine = |m: &Mat4| {
        let c = m.to_cols_array();
        let mut a = [0f32; 12];
        for col in 0..4 {
            a[col * 3..col * 3 + 3].copy_from_slice(&c[col * 4..col * 4 + 3]);
        }
        a
    };
    w.pod(
        &inst
            .iter()
            .map(|i| affine(&i.transform))
            .collect::<Vec<_>>(),
    );
    w.pod(&inst.iter().map(|i| i.material as u8).collect::<Vec<u8>>());
    w.pod(&inst.iter().map(|i| i.motion as u8).collect::<Vec<u8>>());
    frame(LEVEL_MAGIC, &w.0)
}

/// Decodes and validates a level file; `mesh_bounds[m]` are the library's mesh-space bounds.
pub fn decode_level(bytes: &[u8], mesh_bounds: &[Aabb]) -> FResult<Level> {
    let mut r = Reader::new(unframe(LEVEL_MAGIC, bytes)?);
    let id = LevelId(r.u32()?);
    let cell = [r.i32()?, r.i32()?];
    let bounds = r.aabb()?;
    let n = r.count(58)?;
    let ids: Vec<u32> = r.pod(n)?;
    let meshes: Vec<u32> = r.pod(n)?;
    let transforms: Vec<[f32; 12]> = r.finite(n)?;
    let materials = r.bytes(n)?;
    let motions = r.bytes(n)?;
    if r.remaining() != 0 {
        return Err(FormatError::Inconsistent(format!(
            "{} unread bytes",
            r.remaining()
        )));
    }
    let mut instances = Vec::with_capacity(n);
    for k in 0..n {
        let bad = |what: String| FormatError::Inconsistent(format!("instance {k}: {what}"));
        let mesh = meshes[k];
        let mb = mesh_bounds.get(mesh as usize).ok_or_else(|| {
            bad(format!(
                "mesh {mesh} not in the library ({} meshes)",
                mesh_bounds.len()
            ))
        })?;
        let mat = materials[k];
        let material =
            MaterialClass::from_u8(mat).ok_or_else(|| bad(format!("material class {mat}")))?;
        let motion = match motions[k] {
            0 => Motion::Static,
            1 => Motion::Skinned,
            m => return Err(bad(format!("motion {m}"))),
        };
        let a = &transforms[k];
        let mut c = [0f32; 16];
        for col in 0..4 {
            c[col * 4..col * 4 + 3].copy_from_slice(&a[col * 3..col * 3 + 3]);
        }
        c[15] = 1.0;
        instances.push(Instance::new(
            WorldInstanceId(ids[k]),
            WorldMeshId(mesh),
            Mat4::from_cols_array(&c),
            mb,
            material,
            motion,
        ));
    }
    Ok(Level {
        id,
        cell,
        bounds,
        instances,
    })
}

fn write_skeleton(w: &mut Writer, s: &Skeleton) {
    w.u32(s.joints.len() as u32);
    for j in &s.joints {
        w.u16(j.parent.map_or(u16::MAX, |p| p));
        w.vec3(j.translation);
        w.f32s(&j.rotation.to_array());
        w.vec3(j.scale);
        w.f32s(&j.inverse_bind.to_cols_array());
    }
    w.f32s(&s.root.to_cols_array());
    w.f32(s.duration);
    w.u32(s.channels.len() as u32);
    for c in &s.channels {
        w.u16(c.joint);
        w.u8(c.path as u8);
        w.u32(c.times.len() as u32);
        w.pod(&c.times);
        w.pod(&c.values.iter().map(|v| v.to_array()).collect::<Vec<_>>());
    }
}

fn read_mat4(r: &mut Reader) -> FResult<Mat4> {
    let mut c = [0f32; 16];
    for x in &mut c {
        *x = r.f32()?;
    }
    Ok(Mat4::from_cols_array(&c))
}

fn read_skeleton(r: &mut Reader) -> FResult<Skeleton> {
    let n = r.count(2 + 4 * (3 + 4 + 3 + 16))?;
    let mut joints = Vec::with_capacity(n);
    for _ in 0..n {
        let p = r.u16()?;
        joints.push(Joint {
            parent: (p != u16::MAX).then_some(p),
            translation: r.vec3()?,
            rotation: Quat::from_vec4(r.vec4()?),
            scale: r.vec3()?,
            inverse_bind: read_mat4(r)?,
        });
    }
    let root = read_mat4(r)?;
    let duration = r.f32()?;
    let nc = r.count(7)?;
    let mut channels = Vec::with_capacity(nc);
    for _ in 0..nc {
        let joint = r.u16()?;
        let path = match r.u8()? {
            0 => ChannelPath::Translation,
            1 => ChannelPath::Rotation,
            2 => ChannelPath::Scale,
            p => return Err(FormatError::Inconsistent(format!("channel path {p}"))),
        };
        let keys = r.count(20)?;
        let times: Vec<f32> = r.finite(keys)?;
        let values: Vec<[f32; 4]> = r.finite(keys)?;
        let values = values.into_iter().map(Vec4::from_array).collect();
        channels.push(Channel {
            joint,
            path,
            times,
            values,
        });
    }
    let s = Skeleton {
        joints,
        root,
        channels,
        duration,
    };
    s.validate().map_err(FormatError::Inconsistent)?;
    Ok(s)
}

/// Encodes one LOD of one mesh as a framed chunk: a header of 4-byte fields (mesh, LOD, error,
/// vertex count, index count, skinned flag), positions, indices, and for a skinned LOD the joint
/// indices, weights and the skeleton.
pub fn encode_lod(mesh: WorldMeshId, lod: usize, g: &MeshLod) -> Vec<u8> {
    let mut w = Writer(Vec::with_capacity(24 + g.byte_size()));
    w.u32(mesh.0);
    w.u32(lod as u32);
    w.f32(g.error);
    w.u32(g.positions.len() as u32);
    w.u32(g.indices.len() as u32);
    w.u32(u32::from(g.skin.is_some()));
    w.pod(&g.positions);
    w.pod(&g.indices);
    if let Some(s) = &g.skin {
        w.pod(&s.joints);
        w.pod(&s.weights);
        write_skeleton(&mut w, &s.skeleton);
    }
    frame(LOD_MAGIC, &w.0)
}

/// Decodes and validates one mesh-LOD chunk; it must be `(mesh, lod)`.
pub fn decode_lod(bytes: &[u8], mesh: WorldMeshId, lod: usize) -> FResult<MeshLod> {
    let mut r = Reader::new(unframe(LOD_MAGIC, bytes)?);
    let (m, l) = (r.u32()?, r.u32()?);
    if m != mesh.0 || l as usize != lod {
        return Err(FormatError::Inconsistent(format!(
            "chunk holds mesh {m} LOD {l}, index says mesh {} LOD {lod}",
            mesh.0
        )));
    }
    let error = r.f32()?;
    let nv = r.u32()? as usize;
    let ni = r.u32()? as usize;
    let skinned = r.u32()?;
    if ni % 3 != 0 {
        return Err(FormatError::Inconsistent(format!(
            "{ni} indices is not a multiple of 3"
        )));
    }
    let positions: Vec<[f32; 3]> = r.finite(nv)?;
    let indices: Vec<u32> = r.pod(ni)?;
    if let Some(i) = indices.iter().find(|&&i| i as usize >= nv) {
        return Err(FormatError::Inconsistent(format!(
            "index {i} out of range ({nv} vertices)"
        )));
    }
    let skin = match skinned {
        0 => None,
        1 => {
            let joints: Vec<[u16; 4]> = r.pod(nv)?;
            let weights: Vec<[f32; 4]> = r.finite(nv)?;
            let skeleton = read_skeleton(&mut r)?;
            let nj = skeleton.joints.len();
            if joints.iter().flatten().any(|&j| usize::from(j) >= nj) {
                return Err(FormatError::Inconsistent(
                    "skin joint index out of range".into(),
                ));
            }
            Some(SkinWeights {
                joints,
                weights,
                skeleton: Arc::new(skeleton),
            })
        }
        s => return Err(FormatError::Inconsistent(format!("skin flag {s}"))),
    };
    if r.remaining() != 0 {
        return Err(FormatError::Inconsistent(format!(
            "{} unread bytes",
            r.remaining()
        )));
    }
    Ok(MeshLod {
        positions,
        indices,
        error,
        skin,
    })
}

#[cfg(test)]
mod tests;
