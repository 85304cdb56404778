//! The Vulkan backend (ash): context, buffers, acceleration structures, scenes.
//!
//! Everything `unsafe` in rtstream lives under this module, each block with a `// SAFETY:` line.
//! It runs on Mesa lavapipe (CPU) and on NVIDIA GPUs; device selection prefers ray queries.

mod accel;
mod backend;
mod buffer;
mod compute;
mod context;
mod error;
mod geometry;
mod measure;
mod query;
mod rt_pipeline;
mod scene;

pub use super::FaultPoint;
pub use accel::{align_up, AccelStruct, AsSizes, BlasBuild, TriangleGeometry, BUILD_INPUT_USAGE};
pub use backend::{class_flags, VulkanBackend, VulkanBackendDesc, VulkanCounters};
pub use buffer::{BufferDesc, GpuBuffer, MemoryKind};
pub use compute::{BindingKind, Bound, ComputePipeline};
pub use context::{
    live_vulkan_handles, ContextDesc, DeviceInfo, DeviceKind, Validation, ValidationLog,
    VulkanContext,
};
pub use error::{VkResult, VulkanError, INSTALL_HINT};
pub use geometry::{GpuGeometry, MeshDesc};
pub use measure::{
    build_blas_now, compaction_sizes, time_blas_builds, time_refit_vs_rebuild, time_tlas_build,
    CompactionResult,
};
pub use query::{QueryKind, QueryPool};
pub use rt_pipeline::{RayTracingPipeline, RtShaders};
pub use scene::{GpuMesh, InstanceDesc, SceneBuildStats, StaticScene};

pub use ash;
