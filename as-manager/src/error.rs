//! The crate's error type and `Result` alias.

use crate::backend::BackendError;

/// Everything the manager can refuse or fail at.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum AsError {
    /// A [`crate::Config`] value is out of range; the string names the field and the rule.
    #[error("invalid config: {0}")]
    InvalidConfig(String),
    /// A mesh description is unusable (no LODs, bad counts, indices out of range, non-finite data).
    #[error("invalid mesh `{name}`: {reason}")]
    InvalidMesh {
        /// The mesh's debug name.
        name: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A transform holds NaN or infinite values.
    #[error("invalid transform (non-finite values)")]
    InvalidTransform,
    /// An instance description is out of range (customIndex or SBT offset beyond 24 bits).
    #[error("invalid instance: {0}")]
    InvalidInstance(String),
    /// The mesh id is unknown or was unregistered.
    #[error("unknown mesh {0:?}")]
    UnknownMesh(crate::MeshId),
    /// The instance id is unknown or was removed.
    #[error("unknown instance {0:?}")]
    UnknownInstance(crate::InstanceId),
    /// The group id is stale or was never issued.
    #[error("unknown or removed group {0:?}")]
    UnknownGroup(crate::GroupId),
    /// A group's description is unusable (bounds, parent).
    #[error("invalid group: {0}")]
    InvalidGroup(String),
    /// A skinned pose in the engine's GPU buffer is unusable (null or misaligned address or
    /// stride, stride smaller than a position, no vertices).
    #[error("invalid device pose: {0}")]
    InvalidDevicePose(#[source] crate::mesh::DeviceGeometryError),
    /// The operation needs a skinned instance.
    #[error("instance {0:?} is not skinned")]
    NotSkinned(crate::InstanceId),
    /// `update` was given a frame number not after the last one's: frame numbers must
    /// increase (they order retirement and hysteresis). Nothing changed.
    #[error("frame {frame} does not follow frame {last}: frame numbers must increase")]
    FrameNotIncreasing {
        /// The refused frame number.
        frame: u64,
        /// The last frame `update` ran.
        last: u64,
    },
    /// `update(u64::MAX)`: the largest frame number is `u64::MAX - 1` (a GPU timeline signals
    /// `frame + 1` when a frame completes). Nothing changed.
    #[error("frame {0}: the largest frame number is u64::MAX - 1")]
    FrameNumberTooLarge(u64),
    /// The backend reported an error the manager cannot absorb (device lost).
    #[error("backend: {0}")]
    Backend(#[from] BackendError),
}

/// `Result` with [`AsError`].
pub type Result<T, E = AsError> = std::result::Result<T, E>;
