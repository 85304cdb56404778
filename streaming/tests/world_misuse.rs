//! Adversarial tests of the streaming world's public API: what an engine programmer might get
//! wrong with `World`, `StreamConfig`, `StreamFocus`, glTF levels and baked directories.
//!
//! Each probe passes on a correct result or a clean typed error, and fails on a defect: a panic
//! inside the library (turned into a reported failure through `catch_unwind`), NaN in what the
//! world hands out, a level that can never load again after a transient failure, state that
//! grows with every cycle, or streaming that never settles. Streaming runs deterministically
//! (`StreamConfig::apply_after_frames`) or through `update_until_idle` with a generous limit;
//! no assertion reads a clock, so a hang shows as a test that never ends. Worlds are small
//! (3 x 3 levels, generated once per test binary) so that a correct run takes well under a
//! second per probe.
//!
//! Written by a helper agent against the code as it was (fourteenth session): 27 passed and
//! 11 exposed library defects. Fixed since: a NaN focus loaded the whole world (non-finite
//! foci are left out); `update_until_idle(.., Duration::MAX)` panicked; a load failure near
//! frame `u64::MAX` overflowed the retry frame; deterministic streaming stalled after the frame
//! number went back (pending requests and retries now count as made at the new number);
//! `skin_frame` at a NaN or infinite time returned NaN positions; a glTF level scaled by 1e38
//! handed out NaN bounds (`InvalidScene` now); an eviction factor of 1 or below (or NaN)
//! churned finer LODs every frame (`StreamConfig::validate` refuses it); `WorldPreset::crowd`
//! and `small` overflowed on absurd sizes; a world with no instances or no levels baked files
//! its own readers rejected (empty bounds now read back); every reload of a glTF level took new
//! mesh slots (a glTF level now keeps the mesh ids of its first load, checked also for a file
//! that changes its mesh count between loads). `max_in_flight` capping only finer-LOD loads is
//! now what its documentation says (capping level loads would change what streams when).

mod common;

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Duration;

use glam::{Mat4, Quat, Vec3};
use rtstream_streaming::{
    bake, generate, GeneratedWorld, Instance, LevelId, MeshLod, ProxyId, SettleTimeout,
    StreamConfig, StreamFocus, StreamingError, World, WorldEvent, WorldInstanceId, WorldMeshId,
    WorldPreset,
};

// ---------------------------------------------------------------------------------------------
// Fixtures

/// The 3 x 3 level world every probe streams (generated once per test binary).
fn generated() -> &'static GeneratedWorld {
    static WORLD: OnceLock<GeneratedWorld> = OnceLock::new();
    WORLD.get_or_init(|| {
        common::assets();
        generate(&WorldPreset::small(3, 7)).expect("generate")
    })
}

/// A scratch directory removed when dropped (also when the test fails).
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

/// The small world baked into a fresh directory of this probe's own.
fn baked(name: &str) -> (&'static GeneratedWorld, Scratch) {
    let g = generated();
    let dir = Scratch(common::scratch(&format!("misuse-{name}")));
    bake(g, &*dir).expect("bake");
    (g, dir)
}

fn gltf(rel: &str) -> PathBuf {
    common::assets().join(rel)
}

const BOX: &str = "BoxTextured-glTF-Binary/BoxTextured.glb";
const ENGINE: &str = "2CylinderEngine-glTF-Binary/2CylinderEngine.glb";
const SKIN: &str = "simple_skin/simple_skin.gltf";

/// Deterministic streaming: every result one frame after its request.
fn det(c: StreamConfig) -> StreamConfig {
    StreamConfig {
        apply_after_frames: Some(1),
        ..c
    }
}

fn focus(x: f32, z: f32) -> StreamFocus {
    StreamFocus::from(Vec3::new(x, 2.0, z))
}

/// The map's centre (the world is centred on the origin).
fn centre(g: &GeneratedWorld) -> StreamFocus {
    let c = g.extent.center();
    focus(c.x, c.z)
}

/// The levels whose ground rectangle is within `r` of any of `cams`.
fn within(g: &GeneratedWorld, cams: &[StreamFocus], r: f32) -> BTreeSet<LevelId> {
    g.levels
        .iter()
        .filter(|l| cams.iter().any(|c| l.bounds.distance_xz(c.position) <= r))
        .map(|l| l.id)
        .collect()
}

/// Runs `f`, turning a panic inside the library into a test failure that says where.
fn no_panic<T>(what: &str, f: impl FnOnce() -> T) -> T {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(v) => v,
        Err(p) => {
            let msg = p
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "non-string panic payload".into());
            panic!("DEFECT: the library panicked in {what}: {msg}");
        }
    }
}

/// Runs `f`; a panic becomes its message.
fn panic_message<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    catch_unwind(AssertUnwindSafe(f)).map_err(|p| {
        p.downcast_ref::<&str>()
            .map(|s| (*s).to_owned())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "non-string panic payload".into())
    })
}

fn open(dir: &Path, config: StreamConfig) -> World {
    no_panic("World::open", || World::open(dir, config)).expect("open a freshly baked world")
}

fn update(w: &mut World, frame: u64, cams: &[StreamFocus]) -> Vec<WorldEvent> {
    no_panic(&format!("World::update(frame {frame})"), || {
        w.update(frame, cams)
    })
}

fn settle(w: &mut World, frame: u64, cams: &[StreamFocus]) -> Vec<WorldEvent> {
    no_panic(&format!("World::update_until_idle(frame {frame})"), || {
        w.update_until_idle(frame, cams, common::SETTLE)
    })
    .expect("streaming settles")
}

// ---------------------------------------------------------------------------------------------
// What a consumer sees

fn finite_instance(i: &Instance) -> bool {
    i.transform.is_finite()
        && i.aabb.min.is_finite()
        && i.aabb.max.is_finite()
        && i.sphere.center.is_finite()
        && i.sphere.radius.is_finite()
}

fn finite_geometry(g: &MeshLod) -> bool {
    g.error.is_finite() && g.positions.iter().flatten().all(|v| v.is_finite())
}

/// Follows the event stream as a consumer (a BLAS manager) would, and checks it: per-level
/// order, LOD residency, proxies, and that nothing handed out holds NaN or infinity.
#[derive(Default)]
struct Tracker {
    loaded: BTreeMap<LevelId, usize>,
    resident: HashSet<(WorldMeshId, u8)>,
    proxies: HashSet<ProxyId>,
    level_loads: BTreeMap<LevelId, usize>,
    fine_loads: usize,
    failures: Vec<common::Failure>,
    events: usize,
}

impl Tracker {
    fn eat(&mut self, events: &[WorldEvent]) -> usize {
        self.events += events.len();
        for e in events {
            match e {
                WorldEvent::LevelLoaded {
                    level,
                    bounds,
                    instances,
                } => {
                    assert!(
                        self.loaded.insert(*level, instances.len()).is_none(),
                        "{level:?} loaded twice without an unload"
                    );
                    *self.level_loads.entry(*level).or_default() += 1;
                    assert!(
                        !bounds.min.is_nan() && !bounds.max.is_nan(),
                        "{level:?}: NaN level bounds {bounds:?}"
                    );
                    for i in instances.iter() {
                        assert!(
                            finite_instance(i),
                            "{level:?}: instance {:?} is not finite: {i:?}",
                            i.id
                        );
                        assert!(
                            self.resident.iter().any(|(m, _)| *m == i.mesh),
                            "{level:?}: instance {:?} on mesh {:?} with no resident LOD",
                            i.id,
                            i.mesh
                        );
                    }
                }
                WorldEvent::LevelUnloaded { level, instances } => {
                    let n = self.loaded.remove(level);
                    assert_eq!(
                        n,
                        Some(instances.len()),
                        "{level:?} unloaded while not loaded (or with other instances)"
                    );
                }
                WorldEvent::MeshLodLoaded {
                    mesh,
                    lod,
                    lod_count,
                    error,
                    geometry,
                } => {
                    assert!(lod < lod_count, "{mesh:?}: LOD {lod} of {lod_count}");
                    assert_eq!(*error, geometry.error);
                    assert!(finite_geometry(geometry), "{mesh:?} LOD {lod}: not finite");
                    assert!(
                        self.resident.insert((*mesh, *lod)),
                        "{mesh:?} LOD {lod} loaded twice"
                    );
                    self.fine_loads += usize::from(lod + 1 < *lod_count);
                }
                WorldEvent::MeshLodEvicted { mesh, lod } => {
                    assert!(
                        self.resident.remove(&(*mesh, *lod)),
                        "{mesh:?} LOD {lod} evicted while not resident"
                    );
                }
                WorldEvent::ProxyLoaded {
                    node,
                    geometry,
                    landmarks,
                } => {
                    assert!(self.proxies.insert(*node), "{node:?} loaded twice");
                    assert!(finite_geometry(geometry), "{node:?}: proxy not finite");
                    assert!(landmarks.iter().all(|(_, i)| finite_instance(i)));
                }
                WorldEvent::ProxyEvicted { node } => {
                    assert!(self.proxies.remove(node), "{node:?} evicted, not resident");
                }
                WorldEvent::LoadFailed { .. } => {}
            }
        }
        self.failures.extend(common::failures(events));
        events.len()
    }

    /// The world's own answers agree with the event stream.
    fn agrees(&self, w: &World) {
        let st = w.stats();
        for l in 0..w.level_count() as u32 {
            assert_eq!(
                w.is_loaded(LevelId(l)),
                self.loaded.contains_key(&LevelId(l)),
                "level {l}: is_loaded disagrees with the events"
            );
        }
        assert_eq!(st.loaded_levels, self.loaded.len(), "{st:?}");
        assert_eq!(
            st.loaded_instances,
            self.loaded.values().sum::<usize>(),
            "{st:?}"
        );
        assert_eq!(st.resident_lods, self.resident.len(), "{st:?}");
        assert!(
            st.loaded_levels + st.loading_levels + st.failed_levels <= w.level_count(),
            "{st:?}"
        );
        assert!(st.loader_threads_alive >= 1, "{st:?}");
    }

    fn loaded_set(&self) -> BTreeSet<LevelId> {
        self.loaded.keys().copied().collect()
    }
}

/// Every level within the load radius of `cams` is loaded, none beyond the unload radius.
fn assert_band(
    t: &Tracker,
    g: &GeneratedWorld,
    cams: &[StreamFocus],
    config: StreamConfig,
    what: &str,
) {
    let loaded = t.loaded_set();
    let must = within(g, cams, config.load_radius);
    let may = within(g, cams, config.unload_radius.max(config.load_radius));
    assert!(
        must.is_subset(&loaded),
        "{what}: not loaded: {:?}",
        must.difference(&loaded).collect::<Vec<_>>()
    );
    assert!(
        loaded.is_subset(&may),
        "{what}: still loaded: {:?}",
        loaded.difference(&may).collect::<Vec<_>>()
    );
}

/// Runs deterministic frames `frames` with `cams`, feeding `t`; returns the events of the run.
fn run(
    w: &mut World,
    t: &mut Tracker,
    frames: std::ops::Range<u64>,
    cams: &[StreamFocus],
) -> usize {
    let mut n = 0;
    for f in frames {
        n += t.eat(&update(w, f, cams));
    }
    t.agrees(w);
    n
}

// ---------------------------------------------------------------------------------------------
// World::open on what is not a baked world

#[test]
fn open_refuses_what_is_not_a_baked_world() {
    let dir = Scratch(common::scratch("misuse-open"));
    let file = dir.join("a-file");
    std::fs::write(&file, b"not a directory").unwrap();
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let garbage = dir.join("garbage");
    std::fs::create_dir_all(&garbage).unwrap();
    std::fs::write(garbage.join("world.rtw"), b"JUNKJUNKJUNKJUNKJUNK").unwrap();
    let zero = dir.join("zero");
    std::fs::create_dir_all(&zero).unwrap();
    std::fs::write(zero.join("world.rtw"), b"").unwrap();
    let nested = dir.join("manifest-is-a-dir");
    std::fs::create_dir_all(nested.join("world.rtw")).unwrap();
    let cases: Vec<PathBuf> = vec![
        dir.join("missing"),
        empty,
        file,
        garbage,
        zero,
        nested,
        PathBuf::from(""),
        PathBuf::from("/dev/null"),
        PathBuf::from("/proc/self"),
    ];
    for p in cases {
        let r = no_panic(&format!("World::open({})", p.display()), || {
            World::open(&p, StreamConfig::default())
        });
        match r {
            Ok(_) => panic!("{} opened as a world", p.display()),
            Err(e) => {
                assert!(
                    matches!(e, StreamingError::Io { .. } | StreamingError::Format { .. }),
                    "{}: {e:?}",
                    p.display()
                );
                assert!(
                    e.to_string().contains("world.rtw"),
                    "{}: the error names no file: {e}",
                    p.display()
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// StreamConfig nonsense

/// Zero, negative, NaN, infinite and huge radii, and an unload radius below the load radius:
/// no panic, a consistent event stream, and a world that settles (no endless churn). Where the
/// load radius is a number, exactly the levels within it load (the unload radius is documented
/// as greater than the load radius; below it the world uses the load radius).
#[test]
fn nonsense_radii_neither_panic_nor_churn() {
    let (g, dir) = baked("radii");
    let nan = f32::NAN;
    let inf = f32::INFINITY;
    let radii = [
        (0.0, 0.0),
        (-5.0, -5.0),
        (nan, nan),
        (nan, 100.0),
        (60.0, nan),
        (inf, inf),
        (1e30, 1e30),
        (f32::MAX, f32::MAX),
        (60.0, 10.0),
        (60.0, -inf),
        (-inf, inf),
        (60.0, 0.0),
    ];
    let cams = [centre(g)];
    for (load, unload) in radii {
        for far in [f32::INFINITY, 0.0, -1.0, f32::NAN] {
            let config = StreamConfig {
                far_radius: far,
                ..det(StreamConfig::within(load, unload))
            };
            let mut w = open(&dir, config);
            let mut t = Tracker::default();
            run(&mut w, &mut t, 0..12, &cams);
            let calm = run(&mut w, &mut t, 12..16, &cams);
            assert_eq!(
                calm, 0,
                "load {load} unload {unload} far {far}: no settling"
            );
            if !load.is_nan() {
                assert_eq!(
                    t.loaded_set(),
                    within(g, &cams, load),
                    "load {load} unload {unload}"
                );
            }
            assert!(t.failures.is_empty(), "{:?}", t.failures);
        }
    }
}

/// A camera pacing across the map with an unload radius set below the load radius (documented
/// as greater): the world treats it as no hysteresis band; after each stop exactly the levels
/// within the load radius are loaded, a repeated frame number changes nothing, and nothing
/// panics.
#[test]
fn unload_radius_below_load_radius_streams_like_no_band() {
    let (g, dir) = baked("inverted-band");
    let config = det(StreamConfig::within(60.0, 5.0));
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    let c = centre(g).position;
    for stop in 0..40u64 {
        let x = c.x + (stop as f32 * 37.0) % 140.0 - 70.0;
        let cams = [focus(x, c.z)];
        let f = 3 * stop;
        // Results arrive one frame after their request.
        run(&mut w, &mut t, f..f + 2, &cams);
        assert_eq!(
            t.loaded_set(),
            within(g, &cams, 60.0),
            "stop {stop} at x = {x}"
        );
        assert_eq!(
            t.eat(&update(&mut w, f + 1, &cams)),
            0,
            "stop {stop}: repeated frame"
        );
        t.agrees(&w);
    }
}

/// Zero loader threads (the pool keeps one) and many of them: everything still loads.
#[test]
fn zero_or_many_loader_threads_still_stream() {
    let (g, dir) = baked("threads");
    let cams = [centre(g)];
    for threads in [0usize, 1, 64] {
        let config = StreamConfig {
            loader_threads: threads,
            ..StreamConfig::within(1e4, 2e4)
        };
        let r = no_panic("World::open", || World::open(&*dir, config));
        let Ok(mut w) = r else {
            // A typed refusal of a thread count is fine.
            continue;
        };
        let mut t = Tracker::default();
        t.eat(&settle(&mut w, 0, &cams));
        t.eat(&settle(&mut w, 1, &cams));
        t.agrees(&w);
        assert_eq!(t.loaded.len(), g.levels.len(), "{threads} threads");
        assert!(w.stats().loader_threads_alive >= threads.clamp(1, 64));
    }
}

/// No loads in flight allowed, no mesh budget, a budget of usize::MAX: the levels (and their
/// coarsest LODs, which are never refused) still load and the world settles.
#[test]
fn zero_in_flight_and_extreme_budgets_settle() {
    let (g, dir) = baked("budgets");
    let cams = [centre(g)];
    for (in_flight, budget) in [
        (0usize, 256usize << 20),
        (1, 0),
        (0, 0),
        (usize::MAX, usize::MAX),
        (64, usize::MAX),
        (64, 1),
    ] {
        let config = StreamConfig {
            max_in_flight: in_flight,
            mesh_budget_bytes: budget,
            ..det(StreamConfig::within(1e4, 2e4))
        };
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..20, &cams);
        assert_eq!(
            run(&mut w, &mut t, 20..24, &cams),
            0,
            "{in_flight} {budget}"
        );
        assert_eq!(t.loaded.len(), g.levels.len());
        if in_flight == 0 || budget <= 1 {
            assert_eq!(t.fine_loads, 0, "{in_flight} {budget}: finer LODs loaded");
        }
        let st = w.stats();
        assert_eq!(st.in_flight_jobs, 0, "{st:?}");
        assert_eq!(st.in_flight_bytes, 0, "{st:?}");
    }
}

#[test]
fn absurd_lod_error_angles_settle() {
    let (g, dir) = baked("angles");
    let cams = [centre(g)];
    for angle in [0.0, -1.0, f32::NAN, f32::INFINITY, 1e30, f32::MIN_POSITIVE] {
        let config = StreamConfig {
            lod_error_angle: angle,
            ..det(StreamConfig::within(1e4, 2e4))
        };
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..30, &cams);
        assert_eq!(run(&mut w, &mut t, 30..36, &cams), 0, "angle {angle}");
        assert_eq!(t.loaded.len(), g.levels.len());
    }
}

/// With the default eviction factor the world settles and streams finer LODs (the control);
/// with a factor documented as "> 1" but set to 0.5, 0, NaN or -1 the world must either refuse
/// the configuration or still settle: a camera that stays put must not make finer LODs load and
/// evict every frame forever.
#[test]
fn lod_evict_factor_below_one_does_not_thrash() {
    let (g, dir) = baked("evict-factor");
    let cams = [centre(g)];
    let base = det(StreamConfig::within(1e4, 2e4));
    let mut w = open(&dir, base);
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..30, &cams);
    assert!(t.fine_loads > 0, "the control streams no finer LOD");
    assert_eq!(run(&mut w, &mut t, 30..40, &cams), 0, "the control churns");
    for factor in [1.0, 0.5, 0.0, f32::NAN, -1.0] {
        let config = StreamConfig {
            lod_evict_factor: factor,
            ..base
        };
        let Ok(mut w) = no_panic("World::open", || World::open(&*dir, config)) else {
            continue; // Refused: fine.
        };
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..30, &cams);
        let churn = run(&mut w, &mut t, 30..40, &cams);
        assert_eq!(
            churn, 0,
            "lod_evict_factor {factor}: {churn} events in 10 frames of a still camera ({} finer LOD loads in all)",
            t.fine_loads
        );
    }
}

/// Retry settings at their extremes, with one level file missing: retried every frame without
/// limit, never retried, or retried after u32::MAX frames. No panic, the other levels load, the
/// loader threads survive and the retry counter grows no faster than the frames.
#[test]
fn extreme_retry_settings_with_a_missing_level() {
    let (g, dir) = baked("retry");
    let manifest = rtstream_streaming::read_manifest(&*dir).expect("manifest");
    std::fs::remove_file(dir.join(&manifest.levels[4].file)).expect("remove");
    let cams = [centre(g)];
    for (retry, attempts) in [(0u32, u32::MAX), (0, 0), (u32::MAX, u32::MAX), (1, 1)] {
        let config = StreamConfig {
            retry_after_frames: retry,
            max_load_attempts: attempts,
            ..det(StreamConfig::within(1e4, 2e4))
        };
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..50, &cams);
        assert_eq!(t.loaded.len(), g.levels.len() - 1, "{retry} {attempts}");
        assert!(!w.is_loaded(LevelId(4)));
        let failed: Vec<_> = t
            .failures
            .iter()
            .filter(|f| f.level == Some(LevelId(4)))
            .collect();
        assert!(!failed.is_empty());
        assert!(failed
            .iter()
            .all(|f| matches!(&*f.error, StreamingError::Io { .. })));
        let st = w.stats();
        assert!(st.load_retries <= 50, "{st:?}");
        assert_eq!(st.loader_threads_alive, config.loader_threads);
    }
}

/// Results applied after u32::MAX frames: nothing arrives early, and everything arrives on its
/// frame; `update_until_idle` returns at once in this mode (documented).
#[test]
fn apply_after_u32_max_frames() {
    let (g, dir) = baked("apply-late");
    let config = StreamConfig {
        apply_after_frames: Some(u32::MAX),
        ..StreamConfig::within(1e4, 2e4)
    };
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    let cams = [centre(g)];
    run(&mut w, &mut t, 0..5, &cams);
    t.eat(
        &no_panic("update_until_idle", || {
            w.update_until_idle(5, &cams, Duration::MAX)
        })
        .expect("deterministic mode returns at once"),
    );
    assert!(t.loaded.is_empty());
    let due = u64::from(u32::MAX);
    run(&mut w, &mut t, due..due + 3, &cams);
    assert_eq!(t.loaded.len(), g.levels.len());
}

// ---------------------------------------------------------------------------------------------
// Foci

/// No focus at all: every loaded level goes (nothing is near any camera) and comes back.
#[test]
fn no_foci_unloads_and_nothing_breaks() {
    let (g, dir) = baked("no-foci");
    let mut w = open(&dir, det(StreamConfig::within(1e4, 2e4)));
    let mut t = Tracker::default();
    let cams = [centre(g)];
    run(&mut w, &mut t, 0..10, &cams);
    assert_eq!(t.loaded.len(), g.levels.len());
    run(&mut w, &mut t, 10..20, &[]);
    assert!(t.loaded.is_empty(), "{:?}", t.loaded);
    run(&mut w, &mut t, 20..30, &cams);
    assert_eq!(t.loaded.len(), g.levels.len());
    // With an infinite unload radius nothing leaves.
    let mut w = open(&dir, det(StreamConfig::within(1e4, f32::INFINITY)));
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..10, &cams);
    run(&mut w, &mut t, 10..20, &[]);
    assert_eq!(t.loaded.len(), g.levels.len());
    assert!(w.skin_frame(0.0, 2).iter().all(|f| f
        .positions
        .iter()
        .flatten()
        .all(|v| v.is_finite())));
}

/// Foci at +-infinity are farther than any radius: nothing loads; beside a real focus they
/// change nothing.
#[test]
fn infinite_foci_load_nothing() {
    let (g, dir) = baked("inf-foci");
    let inf = f32::INFINITY;
    let config = det(StreamConfig::within(60.0, 90.0));
    for p in [
        Vec3::splat(inf),
        Vec3::splat(-inf),
        Vec3::new(inf, 0.0, 0.0),
        Vec3::new(0.0, 0.0, -inf),
        Vec3::new(f32::MAX, 0.0, f32::MAX),
        Vec3::new(-f32::MAX, 0.0, f32::MAX),
    ] {
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..8, &[StreamFocus::from(p)]);
        assert!(t.loaded.is_empty(), "focus {p}: {:?}", t.loaded);
        let both = [centre(g), StreamFocus::from(p)];
        run(&mut w, &mut t, 8..20, &both);
        assert_eq!(t.loaded_set(), within(g, &both[..1], 60.0), "focus {p}");
    }
}

/// A NaN focus (an uninitialised camera) is nowhere: it must load nothing, and beside a real
/// focus it must change nothing (neither the levels nor the LODs streamed).
#[test]
fn nan_focus_loads_nothing() {
    let (g, dir) = baked("nan-foci");
    let nan = f32::NAN;
    let config = det(StreamConfig::within(20.0, 30.0));
    // The real focus alone, as the reference.
    let real = [focus(g.extent.min.x + 5.0, g.extent.min.z + 5.0)];
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..20, &real);
    let (want_levels, want_bytes) = (t.loaded_set(), w.stats().mesh_bytes);
    assert!(want_levels.len() < g.levels.len());
    for p in [
        Vec3::splat(nan),
        Vec3::new(nan, 0.0, 0.0),
        Vec3::new(0.0, 0.0, nan),
    ] {
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..8, &[StreamFocus::from(p)]);
        assert!(
            t.loaded.is_empty(),
            "focus {p}: {} of {} levels loaded",
            t.loaded.len(),
            g.levels.len()
        );
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..20, &[real[0], StreamFocus::from(p)]);
        assert_eq!(t.loaded_set(), want_levels, "focus {p} beside a real one");
        assert_eq!(w.stats().mesh_bytes, want_bytes, "focus {p}: other LODs");
    }
}

/// Thousands of foci (a grid over the map and beyond, and thousands at one point): exactly the
/// levels within the radius of one of them load.
#[test]
fn thousands_of_foci() {
    let (g, dir) = baked("many-foci");
    let config = det(StreamConfig::within(10.0, 15.0));
    let (lo, hi) = (g.extent.min, g.extent.max);
    let mut cams = Vec::new();
    for i in 0..64 {
        for j in 0..64 {
            // A grid over the western half of the map and a band beyond it.
            let x = lo.x - 100.0 + (hi.x - lo.x) * 0.5 * i as f32 / 63.0;
            let z = lo.z - 100.0 + (hi.z - lo.z + 200.0) * j as f32 / 63.0;
            cams.push(focus(x, z));
        }
    }
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..10, &cams);
    assert_eq!(t.loaded_set(), within(g, &cams, 10.0));
    let same = vec![centre(g); 5000];
    run(&mut w, &mut t, 10..20, &same);
    assert_eq!(t.loaded_set(), within(g, &same[..1], 10.0));
}

/// A 1e12 m teleport and back (and to -f32::MAX): everything unloads, comes back, and nothing
/// is left behind (the same bytes resident as a world that never left).
#[test]
fn teleport_1e12_m_and_back() {
    let (g, dir) = baked("teleport");
    let config = det(StreamConfig::within(60.0, 90.0));
    let home = [centre(g)];
    let mut fresh = open(&dir, config);
    let mut tf = Tracker::default();
    run(&mut fresh, &mut tf, 0..20, &home);
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..20, &home);
    for (k, far) in [
        Vec3::new(1e12, 2.0, 1e12),
        Vec3::new(-f32::MAX, 2.0, f32::MAX),
        Vec3::new(1e12, -1e12, -1e12),
    ]
    .into_iter()
    .enumerate()
    {
        let f0 = 100 + 100 * k as u64;
        run(&mut w, &mut t, f0..f0 + 10, &[StreamFocus::from(far)]);
        assert!(t.loaded.is_empty(), "at {far}: {:?}", t.loaded);
        run(&mut w, &mut t, f0 + 10..f0 + 40, &home);
        assert_eq!(t.loaded_set(), tf.loaded_set(), "back from {far}");
    }
    let st = w.stats();
    assert_eq!(st.in_flight_jobs, 0, "{st:?}");
    assert_eq!(
        st.loaded_instances,
        fresh.stats().loaded_instances,
        "{st:?}"
    );
}

/// A camera teleporting between two corners every frame for hundreds of frames, then parked far
/// away: no state piles up (the same bytes and LODs resident as a world that only ever saw the
/// final position) and the loads in flight drain.
#[test]
fn teleport_storm_leaves_nothing_behind() {
    let (g, dir) = baked("storm");
    let config = det(StreamConfig::within(40.0, 60.0));
    let (lo, hi) = (g.extent.min, g.extent.max);
    let a = [focus(lo.x + 10.0, lo.z + 10.0)];
    let b = [focus(hi.x - 10.0, hi.z - 10.0)];
    let park = [focus(1e7, 1e7)];
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    for f in 0..300u64 {
        let cams = if f % 2 == 0 { &a } else { &b };
        t.eat(&update(&mut w, f, cams));
        assert!(
            w.stats().in_flight_jobs <= 4 * g.levels.len() + 4 * g.meshes.len(),
            "frame {f}: {:?}",
            w.stats()
        );
    }
    run(&mut w, &mut t, 300..330, &park);
    let mut fresh = open(&dir, config);
    let mut tf = Tracker::default();
    run(&mut fresh, &mut tf, 0..30, &park);
    let (st, sf) = (w.stats(), fresh.stats());
    assert_eq!(st.loaded_levels, 0, "{st:?}");
    assert_eq!(st.in_flight_jobs, 0, "{st:?}");
    assert_eq!(
        st.mesh_bytes, sf.mesh_bytes,
        "leftover bytes: {st:?} vs {sf:?}"
    );
    assert_eq!(st.resident_lods, sf.resident_lods, "{st:?} vs {sf:?}");
}

// ---------------------------------------------------------------------------------------------
// Frame numbers

/// Repeated and backward frame numbers, with `update_until_idle`: streaming follows the camera
/// whatever the numbers.
#[test]
fn repeated_and_backward_frames_still_stream() {
    let (g, dir) = baked("frames");
    let config = StreamConfig::within(40.0, 60.0);
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    let (lo, hi) = (g.extent.min, g.extent.max);
    let spots = [
        (500u64, focus(lo.x + 10.0, lo.z + 10.0)),
        (500, focus(hi.x - 10.0, hi.z - 10.0)),
        (3, focus(lo.x + 10.0, hi.z - 10.0)),
        (3, focus(hi.x - 10.0, lo.z + 10.0)),
        (0, centre(g)),
        (u64::MAX - 1, focus(lo.x + 10.0, lo.z + 10.0)),
        (1, focus(hi.x - 10.0, hi.z - 10.0)),
    ];
    for (frame, cam) in spots {
        let cams = [cam];
        t.eat(&settle(&mut w, frame, &cams));
        t.eat(&settle(&mut w, frame, &cams));
        t.agrees(&w);
        assert_band(&t, g, &cams, config, &format!("frame {frame}"));
    }
}

/// Frame u64::MAX (and repeated): streaming works there.
#[test]
fn frame_u64_max_streams() {
    let (g, dir) = baked("u64max");
    for config in [
        StreamConfig::within(1e4, 2e4),
        det(StreamConfig::within(1e4, 2e4)),
    ] {
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        let cams = [centre(g)];
        for _ in 0..4 {
            t.eat(&settle(&mut w, u64::MAX, &cams));
        }
        t.agrees(&w);
        assert_eq!(t.loaded.len(), g.levels.len());
    }
}

/// A level that fails to load on frame u64::MAX is reported like on any other frame.
#[test]
fn a_load_failure_at_frame_u64_max_is_reported() {
    let (g, dir) = baked("u64max-fail");
    let manifest = rtstream_streaming::read_manifest(&*dir).expect("manifest");
    std::fs::remove_file(dir.join(&manifest.levels[0].file)).expect("remove");
    let mut w = open(&dir, StreamConfig::within(1e4, 2e4));
    let mut t = Tracker::default();
    let cams = [centre(g)];
    t.eat(&settle(&mut w, u64::MAX - 1, &cams));
    t.eat(&settle(&mut w, u64::MAX, &cams));
    assert!(t.failures.iter().any(|f| f.level == Some(LevelId(0))));
    assert_eq!(t.loaded.len(), g.levels.len() - 1);
}

/// Deterministic streaming with a frame counter that restarts (a new session, a reloaded save):
/// the loads still arrive within a few frames.
#[test]
fn deterministic_streaming_survives_a_frame_counter_reset() {
    let (g, dir) = baked("frame-reset");
    let config = det(StreamConfig::within(40.0, 60.0));
    let (lo, hi) = (g.extent.min, g.extent.max);
    let a = [focus(lo.x + 10.0, lo.z + 10.0)];
    let b = [focus(hi.x - 10.0, hi.z - 10.0)];
    for last in [1_000u64, u64::MAX - 3] {
        let mut w = open(&dir, config);
        let mut t = Tracker::default();
        run(&mut w, &mut t, last - 10..last, &a);
        assert_eq!(t.loaded_set(), within(g, &a, 40.0));
        // The camera moves on the last frame before the reset: its loads are in flight.
        t.eat(&update(&mut w, last, &b));
        run(&mut w, &mut t, 0..20, &b);
        assert_band(
            &t,
            g,
            &b,
            config,
            &format!("20 frames after a reset from frame {last}: {:?}", w.stats()),
        );
    }
}

// ---------------------------------------------------------------------------------------------
// update_until_idle limits

/// A zero limit: a typed `SettleTimeout` carrying the events so far (or Ok when nothing was in
/// flight); nothing is lost, and the loads in flight arrive on later calls.
#[test]
fn update_until_idle_with_a_zero_limit_loses_nothing() {
    let (g, dir) = baked("idle-zero");
    let mut w = open(&dir, StreamConfig::within(1e4, 2e4));
    let mut t = Tracker::default();
    let cams = [centre(g)];
    let mut timeouts = 0;
    for k in 0..50 {
        match no_panic("update_until_idle(ZERO)", || {
            w.update_until_idle(k, &cams, Duration::ZERO)
        }) {
            Ok(ev) => {
                t.eat(&ev);
                if w.stats().in_flight_jobs == 0 {
                    break;
                }
            }
            Err(SettleTimeout {
                in_flight, events, ..
            }) => {
                assert!(in_flight > 0);
                t.eat(&events);
                timeouts += 1;
            }
        }
    }
    t.eat(&settle(&mut w, 100, &cams));
    t.agrees(&w);
    assert_eq!(t.loaded.len(), g.levels.len(), "{timeouts} timeouts");
    assert!(t.level_loads.values().all(|&n| n == 1));
}

/// A level that fails on every attempt, retried at once and without limit: `update_until_idle`
/// cannot settle, and must say so with a typed `SettleTimeout` (events included) within its
/// limit rather than spin forever or panic; the other levels are in.
#[test]
fn update_until_idle_on_endless_retries_returns() {
    let (g, dir) = baked("idle-endless");
    let manifest = rtstream_streaming::read_manifest(&*dir).expect("manifest");
    std::fs::remove_file(dir.join(&manifest.levels[2].file)).expect("remove");
    let config = StreamConfig {
        retry_after_frames: 0,
        max_load_attempts: u32::MAX,
        ..StreamConfig::within(1e4, 2e4)
    };
    let mut w = open(&dir, config);
    let mut t = Tracker::default();
    let cams = [centre(g)];
    for frame in 0..3 {
        match no_panic("update_until_idle", || {
            w.update_until_idle(frame, &cams, Duration::from_millis(50))
        }) {
            Ok(ev) => t.eat(&ev),
            Err(SettleTimeout { events, .. }) => t.eat(&events),
        };
    }
    t.agrees(&w);
    assert!(t.failures.iter().all(|f| f.level == Some(LevelId(2))));
    assert!(!t.failures.is_empty());
    assert!(!w.is_loaded(LevelId(2)));
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);
}

/// The longest limit there is: waits as long as needed, returns when idle.
#[test]
fn update_until_idle_with_duration_max() {
    let (g, dir) = baked("idle-max");
    let mut w = open(&dir, StreamConfig::within(1e4, 2e4));
    let mut t = Tracker::default();
    let cams = [centre(g)];
    for limit in [Duration::MAX, Duration::from_secs(u64::MAX / 2)] {
        let r = no_panic("update_until_idle(Duration::MAX)", || {
            w.update_until_idle(0, &cams, limit)
        });
        t.eat(&r.expect("an unlimited wait settles"));
    }
    assert_eq!(t.loaded.len(), g.levels.len());
}

// ---------------------------------------------------------------------------------------------
// Files that go bad after World::open

/// After open, level files are deleted, truncated, emptied, replaced by a directory or by
/// another level's file: each fails typed (naming the file), the rest stream, and once the
/// files are back every level loads (no level lost to a transient failure). A level whose
/// attempts ran out loads once the cameras left and came back (documented).
#[test]
fn level_files_broken_after_open_fail_typed_and_recover() {
    let (g, dir) = baked("broken-after-open");
    let manifest = rtstream_streaming::read_manifest(&*dir).expect("manifest");
    let path = |i: usize| dir.join(&manifest.levels[i].file);
    let config = StreamConfig {
        retry_after_frames: 2,
        max_load_attempts: 3,
        ..det(StreamConfig::within(1e4, 2e4))
    };
    let mut w = open(&dir, config);
    let saved: Vec<Vec<u8>> = (0..g.levels.len())
        .map(|i| std::fs::read(path(i)).unwrap())
        .collect();
    std::fs::remove_file(path(0)).unwrap();
    std::fs::write(path(1), &saved[1][..saved[1].len() / 2]).unwrap();
    std::fs::write(path(2), b"").unwrap();
    std::fs::remove_file(path(3)).unwrap();
    std::fs::create_dir(path(3)).unwrap();
    std::fs::write(path(5), &saved[6]).unwrap();
    let broken = [0usize, 1, 2, 3, 5];
    let cams = [centre(g)];
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..3, &cams);
    for &i in &broken {
        let f = t
            .failures
            .iter()
            .find(|f| f.level == Some(LevelId(i as u32)) && f.mesh.is_none())
            .unwrap_or_else(|| panic!("no LoadFailed for level {i}"));
        match &*f.error {
            StreamingError::Io { path: p, .. } | StreamingError::Format { path: p, .. } => {
                assert_eq!(p, &path(i), "level {i}")
            }
            other => panic!("level {i}: {other:?}"),
        }
    }
    assert_eq!(t.loaded.len(), g.levels.len() - broken.len());
    // The files come back: the levels load on their next retry.
    std::fs::remove_dir(path(3)).unwrap();
    for &i in &broken {
        std::fs::write(path(i), &saved[i]).unwrap();
    }
    run(&mut w, &mut t, 3..30, &cams);
    assert_eq!(t.loaded.len(), g.levels.len(), "{:?}", w.stats());
    for (i, l) in g.levels.iter().enumerate() {
        assert_eq!(t.loaded[&LevelId(i as u32)], l.instances.len(), "level {i}");
    }
    // Out of attempts: stays failed while the cameras stay, loads after they left.
    let away = [focus(1e6, 1e6)];
    run(&mut w, &mut t, 30..40, &away);
    std::fs::remove_file(path(7)).unwrap();
    run(&mut w, &mut t, 40..100, &cams);
    assert!(!w.is_loaded(LevelId(7)));
    assert_eq!(w.stats().failed_levels, 1);
    std::fs::write(path(7), &saved[7]).unwrap();
    run(&mut w, &mut t, 100..110, &away);
    run(&mut w, &mut t, 110..120, &cams);
    assert_eq!(t.loaded.len(), g.levels.len(), "{:?}", w.stats());
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);
}

/// The mesh library truncated (then removed) after open: the LOD reads fail typed, naming the
/// library; levels load without the instances whose mesh is missing; once the library is back
/// and the levels reload, every instance is there.
#[test]
fn mesh_library_broken_after_open_recovers() {
    let (g, dir) = baked("broken-library");
    let lib = dir.join(rtstream_streaming::bake::MESH_LIBRARY_FILE);
    let saved = std::fs::read(&lib).unwrap();
    let config = det(StreamConfig::within(1e4, 2e4));
    let cams = [centre(g)];
    let away = [focus(1e6, 1e6)];
    for damage in 0..2 {
        let mut w = open(&dir, config);
        if damage == 0 {
            std::fs::write(&lib, &saved[..saved.len() / 3]).unwrap();
        } else {
            std::fs::remove_file(&lib).unwrap();
        }
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..10, &cams);
        assert!(!t.failures.is_empty(), "damage {damage}: nothing failed");
        for f in &t.failures {
            assert!(
                f.error.to_string().contains("meshes.rtm"),
                "damage {damage}: {}",
                f.error
            );
        }
        std::fs::write(&lib, &saved).unwrap();
        run(&mut w, &mut t, 10..20, &away);
        run(&mut w, &mut t, 20..40, &cams);
        assert_eq!(t.loaded.len(), g.levels.len());
        for (i, l) in g.levels.iter().enumerate() {
            assert_eq!(
                t.loaded[&LevelId(i as u32)],
                l.instances.len(),
                "damage {damage}: level {i}"
            );
        }
    }
}

/// The proxy file replaced by garbage, or by a directory, before open: reported once, typed,
/// and the levels stream regardless.
#[test]
fn a_broken_proxy_file_is_reported_once() {
    let (g, dir) = baked("broken-proxies");
    let proxies = dir.join(rtstream_streaming::proxy::PROXY_FILE);
    for damage in 0..2 {
        let _ = std::fs::remove_file(&proxies);
        let _ = std::fs::remove_dir_all(&proxies);
        if damage == 0 {
            std::fs::write(&proxies, b"JUNK").unwrap();
        } else {
            std::fs::create_dir(&proxies).unwrap();
        }
        let mut w = open(&dir, det(StreamConfig::within(1e4, 2e4)));
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..10, &[centre(g)]);
        assert_eq!(t.failures.len(), 1, "damage {damage}: {:?}", t.failures);
        assert!(w.proxy_tree().is_none());
        assert_eq!(t.loaded.len(), g.levels.len());
    }
}

// ---------------------------------------------------------------------------------------------
// glTF levels

/// glTF levels that are no glTF: a missing file, a text file, an empty file, a directory, a baked
/// level file, garbage behind a GLB magic. Each fails typed naming the file; a good one beside
/// them loads; the loader threads survive.
#[test]
fn gltf_levels_from_bad_files_fail_typed() {
    let (_, dir) = baked("bad-gltf");
    let text = dir.join("passwd.gltf");
    std::fs::write(&text, b"root:x:0:0:root:/root:/bin/bash\n").unwrap();
    let empty = dir.join("empty.glb");
    std::fs::write(&empty, b"").unwrap();
    let folder = dir.join("folder.gltf");
    std::fs::create_dir(&folder).unwrap();
    let glb = dir.join("fake.glb");
    let mut fake = b"glTF".to_vec();
    fake.extend_from_slice(&2u32.to_le_bytes());
    fake.extend_from_slice(&u32::MAX.to_le_bytes());
    fake.extend_from_slice(&[0xAB; 64]);
    std::fs::write(&glb, fake).unwrap();
    let manifest = rtstream_streaming::read_manifest(&*dir).expect("manifest");
    let bad = [
        dir.join("missing.gltf"),
        text,
        empty,
        folder,
        dir.join(&manifest.levels[0].file),
        glb,
        PathBuf::from(""),
    ];
    let config = StreamConfig::within(50.0, 80.0);
    let mut w = no_panic("World::empty", || World::empty(config)).expect("empty world");
    let ids: Vec<LevelId> = bad
        .iter()
        .map(|p| w.add_gltf_level(p, Mat4::IDENTITY))
        .collect();
    let good = w.add_gltf_level(gltf(BOX), Mat4::from_translation(Vec3::X));
    let mut t = Tracker::default();
    t.eat(&settle(&mut w, 0, &[focus(0.0, 0.0)]));
    t.agrees(&w);
    for (p, id) in bad.iter().zip(&ids) {
        let f = t
            .failures
            .iter()
            .find(|f| f.level == Some(*id))
            .unwrap_or_else(|| panic!("no LoadFailed for {}", p.display()));
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned());
        if let Some(name) = name {
            assert!(
                f.error.to_string().contains(&name),
                "{}: {}",
                p.display(),
                f.error
            );
        }
        assert!(!w.is_loaded(*id));
    }
    assert!(w.is_loaded(good));
    assert_eq!(w.stats().loader_threads_alive, config.loader_threads);
}

/// A glTF level placed by a NaN or infinite transform: a typed failure or a level that never
/// comes in range; never a panic, never NaN handed out; a good level beside it loads.
#[test]
fn gltf_levels_with_nonfinite_placements() {
    let nan = f32::NAN;
    let inf = f32::INFINITY;
    let placements = [
        Mat4::from_translation(Vec3::splat(nan)),
        Mat4::from_scale(Vec3::splat(nan)),
        Mat4::from_scale(Vec3::splat(inf)),
        Mat4::from_translation(Vec3::new(inf, 0.0, 0.0)),
        Mat4::from_cols_array(&[nan; 16]),
        Mat4::from_rotation_translation(Quat::from_xyzw(nan, 0.0, 0.0, 1.0), Vec3::ZERO),
        Mat4::ZERO,
    ];
    let config = StreamConfig::within(50.0, 80.0);
    let mut w = World::empty(config).expect("empty world");
    let ids: Vec<LevelId> = placements
        .iter()
        .map(|m| w.add_gltf_level(gltf(BOX), *m))
        .collect();
    let good = w.add_gltf_level(gltf(BOX), Mat4::IDENTITY);
    let mut t = Tracker::default();
    let cams = [focus(0.0, 0.0)];
    t.eat(&settle(&mut w, 0, &cams));
    t.eat(&settle(&mut w, 1, &cams));
    t.agrees(&w);
    assert!(w.is_loaded(good));
    for (m, id) in placements.iter().zip(&ids) {
        if w.is_loaded(*id) {
            // Loaded: only a finite placement may (the tracker checked its instances).
            assert!(m.is_finite(), "{id:?} loaded with placement {m:?}");
        }
    }
    for f in &t.failures {
        assert!(
            matches!(&*f.error, StreamingError::InvalidScene { .. }),
            "{:?}",
            f.error
        );
    }
}

/// A glTF level at 1e30 m (with a camera there): loads with finite bounds.
#[test]
fn gltf_level_placed_far_away_loads_finite() {
    let config = StreamConfig::within(50.0, 80.0);
    let mut w = World::empty(config).expect("empty world");
    let at = Vec3::new(1e30, 0.0, -1e30);
    let id = w.add_gltf_level(gltf(ENGINE), Mat4::from_translation(at));
    let mut t = Tracker::default();
    t.eat(&settle(&mut w, 0, &[StreamFocus::from(at)]));
    t.agrees(&w);
    assert!(w.is_loaded(id), "{:?}", t.failures);
}

/// A glTF level scaled by 1e38 (finite, but its world bounds overflow f32): a typed failure or a
/// level with finite bounds; never NaN handed out.
#[test]
fn gltf_level_with_a_huge_scale_hands_out_no_nan() {
    let config = StreamConfig::within(50.0, 80.0);
    for (rel, scale) in [(ENGINE, 1e38f32), (BOX, 1e38), (ENGINE, f32::MAX)] {
        let mut w = World::empty(config).expect("empty world");
        let id = w.add_gltf_level(gltf(rel), Mat4::from_scale(Vec3::splat(scale)));
        let mut t = Tracker::default();
        // The tracker asserts every instance it is handed is finite.
        t.eat(&settle(&mut w, 0, &[focus(0.0, 0.0)]));
        t.agrees(&w);
        assert!(
            w.is_loaded(id) || t.failures.iter().any(|f| f.level == Some(id)),
            "{rel} x {scale}: neither loaded nor failed"
        );
    }
}

/// A glTF level streaming in and out a hundred times: each time the same content; the world
/// does not grow with the cycles (mesh ids stay bounded, nothing stays resident), and every
/// load hands out the first load's instance ids (each load took new ones, wrapping into the
/// baked ids after 2^31 instances loaded).
#[test]
fn gltf_level_in_and_out_does_not_grow_the_world() {
    let config = StreamConfig::within(10.0, 20.0);
    let mut w = World::empty(config).expect("empty world");
    let id = w.add_gltf_level(gltf(BOX), Mat4::IDENTITY);
    let mut t = Tracker::default();
    let (here, away) = ([focus(0.0, 0.0)], [focus(1000.0, 0.0)]);
    let mut first_meshes = None;
    let mut first_instances: Option<Vec<WorldInstanceId>> = None;
    let mut max_mesh = 0;
    for cycle in 0..100u64 {
        let ev = settle(&mut w, 2 * cycle, &here);
        for e in &ev {
            match e {
                WorldEvent::MeshLodLoaded { mesh, .. } => max_mesh = max_mesh.max(mesh.0),
                WorldEvent::LevelLoaded { instances, .. } => {
                    let ids: Vec<WorldInstanceId> = instances.iter().map(|i| i.id).collect();
                    assert!(!ids.is_empty(), "cycle {cycle}: a level of no instances");
                    let first = first_instances.get_or_insert_with(|| ids.clone());
                    assert_eq!(&ids, first, "cycle {cycle}: instance ids changed");
                }
                _ => {}
            }
        }
        t.eat(&ev);
        assert!(w.is_loaded(id), "cycle {cycle}: {:?}", t.failures);
        let meshes: BTreeSet<WorldMeshId> = t.resident.iter().map(|(m, _)| *m).collect();
        let n = *first_meshes.get_or_insert(meshes.len());
        assert_eq!(meshes.len(), n, "cycle {cycle}");
        assert!(
            (max_mesh as usize) < 2 * n.max(1),
            "cycle {cycle}: mesh id {max_mesh} for a level of {n} meshes"
        );
        t.eat(&settle(&mut w, 2 * cycle + 1, &away));
        assert!(!w.is_loaded(id));
        let st = w.stats();
        assert_eq!((st.resident_lods, st.mesh_bytes), (0, 0), "{st:?}");
    }
}

/// A glTF level whose file changes on disk between loads (one mesh, then many, then one, then
/// many again): each load reuses the ids of the loads before it, in file order, and takes new
/// ones only for meshes beyond them; whatever the file no longer has holds nothing, and the
/// world's counters agree with the events after every load and unload.
#[test]
fn gltf_level_whose_file_changes_between_loads_reuses_its_mesh_ids() {
    let dir = Scratch(common::scratch("misuse-gltf-swap"));
    let file = dir.join("level.glb");
    let mut w = World::empty(StreamConfig::within(10.0, 20.0)).expect("empty world");
    let id = w.add_gltf_level(&file, Mat4::IDENTITY);
    let mut t = Tracker::default();
    let mut bytes: HashMap<(WorldMeshId, u8), usize> = HashMap::new();
    // Far beyond the larger model's extent (its bounds are the level's once it has loaded).
    let (here, away) = ([focus(0.0, 0.0)], [focus(1e5, 0.0)]);
    let mut seen: Vec<BTreeSet<WorldMeshId>> = Vec::new();
    for (cycle, rel) in [BOX, ENGINE, BOX, ENGINE].into_iter().enumerate() {
        std::fs::copy(gltf(rel), &file).expect("copy the glTF model");
        let ev = settle(&mut w, 2 * cycle as u64, &here);
        for e in &ev {
            match e {
                WorldEvent::MeshLodLoaded {
                    mesh,
                    lod,
                    geometry,
                    ..
                } => {
                    bytes.insert((*mesh, *lod), geometry.byte_size());
                }
                WorldEvent::MeshLodEvicted { mesh, lod } => {
                    bytes.remove(&(*mesh, *lod));
                }
                _ => {}
            }
        }
        t.eat(&ev);
        assert!(w.is_loaded(id), "{rel}: {:?}", t.failures);
        t.agrees(&w);
        assert_eq!(w.stats().mesh_bytes, bytes.values().sum::<usize>(), "{rel}");
        seen.push(t.resident.iter().map(|(m, _)| *m).collect());
        t.eat(&settle(&mut w, 2 * cycle as u64 + 1, &away));
        assert!(!w.is_loaded(id));
        t.agrees(&w);
        let st = w.stats();
        assert_eq!((st.resident_lods, st.mesh_bytes), (0, 0), "{rel}: {st:?}");
        bytes.clear();
    }
    let (one, many) = (&seen[0], &seen[1]);
    assert_eq!(one.len(), 1, "{BOX} has one mesh: {one:?}");
    assert!(many.len() > 1, "{ENGINE} has several meshes: {many:?}");
    assert!(one.is_subset(many), "{one:?} not reused in {many:?}");
    assert_eq!(&seen[2], one, "the smaller file again: its first id");
    assert_eq!(&seen[3], many, "the larger file again: the same ids");
    let top = many.iter().map(|m| m.0).max().unwrap_or(0) as usize;
    assert!(
        top < many.len(),
        "ids up to {top} for {} meshes",
        many.len()
    );
}

// ---------------------------------------------------------------------------------------------
// skin_frame

/// A world with skinned instances loaded: the baked world's characters and glTF's simple_skin.
fn skinned_world(name: &str) -> (World, Scratch) {
    let (g, dir) = baked(name);
    let mut w = open(&dir, StreamConfig::within(1e4, 2e4));
    let c = centre(g).position;
    w.add_gltf_level(gltf(SKIN), Mat4::from_translation(c));
    let mut t = Tracker::default();
    t.eat(&settle(&mut w, 0, &[centre(g)]));
    t.eat(&settle(&mut w, 1, &[centre(g)]));
    assert!(t.failures.is_empty(), "{:?}", t.failures);
    (w, dir)
}

fn check_skin(w: &World, time: f32, threads: usize, want: usize) {
    let frames = no_panic(&format!("skin_frame({time}, {threads})"), || {
        w.skin_frame(time, threads)
    });
    assert_eq!(frames.len(), want, "skin_frame({time}, {threads})");
    for f in &frames {
        let (_, g) = w.resident_lod(f.mesh).expect("resident");
        assert_eq!(f.positions.len(), g.positions.len());
        assert!(
            f.positions.iter().flatten().all(|v| v.is_finite()),
            "skin_frame({time}, {threads}): instance {:?} has non-finite positions",
            f.instance
        );
    }
}

/// Finite times of any size and sign, and any thread count: finite positions, the same whatever
/// the thread count.
#[test]
fn skin_frame_with_extreme_finite_times_and_thread_counts() {
    let (w, _dir) = skinned_world("skin-finite");
    let n = w.skin_frame(0.0, 1).len();
    assert!(n >= 1, "{n} skinned instances");
    for time in [
        0.0,
        -0.0,
        -1.0,
        -1e30,
        1e30,
        f32::MAX,
        f32::MIN,
        1e-45,
        123.456,
    ] {
        for threads in [0usize, 1, 3, 10_000, usize::MAX] {
            check_skin(&w, time, threads, n);
        }
    }
    let one = w.skin_frame(0.7, 1);
    let many = w.skin_frame(0.7, 10_000);
    for (a, b) in one.iter().zip(&many) {
        assert_eq!(a.instance, b.instance);
        assert_eq!(a.positions, b.positions);
    }
    // Nothing loaded: nothing to skin.
    let empty = World::empty(StreamConfig::default()).expect("empty world");
    assert!(empty.skin_frame(f32::NAN, 0).is_empty());
}

/// NaN and infinite times: the pose must stay finite (a held or rest pose), never NaN positions
/// (they would go straight into a BLAS refit).
#[test]
fn skin_frame_with_nonfinite_times_gives_finite_positions() {
    let (w, _dir) = skinned_world("skin-nonfinite");
    let n = w.skin_frame(0.0, 1).len();
    assert!(n >= 1);
    for time in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        for threads in [0usize, 1, 10_000] {
            check_skin(&w, time, threads, n);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The generator and the bake

/// Presets are plain data: building one with an absurd size (no generation) must not overflow,
/// and what it says must add up (its instance count covers its characters).
#[test]
fn absurd_presets_do_not_overflow() {
    let mut problems = Vec::new();
    for n in [0u32, 1, 600, u32::MAX / 9, u32::MAX] {
        let p = match panic_message(|| WorldPreset::crowd(n)) {
            Ok(p) => p,
            Err(msg) => {
                problems.push(format!("WorldPreset::crowd({n}) panicked: {msg}"));
                continue;
            }
        };
        let levels = u64::from(p.grid) * u64::from(p.grid);
        let characters = u64::from(p.characters_per_level) * levels;
        // All of them, or as many as the u32 instance count holds (within one level's share).
        let capped = u64::from(p.instances) + 9 > u64::from(u32::MAX);
        if (characters < u64::from(n) && !capped) || u64::from(p.instances) < characters {
            problems.push(format!(
                "crowd({n}): {} instances for {characters} characters",
                p.instances
            ));
        }
    }
    for grid in [0u32, 1, 65_535, 65_536, u32::MAX] {
        match panic_message(|| WorldPreset::small(grid, 1)) {
            Ok(p) if p.cell_size().is_finite() => {}
            Ok(p) => problems.push(format!("small({grid}): {p:?}")),
            Err(msg) => problems.push(format!("WorldPreset::small({grid}) panicked: {msg}")),
        }
    }
    assert!(problems.is_empty(), "DEFECT: {problems:#?}");
}

/// A world without instances, and one without levels: generated, baked and streamed without a
/// panic, and a bake that its own reader accepts (no `LoadFailed` for a file it just wrote).
#[test]
fn degenerate_worlds_bake_files_they_can_read() {
    common::assets();
    let mut no_instances = WorldPreset::small(2, 3);
    no_instances.instances = 0;
    let mut no_levels = WorldPreset::small(2, 3);
    no_levels.grid = 0;
    let mut problems = Vec::new();
    for (k, preset) in [no_instances, no_levels].into_iter().enumerate() {
        let what = format!(
            "{} grid {} instances {}",
            preset.name, preset.grid, preset.instances
        );
        let g = match panic_message(|| generate(&preset)) {
            Ok(Ok(g)) => g,
            Ok(Err(_)) => continue, // A typed refusal is fine.
            Err(msg) => {
                problems.push(format!("{what}: generate panicked: {msg}"));
                continue;
            }
        };
        let dir = Scratch(common::scratch(&format!("misuse-degenerate-{k}")));
        match panic_message(|| bake(&g, &*dir)) {
            Ok(Ok(_)) => {}
            Ok(Err(_)) => continue,
            Err(msg) => {
                problems.push(format!("{what}: bake panicked: {msg}"));
                continue;
            }
        }
        let config = det(StreamConfig::within(1e4, 2e4));
        let mut w = match no_panic("World::open", || World::open(&*dir, config)) {
            Ok(w) => w,
            Err(e) => {
                problems.push(format!("{what}: its own bake does not open: {e}"));
                continue;
            }
        };
        let mut t = Tracker::default();
        run(&mut w, &mut t, 0..5, &[focus(0.0, 0.0)]);
        for f in &t.failures {
            problems.push(format!("{what}: {}", f.error));
        }
        if t.loaded.len() != g.levels.len() {
            problems.push(format!(
                "{what}: {} of {} levels",
                t.loaded.len(),
                g.levels.len()
            ));
        }
    }
    assert!(problems.is_empty(), "DEFECT: {problems:#?}");
}

// ---------------------------------------------------------------------------------------------
// Lifetime and threads

/// Dropping a world with loads in flight (non-deterministic and deterministic, baked and glTF)
/// returns and panics nowhere.
#[test]
fn dropping_the_world_with_loads_in_flight() {
    let (g, dir) = baked("drop");
    let cams = [centre(g)];
    for k in 0..4 {
        let mut w = open(&dir, StreamConfig::within(1e4, 2e4));
        let _ = update(&mut w, 0, &cams);
        if k % 2 == 1 {
            let _ = update(&mut w, 1, &[focus(1e6, 0.0)]);
        }
        no_panic("drop(World)", || drop(w));
    }
    let mut w = open(
        &dir,
        StreamConfig {
            apply_after_frames: Some(1000),
            ..StreamConfig::within(1e4, 2e4)
        },
    );
    for f in 0..5 {
        let _ = update(&mut w, f, &cams);
    }
    assert!(w.stats().in_flight_jobs > 0);
    no_panic("drop(World)", || drop(w));
    let mut w = World::empty(StreamConfig::within(1e4, 2e4)).expect("empty");
    for k in 0..6 {
        w.add_gltf_level(gltf(ENGINE), Mat4::from_translation(Vec3::X * k as f32));
    }
    let _ = update(&mut w, 0, &[focus(0.0, 0.0)]);
    no_panic("drop(World)", || drop(w));
}

fn assert_send_sync<T: Send + Sync>() {}

/// `World` is `Send` and `Sync`: it streams on another thread, and its `&self` queries run from
/// several threads at once, agreeing with each other.
#[test]
fn the_world_moves_between_threads_and_answers_from_many() {
    assert_send_sync::<World>();
    let (g, dir) = baked("threads-use");
    let w = open(&dir, StreamConfig::within(1e4, 2e4));
    let cams = [centre(g)];
    let mut w = std::thread::spawn(move || {
        let mut w = w;
        let _ = w
            .update_until_idle(0, &cams, common::SETTLE)
            .expect("settles");
        w
    })
    .join()
    .expect("streaming thread");
    let _ = settle(&mut w, 1, &cams);
    let w = &w;
    let want = w.stats();
    let skinned = w.skin_frame(0.25, 2);
    let skinned = &skinned;
    std::thread::scope(|s| {
        let handles: Vec<_> = (0..8)
            .map(|k| {
                s.spawn(move || {
                    for _ in 0..20 {
                        assert_eq!(w.stats(), want);
                        assert!(w.is_loaded(LevelId(k % 9)));
                        let f = w.skin_frame(0.25, k as usize);
                        assert_eq!(f.len(), skinned.len());
                        for (a, b) in f.iter().zip(skinned.iter()) {
                            assert_eq!(a.positions, b.positions);
                        }
                        let _ = w.resident_lod(WorldMeshId(k));
                        let _ = w.proxy_tree();
                    }
                })
            })
            .collect();
        for h in handles {
            h.join().expect("query thread");
        }
    });
}

/// Ids that name nothing: no answer, no panic, and fault injection for them does nothing.
#[test]
fn queries_for_ids_that_name_nothing() {
    let (g, dir) = baked("ids");
    let mut w = open(&dir, det(StreamConfig::within(1e4, 2e4)));
    for id in [9, 1000, u32::MAX] {
        assert!(!w.is_loaded(LevelId(id)));
        w.inject_load_fault(LevelId(id), rtstream_streaming::LoadFault::Panic, u32::MAX);
    }
    for id in [g.meshes.len() as u32, u32::MAX] {
        assert!(w.resident_lod(WorldMeshId(id)).is_none());
    }
    let mut t = Tracker::default();
    run(&mut w, &mut t, 0..10, &[centre(g)]);
    assert_eq!(t.loaded.len(), g.levels.len());
    assert!(t.failures.is_empty());
    let mut e = World::empty(StreamConfig::default()).expect("empty world");
    assert!(e.proxy_tree().is_none());
    assert_eq!(e.level_count(), 0);
    for cams in [
        vec![],
        vec![StreamFocus::from(Vec3::NAN)],
        vec![focus(0.0, 0.0); 3000],
    ] {
        for f in [0, u64::MAX, 0] {
            let ev = no_panic("update of an empty world", || {
                e.update_until_idle(f, &cams, Duration::ZERO)
            })
            .expect("nothing to wait for");
            assert!(ev.is_empty());
        }
    }
    assert!(e.skin_frame(1.0, 4).is_empty());
}
