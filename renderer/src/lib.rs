//! # rtstream-renderer
//!
//! A ray-query renderer that traces the manager's TLAS, and image-difference metrics.
