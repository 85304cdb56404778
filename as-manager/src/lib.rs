//! # rtstream-as-manager
//!
//! Keeps bottom-level acceleration structures (BLAS) only for what the cameras can use, and
//! hands a culled top-level acceleration structure (TLAS) to the renderer each frame.
//!
//! Design choices:
//! - The policy core is plain Rust behind a narrow backend trait ([`backend::AsBackend`]);
//!   only `backend::vulkan` (cargo feature `vulkan`, on by default) touches ash. The
//!   [`backend::model::ModelBackend`] accounts sizes and costs from a fitted model
//!   ([`backend::model::SizeModel`], [`backend::model::CostModel`]) so million-instance worlds
//!   run without a GPU.
//! - A static BLAS belongs to a (mesh, LOD) pair and is shared by every instance of it; a
//!   skinned instance owns its BLAS. Residency, budgets and eviction count BLASes and bytes;
//!   culling and assembly count instances.
//! - Residency queries a uniform hash grid ([`spatial::GridIndex`]) around the cameras, so a
//!   frame's cost follows what is near the cameras, not the world's size. Only instances
//!   within r2 of a camera can be in the TLAS. Cameras share one TLAS and one query (cells
//!   deduplicated); distances are to the nearest camera.
//! - The per-instance state a frame touches (LOD target, shown BLAS, cull state and the
//!   64-byte record template) is stored in the grid cells next to the bounding sphere, so a
//!   frame streams through the cells near the cameras instead of chasing instance slots over
//!   the whole world; cold state (skinned poses, the baselines' marks) stays in a slot table.
//!   The benchmark keeps an rstar R*-tree query as the peer design; the grid is ~5x faster.
//! - BLAS entries live in a `slotmap` (generational keys: an instance's shown BLAS or a pending
//!   compaction that outlives its entry goes stale, never aliases a new one). Mesh, instance
//!   and group ids are a dense index plus a generation, allocated by hand: the grid and the
//!   tables index by the dense slot, which slotmap keys do not expose (see `ids.rs`).
//! - Registration is queued ([`Registrar`], one mutex, the only lock) and applied at the start
//!   of `update` in call order, so a frame is deterministic for a given command order.
//! - One frame: apply → residency (request within r1, keep within r2, create after
//!   CreateThreshold consecutive requested frames, release after ReleaseThreshold unkept
//!   frames and a minimum life) → LOD (projected geometric error, hysteresis, finer LOD shown
//!   only once built) → schedule (priority = distance − in-view bonus − aging; per-frame
//!   primitive and GPU-ms budget; an oversized item alone; compaction within its own budget;
//!   skinned refits oldest first, rebuilt when measured refit quality passes the bound) →
//!   memory (budget counts built, compaction copies and freed-but-in-flight bytes; coarser
//!   LOD first, then evict the farthest / least recently traced) → cull (distance and
//!   projected angle, AND/OR, near distance, hysteresis) → assemble (64-byte records, on
//!   rayon's pool when many) → backend (one batched build, refits, TLAS).
//! - The far field's landmarks (large static instances beyond r2, kept beside the proxies)
//!   are kept incrementally: a candidate is looked at again only once the cameras may have
//!   travelled across one of its thresholds (r2, the keep angle and range, its LOD's switch
//!   distances), or on an event, so their cost follows what changes, not how many there are.
//!   Their records stay at the front of the TLAS records; `AsBackend::build_tlas` is told
//!   which records are unchanged (`TlasDelta`), and the Vulkan backend writes only the others.
//! - Backend OOM caps the budget at what fitted and evicts; device lost is returned.
//! - Baselines `Naive` and `SeedR1R2` ([`PolicyKind`]) run behind the same API.
//! - tracing: a span per frame phase (`apply`, `residency`, `schedule`, `cull`, `assemble`,
//!   `record`); BLAS lifecycle events at `trace`.

//!
//! # Wiring (facade / engine)
//! - At start: `AsManager::new(config, backend)`; hand `registrar()` clones to loader threads.
//! - When a mesh's LOD chain is loaded: `register_mesh(MeshDesc { lods, kind, bounds, opaque })`
//!   (data as `Arc<GeometryData>` for a real GPU, the engine's own GPU buffers by device
//!   address as [`LodGeometry::Device`], counts for the model backend); when a level
//!   places it: `add_instance(InstanceDesc { mesh, transform, custom_index, mask, sbt_offset })`.
//!   Level unload: `remove_instance` / `unregister_mesh` (removes its instances too).
//! - Skinned instances: `set_skinned_pose(id, positions)` for the LOD `instance_lod(id)`
//!   reports (or `mark_deformed` without data), or `set_skinned_pose_device(id, vertices)`
//!   when the engine skins on the GPU (refit from its buffer, quality judged on the GPU).
//! - Each frame: `update(FrameInput { frame, cameras })` → `FrameOutput { tlas, instances,
//!   stats, changes }`; the renderer takes the TLAS from the backend (`backend()`). State kept
//!   per record across frames (a shading table) follows `changes` ([`RecordChanges`]: which
//!   records stand as in the previous successful update), not a pass over every record.

#![warn(missing_docs)]

pub mod backend;
pub mod config;
pub mod cull;
mod error;
mod ids;
pub mod lod;
mod manager;
mod mesh;
pub mod quality;
pub mod record;
pub mod spatial;
// Hidden: a fixture (synthetic worlds) for benches, tests and examples, not product API.
#[doc(hidden)]
pub mod synth;

pub use config::{
    AssemblyConfig, BuildBudget, Config, CullConfig, CullMode, FarFieldConfig, LodConfig,
    MemoryBudget, PolicyKind, ResidencyConfig,
};
pub use error::{AsError, Result};
pub use ids::{GroupId, InstanceId, MeshId};
pub use manager::{
    AsManager, FrameInput, FrameOutput, FrameStats, GroupDesc, ImageError, InstanceDesc,
    MemorySplit, RecordChanges, Registrar, SplitPart, Viewpoint,
};
pub use mesh::{
    DeviceGeometry, DeviceGeometryError, DeviceIndices, DeviceVertices, GeometryData, IndexType,
    LodDesc, LodGeometry, MeshData, MeshDesc, MeshKind, VertexFormat, MAX_LODS,
};
