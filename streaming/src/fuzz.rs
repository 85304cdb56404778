//! Fuzz bodies: one plain `fn(&[u8])` per reader of untrusted input. Each must return for any
//! input — a typed error at worst — and never panic, loop or allocate without bound.
//!
//! The cargo-fuzz targets in `streaming/fuzz/` call these (libFuzzer, by hand, on nightly);
//! `streaming/tests/fuzz_corpus.rs` replays the committed corpus and every crash input with
//! stable `cargo test`. Baked files carry a checksum, so each body also wraps the input in a
//! valid frame: the decoder behind the checksum sees arbitrary bytes too.

use std::path::Path;

use crate::format::{self, LEVEL_MAGIC, LOD_MAGIC, MANIFEST_MAGIC};
use crate::model::{Aabb, WorldMeshId};

/// Mesh bounds a fuzzed level may reference (any id beyond them is an error to report).
fn bounds() -> Vec<Aabb> {
    (0..64)
        .map(|i| {
            let v = glam::Vec3::splat(i as f32 + 1.0);
            Aabb { min: -v, max: v }
        })
        .collect()
}

/// A level file (`levels/*.bin`).
pub fn level(data: &[u8]) {
    let b = bounds();
    let _ = format::decode_level(data, &b);
    let _ = format::decode_level(&format::frame(LEVEL_MAGIC, data), &b);
}

/// The world manifest (`manifest.bin`).
pub fn manifest(data: &[u8]) {
    let _ = crate::bake::decode_manifest(data);
    let _ = crate::bake::decode_manifest(&format::frame(MANIFEST_MAGIC, data));
}

/// One LOD chunk of the mesh library (`meshes/*`).
pub fn mesh_lod(data: &[u8]) {
    let _ = format::decode_lod(data, WorldMeshId(0), 0);
    let _ = format::decode_lod(&format::frame(LOD_MAGIC, data), WorldMeshId(0), 0);
}

/// The far-field proxy file (`proxies.bin`).
pub fn proxies(data: &[u8]) {
    let _ = crate::proxy::decode_proxies(data, Path::new("fuzz/proxies.bin"), 256, 256);
}

/// A glTF (JSON with embedded buffers) or GLB file.
pub fn gltf(data: &[u8]) {
    let _ = crate::gltf_import::load_gltf_slice(data, "fuzz.glb");
}

/// A fuzz body.
pub type Body = fn(&[u8]);

/// Every body with its name, for replays.
pub const TARGETS: [(&str, Body); 5] = [
    ("level", level),
    ("manifest", manifest),
    ("mesh_lod", mesh_lod),
    ("proxies", proxies),
    ("gltf", gltf),
];
