//! The Vulkan backend (ash): context, buffers, acceleration structures, scenes.
//!
//! Everything `unsafe` in rtstream lives under this module, each block with a `// SAFETY:` line.
//! It runs on Mesa lavapipe (CPU) and on NVIDIA GPUs; device selection prefers ray queries.

mod accel;
mod buffer;
mod compute;
mod context;
mod error;
mod rt_pipeline;
mod scene;

pub use accel::{
    align_up, AccelStruct, AsSizes, BlasBuild, BlasClass, RawInstance, TriangleGeometry,
    BUILD_INPUT_USAGE,
};
pub use buffer::{BufferDesc, GpuBuffer, MemoryKind};
pub use compute::{BindingKind, Bound, ComputePipeline};
pub use context::{ContextDesc, DeviceInfo, DeviceKind, Validation, ValidationLog, VulkanContext};
pub use error::{VkResult, VulkanError, INSTALL_HINT};
pub use rt_pipeline::{RayTracingPipeline, RtShaders};
pub use scene::{GpuMesh, InstanceDesc, MeshDesc, SceneBuildStats, StaticScene};

pub use ash;
