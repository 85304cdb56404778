//! Small buffers of one kind, sub-allocated from large blocks.
//!
//! A static BLAS keeps its uploaded positions and indices for as long as it lives (shading reads
//! them), so a streaming world holds hundreds of them and frees and makes a few every frame.
//! As buffers of their own, each one cost a `vkCreateBuffer`, a bind and a gpu-allocator
//! allocation, whose free-list search grows with the holes those frees leave (half of
//! `build_blases` on lavapipe). Here they are ranges of a few large buffers, placed by
//! `offset-allocator` (a two-level segregated fit: constant time to allocate and free).
//!
//! Ranges start at multiples of [`UNIT`] bytes. A request larger than half a block gets a block
//! of its own, destroyed when its range is freed; an ordinary block is destroyed when it
//! empties, unless no other ordinary block is empty: one empty block stays, so that a working
//! set hovering at a block boundary does not allocate and free a block of device memory every
//! few frames (a `vkAllocateMemory` of a block is far slower than a range).

use offset_allocator::{Allocation, Allocator};

use ash::vk;

use crate::backend::vulkan::device::buffer::{BufferDesc, GpuBuffer, MemoryKind};
use crate::backend::vulkan::device::context::VulkanContext;
use crate::backend::vulkan::error::VkResult;

/// Bytes per allocation unit: every range starts at a multiple of it (vertex and index data
/// need 4, acceleration-structure storage 256).
pub const UNIT: u64 = 256;

/// Bounds of a block's allocator nodes (one per range and one per free hole between ranges).
const MIN_NODES: u32 = 64;
const MAX_NODES: u32 = 16 * 1024;

/// Nodes of the allocator of a block of `units`: one per four units (ranges averaging 2 KB fill
/// a block however fragmented), within [`MIN_NODES`, `MAX_NODES`]. `offset-allocator`'s own
/// default is 128 Ki nodes whatever the block, 4 MB of node arrays written when the block is
/// made: about 1.5 ms in the frame that needed the block (frames 16 and 60 of the default
/// fly-through on lavapipe were its slowest steady ones), and 4 MB of host memory a block. A
/// block whose nodes run out takes no more ranges (`allocate` answers `None`), and the next
/// range goes to another block.
fn nodes_for(units: u32) -> u32 {
    (units / 4).clamp(MIN_NODES, MAX_NODES)
}

/// Buffers of one usage and memory kind, sub-allocated from blocks of `block_bytes`.
pub struct BufferArena {
    name: &'static str,
    usage: vk::BufferUsageFlags,
    memory: MemoryKind,
    block_bytes: u64,
    blocks: Vec<Option<Block>>,
}

struct Block {
    buffer: GpuBuffer,
    /// `None`: a block of one range (a large request).
    ranges: Option<Allocator>,
    live: u32,
}

/// A range of a [`BufferArena`]'s block. Give it back with [`BufferArena::free`] once the GPU
/// no longer reads it.
pub struct ArenaRange {
    block: u32,
    allocation: Option<Allocation>,
    /// Byte offset in the block's buffer.
    offset: u64,
    /// Bytes asked for.
    pub size: u64,
    /// Device address of the range's first byte (0 without `SHADER_DEVICE_ADDRESS`).
    pub address: vk::DeviceAddress,
}

impl std::fmt::Debug for ArenaRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // By hand: offset-allocator's `Allocation` is not `Debug` (and says nothing the
        // offset does not).
        let (block, offset, size, address) = (self.block, self.offset, self.size, self.address);
        write!(f, "ArenaRange {{ block: {block}, offset: {offset}, size: {size}, address: {address:#x} }}")
    }
}

impl std::fmt::Debug for BufferArena {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BufferArena")
            .field("name", &self.name)
            .field("blocks", &self.blocks.iter().flatten().count())
            .field("block_bytes", &self.allocated_bytes())
            .finish()
    }
}

impl BufferArena {
    /// An empty arena; blocks are made on demand.
    pub fn new(
        name: &'static str,
        usage: vk::BufferUsageFlags,
        memory: MemoryKind,
        block_bytes: u64,
    ) -> Self {
        Self {
            name,
            usage,
            memory,
            block_bytes: block_bytes.next_multiple_of(UNIT).max(UNIT),
            blocks: Vec::new(),
        }
    }

    /// A range of at least `size` bytes: in the first block with room, else in a new block.
    pub fn alloc(&mut self, ctx: &VulkanContext, size: u64) -> VkResult<ArenaRange> {
        let units = size.div_ceil(UNIT).max(1);
        // The allocator rounds a request up to its size class (by less than 1/8): a request of
        // at most half a block always fits an empty block.
        let shared = units * UNIT <= self.block_bytes / 2;
        if shared {
            for (i, b) in self.blocks.iter_mut().enumerate() {
                let Some(b) = b else { continue };
                let Some(ranges) = b.ranges.as_mut() else {
                    continue;
                };
                if let Some(a) = ranges.allocate(units as u32) {
                    b.live += 1;
                    return Ok(range(i as u32, b, Some(a), size));
                }
            }
        }
        let bytes = if shared {
            self.block_bytes
        } else {
            units * UNIT
        };
        let buffer = ctx.create_buffer(&BufferDesc {
            name: self.name,
            size: bytes,
            usage: self.usage,
            memory: self.memory,
        })?;
        let (ranges, a) = if shared {
            let block_units = (bytes / UNIT) as u32;
            let mut ranges = Allocator::with_max_allocs(block_units, nodes_for(block_units));
            let a = ranges
                .allocate(units as u32)
                .expect("an empty block holds half its size");
            (Some(ranges), Some(a))
        } else {
            (None, None)
        };
        let block = Block {
            buffer,
            ranges,
            live: 1,
        };
        let i = match self.blocks.iter().position(Option::is_none) {
            Some(i) => i,
            None => {
                self.blocks.push(None);
                self.blocks.len() - 1
            }
        };
        let b = self.blocks[i].insert(block);
        Ok(range(i as u32, b, a, size))
    }

    /// Gives a range back; destroys its block once empty (an ordinary block only while
    /// another ordinary block is empty too).
    pub fn free(&mut self, ctx: &VulkanContext, r: ArenaRange) {
        let i = r.block as usize;
        let other_empty = self.blocks.iter().enumerate().any(|(j, b)| {
            j != i
                && b.as_ref()
                    .is_some_and(|b| b.live == 0 && b.ranges.is_some())
        });
        let b = self.blocks[i]
            .as_mut()
            .expect("a range's block lives until its last range is freed");
        if let (Some(ranges), Some(a)) = (b.ranges.as_mut(), r.allocation) {
            ranges.free(a);
        }
        b.live -= 1;
        if b.live == 0 && (b.ranges.is_none() || other_empty) {
            let b = self.blocks[i].take().expect("checked above");
            ctx.destroy_buffer(b.buffer);
        }
    }

    /// The bytes of a range of a host-visible arena.
    pub fn bytes(&self, r: &ArenaRange) -> Option<&[u8]> {
        let b = self.blocks.get(r.block as usize)?.as_ref()?;
        let at = r.offset as usize;
        b.buffer.mapped().map(|m| &m[at..at + r.size as usize])
    }

    /// The bytes of a range of a host-visible arena, writable.
    pub fn bytes_mut(&mut self, r: &ArenaRange) -> Option<&mut [u8]> {
        let b = self.blocks.get_mut(r.block as usize)?.as_mut()?;
        let at = r.offset as usize;
        b.buffer
            .mapped_mut()
            .map(|m| &mut m[at..at + r.size as usize])
    }

    /// The buffer holding a range and the range's byte offset in it (where an acceleration
    /// structure is created in the range).
    pub fn placement(&self, r: &ArenaRange) -> Option<(vk::Buffer, u64)> {
        let b = self.blocks.get(r.block as usize)?.as_ref()?;
        Some((b.buffer.raw, r.offset))
    }

    /// Bytes of the blocks (what the arena holds on the device, free space included).
    pub fn allocated_bytes(&self) -> u64 {
        self.blocks.iter().flatten().map(|b| b.buffer.size).sum()
    }

    /// Destroys every block. The caller guarantees the GPU reads none of them any more and
    /// that no range is used after this.
    pub fn destroy(&mut self, ctx: &VulkanContext) {
        for b in self.blocks.drain(..).flatten() {
            ctx.destroy_buffer(b.buffer);
        }
    }
}

fn range(block: u32, b: &Block, allocation: Option<Allocation>, size: u64) -> ArenaRange {
    let offset = allocation.map_or(0, |a| u64::from(a.offset) * UNIT);
    let address = if b.buffer.address == 0 {
        0
    } else {
        b.buffer.address + offset
    };
    ArenaRange {
        block,
        allocation,
        offset,
        size,
        address,
    }
}
