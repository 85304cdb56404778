//! The synthetic worlds are pinned bit for bit: an xxh3-64 hash over a canonical byte encoding
//! of every mesh description and instance placement must equal the stored constants. If a change
//! to the random source or the placement is meant, update the constants and say why.

use rtstream_as_manager::synth::{SynthParams, SynthWorld};
use rtstream_as_manager::{LodGeometry, MeshKind};
use xxhash_rust::xxh3::xxh3_64;

fn synth_hash(params: SynthParams) -> u64 {
    let w = SynthWorld::generate(params);
    let mut b = Vec::new();
    let f32s = |b: &mut Vec<u8>, v: &[f32]| {
        for x in v {
            b.extend_from_slice(&x.to_bits().to_le_bytes());
        }
    };
    b.extend_from_slice(&(w.meshes.len() as u64).to_le_bytes());
    for m in &w.meshes {
        b.extend_from_slice(&(m.name.len() as u64).to_le_bytes());
        b.extend_from_slice(m.name.as_bytes());
        b.push(match m.kind {
            MeshKind::Static => 0,
            MeshKind::Skinned => 1,
        });
        b.push(u8::from(m.opaque));
        f32s(&mut b, &m.bounds_center);
        f32s(&mut b, &[m.bounds_radius]);
        b.extend_from_slice(&(m.lods.len() as u64).to_le_bytes());
        for l in &m.lods {
            match &l.geometry {
                LodGeometry::Counts {
                    vertices,
                    triangles,
                } => {
                    b.extend_from_slice(&vertices.to_le_bytes());
                    b.extend_from_slice(&triangles.to_le_bytes());
                }
                LodGeometry::Data(_) | LodGeometry::Device(_) => {
                    panic!("synthetic meshes are counts only")
                }
            }
            f32s(&mut b, &[l.geometric_error]);
        }
    }
    b.extend_from_slice(&(w.instances.len() as u64).to_le_bytes());
    for (mesh, t) in &w.instances {
        b.extend_from_slice(&(*mesh as u64).to_le_bytes());
        f32s(&mut b, &t.to_cols_array());
    }
    xxh3_64(&b)
}

/// Taken from the generator as of the commit that added this test (before the hand-written
/// SplitMix64 became `rand_xoshiro::SplitMix64`).
const DEFAULT_WORLD_HASH: u64 = 0x64d4_4eea_a09a_87e4;
const MILLION_HASH: u64 = 0xdc5d_37ae_0db6_86c0;
const SMALL_HASH: u64 = 0xe813_d077_26f3_e460;

#[test]
fn default_synth_world_is_bit_identical() {
    let h = synth_hash(SynthParams::default_world());
    assert_eq!(h, DEFAULT_WORLD_HASH, "default synth world hash {h:#018x}");
}

#[test]
fn million_synth_world_is_bit_identical() {
    let h = synth_hash(SynthParams::million());
    assert_eq!(h, MILLION_HASH, "million synth world hash {h:#018x}");
}

#[test]
fn small_synth_world_is_bit_identical() {
    let h = synth_hash(SynthParams::small(2_000, 300.0, 42));
    assert_eq!(h, SMALL_HASH, "small synth world hash {h:#018x}");
}
