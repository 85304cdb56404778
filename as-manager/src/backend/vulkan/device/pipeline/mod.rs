//! Pipelines on the device: a compute pipeline and a ray-tracing pipeline (with its shader
//! binding table), one binding model for both (set 0, bindings in list order, push
//! constants), their descriptor-set rings and pass timestamps for frames in flight. Safe
//! wrappers over the Vulkan objects: the renderer (`renderer/`) creates its pipelines from its
//! own shaders with them, and the backend its refit-quality reduction.

pub(crate) mod binding;
pub(crate) mod compute;
pub(crate) mod ring;
pub(crate) mod rt_pipeline;
