//! Descriptor bindings of the renderer's pipelines: what a binding holds, what is bound for a
//! pass, and writing them into a descriptor set (shared by the compute and ray-tracing
//! pipelines and their recorder).

use ash::vk;

use crate::backend::vulkan::device::accel::AccelStruct;
use crate::backend::vulkan::device::buffer::GpuBuffer;
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::{VkResult, VulkanError};

/// What a descriptor binding holds (binding numbers are positions in the list, set 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BindingKind {
    /// An acceleration structure (TLAS).
    AccelStruct,
    /// A storage buffer.
    StorageBuffer,
}

/// A resource bound for one dispatch, in binding order.
#[derive(Debug, Clone, Copy)]
pub enum Bound<'a> {
    /// A TLAS.
    Accel(&'a AccelStruct),
    /// A raw TLAS handle (e.g. [`TlasRef::raw`](crate::backend::vulkan::TlasRef::raw) of the
    /// manager's current frame TLAS, checked by the caller).
    AccelRaw(vk::AccelerationStructureKHR),
    /// A whole buffer.
    Buffer(&'a GpuBuffer),
    /// The first `.1` bytes of a buffer (a shader's `length()` of a runtime array counts
    /// only those): a table written into a larger, reused buffer. At least 1 byte and within
    /// the buffer.
    BufferPrefix(&'a GpuBuffer, u64),
}

/// Writes `bound` into `set`, binding `i` = `bound[i]`, checked against the layout's `bindings`.
/// The caller guarantees no pending GPU work uses `set`.
pub(crate) fn write_descriptor_set(
    ctx: &VulkanContext,
    set: vk::DescriptorSet,
    bindings: &[BindingKind],
    bound: &[Bound<'_>],
) -> VkResult<()> {
    let handles: Vec<[vk::AccelerationStructureKHR; 1]> = bound
        .iter()
        .map(|b| match b {
            Bound::Accel(a) => [a.raw],
            Bound::AccelRaw(raw) => [*raw],
            Bound::Buffer(_) | Bound::BufferPrefix(..) => [vk::AccelerationStructureKHR::null()],
        })
        .collect();
    let buffer_infos: Vec<[vk::DescriptorBufferInfo; 1]> = bound
        .iter()
        .map(|b| match b {
            Bound::Buffer(buf) => [vk::DescriptorBufferInfo::default()
                .buffer(buf.raw)
                .offset(0)
                .range(vk::WHOLE_SIZE)],
            Bound::BufferPrefix(buf, bytes) => [vk::DescriptorBufferInfo::default()
                .buffer(buf.raw)
                .offset(0)
                .range(*bytes)],
            _ => [vk::DescriptorBufferInfo::default()],
        })
        .collect();
    let mut as_writes: Vec<vk::WriteDescriptorSetAccelerationStructureKHR<'_>> = handles
        .iter()
        .map(|h| {
            vk::WriteDescriptorSetAccelerationStructureKHR::default().acceleration_structures(h)
        })
        .collect();
    let mut writes = Vec::with_capacity(bound.len());
    for (i, ((b, kind), as_write)) in bound
        .iter()
        .zip(bindings)
        .zip(as_writes.iter_mut())
        .enumerate()
    {
        let w = vk::WriteDescriptorSet::default()
            .dst_set(set)
            .dst_binding(i as u32)
            .descriptor_type(descriptor_type(*kind));
        let w = match (b, kind) {
            (Bound::Accel(_) | Bound::AccelRaw(_), BindingKind::AccelStruct) => {
                w.descriptor_count(1).push_next(as_write)
            }
            (Bound::Buffer(_), BindingKind::StorageBuffer) => w.buffer_info(&buffer_infos[i]),
            (Bound::BufferPrefix(buf, bytes), BindingKind::StorageBuffer) => {
                if *bytes == 0 || *bytes > buf.size {
                    return Err(VulkanError::Unsupported(format!(
                        "binding {i}: {bytes} bytes of a {}-byte buffer",
                        buf.size
                    )));
                }
                w.buffer_info(&buffer_infos[i])
            }
            _ => {
                return Err(VulkanError::Unsupported(format!(
                    "binding {i}: {b:?} does not match {kind:?}"
                )))
            }
        };
        writes.push(w);
    }
    // SAFETY: the infos live through the call; by contract no pending work uses `set`.
    unsafe { ctx.device.update_descriptor_sets(&writes, &[]) };
    Ok(())
}

pub(crate) fn descriptor_type(k: BindingKind) -> vk::DescriptorType {
    match k {
        BindingKind::AccelStruct => vk::DescriptorType::ACCELERATION_STRUCTURE_KHR,
        BindingKind::StorageBuffer => vk::DescriptorType::STORAGE_BUFFER,
    }
}
