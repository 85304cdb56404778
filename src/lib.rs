//! # rtstream
//!
//! Ray tracing for large streaming worlds. This facade re-exports the three crates and the
//! shared statistics one:
//!
//! - [`streaming`]: the open world — streaming levels, mesh LOD chains, loader threads. No Vulkan.
//! - [`as_manager`]: the BLAS/TLAS manager — residency (r1/r2), budgets, LOD, refit, culling —
//!   with a Vulkan backend (ash) and a GPU-less model backend.
//! - [`renderer`]: the ray-query renderer that traces the manager's TLAS, and image metrics.
//! - [`stats`]: the one summary (mean, nearest-rank percentiles) every figure is reported with.
//!
//! `streaming` and `as_manager` do not know each other: [`WorldBridge`] wires streaming's events
//! into the manager's API, as an engine would with its own streaming; `examples/flythrough.rs`
//! (the main job) drives it across the 4 km map.

#![warn(missing_docs)]

pub use rtstream_as_manager as as_manager;
pub use rtstream_renderer as renderer;
pub use rtstream_stats as stats;
pub use rtstream_streaming as streaming;

pub mod bridge;
pub mod driver;
mod error;
mod gltf_scene;

pub use bridge::{BridgeStats, ShadingSlot, ShadingTable, WorldBridge};
pub use error::{Error, Result};
pub use gltf_scene::{reference_scene, scene_mesh, world_bounds, GpuGltfScene};
