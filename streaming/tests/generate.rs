//! The generator's presets meet the figures; LOD chains are monotone.

mod common;

use rtstream_streaming::{generate, MaterialClass, Motion, WorldPreset, LOD_MAX_RATIO};

#[test]
fn default_preset_meets_the_shipped_maps_figures() {
    common::assets();
    let preset = WorldPreset::default_world();
    let world = generate(&preset).expect("default world");
    let s = world.stats();
    assert!(s.levels >= 3000, "{} levels", s.levels);
    assert!(s.instances >= 104_366, "{} instances", s.instances);
    assert!(
        s.non_opaque as f64 >= 0.05 * s.instances as f64,
        "{} of {} non-opaque",
        s.non_opaque,
        s.instances
    );
    assert!(s.skinned >= 200, "{} skinned", s.skinned);
    assert!((100..=1000).contains(&s.meshes), "{} meshes", s.meshes);
    // 4 km x 4 km.
    let size = world.extent.max - world.extent.min;
    assert!(
        (size.x - 4000.0).abs() < 50.0 && (size.z - 4000.0).abs() < 50.0,
        "{size:?}"
    );
    // The description stays within 256 bytes per instance.
    let bpi = world.bytes_per_instance();
    assert!(bpi <= 256.0, "{bpi} bytes per instance");
    // Skinned instances are exactly those on skinned meshes; every class appears.
    for l in &world.levels {
        for i in &l.instances {
            let skinned_mesh = world.meshes[i.mesh.0 as usize].is_skinned();
            assert_eq!(
                i.motion == Motion::Skinned,
                skinned_mesh,
                "instance {:?}",
                i.id
            );
            assert!(i.aabb.is_valid() && i.transform.is_finite());
        }
    }
    for class in [
        MaterialClass::Opaque,
        MaterialClass::AlphaMasked,
        MaterialClass::Transparent,
        MaterialClass::WorldPositionOffset,
    ] {
        assert!(
            world
                .levels
                .iter()
                .flat_map(|l| &l.instances)
                .any(|i| i.material == class),
            "{class:?}"
        );
    }
    // Real meshes are in: the engine model and the glTF skin.
    assert!(world
        .meshes
        .iter()
        .any(|m| m.name.starts_with("2CylinderEngine")));
    assert!(world
        .meshes
        .iter()
        .any(|m| m.name.starts_with("simple_skin") && m.is_skinned()));

    // LOD chains: triangles at most ~half per step, errors monotone, LOD0 exact.
    let mut multi = 0;
    for m in &world.meshes {
        assert!(!m.lods.is_empty());
        assert_eq!(m.lods[0].error, 0.0, "{}", m.name);
        for w in m.lods.windows(2) {
            let (a, b) = (w[0].triangle_count(), w[1].triangle_count());
            assert!(
                b as f32 <= a as f32 * LOD_MAX_RATIO,
                "{}: {a} -> {b} triangles",
                m.name
            );
            assert!(
                w[1].error >= w[0].error,
                "{}: error {} -> {}",
                m.name,
                w[0].error,
                w[1].error
            );
            assert!(w[1].error.is_finite());
        }
        for l in &m.lods {
            assert!(l.indices.iter().all(|&i| (i as usize) < l.positions.len()));
            assert_eq!(l.skin.is_some(), m.is_skinned());
        }
        multi += usize::from(m.lods.len() >= 3);
    }
    assert!(
        multi * 2 > world.meshes.len(),
        "most meshes should have >= 3 LODs ({multi})"
    );
}

#[test]
fn generation_is_deterministic_per_seed() {
    common::assets();
    let a = generate(&WorldPreset::small(5, 42)).expect("a");
    let b = generate(&WorldPreset::small(5, 42)).expect("b");
    let c = generate(&WorldPreset::small(5, 43)).expect("c");
    assert_eq!(a.levels, b.levels);
    assert_eq!(a.meshes, b.meshes);
    assert_ne!(a.levels, c.levels);
}

#[test]
fn large_preset_has_a_million_instances_at_the_default_density() {
    let d = WorldPreset::default_world();
    let l = WorldPreset::large_world();
    assert!(l.instances >= 1_000_000);
    assert!((l.size_m - 16_000.0).abs() < 1.0);
    let density = |p: &WorldPreset| f64::from(p.instances) / f64::from(p.size_m * p.size_m);
    assert!((density(&l) / density(&d) - 1.0).abs() < 0.01);
    assert!((l.cell_size() - d.cell_size()).abs() < 1e-3);
}

/// Generates the full 16 km preset (slow in debug; run with `--ignored --release`).
#[test]
#[ignore]
fn large_preset_generates() {
    common::assets();
    let w = generate(&WorldPreset::large_world()).expect("large");
    let s = w.stats();
    assert!(s.instances >= 1_000_000 && s.levels >= 48_000);
    assert!(w.bytes_per_instance() <= 256.0);
}
