//! The baked world's binary format: framing, checksums and (de)serialisation of levels, mesh
//! LODs and the manifest.
//!
//! Every file (and every mesh-LOD chunk inside the mesh library) is framed as
//! `magic[4] | version u32 | payload_len u64 | fnv1a64(payload) u64 | payload`, little-endian.
//! Readers check magic, version, length and checksum before decoding, then validate what they
//! decode (finite numbers, indices and ids in range), so a flipped byte or a truncated file is a
//! [`FormatError`], never a panic or a huge allocation.

use std::sync::Arc;

use glam::{Mat4, Quat, Vec3, Vec4};

use crate::error::FormatError;
use crate::model::{
    Aabb, Instance, InstanceId, Level, LevelId, LodGeometry, MaterialClass, MeshId, Motion,
    SkinWeights,
};
use crate::skeleton::{Channel, ChannelPath, Joint, Skeleton};

/// Format version written and accepted.
pub const VERSION: u32 = 1;
/// Magic of a level file.
pub const LEVEL_MAGIC: [u8; 4] = *b"RTSL";
/// Magic of a mesh-LOD chunk.
pub const LOD_MAGIC: [u8; 4] = *b"RTSC";
/// Magic of the manifest (level table + mesh library index).
pub const MANIFEST_MAGIC: [u8; 4] = *b"RTSW";
/// Header bytes before every payload.
pub const HEADER_LEN: usize = 24;

type FResult<T> = std::result::Result<T, FormatError>;

/// 64-bit FNV-1a.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Frames a payload with magic, version, length and checksum.
pub fn frame(magic: [u8; 4], payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
    out.extend_from_slice(&magic);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&fnv1a64(payload).to_le_bytes());
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
    let actual = fnv1a64(payload);
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
    pub fn aabb(&mut self) -> FResult<Aabb> {
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
}

/// Encodes a level: its header and, per instance, id, mesh, material, motion and a 3x4 affine
/// transform (58 bytes). World bounds are re-derived from the mesh bounds on load.
pub fn encode_level(level: &Level) -> Vec<u8> {
    let mut w = Writer::default();
    w.u32(level.id.0);
    w.i32(level.cell[0]);
    w.i32(level.cell[1]);
    w.aabb(&level.bounds);
    w.u32(level.instances.len() as u32);
    for i in &level.instances {
        w.u32(i.id.0);
        w.u32(i.mesh.0);
        w.u8(i.material as u8);
        w.u8(i.motion as u8);
        let c = i.transform.to_cols_array();
        for col in 0..4 {
            w.f32s(&c[col * 4..col * 4 + 3]);
        }
    }
    frame(LEVEL_MAGIC, &w.0)
}

/// Decodes and validates a level file; `mesh_bounds[m]` are the library's mesh-space bounds.
pub fn decode_level(bytes: &[u8], mesh_bounds: &[Aabb]) -> FResult<Level> {
    let mut r = Reader::new(unframe(LEVEL_MAGIC, bytes)?);
    let id = LevelId(r.u32()?);
    let cell = [r.i32()?, r.i32()?];
    let bounds = r.aabb()?;
    let n = r.count(58)?;
    let mut instances = Vec::with_capacity(n);
    for k in 0..n {
        let iid = InstanceId(r.u32()?);
        let mesh = r.u32()?;
        let bad = |what: String| FormatError::Inconsistent(format!("instance {k}: {what}"));
        let mb = mesh_bounds.get(mesh as usize).ok_or_else(|| {
            bad(format!(
                "mesh {mesh} not in the library ({} meshes)",
                mesh_bounds.len()
            ))
        })?;
        let mat = r.u8()?;
        let material =
            MaterialClass::from_u8(mat).ok_or_else(|| bad(format!("material class {mat}")))?;
        let motion = match r.u8()? {
            0 => Motion::Static,
            1 => Motion::Skinned,
            m => return Err(bad(format!("motion {m}"))),
        };
        let mut c = [0f32; 16];
        for col in 0..4 {
            for row in 0..3 {
                c[col * 4 + row] = r.f32()?;
            }
        }
        c[15] = 1.0;
        let transform = Mat4::from_cols_array(&c);
        instances.push(Instance::new(
            iid,
            MeshId(mesh),
            transform,
            mb,
            material,
            motion,
        ));
    }
    if r.remaining() != 0 {
        return Err(FormatError::Inconsistent(format!(
            "{} unread bytes",
            r.remaining()
        )));
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
        w.f32s(&c.times);
        for v in &c.values {
            w.f32s(&v.to_array());
        }
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
        let times = (0..keys).map(|_| r.f32()).collect::<FResult<Vec<_>>>()?;
        let values = (0..keys).map(|_| r.vec4()).collect::<FResult<Vec<_>>>()?;
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

/// Encodes one LOD of one mesh as a framed chunk.
pub fn encode_lod(mesh: MeshId, lod: usize, g: &LodGeometry) -> Vec<u8> {
    let mut w = Writer::default();
    w.u32(mesh.0);
    w.u8(lod as u8);
    w.f32(g.error);
    w.u32(g.positions.len() as u32);
    for p in &g.positions {
        w.f32s(p);
    }
    w.u32(g.indices.len() as u32);
    for &i in &g.indices {
        w.u32(i);
    }
    match &g.skin {
        None => w.u8(0),
        Some(s) => {
            w.u8(1);
            for j in &s.joints {
                for &x in j {
                    w.u16(x);
                }
            }
            for x in &s.weights {
                w.f32s(x);
            }
            write_skeleton(&mut w, &s.skeleton);
        }
    }
    frame(LOD_MAGIC, &w.0)
}

/// Decodes and validates one mesh-LOD chunk; it must be `(mesh, lod)`.
pub fn decode_lod(bytes: &[u8], mesh: MeshId, lod: usize) -> FResult<LodGeometry> {
    let mut r = Reader::new(unframe(LOD_MAGIC, bytes)?);
    let (m, l) = (r.u32()?, r.u8()?);
    if m != mesh.0 || usize::from(l) != lod {
        return Err(FormatError::Inconsistent(format!(
            "chunk holds mesh {m} LOD {l}, index says mesh {} LOD {lod}",
            mesh.0
        )));
    }
    let error = r.f32()?;
    let nv = r.count(12)?;
    let mut positions = Vec::with_capacity(nv);
    for _ in 0..nv {
        positions.push(r.vec3()?.to_array());
    }
    let ni = r.count(4)?;
    if ni % 3 != 0 {
        return Err(FormatError::Inconsistent(format!(
            "{ni} indices is not a multiple of 3"
        )));
    }
    let mut indices = Vec::with_capacity(ni);
    for _ in 0..ni {
        let i = r.u32()?;
        if i as usize >= nv {
            return Err(FormatError::Inconsistent(format!(
                "index {i} out of range ({nv} vertices)"
            )));
        }
        indices.push(i);
    }
    let skin = match r.u8()? {
        0 => None,
        1 => {
            let mut joints = Vec::with_capacity(nv);
            for _ in 0..nv {
                joints.push([r.u16()?, r.u16()?, r.u16()?, r.u16()?]);
            }
            let mut weights = Vec::with_capacity(nv);
            for _ in 0..nv {
                weights.push(r.vec4()?.to_array());
            }
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
    Ok(LodGeometry {
        positions,
        indices,
        error,
        skin,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural;

    fn sample_level() -> (Level, Vec<Aabb>) {
        let bounds = vec![Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        }];
        let instances = (0..5)
            .map(|k| {
                Instance::new(
                    InstanceId(100 + k),
                    MeshId(0),
                    Mat4::from_translation(Vec3::new(k as f32, 0.0, 2.0)),
                    &bounds[0],
                    MaterialClass::from_u8((k % 4) as u8).unwrap_or(MaterialClass::Opaque),
                    if k == 3 {
                        Motion::Skinned
                    } else {
                        Motion::Static
                    },
                )
            })
            .collect();
        let level = Level {
            id: LevelId(9),
            cell: [3, -4],
            bounds: Aabb {
                min: Vec3::splat(-5.0),
                max: Vec3::splat(5.0),
            },
            instances,
        };
        (level, bounds)
    }

    #[test]
    fn level_round_trips() {
        let (level, bounds) = sample_level();
        let bytes = encode_level(&level);
        let back = decode_level(&bytes, &bounds).expect("decode");
        assert_eq!(back, level);
    }

    #[test]
    fn every_truncation_and_every_byte_flip_of_a_level_is_an_error() {
        let (level, bounds) = sample_level();
        let bytes = encode_level(&level);
        for n in 0..bytes.len() {
            assert!(
                decode_level(&bytes[..n], &bounds).is_err(),
                "truncated to {n} accepted"
            );
        }
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 0x01;
            assert!(decode_level(&b, &bounds).is_err(), "flip at {i} accepted");
        }
    }

    #[test]
    fn unknown_mesh_and_non_finite_transform_are_rejected_even_with_a_valid_checksum() {
        let (mut level, bounds) = sample_level();
        level.instances[2].mesh = MeshId(7);
        let err = decode_level(&encode_level(&level), &bounds).unwrap_err();
        assert!(
            matches!(err, FormatError::Inconsistent(ref s) if s.contains("mesh 7")),
            "{err}"
        );
        let (mut level, bounds) = sample_level();
        level.instances[1].transform.w_axis.x = f32::NAN;
        let err = decode_level(&encode_level(&level), &bounds).unwrap_err();
        assert!(
            matches!(err, FormatError::Inconsistent(ref s) if s.contains("non-finite")),
            "{err}"
        );
    }

    #[test]
    fn skinned_lod_round_trips_and_rejects_corruption() {
        let mesh = procedural::character(3);
        let lod = mesh.lods.last().expect("lod");
        let bytes = encode_lod(MeshId(4), mesh.lods.len() - 1, lod);
        let back = decode_lod(&bytes, MeshId(4), mesh.lods.len() - 1).expect("decode");
        assert_eq!(&back, &**lod);
        assert!(decode_lod(&bytes, MeshId(5), mesh.lods.len() - 1).is_err());
        for i in (0..bytes.len()).step_by(7) {
            let mut b = bytes.clone();
            b[i] ^= 0x80;
            assert!(
                decode_lod(&b, MeshId(4), mesh.lods.len() - 1).is_err(),
                "flip at {i} accepted"
            );
        }
        for n in (0..bytes.len()).step_by(5) {
            assert!(decode_lod(&bytes[..n], MeshId(4), mesh.lods.len() - 1).is_err());
        }
    }

    #[test]
    fn out_of_range_index_is_rejected() {
        let (pos, mut idx) = procedural::glass_pane(1);
        idx[4] = pos.len() as u32;
        let g = LodGeometry {
            positions: pos,
            indices: idx,
            error: 0.0,
            skin: None,
        };
        let err = decode_lod(&encode_lod(MeshId(0), 0, &g), MeshId(0), 0).unwrap_err();
        assert!(
            matches!(err, FormatError::Inconsistent(ref s) if s.contains("out of range")),
            "{err}"
        );
    }
}
