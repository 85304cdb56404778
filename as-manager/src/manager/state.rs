//! The manager's tables: meshes, instances and BLAS entries (slot vectors).

use std::sync::Arc;

use glam::Vec3;

use crate::backend::{BlasHandle, BlasSizes};
use crate::mesh::{MeshDesc, MeshKind, MAX_LODS};
use crate::quality::RefitQuality;
use crate::record::TlasInstance;

pub(crate) const NONE: u32 = u32::MAX;

#[derive(Debug)]
pub(crate) struct MeshState {
    pub desc: Arc<MeshDesc>,
    pub kind: MeshKind,
    pub nlods: u8,
    /// Geometric errors (mesh space), finest first; `nlods` used.
    pub errors: [f32; MAX_LODS],
    /// Triangles per LOD.
    pub lod_tris: [u32; MAX_LODS],
    /// Static: the shared entry per LOD (NONE if none).
    pub lod_entry: [u32; MAX_LODS],
    /// Memory fallback: finest LOD allowed now.
    pub lod_floor: u8,
    pub floor_since: u64,
    /// Live instances of this mesh (slots).
    pub instances: Vec<u32>,
    /// Some group's far-field proxy (the baselines never build it).
    pub proxy: bool,
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
        let lods = &self.desc.lods;
        if !need_data {
            return Some(lod);
        }
        let has = |l: usize| lods[l].geometry.is_buildable();
        if has(lod) || built(lod) {
            return Some(lod);
        }
        let n = lods.len();
        let finer_first = (0..lod).rev().chain(lod + 1..n);
        if let Some(l) = finer_first.clone().find(|&l| built(l)) {
            return Some(l);
        }
        (lod..n).chain((0..lod).rev()).find(|&l| has(l))
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

#[derive(Debug)]
pub(crate) struct BlasEntry {
    pub live: bool,
    pub generation: u32,
    pub mesh: u32,
    pub lod: u8,
    /// Owning instance slot for skinned BLASes, NONE for shared static ones.
    pub owner: u32,
    pub state: EntryState,
    pub handle: Option<BlasHandle>,
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
    /// Skinned: pose version last refitted/built, frame of it, quality bookkeeping.
    pub pose_version: u64,
    pub refit_frame: u64,
    pub quality: Option<RefitQuality>,
    pub last_ratio: f32,
    /// Skinned, posed on the GPU: the latest quality ratio the backend measured
    /// (`AsBackend::take_refit_quality`), not yet acted on.
    pub gpu_ratio: Option<f32>,
    /// Seed baseline: instances holding a reference.
    pub refs: u32,
    /// Index in `Tables::active`.
    pub active_index: u32,
}

/// Per-instance state a frame touches, stored in the spatial index's cells (see
/// `spatial::GridEntry::data`) so the residency/cull/assembly passes stream through memory.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hot {
    /// The record with `blas_address` 0 (transform, customIndex, mask, SBT offset, flags).
    pub template: TlasInstance,
    pub mesh: u32,
    pub scale: f32,
    /// Entry shown in the TLAS (slot, generation).
    pub shown: (u32, u32),
    /// Skinned: own entry for the current LOD target (slot, generation).
    pub own: (u32, u32),
    pub last_visit: u64,
    /// Far-field leaf group slot (NONE if none); here, in the struct's padding, so the
    /// residency pass needs no cold lookup.
    pub group: u32,
    pub lod_target: u8,
    pub culled: bool,
}

const _: () = assert!(std::mem::size_of::<Hot>() <= 104);

/// Per-instance state touched only on changes (and by the baselines' full passes).
#[derive(Debug)]
pub(crate) struct InstanceState {
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
    pub entries: Vec<BlasEntry>,
    pub free_entries: Vec<u32>,
    /// Live entry slots.
    pub active: Vec<u32>,
}

impl Tables {
    pub fn entry_valid(&self, (slot, gen): (u32, u32)) -> bool {
        slot != NONE && (slot as usize) < self.entries.len() && {
            let e = &self.entries[slot as usize];
            e.live && e.generation == gen
        }
    }

    pub fn built(&self, key: (u32, u32)) -> bool {
        self.entry_valid(key) && self.entries[key.0 as usize].state == EntryState::Built
    }

    pub fn new_entry(&mut self, mesh: u32, lod: u8, owner: u32, triangles: u32, frame: u64) -> u32 {
        let slot = self.free_entries.pop().unwrap_or_else(|| {
            self.entries.push(BlasEntry {
                live: false,
                generation: 0,
                mesh: 0,
                lod: 0,
                owner: NONE,
                state: EntryState::Idle,
                handle: None,
                bytes: 0,
                sizes: BlasSizes::default(),
                triangles: 0,
                streak_start: 0,
                last_request: 0,
                last_keep: 0,
                created: 0,
                last_in_tlas: None,
                min_dist: f32::INFINITY,
                dist_frame: 0,
                in_view: false,
                queued_since: 0,
                needs_compaction: false,
                pose_version: 0,
                refit_frame: 0,
                quality: None,
                last_ratio: 1.0,
                gpu_ratio: None,
                refs: 0,
                active_index: 0,
            });
            (self.entries.len() - 1) as u32
        });
        let active_index = self.active.len() as u32;
        self.active.push(slot);
        let e = &mut self.entries[slot as usize];
        let generation = e.generation;
        *e = BlasEntry {
            live: true,
            generation,
            mesh,
            lod,
            owner,
            state: EntryState::Idle,
            handle: None,
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
            pose_version: 0,
            refit_frame: frame,
            quality: None,
            last_ratio: 1.0,
            gpu_ratio: None,
            refs: 0,
            active_index,
        };
        slot
    }

    /// Drops a non-built entry (the caller freed any handle first) and unlinks it.
    pub fn drop_entry(&mut self, slot: u32) {
        let (mesh, lod, owner, ai) = {
            let e = &mut self.entries[slot as usize];
            debug_assert!(e.live && e.handle.is_none());
            e.live = false;
            e.generation = e.generation.wrapping_add(1);
            (e.mesh, e.lod, e.owner, e.active_index)
        };
        self.active.swap_remove(ai as usize);
        if let Some(&moved) = self.active.get(ai as usize) {
            self.entries[moved as usize].active_index = ai;
        }
        if owner == NONE {
            if let Some(Some(m)) = self.meshes.get_mut(mesh as usize) {
                if m.lod_entry[lod as usize] == slot {
                    m.lod_entry[lod as usize] = NONE;
                }
            }
        }
        self.free_entries.push(slot);
    }

    pub fn key(&self, slot: u32) -> (u32, u32) {
        (slot, self.entries[slot as usize].generation)
    }
}
