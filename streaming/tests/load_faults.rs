//! Fault injection in the loader: a level whose read fails or whose decoder panics is reported
//! failed, retried with backoff, and the rest of the world streams as if nothing happened.
//! Deterministic streaming (`apply_after_frames`) makes every frame number exact under any load.

mod common;

use std::collections::BTreeMap;

use glam::Vec3;
use rtstream_streaming::{
    LevelId, LoadFault, StreamConfig, StreamFocus, StreamingError, World, WorldEvent,
};

#[test]
fn failed_loads_are_retried_with_backoff_and_the_rest_carries_on() {
    let (world, dir) = common::baked_small("load-faults", 3);
    let config = StreamConfig {
        apply_after_frames: Some(1),
        retry_after_frames: 8,
        max_load_attempts: 4,
        ..StreamConfig::within(1.0e4, 2.0e4)
    };
    let mut w = World::open(&dir, config).expect("open");
    let n = w.level_count();
    assert!(n >= 4, "{n} levels");
    let (reads, panics, hopeless) = (LevelId(0), LevelId(1), LevelId(2));
    w.inject_load_fault(reads, LoadFault::ReadError, 2);
    w.inject_load_fault(panics, LoadFault::Panic, 1);
    w.inject_load_fault(hopeless, LoadFault::ReadError, 100);

    let centre = (world.extent.min + world.extent.max) * 0.5;
    let cams = [StreamFocus::from(Vec3::new(centre.x, 2.0, centre.z))];
    let mut failed_at: BTreeMap<u32, Vec<u64>> = BTreeMap::new();
    let mut loaded_at: BTreeMap<u32, u64> = BTreeMap::new();
    for f in 0..200 {
        for e in w.update(f, &cams) {
            match e {
                WorldEvent::LoadFailed {
                    level: Some(l),
                    mesh: None,
                    error,
                    ..
                } => {
                    // The error names the level file; a panic is caught and typed.
                    let typed = if l == panics {
                        matches!(&*error, StreamingError::LoaderPanic { message, .. } if message.contains("injected"))
                    } else {
                        matches!(&*error, StreamingError::Io { path, .. } if path.to_string_lossy().contains("level"))
                    };
                    assert!(typed, "level {}: {error}", l.0);
                    failed_at.entry(l.0).or_default().push(f);
                }
                WorldEvent::LevelLoaded { level, .. } => {
                    assert!(
                        loaded_at.insert(level.0, f).is_none(),
                        "level {} loaded twice",
                        level.0
                    );
                }
                _ => {}
            }
        }
    }

    // Everything without a fault loaded on the first result frame.
    for l in 3..n as u32 {
        assert_eq!(loaded_at.get(&l), Some(&1), "level {l}: {loaded_at:?}");
        assert!(!failed_at.contains_key(&l));
    }
    // Two read failures: retried 8 then 16 frames after each failure, then loaded.
    let f0 = &failed_at[&reads.0];
    assert_eq!(f0.len(), 2, "{f0:?}");
    assert_eq!(
        f0[1],
        f0[0] + 8 + 1,
        "retry after 8 frames, result 1 frame later"
    );
    assert_eq!(loaded_at[&reads.0], f0[1] + 16 + 1);
    // One panic: retried once, loaded; the loader thread survived it.
    assert_eq!(failed_at[&panics.0].len(), 1);
    assert_eq!(loaded_at[&panics.0], failed_at[&panics.0][0] + 8 + 1);
    // Never loads: given up after max_load_attempts, reported failed.
    let f2 = &failed_at[&hopeless.0];
    assert_eq!(f2.len(), 4, "{f2:?}");
    assert!(!loaded_at.contains_key(&hopeless.0));
    let st = w.stats();
    assert_eq!(st.failed_levels, 1, "{st:?}");
    assert_eq!(st.load_retries, 2 + 1 + 3, "{st:?}");
    assert_eq!(st.loaded_levels, n - 1, "{st:?}");
    assert_eq!(st.loader_threads_alive, config.loader_threads, "{st:?}");

    // Leaving the unload radius forgets the failure; coming back tries afresh (and the fault
    // still there fails it again: four more attempts).
    let away = [StreamFocus::from(Vec3::new(1.0e6, 2.0, 1.0e6))];
    let mut f = 200;
    while w.stats().loaded_levels > 0 {
        w.update(f, &away);
        f += 1;
        assert!(f < 260, "{:?}", w.stats());
    }
    assert_eq!(w.stats().failed_levels, 0);
    let mut again = 0;
    for g in f..f + 200 {
        again += w
            .update(g, &cams)
            .iter()
            .filter(|e| matches!(e, WorldEvent::LoadFailed { level: Some(l), mesh: None, .. } if *l == hopeless))
            .count();
    }
    assert_eq!(again, 4);
    let _ = std::fs::remove_dir_all(&dir);
}
