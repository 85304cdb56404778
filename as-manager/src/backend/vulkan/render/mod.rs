//! The renderer's side of the device: compute and ray-tracing pipelines, and static scenes
//! built once (the reference renders). The `renderer` crate drives them; they sit here, on the
//! device layer, so that every `unsafe` block of rtstream stays in this one module.

pub(crate) mod binding;
pub(crate) mod compute;
pub(crate) mod geometry;
pub(crate) mod ring;
pub(crate) mod rt_pipeline;
pub(crate) mod scene;
