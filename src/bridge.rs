//! `WorldBridge`: streaming's [`WorldEvent`]s into the BLAS manager's registration API.
//!
//! The two crates do not know each other; this is the wiring an engine would write for its own
//! streaming:
//! - A mesh is registered on its first `MeshLodLoaded` with its whole LOD chain: counts and
//!   errors from the baked world's manifest ([`Manifest`]) for every LOD, [`LodGeometry::Data`]
//!   for the LOD that arrived. Later `MeshLodLoaded`/`MeshLodEvicted` swap one LOD's geometry
//!   between `Data` and `Counts` (`AsManager::set_lod_geometry`), so a GPU backend only builds
//!   from resident data. Skinned meshes (those with skin weights) register as
//!   [`MeshKind::Skinned`].
//! - `LevelLoaded`: every [`MaterialClass::Opaque`] instance gets a manager instance (others are
//!   not BLAS-eligible: counted, skipped) whose customIndex is a stable slot handed out here
//!   and recycled on `LevelUnloaded`. The slot indexes the shading table ([`ShadingSlot`]).
//! - Far landmarks: a `ProxyLoaded` leaf lists its large static instances (see
//!   `rtstream_streaming::proxy`). Those whose level is not loaded are placed at once (their
//!   mesh registered, else as soon as it is: streaming loads the coarsest LOD of a resident
//!   proxy's landmark meshes), so the manager can keep them as far landmarks
//!   beside the proxy. When the level loads, the same instance (same id) is already placed and
//!   stays; when it unloads, the instance stays while its proxy is resident; `ProxyEvicted`
//!   removes those no loaded level holds.
//! - `LoadFailed`: logged (`tracing::warn!`) and counted; nothing to undo.
//! - Skinned poses: [`WorldBridge::pose_skinned`] takes [`World::skin_frame`]'s positions when
//!   they are of the LOD the manager builds the instance at, and otherwise skins that LOD itself
//!   (same animation phase), so a refit never gets a pose of another vertex count.
//! - Shading: [`WorldBridge::shading`] turns the frame's TLAS records into the renderer's
//!   per-customIndex table; geometry addresses come from the backend per BLAS address.
//!
//! Why one file over 600 lines: `WorldBridge` is one state machine over streaming's events (meshes,
//! instances, slots, proxies, skinned poses and the shading table share its slot and mesh maps),
//! and each handler is short; splitting it by event would scatter that shared state's invariants
//! across files.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use rustc_hash::{FxHashMap, FxHashSet};

use glam::{Affine3A, Vec3};
use rtstream_as_manager::backend::AsBackend;
use rtstream_as_manager::record::TlasInstance;
use rtstream_as_manager::{
    AsManager, GroupId, InstanceDesc, InstanceId, LodDesc, LodGeometry, MeshData, MeshDesc, MeshId,
    MeshKind, RecordChanges,
};
use rtstream_renderer::{InstanceShading, ShadingUpdate};
use rtstream_streaming::{
    Aabb, Instance, LevelId, Manifest, MaterialClass, MeshLod, Motion, ProxyId, ProxyTree, World,
    WorldEvent, WorldInstanceId, WorldMeshId,
};

/// What the renderer needs of one customIndex.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadingSlot {
    /// The streaming instance (for a far-field proxy: none, see `proxy`).
    pub instance: WorldInstanceId,
    /// The far-field proxy node this slot shades, if it is one (it stands for many instances).
    pub proxy: Option<ProxyId>,
    /// Its level.
    pub level: LevelId,
    /// Its mesh.
    pub mesh: WorldMeshId,
    /// Linear RGBA base colour.
    pub base_color: [f32; 4],
}

/// Counters of what the bridge did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BridgeStats {
    /// Meshes registered with the manager.
    pub meshes: usize,
    /// Manager instances live now.
    pub instances: usize,
    /// Instances skipped because their material is not BLAS-eligible.
    pub skipped_not_opaque: usize,
    /// `LoadFailed` events seen.
    pub load_failures: usize,
    /// Registration calls the manager rejected (logged).
    pub rejected: usize,
    /// LOD geometry swaps (data in or out).
    pub lod_swaps: usize,
    /// Meshes unregistered because nothing of them was resident or placed any more.
    pub meshes_released: usize,
    /// Instances placed now from a resident proxy's landmark list with their level not loaded.
    pub far_landmarks: usize,
}

#[derive(Debug)]
struct MeshSlot {
    id: MeshId,
    skinned: bool,
    /// Resident streaming geometry per LOD.
    resident: Vec<Option<Arc<MeshLod>>>,
    /// Counts per LOD (for eviction back to counts).
    counts: Vec<(u32, u32)>,
    color: [f32; 4],
    /// Instances of it placed in the manager.
    placed: u32,
}

/// A placed streaming instance, at its slot (customIndex) in `WorldBridge::placed`.
#[derive(Debug, Clone, Copy)]
struct Placed {
    id: InstanceId,
    mesh: WorldMeshId,
    skinned: bool,
    transform: glam::Mat4,
    center: Vec3,
    /// Placed from a proxy's landmark list; no loaded level holds it.
    far: bool,
}

/// Applies [`WorldEvent`]s to an [`AsManager`]; see the module docs.
#[derive(Debug, Default)]
pub struct WorldBridge {
    manifest_meshes: Vec<rtstream_streaming::bake::MeshEntry>,
    meshes: FxHashMap<WorldMeshId, MeshSlot>,
    /// By slot (customIndex); `None` for free slots and proxies' slots.
    placed: Vec<Option<Placed>>,
    /// The slot of each placed streaming instance.
    slot_of: IdTable,
    placed_count: usize,
    slots: Vec<Option<ShadingSlot>>,
    free_slots: Vec<u32>,
    /// The slots assigned or cleared, in order (what a [`ShadingTable`] catches up on).
    slot_log: SlotLog,
    stats: BridgeStats,
    counts_only: bool,
    /// Far field: the manager group of each proxy node, its level's leaf, and each node's
    /// proxy mesh while resident.
    groups: Vec<Option<GroupId>>,
    level_leaf: Vec<Option<ProxyId>>,
    proxy_meshes: FxHashMap<ProxyId, MeshId>,
    proxy_errors: Vec<f32>,
    proxy_bounds: Vec<Aabb>,
    /// Each resident leaf's landmark list, and each listed instance's leaf.
    proxy_landmarks: FxHashMap<ProxyId, Arc<[(LevelId, Instance)]>>,
    landmark_leaf: IdTable,
    /// Landmarks waiting for their mesh's registration (its first resident LOD).
    pending_landmarks: FxHashMap<WorldMeshId, Vec<(WorldInstanceId, u32)>>,
}

/// A `u32` per streaming instance id (a placed instance's slot, a listed landmark's proxy
/// leaf): a table indexed by id for the ids a baked world hands out (dense from 0), a map for
/// the rest (glTF levels' ids count from 2^31). At 10x density about 350,000 instances are
/// placed at once and thousands come and go a frame: in a map of every placed instance each
/// placement or removal was a probe into a table of tens of MB, and the map's growth rehashed
/// it on the frame path (frames of up to 98 ms early in a lavapipe run); the table costs one
/// read or write of four bytes.
#[derive(Debug, Default)]
struct IdTable {
    dense: Vec<u32>,
    sparse: FxHashMap<WorldInstanceId, u32>,
}

impl IdTable {
    /// Ids below this go to the table (64 MB at most); a baked world's ids are below its
    /// instance count.
    const DENSE_IDS: u32 = 1 << 24;
    const NONE: u32 = u32::MAX;

    fn get(&self, id: WorldInstanceId) -> Option<u32> {
        if id.0 < Self::DENSE_IDS {
            let s = *self.dense.get(id.0 as usize)?;
            (s != Self::NONE).then_some(s)
        } else {
            self.sparse.get(&id).copied()
        }
    }

    fn insert(&mut self, id: WorldInstanceId, value: u32) {
        debug_assert_ne!(value, Self::NONE, "u32::MAX marks a vacant id");
        if id.0 < Self::DENSE_IDS {
            let i = id.0 as usize;
            if i >= self.dense.len() {
                self.reserve(i + 1);
            }
            self.dense[i] = value;
        } else {
            self.sparse.insert(id, value);
        }
    }

    fn remove(&mut self, id: WorldInstanceId) -> Option<u32> {
        if id.0 < Self::DENSE_IDS {
            let s = self.dense.get_mut(id.0 as usize)?;
            let old = std::mem::replace(s, Self::NONE);
            (old != Self::NONE).then_some(old)
        } else {
            self.sparse.remove(&id)
        }
    }

    /// Room for the ids below `ids` (to the next power of two, within `DENSE_IDS`).
    fn reserve(&mut self, ids: usize) {
        let len = ids
            .next_power_of_two()
            .min(Self::DENSE_IDS as usize)
            .max(ids.min(Self::DENSE_IDS as usize));
        if len > self.dense.len() {
            self.dense.resize(len, Self::NONE);
        }
    }
}

/// The base colour of far-field proxies (they merge terrain and buildings).
pub const PROXY_COLOR: [f32; 4] = [0.42, 0.46, 0.38, 1.0];

/// The base colour every image of a mesh uses (managed frames and the ground truth alike, so
/// colour metrics compare like with like): terrain green, other meshes a stable muted colour.
pub fn mesh_color(mesh: WorldMeshId, name: &str) -> [f32; 4] {
    let n = name.to_ascii_lowercase();
    if n.contains("terrain") || n.contains("ground") {
        return [0.32, 0.42, 0.22, 1.0];
    }
    // A stable, muted colour per mesh.
    let mut h = (mesh.0 as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut c = [0.0; 3];
    for v in &mut c {
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        *v = 0.35 + 0.5 * ((h >> 40) as f32 / (1u64 << 24) as f32);
    }
    [c[0], c[1], c[2], 1.0]
}

/// A resident streamed LOD as the manager's mesh data: the same `Arc`, no copy, so CPU
/// geometry is counted once (in streaming's budget) and freed when both let go.
#[derive(Debug)]
struct StreamedLod(Arc<MeshLod>);

impl MeshData for StreamedLod {
    fn positions(&self) -> &[[f32; 3]] {
        &self.0.positions
    }
    fn indices(&self) -> &[u32] {
        &self.0.indices
    }
}

fn data_of(g: &Arc<MeshLod>) -> LodGeometry {
    LodGeometry::Data(Arc::new(StreamedLod(Arc::clone(g))))
}

impl WorldBridge {
    /// A bridge for a baked world: its manifest gives every mesh's LOD chain up front.
    /// Without one (`None`, e.g. [`World::empty`] with glTF levels) the LODs not yet seen are
    /// estimated from the ones that arrive.
    pub fn new(manifest: Option<&Manifest>) -> Self {
        Self {
            manifest_meshes: manifest.map(|m| m.meshes.clone()).unwrap_or_default(),
            ..Self::default()
        }
    }

    /// Registers the world's far-field proxy tree as manager groups (parents first), so that
    /// placed instances name their leaf and `ProxyLoaded` events give groups their proxies.
    /// Without it the bridge ignores proxies (the baselines' bridges).
    pub fn register_proxy_tree<B: AsBackend>(&mut self, m: &AsManager<B>, tree: &ProxyTree) {
        self.groups = vec![None; tree.nodes.len()];
        self.proxy_errors = tree.nodes.iter().map(|n| n.error).collect();
        self.proxy_bounds = tree.nodes.iter().map(|n| n.bounds).collect();
        self.level_leaf = tree.leaf_of_level.clone();
        // Leaves first in the tree: parents are registered before their children here.
        for n in tree.nodes.iter().rev() {
            let parent = n.parent.and_then(|p| self.groups[p.0 as usize]);
            let slot = self.free_slots.pop().unwrap_or(self.slots.len() as u32);
            let desc = rtstream_as_manager::GroupDesc {
                parent,
                bounds_min: n.bounds.min.to_array(),
                bounds_max: n.bounds.max.to_array(),
                custom_index: slot,
                mask: 0xff,
            };
            match m.register_group(desc) {
                Ok(g) => {
                    if self.slots.len() <= slot as usize {
                        self.slots.resize(slot as usize + 1, None);
                    }
                    self.slot_log.push(slot);
                    self.slots[slot as usize] = Some(ShadingSlot {
                        instance: WorldInstanceId(u32::MAX),
                        proxy: Some(n.id),
                        level: LevelId(u32::MAX),
                        mesh: WorldMeshId(u32::MAX),
                        base_color: PROXY_COLOR,
                    });
                    self.groups[n.id.0 as usize] = Some(g);
                }
                Err(e) => {
                    self.free_slots.push(slot);
                    self.reject("group", e);
                }
            }
        }
    }

    fn proxy_loaded<B: AsBackend>(&mut self, m: &AsManager<B>, node: ProxyId, g: &Arc<MeshLod>) {
        let Some(Some(group)) = self.groups.get(node.0 as usize).copied() else {
            return; // no proxy tree registered: ignore
        };
        let b = self.proxy_bounds[node.0 as usize];
        let centre = (b.min + b.max) * 0.5;
        let radius = ((b.max - b.min).length() * 0.5).max(1e-3);
        let mut desc = MeshDesc::new(
            format!("proxy{}", node.0),
            MeshKind::Static,
            radius,
            vec![LodDesc {
                geometry: self.geometry_of(g),
                geometric_error: 0.0,
            }],
        );
        desc.bounds_center = centre.to_array();
        let error = self.proxy_errors[node.0 as usize];
        match m.register_mesh(desc) {
            Ok(mesh) => match m.set_group_proxy(group, Some((mesh, error))) {
                Ok(()) => {
                    self.proxy_meshes.insert(node, mesh);
                }
                Err(e) => self.reject("group proxy", e),
            },
            Err(e) => self.reject("proxy mesh", e),
        }
    }

    /// Places a resident leaf's landmarks whose level is not loaded (see the module docs).
    fn landmarks_loaded<B: AsBackend>(
        &mut self,
        m: &AsManager<B>,
        node: ProxyId,
        landmarks: &Arc<[(LevelId, Instance)]>,
    ) {
        if landmarks.is_empty() || self.groups.get(node.0 as usize).is_none() {
            return; // nothing listed, or no proxy tree registered
        }
        self.proxy_landmarks.insert(node, Arc::clone(landmarks));
        for (at, (level, inst)) in landmarks.iter().enumerate() {
            self.landmark_leaf.insert(inst.id, node.0);
            self.place_landmark(m, *level, inst, at as u32);
        }
    }

    /// Places a listed landmark (`at`: its place in its leaf's list), or keeps it for when
    /// its mesh registers.
    fn place_landmark<B: AsBackend>(
        &mut self,
        m: &AsManager<B>,
        level: LevelId,
        inst: &Instance,
        at: u32,
    ) {
        if self.slot_of.get(inst.id).is_some() {
            return; // its level is loaded: placed already
        }
        if !self.meshes.contains_key(&inst.mesh) {
            self.pending_landmarks
                .entry(inst.mesh)
                .or_default()
                .push((inst.id, at));
            return;
        }
        self.place(m, level, inst, true);
    }

    /// Places the landmarks that waited for `mesh` (now registered) and are still listed.
    fn place_pending_landmarks<B: AsBackend>(&mut self, m: &AsManager<B>, mesh: WorldMeshId) {
        let Some(ids) = self.pending_landmarks.remove(&mesh) else {
            return;
        };
        for (id, at) in ids {
            // Where it was listed; the leaf's list may have been loaded again since.
            let Some((level, inst, at)) = self
                .landmark_leaf
                .get(id)
                .and_then(|n| self.proxy_landmarks.get(&ProxyId(n)))
                .and_then(|list| match list.get(at as usize) {
                    Some(&(level, inst)) if inst.id == id => Some((level, inst, at)),
                    _ => list
                        .iter()
                        .position(|(_, i)| i.id == id)
                        .map(|k| (list[k].0, list[k].1, k as u32)),
                })
            else {
                continue; // its proxy left meanwhile
            };
            self.place_landmark(m, level, &inst, at);
        }
    }

    fn proxy_evicted<B: AsBackend>(&mut self, m: &AsManager<B>, node: ProxyId) {
        if let Some(list) = self.proxy_landmarks.remove(&node) {
            for (_, inst) in list.iter() {
                self.landmark_leaf.remove(inst.id);
                if self.placed_ref(inst.id).is_some_and(|p| p.far) {
                    self.remove_placed(m, inst.id);
                }
            }
        }
        let Some(mesh) = self.proxy_meshes.remove(&node) else {
            return;
        };
        if let Some(Some(group)) = self.groups.get(node.0 as usize).copied() {
            if let Err(e) = m.set_group_proxy(group, None) {
                self.reject("group proxy removal", e);
            }
        }
        if let Err(e) = m.unregister_mesh(mesh) {
            self.reject("proxy mesh removal", e);
        }
    }

    /// Registers counts only, never data (for the model backend: no copies of the geometry).
    pub fn counts_only(mut self) -> Self {
        self.counts_only = true;
        self
    }

    fn geometry_of(&self, g: &Arc<MeshLod>) -> LodGeometry {
        if self.counts_only {
            LodGeometry::Counts {
                vertices: g.positions.len() as u32,
                triangles: g.triangle_count() as u32,
            }
        } else {
            data_of(g)
        }
    }

    /// Counters so far.
    pub fn stats(&self) -> BridgeStats {
        BridgeStats {
            meshes: self.meshes.len(),
            instances: self.placed_count,
            far_landmarks: self.placed.iter().flatten().filter(|p| p.far).count(),
            ..self.stats
        }
    }

    /// The customIndex range in use (one past the highest slot ever given out).
    pub fn slot_count(&self) -> u32 {
        self.slots.len() as u32
    }

    /// The shading slot of `custom_index`, if one is live.
    pub fn slot(&self, custom_index: u32) -> Option<&ShadingSlot> {
        self.slots.get(custom_index as usize)?.as_ref()
    }

    /// The manager instance of a streaming instance, if placed.
    pub fn manager_instance(&self, id: WorldInstanceId) -> Option<InstanceId> {
        self.placed_ref(id).map(|p| p.id)
    }

    /// Applies events in order. Rejected registrations are logged and counted, never fatal.
    pub fn apply<B: AsBackend>(&mut self, m: &AsManager<B>, events: &[WorldEvent]) {
        for ev in events {
            match ev {
                WorldEvent::MeshLodLoaded {
                    mesh,
                    lod,
                    lod_count,
                    error,
                    geometry,
                } => self.lod_loaded(
                    m,
                    *mesh,
                    *lod as usize,
                    *lod_count as usize,
                    *error,
                    geometry,
                ),
                WorldEvent::MeshLodEvicted { mesh, lod } => {
                    self.lod_evicted(m, *mesh, *lod as usize)
                }
                WorldEvent::LevelLoaded {
                    level, instances, ..
                } => {
                    for inst in instances.iter() {
                        self.place(m, *level, inst, false);
                    }
                }
                WorldEvent::LevelUnloaded { instances, .. } => {
                    for inst in instances.iter() {
                        self.unplace(m, inst.id);
                    }
                }
                WorldEvent::ProxyLoaded {
                    node,
                    geometry,
                    landmarks,
                } => {
                    self.proxy_loaded(m, *node, geometry);
                    self.landmarks_loaded(m, *node, landmarks);
                }
                WorldEvent::ProxyEvicted { node } => self.proxy_evicted(m, *node),
                WorldEvent::LoadFailed {
                    level, mesh, error, ..
                } => {
                    self.stats.load_failures += 1;
                    tracing::warn!(?level, ?mesh, %error, "load failed; the world carries on");
                }
            }
        }
    }

    fn reject(&mut self, what: &str, e: rtstream_as_manager::AsError) {
        self.stats.rejected += 1;
        tracing::warn!(%e, "manager rejected {what}");
    }

    fn lod_loaded<B: AsBackend>(
        &mut self,
        m: &AsManager<B>,
        mesh: WorldMeshId,
        lod: usize,
        lod_count: usize,
        error: f32,
        g: &Arc<MeshLod>,
    ) {
        if let Some(slot) = self.meshes.get_mut(&mesh) {
            if lod >= slot.resident.len() {
                return;
            }
            slot.resident[lod] = Some(g.clone());
            // The LOD's real triangle count and error replace the guesses made before it
            // was seen (a world without a manifest).
            slot.counts[lod] = (g.positions.len() as u32, g.triangle_count() as u32);
            let id = slot.id;
            self.stats.lod_swaps += 1;
            let desc = LodDesc {
                geometry: self.geometry_of(g),
                geometric_error: error,
            };
            if let Err(e) = m.set_lod(id, lod, desc) {
                self.reject("LOD geometry", e);
            }
            return;
        }
        let skinned = g.skin.is_some();
        let entry = self
            .manifest_meshes
            .get(mesh.0 as usize)
            .filter(|e| e.id == mesh);
        let (bounds, name) = match entry {
            Some(e) => (e.bounds, e.name.clone()),
            None => (Aabb::from_points(&g.positions), format!("mesh{}", mesh.0)),
        };
        let n = entry.map_or(lod_count, |e| e.lods.len()).max(lod + 1);
        let tri_here = g.triangle_count() as u32;
        let vert_here = g.positions.len() as u32;
        let mut counts = Vec::with_capacity(n);
        let mut lods = Vec::with_capacity(n);
        let mut prev_err = 0.0f32;
        for l in 0..n {
            let (tris, verts, err) = match entry.and_then(|e| e.lods.get(l)) {
                Some(le) => {
                    let per_vertex = if skinned { 36 } else { 12 };
                    let v = (le.bytes as u64).saturating_sub(le.triangles as u64 * 12) / per_vertex;
                    (le.triangles.max(1), (v as u32).max(3), le.error)
                }
                None => {
                    // Estimate: triangles halve per LOD, errors double from the known one.
                    let shift = l as i32 - lod as i32;
                    let f = 2f32.powi(-shift);
                    let tris = ((tri_here as f32 * f) as u32).max(1);
                    let verts = ((vert_here as f32 * f) as u32).max(3);
                    let err = if l < lod {
                        error * l as f32 / lod as f32
                    } else {
                        error / f
                    };
                    (tris, verts, err)
                }
            };
            let err = if l == lod { error } else { err }.max(prev_err);
            prev_err = err;
            counts.push((verts, tris));
            let geometry = if l == lod {
                self.geometry_of(g)
            } else {
                LodGeometry::Counts {
                    vertices: verts,
                    triangles: tris,
                }
            };
            lods.push(LodDesc {
                geometry,
                geometric_error: err,
            });
        }
        let center = (bounds.min + bounds.max) * 0.5;
        let radius = ((bounds.max - bounds.min).length() * 0.5).max(1e-3);
        let kind = if skinned {
            MeshKind::Skinned
        } else {
            MeshKind::Static
        };
        let mut desc = MeshDesc::new(name.clone(), kind, radius, lods);
        desc.bounds_center = center.to_array();
        match m.register_mesh(desc) {
            Ok(id) => {
                let mut resident = vec![None; n];
                resident[lod] = Some(g.clone());
                self.meshes.insert(
                    mesh,
                    MeshSlot {
                        id,
                        skinned,
                        resident,
                        counts,
                        color: mesh_color(mesh, &name),
                        placed: 0,
                    },
                );
                self.place_pending_landmarks(m, mesh);
            }
            Err(e) => self.reject("mesh", e),
        }
    }

    fn lod_evicted<B: AsBackend>(&mut self, m: &AsManager<B>, mesh: WorldMeshId, lod: usize) {
        let Some(slot) = self.meshes.get_mut(&mesh) else {
            return;
        };
        let Some(r) = slot.resident.get_mut(lod) else {
            return;
        };
        *r = None;
        let (vertices, triangles) = slot.counts[lod];
        let id = slot.id;
        self.stats.lod_swaps += 1;
        if self.release_if_unused(m, mesh) {
            return;
        }
        if self.counts_only {
            return;
        }
        if let Err(e) = m.set_lod_geometry(
            id,
            lod,
            LodGeometry::Counts {
                vertices,
                triangles,
            },
        ) {
            self.reject("LOD eviction", e);
        }
    }

    /// Places `inst` of `level`; `far`: from a proxy's landmark list (no loaded level holds
    /// it). A landmark placed earlier becomes its level's when the level loads.
    fn place<B: AsBackend>(
        &mut self,
        m: &AsManager<B>,
        level: LevelId,
        inst: &Instance,
        far: bool,
    ) {
        if inst.material != MaterialClass::Opaque {
            self.stats.skipped_not_opaque += 1;
            return;
        }
        if let Some(p) = self.placed_mut(inst.id) {
            p.far &= far;
            return;
        }
        let Some(mesh) = self.meshes.get(&inst.mesh) else {
            // Its mesh failed to load (LoadFailed was logged): nothing to place.
            self.stats.rejected += 1;
            return;
        };
        let slot = self.free_slots.pop().unwrap_or(self.slots.len() as u32);
        debug_assert!(slot < 1 << 24, "customIndex fits in 24 bits");
        let mut desc = InstanceDesc::new(mesh.id, Affine3A::from_mat4(inst.transform));
        desc.custom_index = slot;
        // Static instances join their level's far-field leaf (skinned ones never do).
        if inst.motion == Motion::Static {
            desc.group = self
                .level_leaf
                .get(level.0 as usize)
                .copied()
                .flatten()
                .and_then(|leaf| self.groups.get(leaf.0 as usize).copied().flatten());
        }
        let (color, skinned) = (mesh.color, mesh.skinned);
        match m.add_instance(desc) {
            Ok(id) => {
                if let Some(ms) = self.meshes.get_mut(&inst.mesh) {
                    ms.placed += 1;
                }
                if self.slots.len() <= slot as usize {
                    self.slots.resize(slot as usize + 1, None);
                }
                self.slot_log.push(slot);
                self.slots[slot as usize] = Some(ShadingSlot {
                    instance: inst.id,
                    proxy: None,
                    level,
                    mesh: inst.mesh,
                    base_color: color,
                });
                if self.placed.len() <= slot as usize {
                    self.placed.resize(slot as usize + 1, None);
                }
                self.placed[slot as usize] = Some(Placed {
                    id,
                    mesh: inst.mesh,
                    skinned: skinned && inst.motion == Motion::Skinned,
                    transform: inst.transform,
                    center: inst.sphere.center,
                    far,
                });
                self.slot_of.insert(inst.id, slot);
                self.placed_count += 1;
            }
            Err(e) => {
                self.free_slots.push(slot);
                self.reject("instance", e);
            }
        }
    }

    /// Its level unloaded: removes the instance, unless a resident proxy lists it as a
    /// landmark (then it stays, placed from the proxy).
    fn unplace<B: AsBackend>(&mut self, m: &AsManager<B>, id: WorldInstanceId) {
        if self.landmark_leaf.get(id).is_some() {
            if let Some(p) = self.placed_mut(id) {
                p.far = true;
                return;
            }
        }
        self.remove_placed(m, id);
    }

    fn remove_placed<B: AsBackend>(&mut self, m: &AsManager<B>, id: WorldInstanceId) {
        let Some(slot) = self.slot_of.remove(id) else {
            return;
        };
        let p = self.placed[slot as usize]
            .take()
            .expect("a placed instance's slot holds it");
        self.placed_count -= 1;
        if let Err(e) = m.remove_instance(p.id) {
            self.reject("instance removal", e);
        }
        self.slots[slot as usize] = None;
        self.slot_log.push(slot);
        self.free_slots.push(slot);
        if let Some(ms) = self.meshes.get_mut(&p.mesh) {
            ms.placed = ms.placed.saturating_sub(1);
        }
        self.release_if_unused(m, p.mesh);
    }

    /// Unregisters a mesh from the manager once no LOD of it is resident and no instance of
    /// it is placed (its BLASes go with it); the next `MeshLodLoaded` registers it again.
    fn release_if_unused<B: AsBackend>(&mut self, m: &AsManager<B>, mesh: WorldMeshId) -> bool {
        let unused = self
            .meshes
            .get(&mesh)
            .is_some_and(|s| s.placed == 0 && s.resident.iter().all(Option::is_none));
        if !unused {
            return false;
        }
        let slot = self.meshes.remove(&mesh).expect("checked above");
        if let Err(e) = m.unregister_mesh(slot.id) {
            self.reject("mesh removal", e);
        }
        self.stats.meshes_released += 1;
        true
    }

    /// The manager's id of a streamed mesh, while registered.
    pub fn manager_mesh(&self, mesh: WorldMeshId) -> Option<MeshId> {
        self.meshes.get(&mesh).map(|s| s.id)
    }

    /// Meshes registered in the manager now.
    pub fn registered_meshes(&self) -> usize {
        self.meshes.len()
    }

    /// Sends this frame's poses of skinned instances to the manager (see the module docs).
    /// Returns how many poses were sent.
    pub fn pose_skinned<B: AsBackend>(
        &self,
        m: &AsManager<B>,
        world: &World,
        time: f32,
        threads: usize,
    ) -> usize {
        let mut sent = 0;
        let mut scratch = Vec::new();
        for f in world.skin_frame(time, threads) {
            let Some(p) = self.placed_ref(f.instance).filter(|p| p.skinned) else {
                continue;
            };
            let lod = m.instance_lod(p.id).unwrap_or(f.lod as usize);
            let positions = if lod == f.lod as usize {
                f.positions
            } else {
                // Skin the LOD the manager builds at, with the world's phase for this instance.
                let Some(g) = self
                    .meshes
                    .get(&p.mesh)
                    .and_then(|s| s.resident.get(lod)?.clone())
                else {
                    continue;
                };
                let Some(skin) = &g.skin else { continue };
                let t = rtstream_streaming::skin::animation_time(f.instance, time);
                rtstream_streaming::skin::skin_positions(&g, &skin.skeleton.pose(t), &mut scratch);
                std::mem::take(&mut scratch)
            };
            if m.set_skinned_pose(p.id, Arc::new(positions)).is_ok() {
                sent += 1;
            }
        }
        sent
    }

    /// The renderer's shading table for a frame's records, indexed by customIndex:
    /// base colours from the slots, geometry addresses from `geometry(blas_address)` (e.g.
    /// `VulkanBackend::shading_geometry`). Entries without a record get zero addresses.
    /// A fresh table each call; a frame loop keeps a [`ShadingTable`] instead, which costs
    /// the frame's records rather than every slot.
    pub fn shading(
        &self,
        records: &[TlasInstance],
        geometry: impl Fn(u64) -> Option<(u64, u64)>,
    ) -> Vec<InstanceShading> {
        let mut table: Vec<InstanceShading> = self
            .slots
            .iter()
            .map(|s| InstanceShading::colour_only(s.map_or(UNSHADED, |s| s.base_color)))
            .collect();
        if table.is_empty() {
            table.push(InstanceShading::colour_only(UNSHADED));
        }
        for r in records {
            let ci = r.custom_index_and_mask & 0x00ff_ffff;
            if let Some(e) = table.get_mut(ci as usize) {
                *e = entry(self, ci, geometry(r.blas_address));
            }
        }
        table
    }

    /// The placed instances whose centre lies within `radius` of `at`: (customIndex, mesh,
    /// transform), for reference scenes.
    pub fn placed_within(&self, at: Vec3, radius: f32) -> Vec<(u32, WorldMeshId, glam::Mat4)> {
        // By slot: in customIndex order.
        self.placed
            .iter()
            .enumerate()
            .filter_map(|(slot, p)| Some((slot as u32, p.as_ref()?)))
            .filter(|(_, p)| p.center.distance(at) <= radius)
            .map(|(slot, p)| (slot, p.mesh, p.transform))
            .collect()
    }

    /// Room for the streaming instance ids below `ids` (a baked world's instance count), so
    /// that no placement grows the bridge's id table on the frame path. Optional: it grows
    /// as needed (what grows with the instances placed at once, by doubling, is the table by
    /// slot).
    pub fn reserve_instances(&mut self, ids: usize) {
        self.slot_of.reserve(ids);
        self.landmark_leaf.reserve(ids);
    }

    fn placed_ref(&self, id: WorldInstanceId) -> Option<&Placed> {
        self.placed[self.slot_of.get(id)? as usize].as_ref()
    }

    fn placed_mut(&mut self, id: WorldInstanceId) -> Option<&mut Placed> {
        let slot = self.slot_of.get(id)?;
        self.placed[slot as usize].as_mut()
    }

    /// The finest LOD of `mesh` resident now.
    pub fn finest_resident(&self, mesh: WorldMeshId) -> Option<Arc<MeshLod>> {
        self.meshes
            .get(&mesh)?
            .resident
            .iter()
            .flatten()
            .next()
            .cloned()
    }
}

/// The colour of a shading entry no live slot names.
const UNSHADED: [f32; 4] = [0.5, 0.5, 0.5, 1.0];

/// The slots a bridge assigned or cleared, in order, for readers that catch up
/// ([`ShadingTable`]). Bounded: at [`SlotLog::MAX`] entries it drops the older half, and a
/// reader behind that point starts over (it re-reads every slot its records name).
#[derive(Debug)]
struct SlotLog {
    /// Which bridge's log (so a reader never mixes two bridges).
    id: u64,
    /// Entries dropped so far: `entries[i]` is change number `dropped + i`.
    dropped: u64,
    entries: Vec<u32>,
}

impl Default for SlotLog {
    fn default() -> Self {
        static NEXT_ID: AtomicU64 = AtomicU64::new(1);
        Self {
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            dropped: 0,
            entries: Vec::new(),
        }
    }
}

impl SlotLog {
    /// Changes it holds at most (a reader reads every frame; a level loads a few thousand).
    const MAX: usize = 1 << 18;

    fn push(&mut self, slot: u32) {
        if self.entries.len() >= Self::MAX {
            // The older half goes: a reader that read within the newer half (one that reads
            // every frame) keeps reading only what changed.
            let half = Self::MAX / 2;
            self.dropped += half as u64;
            self.entries.drain(..half);
        }
        self.entries.push(slot);
    }

    /// The position after the last change.
    fn end(&self) -> (u64, u64) {
        (self.id, self.dropped + self.entries.len() as u64)
    }

    /// The changes since `from` (a position of this log), or None when they were dropped or
    /// `from` is another log's.
    fn since(&self, from: (u64, u64)) -> Option<&[u32]> {
        let (id, at) = from;
        if id != self.id || at < self.dropped {
            return None;
        }
        self.entries.get((at - self.dropped) as usize..)
    }
}

/// A shading table kept from frame to frame ([`WorldBridge::shading`] for a frame loop).
///
/// The renderer reads an entry only for a customIndex the traced TLAS holds, so an update
/// writes just the entries its records name, and resets those no record names any more
/// (colour-only, zero addresses, as [`WorldBridge::shading`] leaves them). Most records
/// stand where they stood in the last update's list, with the same customIndex and BLAS
/// (the landmarks' records stay put while they show the same BLAS), so an update looks only
/// at the records that changed, at those whose slot the bridge reassigned since, and at
/// those whose BLAS's geometry answer changed (it asks `geometry` once per BLAS address the
/// records name): a frame costs what changed, not its records. With hundreds of thousands of
/// loaded instances and a TLAS a quarter of that, rebuilding the table every frame was the
/// largest cost on the fly-through's frame path outside `update`.
///
/// Each [`update`](Self::update) also lists the entries whose value it changed, so the
/// renderer writes only those into a frame's instance buffer
/// ([`Renderer::record_update`](rtstream_renderer::Renderer::record_update)).
#[derive(Debug)]
pub struct ShadingTable {
    table: Vec<InstanceShading>,
    /// The last update's records, by position: (customIndex, BLAS address).
    prev: Vec<(u32, u64)>,
    /// Per entry, the records naming it in `prev`.
    refs: Vec<u32>,
    /// Per BLAS address `prev` names: its geometry answer then, and the records naming it.
    geometry: FxHashMap<u64, (Option<(u64, u64)>, u32)>,
    /// Where the bridge's slot log stood at the last update (None: never updated).
    log_at: Option<(u64, u64)>,
    /// Entries the last update changed (below the previous table's length).
    changed: Vec<u32>,
    /// Scratch: entries a record left, addresses and slots to look at again, records that
    /// left a position (with their count) and records that came to one.
    left: Vec<u32>,
    moved: FxHashMap<(u32, u64), u32>,
    came: Vec<(u32, u64)>,
    stale_addresses: FxHashSet<u64>,
    /// The slots the bridge reassigned since the last update (from its log, repeats
    /// included), and per slot the serial of the last update that found it so.
    stale_slots: Vec<u32>,
    stale_at: Vec<u32>,
    id: u64,
    serial: u64,
    /// The frame of the records of the last update, when it had `RecordChanges`.
    seen: Option<u64>,
    /// The `RecordChanges::stable` of the records of the last update (0 without).
    prev_stable: usize,
    /// Scratch for `update_changes`: the last update's records it looks at, whether each
    /// was paired, and per customIndex (update serial, index into the first).
    tail: Vec<(u32, u64)>,
    paired: Vec<bool>,
    marks: Vec<(u32, u32)>,
    /// Scratch for `stale_beyond`: per stale slot and address, the listed records naming it.
    stale_counts: (FxHashMap<u32, u32>, FxHashMap<u64, u32>),
    full: bool,
    full_updates: u64,
}

/// A new table identity ([`ShadingUpdate::table_id`]).
fn next_table_id() -> u64 {
    static NEXT_ID: AtomicU64 = AtomicU64::new(1);
    NEXT_ID.fetch_add(1, Ordering::Relaxed)
}

impl Default for ShadingTable {
    fn default() -> Self {
        Self {
            table: Vec::new(),
            prev: Vec::new(),
            refs: Vec::new(),
            geometry: FxHashMap::default(),
            log_at: None,
            changed: Vec::new(),
            left: Vec::new(),
            moved: FxHashMap::default(),
            came: Vec::new(),
            stale_addresses: FxHashSet::default(),
            stale_slots: Vec::new(),
            stale_at: Vec::new(),
            id: next_table_id(),
            serial: 0,
            seen: None,
            prev_stable: 0,
            tail: Vec::new(),
            paired: Vec::new(),
            marks: Vec::new(),
            stale_counts: Default::default(),
            full: false,
            full_updates: 0,
        }
    }
}

impl ShadingTable {
    /// The table for `records` (one frame's, with `geometry` as in [`WorldBridge::shading`]),
    /// with the entries it changed since the previous update. On the entries the records
    /// name the table equals `bridge.shading(records, geometry)`; every other entry has zero
    /// addresses. Use one table with one bridge; another bridge's update starts over (every
    /// record is looked at), as does the first. Looks at every record; a frame loop that
    /// has the manager's [`RecordChanges`] passes them to
    /// [`update_changes`](Self::update_changes) instead.
    pub fn update(
        &mut self,
        bridge: &WorldBridge,
        records: &[TlasInstance],
        geometry: impl Fn(u64) -> Option<(u64, u64)>,
    ) -> ShadingUpdate<'_> {
        self.update_changes(bridge, records, None, geometry)
    }

    /// [`update`](Self::update) for the records of an `update` whose [`RecordChanges`] are
    /// `changes` (`AsManager::record_changes`): when they compare with the records this
    /// table saw last, it looks only at the records they list and at those from their
    /// `stable` index on (at 10x density about a sixth of the records), not at every record.
    /// The table is the same either way. It looks at every record when `changes` is `None`
    /// or compares with other records (the table missed an update), and when a slot the
    /// bridge reassigned or a BLAS whose geometry answer changed is named by a record the
    /// changes do not list ([`ShadingTable::full_updates`] counts those updates).
    pub fn update_changes(
        &mut self,
        bridge: &WorldBridge,
        records: &[TlasInstance],
        changes: Option<RecordChanges<'_>>,
        geometry: impl Fn(u64) -> Option<(u64, u64)>,
    ) -> ShadingUpdate<'_> {
        self.serial += 1;
        self.changed.clear();
        let prev_len = self.table.len();
        // One entry per customIndex the bridge gave out (at least one, as `shading` gives).
        // The bridge's slots only grow; should they shrink, the table starts over.
        let len = bridge.slots.len().max(1);
        let log = self.log_at.and_then(|at| bridge.slot_log.since(at));
        let all = log.is_none() || len < prev_len;
        if len < prev_len {
            // A new table to the renderer: it writes the whole of it.
            self.id = next_table_id();
            self.table.clear();
            self.prev.clear();
            self.refs.clear();
            self.geometry.clear();
        }
        self.table
            .resize(len, InstanceShading::colour_only(UNSHADED));
        self.refs.resize(len, 0);
        self.stale_slots.clear();
        self.stale_slots.extend(log.unwrap_or_default());
        self.stale_at.resize(len, 0);
        // (A serial that wrapped to an old mark only makes a slot look stale: its entry is
        // written again, never left wrong.)
        let stamp = self.serial as u32;
        for &ci in &self.stale_slots {
            if let Some(at) = self.stale_at.get_mut(ci as usize) {
                *at = stamp;
            }
        }
        self.log_at = Some(bridge.slot_log.end());
        // The geometry answers for the addresses the last records named.
        self.stale_addresses.clear();
        for (&addr, (g, _)) in self.geometry.iter_mut() {
            let now = geometry(addr);
            if now != *g {
                *g = now;
                self.stale_addresses.insert(addr);
            }
        }
        let seen = std::mem::replace(&mut self.seen, changes.map(|c| c.frame));
        let listed =
            changes.filter(|c| !all && c.since.is_some() && c.since == seen && c.is_well_formed());
        let listed = listed.filter(|c| !self.stale_beyond(c));
        // The records against the last update's, position by position: a record equal to
        // the one it replaces (same customIndex and BLAS, neither slot nor geometry changed
        // since) changes nothing. The others moved, came or left; a moved one (its key left
        // one position and came to another) changes nothing either, and only what came or
        // left for good touches the table. With `listed`, the positions it does not list
        // hold the records they held (and are fresh: `stale_beyond`).
        let mut prev = std::mem::take(&mut self.prev);
        let mut moved = std::mem::take(&mut self.moved);
        moved.clear();
        let mut came = std::mem::take(&mut self.came);
        came.clear();
        let old_len = prev.len();
        // A record of the last update (`old`) against one of this update (`new`) at the same
        // place: equal and fresh, nothing to do.
        let mut pair = |this: &mut Self, old: Option<(u32, u64)>, new: Option<(u32, u64)>| {
            if old == new && new.is_some_and(|k| this.fresh(all, k)) {
                return;
            }
            if let Some(k) = old {
                if this.fresh(all, k) {
                    *moved.entry(k).or_insert(0) += 1;
                } else {
                    this.leave(k);
                }
            }
            if let Some(k) = new {
                came.push(k);
            }
        };
        match listed {
            Some(c) => {
                // The landmarks' block (below `stable`) keeps its places: its listed places
                // are looked at, this update's record against the last's. The rest (near
                // records and proxies, after the block, whose length changes) is rebuilt
                // every frame. The last update's records at those places are paired with
                // this update's by customIndex through `marks` (one record per customIndex
                // as a rule); what that leaves unpaired goes through `moved` as above.
                self.full = false;
                let (os, ns) = (self.prev_stable.min(old_len), c.stable.min(records.len()));
                let listed = || {
                    // (Increasing: `is_well_formed`.)
                    c.changed
                        .iter()
                        .map(|&i| i as usize)
                        .take_while(move |&i| i < ns)
                };
                let mut olds = std::mem::take(&mut self.tail);
                olds.clear();
                // A listed place past the last block held a near record: in the tail.
                olds.extend(listed().filter(|&i| i < os).map(|i| prev[i]));
                olds.extend_from_slice(&prev[ns.min(os)..]);
                if self.marks.len() < self.table.len() {
                    self.marks.resize(self.table.len(), (0, 0));
                }
                let stamp = self.serial as u32;
                if stamp == 0 {
                    // Wrapped: no mark may look current.
                    self.marks.iter_mut().for_each(|m| *m = (0, 0));
                }
                let mut paired = std::mem::take(&mut self.paired);
                paired.clear();
                paired.resize(olds.len(), false);
                for (o, &(ci, _)) in olds.iter().enumerate() {
                    if let Some(m) = self.marks.get_mut(ci as usize) {
                        if m.0 != stamp {
                            *m = (stamp, o as u32);
                        }
                    }
                }
                prev.resize(records.len().max(old_len), (0, 0));
                let mut take = |this: &mut Self, k: (u32, u64)| {
                    let m = this.marks.get(k.0 as usize).copied().unwrap_or((0, 0));
                    let o = m.1 as usize;
                    if m.0 == stamp && olds[o] == k && !paired[o] {
                        paired[o] = true;
                        pair(this, Some(k), Some(k));
                    } else {
                        pair(this, None, Some(k));
                    }
                };
                for i in listed() {
                    let k = shading_key(&records[i]);
                    take(self, k);
                    prev[i] = k;
                }
                for (i, r) in records.iter().enumerate().skip(ns) {
                    let k = shading_key(r);
                    take(self, k);
                    prev[i] = k;
                }
                for (o, &k) in olds.iter().enumerate() {
                    if !paired[o] {
                        pair(self, Some(k), None);
                    }
                }
                self.paired = paired;
                self.tail = olds;
                self.prev_stable = ns;
            }
            None => {
                self.full = true;
                self.full_updates += 1;
                let end = records.len().max(old_len);
                prev.resize(end, (0, 0));
                for (i, p) in prev.iter_mut().enumerate() {
                    let new = records.get(i).map(shading_key);
                    pair(self, (i < old_len).then_some(*p), new);
                    if let Some(k) = new {
                        *p = k;
                    }
                }
                self.prev_stable = changes.map_or(0, |c| c.stable.min(records.len()));
            }
        }
        for &k in &came {
            match moved.get_mut(&k) {
                Some(n) if *n > 0 && self.fresh(all, k) => *n -= 1,
                _ => self.come(bridge, k, prev_len, &geometry),
            }
        }
        for (&k, &n) in &moved {
            for _ in 0..n {
                self.leave(k);
            }
        }
        prev.truncate(records.len());
        self.moved = moved;
        self.came = came;
        self.prev = prev;
        // Named before, by no record now: back to colour-only.
        let mut left = std::mem::take(&mut self.left);
        for &ci in &left {
            let i = ci as usize;
            if self.refs[i] > 0 {
                continue;
            }
            let reset = InstanceShading::colour_only(UNSHADED);
            if self.table[i] != reset {
                self.table[i] = reset;
                if i < prev_len {
                    self.changed.push(ci);
                }
            }
        }
        left.clear();
        self.left = left;
        ShadingUpdate {
            table: &self.table,
            changed: &self.changed,
            table_id: self.id,
            serial: self.serial,
        }
    }

    /// Updates that looked at every record (the first, those without usable
    /// [`RecordChanges`], and those that found a stale record the changes do not list).
    pub fn full_updates(&self) -> u64 {
        self.full_updates
    }

    /// Whether the last update looked at every record.
    pub fn last_update_was_full(&self) -> bool {
        self.full
    }

    /// Whether a record neither moved nor stale since the last update (`all`: every record
    /// is to be looked at again).
    fn fresh(&self, all: bool, (ci, addr): (u32, u64)) -> bool {
        !all && !self.is_stale_slot(ci)
            && (self.stale_addresses.is_empty() || !self.stale_addresses.contains(&addr))
    }

    /// Whether the bridge reassigned slot `ci` since the last update.
    fn is_stale_slot(&self, ci: u32) -> bool {
        self.stale_at
            .get(ci as usize)
            .is_some_and(|&at| at == self.serial as u32)
    }

    /// Whether a record at a position `changes` does not list may be stale: the last
    /// records named a reassigned slot or a BLAS whose geometry answer changed more often
    /// than the listed positions held them.
    fn stale_beyond(&mut self, changes: &RecordChanges<'_>) -> bool {
        if self.stale_slots.is_empty() && self.stale_addresses.is_empty() {
            return false;
        }
        let (mut slots, mut addresses) = std::mem::take(&mut self.stale_counts);
        slots.clear();
        addresses.clear();
        // The last records an update with `changes` looks at: the listed places of both
        // blocks, and everything past the shorter block.
        let from = changes.stable.min(self.prev_stable).min(self.prev.len());
        let listed = changes.changed.iter().map(|&i| i as usize);
        let listed = listed
            .take_while(|&i| i < from)
            .chain(from..self.prev.len());
        for i in listed {
            let (ci, addr) = self.prev[i];
            if self.is_stale_slot(ci) {
                *slots.entry(ci).or_insert(0) += 1;
            }
            if !self.stale_addresses.is_empty() && self.stale_addresses.contains(&addr) {
                *addresses.entry(addr).or_insert(0) += 1;
            }
        }
        let named = |n: Option<&u32>| n.copied().unwrap_or(0);
        let beyond = self.stale_slots.iter().any(|&ci| {
            let refs = self.refs.get(ci as usize).copied().unwrap_or(0);
            refs > named(slots.get(&ci))
        }) || self.stale_addresses.iter().any(|&addr| {
            let refs = self.geometry.get(&addr).map_or(0, |g| g.1);
            refs > named(addresses.get(&addr))
        });
        self.stale_counts = (slots, addresses);
        beyond
    }

    /// A record of the last update that no record of this one pairs with.
    fn leave(&mut self, (ci, addr): (u32, u64)) {
        if let Some(r) = self.refs.get_mut(ci as usize) {
            *r -= 1;
            if *r == 0 {
                self.left.push(ci);
            }
        }
        if let Some(g) = self.geometry.get_mut(&addr) {
            g.1 -= 1;
            if g.1 == 0 {
                self.geometry.remove(&addr);
            }
        }
    }

    /// A record of this update that pairs with none of the last: its entry, written.
    fn come(
        &mut self,
        bridge: &WorldBridge,
        (ci, addr): (u32, u64),
        prev_len: usize,
        geometry: &impl Fn(u64) -> Option<(u64, u64)>,
    ) {
        let g = match self.geometry.get_mut(&addr) {
            Some(g) => {
                g.1 += 1;
                g.0
            }
            None => {
                let g = geometry(addr);
                self.geometry.insert(addr, (g, 1));
                g
            }
        };
        let Some(e) = self.table.get_mut(ci as usize) else {
            return;
        };
        self.refs[ci as usize] += 1;
        let value = entry(bridge, ci, g);
        if *e != value {
            *e = value;
            if (ci as usize) < prev_len {
                self.changed.push(ci);
            }
        }
    }
}

/// What a shading table keeps of a record: its customIndex and BLAS address.
fn shading_key(r: &TlasInstance) -> (u32, u64) {
    (r.custom_index(), r.blas_address)
}

/// The shading entry of customIndex `ci` for a record whose BLAS has geometry `g`: its
/// slot's colour and the BLAS's vertex and index addresses.
fn entry(bridge: &WorldBridge, ci: u32, g: Option<(u64, u64)>) -> InstanceShading {
    let colour = bridge
        .slots
        .get(ci as usize)
        .and_then(|s| s.as_ref())
        .map_or(UNSHADED, |s| s.base_color);
    let mut e = InstanceShading::colour_only(colour);
    if let Some((v, i)) = g {
        e.vertices = v;
        e.indices = i;
    }
    e
}
