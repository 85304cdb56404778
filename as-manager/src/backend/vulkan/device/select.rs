//! Choosing the physical device and creating the logical device, for [`VulkanContext::new`]:
//! what each candidate lacks (named in the error when none fits), and the device with the
//! extensions and features rtstream needs.

use std::ffi::CStr;

use ash::{ext, khr, vk};
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use crate::backend::vulkan::device::context::{
    cstr_array, failpoint, handle_created, handle_destroyed, Candidate, ContextDesc, DeviceInfo,
    DeviceKind, DeviceParts, VulkanContext,
};
use crate::backend::vulkan::device::external::DeviceFeatures;
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

impl VulkanContext {
    pub(super) fn choose_device(
        instance: &ash::Instance,
        desc: &ContextDesc,
    ) -> VkResult<Candidate> {
        // SAFETY: instance is valid.
        let pds =
            unsafe { instance.enumerate_physical_devices() }.op("vkEnumeratePhysicalDevices")?;
        let filter = std::env::var("RTSTREAM_DEVICE").ok();
        let mut rejected = Vec::new();
        let mut best: Option<Candidate> = None;
        for pd in pds {
            match Self::evaluate(instance, pd, desc) {
                Ok(c) => {
                    if let Some(f) = &filter {
                        if !c.info.name.to_lowercase().contains(&f.to_lowercase()) {
                            rejected
                                .push((c.info.name, format!("excluded by RTSTREAM_DEVICE={f}")));
                            continue;
                        }
                    }
                    if best.as_ref().is_none_or(|b| c.score > b.score) {
                        if let Some(b) = best.take() {
                            rejected.push((b.info.name, "a better device was found".into()));
                        }
                        best = Some(c);
                    } else {
                        rejected.push((c.info.name, "a better device was found".into()));
                    }
                }
                Err(why) => rejected.push(why),
            }
        }
        match best {
            Some(mut c) => {
                if !rejected.is_empty() {
                    let others: Vec<String> =
                        rejected.iter().map(|(n, w)| format!("{n} ({w})")).collect();
                    c.info
                        .reason
                        .push_str(&format!("; passed over: {}", others.join(", ")));
                }
                Ok(c)
            }
            None => Err(VulkanError::NoSuitableDevice { devices: rejected }),
        }
    }

    pub(crate) fn evaluate(
        instance: &ash::Instance,
        pd: vk::PhysicalDevice,
        desc: &ContextDesc,
    ) -> Result<Candidate, (String, String)> {
        let mut as_props = vk::PhysicalDeviceAccelerationStructurePropertiesKHR::default();
        let mut driver_props = vk::PhysicalDeviceDriverProperties::default();
        let mut props2 = vk::PhysicalDeviceProperties2::default()
            .push_next(&mut as_props)
            .push_next(&mut driver_props);
        // SAFETY: pd comes from this instance; the chained structs are valid for the call.
        unsafe { instance.get_physical_device_properties2(pd, &mut props2) };
        let props = props2.properties;
        let name = cstr_array(&props.device_name);
        let reject = |why: &str| (name.clone(), why.to_owned());
        let api = (
            vk::api_version_major(props.api_version),
            vk::api_version_minor(props.api_version),
            vk::api_version_patch(props.api_version),
        );
        if (api.0, api.1) < (1, 3) {
            return Err(reject(&format!("Vulkan {}.{} < 1.3", api.0, api.1)));
        }
        // SAFETY: as above.
        let exts = unsafe { instance.enumerate_device_extension_properties(pd) }
            .map_err(|e| reject(&format!("cannot list extensions: {e}")))?;
        let has = |n: &CStr| exts.iter().any(|e| e.extension_name_as_c_str() == Ok(n));
        for required in [
            khr::acceleration_structure::NAME,
            khr::deferred_host_operations::NAME,
        ] {
            if !has(required) {
                return Err(reject(&format!("no {}", required.to_string_lossy())));
            }
        }
        let ray_query = has(khr::ray_query::NAME);
        let rt_pipeline = has(khr::ray_tracing_pipeline::NAME);
        if !ray_query && (desc.require_ray_query || !rt_pipeline) {
            return Err(reject(if desc.require_ray_query {
                "no VK_KHR_ray_query"
            } else {
                "neither VK_KHR_ray_query nor VK_KHR_ray_tracing_pipeline"
            }));
        }

        let missing = DeviceFeatures::supported_by(instance, pd).missing();
        if !missing.is_empty() {
            return Err(reject(&format!("missing features: {}", missing.join(", "))));
        }

        // SAFETY: as above.
        let families = unsafe { instance.get_physical_device_queue_family_properties(pd) };
        let queue_family = families
            .iter()
            .enumerate()
            .filter(|(_, f)| f.queue_flags.contains(vk::QueueFlags::COMPUTE))
            // Prefer a family that also has graphics (the universal queue) and timestamps.
            .max_by_key(|(_, f)| {
                (
                    f.timestamp_valid_bits > 0,
                    f.queue_flags.contains(vk::QueueFlags::GRAPHICS),
                )
            })
            .map(|(i, _)| i as u32)
            .ok_or_else(|| reject("no compute queue"))?;

        let kind = match props.device_type {
            vk::PhysicalDeviceType::DISCRETE_GPU => DeviceKind::Discrete,
            vk::PhysicalDeviceType::INTEGRATED_GPU => DeviceKind::Integrated,
            vk::PhysicalDeviceType::VIRTUAL_GPU => DeviceKind::Virtual,
            vk::PhysicalDeviceType::CPU => DeviceKind::Cpu,
            _ => DeviceKind::Other,
        };
        let score = u32::from(ray_query) * 8
            + match kind {
                DeviceKind::Discrete => 4,
                DeviceKind::Integrated => 3,
                DeviceKind::Virtual => 2,
                DeviceKind::Cpu | DeviceKind::Other => 1,
            };
        let reason = format!(
            "{kind:?} device with acceleration structures{}{}",
            if ray_query {
                " and ray queries"
            } else {
                " and ray-tracing pipelines (no ray queries)"
            },
            if kind == DeviceKind::Cpu {
                " — a CPU implementation: correct but slow; GPU figures need a GPU"
            } else {
                ""
            }
        );
        let fam = families[queue_family as usize];
        Ok(Candidate {
            pd,
            queue_family,
            score,
            info: DeviceInfo {
                name,
                kind,
                driver: format!(
                    "{} {}",
                    cstr_array(&driver_props.driver_name),
                    cstr_array(&driver_props.driver_info)
                ),
                api_version: api,
                ray_query,
                ray_tracing_pipeline: rt_pipeline,
                memory_budget: has(ext::memory_budget::NAME),
                min_scratch_alignment: u64::from(
                    as_props.min_acceleration_structure_scratch_offset_alignment,
                )
                .max(1),
                max_primitive_count: as_props.max_primitive_count,
                max_instance_count: as_props.max_instance_count,
                max_storage_buffer_range: u64::from(props.limits.max_storage_buffer_range),
                timestamp_period_ns: props.limits.timestamp_period,
                timestamps: fam.timestamp_valid_bits > 0,
                reason,
            },
        })
    }

    #[allow(clippy::too_many_arguments)]
    /// The device and what hangs off it, for `new` to assemble; on failure nothing created
    /// here is left alive.
    pub(super) fn create_device(
        instance: &ash::Instance,
        has_debug_utils: bool,
        fail_at: Option<&'static str>,
        c: &Candidate,
    ) -> VkResult<DeviceParts> {
        let mut ext_names = vec![
            khr::acceleration_structure::NAME.as_ptr(),
            khr::deferred_host_operations::NAME.as_ptr(),
        ];
        if c.info.ray_query {
            ext_names.push(khr::ray_query::NAME.as_ptr());
        }
        if c.info.ray_tracing_pipeline {
            ext_names.push(khr::ray_tracing_pipeline::NAME.as_ptr());
        }
        if c.info.memory_budget {
            ext_names.push(ext::memory_budget::NAME.as_ptr());
        }
        let priorities = [1.0f32];
        let queue_infos = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(c.queue_family)
            .queue_priorities(&priorities)];
        let core = vk::PhysicalDeviceFeatures::default().shader_int64(true);
        let mut v12 = vk::PhysicalDeviceVulkan12Features::default()
            .buffer_device_address(true)
            .timeline_semaphore(true)
            .host_query_reset(true);
        let mut v13 = vk::PhysicalDeviceVulkan13Features::default()
            .synchronization2(true)
            .maintenance4(true);
        let mut asf = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default()
            .acceleration_structure(true);
        let mut rqf = vk::PhysicalDeviceRayQueryFeaturesKHR::default().ray_query(true);
        let mut rtf =
            vk::PhysicalDeviceRayTracingPipelineFeaturesKHR::default().ray_tracing_pipeline(true);
        let mut feats2 = vk::PhysicalDeviceFeatures2::default()
            .features(core)
            .push_next(&mut v12)
            .push_next(&mut v13)
            .push_next(&mut asf);
        if c.info.ray_query {
            feats2 = feats2.push_next(&mut rqf);
        }
        if c.info.ray_tracing_pipeline {
            feats2 = feats2.push_next(&mut rtf);
        }
        let device_info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queue_infos)
            .enabled_extension_names(&ext_names)
            .push_next(&mut feats2);
        failpoint(fail_at, "device")?;
        // SAFETY: the physical device belongs to `instance`; every chained struct lives through the call.
        let device =
            unsafe { instance.create_device(c.pd, &device_info, None) }.op("vkCreateDevice")?;
        handle_created();
        let device = scopeguard::guard(device, |d| {
            // SAFETY: nothing was submitted; its children have their own guards, dropped first.
            unsafe { d.destroy_device(None) };
            handle_destroyed();
        });
        // SAFETY: queue family and index 0 were requested above.
        let queue = unsafe { device.get_device_queue(c.queue_family, 0) };
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(c.queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        failpoint(fail_at, "command_pool")?;
        // SAFETY: device is valid.
        let command_pool =
            unsafe { device.create_command_pool(&pool_info, None) }.op("vkCreateCommandPool")?;
        handle_created();
        let command_pool = scopeguard::guard(command_pool, |p| {
            // SAFETY: no command buffer of it was ever allocated.
            unsafe { device.destroy_command_pool(p, None) };
            handle_destroyed();
        });
        failpoint(fail_at, "allocator")?;
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.clone(),
            device: (*device).clone(),
            physical_device: c.pd,
            debug_settings: Default::default(),
            buffer_device_address: true,
            allocation_sizes: Default::default(),
        })
        .map_err(|e| VulkanError::from_alloc("allocator creation", e))?;
        let accel = khr::acceleration_structure::Device::new(instance, &device);
        let rt_pipeline = c
            .info
            .ray_tracing_pipeline
            .then(|| khr::ray_tracing_pipeline::Device::new(instance, &device));
        let debug_device =
            has_debug_utils.then(|| ext::debug_utils::Device::new(instance, &device));
        let command_pool = scopeguard::ScopeGuard::into_inner(command_pool);
        Ok(DeviceParts {
            device: scopeguard::ScopeGuard::into_inner(device),
            queue,
            command_pool,
            allocator,
            accel,
            rt_pipeline,
            debug_device,
        })
    }
}
