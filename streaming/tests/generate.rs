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

/// Districts of distinct assets: the same instances as the world without them, each opaque
/// static one on its district's own copy of the mesh (a distinct mesh id with the library
/// mesh's LOD chain); everything else unchanged.
#[test]
fn districts_give_each_district_its_own_copies_of_the_opaque_static_meshes() {
    common::assets();
    let plain = WorldPreset::small(6, 7);
    let districts = WorldPreset {
        districts: 3,
        ..plain.clone()
    };
    assert_eq!(districts.district_count(), 4);
    let a = generate(&plain).expect("world");
    let b = generate(&districts).expect("world with districts");
    let library = a.meshes.len();
    assert!(b.meshes.len() > library);
    assert_eq!(a.levels.len(), b.levels.len());
    // district -> library mesh -> the mesh id it became there.
    let mut copies: std::collections::HashMap<(u32, u32), u32> = Default::default();
    let mut copied = 0;
    for (la, lb) in a.levels.iter().zip(&b.levels) {
        assert_eq!(la.instances.len(), lb.instances.len());
        let district = districts.district_of(la.cell[0] as u32, la.cell[1] as u32);
        for (ia, ib) in la.instances.iter().zip(&lb.instances) {
            assert_eq!(
                (ia.id, ia.transform, ia.material, ia.motion),
                (ib.id, ib.transform, ib.material, ib.motion)
            );
            let (ma, mb) = (&a.meshes[ia.mesh.0 as usize], &b.meshes[ib.mesh.0 as usize]);
            assert_eq!(ma.bounds, mb.bounds);
            assert!(ma.lods.len() == mb.lods.len());
            for (x, y) in ma.lods.iter().zip(&mb.lods) {
                assert!(**x == **y, "a copy's LODs are the library mesh's");
            }
            let copy = ia.material == MaterialClass::Opaque && ia.motion == Motion::Static;
            let terrain = ma.name.contains("terrain");
            if district == 0 || !copy || terrain {
                assert_eq!(ia.mesh, ib.mesh, "{} in district {district}", ma.name);
                continue;
            }
            assert!(ib.mesh.0 as usize >= library, "{} not copied", ma.name);
            copied += 1;
            let at = copies.entry((district, ia.mesh.0)).or_insert(ib.mesh.0);
            assert_eq!(*at, ib.mesh.0, "one copy per district");
        }
    }
    // Copies of one mesh in different districts are different meshes.
    let mut ids: Vec<u32> = copies.values().copied().collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), copies.len());
    assert!(copied > 100, "{copied} instances on copies");
}
