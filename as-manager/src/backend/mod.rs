//! Backends: where BLAS/TLAS are really built.

#[cfg(feature = "vulkan")]
pub mod vulkan;
