//! The Vulkan backend (ash): context, acceleration structures, frames in flight.
