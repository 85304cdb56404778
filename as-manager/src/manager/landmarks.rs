//! Far landmarks, kept incrementally.
//!
//! A landmark is a static instance beyond r2 (and outside a near far-field leaf) whose
//! bounding sphere subtends more than `FarFieldConfig::keep_angle` from the nearest camera
//! (10 % less once shown) and lies within `keep_range`: it stays in the TLAS beside the proxies,
//! at the LOD its distance needs, on the mesh's shared BLAS of that LOD. The default world has
//! about 13,000 of them in view; looking at each one every frame was most of `update`
//! (docs/RESULTS.md).
//!
//! Every decision about a candidate (a static instance at least `landmark_radius` large) is a
//! function of the distance `d` from the nearest camera and of state that changes by events:
//! - it is a landmark while `r2 + R < d <= min(keep range + R, R / tan)`, `tan` the keep
//!   angle's (10 % less once it is one);
//! - its LOD is the selection's (`LodSelector::select`, which holds within
//!   `LodSelector::stable_distance`), resolved to one with data or a BLAS
//!   (`MeshState::with_data`).
//!
//! Cameras that move by `m` metres change `d` by at most `m`. So a candidate looked at with `d`
//! at `slack` metres from its nearest threshold cannot change before the cameras have travelled
//! `slack` in all. The set keeps an odometer of camera travel (per frame, the largest move of
//! any camera) and a queue of when each candidate is due (`DueQueue`, buckets of a metre), and
//! looks at a candidate only then, or at once on an event:
//! - the instance was added, moved or removed;
//! - its leaf group flipped between detail and proxy (`FarField::flipped`);
//! - its mesh's LOD errors or memory floor changed (`mesh_changed`);
//! - what its selected LOD resolves to changed: data arrived or was evicted, a BLAS of the mesh
//!   was built or released (each frame, one `with_data` per selected (mesh, LOD) pair);
//! - the camera count, the configuration or a failed frame changed (everything is due).
//!
//! A landmark whose target BLAS is not built yet (it shows a coarser one, or nothing) chooses
//! its BLAS again every frame until it is. Per frame the set costs the due candidates plus one
//! pass over the (mesh, LOD) pairs the landmarks use, which carry the residency marks every
//! landmark would have set (a few hundred pairs for thousands of landmarks). The records of
//! shown landmarks lead the manager's record list and change only where a landmark joined, left
//! or changed BLAS.
//!
//! The decisions are the ones a look at every candidate every frame makes, with one
//! approximation: a built entry's distance for the eviction order is a lower bound (the distance
//! of its nearest landmark when last looked at, minus the travel since). Entries not built yet
//! (the ones the build priority orders) get exact distances, because their landmarks are looked
//! at every frame.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use glam::Vec3;

use super::state::{EntryKey, EntryState, InstanceHot, Tables, NO_GROUP};
use super::AsManager;
use crate::backend::AsBackend;
use crate::lod::LodSelector;
use crate::mesh::MeshKind;
use crate::record::TlasInstance;
use crate::spatial::{CellHasher, GridIndex};

const NONE: u32 = u32::MAX;
const NONE_LOD: u8 = u8::MAX;

/// Metres of camera travel per bucket of the due queue (a candidate may be looked at up to this
/// much early, never late).
const BUCKET_M: f64 = 1.0;
/// Buckets in the ring (16 km of travel ahead); farther ones wait in the overflow list.
const RING: u64 = 1 << 14;

/// When each candidate is due, as camera travel: a ring of one-metre buckets of (candidate
/// index, stamp).
#[derive(Debug)]
struct DueQueue {
    ring: Vec<Vec<(u32, u32)>>,
    /// Bucket index of the next bucket to pop.
    base: u64,
    /// Due before `base` (within the bucket popped last): popped at the next pop, whatever
    /// the travel.
    soon: Vec<(u32, u32)>,
    /// (bucket, slot, stamp) beyond the ring.
    overflow: Vec<(u64, u32, u32)>,
}

impl Default for DueQueue {
    fn default() -> Self {
        Self {
            ring: (0..RING).map(|_| Vec::new()).collect(),
            base: 0,
            soon: Vec::new(),
            overflow: Vec::new(),
        }
    }
}

impl DueQueue {
    fn clear(&mut self) {
        self.ring.iter_mut().for_each(Vec::clear);
        self.soon.clear();
        self.overflow.clear();
    }

    /// Due once the odometer reaches `due` (a bucket early at most, never late).
    fn push(&mut self, due: f64, slot: u32, stamp: u32) {
        let b = (due / BUCKET_M) as u64;
        if b < self.base {
            self.soon.push((slot, stamp));
        } else if b - self.base >= RING {
            self.overflow.push((b, slot, stamp));
        } else {
            self.ring[(b % RING) as usize].push((slot, stamp));
        }
    }

    /// Appends every entry due at odometer `odo`.
    fn pop_due(&mut self, odo: f64, out: &mut Vec<(u32, u32)>) {
        let current = (odo / BUCKET_M) as u64;
        out.append(&mut self.soon);
        while self.base <= current {
            out.append(&mut self.ring[(self.base % RING) as usize]);
            self.base += 1;
            if self.base % (RING / 4) == 0 && !self.overflow.is_empty() {
                // A quarter of the ring passed: bring the overflow that now fits into it.
                let (base, mut keep) = (self.base, Vec::new());
                for (b, slot, stamp) in std::mem::take(&mut self.overflow) {
                    if b - base.min(b) < RING {
                        self.ring[(b.max(base) % RING) as usize].push((slot, stamp));
                    } else {
                        keep.push((b, slot, stamp));
                    }
                }
                self.overflow = keep;
            }
        }
    }
}

/// A candidate: a static instance large enough to be a landmark somewhere. Its sphere is
/// kept here too, so that the looks that find it near or out touch nothing else.
#[derive(Debug, Clone, Copy)]
struct Cand {
    center: Vec3,
    radius: f32,
    /// Its mesh slot and transform scale (for the LOD selection).
    mesh: u32,
    scale: f32,
    slot: u32,
    /// Queue entries with another stamp are stale.
    stamp: u32,
    /// Index in `members` (NONE: not a landmark now).
    member: u32,
    /// Its far-field leaf (NO_GROUP: none) and its place in that group's list.
    group: u32,
    group_pos: u32,
    /// Last frame it was looked at.
    seen: u64,
    /// In some pair's `unusable` list.
    waiting: bool,
}

/// A shown landmark (a member of the set).
#[derive(Debug, Clone, Copy)]
struct Member {
    slot: u32,
    /// Pairs (indices in `Landmarks::pairs`): the LOD it targets, the LOD its selection
    /// named (they differ when it fell back for data), the LOD of the BLAS it shows (NONE:
    /// none built yet).
    target: u32,
    selected: u32,
    shown: u32,
    /// Places in `selected`'s `selecting` and `shown`'s `showing` lists.
    selected_pos: u32,
    shown_pos: u32,
    /// Index in the manager's records (NONE: nothing shown).
    record: u32,
    /// Last frame its shown BLAS was chosen.
    chosen: u64,
}

/// What the landmarks do with one static (mesh, LOD) pair.
#[derive(Debug)]
struct PairUse {
    mesh: u32,
    lod: u8,
    /// Landmarks targeting it.
    targets: u32,
    /// Landmarks whose selection names it (slots), and what that resolves to now.
    selecting: Vec<u32>,
    resolved: u8,
    /// Candidates whose selection named it and found no usable LOD (slots; may hold stale
    /// ones, checked on use).
    unusable: Vec<u32>,
    /// Landmarks showing its BLAS (slots), and the BLAS address their records hold.
    showing: Vec<u32>,
    address: u64,
    /// Lower bound of the nearest target's surface distance: min over targets, at their last
    /// look, of (surface distance + odometer); and whether one was in view then.
    min_key: f64,
    in_view: bool,
    /// This frame's exact figures, from the targets looked at this frame.
    frame: u64,
    frame_min: f32,
    frame_in_view: bool,
}

impl PairUse {
    fn new(mesh: u32, lod: u8) -> Self {
        Self {
            mesh,
            lod,
            targets: 0,
            selecting: Vec::new(),
            resolved: NONE_LOD,
            unusable: Vec::new(),
            showing: Vec::new(),
            address: 0,
            min_key: 0.0,
            in_view: false,
            frame: u64::MAX,
            frame_min: 0.0,
            frame_in_view: false,
        }
    }

    fn is_unused(&self) -> bool {
        self.targets == 0
            && self.selecting.is_empty()
            && self.showing.is_empty()
            && self.unusable.is_empty()
    }
}

/// The incremental landmark set. See the module docs.
#[derive(Debug)]
pub(crate) struct Landmarks {
    /// Radius from which a static instance is a candidate (infinite: landmarks off).
    min_radius: f32,
    /// Camera travel so far, metres.
    odo: f64,
    cams: Vec<Vec3>,
    /// Every candidate is due (first frame, camera count, configuration, failed frame).
    all_due: bool,
    /// Per instance slot: index in `cands` (NONE: not a candidate).
    index: Vec<u32>,
    /// The candidates, in a slab: an index stays the candidate's while it is one (the queue
    /// names candidates by index; a vacant entry has slot NONE), vacant ones in `free_cands`.
    cands: Vec<Cand>,
    free_cands: Vec<u32>,
    queue: DueQueue,
    next_stamp: u32,
    /// Slots due now by an event.
    now: Vec<u32>,
    /// Meshes whose candidates are all due now.
    meshes_changed: Vec<u32>,
    /// Per leaf group: its candidates (slots).
    groups: HashMap<u32, Vec<u32>>,
    members: Vec<Member>,
    /// `records[i]` (the manager's; the first `record_slots.len()` are the landmarks') is slot
    /// `record_slots[i]`'s.
    record_slots: Vec<u32>,
    /// The (mesh, LOD) pairs in use, in a slab (iterated in index order: deterministic), and
    /// their indices.
    pairs: Vec<Option<PairUse>>,
    free_pairs: Vec<u32>,
    pair_index: HashMap<u64, u32, BuildHasherDefault<CellHasher>>,
    /// Members whose shown BLAS is chosen again this frame.
    rechoose: Vec<u32>,
    /// Members choosing again next frame (their target is not built).
    unsettled: Vec<u32>,
    scratch: Vec<u32>,
    queued_scratch: Vec<u32>,
    due_scratch: Vec<(u32, u32)>,
    /// Candidates looked at this frame.
    pub examined: u32,
    /// Indices of the landmark records written since the last TLAS build (`TlasDelta`).
    pub changed: Vec<u32>,
}

impl Default for Landmarks {
    fn default() -> Self {
        Self {
            min_radius: f32::INFINITY,
            odo: 0.0,
            cams: Vec::new(),
            all_due: true,
            index: Vec::new(),
            cands: Vec::new(),
            free_cands: Vec::new(),
            queue: DueQueue::default(),
            next_stamp: 0,
            now: Vec::new(),
            meshes_changed: Vec::new(),
            groups: HashMap::new(),
            members: Vec::new(),
            record_slots: Vec::new(),
            pairs: Vec::new(),
            free_pairs: Vec::new(),
            pair_index: HashMap::default(),
            rechoose: Vec::new(),
            unsettled: Vec::new(),
            scratch: Vec::new(),
            queued_scratch: Vec::new(),
            due_scratch: Vec::new(),
            examined: 0,
            changed: Vec::new(),
        }
    }
}

/// A candidate's instance as `Landmarks::track` is told of it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct CandSphere {
    pub center: Vec3,
    pub radius: f32,
    pub mesh: u32,
    pub scale: f32,
}

/// What a frame's look at the candidates reads of the configuration.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LandmarkParams {
    pub r2: f32,
    /// tan of the keep angle.
    pub keep_tan: f32,
    /// min(far radius, keep range).
    pub range: f32,
    pub frame: u64,
    pub need_data: bool,
}

impl Landmarks {
    /// Landmark records at the front of the manager's record list.
    pub fn len(&self) -> usize {
        self.record_slots.len()
    }

    /// Whether `slot` is a shown landmark now.
    pub fn is_member(&self, slot: u32) -> bool {
        self.cand(slot).is_some_and(|c| c.member != NONE)
    }

    fn cand(&self, slot: u32) -> Option<&Cand> {
        let i = *self.index.get(slot as usize)?;
        self.cands.get(i as usize)
    }

    fn cand_mut(&mut self, slot: u32) -> Option<&mut Cand> {
        let i = *self.index.get(slot as usize)?;
        self.cands.get_mut(i as usize)
    }

    /// The candidate radius in force (infinite: off).
    pub fn min_radius(&self) -> f32 {
        self.min_radius
    }

    /// Sets the candidate radius; the caller re-adds every instance when it changed.
    pub fn set_min_radius(&mut self, r: f32) {
        self.min_radius = r;
    }

    /// Everything is looked at again next frame (a failed frame, a configuration change):
    /// no landmark is shown until then. The caller drops the landmark records.
    pub fn invalidate(&mut self) {
        self.members.clear();
        self.record_slots.clear();
        self.pairs.clear();
        self.free_pairs.clear();
        self.pair_index.clear();
        self.rechoose.clear();
        self.unsettled.clear();
        self.queue.clear();
        // Every record is pushed again (and listed) when the landmarks come back.
        self.changed.clear();
        for c in &mut self.cands {
            c.member = NONE;
            c.waiting = false;
        }
        self.all_due = true;
    }

    /// Forgets every candidate (before re-adding them under a new radius).
    pub fn clear(&mut self) {
        self.invalidate();
        self.index.clear();
        self.cands.clear();
        self.free_cands.clear();
        self.groups.clear();
        self.now.clear();
        self.meshes_changed.clear();
    }

    /// An instance was added or moved: a candidate when static and at least `min_radius`
    /// large; due now (a moved landmark writes its record again).
    pub fn track(&mut self, slot: u32, sphere: CandSphere, is_static: bool, group: u32) {
        let CandSphere {
            center,
            radius,
            mesh,
            scale,
        } = sphere;
        let wanted = is_static && radius >= self.min_radius;
        if let Some(c) = self.cand_mut(slot) {
            // Removed when looked at if it no longer qualifies (`evaluate`).
            (c.center, c.radius, c.scale) = (center, radius, scale);
            self.now.push(slot);
            if self.is_member(slot) {
                self.rechoose.push(slot);
            }
            return;
        }
        if !wanted {
            return;
        }
        if self.index.len() <= slot as usize {
            self.index.resize(slot as usize + 1, NONE);
        }
        let group_pos = if group == NO_GROUP {
            NONE
        } else {
            let v = self.groups.entry(group).or_default();
            v.push(slot);
            (v.len() - 1) as u32
        };
        let cand = Cand {
            center,
            radius,
            mesh,
            scale,
            slot,
            stamp: 0,
            member: NONE,
            group,
            group_pos,
            seen: u64::MAX,
            waiting: false,
        };
        let ci = match self.free_cands.pop() {
            Some(ci) => {
                self.cands[ci as usize] = cand;
                ci
            }
            None => {
                self.cands.push(cand);
                (self.cands.len() - 1) as u32
            }
        };
        self.index[slot as usize] = ci;
        self.now.push(slot);
    }

    /// Every candidate of `mesh` is due now (its LOD errors or memory floor changed).
    pub fn mesh_changed(&mut self, mesh: u32) {
        if self.min_radius.is_finite() {
            self.meshes_changed.push(mesh);
        }
    }

    fn pair(&mut self, i: u32) -> &mut PairUse {
        self.pairs[i as usize].as_mut().expect("a live pair")
    }

    /// The pair of (mesh, LOD), created when missing.
    fn pair_of(&mut self, mesh: u32, lod: u8) -> u32 {
        if let Some(&i) = self.pair_index.get(&pair_key(mesh, lod)) {
            return i;
        }
        let p = Some(PairUse::new(mesh, lod));
        let i = match self.free_pairs.pop() {
            Some(i) => {
                self.pairs[i as usize] = p;
                i
            }
            None => {
                self.pairs.push(p);
                (self.pairs.len() - 1) as u32
            }
        };
        self.pair_index.insert(pair_key(mesh, lod), i);
        i
    }

    /// Frees pair `i` if nothing uses it any more.
    fn release_pair(&mut self, i: u32) {
        let p = self.pairs[i as usize].as_ref().expect("a live pair");
        if p.is_unused() {
            self.pair_index.remove(&pair_key(p.mesh, p.lod));
            self.pairs[i as usize] = None;
            self.free_pairs.push(i);
        }
    }

    /// Swap-removes `slot` from a pair's member list at `pos`; returns the slot moved there.
    fn list_remove(list: &mut Vec<u32>, pos: u32) -> Option<u32> {
        list.swap_remove(pos as usize);
        list.get(pos as usize).copied()
    }

    fn member_of(&self, slot: u32) -> usize {
        self.cand(slot).map(|c| c.member).expect("a member") as usize
    }

    /// Removes a member's record (swap-remove in the manager's records).
    fn drop_record(&mut self, m: usize, records: &mut Vec<TlasInstance>) {
        let r = self.members[m].record;
        if r == NONE {
            return;
        }
        let last = self.record_slots.len() - 1;
        records.swap(r as usize, last);
        records.truncate(last);
        self.record_slots.swap_remove(r as usize);
        if let Some(&moved) = self.record_slots.get(r as usize) {
            let mi = self.member_of(moved);
            self.members[mi].record = r;
            self.changed.push(r);
        }
        self.members[m].record = NONE;
    }

    fn unselect(&mut self, m: usize) {
        let mb = self.members[m];
        self.unselect_at(mb.selected, mb.selected_pos);
    }

    /// Takes the member at `pos` of `pair`'s selecting list out of it.
    fn unselect_at(&mut self, pair: u32, pos: u32) {
        if let Some(moved) = Self::list_remove(&mut self.pair(pair).selecting, pos) {
            let mi = self.member_of(moved);
            self.members[mi].selected_pos = pos;
        }
        self.release_pair(pair);
    }

    fn select_pair(&mut self, m: usize, pair: u32) {
        let slot = self.members[m].slot;
        let list = &mut self.pair(pair).selecting;
        list.push(slot);
        let pos = (list.len() - 1) as u32;
        self.members[m].selected = pair;
        self.members[m].selected_pos = pos;
    }

    /// Takes a member out of its shown pair's list.
    fn unshow(&mut self, m: usize) {
        let mb = self.members[m];
        if mb.shown == NONE {
            return;
        }
        if let Some(moved) = Self::list_remove(&mut self.pair(mb.shown).showing, mb.shown_pos) {
            let mi = self.member_of(moved);
            self.members[mi].shown_pos = mb.shown_pos;
        }
        self.release_pair(mb.shown);
        self.members[m].shown = NONE;
    }

    fn untarget(&mut self, pair: u32) {
        self.pair(pair).targets -= 1;
        self.release_pair(pair);
    }

    /// A member leaves the set (its record goes, its pairs forget it).
    fn leave(&mut self, slot: u32, records: &mut Vec<TlasInstance>) {
        let ci = self.index[slot as usize] as usize;
        let m = self.cands[ci].member;
        if m == NONE {
            return;
        }
        let m = m as usize;
        self.drop_record(m, records);
        self.unshow(m);
        self.unselect(m);
        self.untarget(self.members[m].target);
        self.members.swap_remove(m);
        if let Some(moved) = self.members.get(m) {
            let mc = self.index[moved.slot as usize];
            self.cands[mc as usize].member = m as u32;
        }
        self.cands[ci].member = NONE;
    }

    /// An instance was removed: it leaves the set and stops being a candidate.
    pub fn remove(&mut self, slot: u32, records: &mut Vec<TlasInstance>) {
        if self.cand(slot).is_none() {
            return;
        }
        self.leave(slot, records);
        let ci = self.index[slot as usize] as usize;
        let c = self.cands[ci];
        if c.group != NO_GROUP {
            if let Some(v) = self.groups.get_mut(&c.group) {
                if let Some(moved) = Self::list_remove(v, c.group_pos) {
                    let mi = self.index[moved as usize];
                    self.cands[mi as usize].group_pos = c.group_pos;
                }
                if v.is_empty() {
                    self.groups.remove(&c.group);
                }
            }
        }
        // Vacant: its queue entries go stale with the new stamp.
        self.next_stamp = self.next_stamp.wrapping_add(1);
        self.cands[ci].slot = NONE;
        self.cands[ci].stamp = self.next_stamp;
        self.free_cands.push(ci as u32);
        self.index[slot as usize] = NONE;
    }

    /// Counts this frame's camera travel; a change of camera count makes everything due.
    fn advance(&mut self, cams: &[Vec3]) {
        if cams.len() != self.cams.len() {
            self.all_due = true;
        } else {
            let moved = cams
                .iter()
                .zip(&self.cams)
                .map(|(a, b)| a.distance(*b))
                .fold(0.0f32, f32::max);
            if moved.is_finite() {
                self.odo += f64::from(moved);
            } else {
                self.all_due = true;
            }
        }
        self.cams.clear();
        self.cams.extend_from_slice(cams);
    }

    /// Which candidates are due this frame, in a deterministic order, into `out`
    /// (duplicates allowed: the caller skips the ones seen this frame).
    fn collect_due(
        &mut self,
        tables: &Tables,
        need_data: bool,
        groups_flipped: &mut Vec<u32>,
        out: &mut Vec<u32>,
        queued: &mut Vec<u32>,
    ) {
        out.clear();
        queued.clear();
        if self.all_due {
            self.all_due = false;
            self.queue.clear();
            self.now.clear();
            self.meshes_changed.clear();
            groups_flipped.clear();
            out.extend(self.cands.iter().map(|c| c.slot).filter(|&s| s != NONE));
            return;
        }
        out.append(&mut self.now);
        for g in groups_flipped.drain(..) {
            if let Some(v) = self.groups.get(&g) {
                out.extend_from_slice(v);
            }
        }
        for m in self.meshes_changed.drain(..) {
            if let Some(Some(mesh)) = tables.meshes.get(m as usize) {
                out.extend(
                    mesh.instances
                        .iter()
                        .copied()
                        .filter(|&s| self.index.get(s as usize).is_some_and(|&i| i != NONE)),
                );
            }
        }
        // Selections whose resolution changed (data or BLASes of the mesh came or went).
        for p in self.pairs.iter_mut().flatten() {
            if p.selecting.is_empty() && p.unusable.is_empty() {
                continue;
            }
            let Some(Some(mesh)) = tables.meshes.get(p.mesh as usize) else {
                continue;
            };
            let built = |l: usize| tables.built(mesh.lod_entry[l]);
            let resolved = mesh
                .with_data(p.lod as usize, need_data, built)
                .map_or(NONE_LOD, |l| l as u8);
            if resolved != p.resolved {
                p.resolved = resolved;
                out.extend_from_slice(&p.selecting);
                out.append(&mut p.unusable);
            }
        }
        let mut due = std::mem::take(&mut self.due_scratch);
        due.clear();
        self.queue.pop_due(self.odo, &mut due);
        let cands = &self.cands;
        queued.extend(
            due.iter()
                .filter(|&&(ci, stamp)| cands[ci as usize].stamp == stamp)
                .map(|&(ci, _)| ci),
        );
        self.due_scratch = due;
    }

    /// Looks at the candidate again once the cameras travelled `slack` more metres (never,
    /// for an infinite slack: only an event makes it due).
    fn due_after(&mut self, ci: u32, slack: f32, d: f32) {
        self.next_stamp = self.next_stamp.wrapping_add(1);
        let stamp = self.next_stamp;
        self.cands[ci as usize].stamp = stamp;
        if !slack.is_finite() {
            return;
        }
        // A margin for rounding in the distances (f32) and the odometer.
        let slack = (slack - 0.01 - 1e-4 * d).max(0.0);
        self.queue.push(self.odo + f64::from(slack), ci, stamp);
    }

    /// Invariants (for `check_invariants`).
    pub fn check(&self, records: &[TlasInstance]) -> Result<(), String> {
        if records.len() < self.record_slots.len() {
            return Err("fewer records than landmark records".into());
        }
        let mut counts: HashMap<u32, (u32, u32, u32)> = HashMap::new();
        for (i, m) in self.members.iter().enumerate() {
            let c = self.cand(m.slot).ok_or("member is no candidate")?;
            if c.member != i as u32 {
                return Err(format!("member {i} (slot {}) not linked", m.slot));
            }
            counts.entry(m.target).or_default().0 += 1;
            counts.entry(m.selected).or_default().1 += 1;
            let sel = self.pairs[m.selected as usize]
                .as_ref()
                .ok_or("dead pair")?;
            if sel.selecting.get(m.selected_pos as usize) != Some(&m.slot) {
                return Err(format!("slot {} not at its selected position", m.slot));
            }
            if m.shown != NONE {
                counts.entry(m.shown).or_default().2 += 1;
                let p = self.pairs[m.shown as usize].as_ref().ok_or("dead pair")?;
                if p.showing.get(m.shown_pos as usize) != Some(&m.slot) {
                    return Err(format!("slot {} not at its shown position", m.slot));
                }
            }
            if m.record != NONE && self.record_slots.get(m.record as usize) != Some(&m.slot) {
                return Err(format!("slot {} not at its record", m.slot));
            }
            if (m.record != NONE) != (m.shown != NONE) {
                return Err(format!("slot {}: a record without a BLAS or back", m.slot));
            }
        }
        for (i, p) in self.pairs.iter().enumerate() {
            let Some(p) = p else { continue };
            let (t, s, w) = counts.get(&(i as u32)).copied().unwrap_or_default();
            if p.targets != t || p.selecting.len() as u32 != s || p.showing.len() as u32 != w {
                return Err(format!("pair ({}, {}) counts are off", p.mesh, p.lod));
            }
            if self.pair_index.get(&pair_key(p.mesh, p.lod)) != Some(&(i as u32)) {
                return Err(format!("pair ({}, {}) not indexed", p.mesh, p.lod));
            }
        }
        if self.record_slots.iter().any(|&s| !self.is_member(s)) {
            return Err("a landmark record of no member".into());
        }
        Ok(())
    }
}

fn pair_key(mesh: u32, lod: u8) -> u64 {
    (u64::from(mesh) << 8) | u64::from(lod)
}

/// Squared distance from the nearest camera to `c` (as the residency pass computes it, so
/// both agree on which side of r2 an instance is).
fn nearest2(cams: &[Vec3], c: Vec3) -> f32 {
    cams.iter()
        .map(|p| p.distance_squared(c))
        .fold(f32::INFINITY, f32::min)
}

/// The look at one candidate (see `Landmarks::evaluate`), with what it borrows.
struct Look<'a> {
    grid: &'a mut GridIndex<InstanceHot>,
    tables: &'a mut Tables,
    lod: &'a LodSelector,
    far: &'a super::far::FarField,
    cams: &'a [Vec3],
    fwds: &'a [Vec3],
    records: &'a mut Vec<TlasInstance>,
    p: LandmarkParams,
}

impl Landmarks {
    /// Looks at candidate `slot`: joins, updates or leaves the set, and says when to look next.
    fn evaluate(&mut self, ci: u32, x: &mut Look<'_>) {
        let frame = x.p.frame;
        let cand = self.cands[ci as usize];
        let slot = cand.slot;
        if cand.radius < self.min_radius {
            // Moved and shrank (`track`).
            self.remove(slot, x.records);
            return;
        }
        self.examined += 1;
        let is_member = cand.member != NONE;
        let (c, radius) = (cand.center, cand.radius);
        let d2 = nearest2(x.cams, c);
        let d = d2.sqrt();
        let reach = x.p.r2 + radius;
        let within_r2 = d2 <= reach * reach;
        if within_r2 || x.far.is_near_leaf(cand.group) {
            // Near field now (within r2, or its leaf is on the detail side): shown by the
            // residency pass, which continues from the landmark's LOD and cull state.
            if is_member {
                if let Some(ge) = x.grid.get_mut(slot) {
                    ge.data.last_visit = frame.wrapping_sub(1);
                    ge.data.culled = false;
                }
                self.leave(slot, x.records);
            }
            // The leaf flipping back is an event; within r2, leaving it is the threshold.
            let slack = if within_r2 { reach - d } else { f32::INFINITY };
            self.due_after(ci, slack, d);
            return;
        }
        let (kt, range) = (x.p.keep_tan, x.p.range);
        if d - radius > range || radius <= kt * 0.9 * d {
            // Out even with the hysteresis: no need to look at the instance.
            if is_member {
                self.leave(slot, x.records);
            }
            let join = (radius / kt).min(range + radius);
            self.due_after(ci, d - join, d);
            return;
        }
        let mesh_ix = cand.mesh;
        let Some(Some(mesh)) = x.tables.meshes.get(mesh_ix as usize) else {
            self.remove(slot, x.records);
            return;
        };
        if mesh.kind != MeshKind::Static {
            self.remove(slot, x.records);
            return;
        }
        // A landmark continues from its LOD (kept here, not in the grid: a look at a landmark
        // touches no instance state); any other candidate from the instance's last visit.
        let (was, last_lod) = if is_member {
            let m = self.members[cand.member as usize];
            (
                true,
                self.pairs[m.target as usize].as_ref().expect("live").lod,
            )
        } else {
            let Some(ge) = x.grid.get(slot) else {
                self.remove(slot, x.records);
                return;
            };
            (
                ge.data.last_visit == frame.wrapping_sub(1),
                ge.data.lod_target,
            )
        };
        let tan = if was { kt * 0.9 } else { kt };
        if radius <= tan * d {
            if is_member {
                self.leave(slot, x.records);
            }
            // Not shown next frame either: it joins once within both limits (no hysteresis).
            let join = (radius / kt).min(range + radius);
            self.due_after(ci, d - join, d);
            return;
        }
        let surface = (d - radius).max(0.0);
        let n = mesh.nlods as usize;
        let current = if was { last_lod as usize } else { n - 1 };
        let selected = x.lod.select(
            mesh.errors(),
            cand.scale,
            surface,
            current,
            mesh.lod_floor as usize,
        );
        let built = |l: usize| x.tables.built(mesh.lod_entry[l]);
        let resolved = mesh.with_data(selected, x.p.need_data, built);
        let Some(lodi) = resolved else {
            // No LOD has data: nothing to show until the selection resolves to one.
            if is_member {
                self.leave(slot, x.records);
            }
            let sel_pair = self.pair_of(mesh_ix, selected as u8);
            self.pair(sel_pair).resolved = NONE_LOD;
            let c = &mut self.cands[ci as usize];
            if !c.waiting {
                c.waiting = true;
                self.pair(sel_pair).unusable.push(slot);
            }
            self.due_after(ci, f32::INFINITY, d);
            return;
        };
        // Next time `current` is this LOD: the selection holds while the surface distance
        // stays within `lod_slack`.
        let lod_slack = x
            .lod
            .stable_distance(mesh.errors(), cand.scale, lodi, surface);
        let tris = mesh.lod_tris[lodi];
        let in_view = x.cams.iter().zip(x.fwds).any(|(p, f)| f.dot(c - *p) >= 0.0);
        if !is_member {
            // Joins: the instance's LOD and cull state as a visit leaves them (a landmark's
            // LOD is written back when it changes, in `landmarks_cull`).
            if let Some(ge) = x.grid.get_mut(slot) {
                ge.data.lod_target = lodi as u8;
                ge.data.last_visit = frame;
                ge.data.culled = false;
            }
        }
        // Its target entry exists from now on (as the residency pass creates it).
        if mesh.lod_entry[lodi].is_none() {
            let key = x.tables.new_entry(mesh_ix, lodi as u8, None, tris, frame);
            x.tables.meshes[mesh_ix as usize]
                .as_mut()
                .expect("live mesh")
                .lod_entry[lodi] = Some(key);
        }
        let target = self.pair_of(mesh_ix, lodi as u8);
        let sel_pair = self.pair_of(mesh_ix, selected as u8);
        if !is_member {
            self.members.push(Member {
                slot,
                target,
                selected: sel_pair,
                shown: NONE,
                selected_pos: NONE,
                shown_pos: NONE,
                record: NONE,
                chosen: u64::MAX,
            });
            let m = self.members.len() - 1;
            self.cands[ci as usize].member = m as u32;
            self.pair(target).targets += 1;
            self.select_pair(m, sel_pair);
            self.rechoose.push(slot);
        } else {
            // The new references first, then the old ones go: a pair freed in between could
            // be one of the new ones.
            let m = self.member_of(slot);
            let old = self.members[m];
            if old.selected != sel_pair {
                self.select_pair(m, sel_pair);
                self.unselect_at(old.selected, old.selected_pos);
            }
            if old.target != target {
                self.pair(target).targets += 1;
                self.members[m].target = target;
                self.untarget(old.target);
                self.rechoose.push(slot);
            }
        }
        self.pair(sel_pair).resolved = lodi as u8;
        let key = surface as f64 + self.odo;
        let pair = self.pair(target);
        if pair.targets == 1 {
            // Its only target: exact again.
            pair.min_key = key;
            pair.in_view = in_view;
        } else {
            pair.min_key = pair.min_key.min(key);
            pair.in_view |= in_view;
        }
        if pair.frame != frame {
            pair.frame = frame;
            pair.frame_min = surface;
            pair.frame_in_view = in_view;
        } else {
            pair.frame_min = pair.frame_min.min(surface);
            pair.frame_in_view |= in_view;
        }
        // Next look: the nearest threshold (shown next frame: the hysteresis one).
        let leave_at = (radius / (kt * 0.9)).min(range + radius);
        let slack = (leave_at - d).min(d - reach).min(lod_slack);
        self.due_after(ci, slack, d);
    }
}

impl<B: AsBackend> AsManager<B> {
    fn landmark_params(&self) -> Option<LandmarkParams> {
        let f = &self.config.far_field;
        if !self.landmarks.min_radius().is_finite() {
            return None;
        }
        Some(LandmarkParams {
            r2: self.config.residency.r2,
            keep_tan: f.keep_angle.tan(),
            range: f.far_radius.min(f.keep_range),
            frame: self.frame,
            need_data: self.backend.needs_geometry(),
        })
    }

    /// Residency step of the landmarks (after `far_prepare`, before the residency pass): looks
    /// at the due candidates and sets the residency marks of the pairs the landmarks use.
    pub(crate) fn landmarks_residency(&mut self) {
        self.landmarks.examined = 0;
        let Some(p) = self.landmark_params() else {
            self.far.flipped.clear();
            return;
        };
        let _s = tracing::trace_span!("landmarks").entered();
        // Last frame's near and proxy records go; the landmarks' stay at the front.
        self.records.truncate(self.landmarks.len());
        let Self {
            landmarks,
            grid,
            tables,
            lod,
            far,
            cam_pos,
            cam_fwd,
            records,
            ..
        } = self;
        landmarks.advance(cam_pos);
        let mut due = std::mem::take(&mut landmarks.scratch);
        let mut queued = std::mem::take(&mut landmarks.queued_scratch);
        landmarks.collect_due(tables, p.need_data, &mut far.flipped, &mut due, &mut queued);
        // Landmarks whose target is not built yet are looked at (the distances of unbuilt
        // entries are exact; see the module docs) and choose their BLAS every frame.
        landmarks.rechoose.extend_from_slice(&landmarks.unsettled);
        due.append(&mut landmarks.unsettled);
        let mut look = Look {
            grid,
            tables,
            lod,
            far,
            cams: cam_pos,
            fwds: cam_fwd,
            records,
            p,
        };
        // Events name instances (slots), the queue names candidates (indices).
        for x in due.iter_mut() {
            *x = landmarks.index.get(*x as usize).copied().unwrap_or(NONE);
        }
        due.extend_from_slice(&queued);
        for &ci in &due {
            let Some(c) = landmarks.cands.get_mut(ci as usize) else {
                continue;
            };
            if c.slot == NONE || c.seen == p.frame {
                continue;
            }
            c.seen = p.frame;
            c.waiting = false;
            landmarks.evaluate(ci, &mut look);
        }
        landmarks.scratch = due;
        landmarks.queued_scratch = queued;
        // The marks every landmark would set on its target and shown entries.
        let frame = p.frame;
        let odo = landmarks.odo;
        for pair in landmarks.pairs.iter().flatten() {
            let (mesh, lod) = (pair.mesh, pair.lod as usize);
            let Some(Some(m)) = tables.meshes.get(mesh as usize) else {
                continue;
            };
            let key = match m.lod_entry[lod] {
                Some(k) => k,
                None if pair.targets > 0 => {
                    // Released since (evicted): the targets ask for it again.
                    let tris = m.lod_tris[lod];
                    let k = tables.new_entry(mesh, lod as u8, None, tris, frame);
                    tables.meshes[mesh as usize]
                        .as_mut()
                        .expect("live mesh")
                        .lod_entry[lod] = Some(k);
                    k
                }
                None => continue,
            };
            let e = &mut tables.entries[key];
            if pair.targets == 0 && pair.showing.is_empty() {
                continue;
            }
            e.last_keep = frame;
            if pair.targets == 0 {
                continue;
            }
            if e.last_request.wrapping_add(1) < frame || e.last_request > frame {
                e.streak_start = frame;
            }
            e.last_request = frame;
            let (dist, in_view) = if e.state != EntryState::Built && pair.frame == frame {
                (pair.frame_min, pair.frame_in_view)
            } else {
                ((pair.min_key - odo).max(0.0) as f32, pair.in_view)
            };
            if e.dist_frame != frame {
                e.dist_frame = frame;
                e.min_dist = dist;
                e.in_view = in_view;
            } else {
                e.min_dist = e.min_dist.min(dist);
                e.in_view |= in_view;
            }
        }
    }

    /// Cull step of the landmarks (after the frame's builds): the BLAS each landmark that
    /// joined, changed LOD or waits for its target shows (its target if built, else what it
    /// showed, else the nearest built LOD), the records of landmarks whose BLAS changed, and
    /// the marks of the shown entries.
    pub(crate) fn landmarks_cull(&mut self) {
        if self.landmark_params().is_none() {
            return;
        }
        let _s = tracing::trace_span!("landmarks_cull").entered();
        let frame = self.frame;
        let Self {
            landmarks,
            grid,
            tables,
            backend,
            records,
            ..
        } = self;
        let address_of = |tables: &Tables, key: Option<EntryKey>| -> u64 {
            match key.and_then(|k| tables.entries.get(k)) {
                Some(e) if e.state == EntryState::Built => e.record_address(&*backend),
                _ => 0,
            }
        };
        let entry_of = |tables: &Tables, mesh: u32, lod: u8| {
            tables
                .meshes
                .get(mesh as usize)
                .and_then(|m| m.as_ref())
                .and_then(|m| m.lod_entry[lod as usize])
        };
        // Pairs whose BLAS changed (built, compacted, released): their landmarks choose again.
        let mut rechoose = std::mem::take(&mut landmarks.rechoose);
        for pair in landmarks.pairs.iter_mut().flatten() {
            if pair.showing.is_empty() {
                continue;
            }
            let address = address_of(tables, entry_of(tables, pair.mesh, pair.lod));
            if address != pair.address {
                pair.address = address;
                rechoose.extend_from_slice(&pair.showing);
            }
        }
        for &slot in &rechoose {
            let Some(c) = landmarks.cand(slot) else {
                continue;
            };
            let mi = c.member;
            if mi == NONE || landmarks.members[mi as usize].chosen == frame {
                continue;
            }
            let mi = mi as usize;
            landmarks.members[mi].chosen = frame;
            let mb = landmarks.members[mi];
            let (mesh_ix, target_lod) = {
                let p = landmarks.pairs[mb.target as usize].as_ref().expect("live");
                (p.mesh, p.lod)
            };
            let Some(ge) = grid.get_mut(slot) else {
                continue;
            };
            let hot = &mut ge.data;
            hot.lod_target = target_lod;
            let mesh = tables.meshes[mesh_ix as usize]
                .as_ref()
                .expect("a landmark's mesh is live");
            let target = mesh.lod_entry[target_lod as usize];
            let chosen = if tables.built(target) {
                target
            } else if tables.built(hot.shown)
                && hot
                    .shown
                    .is_some_and(|k| tables.entries[k].mesh == hot.mesh)
            {
                hot.shown
            } else {
                let (tl, n) = (target_lod as usize, mesh.nlods as usize);
                (tl..n)
                    .chain((0..tl).rev())
                    .map(|l| mesh.lod_entry[l])
                    .find(|&k| tables.built(k))
                    .flatten()
            };
            hot.shown = chosen;
            if chosen != target {
                landmarks.unsettled.push(slot);
            }
            let shown_pair = chosen.map(|k| {
                let lod = tables.entries[k].lod;
                landmarks.pair_of(mesh_ix, lod)
            });
            if shown_pair != (mb.shown != NONE).then_some(mb.shown) {
                landmarks.unshow(mi);
                if let Some(sp) = shown_pair {
                    let address = address_of(tables, chosen);
                    let p = landmarks.pair(sp);
                    if p.showing.is_empty() {
                        p.address = address;
                    }
                    p.showing.push(slot);
                    let pos = (p.showing.len() - 1) as u32;
                    landmarks.members[mi].shown = sp;
                    landmarks.members[mi].shown_pos = pos;
                }
            }
            match chosen {
                Some(k) => {
                    let record = TlasInstance {
                        blas_address: address_of(tables, Some(k)),
                        ..hot.template
                    };
                    let r = landmarks.members[mi].record;
                    if r == NONE {
                        let at = landmarks.record_slots.len();
                        debug_assert_eq!(records.len(), at, "landmark records come first");
                        records.push(record);
                        landmarks.record_slots.push(slot);
                        landmarks.members[mi].record = at as u32;
                        landmarks.changed.push(at as u32);
                    } else if records[r as usize] != record {
                        records[r as usize] = record;
                        landmarks.changed.push(r);
                    }
                }
                None => landmarks.drop_record(mi, records),
            }
        }
        rechoose.clear();
        landmarks.rechoose = rechoose;
        for pair in landmarks.pairs.iter().flatten() {
            if pair.showing.is_empty() {
                continue;
            }
            let key = entry_of(tables, pair.mesh, pair.lod);
            if let Some(e) = key.and_then(|k| tables.entries.get_mut(k)) {
                e.last_in_tlas = Some(frame);
                e.last_keep = frame;
            }
        }
        self.stats.landmark_instances = self.landmarks.len() as u32;
    }
}
