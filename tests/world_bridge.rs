//! Streaming → WorldBridge → AsManager on a small baked world with the model backend: levels
//! stream in and out along a camera path, the TLAS only references instances of loaded levels,
//! BLASes stay far below the naive policy's, and a corrupt level file is only a logged failure.

mod common;

use std::collections::HashSet;
use std::path::PathBuf;
use std::time::Duration;

use glam::Vec3;
use rtstream::as_manager::backend::model::ModelBackend;
use rtstream::as_manager::{AsManager, Config, PolicyKind, Viewpoint};
use rtstream::streaming::{StreamConfig, World};
use rtstream::WorldBridge;

fn baked_world(name: &str) -> (PathBuf, f32) {
    common::baked_small(&format!("bridge-{name}"), 6, 7)
}

fn stream_config() -> StreamConfig {
    StreamConfig {
        load_radius: 80.0,
        unload_radius: 110.0,
        loader_threads: 2,
        ..StreamConfig::default()
    }
}

/// Camera along the diagonal at eye height, looking ahead.
fn camera_at(size: f32, frame: u64, frames: u64) -> Vec3 {
    let t = frame as f32 / frames as f32;
    Vec3::new(size * (0.05 + 0.9 * t), 2.0, size * (0.05 + 0.9 * t))
}

struct RunResult {
    peak_blas: u32,
    tlas_seen: usize,
    levels_unloaded: usize,
    load_failures: usize,
}

fn run(dir: &PathBuf, size: f32, policy: PolicyKind, gpu_like: bool) -> RunResult {
    let mut world = World::open(dir, stream_config()).expect("open");
    let mut bridge = WorldBridge::new(world.manifest());
    let mut backend = ModelBackend::lavapipe();
    backend.require_geometry = gpu_like;
    let config = Config {
        policy,
        ..Config::default()
    };
    let mut m = AsManager::new(config, backend).expect("manager");
    let frames = 120u64;
    let (mut peak_blas, mut tlas_seen, mut unloaded) = (0, 0, 0);
    for frame in 0..frames {
        let pos = camera_at(size, frame, frames);
        // Let loads finish each frame so the test is deterministic in what it checks.
        let events = world
            .update_until_idle(frame, &[pos.into()], Duration::from_secs(10))
            .expect("streaming settles");
        unloaded += events
            .iter()
            .filter(|e| matches!(e, rtstream::streaming::WorldEvent::LevelUnloaded { .. }))
            .count();
        bridge.apply(&m, &events);
        bridge.pose_skinned(&m, &world, frame as f32 / 30.0, 1);
        let camera = Viewpoint::new(pos, Vec3::new(1.0, 0.0, 1.0).normalize());
        let out = common::update_from(&mut m, frame, camera).expect("update");
        let records = out.instances.to_vec();
        peak_blas = peak_blas.max(out.stats.blas_count);
        let mut seen = HashSet::new();
        for r in &records {
            assert!(m.backend().is_live_address(r.blas_address), "live BLAS");
            let ci = r.custom_index_and_mask & 0xff_ffff;
            let slot = bridge.slot(ci).expect("customIndex of a placed instance");
            assert!(
                world.is_loaded(slot.level),
                "TLAS instance of an unloaded level"
            );
            assert!(seen.insert(ci), "one record per instance");
        }
        tlas_seen = tlas_seen.max(records.len());
    }
    RunResult {
        peak_blas,
        tlas_seen,
        levels_unloaded: unloaded,
        load_failures: bridge.stats().load_failures,
    }
}

#[test]
fn streamed_world_feeds_the_manager_and_beats_naive() {
    let (dir, size) = baked_world("path");
    let managed = run(&dir, size, PolicyKind::Managed, true);
    assert!(managed.tlas_seen > 0, "something was traced");
    assert!(managed.levels_unloaded > 0, "the path unloads levels");
    let naive = run(&dir, size, PolicyKind::Naive, false);
    assert!(
        managed.peak_blas * 2 < naive.peak_blas,
        "managed {} BLAS vs naive {}",
        managed.peak_blas,
        naive.peak_blas
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn corrupt_level_is_a_logged_failure_not_a_panic() {
    let (dir, size) = baked_world("corrupt");
    // Corrupt every level file on the first half of the path.
    let manifest = rtstream::streaming::read_manifest(&dir).expect("manifest");
    let mut corrupted = 0;
    for l in &manifest.levels {
        if l.cell[0] == l.cell[1] && l.cell[0] < 3 {
            std::fs::write(dir.join(&l.file), b"not a level").unwrap();
            corrupted += 1;
        }
    }
    assert!(corrupted > 0);
    let r = run(&dir, size, PolicyKind::Managed, true);
    assert!(r.load_failures > 0, "LoadFailed reached the bridge");
    assert!(r.tlas_seen > 0, "the rest of the world carries on");
    let _ = std::fs::remove_dir_all(&dir);
}
