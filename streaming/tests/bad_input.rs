//! Bad input: every broken glTF of assimp-testmodels and corrupted baked files give LoadFailed
//! naming the file; loader threads survive; everything else keeps streaming.

mod common;

use std::path::PathBuf;

use glam::{Mat4, Vec3};
use rtstream_streaming::{
    load_gltf, LevelId, StreamConfig, StreamFocus, StreamingError, World, WorldEvent,
};

/// The broken models under glTF2/ (each folder explored; every .gltf/.glb in it is broken).
const BROKEN: &[&str] = &[
    "IndexOutOfRange/IndexOutOfRange.gltf",
    "IndexOutOfRange/AllIndicesOutOfRange.gltf",
    "BoxWithInfinites-glTF-Binary/BoxWithInfinites.glb",
    "MissingBin/BoxTextured.gltf",
    "wrongTypes/badArray.gltf",
    "wrongTypes/badExtension.gltf",
    "wrongTypes/badNumber.gltf",
    "wrongTypes/badObject.gltf",
    "wrongTypes/badString.gltf",
    "wrongTypes/badUint.gltf",
    "RecursiveNodes/RecursiveNodes.gltf",
    "SchemaFailures/sceneWrongType.gltf",
    "IncorrectVertexArrays/Cube.gltf",
];

fn error_names(e: &StreamingError, file: &std::path::Path) -> bool {
    let name = file
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    e.to_string().contains(&name)
}

#[test]
fn every_broken_model_is_a_typed_error_naming_the_file() {
    let dir = common::assets();
    // Every file in the broken folders is covered by the list.
    for folder in [
        "IndexOutOfRange",
        "MissingBin",
        "wrongTypes",
        "RecursiveNodes",
        "SchemaFailures",
        "IncorrectVertexArrays",
        "BoxWithInfinites-glTF-Binary",
    ] {
        for e in std::fs::read_dir(dir.join(folder)).expect("broken folder") {
            let p = e.expect("entry").path();
            if matches!(p.extension().and_then(|x| x.to_str()), Some("gltf" | "glb")) {
                let rel = p
                    .strip_prefix(&dir)
                    .expect("prefix")
                    .to_string_lossy()
                    .into_owned();
                assert!(BROKEN.contains(&rel.as_str()), "{rel} not covered");
            }
        }
    }
    for rel in BROKEN {
        let path = dir.join(rel);
        match load_gltf(&path) {
            Ok(_) => panic!("{rel} loaded"),
            Err(e) => assert!(
                error_names(&e, &path),
                "{rel}: error does not name the file: {e}"
            ),
        }
    }
}

#[test]
fn broken_models_as_levels_fail_and_the_world_keeps_working() {
    let dir = common::assets();
    let config = StreamConfig::within(50.0, 80.0);
    let mut w = World::empty(config).expect("world");
    let mut broken_levels = Vec::new();
    for (k, rel) in BROKEN.iter().enumerate() {
        let at = Mat4::from_translation(Vec3::new(k as f32, 0.0, 0.0));
        broken_levels.push((w.add_gltf_level(dir.join(rel), at), dir.join(rel)));
    }
    let good = [
        "2CylinderEngine-glTF-Binary/2CylinderEngine.glb",
        "simple_skin/simple_skin.gltf",
        "BoxTextured-glTF-Binary/BoxTextured.glb",
    ];
    let good_levels: Vec<LevelId> = good
        .iter()
        .enumerate()
        .map(|(k, rel)| {
            w.add_gltf_level(
                dir.join(rel),
                Mat4::from_translation(Vec3::new(0.0, 0.0, 5.0 + k as f32)),
            )
        })
        .collect();
    let cam = [StreamFocus::from(Vec3::ZERO)];
    let events = common::settle(&mut w, 0, &cam);
    for (level, path) in &broken_levels {
        let failure = common::failures(&events)
            .find(|f| f.level == Some(*level))
            .map(|f| f.error);
        let error = failure.unwrap_or_else(|| panic!("no LoadFailed for {}", path.display()));
        assert!(error_names(&error, path), "{}: {error}", path.display());
        assert!(!w.is_loaded(*level));
    }
    let mut skinned = 0;
    for level in &good_levels {
        assert!(w.is_loaded(*level), "good level {level:?} not loaded");
        let Some(WorldEvent::LevelLoaded { instances, .. }) = events
            .iter()
            .find(|e| matches!(e, WorldEvent::LevelLoaded { level: l, .. } if l == level))
        else {
            panic!("no LevelLoaded for {level:?}");
        };
        assert!(!instances.is_empty());
        skinned += instances
            .iter()
            .filter(|i| i.motion == rtstream_streaming::Motion::Skinned)
            .count();
    }
    assert_eq!(skinned, 1, "simple_skin should give one skinned instance");
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);

    // The failed levels retry after leaving and re-entering; still failing, still no thread lost.
    let away = [StreamFocus::from(Vec3::new(500.0, 0.0, 0.0))];
    let _ = common::settle(&mut w, 1, &away);
    let again = common::settle(&mut w, 2, &cam);
    let fails = again
        .iter()
        .filter(|e| matches!(e, WorldEvent::LoadFailed { .. }))
        .count();
    assert_eq!(fails, BROKEN.len());
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);
    assert_eq!(w.stats().loaded_levels, good.len());
}

#[test]
fn corrupted_baked_files_fail_and_other_levels_keep_streaming() {
    let (world, dir) = common::baked_small("corrupt", 6);
    let manifest = rtstream_streaming::read_manifest(&dir).expect("manifest");
    let path_of = |i: usize| dir.join(&manifest.levels[i].file);
    // Flip a payload byte, truncate, clobber the magic, swap in another level's file, delete.
    let mut flipped = std::fs::read(path_of(1)).expect("read");
    let n = flipped.len();
    flipped[n / 2] ^= 0x5A;
    std::fs::write(path_of(1), flipped).expect("write");
    let full = std::fs::read(path_of(2)).expect("read");
    std::fs::write(path_of(2), &full[..full.len() * 2 / 3]).expect("write");
    let mut magic = std::fs::read(path_of(3)).expect("read");
    magic[0..4].copy_from_slice(b"JUNK");
    std::fs::write(path_of(3), magic).expect("write");
    std::fs::copy(path_of(5), path_of(4)).expect("copy");
    std::fs::remove_file(path_of(7)).expect("remove");
    let bad: Vec<(usize, &str)> = vec![
        (1, "checksum"),
        (2, "truncated"),
        (3, "magic"),
        (4, "inconsistent"),
        (7, ""),
    ];

    let config = StreamConfig::within(2000.0, 2500.0);
    let mut w = World::open(&dir, config).expect("open");
    let events = common::settle(&mut w, 0, &[StreamFocus::from(Vec3::ZERO)]);
    for (i, reason) in &bad {
        let err = common::failures(&events)
            .find(|f| f.level.is_some_and(|l| l.0 as usize == *i) && f.mesh.is_none())
            .map(|f| f.error)
            .unwrap_or_else(|| panic!("no LoadFailed for level {i}"));
        let msg = err.to_string().to_lowercase();
        assert!(msg.contains(&manifest.levels[*i].file), "level {i}: {msg}");
        assert!(
            msg.contains(reason),
            "level {i}: expected {reason:?} in {msg}"
        );
        match &*err {
            StreamingError::Format { path, .. } | StreamingError::Io { path, .. } => {
                assert_eq!(path, &path_of(*i));
            }
            other => panic!("level {i}: unexpected error kind {other:?}"),
        }
    }
    let st = w.stats();
    assert_eq!(st.failed_levels, bad.len());
    assert_eq!(st.loaded_levels, world.levels.len() - bad.len());
    assert_eq!(st.loader_threads_alive, config.loader_threads);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_corrupt_mesh_chunk_fails_that_lod_only() {
    let (world, dir) = common::baked_small("corrupt-mesh", 4);
    let manifest = rtstream_streaming::read_manifest(&dir).expect("manifest");
    // Corrupt the finest LOD of the terrain tiles' first mesh (mesh 0) and the coarsest of mesh 1.
    let lib: PathBuf = dir.join(rtstream_streaming::bake::MESH_LIBRARY_FILE);
    let mut bytes = std::fs::read(&lib).expect("lib");
    let l0 = manifest.meshes[0].lods[0];
    bytes[(l0.offset + l0.len / 2) as usize] ^= 0xFF;
    let c1 = *manifest.meshes[1].lods.last().expect("lod");
    bytes[(c1.offset + c1.len - 1) as usize] ^= 0xFF;
    std::fs::write(&lib, bytes).expect("write");

    let config = StreamConfig {
        lod_error_angle: 1e-6, // Want LOD0 of everything.
        ..StreamConfig::within(2000.0, 2500.0)
    };
    let mut w = World::open(&dir, config).expect("open");
    let cam = [StreamFocus::from(Vec3::ZERO)];
    let mut events = common::settle(&mut w, 0, &cam);
    events.extend(common::settle(&mut w, 1, &cam));
    let failed: Vec<_> = common::failures(&events)
        .filter_map(|f| Some((f.mesh?, f.error.to_string())))
        .collect();
    let uses = |m: u32| {
        world
            .levels
            .iter()
            .any(|l| l.instances.iter().any(|i| i.mesh.0 == m))
    };
    if uses(0) {
        assert!(
            failed
                .iter()
                .any(|((m, l), msg)| m.0 == 0 && *l == 0 && msg.contains("meshes.rtm")),
            "{failed:?}"
        );
    }
    if uses(1) {
        assert!(failed.iter().any(|((m, _), _)| m.0 == 1), "{failed:?}");
        // Instances of mesh 1 were left out; the levels still loaded.
        for e in &events {
            if let WorldEvent::LevelLoaded { instances, .. } = e {
                assert!(instances.iter().all(|i| i.mesh.0 != 1));
            }
        }
    }
    assert_eq!(w.stats().loaded_levels, world.levels.len());
    assert_eq!(w.stats().failed_levels, 0);
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);
    let _ = std::fs::remove_dir_all(&dir);
}
