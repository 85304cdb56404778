//! Round trips and corruption checks of the baked format (unit tests of `format.rs`).

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
                WorldInstanceId(100 + k),
                WorldMeshId(0),
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
    level.instances[2].mesh = WorldMeshId(7);
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
    let bytes = encode_lod(WorldMeshId(4), mesh.lods.len() - 1, lod);
    let back = decode_lod(&bytes, WorldMeshId(4), mesh.lods.len() - 1).expect("decode");
    assert_eq!(&back, &**lod);
    assert!(decode_lod(&bytes, WorldMeshId(5), mesh.lods.len() - 1).is_err());
    for i in (0..bytes.len()).step_by(7) {
        let mut b = bytes.clone();
        b[i] ^= 0x80;
        assert!(
            decode_lod(&b, WorldMeshId(4), mesh.lods.len() - 1).is_err(),
            "flip at {i} accepted"
        );
    }
    for n in (0..bytes.len()).step_by(5) {
        assert!(decode_lod(&bytes[..n], WorldMeshId(4), mesh.lods.len() - 1).is_err());
    }
}

#[test]
fn a_version_1_file_is_a_version_error() {
    let (level, bounds) = sample_level();
    let mut bytes = encode_level(&level);
    bytes[4..8].copy_from_slice(&1u32.to_le_bytes());
    let err = decode_level(&bytes, &bounds).unwrap_err();
    assert!(
        matches!(
            err,
            FormatError::Version {
                found: 1,
                supported: VERSION
            }
        ),
        "{err}"
    );
}

#[test]
fn unaligned_buffers_decode_the_same() {
    // Every bulk array goes through the byte-wise copy when the buffer is misaligned.
    let (level, bounds) = sample_level();
    let mut buf = vec![0u8];
    buf.extend_from_slice(&encode_level(&level));
    assert_eq!(decode_level(&buf[1..], &bounds).expect("decode"), level);
    let mesh = procedural::character(3);
    let lod = &mesh.lods[0];
    let mut buf = vec![0u8; 3];
    buf.extend_from_slice(&encode_lod(WorldMeshId(2), 0, lod));
    assert_eq!(
        &decode_lod(&buf[3..], WorldMeshId(2), 0).expect("decode"),
        &**lod
    );
}

#[test]
fn huge_counts_behind_a_valid_checksum_are_truncation_errors() {
    let mut w = Writer::default();
    w.u32(0);
    w.u32(0);
    w.f32(0.0);
    w.u32(u32::MAX);
    w.u32(0);
    w.u32(0);
    let err = decode_lod(&frame(LOD_MAGIC, &w.0), WorldMeshId(0), 0).unwrap_err();
    assert!(matches!(err, FormatError::Truncated { .. }), "{err}");
    let mut w = Writer::default();
    w.u32(0);
    w.i32(0);
    w.i32(0);
    w.aabb(&Aabb {
        min: Vec3::ZERO,
        max: Vec3::ONE,
    });
    w.u32(u32::MAX);
    let err = decode_level(&frame(LEVEL_MAGIC, &w.0), &[]).unwrap_err();
    assert!(matches!(err, FormatError::Truncated { .. }), "{err}");
}

#[test]
fn out_of_range_index_is_rejected() {
    let (pos, mut idx) = procedural::glass_pane(1);
    idx[4] = pos.len() as u32;
    let g = MeshLod {
        positions: pos,
        indices: idx,
        error: 0.0,
        skin: None,
    };
    let err = decode_lod(&encode_lod(WorldMeshId(0), 0, &g), WorldMeshId(0), 0).unwrap_err();
    assert!(
        matches!(err, FormatError::Inconsistent(ref s) if s.contains("out of range")),
        "{err}"
    );
}
