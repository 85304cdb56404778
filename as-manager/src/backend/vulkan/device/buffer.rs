//! Device buffers, sub-allocated from device memory by gpu-allocator.

use std::sync::atomic::Ordering;

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

/// Where a buffer's memory lives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MemoryKind {
    /// Device-local, not mapped (AS storage, scratch).
    DeviceLocal,
    /// Host-visible, written by the CPU, read by the GPU (build inputs, instance records).
    Upload,
    /// Host-visible, written by the GPU, read by the CPU (images, hit buffers, query results).
    Readback,
}

/// Creation parameters of a [`GpuBuffer`].
#[derive(Debug, Clone, Copy)]
pub struct BufferDesc<'a> {
    /// Debug name.
    pub name: &'a str,
    /// Size in bytes (> 0).
    pub size: u64,
    /// Vulkan usage; `SHADER_DEVICE_ADDRESS` is what gives the buffer a device address.
    pub usage: vk::BufferUsageFlags,
    /// Memory location.
    pub memory: MemoryKind,
}

/// A buffer and its memory. Destroy it with [`VulkanContext::destroy_buffer`] (by value) once
/// the GPU no longer uses it; the context reports buffers left alive when it is dropped.
#[derive(Debug)]
pub struct GpuBuffer {
    /// The `vk::Buffer` handle.
    pub raw: vk::Buffer,
    allocation: Allocation,
    /// Size requested at creation.
    pub size: u64,
    /// Device address, or 0 when the buffer was created without `SHADER_DEVICE_ADDRESS`.
    pub address: vk::DeviceAddress,
}

impl GpuBuffer {
    /// The mapped bytes of a host-visible buffer.
    pub fn mapped(&self) -> Option<&[u8]> {
        self.allocation
            .mapped_slice()
            .map(|s| &s[..self.size as usize])
    }

    /// The mapped bytes of a host-visible buffer, writable.
    pub fn mapped_mut(&mut self) -> Option<&mut [u8]> {
        let size = self.size as usize;
        self.allocation.mapped_slice_mut().map(|s| &mut s[..size])
    }

    /// Copies `bytes` into a host-visible buffer at `offset`.
    ///
    /// # Panics
    /// If the buffer is not host-visible or the range does not fit (a broken contract).
    pub fn write(&mut self, offset: usize, bytes: &[u8]) {
        let dst = self
            .mapped_mut()
            .expect("GpuBuffer::write on a buffer that is not host-visible");
        dst[offset..offset + bytes.len()].copy_from_slice(bytes);
    }
}

impl VulkanContext {
    /// Creates a buffer with its memory.
    pub fn create_buffer(&self, desc: &BufferDesc<'_>) -> VkResult<GpuBuffer> {
        if desc.size == 0 {
            return Err(VulkanError::Unsupported(format!(
                "buffer {:?} of size 0",
                desc.name
            )));
        }
        let _s = tracing::trace_span!("create_buffer").entered();
        let info = vk::BufferCreateInfo::default()
            .size(desc.size)
            .usage(desc.usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: device is valid; info is well-formed.
        let raw = unsafe { self.device.create_buffer(&info, None) }.op("vkCreateBuffer")?;
        // SAFETY: raw was just created on this device.
        let requirements = unsafe { self.device.get_buffer_memory_requirements(raw) };
        let location = match desc.memory {
            MemoryKind::DeviceLocal => MemoryLocation::GpuOnly,
            MemoryKind::Upload => MemoryLocation::CpuToGpu,
            MemoryKind::Readback => MemoryLocation::GpuToCpu,
        };
        let allocation = tracing::trace_span!("allocate").in_scope(|| {
            self.allocator.lock().allocate(&AllocationCreateDesc {
                name: desc.name,
                requirements,
                location,
                linear: true,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            })
        });
        let allocation = match allocation {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: raw is unused and unbound.
                unsafe { self.device.destroy_buffer(raw, None) };
                return Err(VulkanError::from_alloc("buffer allocation", e));
            }
        };
        // SAFETY: memory and offset come from an allocation made for these requirements.
        let bound = unsafe {
            self.device
                .bind_buffer_memory(raw, allocation.memory(), allocation.offset())
        }
        .op("vkBindBufferMemory");
        if let Err(e) = bound {
            // SAFETY: the buffer failed to bind and is unused.
            unsafe { self.device.destroy_buffer(raw, None) };
            let _ = self.allocator.lock().free(allocation);
            return Err(e);
        }
        let address = if desc
            .usage
            .contains(vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS)
        {
            // SAFETY: the buffer is bound and was created with SHADER_DEVICE_ADDRESS.
            unsafe {
                self.device
                    .get_buffer_device_address(&vk::BufferDeviceAddressInfo::default().buffer(raw))
            }
        } else {
            0
        };
        self.set_name(raw, desc.name);
        self.live_buffers.fetch_add(1, Ordering::Relaxed);
        Ok(GpuBuffer {
            raw,
            allocation,
            size: desc.size,
            address,
        })
    }

    /// Creates a host-visible buffer holding `bytes`.
    pub fn create_buffer_with_data(
        &self,
        name: &str,
        usage: vk::BufferUsageFlags,
        bytes: &[u8],
    ) -> VkResult<GpuBuffer> {
        let mut buf = self.create_buffer(&BufferDesc {
            name,
            size: bytes.len().max(4) as u64,
            usage,
            memory: MemoryKind::Upload,
        })?;
        buf.write(0, bytes);
        Ok(buf)
    }

    /// Destroys a buffer. The caller guarantees the GPU no longer uses it.
    pub fn destroy_buffer(&self, buffer: GpuBuffer) {
        // SAFETY: by contract no pending GPU work references the buffer.
        unsafe { self.device.destroy_buffer(buffer.raw, None) };
        if let Err(e) = self.allocator.lock().free(buffer.allocation) {
            tracing::error!("freeing buffer memory failed: {e}");
        }
        self.live_buffers.fetch_sub(1, Ordering::Relaxed);
    }
}
