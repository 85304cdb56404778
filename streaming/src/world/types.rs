//! The world's public types: stream foci, streaming parameters, events and counters.

use std::sync::Arc;

use glam::Vec3;

use crate::error::StreamingError;
use crate::model::{Aabb, Instance, LevelId, MeshLod, WorldInstanceId, WorldMeshId};
use crate::proxy::ProxyId;

/// A point that drives streaming (usually a camera's position): levels, LODs and far-field
/// proxies are loaded by their distance to the nearest focus. Not the manager's `Viewpoint` (which
/// also carries a view direction) nor the renderer's `Camera` (a pinhole with a field of view).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamFocus {
    /// World position.
    pub position: Vec3,
}

impl From<Vec3> for StreamFocus {
    fn from(position: Vec3) -> StreamFocus {
        StreamFocus { position }
    }
}

/// Streaming parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamConfig {
    /// Levels whose ground rectangle is within this distance (XZ) of a camera are loaded.
    pub load_radius: f32,
    /// Loaded levels farther than this from every camera are unloaded (> `load_radius`).
    pub unload_radius: f32,
    /// Loader threads.
    pub loader_threads: usize,
    /// CPU memory budget for mesh LOD data in bytes.
    pub mesh_budget_bytes: usize,
    /// A LOD is fine enough when its error is at most this angle (radians) x distance.
    pub lod_error_angle: f32,
    /// Hysteresis factor for evicting finer LODs (> 1; `World::open` refuses others: at 1 or
    /// below a still camera would load and evict the same LODs every frame).
    pub lod_evict_factor: f32,
    /// At most this many finer-LOD loads in flight (closer requests go first). Level loads
    /// and the far field's coarsest-LOD and proxy loads are not capped: a level within the load
    /// radius is always asked for.
    pub max_in_flight: usize,
    /// Far-field proxies within this distance (XZ, to the node's bounds) of a camera are
    /// resident; they leave beyond 1.1x it. Default: the whole map.
    pub far_radius: f32,
    /// Deterministic streaming: `Some(n)` applies every loader result exactly `n` frames after
    /// its request, in request order, waiting for the loader when it is late (`n` = 0 waits in
    /// the same frame). Frame numbers that go back count what was asked later as asked at the
    /// new number. With the same cameras per frame the event stream is then identical
    /// under any machine load. `None` (the default, for interactive runs) applies whatever has
    /// arrived and never waits.
    pub apply_after_frames: Option<u32>,
    /// A level whose load failed (I/O error, bad file, a panicking decoder) is retried this
    /// many frames later, doubling after each further failure, while a camera stays within
    /// `load_radius`.
    pub retry_after_frames: u32,
    /// Loads of a level before it stays failed (until every camera leaves `unload_radius`).
    pub max_load_attempts: u32,
}

impl Default for StreamConfig {
    fn default() -> StreamConfig {
        StreamConfig {
            load_radius: 300.0,
            unload_radius: 400.0,
            loader_threads: 2,
            mesh_budget_bytes: 256 << 20,
            lod_error_angle: 0.002,
            lod_evict_factor: 1.5,
            max_in_flight: 64,
            apply_after_frames: None,
            far_radius: f32::INFINITY,
            retry_after_frames: 8,
            max_load_attempts: 4,
        }
    }
}

impl StreamConfig {
    /// Refuses what the world cannot stream with: a LOD eviction factor that is not a number
    /// above 1. (The rest is lenient: a radius that is not a number loads nothing, an unload
    /// radius below the load radius streams with no hysteresis band, a LOD error angle of 0
    /// or less asks for the finest LODs.)
    pub fn validate(&self) -> Result<(), crate::StreamingError> {
        if !(self.lod_evict_factor > 1.0 && self.lod_evict_factor.is_finite()) {
            return Err(crate::StreamingError::InvalidConfig(format!(
                "lod_evict_factor {} (a finite number above 1)",
                self.lod_evict_factor
            )));
        }
        Ok(())
    }

    /// The default configuration but for its radii: levels load within `load_radius` of a
    /// camera and unload beyond `unload_radius`.
    pub fn within(load_radius: f32, unload_radius: f32) -> StreamConfig {
        StreamConfig {
            load_radius,
            unload_radius,
            ..StreamConfig::default()
        }
    }

    /// This configuration with a budget of `bytes` for mesh LOD data.
    pub fn with_mesh_budget(self, bytes: usize) -> StreamConfig {
        StreamConfig {
            mesh_budget_bytes: bytes,
            ..self
        }
    }
}

/// [`World::update_until_idle`](super::World::update_until_idle) ran out of time with loads
/// still in flight. Nothing is lost: the events of the frames it did run are here, and the
/// loads still in flight arrive on later updates.
#[derive(Debug, thiserror::Error)]
#[error("streaming did not settle within {waited:?}: {in_flight} loads still in flight")]
pub struct SettleTimeout {
    /// How long it waited.
    pub waited: std::time::Duration,
    /// Loads still in flight.
    pub in_flight: usize,
    /// Every event of the updates it ran.
    pub events: Vec<WorldEvent>,
}

/// What the world tells its consumer (the facade feeds these to the BLAS manager).
#[derive(Debug, Clone)]
pub enum WorldEvent {
    /// A level is in: register its instances. Their meshes' coarsest LODs were announced
    /// (by `MeshLodLoaded`) before this event or are already resident.
    LevelLoaded {
        /// The level.
        level: LevelId,
        /// Its world bounds.
        bounds: Aabb,
        /// Its instances (ids, mesh ids, transforms, bounds, material class, static/skinned).
        instances: Arc<[Instance]>,
    },
    /// A level is out: unregister these instances (the same list `LevelLoaded` gave).
    LevelUnloaded {
        /// The level.
        level: LevelId,
        /// Its instances.
        instances: Arc<[Instance]>,
    },
    /// A mesh LOD's geometry is resident.
    MeshLodLoaded {
        /// The mesh.
        mesh: WorldMeshId,
        /// LOD index (0 finest).
        lod: u8,
        /// LODs the mesh has.
        lod_count: u8,
        /// Geometric error in mesh-space metres (multiply by the instance's scale).
        error: f32,
        /// The geometry (shared; skinned meshes carry their weights and skeleton).
        geometry: Arc<MeshLod>,
    },
    /// A mesh LOD's geometry was dropped; release what was built from it.
    MeshLodEvicted {
        /// The mesh.
        mesh: WorldMeshId,
        /// LOD index.
        lod: u8,
    },
    /// A far-field proxy is resident (within [`StreamConfig::far_radius`]): register it. Its
    /// place in the quadtree is in [`World::proxy_tree`](crate::World::proxy_tree).
    ProxyLoaded {
        /// The node.
        node: ProxyId,
        /// World-space geometry (no transform to apply).
        geometry: Arc<MeshLod>,
        /// Its landmarks with their levels (leaves only; see [`crate::proxy`]): instances
        /// large enough to keep their own silhouette far away, placeable without loading
        /// their level. The same instance arrives again, with the same id, when its level
        /// loads.
        landmarks: Arc<[(LevelId, Instance)]>,
    },
    /// A proxy left the far radius: release what was built from it.
    ProxyEvicted {
        /// The node.
        node: ProxyId,
    },
    /// Something could not be loaded; the rest of the world carries on.
    LoadFailed {
        /// The level being loaded, if any.
        level: Option<LevelId>,
        /// The mesh LOD being loaded, if any.
        mesh: Option<(WorldMeshId, u8)>,
        /// The proxy being loaded, if any (the proxy file as a whole when `level`, `mesh` and
        /// `proxy` are all None).
        proxy: Option<ProxyId>,
        /// What went wrong (names the file).
        error: Arc<StreamingError>,
    },
}

/// A snapshot of the streaming state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamStats {
    /// Levels loaded.
    pub loaded_levels: usize,
    /// Levels being loaded.
    pub loading_levels: usize,
    /// Levels whose last load failed (retried with backoff, see
    /// [`StreamConfig::retry_after_frames`]).
    pub failed_levels: usize,
    /// Level loads retried after a failure, since the world opened.
    pub load_retries: u64,
    /// Instances in loaded levels.
    pub loaded_instances: usize,
    /// Mesh LODs resident.
    pub resident_lods: usize,
    /// Bytes of resident mesh LOD data.
    pub mesh_bytes: usize,
    /// Bytes of finer LODs requested but not yet arrived.
    pub in_flight_bytes: usize,
    /// Loader jobs in flight.
    pub in_flight_jobs: usize,
    /// Loader threads running.
    pub loader_threads_alive: usize,
    /// Baked mesh LODs read from the mesh library since the world opened.
    pub lod_reads: u64,
    /// LOD loads (a level's coarsest LODs, LOD streaming's finer ones) answered with the LOD
    /// read before, still held by the world or a BLAS manager: no read, no second copy.
    pub lod_reads_shared: u64,
}

/// Deformed positions of one skinned instance for one frame.
#[derive(Debug, Clone)]
pub struct SkinnedFrame {
    /// The instance.
    pub instance: WorldInstanceId,
    /// Its mesh.
    pub mesh: WorldMeshId,
    /// The LOD that was deformed (the finest resident one).
    pub lod: u8,
    /// Mesh-space positions (apply the instance transform), one per vertex of that LOD.
    pub positions: Vec<[f32; 3]>,
}
