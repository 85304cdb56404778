//! The device layer's `BufferArena` (lavapipe, validation on): ranges are disjoint, aligned and
//! addressable, hold what is written into them, reuse freed space, and give their blocks back.
//! Static BLAS inputs and every BLAS's storage live in one each; the backend tests build and
//! free through them.

mod common;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{
    AccelStorage, ArenaRange, BufferArena, MemoryKind, VulkanContext, ACCEL_STORAGE_USAGE,
    ARENA_UNIT,
};

const BLOCK: u64 = 64 * 1024;

fn arena() -> BufferArena {
    BufferArena::new(
        "test arena",
        vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
        MemoryKind::Upload,
        BLOCK,
    )
}

/// A validated context, its live buffer count and an empty test arena.
fn fresh() -> (common::TestContext, i64, BufferArena) {
    let ctx = common::context();
    let before = ctx.live_buffers();
    (ctx, before, arena())
}

/// Frees `ranges`: one empty block of `BLOCK` bytes stays, and goes with the arena.
fn free_all(
    ctx: &VulkanContext,
    mut a: BufferArena,
    ranges: impl IntoIterator<Item = ArenaRange>,
    before: i64,
) {
    for r in ranges {
        a.free(ctx, r);
    }
    assert_eq!(ctx.live_buffers(), before + 1, "one empty block stays");
    assert_eq!(a.allocated_bytes(), BLOCK);
    a.destroy(ctx);
    assert_eq!(ctx.live_buffers(), before);
}

#[test]
fn ranges_are_disjoint_hold_their_bytes_and_reuse_space() {
    let (ctx, before, mut a) = fresh();
    let sizes = [1u64, 255, 256, 257, 1000, 4096, 12, 20_000];
    let mut ranges: Vec<_> = sizes.iter().map(|&s| a.alloc(&ctx, s).unwrap()).collect();
    assert_eq!(ctx.live_buffers(), before + 1, "all of them fit one block");
    for (k, r) in ranges.iter().enumerate() {
        assert_ne!(r.address, 0);
        assert_eq!(r.address % ARENA_UNIT, 0, "ranges start at a unit");
        a.bytes_mut(r).unwrap().fill(k as u8 + 1);
    }
    let mut spans: Vec<(u64, u64)> = ranges
        .iter()
        .map(|r| (r.address, r.address + r.size))
        .collect();
    spans.sort_unstable();
    assert!(
        spans.windows(2).all(|w| w[0].1 <= w[1].0),
        "disjoint: {spans:?}"
    );
    for (k, r) in ranges.iter().enumerate() {
        let b = a.bytes(r).unwrap();
        assert_eq!(b.len() as u64, r.size);
        assert!(
            b.iter().all(|&x| x == k as u8 + 1),
            "range {k} kept its bytes"
        );
    }
    // Freed space is used again: the same sizes again fit the same block.
    let held = a.allocated_bytes();
    let second = ranges.split_off(4);
    for r in second {
        a.free(&ctx, r);
    }
    for &s in &sizes[4..] {
        ranges.push(a.alloc(&ctx, s).unwrap());
    }
    assert_eq!(a.allocated_bytes(), held, "no new block for freed space");
    free_all(&ctx, a, ranges, before);
}

#[test]
fn blocks_come_and_go_with_their_ranges() {
    let (ctx, before, mut a) = fresh();
    // Quarter blocks: at least three blocks for twelve, each a buffer.
    let quarters: Vec<_> = (0..12).map(|_| a.alloc(&ctx, BLOCK / 4).unwrap()).collect();
    let blocks = a.allocated_bytes() / BLOCK;
    assert!(blocks >= 3, "{blocks} blocks for 12 quarter blocks");
    assert_eq!(ctx.live_buffers(), before + blocks as i64);
    // Larger than a block: a block of its own, gone with its range.
    let big = a.alloc(&ctx, 3 * BLOCK + 1).unwrap();
    assert_eq!(ctx.live_buffers(), before + blocks as i64 + 1);
    a.bytes_mut(&big).unwrap().fill(7);
    a.free(&ctx, big);
    assert_eq!(ctx.live_buffers(), before + blocks as i64);
    // Emptied blocks go while another remains.
    free_all(&ctx, a, quarters, before);
}

#[test]
fn an_emptied_block_waits_for_the_next_range() {
    let (ctx, before, mut a) = fresh();
    // Two blocks: the first full of quarters, the second with one quarter.
    let quarters: Vec<_> = (0..4).map(|_| a.alloc(&ctx, BLOCK / 4).unwrap()).collect();
    let mut last = a.alloc(&ctx, BLOCK / 2).unwrap();
    let blocks = ctx.live_buffers() - before;
    assert!(blocks >= 2, "{blocks} blocks");
    // The range of a block comes and goes, frame after frame: the block stays (no other block
    // is empty), and no buffer is made or destroyed.
    for _ in 0..8 {
        a.free(&ctx, last);
        assert_eq!(
            ctx.live_buffers() - before,
            blocks,
            "the emptied block stays"
        );
        last = a.alloc(&ctx, BLOCK / 2).unwrap();
        assert_eq!(
            ctx.live_buffers() - before,
            blocks,
            "and takes the next range"
        );
    }
    // With one block empty, a second emptied block goes.
    a.free(&ctx, last);
    free_all(&ctx, a, quarters, before);
}

/// A block's allocator has a node per four units (at least 64), not offset-allocator's
/// default 128 Ki (4 MB written in the frame that made the block). Ranges of one unit each run
/// a block out of nodes before out of space: the next ones go to another block, and all of them
/// stay disjoint and hold their bytes.
#[test]
fn a_block_out_of_nodes_sends_ranges_to_another() {
    let (ctx, before, mut a) = fresh();
    let units = BLOCK / ARENA_UNIT;
    let n = units as usize - 16;
    let ranges: Vec<_> = (0..n).map(|_| a.alloc(&ctx, 1).unwrap()).collect();
    let blocks = a.allocated_bytes() / BLOCK;
    assert!(
        blocks >= 2,
        "{n} one-unit ranges fit one block by space but not by nodes: {blocks} block(s)"
    );
    assert_eq!(ctx.live_buffers(), before + blocks as i64);
    let mut addresses: Vec<u64> = ranges.iter().map(|r| r.address).collect();
    addresses.sort_unstable();
    addresses.dedup();
    assert_eq!(addresses.len(), n, "distinct ranges");
    for (k, r) in ranges.iter().enumerate() {
        a.bytes_mut(r).unwrap()[0] = k as u8;
    }
    for (k, r) in ranges.iter().enumerate() {
        assert_eq!(a.bytes(r).unwrap()[0], k as u8, "range {k} kept its byte");
    }
    free_all(&ctx, a, ranges, before);
}

#[test]
fn acceleration_structures_share_an_arena_block() {
    let ctx = common::context();
    let before = ctx.live_buffers();
    let mut a = BufferArena::new(
        "test accels",
        ACCEL_STORAGE_USAGE,
        MemoryKind::DeviceLocal,
        BLOCK,
    );
    let ty = vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL;
    let sizes = [256u64, 1000, 4096, 300, 8192, 256];
    let accels: Vec<_> = sizes
        .iter()
        .map(|&s| ctx.create_accel_in(ty, &mut a, s, "test BLAS").unwrap())
        .collect();
    assert_eq!(ctx.live_buffers(), before + 1, "one block, no buffer each");
    let mut addresses: Vec<u64> = accels.iter().map(|x| x.address).collect();
    assert!(addresses.iter().all(|&x| x != 0));
    addresses.sort_unstable();
    addresses.dedup();
    assert_eq!(addresses.len(), sizes.len(), "distinct structures");
    for x in &accels {
        assert!(matches!(x.storage, AccelStorage::Arena(_)));
    }
    for x in accels {
        ctx.destroy_accel_in(x, &mut a);
    }
    assert_eq!(ctx.live_buffers(), before + 1, "the empty block stays");
    a.destroy(&ctx);
    assert_eq!(ctx.live_buffers(), before);
    common::assert_no_validation_messages(&ctx);
}
