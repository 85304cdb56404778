//! The Vulkan backend (ash), in three layers, each in its own folder:
//! - `device/`: the context (created here, or imported from the engine), buffers, query pools,
//!   acceleration-structure objects and barriers;
//! - `as_backend/`: [`VulkanBackend`], the manager's [`AsBackend`](crate::backend::AsBackend):
//!   frame ring, builds, refits, compaction, splitting, retirement;
//! - `render/`: the renderer's compute and ray-tracing pipelines and static scenes.
//!
//! Everything `unsafe` in rtstream lives under this module, each block with a `// SAFETY:` line.
//! It runs on Mesa lavapipe (CPU) and on NVIDIA GPUs; device selection prefers ray queries.

mod as_backend;
mod device;
mod error;
mod render;

pub use super::FaultPoint;
pub use as_backend::measure::{
    build_blas_now, compaction_sizes, time_blas_builds, time_build_recording,
    time_refit_vs_rebuild, time_tlas_beside_builds, time_tlas_build, time_tlas_update,
    BesideBuilds, CompactionResult, RecordingCost,
};
pub use as_backend::{
    class_flags, Recording, TlasUpdates, VulkanBackend, VulkanBackendDesc, VulkanCounters,
};
pub use device::accel::{
    align_up, AccelStorage, AccelStruct, AsSizes, BlasBuildInput, TlasBuildInput, TriangleGeometry,
    ACCEL_STORAGE_USAGE, BUILD_INPUT_USAGE,
};
pub use device::arena::{ArenaRange, BufferArena, UNIT as ARENA_UNIT};
pub use device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
pub use device::context::{
    live_vulkan_handles, ContextDesc, DeviceInfo, DeviceKind, Validation, ValidationLog,
    VulkanContext,
};
pub use device::external::{DeviceFeatures, ExternalDevice, REQUIRED_DEVICE_EXTENSIONS};
pub use device::frames::{FrameCmd, FrameLoop};
pub use device::query::{QueryKind, QueryPool};
pub use error::{VkResult, VulkanError, INSTALL_HINT};
pub use render::binding::{BindingKind, Bound};
pub use render::compute::ComputePipeline;
pub use render::geometry::{GpuGeometry, SceneMesh};
pub use render::ring::{read_timer, Pass, PassTimer, RECORDED_SETS};
pub use render::rt_pipeline::{RayTracingPipeline, RtShaders};
pub use render::scene::{GpuMesh, SceneBuildStats, StaticInstance, StaticScene};

pub use ash;
