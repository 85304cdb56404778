//! Streaming a baked world: hysteresis, event order, LOD streaming and the mesh budget.

mod common;

use std::collections::{HashMap, HashSet};

use glam::Vec3;
use rtstream_streaming::{LevelId, StreamConfig, StreamFocus, World, WorldEvent, WorldMeshId};

/// Checks per-level order and mesh residency as a consumer would see it.
#[derive(Default)]
struct Consumer {
    loaded: HashSet<LevelId>,
    loads: HashMap<LevelId, u32>,
    unloads: HashMap<LevelId, u32>,
    resident: HashSet<(WorldMeshId, u8)>,
    fine_loads: usize,
    fine_evictions: usize,
}

impl Consumer {
    fn eat(&mut self, events: Vec<WorldEvent>) {
        for e in events {
            match e {
                WorldEvent::LevelLoaded {
                    level, instances, ..
                } => {
                    assert!(
                        self.loaded.insert(level),
                        "{level:?} loaded twice without unload"
                    );
                    *self.loads.entry(level).or_default() += 1;
                    for i in instances.iter() {
                        assert!(
                            self.resident.iter().any(|(m, _)| *m == i.mesh),
                            "{level:?}: instance {:?} on mesh {:?} with no resident LOD",
                            i.id,
                            i.mesh
                        );
                    }
                }
                WorldEvent::LevelUnloaded { level, .. } => {
                    assert!(
                        self.loaded.remove(&level),
                        "{level:?} unloaded while not loaded"
                    );
                    *self.unloads.entry(level).or_default() += 1;
                }
                WorldEvent::MeshLodLoaded {
                    mesh,
                    lod,
                    lod_count,
                    geometry,
                    error,
                } => {
                    assert!(lod < lod_count);
                    assert_eq!(error, geometry.error);
                    assert!(
                        self.resident.insert((mesh, lod)),
                        "{mesh:?} LOD {lod} loaded twice"
                    );
                    self.fine_loads += usize::from(lod + 1 < lod_count);
                }
                WorldEvent::MeshLodEvicted { mesh, lod } => {
                    assert!(
                        self.resident.remove(&(mesh, lod)),
                        "{mesh:?} LOD {lod} evicted, not resident"
                    );
                    self.fine_evictions += 1;
                }
                WorldEvent::LoadFailed { error, .. } => panic!("unexpected failure: {error}"),
                WorldEvent::ProxyLoaded { .. } | WorldEvent::ProxyEvicted { .. } => {}
            }
        }
    }
}

#[test]
fn camera_path_streams_levels_with_hysteresis() {
    let (world, dir) = common::baked_small("path", 12);
    let config = StreamConfig::within(120.0, 200.0).with_mesh_budget(64 << 20);
    let mut w = World::open(&dir, config).expect("open");
    assert_eq!(w.level_count(), world.levels.len());
    let mut c = Consumer::default();
    let (lo, hi) = (world.extent.min, world.extent.max);

    // Fly diagonally across the whole map.
    let steps = 60;
    for f in 0..=steps {
        let t = f as f32 / steps as f32;
        let p = Vec3::new(lo.x + (hi.x - lo.x) * t, 2.0, lo.z + (hi.z - lo.z) * t);
        c.eat(common::settle(&mut w, f, &[StreamFocus::from(p)]));
        let st = w.stats();
        assert!(st.mesh_bytes <= config.mesh_budget_bytes, "{st:?}");
        // Everything within the load radius is in; nothing beyond the unload radius is.
        for (i, l) in world.levels.iter().enumerate() {
            let d = l.bounds.distance_xz(p);
            let loaded = w.is_loaded(LevelId(i as u32));
            if d <= config.load_radius {
                assert!(loaded, "frame {f}: level {i} at {d} m not loaded");
            }
            if d > config.unload_radius {
                assert!(!loaded, "frame {f}: level {i} at {d} m still loaded");
            }
        }
    }
    assert!(
        c.loads.len() > 20,
        "only {} levels loaded along the path",
        c.loads.len()
    );
    assert!(!c.unloads.is_empty(), "nothing unloaded along the path");
    assert!(c.fine_loads > 0, "no finer LOD streamed in");
    assert!(c.fine_evictions > 0, "nothing evicted");

    // Oscillate inside the hysteresis band: at most one load and one unload per level.
    let mut osc = Consumer {
        loaded: c.loaded.clone(),
        resident: c.resident.clone(),
        ..Consumer::default()
    };
    let mid = (lo + hi) * 0.5;
    let amp = (config.unload_radius - config.load_radius) * 0.45;
    for f in 0..80u64 {
        let x = if f % 2 == 0 { -amp } else { amp };
        let p = mid + Vec3::new(x, 0.0, 0.0);
        osc.eat(common::settle(&mut w, 1000 + f, &[StreamFocus::from(p)]));
    }
    for (level, n) in &osc.loads {
        assert!(*n <= 1, "{level:?} loaded {n} times while oscillating");
    }
    for (level, n) in &osc.unloads {
        assert!(*n <= 1, "{level:?} unloaded {n} times while oscillating");
    }
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn mesh_budget_is_respected_and_lods_follow_the_camera() {
    let (_world, dir) = common::baked_small("budget", 6);
    let big = StreamConfig::within(1000.0, 1500.0).with_mesh_budget(1 << 30);
    // Unlimited: everything near wants LOD0; measure what that takes.
    let mut w = World::open(&dir, big).expect("open");
    let cam = [StreamFocus::from(Vec3::ZERO)];
    let mut c = Consumer::default();
    c.eat(common::settle(&mut w, 0, &cam));
    c.eat(common::settle(&mut w, 1, &cam));
    let unlimited = w.stats().mesh_bytes;
    assert!(c.fine_loads > 0);
    drop(w);

    // Half of that: stays within budget, still streams some finer LODs.
    let tight = big.with_mesh_budget(unlimited / 2);
    let mut w = World::open(&dir, tight).expect("open");
    let mut c = Consumer::default();
    for f in 0..5 {
        c.eat(common::settle(&mut w, f, &cam));
        let st = w.stats();
        assert!(
            st.mesh_bytes + st.in_flight_bytes <= tight.mesh_budget_bytes,
            "{st:?}"
        );
    }
    assert!(c.fine_loads > 0);
    assert!(w.stats().mesh_bytes < unlimited);
    // Settled under pressure: a further frame with the same camera changes nothing (no thrash).
    let calm = common::settle(&mut w, 5, &cam);
    assert!(
        calm.is_empty(),
        "{} events after settling under budget pressure",
        calm.len()
    );

    // Move away (levels stay loaded): finer LODs are evicted, coarsest ones stay.
    let far = [StreamFocus::from(Vec3::new(1100.0, 0.0, 0.0))];
    let evicted_before = c.fine_evictions;
    let loaded_before = w.stats().loaded_levels;
    c.eat(common::settle(&mut w, 10, &far));
    assert!(
        c.fine_evictions > evicted_before,
        "no finer LOD evicted when the camera left"
    );
    assert_eq!(
        w.stats().loaded_levels,
        loaded_before,
        "levels should stay loaded"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The skinned instances of the loaded levels, by the events so far.
fn loaded_skinned(loaded: &mut std::collections::BTreeSet<u64>, events: &[WorldEvent]) -> Vec<u64> {
    for e in events {
        match e {
            WorldEvent::LevelLoaded { instances, .. } => loaded.extend(
                instances
                    .iter()
                    .filter(|i| i.motion == rtstream_streaming::Motion::Skinned)
                    .map(|i| u64::from(i.id.0)),
            ),
            WorldEvent::LevelUnloaded { instances, .. } => {
                for i in instances.iter() {
                    loaded.remove(&u64::from(i.id.0));
                }
            }
            _ => {}
        }
    }
    loaded.iter().copied().collect()
}

#[test]
fn skinned_instances_deform_each_frame() {
    let (world, dir) = common::baked_small("skin", 8);
    let mut w = World::open(&dir, StreamConfig::within(300.0, 350.0)).expect("open");
    let cam = [StreamFocus::from(Vec3::ZERO)];
    let mut loaded = std::collections::BTreeSet::new();
    let events = common::settle(&mut w, 0, &cam);
    let want = loaded_skinned(&mut loaded, &events);
    let a = w.skin_frame(0.0, 2);
    // Every loaded skinned instance, and only those (skin_frame keeps its own list of them).
    let ids = |f: &[rtstream_streaming::SkinnedFrame]| {
        let mut v: Vec<u64> = f.iter().map(|x| u64::from(x.instance.0)).collect();
        v.sort_unstable();
        v
    };
    assert_eq!(ids(&a), want);
    // Elsewhere on the map: levels unload and load; the list follows.
    let other = [StreamFocus::from(world.extent.max)];
    let events = common::settle(&mut w, 1000, &other);
    let want_there = loaded_skinned(&mut loaded, &events);
    assert_ne!(
        want_there, want,
        "the move changed which skinned instances are loaded"
    );
    assert_eq!(ids(&w.skin_frame(0.0, 2)), want_there);
    let events = common::settle(&mut w, 2000, &cam);
    assert_eq!(
        ids(&w.skin_frame(0.0, 2)),
        loaded_skinned(&mut loaded, &events)
    );
    let b = w.skin_frame(0.4, 2);
    assert!(!a.is_empty(), "no skinned instance loaded");
    assert_eq!(a.len(), b.len());
    let mut moved = 0;
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.instance, y.instance);
        assert_eq!(x.positions.len(), y.positions.len());
        let (geom_lod, geom) = w.resident_lod(x.mesh).expect("resident");
        assert_eq!(geom_lod as u8, x.lod);
        assert_eq!(x.positions.len(), geom.positions.len());
        assert!(x.positions.iter().flatten().all(|v| v.is_finite()));
        moved += usize::from(x.positions != y.positions);
    }
    assert!(moved > 0, "animation did not move any vertex");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn two_cameras_keep_two_areas_loaded() {
    let (world, dir) = common::baked_small("two-cams", 10);
    let config = StreamConfig::within(80.0, 150.0);
    let mut w = World::open(&dir, config).expect("open");
    let (lo, hi) = (world.extent.min, world.extent.max);
    let a = Vec3::new(lo.x + 60.0, 0.0, lo.z + 60.0);
    let b = Vec3::new(hi.x - 60.0, 0.0, hi.z - 60.0);
    let mut c = Consumer::default();
    c.eat(common::settle(
        &mut w,
        0,
        &[StreamFocus::from(a), StreamFocus::from(b)],
    ));
    let near = |p: Vec3| {
        world
            .levels
            .iter()
            .filter(|l| l.bounds.distance_xz(p) <= config.load_radius)
            .map(|l| l.id)
            .collect::<Vec<_>>()
    };
    for id in near(a).into_iter().chain(near(b)) {
        assert!(w.is_loaded(id), "{id:?} not loaded");
    }
    // Dropping camera b unloads its area only.
    c.eat(common::settle(&mut w, 1, &[StreamFocus::from(a)]));
    for id in near(b) {
        assert!(
            !w.is_loaded(id) || near(a).contains(&id),
            "{id:?} still loaded"
        );
    }
    for id in near(a) {
        assert!(w.is_loaded(id));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// What `a_lod_is_read_again_only_once_nobody_holds_it` holds: the resident LODs, and (in
/// `kept`) some the world evicted.
#[derive(Default)]
struct Holder {
    held: HashMap<(WorldMeshId, u8), std::sync::Arc<rtstream_streaming::MeshLod>>,
    kept: HashMap<(WorldMeshId, u8), std::sync::Arc<rtstream_streaming::MeshLod>>,
    arrivals: u64,
    shared_arrivals: u64,
}

impl Holder {
    fn eat(&mut self, events: Vec<WorldEvent>, keep_evicted: bool) {
        for e in events {
            match e {
                WorldEvent::MeshLodLoaded {
                    mesh,
                    lod,
                    geometry,
                    ..
                } => {
                    self.arrivals += 1;
                    if let Some(old) = self.kept.get(&(mesh, lod)) {
                        assert!(
                            std::sync::Arc::ptr_eq(old, &geometry),
                            "{mesh:?} LOD {lod} read again while held"
                        );
                        self.shared_arrivals += 1;
                    }
                    self.held.insert((mesh, lod), geometry);
                }
                WorldEvent::MeshLodEvicted { mesh, lod } => {
                    let g = self
                        .held
                        .remove(&(mesh, lod))
                        .expect("evicted a resident LOD");
                    if keep_evicted {
                        self.kept.insert((mesh, lod), g);
                    }
                }
                WorldEvent::LoadFailed { error, .. } => panic!("unexpected failure: {error}"),
                _ => {}
            }
        }
    }
}

/// The loaders read a LOD from the mesh library only when nobody holds the one read before: a
/// level's coarsest LODs, shared with the levels around it, arrive as the copy already held,
/// and a LOD that was let go everywhere is read again (the loaders keep nothing alive).
#[test]
fn a_lod_is_read_again_only_once_nobody_holds_it() {
    let (_world, dir) = common::baked_small("lod_reads", 6);
    let config = StreamConfig {
        loader_threads: 1,
        ..StreamConfig::within(1000.0, 1500.0).with_mesh_budget(1 << 30)
    };
    let mut w = World::open(&dir, config).expect("open");
    let mut h = Holder::default();
    let home = [StreamFocus::from(Vec3::ZERO)];
    for f in 0..3 {
        h.eat(common::settle(&mut w, f, &home), true);
    }
    let st = w.stats();
    assert!(st.lod_reads_shared > 0, "levels share meshes: {st:?}");
    assert!(
        st.lod_reads <= h.arrivals,
        "one loader: a LOD is read only when it arrives ({} reads, {} arrivals)",
        st.lod_reads,
        h.arrivals
    );

    // Away (levels stay loaded, finer LODs go; this test keeps them), then back: what comes
    // back is the copy kept, not a new read.
    let away = [StreamFocus::from(Vec3::new(1100.0, 0.0, 0.0))];
    for f in 3..6 {
        h.eat(common::settle(&mut w, f, &away), true);
    }
    assert!(!h.kept.is_empty(), "finer LODs evicted away from them");
    let (reads_away, arrivals_away) = (w.stats().lod_reads, h.arrivals);
    for f in 6..9 {
        h.eat(common::settle(&mut w, f, &home), true);
    }
    assert!(h.shared_arrivals > 0, "evicted LODs came back");
    let back = h.arrivals - arrivals_away;
    assert!(
        w.stats().lod_reads - reads_away <= back - h.shared_arrivals,
        "a kept LOD was read again"
    );

    // The levels unload far away (the far-field proxies' landmark LODs stay) and nobody holds
    // what the world evicted: coming back reads every LOD that arrives.
    h.kept.clear();
    let resident = h.held.len();
    let gone = [StreamFocus::from(Vec3::new(1.0e5, 0.0, 1.0e5))];
    for f in 9..12 {
        h.eat(common::settle(&mut w, f, &gone), false);
    }
    assert!(
        h.held.len() < resident / 2,
        "most LODs evicted: {} of {resident} still resident",
        h.held.len()
    );
    let (reads_gone, arrivals_gone) = (w.stats().lod_reads, h.arrivals);
    for f in 12..15 {
        h.eat(common::settle(&mut w, f, &home), false);
    }
    let again = h.arrivals - arrivals_gone;
    assert!(again > 0);
    assert_eq!(
        w.stats().lod_reads - reads_gone,
        again,
        "each LOD that nobody held is read once"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
