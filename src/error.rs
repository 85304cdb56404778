//! The facade's error type: any crate's error.

use std::path::PathBuf;

/// Any error of rtstream's crates.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading world data failed.
    #[error(transparent)]
    Streaming(#[from] rtstream_streaming::StreamingError),
    /// The manager refused a call.
    #[error(transparent)]
    Manager(#[from] rtstream_as_manager::AsError),
    /// A Vulkan failure.
    #[error(transparent)]
    Vulkan(#[from] rtstream_as_manager::backend::vulkan::VulkanError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] rtstream_renderer::RenderError),
    /// Writing an output file failed.
    #[error("cannot write {path}: {message}")]
    Output {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A run was asked for something it cannot do.
    #[error("invalid run: {0}")]
    InvalidRun(String),
}

/// The facade's result alias.
pub type Result<T, E = Error> = std::result::Result<T, E>;
