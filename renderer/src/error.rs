//! The renderer's error type.

use std::path::PathBuf;

use rtstream_as_manager::backend::vulkan::VulkanError;

/// Everything rendering can fail with.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderError {
    /// A Vulkan failure (device lost, out of memory, ...).
    #[error(transparent)]
    Vulkan(#[from] VulkanError),
    /// The device has no VK_KHR_ray_query (this path needs it).
    #[error("device {0:?} has no VK_KHR_ray_query")]
    NoRayQuery(String),
    /// The device has neither VK_KHR_ray_query nor VK_KHR_ray_tracing_pipeline.
    #[error("device {0:?} has neither VK_KHR_ray_query nor VK_KHR_ray_tracing_pipeline")]
    NoRayTracing(String),
    /// Two frames that cannot be compared (different sizes).
    #[error("frames differ in size: {0}x{1} vs {2}x{3}")]
    FrameMismatch(u32, u32, u32, u32),
    /// A render request that cannot be satisfied.
    #[error("invalid render request: {0}")]
    InvalidRequest(String),
    /// A recorded frame needs the resources of frame `waiting_for`, which has not completed
    /// (more frames in flight than `RECORDED_SETS`), or the frame was recorded already.
    #[error("frame {frame} needs frame {waiting_for} to be done first")]
    FrameInFlight {
        /// The frame being recorded.
        frame: u64,
        /// The frame that last used the resources it needs.
        waiting_for: u64,
    },
    /// Writing an image failed.
    #[error("{path}: cannot write image: {source}")]
    Image {
        /// The image file that could not be written.
        path: PathBuf,
        /// The image encoder's error.
        #[source]
        source: image::ImageError,
    },
}

/// The renderer's result alias.
pub type Result<T, E = RenderError> = std::result::Result<T, E>;
