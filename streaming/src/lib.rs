//! # rtstream-streaming
//!
//! The open world that the BLAS manager serves: streaming levels, meshes with LOD chains, and
//! loader threads. This crate knows nothing of acceleration structures or Vulkan; it emits events
//! that the facade feeds to the manager, so an engine can use its own streaming instead.
//!
//! Design choices:
//! - glTF 2.0 is the mesh interchange format ([`load_gltf`]); every mesh is validated on load
//!   (finite positions, indices in range, acyclic nodes, skins and animations) and bad input is a
//!   typed error naming the file, never a panic. Alpha modes become [`MaterialClass`]es; only
//!   opaque instances are BLAS-eligible.
//! - The world model ([`model`]) keeps instances small (128 bytes: transform, bounds, ids,
//!   material class, static/skinned) and mesh geometry apart behind `Arc`s shared by instances.
//!   Its ids ([`WorldMeshId`], [`WorldInstanceId`]) index the world; a BLAS manager hands out
//!   handles of its own. A mesh's LOD is a [`MeshLod`]; what drives loading is a
//!   [`StreamFocus`] (a position), not a camera.
//! - LOD chains come from meshoptimizer ([`build_lod_chain`]); errors are meshopt's, accumulated
//!   along the chain in mesh-space metres, so they are monotone.
//! - The generator ([`generate()`]) is deterministic per seed; presets match the shipped game's
//!   map ([`WorldPreset::default_world`]) and a 16 km scale test ([`WorldPreset::large_world`]).
//! - Baked worlds ([`bake()`]) are a manifest, a mesh library of individually checksummed LOD
//!   chunks and one file per level, in a small versioned, xxh3-checksummed binary format
//!   ([`mod@format`]).
//! - [`World`] owns all state on the thread that calls [`World::update`]; loader threads only
//!   decode files and send results over crossbeam channels, so events come out in one ordered
//!   stream ([`WorldEvent`]). Loader jobs run under `catch_unwind`: no thread is lost to a file.
//! - Skinning is CPU-side and parallel ([`skin::skin_parallel`], [`World::skin_frame`]).
//! - No `unsafe` in this crate.
//!
//! Wiring to a BLAS manager (what the facade does with [`WorldEvent`]s):
//! - `MeshLodLoaded { mesh, lod, geometry, error, .. }`: register (mesh, LOD) geometry; static
//!   instances share it. Always precedes the `LevelLoaded` whose instances first use the mesh.
//! - `LevelLoaded { instances, .. }`: register each [`Instance`] (id, mesh, transform, bounds,
//!   [`MaterialClass`] — only opaque is BLAS-eligible — and [`Motion`]).
//! - `LevelUnloaded { instances, .. }`: unregister the same instances.
//! - `MeshLodEvicted { mesh, lod }`: drop what was built from that LOD (fall back to a coarser
//!   resident one; the coarsest stays while any loaded instance uses the mesh).
//! - `LoadFailed { .. }`: log; nothing to undo.
//! - Each frame, [`World::skin_frame`] gives skinned instances' deformed positions to refit from.

#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod bake;
mod error;
pub mod format;
#[doc(hidden)]
pub mod fuzz;
mod generate;
mod gltf_import;
mod loader;
mod lod;
pub mod model;
pub mod procedural;
pub mod proxy;
pub mod skeleton;
pub mod skin;
mod world;

pub use bake::{bake, read_manifest, BakeReport, Manifest};
pub use error::{FormatError, Result, StreamingError};
pub use generate::{
    generate, GeneratedWorld, WorldPreset, WorldStats, WorldStyle, ASSIMP_GLTF2_DIR, REAL_PROPS,
    REAL_SKINNED,
};
pub use gltf_import::{load_gltf, load_gltf_slice, GltfScene, MeshInstance, TriMesh};
pub use loader::LoadFault;
pub use lod::{build_lod_chain, MAX_RATIO as LOD_MAX_RATIO};
pub use model::{
    Aabb, Instance, Level, LevelId, MaterialClass, Mesh, MeshLod, Motion, SkinWeights, Sphere,
    WorldInstanceId, WorldMeshId,
};
pub use proxy::{ProxyId, ProxyNode, ProxyTree};
pub use world::{
    SettleTimeout, SkinnedFrame, StreamConfig, StreamFocus, StreamStats, World, WorldEvent,
};
