//! Errors of the Vulkan backend.

use ash::vk;

/// How to get a Vulkan driver with ray tracing on a Debian 12 machine; quoted in errors.
pub const INSTALL_HINT: &str = "install a Vulkan driver with ray tracing: on Debian 12 run \
`scripts/setup.sh` (it installs mesa-vulkan-drivers 25.x from bookworm-backports, whose lavapipe \
has VK_KHR_acceleration_structure and VK_KHR_ray_query; bookworm's own 22.3 has neither)";

/// Everything the Vulkan backend can fail with.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VulkanError {
    /// libvulkan could not be loaded.
    #[error("no Vulkan loader (libvulkan.so.1) could be loaded: {reason}; {hint}", hint = INSTALL_HINT)]
    NoLoader {
        /// Why loading failed, in the loader's words.
        reason: String,
    },
    /// The validation layer was required but is not installed.
    #[error("validation was required but VK_LAYER_KHRONOS_validation is not installed (apt-get install vulkan-validationlayers)")]
    NoValidationLayer,
    /// No physical device offers what rtstream needs. `devices` says what each one lacked.
    #[error("no suitable Vulkan device: {}; {hint}", describe_devices(.devices), hint = INSTALL_HINT)]
    NoSuitableDevice {
        /// Each physical device passed over: its name and what it lacked.
        devices: Vec<(String, String)>,
    },
    /// The engine's device (see `VulkanContext::from_external`) lacks what rtstream needs:
    /// device extensions or features the engine did not enable, or, in `unsupported`, why the
    /// physical device itself cannot run rtstream.
    #[error("the engine's device {device} lacks what rtstream needs: {}", describe_missing(.extensions, .features, .unsupported))]
    MissingDeviceSupport {
        /// The device's name.
        device: String,
        /// Device extensions rtstream needs that the engine did not enable.
        extensions: Vec<String>,
        /// Device features rtstream needs that the engine did not enable.
        features: Vec<String>,
        /// Why the physical device itself cannot run rtstream, if it cannot.
        unsupported: Option<String>,
    },
    /// The device ran out of memory (VK_ERROR_OUT_OF_DEVICE_MEMORY or an allocator failure
    /// for lack of memory). Callers may free something and retry.
    #[error("out of device memory during {op}")]
    OutOfDeviceMemory {
        /// The operation that ran out of memory.
        op: &'static str,
    },
    /// The device was lost (driver crash, GPU reset, or a hang the driver gave up on).
    #[error("device lost during {op}")]
    DeviceLost {
        /// The operation during which the device was lost.
        op: &'static str,
    },
    /// Any other Vulkan error code.
    #[error("{op} failed: {result}")]
    Vk {
        /// The operation that failed.
        op: &'static str,
        /// The error code Vulkan returned.
        result: vk::Result,
    },
    /// gpu-allocator failed for a reason other than lack of memory.
    #[error("device-memory allocation for {op} failed: {source}")]
    Allocation {
        /// The operation the memory was for.
        op: &'static str,
        /// The allocator's error.
        #[source]
        source: gpu_allocator::AllocationError,
    },
    /// A request the device cannot satisfy (a size over a device limit, ...).
    #[error("{0}")]
    Unsupported(String),
    /// A handle names an object that no longer exists: a TLAS whose frame slot was reused by a
    /// later frame, or a BLAS that was freed (its slot may hold a newer BLAS of another
    /// generation, which a stale handle never resolves to).
    #[error("stale {what} handle: {detail}")]
    StaleHandle {
        /// The kind of handle ("BLAS" or "TLAS").
        what: &'static str,
        /// Which object the handle named and what became of it.
        detail: String,
    },
    /// A [`FrameCmd`](crate::backend::vulkan::FrameCmd) that cannot be recorded into or
    /// submitted: another device's or another frame loop's, or one no longer recording its
    /// frame (submitted already, or abandoned by a later `FrameLoop::begin`).
    #[error("frame {frame}'s command buffer {why}")]
    FrameCmdUnusable {
        /// The frame the `FrameCmd` names.
        frame: u64,
        /// What is wrong with it.
        why: &'static str,
    },
    /// A failure injected by a test at a named step (see `VulkanContext::inject_failure`).
    #[error("injected failure at {at}")]
    Injected {
        /// The step the failure was injected at.
        at: &'static str,
    },
}

fn describe_missing(
    extensions: &[String],
    features: &[String],
    unsupported: &Option<String>,
) -> String {
    let mut parts = Vec::new();
    if !extensions.is_empty() {
        parts.push(format!("extensions not enabled: {}", extensions.join(", ")));
    }
    if !features.is_empty() {
        parts.push(format!("features not enabled: {}", features.join(", ")));
    }
    if let Some(why) = unsupported {
        parts.push(format!("the device cannot: {why}"));
    }
    parts.join("; ")
}

fn describe_devices(devices: &[(String, String)]) -> String {
    if devices.is_empty() {
        return "the Vulkan loader found no physical device".into();
    }
    devices
        .iter()
        .map(|(name, why)| format!("{name}: {why}"))
        .collect::<Vec<_>>()
        .join("; ")
}

/// The backend's result alias.
pub type VkResult<T> = std::result::Result<T, VulkanError>;

/// `items[index]` for an index a caller passed in, or [`VulkanError::Unsupported`] with the
/// message `what` makes of how many items there are.
pub(crate) fn caller_index<T>(
    items: &[T],
    index: usize,
    what: impl FnOnce(usize) -> String,
) -> VkResult<&T> {
    items
        .get(index)
        .ok_or_else(|| VulkanError::Unsupported(what(items.len())))
}

/// Extension trait mapping `ash`'s results to [`VulkanError`], naming the operation.
pub(crate) trait VkResultExt<T> {
    fn op(self, op: &'static str) -> VkResult<T>;
}

impl<T> VkResultExt<T> for Result<T, vk::Result> {
    fn op(self, op: &'static str) -> VkResult<T> {
        self.map_err(|result| VulkanError::from_vk(op, result))
    }
}

impl VulkanError {
    /// Classifies a raw `vk::Result`.
    pub fn from_vk(op: &'static str, result: vk::Result) -> Self {
        match result {
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
                Self::OutOfDeviceMemory { op }
            }
            vk::Result::ERROR_DEVICE_LOST => Self::DeviceLost { op },
            result => Self::Vk { op, result },
        }
    }

    pub(crate) fn from_alloc(op: &'static str, source: gpu_allocator::AllocationError) -> Self {
        match source {
            gpu_allocator::AllocationError::OutOfMemory => Self::OutOfDeviceMemory { op },
            source => Self::Allocation { op, source },
        }
    }

    /// Whether freeing memory and retrying could help.
    pub fn is_out_of_memory(&self) -> bool {
        matches!(self, Self::OutOfDeviceMemory { .. })
    }
}
