//! The Vulkan context: instance, validation, device selection, queue, allocator, one-shot submits.
//!
//! Why one file just over 600 lines: the context's fields, its creation with every failure path
//! guarded (instance, messenger, device) and its drop are one ownership story; device
//! selection and device creation live in `select.rs`, the engine's device in `external.rs`.
//!
//! One context per process is the intended use; the renderer borrows it (`Arc<VulkanContext>`).
//! Lock order, where more than one lock is held: `command_pool` before `queue`; the allocator lock
//! is never held while either of the others is taken.

use std::ffi::{c_void, CStr, CString};
use std::mem::ManuallyDrop;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::Arc;

use ash::{ext, khr, vk};
use gpu_allocator::vulkan::Allocator;
use parking_lot::Mutex;

use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// Whether the validation layer also runs synchronization validation: on unless
/// `RTSTREAM_SYNC_VALIDATION=0`.
fn sync_validation() -> bool {
    std::env::var("RTSTREAM_SYNC_VALIDATION").as_deref() != Ok("0")
}

/// Whether to load the Khronos validation layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Validation {
    /// On in debug builds when the layer is installed; `RTSTREAM_VALIDATION=0|1` overrides.
    #[default]
    Auto,
    /// On, and an error ([`VulkanError::NoValidationLayer`]) when the layer is missing. Tests use this.
    Required,
    /// Off.
    Off,
}

/// Creation parameters of a [`VulkanContext`].
#[derive(Debug, Clone)]
pub struct ContextDesc {
    /// Application name given to the driver.
    pub app_name: String,
    /// Validation-layer policy.
    pub validation: Validation,
    /// Refuse devices without VK_KHR_ray_query (otherwise a device with acceleration structures
    /// and ray-tracing pipelines, such as the NVIDIA H100 driver here, is accepted).
    pub require_ray_query: bool,
    /// Test-only: fail creation at this step (`"messenger"`, `"device"`, `"command_pool"`,
    /// `"allocator"`) with [`VulkanError::Injected`], to check that nothing leaks.
    #[doc(hidden)]
    pub fail_at: Option<&'static str>,
}

/// Vulkan handles rtstream created and has not destroyed yet, process-wide: instances, debug
/// messengers, devices, command pools, semaphores and query pools (buffers are counted per
/// context). Leak tests compare it before and after a failed creation.
pub fn live_vulkan_handles() -> i64 {
    LIVE_HANDLES.load(Ordering::SeqCst)
}

static LIVE_HANDLES: AtomicI64 = AtomicI64::new(0);

/// One more live handle (see [`live_vulkan_handles`]).
pub(crate) fn handle_created() {
    LIVE_HANDLES.fetch_add(1, Ordering::SeqCst);
}

/// One handle fewer (see [`live_vulkan_handles`]).
pub(crate) fn handle_destroyed() {
    LIVE_HANDLES.fetch_sub(1, Ordering::SeqCst);
}

pub(crate) fn failpoint(armed: Option<&'static str>, at: &'static str) -> VkResult<()> {
    match armed {
        Some(a) if a == at => Err(VulkanError::Injected { at }),
        _ => Ok(()),
    }
}

impl Default for ContextDesc {
    fn default() -> Self {
        Self {
            app_name: "rtstream".into(),
            validation: Validation::Auto,
            require_ray_query: false,
            fail_at: None,
        }
    }
}

/// What kind of device the context runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceKind {
    /// A discrete GPU.
    Discrete,
    /// An integrated GPU.
    Integrated,
    /// A virtual GPU.
    Virtual,
    /// A CPU implementation (lavapipe): its AS builder is single-threaded, compaction saves
    /// nothing and an update costs a rebuild, so speed figures must come from a GPU.
    Cpu,
    /// Anything else.
    Other,
}

/// The chosen device: identity, capabilities and the limits the backend must respect.
#[derive(Debug, Clone)]
pub struct DeviceInfo {
    /// `deviceName`.
    pub name: String,
    /// `deviceType`.
    pub kind: DeviceKind,
    /// Driver name and info string (e.g. "llvmpipe", "Mesa 25.0.7").
    pub driver: String,
    /// Vulkan API version the device reports, as (major, minor, patch).
    pub api_version: (u32, u32, u32),
    /// VK_KHR_ray_query is available and enabled.
    pub ray_query: bool,
    /// VK_KHR_ray_tracing_pipeline is available and enabled.
    pub ray_tracing_pipeline: bool,
    /// VK_EXT_memory_budget is available and enabled.
    pub memory_budget: bool,
    /// `minAccelerationStructureScratchOffsetAlignment`: every scratch address is a multiple.
    pub min_scratch_alignment: u64,
    /// `maxPrimitiveCount` per BLAS.
    pub max_primitive_count: u64,
    /// `maxInstanceCount` per TLAS.
    pub max_instance_count: u64,
    /// `maxStorageBufferRange`.
    pub max_storage_buffer_range: u64,
    /// Nanoseconds per timestamp tick.
    pub timestamp_period_ns: f32,
    /// The queue writes timestamps (timestampValidBits > 0).
    pub timestamps: bool,
    /// Why this device was chosen, in words.
    pub reason: String,
}

/// Messages the debug messenger received. Validation warnings and errors are counted as
/// failures; the test suite asserts the count stays zero.
#[derive(Debug, Default)]
pub struct ValidationLog {
    failures: AtomicU64,
    messages: Mutex<Vec<String>>,
}

impl ValidationLog {
    /// Number of validation warnings and errors so far.
    pub fn failure_count(&self) -> u64 {
        self.failures.load(Ordering::Relaxed)
    }
    /// The failure messages so far (at most the first 64 are kept).
    pub fn messages(&self) -> Vec<String> {
        self.messages.lock().clone()
    }
}

/// The Vulkan context: instance, device, one queue, the device-memory allocator.
///
/// Two ways in: [`VulkanContext::new`] creates everything (the examples' path), and
/// [`VulkanContext::from_external`] takes the engine's instance, device, queue and (optionally)
/// allocator, and creates nothing global (see [`ExternalDevice`](super::external::ExternalDevice)).
pub struct VulkanContext {
    /// The loader, when the context created the instance (None on an engine's device).
    pub(crate) _entry: Option<ash::Entry>,
    /// Whether the context created the instance and device (and destroys them on drop).
    pub(crate) owns_device: bool,
    pub(crate) instance: ash::Instance,
    pub(crate) debug_instance: Option<(ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    pub(crate) debug_device: Option<ext::debug_utils::Device>,
    pub(crate) log: Box<ValidationLog>,
    pub(crate) validation: bool,
    pub(crate) physical_device: vk::PhysicalDevice,
    pub(crate) device: ash::Device,
    pub(crate) accel: khr::acceleration_structure::Device,
    pub(crate) rt_pipeline: Option<khr::ray_tracing_pipeline::Device>,
    pub(crate) queue: Mutex<vk::Queue>,
    pub(crate) queue_family: u32,
    pub(crate) command_pool: Mutex<vk::CommandPool>,
    /// Ours, or the engine's (shared behind its lock); dropped before the device.
    pub(crate) allocator: ManuallyDrop<Arc<Mutex<Allocator>>>,
    pub(crate) live_buffers: AtomicI64,
    pub(crate) info: DeviceInfo,
    /// A failure armed by `inject_failure` (test-only).
    pub(crate) failpoint: Mutex<Option<&'static str>>,
    /// The top-level acceleration structures alive on this context, each with the serial of
    /// its last recorded build (see [`TlasRef`](super::tlas_ref::TlasRef) and
    /// [`VulkanContext::is_live_tlas`]).
    pub(crate) live_tlases: Mutex<rustc_hash::FxHashMap<vk::AccelerationStructureKHR, u64>>,
}

impl std::fmt::Debug for VulkanContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VulkanContext")
            .field("device", &self.info.name)
            .field("validation", &self.validation)
            .finish_non_exhaustive()
    }
}

/// What `create_device` made, for `new` to assemble.
pub(crate) struct DeviceParts {
    pub(crate) device: ash::Device,
    pub(crate) queue: vk::Queue,
    pub(crate) command_pool: vk::CommandPool,
    pub(crate) allocator: Allocator,
    pub(crate) accel: khr::acceleration_structure::Device,
    pub(crate) rt_pipeline: Option<khr::ray_tracing_pipeline::Device>,
    pub(crate) debug_device: Option<ext::debug_utils::Device>,
}

pub(crate) struct Candidate {
    pub(crate) pd: vk::PhysicalDevice,
    pub(crate) info: DeviceInfo,
    pub(crate) queue_family: u32,
    pub(crate) score: u32,
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the loader passes a valid callback-data pointer (or null) for the call's duration.
    let message = unsafe { data.as_ref() }
        .filter(|d| !d.p_message.is_null())
        .map(|d| {
            // SAFETY: p_message is a NUL-terminated string owned by the loader for the call.
            unsafe { CStr::from_ptr(d.p_message) }
                .to_string_lossy()
                .into_owned()
        })
        .unwrap_or_default();
    let failure = types.intersects(
        vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
            | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
    ) && severity.intersects(
        vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
            | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR,
    );
    if failure {
        tracing::error!(target: "vulkan", "{message}");
        // SAFETY: `user` is the Box<ValidationLog> the context owns; it outlives the messenger.
        if let Some(log) = unsafe { (user as *const ValidationLog).as_ref() } {
            log.failures.fetch_add(1, Ordering::Relaxed);
            let mut m = log.messages.lock();
            if m.len() < 64 {
                m.push(message);
            }
        }
    } else if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING) {
        tracing::warn!(target: "vulkan", "{message}");
    } else {
        tracing::debug!(target: "vulkan", "{message}");
    }
    vk::FALSE
}

fn validation_wanted(v: Validation) -> bool {
    match v {
        Validation::Required => true,
        Validation::Off => false,
        Validation::Auto => match std::env::var("RTSTREAM_VALIDATION").as_deref() {
            Ok("0") | Ok("false") | Ok("off") => false,
            Ok(_) => true,
            Err(_) => cfg!(debug_assertions),
        },
    }
}

pub(crate) fn cstr_array(bytes: &[std::ffi::c_char]) -> String {
    // SAFETY: Vulkan fixed-size name arrays are NUL-terminated.
    unsafe { CStr::from_ptr(bytes.as_ptr()) }
        .to_string_lossy()
        .into_owned()
}

impl VulkanContext {
    /// Creates the instance and device, choosing the best device with acceleration structures.
    ///
    /// Prefers a device with VK_KHR_ray_query; takes one with only ray-tracing pipelines when
    /// `desc.require_ray_query` is false; `RTSTREAM_DEVICE=<substring>` restricts the choice by name.
    pub fn new(desc: &ContextDesc) -> VkResult<Self> {
        // SAFETY: loading libvulkan runs its initialisers; we trust the system's loader.
        let entry = unsafe { ash::Entry::load() }.map_err(|e| VulkanError::NoLoader {
            reason: e.to_string(),
        })?;

        // SAFETY: entry is a loaded Vulkan entry.
        let layers = unsafe { entry.enumerate_instance_layer_properties() }
            .op("vkEnumerateInstanceLayerProperties")?;
        let has_layer = layers
            .iter()
            .any(|l| l.layer_name_as_c_str() == Ok(VALIDATION_LAYER));
        let mut validation = validation_wanted(desc.validation);
        if validation && !has_layer {
            if desc.validation == Validation::Required {
                return Err(VulkanError::NoValidationLayer);
            }
            tracing::warn!("validation layer not installed; continuing without it");
            validation = false;
        }
        // SAFETY: as above.
        let exts = unsafe { entry.enumerate_instance_extension_properties(None) }
            .op("vkEnumerateInstanceExtensionProperties")?;
        let has_debug_utils = exts
            .iter()
            .any(|e| e.extension_name_as_c_str() == Ok(ext::debug_utils::NAME));

        let app_name = CString::new(desc.app_name.as_str()).unwrap_or_else(|_| c"rtstream".into());
        let app = vk::ApplicationInfo::default()
            .application_name(&app_name)
            .engine_name(c"rtstream")
            .api_version(vk::API_VERSION_1_3);
        let layer_ptrs: Vec<*const std::ffi::c_char> = if validation {
            vec![VALIDATION_LAYER.as_ptr()]
        } else {
            vec![]
        };
        let ext_ptrs: Vec<*const std::ffi::c_char> = if has_debug_utils {
            vec![ext::debug_utils::NAME.as_ptr()]
        } else {
            vec![]
        };
        // With the layer: synchronization validation too (hazards between frames in flight,
        // in-place refits and TLAS rebuilds against the traces that read them). The layer
        // provides VK_EXT_validation_features.
        let sync_features = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features =
            vk::ValidationFeaturesEXT::default().enabled_validation_features(&sync_features);
        let mut instance_info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layer_ptrs)
            .enabled_extension_names(&ext_ptrs);
        if validation && sync_validation() {
            instance_info = instance_info.push_next(&mut features);
        }
        // SAFETY: all pointers in instance_info point to locals that outlive the call.
        let instance = match unsafe { entry.create_instance(&instance_info, None) } {
            Ok(i) => i,
            // The loader found no driver (ICD) at all.
            Err(vk::Result::ERROR_INCOMPATIBLE_DRIVER) => {
                return Err(VulkanError::NoSuitableDevice { devices: vec![] })
            }
            Err(e) => return Err(VulkanError::from_vk("vkCreateInstance", e)),
        };
        handle_created();
        // Every step below may fail: each object is owned by a guard that destroys it unless
        // the context takes it over at the end.
        let instance = scopeguard::guard(instance, |i| {
            // SAFETY: creation failed later on; nothing else created from it is alive (each
            // child has its own guard, dropped first).
            unsafe { i.destroy_instance(None) };
            handle_destroyed();
        });

        let log = Box::<ValidationLog>::default();
        let debug_instance = if has_debug_utils {
            let du = ext::debug_utils::Instance::new(&entry, &instance);
            let info = vk::DebugUtilsMessengerCreateInfoEXT::default()
                .message_severity(
                    vk::DebugUtilsMessageSeverityFlagsEXT::ERROR
                        | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
                        | vk::DebugUtilsMessageSeverityFlagsEXT::INFO,
                )
                .message_type(
                    vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                        | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                        | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
                )
                .pfn_user_callback(Some(debug_callback))
                .user_data(&*log as *const ValidationLog as *mut c_void);
            failpoint(desc.fail_at, "messenger")?;
            // SAFETY: the callback's user data is the boxed log, which lives as long as the context
            // and is dropped only after the messenger is destroyed (see Drop).
            let messenger = unsafe { du.create_debug_utils_messenger(&info, None) }
                .op("vkCreateDebugUtilsMessengerEXT")?;
            handle_created();
            Some((du, messenger))
        } else {
            None
        };
        let debug_instance = scopeguard::guard(debug_instance, |d| {
            if let Some((du, m)) = d {
                // SAFETY: created above; nothing reports through it any more.
                unsafe { du.destroy_debug_utils_messenger(m, None) };
                handle_destroyed();
            }
        });

        let chosen = Self::choose_device(&instance, desc)?;
        tracing::info!(
            device = %chosen.info.name,
            driver = %chosen.info.driver,
            kind = ?chosen.info.kind,
            validation,
            "Vulkan device chosen: {}",
            chosen.info.reason
        );
        let parts = Self::create_device(&instance, has_debug_utils, desc.fail_at, &chosen)?;
        let ctx = Self {
            _entry: Some(entry),
            owns_device: true,
            instance: scopeguard::ScopeGuard::into_inner(instance),
            debug_instance: scopeguard::ScopeGuard::into_inner(debug_instance),
            debug_device: parts.debug_device,
            log,
            validation,
            physical_device: chosen.pd,
            device: parts.device,
            accel: parts.accel,
            rt_pipeline: parts.rt_pipeline,
            queue: Mutex::new(parts.queue),
            queue_family: chosen.queue_family,
            command_pool: Mutex::new(parts.command_pool),
            allocator: ManuallyDrop::new(Arc::new(Mutex::new(parts.allocator))),
            live_buffers: AtomicI64::new(0),
            info: chosen.info,
            failpoint: Mutex::new(None),
            live_tlases: Mutex::default(),
        };
        ctx.set_name(parts.queue, "rtstream queue");
        ctx.set_name(parts.command_pool, "rtstream one-shot pool");
        Ok(ctx)
    }

    /// Test-only: the next [`VulkanContext::failpoint`] check at `at` fails with
    /// [`VulkanError::Injected`] (steps: `"backend.pool"`, `"backend.semaphore"`,
    /// `"backend.command_buffers"`, `"query_pool"`, `"build_blas_now.scratch"`,
    /// `"create_accel_in"`).
    #[doc(hidden)]
    pub fn inject_failure(&self, at: &'static str) {
        *self.failpoint.lock() = Some(at);
    }

    /// GPU buffers created on this context and not destroyed yet.
    pub fn live_buffers(&self) -> i64 {
        self.live_buffers.load(Ordering::Relaxed)
    }

    /// Fails once with [`VulkanError::Injected`] if a test armed `at`.
    pub(crate) fn failpoint(&self, at: &'static str) -> VkResult<()> {
        let mut f = self.failpoint.lock();
        let r = failpoint(*f, at);
        if r.is_err() {
            *f = None;
        }
        r
    }

    /// The chosen device.
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }

    /// Whether the validation layer is loaded.
    pub fn validation_enabled(&self) -> bool {
        self.validation
    }

    /// Validation messages received so far.
    pub fn validation_log(&self) -> &ValidationLog {
        &self.log
    }

    /// The raw `ash` device, for crates that record their own commands (the renderer).
    pub fn device(&self) -> &ash::Device {
        &self.device
    }

    /// The ray-tracing-pipeline extension functions, when the device has them.
    pub fn ray_tracing_pipeline(&self) -> Option<&khr::ray_tracing_pipeline::Device> {
        self.rt_pipeline.as_ref()
    }

    /// The queue family of the context's queue.
    pub fn queue_family(&self) -> u32 {
        self.queue_family
    }

    /// Gives a Vulkan object a debug name (shown by validation messages and capture tools).
    pub fn set_name<H: vk::Handle>(&self, handle: H, name: &str) {
        let Some(du) = &self.debug_device else { return };
        let Ok(name) = CString::new(name) else { return };
        let info = vk::DebugUtilsObjectNameInfoEXT::default()
            .object_handle(handle)
            .object_name(&name);
        // SAFETY: the handle belongs to this device; naming is externally synchronised per
        // object, and names are set right after creation by the creating thread.
        if let Err(e) = unsafe { du.set_debug_utils_object_name(&info) } {
            tracing::debug!("naming {name:?} failed: {e}");
        }
    }

    /// Records commands with `record`, submits them, and waits for completion.
    ///
    /// For set-up work and tests; per-frame work goes through the frame timeline instead.
    pub fn submit_and_wait<R>(
        &self,
        name: &str,
        record: impl FnOnce(&ash::Device, vk::CommandBuffer) -> R,
    ) -> VkResult<R> {
        let pool = self.command_pool.lock();
        let alloc = vk::CommandBufferAllocateInfo::default()
            .command_pool(*pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool is locked for the whole recording (external synchronisation).
        let cmd = unsafe { self.device.allocate_command_buffers(&alloc) }
            .op("vkAllocateCommandBuffers")?[0];
        self.set_name(cmd, name);
        let result = (|| {
            let begin = vk::CommandBufferBeginInfo::default()
                .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
            // SAFETY: cmd is a fresh primary command buffer from the locked pool.
            unsafe { self.device.begin_command_buffer(cmd, &begin) }.op("vkBeginCommandBuffer")?;
            let out = record(&self.device, cmd);
            // SAFETY: cmd is in the recording state.
            unsafe { self.device.end_command_buffer(cmd) }.op("vkEndCommandBuffer")?;
            // SAFETY: device is valid.
            let fence = unsafe {
                self.device
                    .create_fence(&vk::FenceCreateInfo::default(), None)
            }
            .op("vkCreateFence")?;
            let cmd_infos = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
            let submit = [vk::SubmitInfo2::default().command_buffer_infos(&cmd_infos)];
            let submitted = {
                let queue = self.queue.lock();
                // SAFETY: the queue is locked; cmd is executable; fence is unsignalled.
                unsafe { self.device.queue_submit2(*queue, &submit, fence) }.op("vkQueueSubmit2")
            };
            let waited = submitted.and_then(|()| {
                // SAFETY: fence was submitted above.
                unsafe { self.device.wait_for_fences(&[fence], true, u64::MAX) }
                    .op("vkWaitForFences")
            });
            // SAFETY: the fence is signalled or was never submitted; no one else uses it.
            unsafe { self.device.destroy_fence(fence, None) };
            waited.map(|()| out)
        })();
        // SAFETY: the command buffer is no longer pending (waited, or never submitted).
        unsafe { self.device.free_command_buffers(*pool, &[cmd]) };
        result
    }

    /// Submits already-recorded work with timeline-semaphore waits/signals (frames in flight).
    #[allow(dead_code)] // used by the frame timeline (frames in flight)
    pub(crate) fn submit(&self, submit: &[vk::SubmitInfo2<'_>]) -> VkResult<()> {
        let queue = self.queue.lock();
        // SAFETY: the queue is locked; the caller guarantees the submit infos are valid.
        unsafe { self.device.queue_submit2(*queue, submit, vk::Fence::null()) }.op("vkQueueSubmit2")
    }

    /// Waits until timeline semaphore `semaphore` (of this device) reaches `value`.
    pub fn wait_timeline(&self, semaphore: vk::Semaphore, value: u64) -> VkResult<()> {
        let sems = [semaphore];
        let vals = [value];
        // SAFETY: a timeline semaphore of this device (the caller's); waiting reads it only.
        unsafe {
            self.device.wait_semaphores(
                &vk::SemaphoreWaitInfo::default()
                    .semaphores(&sems)
                    .values(&vals),
                u64::MAX,
            )
        }
        .op("vkWaitSemaphores")
    }

    /// Waits until the device is idle.
    pub fn wait_idle(&self) -> VkResult<()> {
        let _queue = self.queue.lock();
        // SAFETY: device is valid; holding the queue lock keeps other submits out.
        unsafe { self.device.device_wait_idle() }.op("vkDeviceWaitIdle")
    }

    /// Device-local heap usage and budget in bytes (VK_EXT_memory_budget), when available.
    pub fn memory_budget(&self) -> Option<(u64, u64)> {
        if !self.info.memory_budget {
            return None;
        }
        let mut budget = vk::PhysicalDeviceMemoryBudgetPropertiesEXT::default();
        let mut props = vk::PhysicalDeviceMemoryProperties2::default().push_next(&mut budget);
        // SAFETY: physical device is valid; the chain lives through the call.
        unsafe {
            self.instance
                .get_physical_device_memory_properties2(self.physical_device, &mut props)
        };
        let mp = props.memory_properties;
        let (mut usage, mut limit) = (0, 0);
        for (i, heap) in mp.memory_heaps[..mp.memory_heap_count as usize]
            .iter()
            .enumerate()
        {
            if heap.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL) {
                usage += budget.heap_usage[i];
                limit += budget.heap_budget[i];
            }
        }
        Some((usage, limit))
    }
}

impl Drop for VulkanContext {
    fn drop(&mut self) {
        if !self.owns_device {
            self.drop_imported();
            return;
        }
        // SAFETY: we own every object below and destroy them children-first after the device is
        // idle; the allocator is dropped before the device it allocates from.
        unsafe {
            let _ = self.device.device_wait_idle();
            let leaked = self.live_buffers.load(Ordering::Relaxed);
            if leaked != 0 {
                tracing::error!("{leaked} GPU buffers were not destroyed before the context");
            }
            ManuallyDrop::drop(&mut self.allocator);
            self.device
                .destroy_command_pool(*self.command_pool.get_mut(), None);
            self.device.destroy_device(None);
            if let Some((du, m)) = self.debug_instance.take() {
                du.destroy_debug_utils_messenger(m, None);
                handle_destroyed();
            }
            self.instance.destroy_instance(None);
            // Instance, device and command pool.
            for _ in 0..3 {
                handle_destroyed();
            }
        }
    }
}
