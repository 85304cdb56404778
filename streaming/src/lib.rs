//! # rtstream-streaming
//!
//! The open world that the BLAS manager serves: streaming levels, meshes with LOD chains, and
//! loader threads. This crate knows nothing of acceleration structures or Vulkan; it emits events
//! that the facade feeds to the manager, so an engine can use its own streaming instead.
//!
//! Design choices:
//! - glTF 2.0 is the mesh interchange format ([`load_gltf`]); every mesh is validated on load
//!   (finite positions, indices in range, acyclic nodes) and bad input is a typed error naming
//!   the file, never a panic.

mod error;
mod gltf_import;

pub use error::{Result, StreamingError};
pub use gltf_import::{load_gltf, GltfScene, MeshInstance, TriMesh};
