//! The device layer's `BufferArena` (lavapipe, validation on): ranges are disjoint, aligned and
//! addressable, hold what is written into them, reuse freed space, and give their blocks back.
//! Static BLAS inputs live in one; the backend tests build and free through it.

mod common;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{BufferArena, MemoryKind, ARENA_UNIT};

const BLOCK: u64 = 64 * 1024;

fn arena() -> BufferArena {
    BufferArena::new(
        "test arena",
        vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
        MemoryKind::Upload,
        BLOCK,
    )
}

#[test]
fn ranges_are_disjoint_hold_their_bytes_and_reuse_space() {
    let ctx = common::context();
    let before = ctx.live_buffers();
    let mut a = arena();
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
    for r in ranges {
        a.free(&ctx, r);
    }
    assert_eq!(ctx.live_buffers(), before + 1, "the last block stays");
    a.destroy(&ctx);
    assert_eq!(ctx.live_buffers(), before);
}

#[test]
fn blocks_come_and_go_with_their_ranges() {
    let ctx = common::context();
    let before = ctx.live_buffers();
    let mut a = arena();
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
    for r in quarters {
        a.free(&ctx, r);
    }
    assert_eq!(ctx.live_buffers(), before + 1);
    assert_eq!(a.allocated_bytes(), BLOCK);
    a.destroy(&ctx);
    assert_eq!(ctx.live_buffers(), before);
}
