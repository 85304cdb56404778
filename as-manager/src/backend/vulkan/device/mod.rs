//! The device layer: the context (our own, or one imported from the engine), buffers, query
//! pools, acceleration-structure objects and barriers, debug names; GPU geometry, pipelines
//! (`pipeline/`) and static scenes on them. Nothing outside this folder creates device-level
//! Vulkan objects except through it.

pub(crate) mod accel;
pub(crate) mod accel_object;
pub(crate) mod arena;
pub(crate) mod buffer;
pub(crate) mod context;
pub(crate) mod external;
pub(crate) mod frames;
pub(crate) mod geometry;
pub(crate) mod pipeline;
pub(crate) mod query;
pub(crate) mod scene;
mod select;
pub(crate) mod tlas_ref;
