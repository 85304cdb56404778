//! The engine's own device: [`ExternalDevice`] and [`VulkanContext::from_external`].
//!
//! An engine already has an instance, a device, queues and an allocator. It hands them over;
//! rtstream checks that the device has what it needs (a typed error names what is missing) and
//! creates nothing global: no instance, no device, no debug messenger. What it does create lives
//! on the engine's device and is destroyed when the context drops: one command pool for set-up
//! work, and (unless the engine shares its own) a gpu-allocator.

use std::ffi::{CStr, CString};
use std::mem::ManuallyDrop;
use std::sync::atomic::AtomicI64;
use std::sync::Arc;

use ash::{ext, khr, vk};
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};
use parking_lot::Mutex;

use crate::backend::vulkan::device::context::{handle_created, handle_destroyed, VulkanContext};
use crate::backend::vulkan::error::{caller_index, VkResult, VkResultExt, VulkanError};

/// Device features rtstream uses. An engine says which it enabled on its device (Vulkan cannot
/// be asked afterwards); [`DeviceFeatures::REQUIRED`] is what it must enable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DeviceFeatures {
    /// Vulkan 1.2 `bufferDeviceAddress`.
    pub buffer_device_address: bool,
    /// Vulkan 1.2 `timelineSemaphore`.
    pub timeline_semaphore: bool,
    /// Vulkan 1.2 `hostQueryReset`.
    pub host_query_reset: bool,
    /// Vulkan 1.3 `synchronization2`.
    pub synchronization2: bool,
    /// Vulkan 1.3 `maintenance4`.
    pub maintenance4: bool,
    /// `VkPhysicalDeviceAccelerationStructureFeaturesKHR::accelerationStructure`.
    pub acceleration_structure: bool,
    /// Core `shaderInt64`.
    pub shader_int64: bool,
    /// `VkPhysicalDeviceRayQueryFeaturesKHR::rayQuery` (with VK_KHR_ray_query).
    pub ray_query: bool,
    /// `VkPhysicalDeviceRayTracingPipelineFeaturesKHR::rayTracingPipeline`.
    pub ray_tracing_pipeline: bool,
}

impl DeviceFeatures {
    /// What rtstream needs, besides ray queries or ray-tracing pipelines (at least one of the
    /// two, for the renderer; the manager itself needs neither).
    pub const REQUIRED: DeviceFeatures = DeviceFeatures {
        buffer_device_address: true,
        timeline_semaphore: true,
        host_query_reset: true,
        synchronization2: true,
        maintenance4: true,
        acceleration_structure: true,
        shader_int64: true,
        ray_query: false,
        ray_tracing_pipeline: false,
    };

    /// The required features physical device `pd` of `instance` supports (ray queries and
    /// ray-tracing pipelines stay false: [`VulkanContext::new`] asks for those by extension).
    pub(crate) fn supported_by(instance: &ash::Instance, pd: vk::PhysicalDevice) -> Self {
        let mut v12 = vk::PhysicalDeviceVulkan12Features::default();
        let mut v13 = vk::PhysicalDeviceVulkan13Features::default();
        let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default();
        let mut feats2 = vk::PhysicalDeviceFeatures2::default()
            .push_next(&mut v12)
            .push_next(&mut v13)
            .push_next(&mut asf);
        // SAFETY: pd comes from this instance; the chained structs are valid for the call.
        unsafe { instance.get_physical_device_features2(pd, &mut feats2) };
        let core = feats2.features;
        let on = |f: vk::Bool32| f == vk::TRUE;
        DeviceFeatures {
            buffer_device_address: on(v12.buffer_device_address),
            timeline_semaphore: on(v12.timeline_semaphore),
            host_query_reset: on(v12.host_query_reset),
            synchronization2: on(v13.synchronization2),
            maintenance4: on(v13.maintenance4),
            acceleration_structure: on(asf.acceleration_structure),
            shader_int64: on(core.shader_int64),
            ray_query: false,
            ray_tracing_pipeline: false,
        }
    }

    /// Names (as in the Vulkan spec) of the required features this set lacks.
    pub fn missing(&self) -> Vec<&'static str> {
        [
            (self.buffer_device_address, "bufferDeviceAddress"),
            (self.timeline_semaphore, "timelineSemaphore"),
            (self.host_query_reset, "hostQueryReset"),
            (self.synchronization2, "synchronization2"),
            (self.maintenance4, "maintenance4"),
            (self.acceleration_structure, "accelerationStructure"),
            (self.shader_int64, "shaderInt64"),
        ]
        .iter()
        .filter(|(on, _)| !on)
        .map(|(_, n)| *n)
        .collect()
    }
}

/// Device extensions rtstream needs on every device.
pub const REQUIRED_DEVICE_EXTENSIONS: [&CStr; 2] = [
    khr::acceleration_structure::NAME,
    khr::deferred_host_operations::NAME,
];

/// What an engine hands over to run rtstream on its device.
///
/// The engine keeps ownership: it destroys the device and instance after the context (and
/// every backend and renderer on it) has dropped. The queue is used for rtstream's own
/// submissions (set-up work, own-submit frames): the engine must not submit to it from another
/// thread while rtstream does, or must give rtstream a queue of its own.
pub struct ExternalDevice {
    /// The engine's instance (Vulkan 1.3).
    pub instance: ash::Instance,
    /// The physical device the engine's device was created on.
    pub physical_device: vk::PhysicalDevice,
    /// The engine's device.
    pub device: ash::Device,
    /// Queue family of `queue` (it must support compute).
    pub queue_family: u32,
    /// The queue rtstream submits to.
    pub queue: vk::Queue,
    /// The device extensions the engine enabled (at least [`REQUIRED_DEVICE_EXTENSIONS`]).
    pub enabled_extensions: Vec<CString>,
    /// The features the engine enabled (at least [`DeviceFeatures::REQUIRED`]).
    pub enabled_features: DeviceFeatures,
    /// The engine's allocator, shared behind its lock; None: rtstream creates its own on the
    /// engine's device (created with `buffer_device_address` on).
    pub allocator: Option<Arc<Mutex<Allocator>>>,
    /// Whether VK_EXT_debug_utils is enabled on the instance (then rtstream names its objects).
    pub debug_utils: bool,
}

impl std::fmt::Debug for ExternalDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExternalDevice")
            .field("physical_device", &self.physical_device)
            .field("queue_family", &self.queue_family)
            .field("enabled_extensions", &self.enabled_extensions)
            .field("enabled_features", &self.enabled_features)
            .field("shared_allocator", &self.allocator.is_some())
            .finish_non_exhaustive()
    }
}

impl VulkanContext {
    /// A context on the engine's device. Checks the device's extensions and features (what the
    /// engine enabled, and what the device supports) and fails with
    /// [`VulkanError::MissingDeviceSupport`] naming everything missing.
    ///
    /// ```no_run
    /// # use std::sync::Arc;
    /// # use rtstream_as_manager::backend::vulkan::{
    /// #     ash, DeviceFeatures, ExternalDevice, VulkanBackend, VulkanBackendDesc, VulkanContext,
    /// #     REQUIRED_DEVICE_EXTENSIONS,
    /// # };
    /// # fn engine() -> (ash::Instance, ash::vk::PhysicalDevice, ash::Device, u32, ash::vk::Queue) {
    /// #     unimplemented!()
    /// # }
    /// // The engine created these with REQUIRED_DEVICE_EXTENSIONS plus VK_KHR_ray_query, and
    /// // DeviceFeatures::REQUIRED plus rayQuery, enabled.
    /// let (instance, physical_device, device, queue_family, queue) = engine();
    /// let mut enabled_extensions: Vec<std::ffi::CString> =
    ///     REQUIRED_DEVICE_EXTENSIONS.iter().map(|n| (*n).to_owned()).collect();
    /// enabled_extensions.push(ash::khr::ray_query::NAME.to_owned());
    /// let ctx = Arc::new(VulkanContext::from_external(ExternalDevice {
    ///     instance,
    ///     physical_device,
    ///     device,
    ///     queue_family,
    ///     queue,
    ///     enabled_extensions,
    ///     enabled_features: DeviceFeatures { ray_query: true, ..DeviceFeatures::REQUIRED },
    ///     allocator: None,
    ///     debug_utils: false,
    /// })?);
    /// let backend = VulkanBackend::new(ctx, VulkanBackendDesc::engine_recorded(3))?;
    /// # Ok::<(), rtstream_as_manager::backend::vulkan::VulkanError>(())
    /// ```
    pub fn from_external(ext: ExternalDevice) -> VkResult<Self> {
        let enabled = |n: &CStr| ext.enabled_extensions.iter().any(|e| e.as_c_str() == n);
        let mut missing_ext: Vec<String> = REQUIRED_DEVICE_EXTENSIONS
            .iter()
            .filter(|n| !enabled(n))
            .map(|n| n.to_string_lossy().into_owned())
            .collect();
        let mut missing_feat: Vec<String> = ext
            .enabled_features
            .missing()
            .into_iter()
            .map(String::from)
            .collect();
        let ray_query = enabled(khr::ray_query::NAME) && ext.enabled_features.ray_query;
        let rt_pipeline =
            enabled(khr::ray_tracing_pipeline::NAME) && ext.enabled_features.ray_tracing_pipeline;
        if !ray_query && !rt_pipeline {
            missing_ext.push("VK_KHR_ray_query or VK_KHR_ray_tracing_pipeline".into());
            missing_feat.push("rayQuery or rayTracingPipeline".into());
        }
        // What the device itself supports (an engine may have enabled everything on a device
        // that cannot do it, or picked the wrong physical device).
        let desc = crate::backend::vulkan::ContextDesc::default();
        let candidate = VulkanContext::evaluate(&ext.instance, ext.physical_device, &desc);
        let (name, supported) = match &candidate {
            Ok(c) => (c.info.name.clone(), None),
            Err((name, why)) => (name.clone(), Some(why.clone())),
        };
        if !missing_ext.is_empty() || !missing_feat.is_empty() || supported.is_some() {
            return Err(VulkanError::MissingDeviceSupport {
                device: name,
                extensions: missing_ext,
                features: missing_feat,
                unsupported: supported,
            });
        }
        let mut info = candidate
            .map_err(|(device, why)| VulkanError::MissingDeviceSupport {
                device,
                extensions: vec![],
                features: vec![],
                unsupported: Some(why),
            })?
            .info;
        // What is enabled, not what could be.
        info.ray_query = ray_query;
        info.ray_tracing_pipeline = rt_pipeline;
        info.memory_budget = enabled(ext::memory_budget::NAME);
        // SAFETY: the physical device belongs to the engine's instance.
        let families = unsafe {
            ext.instance
                .get_physical_device_queue_family_properties(ext.physical_device)
        };
        let family = caller_index(&families, ext.queue_family as usize, |n| {
            format!(
                "queue family {} does not exist ({n} families)",
                ext.queue_family
            )
        })?;
        if !family.queue_flags.contains(vk::QueueFlags::COMPUTE) {
            return Err(VulkanError::Unsupported(format!(
                "queue family {} has no compute",
                ext.queue_family
            )));
        }
        info.timestamps = family.timestamp_valid_bits > 0;
        info.reason = "the engine's device".into();

        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(ext.queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: the engine's device is valid; the pool is ours and destroyed in drop_imported.
        let command_pool = unsafe { ext.device.create_command_pool(&pool_info, None) }
            .op("vkCreateCommandPool")?;
        handle_created();
        let device = ext.device.clone();
        let command_pool = scopeguard::guard(command_pool, move |p| {
            // SAFETY: no command buffer of it was allocated yet.
            unsafe { device.destroy_command_pool(p, None) };
            handle_destroyed();
        });
        let allocator = match ext.allocator {
            Some(a) => a,
            None => Arc::new(Mutex::new(
                Allocator::new(&AllocatorCreateDesc {
                    instance: ext.instance.clone(),
                    device: ext.device.clone(),
                    physical_device: ext.physical_device,
                    debug_settings: Default::default(),
                    buffer_device_address: true,
                    allocation_sizes: Default::default(),
                })
                .map_err(|e| VulkanError::from_alloc("allocator creation", e))?,
            )),
        };
        let accel = khr::acceleration_structure::Device::new(&ext.instance, &ext.device);
        let rt =
            rt_pipeline.then(|| khr::ray_tracing_pipeline::Device::new(&ext.instance, &ext.device));
        let debug_device = ext
            .debug_utils
            .then(|| ext::debug_utils::Device::new(&ext.instance, &ext.device));
        tracing::info!(device = %info.name, "Vulkan context on the engine's device");
        let ctx = Self {
            _entry: None,
            owns_device: false,
            instance: ext.instance,
            debug_instance: None,
            debug_device,
            log: Box::default(),
            validation: false,
            physical_device: ext.physical_device,
            device: ext.device,
            accel,
            rt_pipeline: rt,
            queue: Mutex::new(ext.queue),
            queue_family: ext.queue_family,
            command_pool: Mutex::new(scopeguard::ScopeGuard::into_inner(command_pool)),
            allocator: ManuallyDrop::new(allocator),
            live_buffers: AtomicI64::new(0),
            info,
            failpoint: Mutex::new(None),
            live_tlases: Mutex::default(),
        };
        ctx.set_name(*ctx.command_pool.lock(), "rtstream one-shot pool");
        Ok(ctx)
    }

    /// Whether the context runs on a device the engine handed over.
    pub fn is_external(&self) -> bool {
        !self.owns_device
    }

    /// Drop of a context on the engine's device: destroys only what rtstream created.
    pub(crate) fn drop_imported(&mut self) {
        let leaked = self.live_buffers.load(std::sync::atomic::Ordering::Relaxed);
        if leaked != 0 {
            tracing::error!("{leaked} GPU buffers were not destroyed before the context");
        }
        // SAFETY: every submission of ours completed (backends and renderers wait before they
        // drop, and one-shot submits wait); our allocator (if it is ours) frees its blocks on
        // the engine's device, which the engine destroys only after this.
        unsafe {
            ManuallyDrop::drop(&mut self.allocator);
            self.device
                .destroy_command_pool(*self.command_pool.get_mut(), None);
        }
        handle_destroyed();
    }
}

impl VulkanContext {
    /// Bench and test support: this context's device as an engine would hand it over (the
    /// same instance, physical device, device, queue and allocator), for a second context made
    /// with [`VulkanContext::from_external`]; `gpu_bench` measures the engine's path this way on
    /// the same device. Drop the second context first. Each context locks the queue only for
    /// itself, so the two must not submit from two threads at once.
    #[doc(hidden)]
    pub fn as_external(&self) -> ExternalDevice {
        let mut enabled_extensions: Vec<CString> = REQUIRED_DEVICE_EXTENSIONS
            .iter()
            .map(|n| (*n).to_owned())
            .collect();
        let optional = [
            (self.info.ray_query, khr::ray_query::NAME),
            (
                self.info.ray_tracing_pipeline,
                khr::ray_tracing_pipeline::NAME,
            ),
            (self.info.memory_budget, ext::memory_budget::NAME),
        ];
        enabled_extensions.extend(
            optional
                .into_iter()
                .filter(|(on, _)| *on)
                .map(|(_, n)| n.to_owned()),
        );
        ExternalDevice {
            instance: self.instance.clone(),
            physical_device: self.physical_device,
            device: self.device.clone(),
            queue_family: self.queue_family,
            queue: *self.queue.lock(),
            enabled_extensions,
            enabled_features: DeviceFeatures {
                ray_query: self.info.ray_query,
                ray_tracing_pipeline: self.info.ray_tracing_pipeline,
                ..DeviceFeatures::REQUIRED
            },
            allocator: Some(Arc::clone(&self.allocator)),
            debug_utils: self.debug_device.is_some(),
        }
    }
}
