//! The crate's error type.

use std::path::PathBuf;

/// Everything that can go wrong while reading world data. Each variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum StreamingError {
    /// The file could not be read or parsed as glTF 2.0.
    #[error("{path}: not a readable glTF 2.0 file: {source}")]
    Gltf {
        path: PathBuf,
        #[source]
        source: gltf::Error,
    },
    /// The glTF parsed, but a mesh in it is unusable (non-finite positions, indices out of range,
    /// missing positions, ...).
    #[error("{path}: mesh {mesh:?}: {reason}")]
    InvalidMesh {
        path: PathBuf,
        mesh: String,
        reason: String,
    },
    /// The glTF's node graph is unusable (a cycle, or nesting deeper than we accept).
    #[error("{path}: node graph: {reason}")]
    InvalidScene { path: PathBuf, reason: String },
}

/// The crate's result alias.
pub type Result<T, E = StreamingError> = std::result::Result<T, E>;
