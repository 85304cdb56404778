//! The facade's error type: any crate's error.

/// Any error of rtstream's crates.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Reading world data failed.
    #[error(transparent)]
    Streaming(#[from] rtstream_streaming::StreamingError),
    /// A Vulkan failure.
    #[error(transparent)]
    Vulkan(#[from] rtstream_as_manager::backend::vulkan::VulkanError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] rtstream_renderer::RenderError),
}

/// The facade's result alias.
pub type Result<T, E = Error> = std::result::Result<T, E>;
