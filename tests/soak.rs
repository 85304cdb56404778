//! Soak: a small baked world streamed along random teleports (one every 30 frames, seeded,
//! cycling through ten places) into the manager on lavapipe, validation on, two frames in
//! flight, a tiny render every 10th frame. `SOAK_FRAMES` frames (1,600 in the suite; 10,000 by
//! hand, see docs/RELIABILITY.md). Required: no validation message; nothing Vulkan left alive
//! at shutdown (no buffer, no handle); resident memory, taken at the same place and frame
//! phase every 300 frames after the first tenth of the run, does not grow in every interval
//! (a leak does; a one-off step does not: a new allocator arena or a vector's new high-water
//! mark, which a busy machine's timing can move between probes) and grows at most 10 % in all.

mod common;

use std::sync::Arc;

use glam::Vec3;
use rtstream::as_manager::backend::vulkan::{
    live_vulkan_handles, VulkanBackend, VulkanBackendDesc,
};
use rtstream::as_manager::{AsManager, Config, Viewpoint};
use rtstream::renderer::{Camera, RenderDesc, Renderer};
use rtstream::streaming::World;
use rtstream::WorldBridge;

/// Resident set size of this process in KiB (Linux).
fn rss_kib() -> u64 {
    let s = std::fs::read_to_string("/proc/self/status").expect("procfs");
    s.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .expect("VmRSS")
}

#[test]
fn soak_teleports_and_streaming_leave_nothing_behind() {
    let frames: u64 = std::env::var("SOAK_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_600);
    assert!(frames >= 1_100, "SOAK_FRAMES >= 1100 (three memory probes)");
    let handles_before = live_vulkan_handles();
    let ctx = common::context();
    let (dir, size) = common::baked_small("soak", 8, 3);
    let stream = common::small_world_stream();
    let mut world = World::open(&dir, stream).expect("open");
    let mut bridge = WorldBridge::new(world.manifest());
    let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default()).unwrap();
    let mut config = Config::default();
    config.memory.blas_bytes = 24 << 20;
    let mut m = AsManager::new(config, backend).unwrap();
    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    // Ten places (seeded); the camera jumps every 30 frames and cycles every 300.
    let mut h = 0x5EEDu64;
    let mut unit = || {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        (h >> 11) as f32 / (1u64 << 53) as f32
    };
    let places: Vec<Vec3> = (0..10)
        .map(|_| {
            Vec3::new(
                size * (0.1 + 0.8 * unit()),
                3.0,
                size * (0.1 + 0.8 * unit()),
            )
        })
        .collect();
    // Memory at the same place and phase (frame % 300 == 100), from after a tenth of the run
    // and a whole cycle of places (allocators and caches have seen every place) on.
    let first = (frames / 10).max(300);
    let probe_early = 100 + 300 * (first - 100).div_ceil(300);
    let mut probes: Vec<(u64, u64)> = Vec::new();
    let mut renders = 0;
    for frame in 0..frames {
        let place = places[((frame / 30) % 10) as usize];
        let eye = place + Vec3::new((frame % 30) as f32 * 0.5, 0.0, 0.0);
        let events = world.update(frame, &[eye.into()]);
        bridge.apply(&m, &events);
        let out = common::update_from(&mut m, frame, Viewpoint::new(eye, Vec3::X)).expect("update");
        let s = out.stats.clone();
        assert!(
            s.blas_bytes + s.retiring_bytes <= s.memory_budget,
            "frame {frame}: over budget"
        );
        let (tlas, records) = (out.tlas, out.instances.to_vec());
        if frame % 10 == 9 {
            m.backend_mut().wait_idle().unwrap();
            let backend = m.backend();
            let table = bridge.shading(&records, |a| backend.shading_geometry(a));
            let traced = backend.tlas(tlas).expect("this frame's TLAS");
            let cam = Camera::look_at(eye, eye + Vec3::X * 10.0, 1.0);
            let desc = RenderDesc {
                primitive_bases: backend.primitive_bases(tlas),
                ..RenderDesc::new(32, 18, cam)
            };
            renderer.render(traced, &table, &desc).expect("render");
            renders += 1;
        }
        if frame >= probe_early && frame % 300 == 100 {
            probes.push((frame, rss_kib()));
        }
    }
    assert!(renders >= frames / 10);
    common::assert_no_validation_messages(&ctx);
    drop(renderer);
    drop(m);
    drop(world);
    assert_eq!(ctx.live_buffers(), 0, "every GPU buffer was destroyed");
    let ctx = Arc::try_unwrap(ctx.into_inner()).expect("the test holds the last context");
    drop(ctx);
    assert_eq!(
        live_vulkan_handles(),
        handles_before,
        "no Vulkan handle alive at shutdown"
    );
    let _ = std::fs::remove_dir_all(&dir);
    eprintln!("soak: {frames} frames, {renders} renders, RSS (frame, KiB) {probes:?}");
    assert!(probes.len() >= 3, "{probes:?}");
    let growth: Vec<f64> = probes
        .windows(2)
        .map(|w| w[1].1 as f64 / w[0].1.max(1) as f64 - 1.0)
        .collect();
    let least = growth.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(
        least <= 0.015,
        "resident memory grew in every interval of 300 frames at the same place (at least \
         {:.1} %): {probes:?}",
        least * 100.0
    );
    let (first_rss, last_rss) = (probes[0].1, probes[probes.len() - 1].1);
    assert!(
        last_rss as f64 <= first_rss as f64 * 1.10,
        "resident memory grew more than 10 % at the same place: {probes:?}"
    );
}
