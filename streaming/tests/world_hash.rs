//! The generator's output is pinned bit for bit: an xxh3-64 hash over a canonical byte encoding
//! of the whole default world (every mesh LOD, every level, every instance) and of a small
//! preset must equal the stored constants. A change to the random source, the placement or the
//! procedural meshes that moves a single bit fails here; if the change is meant, update the
//! constant and say why in the commit.

mod common;

use glam::{Mat4, Vec3};
use rtstream_streaming::{generate, Aabb, GeneratedWorld, MeshLod, WorldPreset};
use xxhash_rust::xxh3::xxh3_64;

/// A canonical, little-endian encoding of what the generator produced (independent of the
/// baked format, which may change on its own).
#[derive(Default)]
struct Canon(Vec<u8>);

impl Canon {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn len(&mut self, n: usize) {
        self.0.extend_from_slice(&(n as u64).to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.u32(v.to_bits());
    }
    fn f32s(&mut self, v: &[f32]) {
        for &x in v {
            self.f32(x);
        }
    }
    fn vec3(&mut self, v: Vec3) {
        self.f32s(&v.to_array());
    }
    fn mat4(&mut self, m: &Mat4) {
        self.f32s(&m.to_cols_array());
    }
    fn aabb(&mut self, b: &Aabb) {
        self.vec3(b.min);
        self.vec3(b.max);
    }
    fn str(&mut self, s: &str) {
        self.len(s.len());
        self.0.extend_from_slice(s.as_bytes());
    }
    fn lod(&mut self, g: &MeshLod) {
        self.f32(g.error);
        self.len(g.positions.len());
        for p in &g.positions {
            self.f32s(p);
        }
        self.len(g.indices.len());
        for &i in &g.indices {
            self.u32(i);
        }
        match &g.skin {
            None => self.u8(0),
            Some(s) => {
                self.u8(1);
                for j in s.joints.iter().flatten() {
                    self.0.extend_from_slice(&j.to_le_bytes());
                }
                for w in &s.weights {
                    self.f32s(w);
                }
                let sk = &s.skeleton;
                self.len(sk.joints.len());
                for j in &sk.joints {
                    self.u32(j.parent.map_or(u32::MAX, u32::from));
                    self.vec3(j.translation);
                    self.f32s(&j.rotation.to_array());
                    self.vec3(j.scale);
                    self.mat4(&j.inverse_bind);
                }
                self.mat4(&sk.root);
                self.f32(sk.duration);
                self.len(sk.channels.len());
                for c in &sk.channels {
                    self.u32(u32::from(c.joint));
                    self.u8(c.path as u8);
                    self.len(c.times.len());
                    self.f32s(&c.times);
                    for v in &c.values {
                        self.f32s(&v.to_array());
                    }
                }
            }
        }
    }
    fn world(&mut self, w: &GeneratedWorld) {
        self.aabb(&w.extent);
        self.len(w.meshes.len());
        for m in &w.meshes {
            self.u32(m.id.0);
            self.str(&m.name);
            self.aabb(&m.bounds);
            self.len(m.lods.len());
            for g in &m.lods {
                self.lod(g);
            }
        }
        self.len(w.levels.len());
        for l in &w.levels {
            self.u32(l.id.0);
            self.i32(l.cell[0]);
            self.i32(l.cell[1]);
            self.aabb(&l.bounds);
            self.len(l.instances.len());
            for i in &l.instances {
                self.u32(i.id.0);
                self.u32(i.mesh.0);
                self.u8(i.material as u8);
                self.u8(i.motion as u8);
                self.mat4(&i.transform);
                self.aabb(&i.aabb);
                self.vec3(i.sphere.center);
                self.f32(i.sphere.radius);
            }
        }
    }
}

fn world_hash(preset: &WorldPreset) -> u64 {
    common::assets();
    let world = generate(preset).expect("generate");
    let mut c = Canon::default();
    c.world(&world);
    xxh3_64(&c.0)
}

/// Taken from the generator as of the commit that added this test (before the hand-written
/// SplitMix64 became `rand_xoshiro::SplitMix64`).
const DEFAULT_WORLD_HASH: u64 = 0xf159_8f52_e0ce_3e87;
const SMALL_8_SEED_7_HASH: u64 = 0x4456_411f_4688_77fe;

#[test]
fn default_world_is_bit_identical() {
    let h = world_hash(&WorldPreset::default_world());
    assert_eq!(h, DEFAULT_WORLD_HASH, "default world hash {h:#018x}");
}

#[test]
fn small_world_is_bit_identical() {
    let h = world_hash(&WorldPreset::small(8, 7));
    assert_eq!(h, SMALL_8_SEED_7_HASH, "small(8, 7) hash {h:#018x}");
}
