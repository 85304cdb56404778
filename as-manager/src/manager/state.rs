//! The manager's tables: meshes and instances (slot vectors indexed by their ids' dense
//! indices) and BLAS entries (a `slotmap` keyed by [`EntryKey`]).

use std::sync::Arc;

use glam::Vec3;
use slotmap::SlotMap;

use crate::backend::{BlasHandle, BlasSizes};
use crate::mesh::{MeshDesc, MeshKind, MAX_LODS};
use crate::quality::RefitQuality;

slotmap::new_key_type! {
    /// A BLAS entry in [`Tables::entries`]. Dropping the entry makes its key stale: a key kept
    /// elsewhere (an instance's shown BLAS, a pending compaction) is checked, never trusted.
    pub(crate) struct EntryKey;
}

/// `InstanceHot::group` when the instance has no far-field group. A sentinel, not an
/// `Option<u32>`: the option would take 4 more bytes and push a grid entry past its cache line
/// (the residency and cull passes stream through these records; see the assert below
/// `InstanceHot`).
pub(crate) const NO_GROUP: u32 = u32::MAX;

#[derive(Debug)]
pub(crate) struct MeshState {
    pub desc: Arc<MeshDesc>,
    pub kind: MeshKind,
    pub nlods: u8,
    /// Geometric errors (mesh space), finest first; `nlods` used.
    pub errors: [f32; MAX_LODS],
    /// Triangles per LOD.
    pub lod_tris: [u32; MAX_LODS],
    /// Bit `l`: LOD `l` has data a backend can build from (`LodGeometry::is_buildable`), kept
    /// with `desc` so that `with_data` reads no LOD descriptions.
    pub buildable: u8,
    /// Static: the shared entry per LOD.
    pub lod_entry: [Option<EntryKey>; MAX_LODS],
    /// Memory fallback: finest LOD allowed now.
    pub lod_floor: u8,
    pub floor_since: u64,
    /// Live instances of this mesh (slots).
    pub instances: Vec<u32>,
    /// Some group's far-field proxy (the baselines never build it).
    pub proxy: bool,
    /// The last frame a BLAS of one of its LODs was built, compacted, released or rolled
    /// back: what a landmark waiting for its target chooses from changed (`landmarks_cull`).
    pub blas_epoch: u64,
}

impl MeshState {
    pub fn kind(&self) -> MeshKind {
        self.kind
    }

    pub fn errors(&self) -> &[f32] {
        &self.errors[..self.nlods as usize]
    }

    /// `lod` if it has data or a built BLAS, else the nearest LOD with a built BLAS (finer
    /// first: showing it costs nothing more), else the nearest with data (coarser first, then
    /// finer); any LOD when `need_data` is false. `None`: no LOD is usable.
    ///
    /// A built BLAS needs no CPU data: streaming may have evicted a LOD's data while its BLAS
    /// still serves, and ignoring it would fall back to the coarsest LOD next to the camera.
    pub fn with_data(
        &self,
        lod: usize,
        need_data: bool,
        built: impl Fn(usize) -> bool,
    ) -> Option<usize> {
        if !need_data {
            return Some(lod);
        }
        let has = |l: usize| self.buildable & (1 << l) != 0;
        if has(lod) || built(lod) {
            return Some(lod);
        }
        let n = self.nlods as usize;
        let finer_first = (0..lod).rev().chain(lod + 1..n);
        if let Some(l) = finer_first.clone().find(|&l| built(l)) {
            return Some(l);
        }
        (lod..n).chain((0..lod).rev()).find(|&l| has(l))
    }
}

/// Merges one requester's distance and view into a frame's nearest: the first of `frame`
/// replaces what an earlier frame left, later ones keep the minimum and any view.
pub(crate) fn merge_nearest(
    at: &mut u64,
    min: &mut f32,
    view: &mut bool,
    frame: u64,
    dist: f32,
    in_view: bool,
) {
    if *at != frame {
        *at = frame;
        *min = dist;
        *view = in_view;
    } else {
        *min = min.min(dist);
        *view |= in_view;
    }
}

impl BlasEntry {
    /// Requested in `frame`: a new streak unless it was requested the frame before.
    pub fn mark_request(&mut self, frame: u64) {
        if self.last_request.wrapping_add(1) < frame || self.last_request > frame {
            self.streak_start = frame;
        }
        self.last_request = frame;
    }

    /// A requester `dist` metres away (surface), in view or not, this frame (build priority and
    /// eviction order read the nearest).
    pub fn mark_distance(&mut self, frame: u64, dist: f32, in_view: bool) {
        merge_nearest(
            &mut self.dist_frame,
            &mut self.min_dist,
            &mut self.in_view,
            frame,
            dist,
            in_view,
        );
    }

    /// The BLAS address an instance record of this (built) entry names; see `address`.
    pub fn record_address(&self, backend: &impl crate::backend::AsBackend) -> u64 {
        match (self.owner, self.handle) {
            (Some(_), Some(h)) => backend.blas_address(h),
            _ => self.address,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EntryState {
    /// Known (requested/kept recently), not queued, not built.
    Idle,
    /// Waiting in the build queue.
    Queued,
    /// Built (handle valid).
    Built,
}

/// A skinned BLAS's refit bookkeeping.
#[derive(Debug, Clone)]
pub(crate) struct RefitState {
    /// Pose version last refitted or built, and the frame of it.
    pub pose_version: u64,
    pub refit_frame: u64,
    /// The quality metric at the last build, and the last refit's ratio to it.
    pub quality: Option<RefitQuality>,
    pub last_ratio: f32,
    /// Posed on the GPU: the latest quality ratio the backend measured
    /// (`AsBackend::take_refit_quality`), not yet acted on.
    pub gpu_ratio: Option<f32>,
}

#[derive(Debug)]
pub(crate) struct BlasEntry {
    pub mesh: u32,
    pub lod: u8,
    /// Its mesh is some group's far-field proxy (`MeshState::proxy`, copied here: the
    /// per-frame passes over the entries read it without the mesh's state).
    pub proxy: bool,
    /// Owning instance slot for skinned BLASes, `None` for shared static ones.
    pub owner: Option<u32>,
    pub state: EntryState,
    pub handle: Option<BlasHandle>,
    /// The BLAS device address of `handle` (0 without one), asked once per handle: the
    /// records of every instance that shows the entry name it. A static BLAS keeps its
    /// address; a skinned one may move on each refit (refit rings), so it is asked anew.
    pub address: u64,
    pub bytes: u64,
    pub sizes: BlasSizes,
    pub triangles: u32,
    /// First frame of the current consecutive request streak.
    pub streak_start: u64,
    pub last_request: u64,
    pub last_keep: u64,
    pub created: u64,
    pub last_in_tlas: Option<u64>,
    /// Nearest requesting distance seen in `dist_frame`.
    pub min_dist: f32,
    pub dist_frame: u64,
    pub in_view: bool,
    pub queued_since: u64,
    /// Static: waiting for compaction.
    pub needs_compaction: bool,
    /// Skinned: what the refits and rebuilds keep (a failed frame puts it back as it was).
    pub refit: RefitState,
    /// Seed baseline: instances holding a reference.
    pub refs: u32,
    /// Index in `Tables::active`.
    pub active_index: u32,
}

/// Per-instance state a frame touches (the hot half of an instance; [`InstanceState`] is the
/// cold half), stored in the spatial index's cells (see `spatial::GridEntry::data`) so the
/// residency and cull passes stream through memory. Its TLAS record template is apart
/// (`AsManager::templates`), read by assembly.
#[derive(Debug, Clone, Copy)]
pub(crate) struct InstanceHot {
    pub mesh: u32,
    pub scale: f32,
    /// Entry shown in the TLAS (may be stale: check it against `Tables::entries`).
    pub shown: Option<EntryKey>,
    /// Skinned: own entry for the current LOD target (may be stale).
    pub own: Option<EntryKey>,
    pub last_visit: u64,
    /// Far-field leaf group slot ([`NO_GROUP`] if none); here, in the struct's padding, so
    /// the residency pass needs no cold lookup.
    pub group: u32,
    pub lod_target: u8,
    pub culled: bool,
}

// With its centre, radius and slot, a grid entry is one cache line: the residency pass walks
// the cells near the cameras, and with the record template in the entry (two lines) it
// touched twice the memory. The templates are `AsManager::templates`.
const _: () = assert!(std::mem::size_of::<crate::spatial::GridEntry<InstanceHot>>() <= 64);

/// Per-instance state touched only on changes (and by the baselines' full passes).
#[derive(Debug)]
pub(crate) struct InstanceState {
    /// The generation of the `InstanceId` it was added with (a stale id names an older one).
    pub generation: u32,
    pub mesh: u32,
    /// Index in the mesh's instance list.
    pub mesh_pos: u32,
    pub center: Vec3,
    pub radius: f32,
    pub pose: Option<Arc<Vec<[f32; 3]>>>,
    /// The pose in the engine's GPU buffer (`set_skinned_pose_device`); excludes `pose`.
    pub device_pose: Option<crate::mesh::DeviceVertices>,
    pub pose_version: u64,
    /// Seed baseline marks.
    pub seed_request: Option<u64>,
    pub seed_keep: Option<u64>,
    pub seed_has: bool,
}

#[derive(Debug, Default)]
pub(crate) struct Tables {
    pub meshes: Vec<Option<MeshState>>,
    pub instances: Vec<Option<InstanceState>>,
    /// BLAS entries. A removed entry's slot is reused last-freed-first, as the hand-written
    /// free list before it did, so the decisions (which break ties by key) did not change.
    pub entries: SlotMap<EntryKey, BlasEntry>,
    /// Live entries in the order the passes visit them (`BlasEntry::active_index` is each
    /// one's place; removal swaps the last one in). Not `entries`' own order: that is slot
    /// order, and the passes' decisions depend on this one.
    pub active: Vec<EntryKey>,
    /// The meshes whose LODs' data or BLASes changed, for the landmark set.
    pub mesh_log: MeshLog,
}

/// Meshes whose LOD data or BLASes changed (registered, a LOD's data replaced, removed; a BLAS
/// built, compacted, released or rolled back), kept for the landmark set's two steps while it
/// is active. What its pairs resolve to and which BLAS address they show change only so: each
/// step looks at the pairs of the meshes logged since it last ran instead of at every pair
/// every frame (about 260 pairs in the default world, each scan 1 µs of the far field's
/// frame; `docs/PROFILE.md`, "The pair scans by event").
#[derive(Debug, Default)]
pub(crate) struct MeshLog {
    on: bool,
    /// For the residency step (which selections' resolution changed), and whether it looks
    /// at every pair instead (just started, or the log overflowed).
    resolve: Vec<u32>,
    resolve_all: bool,
    /// For the cull step (which shown BLAS addresses changed).
    cull: Vec<u32>,
    cull_all: bool,
}

/// Log entries a step may have waiting before it looks at every pair instead (a frame that
/// registers or changes thousands of meshes).
const MESH_LOG_CAP: usize = 4096;

/// Which pairs a step of the landmark set looks at.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Logged {
    /// Every pair.
    All,
    /// The pairs of these meshes (sorted, each once).
    Meshes,
}

impl MeshLog {
    /// The landmark set is active: log from now on (its steps look at every pair once).
    pub fn start(&mut self) {
        if !self.on {
            self.on = true;
            self.resolve_all = true;
            self.cull_all = true;
        }
    }

    /// The landmark set is inactive: nothing to log.
    pub fn stop(&mut self) {
        *self = Self::default();
    }

    pub fn note(&mut self, mesh: u32) {
        if !self.on {
            return;
        }
        for (list, all) in [
            (&mut self.resolve, &mut self.resolve_all),
            (&mut self.cull, &mut self.cull_all),
        ] {
            if *all {
                continue;
            }
            if list.len() >= MESH_LOG_CAP {
                list.clear();
                *all = true;
            } else {
                list.push(mesh);
            }
        }
    }

    /// The residency step's meshes into `out` (cleared first), and whether it looks at all.
    pub fn take_resolve(&mut self, out: &mut Vec<u32>) -> Logged {
        Self::take(&mut self.resolve, &mut self.resolve_all, out)
    }

    /// The cull step's meshes into `out` (cleared first), and whether it looks at all.
    pub fn take_cull(&mut self, out: &mut Vec<u32>) -> Logged {
        Self::take(&mut self.cull, &mut self.cull_all, out)
    }

    fn take(list: &mut Vec<u32>, all: &mut bool, out: &mut Vec<u32>) -> Logged {
        out.clear();
        if std::mem::take(all) {
            list.clear();
            return Logged::All;
        }
        out.append(list);
        out.sort_unstable();
        out.dedup();
        Logged::Meshes
    }
}

impl Tables {
    /// A BLAS of `key`'s mesh was built, compacted, released or rolled back in `frame`.
    pub fn blas_changed(&mut self, key: EntryKey, frame: u64) {
        let Some(e) = self.entries.get(key) else {
            return;
        };
        let mesh = e.mesh;
        if let Some(Some(m)) = self.meshes.get_mut(mesh as usize) {
            m.blas_epoch = frame;
        }
        self.mesh_log.note(mesh);
    }

    /// The entry of a mesh's LOD (`None`: none yet, or the mesh is gone).
    pub fn lod_entry(&self, mesh: u32, lod: u8) -> Option<EntryKey> {
        self.meshes
            .get(mesh as usize)?
            .as_ref()?
            .lod_entry
            .get(lod as usize)
            .copied()
            .flatten()
    }

    /// A new entry for a static mesh's LOD, recorded as that LOD's entry (`None`: the mesh is
    /// gone).
    pub fn new_lod_entry(&mut self, mesh: u32, lod: u8, frame: u64) -> Option<EntryKey> {
        let tris = self.meshes.get(mesh as usize)?.as_ref()?.lod_tris[lod as usize];
        let key = self.new_entry(mesh, lod, None, tris, frame);
        self.meshes[mesh as usize]
            .as_mut()
            .expect("live mesh")
            .lod_entry[lod as usize] = Some(key);
        Some(key)
    }

    /// Whether `key` names a live, built entry.
    pub fn built(&self, key: Option<EntryKey>) -> bool {
        key.and_then(|k| self.entries.get(k))
            .is_some_and(|e| e.state == EntryState::Built)
    }

    pub fn new_entry(
        &mut self,
        mesh: u32,
        lod: u8,
        owner: Option<u32>,
        triangles: u32,
        frame: u64,
    ) -> EntryKey {
        let active_index = self.active.len() as u32;
        let proxy = matches!(self.meshes.get(mesh as usize), Some(Some(m)) if m.proxy);
        let key = self.entries.insert(BlasEntry {
            mesh,
            lod,
            proxy,
            owner,
            state: EntryState::Idle,
            handle: None,
            address: 0,
            bytes: 0,
            sizes: BlasSizes::default(),
            triangles,
            streak_start: frame,
            last_request: frame,
            last_keep: frame,
            created: frame,
            last_in_tlas: None,
            min_dist: f32::INFINITY,
            dist_frame: frame,
            in_view: false,
            queued_since: frame,
            needs_compaction: false,
            refit: RefitState {
                pose_version: 0,
                refit_frame: frame,
                quality: None,
                last_ratio: 1.0,
                gpu_ratio: None,
            },
            refs: 0,
            active_index,
        });
        self.active.push(key);
        key
    }

    /// The BLAS an instance of `mesh` (slot `mesh_ix`) shows: its `target` if built, else what
    /// it `shown` until now if that is still built (and of this mesh), else (static) the
    /// nearest built LOD to `target_lod`, coarser first, so nothing goes missing while a finer
    /// LOD builds.
    pub fn choose_shown(
        &self,
        mesh: &MeshState,
        mesh_ix: u32,
        target: Option<EntryKey>,
        target_lod: usize,
        shown: Option<EntryKey>,
    ) -> Option<EntryKey> {
        if self.built(target) {
            target
        } else if self.built(shown) && shown.is_some_and(|k| self.entries[k].mesh == mesh_ix) {
            shown
        } else if mesh.kind == MeshKind::Static {
            let n = mesh.nlods as usize;
            (target_lod..n)
                .chain((0..target_lod).rev())
                .map(|l| mesh.lod_entry[l])
                .find(|&k| self.built(k))
                .flatten()
        } else {
            None
        }
    }

    /// Drops a non-built entry (the caller freed any handle first) and unlinks it.
    pub fn drop_entry(&mut self, key: EntryKey) {
        let e = self.entries.remove(key).expect("live entry");
        debug_assert!(e.handle.is_none());
        let ai = e.active_index;
        self.active.swap_remove(ai as usize);
        if let Some(&moved) = self.active.get(ai as usize) {
            self.entries[moved].active_index = ai;
        }
        if e.owner.is_none() {
            if let Some(Some(m)) = self.meshes.get_mut(e.mesh as usize) {
                if m.lod_entry[e.lod as usize] == Some(key) {
                    m.lod_entry[e.lod as usize] = None;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dropped_entry_goes_stale_and_leaves_the_active_list() {
        let mut tables = Tables::default();
        let a = tables.new_entry(0, 0, None, 12, 1);
        let b = tables.new_entry(0, 1, Some(3), 12, 1);
        assert!(!tables.built(Some(a)) && !tables.built(None));
        tables.entries[a].state = EntryState::Built;
        assert!(tables.built(Some(a)));
        tables.entries[a].state = EntryState::Idle;
        tables.drop_entry(a);
        assert!(!tables.entries.contains_key(a));
        assert_eq!(tables.active, vec![b]);
        assert_eq!(tables.entries[b].active_index, 0);
        // The slot comes back under a new key: the old one never aliases the new entry.
        let c = tables.new_entry(0, 0, None, 12, 2);
        assert_ne!(a, c);
        tables.entries[c].state = EntryState::Built;
        assert!(!tables.built(Some(a)) && tables.built(Some(c)));
        assert_eq!(tables.active, vec![b, c]);
    }
}
