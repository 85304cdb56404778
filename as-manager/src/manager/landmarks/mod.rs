//! Far landmarks, kept incrementally.
//!
//! Why one file over 600 lines: the set's state (`Cand`, `Member`, `PairUse`, `Landmarks`) and
//! its membership bookkeeping (`track`, `remove`, the invariant check) share private fields;
//! the frame steps, the looks, the pairs and the queue are the submodules.
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
//!   `LodSelector::stable_band`), resolved to one with data or a BLAS
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
//! its BLAS again every frame until it is, and its distance is taken every frame (its target
//! pair's, for the build order); it is looked at again only when that distance leaves its last
//! look's band, as a queued candidate is. (Looking at every one of them every frame made a
//! backlog of builds cost thousands of looks a frame: `docs/PROFILE.md`.) Per frame the set costs the due candidates plus one
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

mod frame;
mod look;
mod pairs;
mod queue;

use std::collections::HashMap;

use rustc_hash::FxHashMap;

use glam::Vec3;

use super::state::{EntryKey, InstanceHot, NO_GROUP};
use crate::record::TlasInstance;
use queue::{Due, DueQueue};

const NONE: u32 = u32::MAX;
const NONE_LOD: u8 = u8::MAX;

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
    /// Index in `members` (NONE: not a landmark now).
    member: u32,
    /// Its far-field leaf (NO_GROUP: none) and its place in that group's list.
    group: u32,
    group_pos: u32,
    /// Last frame it was looked at.
    seen: u64,
    /// In some pair's `unusable` list.
    waiting: bool,
    /// A landmark's target LOD and selected LOD (its member's pairs), so that a look that
    /// changes neither touches nothing else.
    lod: u8,
    sel: u8,
    /// A landmark that chooses its BLAS every frame (`Landmarks::unsettled`).
    unsettled: bool,
    /// The centre distances between which its last look's outcome holds (margins taken off;
    /// empty: due next frame). An unsettled landmark is looked at again only once outside.
    band: (f32, f32),
    /// Detail of a near leaf: culled by its projected angle (`InstanceCuller::cull_small`).
    culled: bool,
    /// Detail not ready (no LOD of its mesh has data or a BLAS): counted in its leaf's
    /// `Landmarks::unready` until its next look.
    unready: bool,
}

// A look at a candidate reads one cache line of it (the band added in the seventh session
// still fits).
const _: () = assert!(std::mem::size_of::<Cand>() <= 64);

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
    /// Detail of a near leaf beyond r2 (not a landmark): culled by angle like the near field,
    /// and out of the TLAS while its leaf's proxy covers it.
    detail: bool,
    /// Counted in its shown pair's `visible` (shown and not culled).
    counted: bool,
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
    /// Its mesh's entry of this LOD as last found (checked on use: `frame::pair_entry`).
    entry: Option<EntryKey>,
    /// Of `showing`, those not culled (what marks the entry as in the TLAS).
    visible: u32,
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
            entry: None,
            visible: 0,
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
    /// Also the near leaves' detail beyond r2 (`FarFieldConfig::incremental_detail`): every
    /// static instance of a leaf group is a candidate.
    detail: bool,
    /// Leaf groups whose detail records are out of the TLAS: near, but covered by their proxy
    /// (handing over), as of the last `hide_covered`.
    hidden: Vec<u32>,
    /// Of the records, the near-leaf detail ones.
    pub detail_records: u32,
    /// With `detail`: per leaf group, its instances that are not candidates (skinned ones),
    /// which the residency pass visits beyond r2 when the leaf is near; and each slot's place
    /// in its list (NONE: listed nowhere).
    others: FxHashMap<u32, Vec<u32>>,
    other_pos: Vec<u32>,
    other_group: Vec<u32>,
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
    /// Per candidate index, the stamp of its one live queue entry (entries with another are
    /// stale): apart from `cands`, so that settling a due entry reads four bytes of it.
    stamps: Vec<u32>,
    queue: DueQueue,
    next_stamp: u32,
    /// Slots due now by an event.
    now: Vec<u32>,
    /// Meshes whose candidates are all due now.
    meshes_changed: Vec<u32>,
    /// Per leaf group: its candidates (slots).
    groups: FxHashMap<u32, Vec<u32>>,
    members: Vec<Member>,
    /// `records[i]` (the manager's; the first `record_slots.len()` are the landmarks') is slot
    /// `record_slots[i]`'s.
    record_slots: Vec<u32>,
    /// The (mesh, LOD) pairs in use, in a slab (iterated in index order: deterministic), and
    /// their indices.
    pairs: Vec<Option<PairUse>>,
    free_pairs: Vec<u32>,
    pair_index: FxHashMap<u64, u32>,
    /// Members whose shown BLAS is chosen again this frame.
    rechoose: Vec<u32>,
    /// Per leaf group, its detail that is not ready (no LOD of its mesh has data or a BLAS):
    /// the leaf's proxy waits for it every frame (`FarField::add_unready`). Such detail is
    /// looked at again only when data or a BLAS of its mesh comes (its selection's
    /// resolution), when its leaf flips or when it comes within r2.
    unready: FxHashMap<u32, u32>,
    /// Members choosing again next frame (their target is not built).
    unsettled: Vec<u32>,
    /// Last frame's `unsettled`, from the residency step to the cull step; and the cull step's
    /// scratch lists.
    waiting: Vec<u32>,
    kept_scratch: Vec<u32>,
    order_scratch: Vec<u32>,
    /// This frame's unsettled landmarks that waited without a look (tests check their
    /// distances).
    #[cfg(test)]
    waited_unlooked: Vec<u32>,
    scratch: Vec<u32>,
    queued_scratch: Vec<Due>,
    /// The steps' scratch lists for the mesh log: meshes, pair indices.
    log_scratch: (Vec<u32>, Vec<u32>),
    /// Candidates looked at this frame.
    pub examined: u32,
    /// Queued candidates found still inside their band this frame (they only waited again).
    pub waited: u32,
    /// Indices of the landmark records written since the last TLAS build (`TlasDelta`).
    pub changed: Vec<u32>,
}

impl Default for Landmarks {
    fn default() -> Self {
        Self {
            min_radius: f32::INFINITY,
            detail: false,
            hidden: Vec::new(),
            detail_records: 0,
            others: FxHashMap::default(),
            other_pos: Vec::new(),
            other_group: Vec::new(),
            odo: 0.0,
            cams: Vec::new(),
            all_due: true,
            index: Vec::new(),
            cands: Vec::new(),
            free_cands: Vec::new(),
            stamps: Vec::new(),
            queue: DueQueue::default(),
            next_stamp: 0,
            now: Vec::new(),
            meshes_changed: Vec::new(),
            groups: FxHashMap::default(),
            members: Vec::new(),
            record_slots: Vec::new(),
            pairs: Vec::new(),
            free_pairs: Vec::new(),
            pair_index: HashMap::default(),
            rechoose: Vec::new(),
            unready: FxHashMap::default(),
            unsettled: Vec::new(),
            waiting: Vec::new(),
            kept_scratch: Vec::new(),
            order_scratch: Vec::new(),
            #[cfg(test)]
            waited_unlooked: Vec::new(),
            scratch: Vec::new(),
            log_scratch: (Vec::new(), Vec::new()),
            queued_scratch: Vec::new(),
            examined: 0,
            waited: 0,
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

    /// Counts candidate `ci` as detail not ready in its leaf (`on`), or no longer.
    fn set_unready(&mut self, ci: u32, on: bool) {
        let c = &mut self.cands[ci as usize];
        if c.unready == on || c.group == NO_GROUP {
            return;
        }
        c.unready = on;
        let group = c.group;
        if on {
            *self.unready.entry(group).or_default() += 1;
        } else if let Some(n) = self.unready.get_mut(&group) {
            *n -= 1;
            if *n == 0 {
                self.unready.remove(&group);
            }
        }
    }

    /// Leaf groups whose proxy waits for their detail that is not ready.
    pub fn unready_leaves(&self) -> impl Iterator<Item = u32> + '_ {
        self.unready.keys().copied()
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

    /// Whether the set keeps the near leaves' detail beyond r2.
    pub fn detail(&self) -> bool {
        self.detail
    }

    /// Sets whether the set keeps the near leaves' detail; the caller re-adds every instance
    /// when it changed.
    pub fn set_detail(&mut self, on: bool) {
        self.detail = on;
    }

    /// Whether the set has anything to keep (landmarks or detail).
    pub fn is_active(&self) -> bool {
        self.min_radius.is_finite() || self.detail
    }

    /// Whether `slot` is a landmark now (a member, not near-leaf detail).
    #[cfg(test)]
    pub fn is_landmark(&self, slot: u32) -> bool {
        self.cand(slot)
            .is_some_and(|c| c.member != NONE && !self.members[c.member as usize].detail)
    }

    /// Checks that no landmark waits for a target that is built, and the distances the set
    /// gives the build order (after a frame's `update`): a pair
    /// whose entry is not built, targeted only by landmarks that waited for it this frame
    /// without a look (`unsettled_wait`), has this frame's exact nearest surface distance over
    /// them and whether one is in front of a camera. `None`: no difference; else the first one.
    /// Also the number of landmarks that waited so.
    #[cfg(test)]
    pub fn unbuilt_distance_error(
        &self,
        tables: &super::state::Tables,
        (cams, fwds): (&[Vec3], &[Vec3]),
        frame: u64,
    ) -> (Option<String>, usize) {
        let before: std::collections::HashSet<u32> = self.waited_unlooked.iter().copied().collect();
        let mut exact: FxHashMap<u32, (f32, bool)> = FxHashMap::default();
        let mut other: std::collections::HashSet<u32> = Default::default();
        let mut waiting = 0;
        for m in &self.members {
            let Some(c) = self.cand(m.slot) else { continue };
            // One waiting for its target shows it as soon as it is built.
            if let Some(p) = self.pairs[m.target as usize].as_ref() {
                let key = tables
                    .meshes
                    .get(p.mesh as usize)
                    .and_then(|m| m.as_ref())
                    .and_then(|m| m.lod_entry[p.lod as usize]);
                // (A target built this frame shows from the next: the frame's builds come
                // after its records.)
                let built_before = key.and_then(|k| tables.entries.get(k)).is_some_and(|e| {
                    e.state == super::state::EntryState::Built && e.created < frame
                });
                if c.unsettled && built_before {
                    let e = format!(
                        "slot {} waits for a built target (pair {})",
                        m.slot, m.target
                    );
                    return (Some(e), 0);
                }
            }
            if !c.unsettled || c.seen != frame || !before.contains(&m.slot) {
                // Looked at this frame, or not waiting: not what this checks.
                other.insert(m.target);
                continue;
            }
            waiting += 1;
            let d = cams
                .iter()
                .map(|p| p.distance_squared(c.center))
                .fold(f32::INFINITY, f32::min)
                .sqrt();
            let surface = (d - c.radius).max(0.0);
            let view = cams
                .iter()
                .zip(fwds)
                .any(|(p, f)| f.dot(c.center - *p) >= 0.0);
            let e = exact.entry(m.target).or_insert((f32::INFINITY, false));
            *e = (e.0.min(surface), e.1 | view);
        }
        for (i, p) in self.pairs.iter().enumerate() {
            let Some(p) = p else { continue };
            let key = tables
                .meshes
                .get(p.mesh as usize)
                .and_then(|m| m.as_ref())
                .and_then(|m| m.lod_entry[p.lod as usize]);
            if tables.built(key) || other.contains(&(i as u32)) {
                continue;
            }
            let Some(&(d, view)) = exact.get(&(i as u32)) else {
                continue;
            };
            let off = (p.frame_min - d).abs() > 1e-3 * (1.0 + d);
            if p.frame != frame || off || p.frame_in_view != view {
                let e = format!(
                    "pair {i} (mesh {}, LOD {}): frame {} min {} in view {}, exact {d} in view {view}",
                    p.mesh, p.lod, p.frame, p.frame_min, p.frame_in_view
                );
                return (Some(e), waiting);
            }
        }
        (None, waiting)
    }

    /// Before `invalidate`: the detail members' state goes to their instances as a visit at
    /// `frame` leaves it (the residency pass would have visited them), so the looks after
    /// continue from it.
    pub fn write_back_detail(&self, grid: &mut crate::spatial::GridIndex<InstanceHot>, frame: u64) {
        for m in self.members.iter().filter(|m| m.detail) {
            let (Some(c), Some(ge)) = (self.cand(m.slot), grid.get_mut(m.slot)) else {
                continue;
            };
            ge.data.last_visit = frame;
            ge.data.lod_target = c.lod;
            ge.data.culled = c.culled;
        }
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
        self.unready.clear();
        self.unsettled.clear();
        self.waiting.clear();
        self.queue.clear();
        self.hidden.clear();
        self.detail_records = 0;
        // Every record is pushed again (and listed) when the landmarks come back.
        self.changed.clear();
        for c in &mut self.cands {
            c.member = NONE;
            c.waiting = false;
            c.unsettled = false;
            c.culled = false;
            c.unready = false;
        }
        self.all_due = true;
    }

    /// Forgets every candidate (before re-adding them under a new radius).
    pub fn clear(&mut self) {
        self.invalidate();
        self.index.clear();
        self.cands.clear();
        self.free_cands.clear();
        self.stamps.clear();
        self.groups.clear();
        self.others.clear();
        self.other_pos.clear();
        self.other_group.clear();
        self.now.clear();
        self.meshes_changed.clear();
    }

    /// The instances of leaf `group` that the set does not keep (see `others`).
    pub fn others_of(&self, group: u32) -> &[u32] {
        self.others.get(&group).map_or(&[], Vec::as_slice)
    }

    /// Lists `slot` among its leaf's others (once).
    fn list_other(&mut self, slot: u32, group: u32) {
        if !self.detail || group == NO_GROUP {
            return;
        }
        if self.other_pos.len() <= slot as usize {
            self.other_pos.resize(slot as usize + 1, NONE);
        }
        if self.other_pos[slot as usize] != NONE {
            return;
        }
        let v = self.others.entry(group).or_default();
        v.push(slot);
        self.other_pos[slot as usize] = (v.len() - 1) as u32;
        self.other_group_of(slot, group);
    }

    /// Takes `slot` out of its leaf's others.
    fn unlist_other(&mut self, slot: u32) {
        let Some(&pos) = self.other_pos.get(slot as usize) else {
            return;
        };
        if pos == NONE {
            return;
        }
        let group = self.other_group[slot as usize];
        if let Some(v) = self.others.get_mut(&group) {
            if let Some(moved) = Self::list_remove(v, pos) {
                self.other_pos[moved as usize] = pos;
            }
            if v.is_empty() {
                self.others.remove(&group);
            }
        }
        self.other_pos[slot as usize] = NONE;
    }

    fn other_group_of(&mut self, slot: u32, group: u32) {
        if self.other_group.len() <= slot as usize {
            self.other_group.resize(slot as usize + 1, NO_GROUP);
        }
        self.other_group[slot as usize] = group;
    }

    /// A candidate the set cannot keep after all (its mesh is not static): out of the set,
    /// and the residency pass's like any other instance of its leaf.
    pub(super) fn disqualify(&mut self, slot: u32, records: &mut Vec<TlasInstance>) {
        let group = self.cand(slot).map_or(NO_GROUP, |c| c.group);
        self.remove(slot, records);
        self.list_other(slot, group);
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
        let wanted = is_static && (radius >= self.min_radius || (self.detail && group != NO_GROUP));
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
            self.list_other(slot, group);
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
            member: NONE,
            group,
            group_pos,
            seen: u64::MAX,
            waiting: false,
            lod: NONE_LOD,
            sel: NONE_LOD,
            unsettled: false,
            band: (0.0, 0.0),
            culled: false,
            unready: false,
        };
        let ci = slab_insert(&mut self.cands, &mut self.free_cands, cand);
        // Stamp 0 is never issued: a reused index's old entries stay stale.
        self.stamps.resize(self.cands.len(), 0);
        self.stamps[ci as usize] = 0;
        self.index[slot as usize] = ci;
        self.now.push(slot);
    }

    /// Every candidate of `mesh` is due now (its LOD errors or memory floor changed).
    pub fn mesh_changed(&mut self, mesh: u32) {
        if self.is_active() {
            self.meshes_changed.push(mesh);
        }
    }

    /// An instance was removed: it leaves the set and stops being a candidate.
    pub fn remove(&mut self, slot: u32, records: &mut Vec<TlasInstance>) {
        self.unlist_other(slot);
        if self.cand(slot).is_none() {
            return;
        }
        self.leave(slot, records);
        let ci = self.index[slot as usize] as usize;
        self.set_unready(ci as u32, false);
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
        self.cands[ci].slot = NONE;
        self.stamps[ci] = self.bump_stamp();
        self.free_cands.push(ci as u32);
        self.index[slot as usize] = NONE;
    }

    /// Invariants (for `check_invariants`).
    pub fn check(&self, records: &[TlasInstance]) -> Result<(), String> {
        if records.len() < self.record_slots.len() {
            return Err("fewer records than landmark records".into());
        }
        let mut counts: HashMap<u32, (u32, u32, u32, u32)> = HashMap::new();
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
            let wants_record =
                m.shown != NONE && !(m.detail && (c.culled || self.hidden.contains(&c.group)));
            if (m.record != NONE) != wants_record {
                return Err(format!("slot {}: a record without a BLAS or back", m.slot));
            }
            if m.counted != (m.shown != NONE && !(m.detail && c.culled)) {
                return Err(format!("slot {}: counted wrongly as visible", m.slot));
            }
            if m.counted {
                counts.entry(m.shown).or_default().3 += 1;
            }
        }
        for (i, p) in self.pairs.iter().enumerate() {
            let Some(p) = p else { continue };
            let (t, s, w, v) = counts.get(&(i as u32)).copied().unwrap_or_default();
            if p.targets != t
                || p.selecting.len() as u32 != s
                || p.showing.len() as u32 != w
                || p.visible != v
            {
                return Err(format!("pair ({}, {}) counts are off", p.mesh, p.lod));
            }
            if self.pair_index.get(&pair_key(p.mesh, p.lod)) != Some(&(i as u32)) {
                return Err(format!("pair ({}, {}) not indexed", p.mesh, p.lod));
            }
        }
        if self.record_slots.iter().any(|&s| !self.is_member(s)) {
            return Err("a landmark record of no member".into());
        }
        let mut unready: HashMap<u32, u32> = HashMap::new();
        for c in self.cands.iter().filter(|c| c.slot != NONE && c.unready) {
            *unready.entry(c.group).or_default() += 1;
        }
        if unready.len() != self.unready.len()
            || unready.iter().any(|(g, n)| self.unready.get(g) != Some(n))
        {
            return Err("the leaves' counts of detail not ready are off".into());
        }
        Ok(())
    }
}

/// Puts `item` in a vacant place of `items` (listed in `free`), or at the end; its index.
fn slab_insert<T>(items: &mut Vec<T>, free: &mut Vec<u32>, item: T) -> u32 {
    match free.pop() {
        Some(i) => {
            items[i as usize] = item;
            i
        }
        None => {
            items.push(item);
            (items.len() - 1) as u32
        }
    }
}

fn pair_key(mesh: u32, lod: u8) -> u64 {
    (u64::from(mesh) << 8) | u64::from(lod)
}
