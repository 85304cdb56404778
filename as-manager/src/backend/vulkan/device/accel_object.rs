//! Acceleration-structure objects: created in a buffer of their own or in a range of a
//! [`BufferArena`], and destroyed with it.

use ash::vk;

use crate::backend::vulkan::device::arena::{ArenaRange, BufferArena};
use crate::backend::vulkan::device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::{VkResult, VulkanError};

/// Usage of buffers that hold acceleration structures.
pub const ACCEL_STORAGE_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR.as_raw()
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw(),
);

/// Where an acceleration structure's storage lives.
#[derive(Debug)]
pub enum AccelStorage {
    /// A buffer of its own ([`VulkanContext::create_accel`]).
    Own(GpuBuffer),
    /// A range of a [`BufferArena`] ([`VulkanContext::create_accel_in`]): give it back with
    /// [`VulkanContext::destroy_accel_in`].
    Arena(ArenaRange),
}

/// An acceleration structure and its storage.
#[derive(Debug)]
pub struct AccelStruct {
    /// The `vk::AccelerationStructureKHR` handle.
    pub raw: vk::AccelerationStructureKHR,
    /// Its backing storage.
    pub storage: AccelStorage,
    /// Device address (what TLAS instance records reference).
    pub address: vk::DeviceAddress,
    /// Storage size in bytes.
    pub size: u64,
}

impl VulkanContext {
    /// Creates an acceleration structure of `size` bytes in its own buffer.
    pub fn create_accel(
        &self,
        ty: vk::AccelerationStructureTypeKHR,
        size: u64,
        name: &str,
    ) -> VkResult<AccelStruct> {
        let _s = tracing::trace_span!("create_accel").entered();
        let buffer = self.create_buffer(&BufferDesc {
            name,
            size,
            usage: ACCEL_STORAGE_USAGE,
            memory: MemoryKind::DeviceLocal,
        })?;
        match self.accel_at(ty, buffer.raw, 0, size, name) {
            Ok((raw, address)) => Ok(AccelStruct {
                raw,
                storage: AccelStorage::Own(buffer),
                address,
                size,
            }),
            Err(e) => {
                self.destroy_buffer(buffer);
                Err(e)
            }
        }
    }

    /// Creates an acceleration structure of `size` bytes in a range of `arena` (whose buffers
    /// have [`ACCEL_STORAGE_USAGE`]): no buffer or allocation of its own. Destroy it with
    /// [`VulkanContext::destroy_accel_in`] and the same arena.
    pub fn create_accel_in(
        &self,
        ty: vk::AccelerationStructureTypeKHR,
        arena: &mut BufferArena,
        size: u64,
        name: &str,
    ) -> VkResult<AccelStruct> {
        let _s = tracing::trace_span!("create_accel").entered();
        self.failpoint("create_accel_in")?;
        let range = arena.alloc(self, size)?;
        let (buffer, offset) = arena.placement(&range).expect("a range's block is live");
        match self.accel_at(ty, buffer, offset, size, name) {
            Ok((raw, address)) => Ok(AccelStruct {
                raw,
                storage: AccelStorage::Arena(range),
                address,
                size,
            }),
            Err(e) => {
                arena.free(self, range);
                Err(e)
            }
        }
    }

    /// An acceleration structure over `size` bytes of `buffer` from `offset`, named, and its
    /// device address.
    fn accel_at(
        &self,
        ty: vk::AccelerationStructureTypeKHR,
        buffer: vk::Buffer,
        offset: u64,
        size: u64,
        name: &str,
    ) -> VkResult<(vk::AccelerationStructureKHR, vk::DeviceAddress)> {
        let info = vk::AccelerationStructureCreateInfoKHR::default()
            .buffer(buffer)
            .offset(offset)
            .size(size)
            .ty(ty);
        // SAFETY: the buffer is bound, has AS-storage usage and holds `offset + size` bytes;
        // `offset` is a multiple of 256 (own buffers: 0; arena ranges: multiples of UNIT).
        let raw = unsafe { self.accel.create_acceleration_structure(&info, None) }
            .map_err(|e| VulkanError::from_vk("vkCreateAccelerationStructureKHR", e))?;
        self.set_name(raw, name);
        if ty == vk::AccelerationStructureTypeKHR::TOP_LEVEL {
            self.tlas_created(raw);
        }
        // SAFETY: raw is a valid acceleration structure of this device.
        let address = unsafe {
            self.accel.get_acceleration_structure_device_address(
                &vk::AccelerationStructureDeviceAddressInfoKHR::default()
                    .acceleration_structure(raw),
            )
        };
        Ok((raw, address))
    }

    /// Destroys an acceleration structure made by [`VulkanContext::create_accel`]. The caller
    /// guarantees the GPU no longer uses it. (One in an arena's range is destroyed too, but its
    /// range stays taken until the arena is: use [`VulkanContext::destroy_accel_in`].)
    pub fn destroy_accel(&self, accel: AccelStruct) {
        self.tlas_destroyed(accel.raw);
        // SAFETY: by contract no pending GPU work references it.
        unsafe { self.accel.destroy_acceleration_structure(accel.raw, None) };
        match accel.storage {
            AccelStorage::Own(b) => self.destroy_buffer(b),
            AccelStorage::Arena(_) => {
                debug_assert!(
                    false,
                    "an arena's acceleration structure destroyed without it"
                );
            }
        }
    }

    /// Destroys an acceleration structure, giving its range back to `arena` if it has one
    /// there. The caller guarantees the GPU no longer uses it.
    pub fn destroy_accel_in(&self, accel: AccelStruct, arena: &mut BufferArena) {
        self.tlas_destroyed(accel.raw);
        // SAFETY: by contract no pending GPU work references it.
        unsafe { self.accel.destroy_acceleration_structure(accel.raw, None) };
        match accel.storage {
            AccelStorage::Own(b) => self.destroy_buffer(b),
            AccelStorage::Arena(r) => arena.free(self, r),
        }
    }
}
