//! # rtstream-as-manager
//!
//! Keeps bottom-level acceleration structures (BLAS) only for what the cameras can use, and
//! hands a culled top-level acceleration structure (TLAS) to the renderer each frame.
//!
//! Design choices:
//! - The policy core is plain Rust behind a narrow backend trait; only [`backend::vulkan`]
//!   (cargo feature `vulkan`, on by default) touches ash.

pub mod backend;
