//! The Vulkan backend (ash), in two layers, each in its own folder (the renderer is a third,
//! in its own crate, on the first):
//! - `device/`: the device layer. The context (created here, or imported from the engine),
//!   buffers, query pools, acceleration-structure objects and barriers, debug names, and the
//!   safe wrappers the layers above build on: GPU geometry, compute and ray-tracing pipelines
//!   with their descriptor rings and pass timers (`device/pipeline/`), and a static scene built
//!   once. Nothing else creates Vulkan objects.
//! - `as_backend/`: [`VulkanBackend`], the manager's [`AsBackend`](crate::backend::AsBackend):
//!   frame ring, builds, refits, compaction, splitting, retirement.
//!
//! The renderer's own pipelines (its shaders, bindings and passes), frames and scenes are in the
//! `renderer` crate, on the device layer's wrappers. Everything `unsafe` in rtstream lives under
//! this module, each block with a `// SAFETY:` line. It runs on Mesa lavapipe (CPU) and on
//! NVIDIA GPUs; device selection prefers ray queries.

mod as_backend;
mod device;
mod error;

pub use super::FaultPoint;
pub use as_backend::measure::{
    build_blas_now, compaction_sizes, time_blas_builds, time_build_recording,
    time_refit_vs_rebuild, time_tlas_beside_builds, time_tlas_build, time_tlas_update,
    BesideBuilds, CompactionResult, RecordingCost,
};
pub use as_backend::{Recording, TlasUpdates, VulkanBackend, VulkanBackendDesc, VulkanCounters};
pub use device::accel::{
    align_up, class_flags, AccelStorage, AccelStruct, AsSizes, BlasBuildInput, TlasBuildInput,
    TriangleGeometry, ACCEL_STORAGE_USAGE, BUILD_INPUT_USAGE,
};
pub use device::arena::{ArenaRange, BufferArena, UNIT as ARENA_UNIT};
pub use device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
pub use device::context::{
    live_vulkan_handles, ContextDesc, DeviceInfo, DeviceKind, Validation, ValidationLog,
    VulkanContext,
};
pub use device::external::{DeviceFeatures, ExternalDevice, REQUIRED_DEVICE_EXTENSIONS};
pub use device::frames::{FrameCmd, FrameLoop};
pub use device::geometry::{GpuGeometry, SceneMesh};
pub use device::pipeline::binding::{BindingKind, Bound};
pub use device::pipeline::compute::ComputePipeline;
pub use device::pipeline::ring::{read_timer, Pass, PassTimer, RECORDED_SETS};
pub use device::pipeline::rt_pipeline::{RayTracingPipeline, RtShaders};
pub use device::query::{QueryKind, QueryPool};
pub use device::scene::{GpuMesh, SceneBuildStats, StaticInstance, StaticScene};
pub use device::tlas_ref::TlasRef;
pub use error::{VkResult, VulkanError, INSTALL_HINT};

pub use ash;
