//! `driver::prepare_world` re-bakes a world directory that holds a bake of an older format (its
//! stamp from before the format version was in it, its files of version 1) instead of leaving a
//! `FormatError::Version` for the user to clear by hand. No Vulkan.

use rtstream::driver;
use rtstream::streaming::{format, read_manifest, WorldPreset};

/// Rewrites the version field of a framed file (bytes 4..8) to 1, as a version-1 bake has it.
fn make_v1(path: &std::path::Path) {
    let mut bytes = std::fs::read(path).expect("read");
    bytes[4..8].copy_from_slice(&1u32.to_le_bytes());
    std::fs::write(path, bytes).expect("write");
}

#[test]
fn a_stale_version_1_bake_is_rebaked() {
    let dir = std::env::temp_dir().join(format!("rtstream-prepare-world-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let preset = WorldPreset::small(2, 7);
    driver::prepare_world(&preset, &dir).expect("first bake");
    let manifest = read_manifest(&dir).expect("manifest");

    // What a version-1 bake left: files of version 1, a stamp without the format version.
    let stamp_path = dir.join("preset.txt");
    let stamp = std::fs::read_to_string(&stamp_path).expect("stamp");
    let old_stamp = stamp.replace(&format!(" format={}", format::VERSION), "");
    assert_ne!(
        old_stamp, stamp,
        "the stamp names the format version: {stamp}"
    );
    std::fs::write(&stamp_path, old_stamp).expect("write stamp");
    make_v1(&dir.join(rtstream::streaming::bake::MANIFEST_FILE));
    let level = manifest
        .level_path(&dir, manifest.levels[0].id)
        .expect("level");
    make_v1(&level);
    assert!(read_manifest(&dir).is_err());

    driver::prepare_world(&preset, &dir).expect("re-bake");
    assert_eq!(std::fs::read_to_string(&stamp_path).expect("stamp"), stamp);
    assert_eq!(read_manifest(&dir).expect("manifest"), manifest);
    let bytes = std::fs::read(&level).expect("level");
    assert_eq!(bytes[4..8], format::VERSION.to_le_bytes());
    let _ = std::fs::remove_dir_all(&dir);
}
