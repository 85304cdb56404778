//! The streaming world: level residency with hysteresis, mesh LOD streaming under a CPU memory
//! budget, and the ordered event stream.
//!
//! The thread that calls [`World::update`] owns all world state; loader threads only decode files
//! (see `loader`). Events are therefore produced by one thread, in program order, which gives the
//! per-level ordering for free: a level's `MeshLodLoaded` (its meshes' coarsest LODs, when new)
//! come before its `LevelLoaded`; its `LevelUnloaded` comes before the `MeshLodEvicted` of meshes
//! no other loaded level uses. A level unloaded while still loading emits nothing (its late result
//! is discarded by ticket).
//!
//! LOD policy: a mesh's coarsest LOD stays resident while any loaded level uses it, or any
//! resident far-field proxy lists a landmark of it (it is loaded with the proxy, after the
//! proxy's `ProxyLoaded`: a world whose regions have meshes of their own uses none of a far
//! region's meshes in the levels loaded, and the bridge places a landmark once its mesh has a
//! LOD); at most one
//! finer LOD is kept, chosen per mesh as the coarsest LOD whose world-space error is at most
//! `lod_error_angle` x distance to the nearest loaded instance (the nearest camera). A finer LOD
//! is evicted when it is finer than needed even at `1 / lod_evict_factor` of that distance
//! (hysteresis). Finer LODs are only requested while resident + in-flight bytes stay within
//! `mesh_budget_bytes`, evicting the farthest meshes' finer LODs first; coarsest LODs arrive with
//! their levels and are never refused (so the budget must exceed what the load radius holds).
//! Finer LODs admitted while levels were still loading can be overtaken by those levels'
//! coarsest LODs: each update then sheds finer LODs, farthest first, until the total fits, so
//! the budget can be exceeded only while finer loads admitted earlier are still in flight.
//!
//! Why one file over 600 lines: `World` owns all streaming state on one thread, and its residency,
//! load completion and unload paths update the same level and mesh slots in an order the event
//! guarantees above depend on, so they read best together; LOD streaming (`lod_stream.rs`), the
//! per-frame lists of what the loaded levels hold (`ranges.rs`), the public types (`types.rs`)
//! and the loader threads (`loader.rs`) are already apart.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{Mat4, Vec3};

use crate::bake::{read_manifest, Manifest};
use crate::error::{Result, StreamingError};
use crate::loader::{Done, Job, LevelSource, LoadedLevel, LoaderPool, LoaderShared};
use crate::model::{
    Aabb, Instance, LevelId, MaterialClass, MeshLod, Motion, WorldInstanceId, WorldMeshId,
};
use crate::skin::{skin_parallel, SkinJob};

mod lod_stream;
mod ranges;
mod types;

pub use types::{SettleTimeout, SkinnedFrame, StreamConfig, StreamFocus, StreamStats, WorldEvent};

#[derive(Debug)]
enum LevelState {
    Unloaded,
    Loading(u64),
    Loaded {
        instances: Arc<[Instance]>,
        meshes: Vec<WorldMeshId>,
    },
    /// The last load failed; after `attempts` loads it may be tried again at frame `retry_at`.
    Failed {
        attempts: u32,
        retry_at: u64,
    },
}

/// What LOD streaming reads of an instance of a streamed mesh (`LevelState::Loaded`).
#[derive(Debug, Clone, Copy)]
struct LodPoint {
    mesh: WorldMeshId,
    center: Vec3,
    radius: f32,
    /// Its largest axis scale (at least 1e-6).
    scale: f32,
}

#[derive(Debug)]
struct LevelSlot {
    bounds: Aabb,
    source: LevelSource,
    state: LevelState,
    /// Loads that failed in a row (reset by a success or by leaving the unload radius).
    failures: u32,
    /// A glTF level's mesh ids, in the file's mesh order, given on its first load: every
    /// later load refills these slots (new ones only for meshes beyond them, when the file
    /// changed), so a level streaming in and out does not grow the world. Empty for baked
    /// levels (their ids are the manifest's).
    gltf_meshes: Vec<WorldMeshId>,
    /// A glTF level's instance ids, in the file's instance order, given on its first load
    /// and reused by every later one (as `gltf_meshes`), so a level streaming in and out
    /// keeps its instances' ids and does not use up the dynamic id range.
    gltf_instances: Vec<WorldInstanceId>,
}

#[derive(Debug)]
struct MeshSlot {
    /// Bytes and error per LOD.
    lods: Vec<(usize, f32)>,
    /// Baked meshes stream their finer LODs; glTF-level meshes are all in memory.
    streamed: bool,
    refs: u32,
    /// Resident proxies that list a landmark of this mesh: its coarsest LOD stays resident
    /// while one does, as while a loaded level uses it.
    landmark_refs: u32,
    /// The ticket of its coarsest LOD's load for those landmarks (apart from `pending`,
    /// which is LOD streaming's).
    landmark_load: Option<u64>,
    resident: Vec<Option<Arc<MeshLod>>>,
    pending: Option<(usize, u64)>,
    failed: Vec<bool>,
}

impl MeshSlot {
    fn coarsest(&self) -> usize {
        self.lods.len() - 1
    }
    /// LOD `lod` of this slot's mesh `mesh` arrived as `g`: resident, its bytes added to
    /// `mesh_bytes`, announced in `ev`.
    fn arrive(
        &mut self,
        mesh: WorldMeshId,
        lod: usize,
        g: Arc<MeshLod>,
        mesh_bytes: &mut usize,
        ev: &mut Vec<WorldEvent>,
    ) {
        ev.push(lod_loaded(mesh, lod, self.lods.len() as u8, &g));
        self.resident[lod] = Some(g);
        *mesh_bytes += self.lods[lod].0;
    }
    /// LOD `lod` of this slot's mesh `mesh` failed to load (`level`: the level it came with,
    /// if any): not asked for again, announced in `ev`.
    fn fail(
        &mut self,
        mesh: WorldMeshId,
        lod: usize,
        level: Option<LevelId>,
        error: StreamingError,
        ev: &mut Vec<WorldEvent>,
    ) {
        self.failed[lod] = true;
        ev.push(WorldEvent::LoadFailed {
            level,
            mesh: Some((mesh, lod as u8)),
            proxy: None,
            error: Arc::new(error),
        });
    }
    fn finest_resident(&self) -> Option<usize> {
        self.resident.iter().position(Option::is_some)
    }
    fn desired(&self, distance: f32, angle: f32) -> usize {
        let mut i = self.coarsest();
        while i > 0 && self.lods[i].1 > angle * distance {
            i -= 1;
        }
        i
    }
}

/// The streaming world.
///
/// ```no_run
/// use rtstream_streaming::{bake, generate, StreamFocus, StreamConfig, World, WorldEvent, WorldPreset};
/// let dir = std::env::temp_dir().join("rtstream-doc-world");
/// bake(&generate(&WorldPreset::small(6, 1))?, &dir)?;
/// let mut world = World::open(&dir, StreamConfig::default())?;
/// let cams = [StreamFocus::from(glam::Vec3::ZERO)];
/// for frame in 0..10 {
///     for event in world.update(frame, &cams) {
///         if let WorldEvent::LevelLoaded { instances, .. } = event {
///             println!("{} instances in", instances.len());
///         }
///     }
/// }
/// # Ok::<(), rtstream_streaming::StreamingError>(())
/// ```
#[derive(Debug)]
pub struct World {
    config: StreamConfig,
    dir: PathBuf,
    manifest: Option<Arc<LoaderShared>>,
    pool: LoaderPool,
    levels: Vec<LevelSlot>,
    meshes: Vec<MeshSlot>,
    next_ticket: u64,
    next_dynamic_instance: u32,
    in_flight: usize,
    /// Of `in_flight`, the landmarks' coarsest LODs (they do not hold back LOD streaming).
    landmark_in_flight: usize,
    in_flight_bytes: usize,
    mesh_bytes: usize,
    frame: u64,
    /// Level loads retried after a failure.
    load_retries: u64,
    /// Deterministic mode: (ticket, request frame) of every job in flight, in request order.
    requests: std::collections::VecDeque<(u64, u64)>,
    /// Deterministic mode: results that arrived before their turn, by ticket.
    early: std::collections::BTreeMap<u64, Done>,
    /// The far-field proxies (read at open), or why the file could not be read.
    proxies: Option<std::result::Result<crate::proxy::ProxyFile, Arc<crate::StreamingError>>>,
    /// Per proxy node: resident, or its failure reported.
    proxy_state: Vec<ProxyState>,
    /// LOD streaming's per-mesh nearest distances, kept between frames (`lod_stream.rs`).
    lod_eff: Vec<f32>,
    /// The loaded instances of streamed meshes as LOD streaming reads them every frame, all
    /// levels in one array, with what lets the pass skip a level.
    lod_points: lod_stream::LodPoints,
    /// The loaded skinned instances (level, index in its instances), for `skin_frame`: a
    /// few dozen among tens of thousands.
    skinned: ranges::LevelRanges<(u32, u32)>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ProxyState {
    Out,
    Resident,
    Failed,
}

impl World {
    /// Opens a baked world directory (see [`crate::bake()`]) and starts the loader threads.
    pub fn open(dir: impl AsRef<Path>, config: StreamConfig) -> Result<World> {
        let dir = dir.as_ref().to_owned();
        let manifest = read_manifest(&dir)?;
        World::with_manifest(dir, Some(manifest), config)
    }

    /// A world with no baked content; add glTF levels with [`World::add_gltf_level`].
    pub fn empty(config: StreamConfig) -> Result<World> {
        World::with_manifest(PathBuf::new(), None, config)
    }

    fn with_manifest(
        dir: PathBuf,
        manifest: Option<Manifest>,
        config: StreamConfig,
    ) -> Result<World> {
        config.validate()?;
        let m = manifest.unwrap_or(Manifest {
            extent: Aabb::EMPTY,
            levels: Vec::new(),
            meshes: Vec::new(),
        });
        let levels = m
            .levels
            .iter()
            .map(|l| LevelSlot {
                bounds: l.bounds,
                source: LevelSource::Baked(PathBuf::from(&l.file)),
                state: LevelState::Unloaded,
                failures: 0,
                gltf_meshes: Vec::new(),
                gltf_instances: Vec::new(),
            })
            .collect();
        let meshes = m
            .meshes
            .iter()
            .map(|e| MeshSlot {
                lods: e.lods.iter().map(|l| (l.bytes as usize, l.error)).collect(),
                streamed: true,
                refs: 0,
                landmark_refs: 0,
                landmark_load: None,
                resident: vec![None; e.lods.len()],
                pending: None,
                failed: vec![false; e.lods.len()],
            })
            .collect();
        let shared = Arc::new(LoaderShared {
            dir: dir.clone(),
            mesh_bounds: m.meshes.iter().map(|e| e.bounds).collect(),
            lods: crate::loader::LodCache::new(&m),
            manifest: m,
            faults: parking_lot::Mutex::new(Vec::new()),
        });
        let pool = LoaderPool::new(Arc::clone(&shared), config.loader_threads)?;
        // Proxies are small and read whole here; a bad file is reported by the first update
        // and the levels stream regardless.
        let proxies = if dir.as_os_str().is_empty() {
            None
        } else {
            match crate::proxy::read_proxies(
                &dir,
                shared.manifest.levels.len(),
                shared.manifest.meshes.len(),
            ) {
                Ok(p) => p.map(Ok),
                Err(e) => Some(Err(Arc::new(e))),
            }
        };
        Ok(World {
            config,
            dir,
            manifest: Some(shared),
            pool,
            levels,
            meshes,
            next_ticket: 1,
            next_dynamic_instance: 1 << 31,
            in_flight: 0,
            landmark_in_flight: 0,
            in_flight_bytes: 0,
            mesh_bytes: 0,
            frame: 0,
            load_retries: 0,
            requests: std::collections::VecDeque::new(),
            early: std::collections::BTreeMap::new(),
            proxy_state: vec![
                ProxyState::Out;
                proxies
                    .as_ref()
                    .map_or(0, |p| p.as_ref().map_or(0, |f| f.tree.nodes.len()))
            ],
            proxies,
            lod_eff: Vec::new(),
            lod_points: lod_stream::LodPoints::default(),
            skinned: ranges::LevelRanges::default(),
        })
    }

    /// Registers a glTF 2.0 file as a level placed by `transform`; it streams in and out like any
    /// other level (its bounds are the placement point until it has loaded). Its meshes get new
    /// ids on its first load, which every later load reuses (a file changed on disk keeps the
    /// ids of its first meshes, in file order, and gets new ones only for meshes beyond them);
    /// their whole LOD chains arrive with it.
    pub fn add_gltf_level(&mut self, path: impl AsRef<Path>, transform: Mat4) -> LevelId {
        let p = transform.w_axis.truncate();
        let id = LevelId(self.levels.len() as u32);
        self.levels.push(LevelSlot {
            bounds: Aabb { min: p, max: p },
            source: LevelSource::Gltf {
                path: path.as_ref().to_owned(),
                transform,
            },
            state: LevelState::Unloaded,
            failures: 0,
            gltf_meshes: Vec::new(),
            gltf_instances: Vec::new(),
        });
        id
    }

    /// Test-only fault injection: the next `times` loads of `level` fail with `fault`, on the
    /// loader thread, as a real failure would. The level is reported failed
    /// ([`WorldEvent::LoadFailed`]) and retried with backoff
    /// ([`StreamConfig::retry_after_frames`]); the rest of the world carries on.
    #[doc(hidden)]
    pub fn inject_load_fault(&self, level: LevelId, fault: crate::loader::LoadFault, times: u32) {
        if let Some(shared) = &self.manifest {
            shared.faults.lock().push((level, fault, times));
        }
    }

    /// The baked world's directory (empty for [`World::empty`]).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The baked world's manifest.
    pub fn manifest(&self) -> Option<&Manifest> {
        self.manifest.as_ref().map(|s| &s.manifest)
    }

    /// Number of levels (baked and glTF).
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Whether a level is loaded.
    pub fn is_loaded(&self, level: LevelId) -> bool {
        matches!(
            self.levels.get(level.0 as usize).map(|l| &l.state),
            Some(LevelState::Loaded { .. })
        )
    }

    /// The finest resident LOD of a mesh.
    pub fn resident_lod(&self, mesh: WorldMeshId) -> Option<(usize, Arc<MeshLod>)> {
        let s = self.meshes.get(mesh.0 as usize)?;
        let i = s.finest_resident()?;
        s.resident[i].clone().map(|g| (i, g))
    }

    /// Current counters.
    pub fn stats(&self) -> StreamStats {
        let mut st = StreamStats {
            loaded_levels: 0,
            loading_levels: 0,
            failed_levels: 0,
            loaded_instances: 0,
            resident_lods: self
                .meshes
                .iter()
                .flat_map(|m| &m.resident)
                .filter(|r| r.is_some())
                .count(),
            mesh_bytes: self.mesh_bytes,
            in_flight_bytes: self.in_flight_bytes,
            in_flight_jobs: self.in_flight,
            load_retries: self.load_retries,
            loader_threads_alive: self.pool.alive(),
            lod_reads: self
                .manifest
                .as_ref()
                .map_or(0, |m| m.lods.reads.load(Relaxed)),
            lod_reads_shared: self
                .manifest
                .as_ref()
                .map_or(0, |m| m.lods.shared.load(Relaxed)),
        };
        for l in &self.levels {
            match &l.state {
                LevelState::Loaded { instances, .. } => {
                    st.loaded_levels += 1;
                    st.loaded_instances += instances.len();
                }
                LevelState::Loading(_) => st.loading_levels += 1,
                LevelState::Failed { .. } => st.failed_levels += 1,
                LevelState::Unloaded => {}
            }
        }
        st
    }

    /// Advances streaming by one frame: takes finished loads, loads/unloads levels around the
    /// cameras, streams LODs, and returns the events in order. Never blocks on I/O.
    ///
    /// A focus whose position is not finite is left out (with a warning): it is at no
    /// distance from anything, and would stream in the whole world.
    pub fn update(&mut self, frame: u64, cameras: &[StreamFocus]) -> Vec<WorldEvent> {
        let _span = tracing::debug_span!("world_update", frame).entered();
        let finite;
        let cameras = if cameras.iter().all(|c| c.position.is_finite()) {
            cameras
        } else {
            tracing::warn!(frame, "streaming foci with non-finite positions left out");
            finite = cameras
                .iter()
                .filter(|c| c.position.is_finite())
                .copied()
                .collect::<Vec<_>>();
            &finite[..]
        };
        if frame < self.frame {
            self.frame_went_back(frame);
        }
        self.frame = frame;
        let mut ev = Vec::new();
        match self.config.apply_after_frames {
            None => {
                while let Ok(done) = self.pool.results.try_recv() {
                    self.finish(done, &mut ev);
                }
            }
            Some(n) => self.finish_due(frame, u64::from(n), &mut ev),
        }
        self.residency(cameras, &mut ev);
        self.stream_lods(cameras, &mut ev);
        self.stream_proxies(cameras, &mut ev);
        ev
    }

    /// The far-field proxy tree (None when the world has no readable proxy file).
    pub fn proxy_tree(&self) -> Option<&crate::proxy::ProxyTree> {
        match &self.proxies {
            Some(Ok(f)) => Some(&f.tree),
            _ => None,
        }
    }

    /// Proxies within the far radius become resident (geometry from memory: the file was read
    /// at open); beyond 1.1x it they leave. Failures are reported once.
    fn stream_proxies(&mut self, cameras: &[StreamFocus], ev: &mut Vec<WorldEvent>) {
        let Some(p) = &self.proxies else { return };
        let file = match p {
            Ok(f) => f,
            Err(e) => {
                if self.proxy_state.is_empty() {
                    self.proxy_state.push(ProxyState::Failed);
                    ev.push(WorldEvent::LoadFailed {
                        level: None,
                        mesh: None,
                        proxy: None,
                        error: Arc::clone(e),
                    });
                }
                return;
            }
        };
        let far = self.config.far_radius;
        let (mut came, mut left) = (Vec::new(), Vec::new());
        for (i, node) in file.tree.nodes.iter().enumerate() {
            let d = cameras
                .iter()
                .map(|c| node.bounds.distance_xz(c.position))
                .fold(f32::INFINITY, f32::min);
            match self.proxy_state[i] {
                ProxyState::Out if d <= far => match &file.geometry[i] {
                    Ok(g) => {
                        self.proxy_state[i] = ProxyState::Resident;
                        let bounds = self.manifest.as_ref().map(|s| &s.mesh_bounds);
                        let landmarks: Arc<[(LevelId, Instance)]> = node
                            .landmarks
                            .iter()
                            .filter_map(|l| {
                                let b = bounds?.get(l.mesh.0 as usize)?;
                                Some((
                                    l.level,
                                    Instance::new(
                                        l.instance,
                                        l.mesh,
                                        l.transform,
                                        b,
                                        MaterialClass::Opaque,
                                        Motion::Static,
                                    ),
                                ))
                            })
                            .collect();
                        ev.push(WorldEvent::ProxyLoaded {
                            node: node.id,
                            geometry: Arc::clone(g),
                            landmarks,
                        });
                        came.push(i);
                    }
                    Err(e) => {
                        self.proxy_state[i] = ProxyState::Failed;
                        ev.push(WorldEvent::LoadFailed {
                            level: None,
                            mesh: None,
                            proxy: Some(node.id),
                            error: Arc::clone(e),
                        });
                    }
                },
                ProxyState::Resident if d > far * 1.1 => {
                    self.proxy_state[i] = ProxyState::Out;
                    ev.push(WorldEvent::ProxyEvicted { node: node.id });
                    left.push(i);
                }
                _ => {}
            }
        }
        for (nodes, resident) in [(left, false), (came, true)] {
            for i in nodes {
                for m in self.landmark_meshes(i) {
                    self.landmark_mesh(m, resident, ev);
                }
            }
        }
    }

    /// The meshes of proxy node `i`'s landmarks, each once.
    fn landmark_meshes(&self, i: usize) -> Vec<WorldMeshId> {
        let Some(Ok(file)) = &self.proxies else {
            return Vec::new();
        };
        let mut ms: Vec<WorldMeshId> = file.tree.nodes[i]
            .landmarks
            .iter()
            .map(|l| l.mesh)
            .filter(|m| (m.0 as usize) < self.meshes.len())
            .collect();
        ms.sort_unstable();
        ms.dedup();
        ms
    }

    /// A resident proxy lists a landmark of `mesh` (`resident`), or no longer does. The bridge
    /// places a landmark once its mesh has a resident LOD; beyond the levels loaded, in a
    /// world whose regions have meshes of their own, none would, so the coarsest LOD comes
    /// with the proxy (as it does with a level) and goes when neither a level nor a proxy
    /// wants it.
    fn landmark_mesh(&mut self, mesh: WorldMeshId, resident: bool, ev: &mut Vec<WorldEvent>) {
        let slot = &mut self.meshes[mesh.0 as usize];
        if !resident {
            slot.landmark_refs = slot.landmark_refs.saturating_sub(1);
            if slot.landmark_refs == 0 && slot.refs == 0 {
                self.release_mesh(mesh, false, ev);
            }
            return;
        }
        slot.landmark_refs += 1;
        let c = slot.coarsest();
        if !slot.streamed
            || slot.resident[c].is_some()
            || slot.landmark_load.is_some()
            || slot.failed[c]
        {
            return;
        }
        let ticket = self.new_ticket();
        self.meshes[mesh.0 as usize].landmark_load = Some(ticket);
        self.in_flight += 1;
        self.landmark_in_flight += 1;
        self.pool.submit(Job::Lod {
            mesh,
            lod: c,
            ticket,
        });
    }

    /// Evicts `mesh`'s resident LODs (all, or all but the coarsest) and cancels LOD
    /// streaming's load of it.
    fn release_mesh(&mut self, mesh: WorldMeshId, keep_coarsest: bool, ev: &mut Vec<WorldEvent>) {
        let slot = &mut self.meshes[mesh.0 as usize];
        if let Some((lod, _)) = slot.pending.take() {
            self.in_flight_bytes = self.in_flight_bytes.saturating_sub(slot.lods[lod].0);
        }
        let c = slot.coarsest();
        for (lod, r) in slot.resident.iter_mut().enumerate() {
            if keep_coarsest && lod == c {
                continue;
            }
            if r.take().is_some() {
                self.mesh_bytes -= slot.lods[lod].0;
                ev.push(WorldEvent::MeshLodEvicted {
                    mesh,
                    lod: lod as u8,
                });
            }
        }
        if !keep_coarsest {
            // A failed LOD may be retried once the mesh comes back.
            slot.failed.iter_mut().for_each(|f| *f = false);
        }
    }

    /// Deterministic mode: applies, in request order, every result requested at least `n`
    /// frames ago, waiting for the loader threads when one is late.
    /// The caller's frame numbers went back (a new session, a counter reset): what was asked
    /// or scheduled at a later frame counts as asked or scheduled at `frame`, so that pending
    /// loads and retries come due instead of waiting for the old numbers to come round.
    fn frame_went_back(&mut self, frame: u64) {
        tracing::warn!(
            frame,
            last = self.frame,
            "streaming frame numbers went back"
        );
        for (_, asked) in &mut self.requests {
            *asked = (*asked).min(frame);
        }
        for slot in &mut self.levels {
            if let LevelState::Failed { retry_at, .. } = &mut slot.state {
                *retry_at = (*retry_at).min(frame);
            }
        }
    }

    fn finish_due(&mut self, frame: u64, n: u64, ev: &mut Vec<WorldEvent>) {
        while let Some(&(ticket, asked)) = self.requests.front() {
            if asked.saturating_add(n) > frame {
                break;
            }
            let done = loop {
                if let Some(d) = self.early.remove(&ticket) {
                    break Some(d);
                }
                match self.pool.results.recv() {
                    Ok(d) => {
                        self.early.insert(d.ticket(), d);
                    }
                    // Every loader thread is gone (they outlive panics, so only at shutdown).
                    Err(_) => break None,
                }
            };
            self.requests.pop_front();
            match done {
                Some(d) => self.finish(d, ev),
                None => {
                    tracing::error!("loader threads are gone; dropping the pending loads");
                    self.requests.clear();
                    self.in_flight = 0;
                    self.landmark_in_flight = 0;
                    return;
                }
            }
        }
    }

    /// A new loader ticket, recorded with this frame (deterministic mode applies it later).
    pub(crate) fn new_ticket(&mut self) -> u64 {
        let ticket = self.next_ticket;
        self.next_ticket += 1;
        if self.config.apply_after_frames.is_some() {
            self.requests.push_back((ticket, self.frame));
        }
        ticket
    }

    /// Calls [`World::update`] (same frame and cameras) until no load is in flight, waiting on
    /// the loaders in between; returns every event. For tests and tools. Waiting longer than
    /// `timeout` is a [`SettleTimeout`] carrying the events so far (a slow or overloaded
    /// machine, or a stuck loader), never a silent partial result. In deterministic mode
    /// ([`StreamConfig::apply_after_frames`]) this is [`World::update`]: results arrive on
    /// their fixed frame, never earlier.
    pub fn update_until_idle(
        &mut self,
        frame: u64,
        cameras: &[StreamFocus],
        timeout: Duration,
    ) -> Result<Vec<WorldEvent>, SettleTimeout> {
        if self.config.apply_after_frames.is_some() {
            return Ok(self.update(frame, cameras));
        }
        let start = Instant::now();
        // A limit past the clock's range (`Duration::MAX`) waits without one.
        let deadline = start.checked_add(timeout);
        let mut all = Vec::new();
        loop {
            all.extend(self.update(frame, cameras));
            if self.in_flight == 0 {
                return Ok(all);
            }
            let got = match deadline {
                Some(d) => self
                    .pool
                    .results
                    .recv_timeout(d.saturating_duration_since(Instant::now())),
                None => self
                    .pool
                    .results
                    .recv()
                    .map_err(|_| crossbeam::channel::RecvTimeoutError::Disconnected),
            };
            match got {
                Ok(done) => self.finish(done, &mut all),
                Err(_) => {
                    return Err(SettleTimeout {
                        waited: start.elapsed(),
                        in_flight: self.in_flight,
                        events: all,
                    })
                }
            }
        }
    }

    fn finish(&mut self, done: Done, ev: &mut Vec<WorldEvent>) {
        self.in_flight = self.in_flight.saturating_sub(1);
        match done {
            Done::Level {
                level,
                ticket,
                result,
            } => self.level_done(level, ticket, result, ev),
            Done::Lod {
                mesh,
                lod,
                ticket,
                result,
            } => self.lod_done(mesh, lod, ticket, result, ev),
        }
    }

    /// The load of `level` with `ticket` ended with `result` (dropped if no longer wanted).
    fn level_done(
        &mut self,
        level: LevelId,
        ticket: u64,
        result: Result<LoadedLevel>,
        ev: &mut Vec<WorldEvent>,
    ) {
        let Some(slot) = self.levels.get(level.0 as usize) else {
            return;
        };
        if !matches!(slot.state, LevelState::Loading(t) if t == ticket) {
            return; // Unloaded while loading: drop silently.
        }
        match result {
            Err(e) => {
                let slot = &mut self.levels[level.0 as usize];
                slot.failures += 1;
                let backoff =
                    u64::from(self.config.retry_after_frames) << (slot.failures - 1).min(16);
                tracing::warn!(level = level.0, error = %e, attempts = slot.failures, "level load failed");
                slot.state = LevelState::Failed {
                    attempts: slot.failures,
                    retry_at: self.frame.saturating_add(backoff),
                };
                ev.push(WorldEvent::LoadFailed {
                    level: Some(level),
                    mesh: None,
                    proxy: None,
                    error: Arc::new(e),
                });
            }
            Ok(loaded) => {
                self.levels[level.0 as usize].failures = 0;
                self.level_arrived(level, loaded, ev);
            }
        }
    }

    /// The load of LOD `lod` of `mesh` with `ticket` ended with `result` (dropped if cancelled).
    fn lod_done(
        &mut self,
        mesh: WorldMeshId,
        lod: usize,
        ticket: u64,
        result: Result<Arc<MeshLod>>,
        ev: &mut Vec<WorldEvent>,
    ) {
        let Some(slot) = self.meshes.get_mut(mesh.0 as usize) else {
            return;
        };
        if slot.landmark_load == Some(ticket) {
            // The coarsest LOD for a proxy's landmarks: kept if still wanted and not brought
            // by a level meanwhile.
            slot.landmark_load = None;
            self.landmark_in_flight = self.landmark_in_flight.saturating_sub(1);
            let wanted = slot.landmark_refs > 0 || slot.refs > 0;
            match result {
                Ok(g) if wanted && slot.resident[lod].is_none() => {
                    slot.arrive(mesh, lod, g, &mut self.mesh_bytes, ev)
                }
                Err(e) if wanted => slot.fail(mesh, lod, None, e, ev),
                _ => {}
            }
            return;
        }
        if slot.pending != Some((lod, ticket)) {
            return; // Cancelled (its bytes were released then).
        }
        slot.pending = None;
        self.in_flight_bytes = self.in_flight_bytes.saturating_sub(slot.lods[lod].0);
        match result {
            Err(e) => slot.fail(mesh, lod, None, e, ev),
            Ok(g) => {
                let coarsest = slot.coarsest();
                slot.arrive(mesh, lod, g, &mut self.mesh_bytes, ev);
                // Keep one finer LOD: drop the others (not the coarsest).
                for k in 0..coarsest {
                    if k != lod && slot.resident[k].take().is_some() {
                        self.mesh_bytes -= slot.lods[k].0;
                        ev.push(WorldEvent::MeshLodEvicted { mesh, lod: k as u8 });
                    }
                }
            }
        }
    }

    fn level_arrived(&mut self, level: LevelId, loaded: LoadedLevel, ev: &mut Vec<WorldEvent>) {
        let (instances, meshes): (Vec<Instance>, Vec<WorldMeshId>) = match loaded {
            LoadedLevel::Baked { level: l, coarse } => {
                for (m, lod, res) in coarse {
                    let slot = &mut self.meshes[m.0 as usize];
                    if slot.resident[lod].is_some() {
                        continue;
                    }
                    match res {
                        Ok(g) => slot.arrive(m, lod, g, &mut self.mesh_bytes, ev),
                        Err(e) => slot.fail(m, lod, Some(level), e, ev),
                    }
                }
                // Instances whose mesh has no coarsest LOD cannot be used: leave them out.
                let kept: Vec<Instance> = l
                    .instances
                    .into_iter()
                    .filter(|i| {
                        let s = &self.meshes[i.mesh.0 as usize];
                        s.resident[s.coarsest()].is_some()
                    })
                    .collect();
                let mut ids: Vec<WorldMeshId> = kept.iter().map(|i| i.mesh).collect();
                ids.sort_unstable();
                ids.dedup();
                (kept, ids)
            }
            LoadedLevel::Gltf { meshes, instances } => {
                let mut ids = Vec::with_capacity(meshes.len());
                let mut bounds = Vec::with_capacity(meshes.len());
                for (k, m) in meshes.into_iter().enumerate() {
                    let id = self.gltf_mesh_slot(level, k, ev);
                    let n = m.lods.len() as u8;
                    // Coarsest first, as for baked levels.
                    for (lod, g) in m.lods.iter().enumerate().rev() {
                        ev.push(lod_loaded(id, lod, n, g));
                        self.mesh_bytes += g.byte_size();
                    }
                    tracing::trace!(mesh = id.0, name = %m.name, "glTF level mesh");
                    let slot = &mut self.meshes[id.0 as usize];
                    // Its refs (and landmark refs, which only baked meshes get) stay as
                    // released: 0, the level's own count is added below.
                    slot.lods = m.lods.iter().map(|g| (g.byte_size(), g.error)).collect();
                    slot.streamed = false;
                    slot.landmark_load = None;
                    slot.failed = vec![false; m.lods.len()];
                    slot.resident = m.lods.into_iter().map(Some).collect();
                    slot.pending = None;
                    ids.push(id);
                    bounds.push(m.bounds);
                }
                // Ids of meshes the file no longer has (it changed on disk) stay the level's
                // for a later load, holding nothing.
                for k in ids.len()..self.levels[level.0 as usize].gltf_meshes.len() {
                    let id = self.levels[level.0 as usize].gltf_meshes[k];
                    self.release_mesh(id, false, ev);
                }
                let inst = instances
                    .into_iter()
                    .enumerate()
                    .map(|(k, i)| {
                        let id = self.gltf_instance_id(level, k);
                        Instance::new(
                            id,
                            ids[i.mesh],
                            i.transform,
                            &bounds[i.mesh],
                            i.material,
                            i.motion,
                        )
                    })
                    .collect();
                (inst, ids)
            }
        };
        for m in &meshes {
            self.meshes[m.0 as usize].refs += 1;
        }
        let slot = &mut self.levels[level.0 as usize];
        if matches!(slot.source, LevelSource::Gltf { .. }) {
            let p = slot.bounds.min;
            slot.bounds = instances
                .iter()
                .fold(Aabb { min: p, max: p }, |b, i| b.union(i.aabb));
        }
        let instances: Arc<[Instance]> = instances.into();
        tracing::trace!(level = level.0, instances = instances.len(), "level loaded");
        ev.push(WorldEvent::LevelLoaded {
            level,
            bounds: slot.bounds,
            instances: Arc::clone(&instances),
        });
        let points = instances
            .iter()
            .filter(|i| self.meshes[i.mesh.0 as usize].streamed)
            .map(|i| LodPoint {
                mesh: i.mesh,
                center: i.sphere.center,
                radius: i.sphere.radius,
                scale: i.max_scale().max(1e-6),
            });
        self.lod_points.insert(level.0, points);
        let skinned = instances
            .iter()
            .enumerate()
            .filter(|(_, i)| i.motion == Motion::Skinned)
            .map(|(k, _)| (level.0, k as u32));
        self.skinned.insert(level.0, skinned);
        let slot = &mut self.levels[level.0 as usize];
        slot.state = LevelState::Loaded { instances, meshes };
    }

    /// The id of mesh `k` (in file order) of glTF level `level`: the one it got on an earlier
    /// load, emptied of anything still resident (nothing is, once the level unloaded: its
    /// meshes are its own), or a new slot the level keeps for its later loads.
    fn gltf_mesh_slot(
        &mut self,
        level: LevelId,
        k: usize,
        ev: &mut Vec<WorldEvent>,
    ) -> WorldMeshId {
        if let Some(&id) = self.levels[level.0 as usize].gltf_meshes.get(k) {
            self.release_mesh(id, false, ev);
            return id;
        }
        let id = WorldMeshId(self.meshes.len() as u32);
        self.meshes.push(MeshSlot {
            lods: Vec::new(),
            streamed: false,
            refs: 0,
            landmark_refs: 0,
            landmark_load: None,
            resident: Vec::new(),
            pending: None,
            failed: Vec::new(),
        });
        self.levels[level.0 as usize].gltf_meshes.push(id);
        id
    }

    /// The id of instance `k` (in file order) of glTF level `level`: the one it got on an
    /// earlier load, or the next dynamic id, which the level keeps for its later loads.
    ///
    /// Dynamic ids start at 2^31, past a baked world's (those count from 0; 2^31 baked
    /// instances would take hundreds of GB). They are only taken by instances that no glTF
    /// level had before, so running out needs 2^31 distinct glTF instances, whose id lists
    /// alone would hold 8 GB. (Before, every load took new ids: a level of 10,000 instances
    /// streaming in and out wrapped into the baked range after about 200,000 loads.)
    fn gltf_instance_id(&mut self, level: LevelId, k: usize) -> WorldInstanceId {
        let ids = &mut self.levels[level.0 as usize].gltf_instances;
        if let Some(&id) = ids.get(k) {
            return id;
        }
        let id = WorldInstanceId(self.next_dynamic_instance);
        self.next_dynamic_instance = self.next_dynamic_instance.wrapping_add(1);
        ids.push(id);
        id
    }

    fn residency(&mut self, cameras: &[StreamFocus], ev: &mut Vec<WorldEvent>) {
        let _span = tracing::trace_span!("residency").entered();
        let (load, unload) = (
            self.config.load_radius,
            self.config.unload_radius.max(self.config.load_radius),
        );
        for i in 0..self.levels.len() {
            let slot = &self.levels[i];
            let d = cameras
                .iter()
                .map(|c| slot.bounds.distance_xz(c.position))
                .fold(f32::INFINITY, f32::min);
            let retry = match slot.state {
                LevelState::Failed { attempts, retry_at } => {
                    attempts < self.config.max_load_attempts && self.frame >= retry_at
                }
                _ => false,
            };
            match slot.state {
                LevelState::Unloaded | LevelState::Failed { .. }
                    if d <= load && (retry || matches!(slot.state, LevelState::Unloaded)) =>
                {
                    let source = slot.source.clone();
                    let ticket = self.new_ticket();
                    self.pool.submit(Job::Level {
                        level: LevelId(i as u32),
                        ticket,
                        source,
                    });
                    self.in_flight += 1;
                    self.load_retries += u64::from(retry);
                    self.levels[i].state = LevelState::Loading(ticket);
                }
                LevelState::Loading(_) | LevelState::Failed { .. } if d > unload => {
                    self.levels[i].state = LevelState::Unloaded;
                    self.levels[i].failures = 0;
                }
                LevelState::Loaded { .. } if d > unload => self.unload(LevelId(i as u32), ev),
                _ => {}
            }
        }
    }

    fn unload(&mut self, level: LevelId, ev: &mut Vec<WorldEvent>) {
        let state = std::mem::replace(
            &mut self.levels[level.0 as usize].state,
            LevelState::Unloaded,
        );
        let LevelState::Loaded { instances, meshes } = state else {
            return;
        };
        self.lod_points.remove(level.0);
        self.skinned.remove(level.0);
        ev.push(WorldEvent::LevelUnloaded { level, instances });
        for m in meshes {
            let slot = &mut self.meshes[m.0 as usize];
            slot.refs = slot.refs.saturating_sub(1);
            if slot.refs > 0 {
                continue;
            }
            // A resident proxy's landmarks still want the coarsest LOD.
            let keep_coarsest = slot.landmark_refs > 0;
            self.release_mesh(m, keep_coarsest, ev);
        }
    }

    /// Deforms every loaded skinned instance (its mesh's finest resident LOD) at `time` seconds,
    /// spread over `threads` threads. Each instance gets its own animation phase.
    pub fn skin_frame(&self, time: f32, threads: usize) -> Vec<SkinnedFrame> {
        let mut meta = Vec::new();
        let mut jobs = Vec::new();
        // The loaded skinned instances, in level order (as a walk over the levels finds them).
        let mut skinned: Vec<(u32, u32)> = self.skinned.live().copied().collect();
        skinned.sort_unstable();
        for (level, k) in skinned {
            let LevelState::Loaded { instances, .. } = &self.levels[level as usize].state else {
                continue;
            };
            let inst = &instances[k as usize];
            let slot = &self.meshes[inst.mesh.0 as usize];
            let Some(lod) = slot.finest_resident() else {
                continue;
            };
            let Some(g) = slot.resident[lod].as_deref() else {
                continue;
            };
            meta.push((inst.id, inst.mesh, lod as u8));
            jobs.push(SkinJob {
                geometry: g,
                time: crate::skin::animation_time(inst.id, time),
                positions: Vec::new(),
            });
        }
        skin_parallel(&mut jobs, threads);
        meta.into_iter()
            .zip(jobs)
            .map(|((instance, mesh, lod), j)| SkinnedFrame {
                instance,
                mesh,
                lod,
                positions: j.positions,
            })
            .collect()
    }
}

fn lod_loaded(mesh: WorldMeshId, lod: usize, lod_count: u8, g: &Arc<MeshLod>) -> WorldEvent {
    WorldEvent::MeshLodLoaded {
        mesh,
        lod: lod as u8,
        lod_count,
        error: g.error,
        geometry: Arc::clone(g),
    }
}
