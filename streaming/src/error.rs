//! The crate's error type.

use std::path::PathBuf;

/// Everything that can go wrong while reading world data (each of those variants names the
/// file), and a configuration the world cannot stream with.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StreamingError {
    /// A `StreamConfig` the world cannot stream with (see `StreamConfig::validate`).
    #[error("invalid streaming configuration: {0}")]
    InvalidConfig(String),
    /// The file could not be read or parsed as glTF 2.0.
    #[error("{path}: not a readable glTF 2.0 file: {source}")]
    Gltf {
        /// The glTF file.
        path: PathBuf,
        /// The glTF parser's error.
        #[source]
        source: gltf::Error,
    },
    /// The glTF parsed, but a mesh in it is unusable (non-finite positions, indices out of range,
    /// missing positions, ...).
    #[error("{path}: mesh {mesh:?}: {reason}")]
    InvalidMesh {
        /// The glTF file.
        path: PathBuf,
        /// The mesh's name (`mesh<index>` when it has none).
        mesh: String,
        /// What is wrong with the mesh.
        reason: String,
    },
    /// The glTF's node graph is unusable (a cycle, or nesting deeper than we accept).
    #[error("{path}: node graph: {reason}")]
    InvalidScene {
        /// The glTF file.
        path: PathBuf,
        /// What is wrong with the node graph.
        reason: String,
    },
    /// The glTF JSON breaks the glTF 2.0 schema in a way the parser tolerates (e.g. an
    /// extension whose value is not an object).
    #[error("{path}: glTF schema violation: {reason}")]
    Schema {
        /// The glTF file.
        path: PathBuf,
        /// Which rule of the schema the JSON breaks.
        reason: String,
    },
    /// A baked world file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file that could not be read or written.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A baked world file is corrupt, truncated, of another version, or inconsistent.
    #[error("{path}: {reason}")]
    Format {
        /// The baked file.
        path: PathBuf,
        /// Why the file was rejected.
        #[source]
        reason: FormatError,
    },
    /// The real assets the generator builds on (Debian's assimp-testmodels) are missing.
    #[error("{path}: generator assets missing ({reason}); install Debian's assimp-testmodels")]
    MissingAssets {
        /// The asset file that was looked for.
        path: PathBuf,
        /// Why the assets count as missing.
        reason: String,
    },
    /// A loader job panicked; the loader thread caught it and carries on.
    #[error("{path}: loader panicked: {message}")]
    LoaderPanic {
        /// The file the job was loading.
        path: PathBuf,
        /// The panic's message (a placeholder when it was not a string).
        message: String,
    },
}

/// Why a baked file was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum FormatError {
    /// The file does not start with the expected magic.
    #[error("bad magic {found:?} (expected {expected:?})")]
    BadMagic {
        /// The magic this kind of file starts with.
        expected: [u8; 4],
        /// The first four bytes of the file.
        found: [u8; 4],
    },
    /// The file was written by an unsupported format version.
    #[error("unsupported format version {found} (this build reads {supported})")]
    Version {
        /// The version the file was written with.
        found: u32,
        /// The version this build reads.
        supported: u32,
    },
    /// The file ends before the data it announces.
    #[error("truncated: needed {needed} bytes at offset {offset}, {available} available")]
    Truncated {
        /// The byte offset the announced data starts at.
        offset: usize,
        /// Bytes the data needs.
        needed: usize,
        /// Bytes from `offset` to the end of what was read.
        available: usize,
    },
    /// The payload's checksum does not match the header.
    #[error("checksum mismatch: header says {expected:#018x}, payload hashes to {actual:#018x}")]
    Checksum {
        /// The checksum the header records.
        expected: u64,
        /// The checksum of the payload as read.
        actual: u64,
    },
    /// The payload decodes but breaks an invariant (index out of range, NaN, unknown id...).
    #[error("inconsistent data: {0}")]
    Inconsistent(String),
}

/// The crate's result alias.
pub type Result<T, E = StreamingError> = std::result::Result<T, E>;
