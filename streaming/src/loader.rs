//! The loader thread pool: jobs in, results out, over crossbeam channels.
//!
//! Loader threads only read files and decode/validate them; they own no world state, so the
//! world (on the thread calling `World::update`) stays the single writer and orders every event.
//! Each job runs under `catch_unwind`: a bug in a decoder (ours or a dependency's) on a hostile
//! file becomes a [`StreamingError::LoaderPanic`] result and the thread takes the next job.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Weak};
use std::thread::JoinHandle;

use crossbeam::channel::{Receiver, Sender};
use glam::Mat4;

use crate::bake::{Manifest, MESH_LIBRARY_FILE};
use crate::error::{Result, StreamingError};
use crate::format;
use crate::gltf_import::load_gltf;
use crate::lod::build_lod_chain;
use crate::model::{Aabb, Level, LevelId, MaterialClass, MeshLod, Motion, WorldMeshId};

/// Where a level's content comes from.
#[derive(Debug, Clone)]
pub(crate) enum LevelSource {
    /// A baked level file.
    Baked(PathBuf),
    /// A glTF 2.0 file placed by a transform.
    Gltf { path: PathBuf, transform: Mat4 },
}

#[derive(Debug)]
pub(crate) enum Job {
    Level {
        level: LevelId,
        ticket: u64,
        source: LevelSource,
    },
    Lod {
        mesh: WorldMeshId,
        lod: usize,
        ticket: u64,
    },
}

/// A mesh decoded from a glTF level: its LOD chain and local bounds.
#[derive(Debug)]
pub(crate) struct GltfMesh {
    pub name: String,
    pub bounds: Aabb,
    pub lods: Vec<Arc<MeshLod>>,
}

/// An instance of a glTF level, before the world assigns ids.
#[derive(Debug)]
pub(crate) struct GltfInstance {
    pub mesh: usize,
    pub transform: Mat4,
    pub material: MaterialClass,
    pub motion: Motion,
}

#[derive(Debug)]
pub(crate) enum LoadedLevel {
    Baked {
        level: Level,
        /// Coarsest LOD of every distinct mesh the level uses (or why it failed).
        coarse: Vec<(WorldMeshId, usize, Result<Arc<MeshLod>>)>,
    },
    Gltf {
        meshes: Vec<GltfMesh>,
        instances: Vec<GltfInstance>,
    },
}

#[derive(Debug)]
pub(crate) enum Done {
    Level {
        level: LevelId,
        ticket: u64,
        result: Result<LoadedLevel>,
    },
    Lod {
        mesh: WorldMeshId,
        lod: usize,
        ticket: u64,
        result: Result<Arc<MeshLod>>,
    },
}

impl Done {
    /// The ticket of the job this answers.
    pub fn ticket(&self) -> u64 {
        match self {
            Done::Level { ticket, .. } | Done::Lod { ticket, .. } => *ticket,
        }
    }
}

/// What the loader threads share (read-only, but for the LOD cache and the counters).
#[derive(Debug)]
pub(crate) struct LoaderShared {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub mesh_bounds: Vec<Aabb>,
    /// Test-only faults: the next loads of these levels fail (see `World::inject_load_fault`).
    pub faults: parking_lot::Mutex<Vec<(LevelId, LoadFault, u32)>>,
    /// Each baked mesh's LODs as last read, while anyone (the world, a BLAS manager) still
    /// holds them: see [`shared_lod`].
    pub lods: LodCache,
}

/// A weak reference per (mesh, LOD) read from the mesh library, by mesh id (a lock each).
#[derive(Debug, Default)]
pub(crate) struct LodCache {
    meshes: Vec<parking_lot::Mutex<Vec<Weak<MeshLod>>>>,
    /// LOD reads from the file, and loads answered from a LOD still held.
    pub reads: AtomicU64,
    pub shared: AtomicU64,
}

impl LodCache {
    pub fn new(manifest: &Manifest) -> Self {
        Self {
            meshes: manifest
                .meshes
                .iter()
                .map(|m| parking_lot::Mutex::new((0..m.lods.len()).map(|_| Weak::new()).collect()))
                .collect(),
            ..Self::default()
        }
    }
}

/// A fault for the next loads of a level (tests of the retry path; see
/// [`World::inject_load_fault`](crate::World::inject_load_fault)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoadFault {
    /// Reading the level file fails with an I/O error.
    ReadError,
    /// The decoder panics (caught on the loader thread and reported as
    /// [`StreamingError::LoaderPanic`]).
    Panic,
}

impl LoaderShared {
    fn lib_path(&self) -> PathBuf {
        self.dir.join(MESH_LIBRARY_FILE)
    }
}

/// The pool. Dropping it closes the job channel and joins the threads.
#[derive(Debug)]
pub(crate) struct LoaderPool {
    jobs: Option<Sender<Job>>,
    pub results: Receiver<Done>,
    threads: Vec<JoinHandle<()>>,
}

impl LoaderPool {
    pub fn new(shared: Arc<LoaderShared>, threads: usize) -> Result<LoaderPool> {
        let (jtx, jrx) = crossbeam::channel::unbounded::<Job>();
        let (rtx, rrx) = crossbeam::channel::unbounded::<Done>();
        let mut handles = Vec::new();
        for k in 0..threads.max(1) {
            let (jrx, rtx, shared) = (jrx.clone(), rtx.clone(), Arc::clone(&shared));
            let h = std::thread::Builder::new()
                .name(format!("rtstream-loader-{k}"))
                .spawn(move || worker(&shared, &jrx, &rtx))
                .map_err(|source| StreamingError::Io {
                    path: shared_dir_hint(),
                    source,
                })?;
            handles.push(h);
        }
        Ok(LoaderPool {
            jobs: Some(jtx),
            results: rrx,
            threads: handles,
        })
    }

    pub fn submit(&self, job: Job) {
        if let Some(tx) = &self.jobs {
            // Workers only stop when this sender is dropped, so the send cannot fail while we
            // hold it; if it ever did, the job is simply not run.
            let _ = tx.send(job);
        }
    }

    /// Threads still running.
    pub fn alive(&self) -> usize {
        self.threads.iter().filter(|h| !h.is_finished()).count()
    }
}

fn shared_dir_hint() -> PathBuf {
    PathBuf::from("<loader thread>")
}

impl Drop for LoaderPool {
    fn drop(&mut self) {
        self.jobs = None;
        for h in self.threads.drain(..) {
            if h.join().is_err() {
                tracing::error!("a loader thread panicked outside a job");
            }
        }
    }
}

fn worker(shared: &LoaderShared, jobs: &Receiver<Job>, results: &Sender<Done>) {
    while let Ok(job) = jobs.recv() {
        let done = match job {
            Job::Level {
                level,
                ticket,
                source,
            } => {
                let _span = tracing::trace_span!("load_level", level = level.0).entered();
                let result = guarded(source_path(shared, &source), || {
                    load_level(shared, level, &source)
                });
                Done::Level {
                    level,
                    ticket,
                    result,
                }
            }
            Job::Lod { mesh, lod, ticket } => {
                let _span = tracing::trace_span!("load_lod", mesh = mesh.0, lod).entered();
                let result = guarded(shared.lib_path(), || shared_lod(shared, mesh, lod));
                Done::Lod {
                    mesh,
                    lod,
                    ticket,
                    result,
                }
            }
        };
        if results.send(done).is_err() {
            break; // The world is gone.
        }
    }
}

fn source_path(shared: &LoaderShared, s: &LevelSource) -> PathBuf {
    match s {
        LevelSource::Baked(p) => shared.dir.join(p),
        LevelSource::Gltf { path, .. } => path.clone(),
    }
}

fn guarded<T>(path: PathBuf, f: impl FnOnce() -> Result<T>) -> Result<T> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "non-string panic payload".into());
            Err(StreamingError::LoaderPanic { path, message })
        }
    }
}

fn load_level(shared: &LoaderShared, level: LevelId, source: &LevelSource) -> Result<LoadedLevel> {
    let fault = {
        let mut faults = shared.faults.lock();
        faults
            .iter_mut()
            .find(|f| f.0 == level && f.2 > 0)
            .map(|f| {
                f.2 -= 1;
                f.1
            })
    };
    match fault {
        Some(LoadFault::ReadError) => {
            return Err(StreamingError::Io {
                path: source_path(shared, source),
                source: std::io::Error::other("injected read fault"),
            })
        }
        Some(LoadFault::Panic) => panic!("injected loader panic (level {})", level.0),
        None => {}
    }
    match source {
        LevelSource::Baked(rel) => {
            let path = shared.dir.join(rel);
            let bytes = std::fs::read(&path).map_err(|source| StreamingError::Io {
                path: path.clone(),
                source,
            })?;
            let decoded = format::decode_level(&bytes, &shared.mesh_bounds).map_err(|reason| {
                StreamingError::Format {
                    path: path.clone(),
                    reason,
                }
            })?;
            if decoded.id != level {
                return Err(StreamingError::Format {
                    path,
                    reason: crate::FormatError::Inconsistent(format!(
                        "file holds level {}, manifest expects {}",
                        decoded.id.0, level.0
                    )),
                });
            }
            let mut ids: Vec<WorldMeshId> = decoded.instances.iter().map(|i| i.mesh).collect();
            ids.sort_unstable();
            ids.dedup();
            let coarse = ids
                .into_iter()
                .map(|m| {
                    let last = shared.manifest.meshes[m.0 as usize].lods.len() - 1;
                    (m, last, shared_lod(shared, m, last))
                })
                .collect();
            Ok(LoadedLevel::Baked {
                level: decoded,
                coarse,
            })
        }
        LevelSource::Gltf { path, transform } => load_gltf_level(path, transform),
    }
}

fn load_gltf_level(path: &Path, placement: &Mat4) -> Result<LoadedLevel> {
    if !placement.is_finite() {
        return Err(StreamingError::InvalidScene {
            path: path.to_owned(),
            reason: "non-finite level placement".into(),
        });
    }
    let scene = load_gltf(path)?;
    let mut materials = Vec::new();
    let mut meshes = Vec::new();
    for m in scene.meshes {
        materials.push((m.material, m.skin.is_some()));
        let bounds = Aabb::from_points(&m.positions);
        let lods = build_lod_chain(m.positions, m.indices, m.skin)
            .into_iter()
            .map(Arc::new)
            .collect();
        meshes.push(GltfMesh {
            name: m.name,
            bounds,
            lods,
        });
    }
    let instances: Vec<GltfInstance> = scene
        .instances
        .iter()
        .map(|i| GltfInstance {
            mesh: i.mesh,
            transform: *placement * i.transform,
            material: materials[i.mesh].0,
            motion: if materials[i.mesh].1 {
                Motion::Skinned
            } else {
                Motion::Static
            },
        })
        .collect();
    // A finite placement can still overflow f32 once applied (a scale of 1e38): the level's
    // instances and bounds would be infinite or NaN.
    let overflows = instances.iter().any(|i| {
        let placed = crate::Instance::new(
            crate::WorldInstanceId(0),
            crate::WorldMeshId(0),
            i.transform,
            &meshes[i.mesh].bounds,
            i.material,
            i.motion,
        );
        let (b, s) = (placed.aabb, placed.sphere);
        !(i.transform.is_finite()
            && (b.max - b.min).is_finite()
            && s.center.is_finite()
            && s.radius.is_finite()
            && placed.max_scale().is_finite())
    });
    if overflows {
        return Err(StreamingError::InvalidScene {
            path: path.to_owned(),
            reason: "the level placement takes its instances past f32's range".into(),
        });
    }
    Ok(LoadedLevel::Gltf { meshes, instances })
}

/// One LOD of a baked mesh: the one read last if anyone still holds it, else read from the
/// mesh library. A level load brings the coarsest LOD of each of its meshes, and most are
/// resident already (shared by the levels around): reading and decoding them again cost the
/// loaders a file open and a decode each, and the world's thread then freed the copy, memory
/// that another thread's allocator arena had handed out (`docs/PROFILE.md`, "The bridge's id
/// table and the loaders' shared LODs"). Two loaders that miss at once both read; either copy
/// is the file's.
pub(crate) fn shared_lod(
    shared: &LoaderShared,
    mesh: WorldMeshId,
    lod: usize,
) -> Result<Arc<MeshLod>> {
    let cell = shared.lods.meshes.get(mesh.0 as usize);
    if let Some(held) = cell.and_then(|c| c.lock().get(lod).and_then(Weak::upgrade)) {
        shared.lods.shared.fetch_add(1, Ordering::Relaxed);
        return Ok(held);
    }
    let g = Arc::new(read_lod(shared, mesh, lod)?);
    shared.lods.reads.fetch_add(1, Ordering::Relaxed);
    if let Some(c) = cell {
        if let Some(w) = c.lock().get_mut(lod) {
            *w = Arc::downgrade(&g);
        }
    }
    Ok(g)
}

/// Reads one LOD chunk from the mesh library.
pub(crate) fn read_lod(shared: &LoaderShared, mesh: WorldMeshId, lod: usize) -> Result<MeshLod> {
    let path = shared.lib_path();
    let entry = shared
        .manifest
        .meshes
        .get(mesh.0 as usize)
        .and_then(|m| m.lods.get(lod))
        .ok_or_else(|| StreamingError::Format {
            path: path.clone(),
            reason: crate::FormatError::Inconsistent(format!(
                "no mesh {} LOD {lod} in the index",
                mesh.0
            )),
        })?;
    let io = |source| StreamingError::Io {
        path: path.clone(),
        source,
    };
    let mut f = File::open(&path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    if entry.offset.saturating_add(entry.len) > len {
        return Err(StreamingError::Format {
            path: path.clone(),
            reason: crate::FormatError::Truncated {
                offset: entry.offset as usize,
                needed: entry.len as usize,
                available: len.saturating_sub(entry.offset) as usize,
            },
        });
    }
    f.seek(SeekFrom::Start(entry.offset)).map_err(io)?;
    let mut buf = vec![0u8; entry.len as usize];
    f.read_exact(&mut buf).map_err(io)?;
    // Meshes that share a LOD (a district's copies, `WorldPreset::districts`) name one chunk,
    // written once: the chunk names the first of them in the index.
    let owner = shared.manifest.meshes[..=mesh.0 as usize]
        .iter()
        .position(|m| {
            m.lods
                .get(lod)
                .is_some_and(|l| l.offset == entry.offset && l.len == entry.len)
        })
        .map_or(mesh, |i| WorldMeshId(i as u32));
    format::decode_lod(&buf, owner, lod).map_err(|reason| StreamingError::Format { path, reason })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panicking_job_becomes_an_error_naming_the_file() {
        let r: Result<()> = guarded(PathBuf::from("levels/000042.rtl"), || panic!("decoder bug"));
        match r {
            Err(StreamingError::LoaderPanic { path, message }) => {
                assert_eq!(path, PathBuf::from("levels/000042.rtl"));
                assert!(message.contains("decoder bug"));
            }
            other => panic!("expected LoaderPanic, got {other:?}"),
        }
    }

    #[test]
    fn pool_threads_survive_failing_jobs() {
        let shared = Arc::new(LoaderShared {
            dir: std::env::temp_dir().join("rtstream-no-such-world"),
            manifest: Manifest {
                extent: Aabb::EMPTY,
                levels: Vec::new(),
                meshes: Vec::new(),
            },
            mesh_bounds: Vec::new(),
            faults: parking_lot::Mutex::new(Vec::new()),
            lods: LodCache::default(),
        });
        let pool = LoaderPool::new(shared, 2).expect("pool");
        for k in 0..20 {
            pool.submit(Job::Level {
                level: LevelId(k),
                ticket: u64::from(k),
                source: LevelSource::Baked(PathBuf::from(format!("missing{k}.rtl"))),
            });
            pool.submit(Job::Lod {
                mesh: WorldMeshId(k),
                lod: 0,
                ticket: 0,
            });
        }
        for _ in 0..40 {
            let done = pool
                .results
                .recv_timeout(std::time::Duration::from_secs(10))
                .expect("result");
            match done {
                Done::Level { result, .. } => assert!(result.is_err()),
                Done::Lod { result, .. } => assert!(result.is_err()),
            }
        }
        assert_eq!(pool.alive(), 2);
    }
}
