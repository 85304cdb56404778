//! Far-field proxies: baked with the world into their own checksummed file, read back
//! identically, streamed within the far radius, and a corrupt proxy loses only itself.

mod common;

use std::collections::HashSet;

use glam::Vec3;
use rtstream_streaming::proxy::{
    build_proxies, encode_proxies, read_proxies, ProxyConfig, PROXY_FILE,
};
use rtstream_streaming::{
    MaterialClass, Motion, ProxyId, StreamConfig, StreamFocus, StreamingError, World, WorldEvent,
};

/// Streams with deterministic application (no waiting on wall clock) until `frames` frames.
fn stream(dir: &std::path::Path, config: StreamConfig, frames: u64) -> Vec<WorldEvent> {
    let config = StreamConfig {
        apply_after_frames: Some(1),
        ..config
    };
    let mut w = World::open(dir, config).expect("open");
    let cam = [StreamFocus::from(Vec3::new(0.0, 2.0, 0.0))];
    (0..frames).flat_map(|f| w.update(f, &cam)).collect()
}

#[test]
fn bake_writes_proxies_and_reads_them_back() {
    let (world, dir) = common::baked_small("proxies-roundtrip", 8);
    let file = read_proxies(&dir, world.levels.len(), world.meshes.len())
        .expect("readable")
        .expect("a proxy file");
    let (built, report) = build_proxies(&world, &ProxyConfig::default());
    assert_eq!(file.tree, built.tree, "the index round-trips");
    for (i, g) in file.geometry.iter().enumerate() {
        let g = g.as_ref().expect("every chunk reads");
        assert_eq!(**g, *built.geometry[i], "node {i} geometry round-trips");
    }
    // Deterministic: the same world gives the same bytes.
    let again = build_proxies(&world, &ProxyConfig::default()).0;
    assert_eq!(
        encode_proxies(&again),
        std::fs::read(dir.join(PROXY_FILE)).unwrap()
    );
    // 8x8 levels: 16 leaves (2x2), 4 (4x4), 1 (8x8).
    let depths: Vec<u8> = file.tree.nodes.iter().map(|n| n.depth).collect();
    assert_eq!(depths.iter().filter(|&&d| d == 1).count(), 16);
    assert_eq!(depths.iter().filter(|&&d| d == 2).count(), 4);
    assert_eq!(depths.iter().filter(|&&d| d == 3).count(), 1);
    assert_eq!(report.nodes, 21);
    // Every level has one leaf; every leaf's bounds hold its static opaque instances; every
    // parent's bounds hold its children's.
    for l in &world.levels {
        let leaf = file.tree.leaf_of(l.id).expect("a leaf per level");
        let b = file.tree.node(leaf).unwrap().bounds;
        for i in l
            .instances
            .iter()
            .filter(|i| i.material == MaterialClass::Opaque && i.motion == Motion::Static)
        {
            assert!(b.min.cmple(i.aabb.min + 1e-3).all() && b.max.cmpge(i.aabb.max - 1e-3).all());
        }
    }
    for n in &file.tree.nodes {
        for c in &n.children {
            let cb = file.tree.node(*c).unwrap().bounds;
            assert!(n.bounds.min.cmple(cb.min).all() && n.bounds.max.cmpge(cb.max).all());
            assert!(
                file.tree.node(*c).unwrap().error <= n.error + 1e-6,
                "errors grow up the tree"
            );
        }
        assert!(n.triangles > 0 && n.triangles <= ProxyConfig::default().triangles);
    }
    // Each leaf lists exactly its levels' static opaque instances of at least the landmark
    // radius; parents list none.
    let radius = ProxyConfig::default().landmark_radius;
    let mut listed = 0;
    for n in &file.tree.nodes {
        if n.depth != 1 {
            assert!(n.landmarks.is_empty(), "a parent lists no landmarks");
            continue;
        }
        let want: Vec<_> = n
            .levels
            .iter()
            .flat_map(|l| &world.levels[l.0 as usize].instances)
            .filter(|i| {
                i.material == MaterialClass::Opaque
                    && i.motion == Motion::Static
                    && i.sphere.radius >= radius
            })
            .map(|i| (i.id, i.mesh, i.transform))
            .collect();
        let got: Vec<_> = n
            .landmarks
            .iter()
            .map(|l| (l.instance, l.mesh, l.transform))
            .collect();
        assert_eq!(got, want, "node {:?}'s landmarks", n.id);
        listed += got.len();
    }
    assert!(listed > 0, "the small world has landmarks to list");
    assert_eq!(report.landmarks, listed as u64);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn proxies_stream_within_the_far_radius() {
    let (_, dir) = common::baked_small("proxies-radius", 8);
    let all = stream(&dir, StreamConfig::default(), 3);
    let loaded: HashSet<ProxyId> = all
        .iter()
        .filter_map(|e| match e {
            WorldEvent::ProxyLoaded { node, .. } => Some(*node),
            _ => None,
        })
        .collect();
    assert_eq!(loaded.len(), 21, "the default far radius is the whole map");
    let near = stream(
        &dir,
        StreamConfig {
            far_radius: 60.0,
            ..StreamConfig::default()
        },
        3,
    );
    let n = near
        .iter()
        .filter(|e| matches!(e, WorldEvent::ProxyLoaded { .. }))
        .count();
    assert!(n > 0 && n < 21, "{n} proxies within 60 m");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_corrupt_proxy_is_a_typed_error_and_the_levels_still_stream() {
    let (world, dir) = common::baked_small("proxies-corrupt", 8);
    let path = dir.join(PROXY_FILE);
    let mut bytes = std::fs::read(&path).unwrap();
    // Flip a byte in the last node's chunk.
    let n = bytes.len();
    bytes[n - 20] ^= 0xff;
    std::fs::write(&path, &bytes).unwrap();
    let events = stream(&dir, StreamConfig::default(), 4);
    let failed: Vec<_> = common::failures(&events)
        .filter_map(|f| Some((f.proxy?, f.error)))
        .collect();
    assert_eq!(failed.len(), 1, "one corrupt node");
    assert!(matches!(*failed[0].1, StreamingError::Format { .. }));
    let proxies = events
        .iter()
        .filter(|e| matches!(e, WorldEvent::ProxyLoaded { .. }))
        .count();
    assert_eq!(proxies, 20, "the other nodes load");
    assert!(events
        .iter()
        .any(|e| matches!(e, WorldEvent::LevelLoaded { .. })));

    // A truncated file: the index fails as a whole (typed), the levels stream.
    std::fs::write(&path, &bytes[..10]).unwrap();
    assert!(matches!(
        read_proxies(&dir, world.levels.len(), world.meshes.len()),
        Err(StreamingError::Format { .. })
    ));
    let events = stream(&dir, StreamConfig::default(), 4);
    assert!(events.iter().any(|e| matches!(
        e,
        WorldEvent::LoadFailed {
            level: None,
            mesh: None,
            proxy: None,
            ..
        }
    )));
    assert!(!events
        .iter()
        .any(|e| matches!(e, WorldEvent::ProxyLoaded { .. })));
    assert!(events
        .iter()
        .any(|e| matches!(e, WorldEvent::LevelLoaded { .. })));
    std::fs::remove_dir_all(&dir).ok();
}

/// A proxy's landmarks bring their meshes' coarsest LODs with it, as a level brings its
/// meshes': in a world whose districts have meshes of their own, a far district's meshes are
/// used by no loaded level, yet a resident proxy's landmarks have theirs resident (the bridge
/// places a landmark once its mesh has a LOD). They go with the proxy unless a loaded level
/// uses them. (The copies' LODs are baked once and read through the library meshes' chunks.)
#[test]
fn a_proxys_landmarks_bring_their_meshes_coarsest_lods() {
    use rtstream_streaming::{bake, generate, WorldMeshId, WorldPreset};
    use std::collections::HashMap;
    common::assets();
    let preset = WorldPreset {
        districts: 2,
        ..WorldPreset::small(8, 7)
    };
    let world = generate(&preset).expect("generate");
    let dir = common::scratch("proxies-landmark-meshes");
    let report = bake(&world, &dir).expect("bake");
    // A copy's LODs are written once, with the library mesh's: the mesh library is the
    // plain world's, byte for byte.
    let plain = common::scratch("proxies-landmark-meshes-plain");
    let plain_world = generate(&WorldPreset::small(8, 7)).expect("generate");
    let plain_report = bake(&plain_world, &plain).expect("bake");
    assert_eq!(
        std::fs::read(dir.join("meshes.rtm")).unwrap(),
        std::fs::read(plain.join("meshes.rtm")).unwrap()
    );
    assert_eq!(report.mesh_library_bytes, plain_report.mesh_library_bytes);
    std::fs::remove_dir_all(&plain).ok();
    let config = StreamConfig {
        apply_after_frames: Some(1),
        load_radius: 40.0,
        unload_radius: 60.0,
        far_radius: 400.0,
        ..StreamConfig::default()
    };
    let mut w = World::open(&dir, config).expect("open");
    let half = preset.size_m * 0.5;
    // Resident LODs per mesh, levels' meshes, proxies' landmark meshes, from the events.
    let mut lods: HashMap<WorldMeshId, HashSet<u8>> = HashMap::new();
    let mut levels: HashMap<u32, Vec<WorldMeshId>> = HashMap::new();
    let mut proxies: HashMap<ProxyId, Vec<WorldMeshId>> = HashMap::new();
    let mut check = |events: Vec<WorldEvent>, settled: bool| {
        for e in events {
            match e {
                WorldEvent::MeshLodLoaded { mesh, lod, .. } => {
                    assert!(lods.entry(mesh).or_default().insert(lod), "loaded twice");
                }
                WorldEvent::MeshLodEvicted { mesh, lod } => {
                    assert!(lods.entry(mesh).or_default().remove(&lod), "not resident");
                }
                WorldEvent::LevelLoaded {
                    level, instances, ..
                } => {
                    levels.insert(level.0, instances.iter().map(|i| i.mesh).collect());
                }
                WorldEvent::LevelUnloaded { level, .. } => {
                    levels.remove(&level.0);
                }
                WorldEvent::ProxyLoaded {
                    node, landmarks, ..
                } => {
                    proxies.insert(node, landmarks.iter().map(|(_, i)| i.mesh).collect());
                }
                WorldEvent::ProxyEvicted { node } => {
                    proxies.remove(&node);
                }
                WorldEvent::LoadFailed { error, .. } => panic!("{error}"),
            }
        }
        lods.retain(|_, l| !l.is_empty());
        let by_levels: HashSet<WorldMeshId> = levels.values().flatten().copied().collect();
        let by_proxies: HashSet<WorldMeshId> = proxies.values().flatten().copied().collect();
        // Nothing resident that nobody wants.
        for m in lods.keys() {
            assert!(
                by_levels.contains(m) || by_proxies.contains(m),
                "{m:?} resident for nobody"
            );
        }
        if settled {
            for m in &by_proxies {
                let coarsest = (world.meshes[m.0 as usize].lods.len() - 1) as u8;
                assert!(
                    lods.get(m).is_some_and(|l| l.contains(&coarsest)),
                    "{m:?}: a landmark's mesh without its coarsest LOD"
                );
            }
        }
        by_proxies.difference(&by_levels).count()
    };
    // In a corner: the loaded levels are the corner's; the proxies within 400 m list
    // landmarks of other districts.
    let corner = [StreamFocus::from(Vec3::new(
        -half + 10.0,
        2.0,
        -half + 10.0,
    ))];
    let mut only_landmarks = 0;
    for f in 0..6 {
        only_landmarks = check(w.update(f, &corner), f >= 3);
    }
    assert!(
        only_landmarks > 0,
        "no landmark mesh beyond the loaded levels"
    );
    // The opposite corner: the first corner's proxies leave, and with them their meshes.
    let other = [StreamFocus::from(Vec3::new(half - 10.0, 2.0, half - 10.0))];
    for f in 6..12 {
        check(w.update(f, &other), f >= 9);
    }
    std::fs::remove_dir_all(&dir).ok();
}
