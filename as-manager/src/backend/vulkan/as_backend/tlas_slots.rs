//! Stable TLAS record slots for updates in place (`TlasUpdates`): the order of the instance
//! buffer, kept from frame to frame so that an updated tree's leaves stay where they were
//! built.
//!
//! An update (`VK_BUILD_ACCELERATION_STRUCTURE_MODE_UPDATE_KHR`) keeps the tree of the last
//! build and refits its boxes to whatever each instance slot holds now. The manager's record
//! list is compact: a landmark that leaves is replaced by the last one, and the near field is
//! listed anew each frame, so record `i` of one frame may stand a kilometre from record `i` of
//! the one before. Written in list order, every update stretched boxes across the map: the
//! updated trees traced 10x slower on the H200 (`docs/GPU.md`). [`SlotKeeper`] gives each
//! record a slot of the instance buffer instead:
//! - a record that stays (same translation) keeps its slot, whatever its index in the list;
//!   a LOD change rewrites the slot in place;
//! - a record that leaves parks its slot where it stood (mask 0, scaled to a point), so the
//!   slot's box shrinks to a point inside the old one;
//! - a record that joins takes a parked slot.
//!
//! Only slots whose content changed are written (`SlotKeeper::written`). A build keeps the
//! layout too while the parked slots are few, so build frames write deltas as well.

use rustc_hash::FxHashMap;

use crate::backend::TlasDelta;
use crate::record::TlasInstance;

const NONE: u32 = u32::MAX;
/// Cell size for matching joining records to parked slots, metres.
const CELL_M: f32 = 64.0;
/// Rings of cells around a joining record's own searched for the nearest parked slot (a
/// joining record beyond the first ring counts as misplaced: `TlasUpdates::max_misplaced`).
const SEARCH_RINGS: i32 = 4;

fn cell_xz(x: f32, z: f32) -> (i32, i32) {
    ((x / CELL_M).floor() as i32, (z / CELL_M).floor() as i32)
}

fn cell_key((x, z): (i32, i32)) -> u64 {
    (u64::from(x as u32) << 32) | u64::from(z as u32)
}

fn cell_of_record(r: &TlasInstance) -> (i32, i32) {
    cell_xz(r.transform[3], r.transform[11])
}

/// What identifies a record from one frame to the next: its translation's bits, and for a
/// record at the origin (a mesh in world space, such as the far field's proxies, which all
/// have the identity transform) its BLAS too, or every proxy would match every other.
fn key(r: &TlasInstance) -> [u32; 4] {
    let t = [r.transform[3], r.transform[7], r.transform[11]];
    let blas = if t == [0.0; 3] {
        (r.blas_address ^ (r.blas_address >> 32)) as u32
    } else {
        0
    };
    [t[0].to_bits(), t[1].to_bits(), t[2].to_bits(), blas]
}

fn hash(k: [u32; 4]) -> u64 {
    u64::from(k[0])
        ^ (u64::from(k[1]) << 21)
        ^ (u64::from(k[2]) << 42)
        ^ (u64::from(k[2]) >> 22)
        ^ (u64::from(k[3]) << 11)
}

/// A parked record: never hit (mask 0), a point at `at`'s translation, on the parking BLAS.
fn parked(at: &TlasInstance, parking: u64) -> TlasInstance {
    let mut transform = [0.0f32; 12];
    (transform[3], transform[7], transform[11]) =
        (at.transform[3], at.transform[7], at.transform[11]);
    TlasInstance {
        transform,
        blas_address: parking,
        ..bytemuck::Zeroable::zeroed()
    }
}

/// Where the `k`-th of `spare` parked slots stands for `records`: spread evenly over them, at
/// a record's translation. (Putting half of them at the near field's records, where most
/// records join, made the H200's TLAS builds 1.7x as slow and found no more slots for the
/// joining records: `docs/GPU.md`.)
fn park_site(records: &[TlasInstance], k: usize, spare: usize) -> TlasInstance {
    let n = records.len();
    records
        .get(k * n / spare.max(1))
        .copied()
        .unwrap_or_else(bytemuck::Zeroable::zeroed)
}

/// The instance buffer's layout: which slot holds each of the manager's records. See the
/// module docs.
#[derive(Debug, Default)]
pub(super) struct SlotKeeper {
    /// The records in slot order, parked ones included: what the instance buffer holds.
    image: Vec<TlasInstance>,
    /// Per record of the last call (its index in the manager's list): its slot.
    slot_of: Vec<u32>,
    /// Parked slots, and each one's place in it (NONE: not parked).
    free: Vec<u32>,
    free_pos: Vec<u32>,
    /// Parked slots by the cell (`CELL_M`) where they stand (that of their parked record), and
    /// each one's place in its cell's list: a joining record takes a parked slot in its own
    /// cell or next to it, so the updated tree's box of that slot grows by little.
    cells: FxHashMap<u64, Vec<u32>>,
    cell_pos: Vec<u32>,
    /// Per slot: the call that last listed it as vacated or claimed it (`call`).
    vacated: Vec<u32>,
    claimed: Vec<u32>,
    /// Per record index: the call that last took it as changed (repeats in a delta).
    seen: Vec<u32>,
    call: u32,
    /// Vacated slots by key: chains through `next` (a few records may share a translation).
    heads: FxHashMap<u64, u32>,
    next: Vec<u32>,
    vacated_list: Vec<u32>,
    joining: Vec<u32>,
    /// This call's records matched without hashing (index, slot), and the others.
    matched: Vec<(u32, u32)>,
    leftover: Vec<u32>,
    /// Slots written by the last call (`all`: every slot).
    pub written: Vec<u32>,
    pub all: bool,
    /// The next call ignores its delta (see `distrust_next_delta`).
    distrust: bool,
    /// Records of the last call that took a slot another record held (joined, or moved).
    pub joined: u32,
    /// Of them, those that found no parked slot in or next to their cell, since the last
    /// layout or `reset_misplaced` (they stretch the updated tree most).
    pub misplaced: u32,
    /// Of the last call's joining records, those misplaced.
    pub misplaced_now: u32,
}

impl SlotKeeper {
    /// Slots laid out (records and parked ones).
    pub fn len(&self) -> usize {
        self.image.len()
    }

    /// What the instance buffer holds, in slot order.
    pub fn image(&self) -> &[TlasInstance] {
        &self.image
    }

    /// Parked slots.
    pub fn parked(&self) -> usize {
        self.free.len()
    }

    /// Forgets the layout (the next call lays it out anew).
    pub fn reset(&mut self) {
        self.image.clear();
        self.slot_of.clear();
        self.clear_free();
        self.distrust = false;
        self.misplaced = 0;
    }

    fn clear_free(&mut self) {
        self.free.clear();
        self.cells.clear();
        self.free_pos.clear();
        self.cell_pos.clear();
    }

    /// Starts counting `misplaced` again (at a build: the tree is new).
    pub fn reset_misplaced(&mut self) {
        self.misplaced = 0;
    }

    /// Parks slot `s` (already holding its parked record).
    fn push_free(&mut self, s: u32) {
        self.free_pos[s as usize] = self.free.len() as u32;
        self.free.push(s);
        self.put_cell(s);
    }

    /// Lists parked slot `s` in the cell where it stands.
    fn put_cell(&mut self, s: u32) {
        let c = cell_key(cell_of_record(&self.image[s as usize]));
        let list = self.cells.entry(c).or_default();
        self.cell_pos[s as usize] = list.len() as u32;
        list.push(s);
    }

    /// Takes parked slot `s` out of the parked ones.
    fn take_free(&mut self, s: u32) {
        let p = self.free_pos[s as usize];
        self.free.swap_remove(p as usize);
        if let Some(&moved) = self.free.get(p as usize) {
            self.free_pos[moved as usize] = p;
        }
        self.free_pos[s as usize] = NONE;
        self.take_cell(s);
    }

    /// Takes parked slot `s` out of its cell's list (while it still holds its parked record).
    fn take_cell(&mut self, s: u32) {
        let c = cell_key(cell_of_record(&self.image[s as usize]));
        let list = self.cells.get_mut(&c).expect("a parked slot's cell");
        let q = self.cell_pos[s as usize];
        list.swap_remove(q as usize);
        if let Some(&moved) = list.get(q as usize) {
            self.cell_pos[moved as usize] = q;
        }
        if list.is_empty() {
            self.cells.remove(&c);
        }
    }

    /// A parked slot for a record joining at `r`'s place: the nearest by rings of cells
    /// around its own, out to `SEARCH_RINGS` (`true` if within the first ring: its cell or a
    /// neighbour), else any.
    fn free_slot_for(&mut self, r: &TlasInstance) -> Option<(u32, bool)> {
        let (cx, cz) = cell_of_record(r);
        for ring in 0..=SEARCH_RINGS {
            let mut found = None;
            'ring: for dx in -ring..=ring {
                for dz in -ring..=ring {
                    if dx.abs().max(dz.abs()) != ring {
                        continue;
                    }
                    let cell = self.cells.get(&cell_key((cx + dx, cz + dz)));
                    if let Some(&s) = cell.and_then(|l| l.last()) {
                        found = Some(s);
                        break 'ring;
                    }
                }
            }
            if let Some(s) = found {
                self.take_free(s);
                return Some((s, ring <= 1));
            }
        }
        let s = *self.free.last()?;
        self.take_free(s);
        Some((s, false))
    }

    /// The next call's delta may not be relative to the last call (that frame was aborted):
    /// it matches every record by its place instead, keeping the layout.
    pub fn distrust_next_delta(&mut self) {
        self.distrust = true;
    }

    /// Lays the slots out anew: record `i` in slot `i`, then parked slots up to `count`, each
    /// at a record's translation (`park_site`; a cluster of parked slots in one place makes a
    /// degenerate subtree that builds and updates slowly). Every slot is written.
    pub fn lay_out(&mut self, records: &[TlasInstance], count: usize, parking: u64) {
        let (n, count) = (records.len(), count.max(records.len()));
        self.image.clear();
        self.image.extend_from_slice(records);
        let spare = count - n;
        for k in 0..spare {
            self.image
                .push(parked(&park_site(records, k, spare), parking));
        }
        self.slot_of.clear();
        self.slot_of.extend(0..records.len() as u32);
        self.clear_free();
        self.resize_marks();
        for s in records.len() as u32..count as u32 {
            self.push_free(s);
        }
        self.written.clear();
        self.all = true;
        self.distrust = false;
        self.joined = 0;
        self.misplaced = 0;
        self.misplaced_now = 0;
    }

    /// At a build (the tree is new, slot order does not matter): the parked slots move to
    /// where `lay_out` puts them for this frame's records, rather than where records left.
    /// Writes the parked slots; `place` must have placed `records` first.
    pub fn repark(&mut self, records: &[TlasInstance], parking: u64) {
        let slots = std::mem::take(&mut self.free);
        for &s in &slots {
            self.take_cell(s);
        }
        self.free = slots;
        let spare = self.free.len();
        for k in 0..spare {
            let s = self.free[k];
            self.image[s as usize] = parked(&park_site(records, k, spare), parking);
            self.put_cell(s);
            self.written.push(s);
        }
    }

    fn resize_marks(&mut self) {
        let n = self.image.len();
        self.vacated.resize(n, 0);
        self.claimed.resize(n, 0);
        self.next.resize(n, NONE);
        self.free_pos.resize(n, NONE);
        self.cell_pos.resize(n, NONE);
    }

    /// Places this call's records in the slots of the last call's, `delta` naming the records
    /// equal to the last call's at the same index. `false` (nothing changed): they do not fit,
    /// lay the slots out anew.
    pub fn place(&mut self, records: &[TlasInstance], delta: TlasDelta<'_>, parking: u64) -> bool {
        let prev = self.slot_of.len();
        if records.len() > self.image.len() {
            return false;
        }
        let delta = if std::mem::take(&mut self.distrust) {
            TlasDelta::ALL
        } else {
            delta
        };
        self.call = self.call.wrapping_add(1).max(1);
        let call = self.call;
        if self.seen.len() < records.len().max(prev) {
            self.seen.resize(records.len().max(prev), 0);
        }
        self.written.clear();
        self.all = false;
        self.joined = 0;
        // Records at or after `stable` are all taken as changed.
        let stable = delta.stable.min(prev).min(records.len());
        let changed = || {
            delta
                .changed
                .iter()
                .map(|&i| i as usize)
                .filter(move |&i| i < stable)
        };
        // First without hashing: a changed record standing where the last call's record at
        // its index stood takes that record's slot (a LOD change). The tail (the near field,
        // the proxies) is mostly listed in the order of the last call, or shifted by a record
        // that joined or left: there the index of the last match's shift, or one off, is
        // tried too.
        self.leftover.clear();
        self.matched.clear();
        let mut shift = 0isize;
        for i in changed().chain(stable..records.len()) {
            if self.seen[i] == call {
                continue;
            }
            self.seen[i] = call;
            let k = key(&records[i]);
            let mut hit = None;
            // A changed index before `stable` (a landmark's LOD changed, or another took its
            // place) may only take its own index's slot; the tail also the shifted ones.
            let offsets: &[isize] = if i >= stable {
                &[0, shift, -1, 1]
            } else {
                &[0]
            };
            if i < prev {
                for &off in offsets {
                    let j = i as isize + off;
                    let lo = if i >= stable { stable as isize } else { 0 };
                    if j < lo || j >= prev as isize {
                        continue;
                    }
                    let s = self.slot_of[j as usize];
                    if self.claimed[s as usize] != call && key(&self.image[s as usize]) == k {
                        hit = Some(s);
                        if i >= stable {
                            shift = off;
                        }
                        break;
                    }
                }
            }
            match hit {
                Some(s) => {
                    self.claimed[s as usize] = call;
                    self.matched.push((i as u32, s));
                }
                None => self.leftover.push(i as u32),
            }
        }
        // The other slots of the last call's records that may have left (those at the changed
        // indices and the tail), keyed for the records that come back.
        self.heads.clear();
        self.vacated_list.clear();
        for i in changed().chain(stable..prev) {
            let s = self.slot_of[i];
            if self.vacated[s as usize] == call {
                continue;
            }
            self.vacated[s as usize] = call;
            self.vacated_list.push(s);
            if self.claimed[s as usize] == call {
                continue;
            }
            let h = hash(key(&self.image[s as usize]));
            let head = self.heads.entry(h).or_insert(NONE);
            self.next[s as usize] = *head;
            *head = s;
        }
        self.slot_of.resize(records.len(), NONE);
        self.joining.clear();
        for m in 0..self.matched.len() {
            let (i, s) = self.matched[m];
            self.put(i as usize, s, &records[i as usize]);
        }
        for m in 0..self.leftover.len() {
            let i = self.leftover[m] as usize;
            match self.take_vacated(key(&records[i])) {
                Some(s) => {
                    self.claimed[s as usize] = call;
                    self.put(i, s, &records[i]);
                }
                None => self.joining.push(i as u32),
            }
        }
        // What left parks where it stood; what joined takes a parked slot.
        for k in 0..self.vacated_list.len() {
            let s = self.vacated_list[k];
            if self.claimed[s as usize] != call {
                self.image[s as usize] = parked(&self.image[s as usize], parking);
                self.written.push(s);
                self.push_free(s);
            }
        }
        let misplaced_before = self.misplaced;
        for k in 0..self.joining.len() {
            let i = self.joining[k] as usize;
            let (s, near) = self
                .free_slot_for(&records[i])
                .expect("fewer records than slots");
            self.misplaced += u32::from(!near);
            self.image[s as usize] = records[i];
            self.slot_of[i] = s;
            self.written.push(s);
        }
        self.joined = self.joining.len() as u32;
        self.misplaced_now = self.misplaced - misplaced_before;
        true
    }

    /// Record `i` (`r`) in slot `s`, written if the slot held something else.
    fn put(&mut self, i: usize, s: u32, r: &TlasInstance) {
        self.slot_of[i] = s;
        if self.image[s as usize] != *r {
            self.image[s as usize] = *r;
            self.written.push(s);
        }
    }

    /// A vacated slot whose record had key `k`, unlinked from its chain.
    fn take_vacated(&mut self, k: [u32; 4]) -> Option<u32> {
        let h = hash(k);
        let head = *self.heads.get(&h)?;
        let (mut prev, mut s) = (NONE, head);
        while s != NONE {
            let after = self.next[s as usize];
            if key(&self.image[s as usize]) == k {
                if prev == NONE {
                    if after == NONE {
                        self.heads.remove(&h);
                    } else {
                        self.heads.insert(h, after);
                    }
                } else {
                    self.next[prev as usize] = after;
                }
                return Some(s);
            }
            (prev, s) = (s, after);
        }
        None
    }

    /// Invariants, for tests: every record is in its slot, each slot holds at most one, and
    /// the other slots are parked on `parking`.
    #[cfg(test)]
    fn check(&self, records: &[TlasInstance], parking: u64) -> Result<(), String> {
        let mut owner = vec![NONE; self.image.len()];
        if self.slot_of.len() != records.len() {
            return Err("slot_of length".into());
        }
        for (i, (&s, r)) in self.slot_of.iter().zip(records).enumerate() {
            let s = s as usize;
            if s >= self.image.len() || owner[s] != NONE {
                return Err(format!("record {i}: slot {s} out of range or shared"));
            }
            owner[s] = i as u32;
            if self.image[s] != *r {
                return Err(format!("record {i}: slot {s} holds another record"));
            }
        }
        let parked: Vec<u32> = (0..self.image.len() as u32)
            .filter(|&s| owner[s as usize] == NONE)
            .collect();
        let mut free = self.free.clone();
        free.sort_unstable();
        if free != parked {
            return Err("free slots are not the unowned ones".into());
        }
        let mut by_cell: Vec<u32> = self.cells.values().flatten().copied().collect();
        by_cell.sort_unstable();
        if by_cell != parked {
            return Err("the cells' parked slots are not the unowned ones".into());
        }
        for (&c, list) in &self.cells {
            for (q, &s) in list.iter().enumerate() {
                let here = cell_key(cell_of_record(&self.image[s as usize]));
                if here != c || self.cell_pos[s as usize] != q as u32 {
                    return Err(format!("parked slot {s} listed in the wrong cell or place"));
                }
            }
        }
        if parked.iter().any(|&s| {
            let r = &self.image[s as usize];
            r.mask() != 0 || r.blas_address != parking
        }) {
            return Err("an unowned slot is not parked".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Affine3A, Vec3};

    const PARKING: u64 = 0xdead_0000;

    fn rec(id: u32, blas: u64) -> TlasInstance {
        let t = Affine3A::from_translation(Vec3::new(id as f32 * 3.0, 1.0, -(id as f32)));
        TlasInstance::new(&t, id, 0xff, 0, 0, blas)
    }

    /// A small deterministic generator.
    struct Lcg(u64);
    impl Lcg {
        fn below(&mut self, n: usize) -> usize {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 33) as usize) % n.max(1)
        }
    }

    /// A list like the manager's: landmarks first (swap-removed, appended, listed in
    /// `changed`), then a tail listed anew each frame (shifted by inserts and removals).
    #[test]
    fn records_keep_their_slots_through_churn() {
        let mut rng = Lcg(7);
        let mut keeper = SlotKeeper::default();
        let mut head: Vec<TlasInstance> = (0..300).map(|i| rec(i, 1)).collect();
        let mut tail: Vec<u32> = (1000..1200).collect();
        let mut next_id = 5000;
        let list = |head: &[TlasInstance], tail: &[u32]| -> Vec<TlasInstance> {
            let mut v = head.to_vec();
            v.extend(tail.iter().map(|&id| rec(id, 2)));
            v
        };
        let mut records = list(&head, &tail);
        keeper.lay_out(&records, records.len() + 64, PARKING);
        keeper.check(&records, PARKING).unwrap();
        let (mut kept, mut stayed, mut written) = (0usize, 0usize, 0usize);
        let (mut tail_records, mut unhashed) = (0usize, 0usize);
        for _frame in 0..200 {
            let before: std::collections::HashMap<[u32; 4], usize> = keeper
                .image()
                .iter()
                .enumerate()
                .filter(|(_, r)| r.mask() != 0)
                .map(|(s, r)| (key(r), s))
                .collect();
            let mut changed = Vec::new();
            // Landmarks: one leaves (the last takes its place), one joins, one changes LOD.
            let r = rng.below(head.len());
            head.swap_remove(r);
            if r < head.len() {
                changed.push(r as u32);
            }
            head.push(rec(next_id, 1));
            next_id += 1;
            changed.push((head.len() - 1) as u32);
            let l = rng.below(head.len());
            head[l].blas_address += 16;
            changed.push(l as u32);
            // The tail: an insert and a removal somewhere, the rest in the same order.
            let at = rng.below(tail.len());
            tail.insert(at, next_id);
            next_id += 1;
            tail.remove(rng.below(tail.len()));
            let new = list(&head, &tail);
            let delta = TlasDelta {
                stable: head.len(),
                changed: &changed,
            };
            assert!(keeper.place(&new, delta, PARKING));
            keeper.check(&new, PARKING).unwrap();
            written += keeper.written.len();
            (tail_records, unhashed) = (tail_records + tail.len(), unhashed + keeper.matched.len());
            for (i, r) in new.iter().enumerate() {
                if let Some(&s) = before.get(&key(r)) {
                    stayed += 1;
                    kept += usize::from(keeper.slot_of[i] as usize == s);
                }
            }
            records = new;
        }
        assert_eq!(kept, stayed, "every record that stayed kept its slot");
        // The shifted tail is matched by index, not through the hash map.
        assert!(
            unhashed * 100 >= tail_records * 95,
            "{unhashed} of {tail_records} tail records matched by index"
        );
        // About 4 changes a frame (a leave, two joins, a LOD change, a tail removal) and no
        // rewrite of the shifted tail.
        assert!(written <= 200 * 8, "{written} slots written");
        assert_eq!(keeper.len(), 500 + 64);
        let _ = records;
    }

    /// A joining record takes the parked slot in its cell, not the last one parked.
    #[test]
    fn joining_records_take_a_parked_slot_near_them() {
        let at = |x: f32, z: f32, id: u32| {
            TlasInstance::new(
                &Affine3A::from_translation(Vec3::new(x, 0.0, z)),
                id,
                0xff,
                0,
                0,
                1,
            )
        };
        let mut keeper = SlotKeeper::default();
        let a: Vec<TlasInstance> = (0..40).map(|i| at(i as f32 * 200.0, 0.0, i)).collect();
        keeper.lay_out(&a, 40, PARKING);
        // Records 5 and 30 leave; one joins 10 m from where 5 stood, one 10 m from 30.
        let mut b = a.clone();
        b[5] = at(5.0 * 200.0 + 10.0, 0.0, 100);
        b[30] = at(30.0 * 200.0 - 10.0, 5.0, 101);
        b.swap(5, 30);
        assert!(keeper.place(
            &b,
            TlasDelta {
                stable: 40,
                changed: &[5, 30]
            },
            PARKING
        ));
        keeper.check(&b, PARKING).unwrap();
        assert_eq!((keeper.slot_of[5], keeper.slot_of[30]), (30, 5));
        assert_eq!((keeper.joined, keeper.misplaced), (2, 0));
        // One joining far from any parked slot is counted as misplaced.
        let mut c = b.clone();
        c[7] = at(-5000.0, -5000.0, 102);
        assert!(keeper.place(
            &c,
            TlasDelta {
                stable: 40,
                changed: &[7]
            },
            PARKING
        ));
        keeper.check(&c, PARKING).unwrap();
        assert_eq!((keeper.joined, keeper.misplaced), (1, 1));
        keeper.reset_misplaced();
        assert_eq!(keeper.misplaced, 0);
        // At a build the parked slots move to where records stand now.
        let d = c[..36].to_vec();
        let delta = TlasDelta {
            stable: 36,
            changed: &[],
        };
        assert!(keeper.place(&d, delta, PARKING));
        keeper.repark(&d, PARKING);
        keeper.check(&d, PARKING).unwrap();
        assert_eq!(keeper.parked(), 4);
        for &s in &keeper.free {
            let x = keeper.image[s as usize].transform[3];
            assert!(
                d.iter().any(|r| r.transform[3] == x),
                "slot {s} parked at {x}"
            );
        }
    }

    /// Records in world space (the identity transform, as the far field's proxies) are told
    /// apart by their BLAS: each keeps its slot when the list is reordered.
    #[test]
    fn records_at_the_origin_keep_their_slots_by_blas() {
        let proxy = |b: u64| TlasInstance::new(&Affine3A::IDENTITY, 0, 0xff, 0, 0, b << 8);
        let mut keeper = SlotKeeper::default();
        let a: Vec<TlasInstance> = (1..=10).map(proxy).collect();
        keeper.lay_out(&a, 12, PARKING);
        let b: Vec<TlasInstance> = [3, 9, 1, 10, 2, 8, 4, 7, 5, 6].map(proxy).to_vec();
        assert!(keeper.place(&b, TlasDelta::ALL, PARKING));
        keeper.check(&b, PARKING).unwrap();
        for (i, r) in b.iter().enumerate() {
            let was = a.iter().position(|x| x == r).unwrap();
            assert_eq!(keeper.slot_of[i] as usize, was, "proxy {i} changed slot");
        }
        assert_eq!(keeper.written.len(), 0);
    }

    #[test]
    fn too_many_records_ask_for_a_new_layout() {
        let mut keeper = SlotKeeper::default();
        let a: Vec<TlasInstance> = (0..10).map(|i| rec(i, 1)).collect();
        keeper.lay_out(&a, 12, PARKING);
        let b: Vec<TlasInstance> = (0..13).map(|i| rec(i, 1)).collect();
        assert!(!keeper.place(&b, TlasDelta::ALL, PARKING));
        keeper.check(&a, PARKING).unwrap();
        let c: Vec<TlasInstance> = (2..14).map(|i| rec(i, 1)).collect();
        assert!(keeper.place(&c, TlasDelta::ALL, PARKING));
        keeper.check(&c, PARKING).unwrap();
        // 0 and 1 left, 10..14 joined: two parked slots were taken, two freed.
        assert_eq!((keeper.joined, keeper.parked()), (4, 0));
    }

    #[test]
    fn shared_translations_and_repeated_changes() {
        let mut keeper = SlotKeeper::default();
        let mut a: Vec<TlasInstance> = (0..6).map(|i| rec(i % 2, i as u64)).collect();
        keeper.lay_out(&a, 8, PARKING);
        a.swap(0, 5);
        a[3].blas_address = 99;
        let delta = TlasDelta {
            stable: 6,
            changed: &[0, 5, 5, 3, 0],
        };
        assert!(keeper.place(&a, delta, PARKING));
        keeper.check(&a, PARKING).unwrap();
        assert_eq!(keeper.joined, 0);
    }
}
