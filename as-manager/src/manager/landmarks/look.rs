//! Looking at candidates: the odometer, which candidates are due, and the look itself.

use glam::Vec3;

use super::*;
use crate::lod::LodSelector;
use crate::manager::state::{InstanceHot, Tables};
use crate::mesh::MeshKind;
use crate::spatial::GridIndex;

impl Landmarks {
    /// Counts this frame's camera travel; a change of camera count, or a move longer than
    /// the due queue's ring (a teleport), makes everything due.
    pub(super) fn advance(&mut self, cams: &[Vec3]) {
        if cams.len() != self.cams.len() {
            self.all_due = true;
        } else {
            let moved = cams
                .iter()
                .zip(&self.cams)
                .map(|(a, b)| a.distance(*b))
                .fold(0.0f32, f32::max);
            if moved.is_finite() && f64::from(moved) <= queue::MAX_STEP_M {
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
    pub(super) fn collect_due(
        &mut self,
        tables: &mut Tables,
        need_data: bool,
        groups_flipped: &mut Vec<u32>,
        out: &mut Vec<u32>,
        queued: &mut Vec<Due>,
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
        // Selections whose resolution changed (data or BLASes of the mesh came or went): only
        // the pairs of the meshes logged since the last frame can have (`MeshLog`).
        let (mut meshes, mut pairs) = std::mem::take(&mut self.log_scratch);
        let logged = tables.mesh_log.take_resolve(&mut meshes);
        self.logged_pairs(logged, &meshes, &mut pairs);
        for &i in &pairs {
            let p = self.pairs[i as usize].as_mut().expect("a live pair");
            if let Some(resolved) = selection_now(p, tables, need_data) {
                if resolved != p.resolved {
                    p.resolved = resolved;
                    out.extend_from_slice(&p.selecting);
                    out.append(&mut p.unusable);
                }
            }
        }
        #[cfg(debug_assertions)]
        for p in self.pairs.iter().flatten() {
            let now = selection_now(p, tables, need_data);
            debug_assert!(
                now.is_none_or(|r| r == p.resolved),
                "pair ({}, {}) resolves to {now:?}, not {}: a change to its mesh was not logged",
                p.mesh,
                p.lod,
                p.resolved
            );
        }
        self.log_scratch = (meshes, pairs);
        // Stale entries are skipped by the caller (the events looked at first may make more).
        self.queue.pop_due(self.odo, queued);
    }

    /// Reads, ahead of the looks, what they read first: each queue entry's stamp and, for the
    /// events and the live entries, the candidate. The reads are independent of each other, so
    /// the core overlaps their cache misses, where the looks, one after another, would wait for
    /// each in turn. Decides nothing.
    pub(super) fn warm(&self, due: &[u32], queued: &[Due]) {
        let mut acc = 0u64;
        for &slot in due {
            acc ^= self.cand(slot).map_or(0, |c| c.seen);
        }
        for e in queued {
            let live = self.stamps.get(e.ci as usize) == Some(&e.stamp);
            if live {
                acc ^= self.cands.get(e.ci as usize).map_or(0, |c| c.seen);
            }
        }
        std::hint::black_box(acc);
    }

    /// `warm`'s counterpart for the cull step's choices: reads each listed landmark's
    /// candidate, member and grid entry ahead of the choices, whose reads would otherwise
    /// wait one after another. Decides nothing.
    pub(super) fn warm_members(&self, slots: &[u32], grid: &GridIndex<InstanceHot>) {
        let mut acc = 0u64;
        for &slot in slots {
            let Some(c) = self.cand(slot) else {
                continue;
            };
            acc ^= self.members.get(c.member as usize).map_or(0, |m| m.chosen);
            acc ^= grid.get(slot).map_or(0, |g| u64::from(g.data.lod_target));
        }
        std::hint::black_box(acc);
    }

    /// A fresh stamp for a candidate's queue entry (never 0, which a new candidate holds).
    pub(super) fn bump_stamp(&mut self) -> u32 {
        self.next_stamp = self.next_stamp.wrapping_add(1).max(1);
        self.next_stamp
    }

    /// Whether `e` is the candidate's live entry (not stale: the candidate was not looked at,
    /// removed or queued again since).
    pub(super) fn is_live(&self, e: &Due) -> bool {
        self.stamps[e.ci as usize] == e.stamp
    }

    /// Looks at the candidate again once its distance may have left `lo..hi` (the distances
    /// between which this look's outcome holds; never, for an unbounded band: only an event
    /// makes it due). Queued for the travel to the nearer end; `wait_if_inside` waits again
    /// while it is still inside.
    pub(super) fn due_between(&mut self, ci: u32, lo: f32, hi: f32, d: f32) {
        let stamp = self.bump_stamp();
        self.stamps[ci as usize] = stamp;
        // A margin for rounding in the distances (f32) and the odometer.
        let m = 0.01 + 1e-4 * d;
        let band = (lo + m, hi - m);
        self.cands[ci as usize].band = band;
        if lo <= 0.0 && hi == f32::INFINITY {
            return;
        }
        let c = &self.cands[ci as usize];
        if c.unsettled && c.member != NONE {
            // A landmark choosing its BLAS every frame is looked at every frame until its
            // target is built: an entry now would only go stale in the queue (they were most
            // of what the queue popped after a start or a teleport). `landmarks_cull` makes it
            // due at once when it settles, and that look queues it.
            return;
        }
        let slack = (d - band.0).min(band.1 - d).max(0.0);
        let center = self.cands[ci as usize].center;
        let entry = Due {
            ci,
            stamp,
            center,
            band,
        };
        self.queue.push(self.odo + f64::from(slack), entry);
    }

    /// An unsettled landmark (`Landmarks::unsettled`) whose distance is still inside its last
    /// look's band, with no event this frame: the look would decide the same, so only its
    /// distance is taken, into its target pair's distances (which order that pair's build), as
    /// the look does. Returns `false` when it needs a look (outside its band, or no longer an
    /// unsettled landmark); `true` also when there is nothing to look at (vacant, or looked at
    /// this frame).
    pub(super) fn unsettled_wait(&mut self, ci: u32, x: &Look<'_>) -> bool {
        let frame = x.p.frame;
        let Some(&c) = self.cands.get(ci as usize) else {
            return true;
        };
        if c.slot == NONE || c.seen == frame {
            return true;
        }
        if c.member == NONE || !c.unsettled {
            return false;
        }
        let (center, radius) = (c.center, c.radius);
        let d = nearest2(x.cams, center).sqrt();
        let (lo, hi) = c.band;
        if !(d > lo && d < hi) {
            return false;
        }
        self.cands[ci as usize].seen = frame;
        self.waited += 1;
        #[cfg(test)]
        self.waited_unlooked.push(c.slot);
        let target = self.members[c.member as usize].target;
        let surface = (d - radius).max(0.0);
        self.note_target_distance(target, surface, in_view(x, center), frame);
        true
    }

    /// A target's look (or wait) this frame: its surface distance and whether it is in front of
    /// a camera go into its target pair's lower bound and this frame's exact figures.
    fn note_target_distance(&mut self, target: u32, surface: f32, in_view: bool, frame: u64) {
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
        crate::manager::state::merge_nearest(
            &mut pair.frame,
            &mut pair.frame_min,
            &mut pair.frame_in_view,
            frame,
            surface,
            in_view,
        );
    }

    /// A live queue entry whose candidate's distance is still inside the band of its last
    /// look: the look would decide the same (every other input changes by an event, which
    /// looks at it in full), so it waits again, for the travel to the band's nearer end.
    /// Touches the queue only. (A landmark choosing its BLAS every frame, or a candidate
    /// waiting for LOD data, has no live entry: it is an event each frame, or its look queued
    /// nothing.)
    pub(super) fn wait_if_inside(&mut self, e: Due, cams: &[Vec3]) -> bool {
        let d = nearest2(cams, e.center).sqrt();
        let (lo, hi) = e.band;
        if !(d > lo && d < hi) {
            return false;
        }
        let slack = ((d - lo).min(hi - d) - 0.01).max(0.0);
        self.queue.push(self.odo + f64::from(slack), e);
        self.waited += 1;
        true
    }
}

/// What a pair's selection resolves to now (`None`: nothing to check: no landmark selects it
/// and no candidate waits for it, or its mesh is gone).
fn selection_now(p: &PairUse, tables: &Tables, need_data: bool) -> Option<u8> {
    if p.selecting.is_empty() && p.unusable.is_empty() {
        return None;
    }
    let Some(Some(mesh)) = tables.meshes.get(p.mesh as usize) else {
        return None;
    };
    let built = |l: usize| tables.built(mesh.lod_entry[l]);
    Some(
        mesh.with_data(p.lod as usize, need_data, built)
            .map_or(NONE_LOD, |l| l as u8),
    )
}

/// Whether `c` is in front of some camera (a half-space test, as the build priority's).
fn in_view(x: &Look<'_>, c: Vec3) -> bool {
    x.cams.iter().zip(x.fwds).any(|(p, f)| f.dot(c - *p) >= 0.0)
}

/// Squared distance from the nearest camera to `c` (as the residency pass computes it, so
/// both agree on which side of r2 an instance is).
fn nearest2(cams: &[Vec3], c: Vec3) -> f32 {
    cams.iter()
        .map(|p| p.distance_squared(c))
        .fold(f32::INFINITY, f32::min)
}

/// The look at one candidate (see `Landmarks::evaluate`), with what it borrows.
pub(super) struct Look<'a> {
    pub(super) grid: &'a mut GridIndex<InstanceHot>,
    pub(super) tables: &'a mut Tables,
    pub(super) lod: &'a LodSelector,
    pub(super) culler: &'a crate::cull::InstanceCuller,
    pub(super) far: &'a crate::manager::far::FarField,
    pub(super) cams: &'a [Vec3],
    pub(super) fwds: &'a [Vec3],
    pub(super) records: &'a mut Vec<TlasInstance>,
    pub(super) p: LandmarkParams,
}

impl Landmarks {
    /// Whether `cand` is still a candidate (`track`'s rule, after a move).
    fn wanted(&self, cand: &Cand) -> bool {
        cand.radius >= self.min_radius || (self.detail && cand.group != NO_GROUP)
    }

    /// Looks at candidate `ci` unless vacant or looked at this frame.
    pub(super) fn look_at(&mut self, ci: u32, x: &mut Look<'_>) {
        let Some(c) = self.cands.get_mut(ci as usize) else {
            return;
        };
        if c.slot == NONE || c.seen == x.p.frame {
            return;
        }
        c.seen = x.p.frame;
        c.waiting = false;
        self.evaluate(ci, x);
    }

    /// Looks at candidate `slot`: joins, updates or leaves the set, and says when to look next.
    pub(super) fn evaluate(&mut self, ci: u32, x: &mut Look<'_>) {
        let frame = x.p.frame;
        // Counted as not ready until this look says so again.
        self.set_unready(ci, false);
        let cand = self.cands[ci as usize];
        let slot = cand.slot;
        if !self.wanted(&cand) {
            // Moved and shrank (`track`).
            self.remove(slot, x.records);
            return;
        }
        self.examined += 1;
        let is_member = cand.member != NONE;
        let was_detail = is_member && self.members[cand.member as usize].detail;
        let (c, radius) = (cand.center, cand.radius);
        let d2 = nearest2(x.cams, c);
        let d = d2.sqrt();
        let reach = x.p.r2 + radius;
        let within_r2 = d2 <= reach * reach;
        // A landmark whose leaf turned near is checked first; any other candidate's leaf only
        // once it is not out by distance (unless the set keeps the detail too).
        let near_leaf = |x: &Look<'_>| x.far.is_near_leaf(cand.group);
        let detail = self.detail && !within_r2 && near_leaf(x);
        if within_r2 || (!self.detail && is_member && near_leaf(x)) {
            // Near field now (within r2, or its leaf is on the detail side and the residency
            // pass keeps that): shown by the residency pass, which continues from the
            // member's LOD and cull state.
            if is_member {
                if let Some(ge) = x.grid.get_mut(slot) {
                    ge.data.last_visit = frame.wrapping_sub(1);
                    ge.data.culled = was_detail && cand.culled;
                }
                self.leave(slot, x.records);
            }
            // The leaf flipping back is an event; within r2, leaving it is the threshold.
            let hi = if within_r2 { reach } else { f32::INFINITY };
            self.due_between(ci, f32::NEG_INFINITY, hi, d);
            return;
        }
        if is_member && was_detail != detail {
            // Its leaf flipped: it stays a member and continues as the other kind from its
            // LOD and cull state (what a visit last frame would have left: a landmark is
            // never culled). Its record goes and is chosen again in `landmarks_cull` (a
            // landmark's shows beside its leaf's proxy, a detail one hides with it). Leaving
            // and joining again cost about twice as much: 50 flips a frame at 8.2 m a frame.
            let m = cand.member as usize;
            self.drop_record(m, x.records);
            self.members[m].detail = detail;
            self.cands[ci as usize].unsettled = false;
            self.rechoose.push(slot);
        }
        if detail {
            return self.look_detail(ci, x, d);
        }
        let (kt, range) = (x.p.keep_tan, x.p.range);
        if d - radius > range || radius <= kt * 0.9 * d {
            // Out even with the hysteresis: no need to look at the instance.
            if is_member {
                self.leave(slot, x.records);
            }
            // Farther it stays out.
            self.stay_out(ci, radius, kt, range, reach, d);
            return;
        }
        if near_leaf(x) {
            // Detail of a near leaf (not a landmark now): its leaf flipping is an event.
            self.due_between(ci, f32::NEG_INFINITY, f32::INFINITY, d);
            return;
        }
        let Some((was, last_lod, _)) = self.continued(ci, x) else {
            return;
        };
        let tan = if was { kt * 0.9 } else { kt };
        if radius <= tan * d {
            if is_member {
                self.leave(slot, x.records);
            }
            // Not shown next frame either: it joins once within both limits (no hysteresis).
            self.stay_out(ci, radius, kt, range, reach, d);
            return;
        }
        let leave_at = (radius / (kt * 0.9)).min(range + radius);
        let kind = Kind {
            detail: false,
            culled: false,
            lo: reach,
            hi: leave_at,
        };
        self.settle(ci, x, d, was, last_lod, kind);
    }

    /// An out candidate (neither shown nor detail) looks again once within both limits
    /// (`join`: the keep angle's distance, the keep range). A candidate whose `join` is not
    /// beyond r2 (`reach`) can never be a landmark: closer than `join` it is within r2, where
    /// the residency pass has it. Travel alone then changes nothing, and it waits for an event
    /// only (its leaf turning near, its mesh or the configuration changing). Most small
    /// instances are such candidates when the set also keeps the near leaves' detail.
    fn stay_out(&mut self, ci: u32, radius: f32, kt: f32, range: f32, reach: f32, d: f32) {
        let join = (radius / kt).min(range + radius);
        let lo = if join <= reach {
            f32::NEG_INFINITY
        } else {
            join
        };
        self.due_between(ci, lo, f32::INFINITY, d);
    }

    /// Whether the candidate continues from a visit or a look of last frame, its LOD then and
    /// its cull state then (`None`: removed, its mesh or instance is gone or not static).
    fn continued(&mut self, ci: u32, x: &mut Look<'_>) -> Option<(bool, u8, bool)> {
        let cand = self.cands[ci as usize];
        let slot = cand.slot;
        let is_static = matches!(
            x.tables.meshes.get(cand.mesh as usize),
            Some(Some(m)) if m.kind == MeshKind::Static
        );
        if !is_static {
            self.disqualify(slot, x.records);
            return None;
        }
        // A member continues from its LOD (kept here, not in the grid: a look at a member
        // touches no instance state); any other candidate from the instance's last visit.
        if cand.member != NONE {
            return Some((true, cand.lod, cand.culled));
        }
        let Some(ge) = x.grid.get(slot) else {
            self.remove(slot, x.records);
            return None;
        };
        let was = ge.data.last_visit == x.p.frame.wrapping_sub(1);
        // A visit that finds an instance new (not visited last frame) starts it culled.
        Some((was, ge.data.lod_target, !was || ge.data.culled))
    }

    /// Detail of a near leaf beyond r2: its LOD as the residency pass picks it, culled by
    /// angle as the near field's detail beyond r2 is (`InstanceCuller::cull_small`).
    fn look_detail(&mut self, ci: u32, x: &mut Look<'_>, d: f32) {
        let Some((was, last_lod, was_culled)) = self.continued(ci, x) else {
            return;
        };
        let radius = self.cands[ci as usize].radius;
        let culled = x.culler.cull_small(radius, d, was_culled);
        // Culled, it stays so while beyond the hysteresis distance; shown, while within the
        // culling distance.
        let (cull_lo, cull_hi) = if culled {
            (x.culler.small_beyond(radius, true), f32::INFINITY)
        } else {
            (f32::NEG_INFINITY, x.culler.small_beyond(radius, false))
        };
        let kind = Kind {
            detail: true,
            culled,
            lo: (x.p.r2 + radius).max(cull_lo),
            hi: cull_hi,
        };
        self.settle(ci, x, d, was, last_lod, kind);
    }

    /// The rest of a look at a member-to-be: its LOD, its pairs and the next look.
    fn settle(&mut self, ci: u32, x: &mut Look<'_>, d: f32, was: bool, last_lod: u8, kind: Kind) {
        let frame = x.p.frame;
        let cand = self.cands[ci as usize];
        let slot = cand.slot;
        let is_member = cand.member != NONE;
        let (c, radius) = (cand.center, cand.radius);
        let mesh_ix = cand.mesh;
        let mesh = x.tables.meshes[mesh_ix as usize]
            .as_ref()
            .expect("checked by `continued`");
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
            if kind.detail {
                // Detail not ready: it holds its leaf's proxy, whatever its angle, as the
                // residency pass's not-ready instances do (`Visit::ready`), every frame until
                // data or a BLAS of its mesh comes (its selection's resolution changes), its
                // leaf flips (both events) or it comes within r2.
                self.set_unready(ci, true);
                self.due_between(ci, x.p.r2 + radius, f32::INFINITY, d);
            } else {
                self.due_between(ci, f32::NEG_INFINITY, f32::INFINITY, d);
            }
            return;
        };
        // Next time `current` is this LOD: the selection holds between its switch points.
        let (lod_lo, lod_hi) = x.lod.stable_band(mesh.errors(), cand.scale, lodi, surface);
        // The band in centre distance: the kind's limits and the LOD's switch points. A
        // surface distance clamped at 0 is the same for every centre distance below the
        // radius.
        let lod_lo = if lod_lo <= 0.0 {
            f32::NEG_INFINITY
        } else {
            lod_lo + radius
        };
        let (lo, hi) = (kind.lo.max(lod_lo), kind.hi.min(lod_hi + radius));
        // The next look selects from the LOD resolved now. After a fallback (the selection had
        // no data) that can answer otherwise at this very distance: then it is due next frame,
        // as the rule, applied every frame, selects again then.
        let (lo, hi) = if lodi != selected
            && x.lod.select(
                mesh.errors(),
                cand.scale,
                surface,
                lodi,
                mesh.lod_floor as usize,
            ) != selected
        {
            (d, d)
        } else {
            (lo, hi)
        };
        if is_member
            && !cand.unsettled
            && cand.lod as usize == lodi
            && cand.sel as usize == selected
            && cand.culled == kind.culled
            && mesh.lod_entry[lodi].is_some()
        {
            // A member that stays as it is: its pairs and BLAS are unchanged (its target is
            // built, so its pair's distances only bound the eviction order: the ones from its
            // last change still do).
            self.due_between(ci, lo, hi, d);
            return;
        }
        let in_view = in_view(x, c);
        if !is_member {
            // Joins: the instance's LOD and cull state as a visit leaves them (a member's
            // LOD is written back when it changes, in `landmarks_cull`).
            if let Some(ge) = x.grid.get_mut(slot) {
                ge.data.lod_target = lodi as u8;
                ge.data.last_visit = frame;
                ge.data.culled = kind.culled;
            }
        }
        // Its target entry exists from now on (as the residency pass creates it).
        if mesh.lod_entry[lodi].is_none() {
            x.tables.new_lod_entry(mesh_ix, lodi as u8, frame);
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
                detail: kind.detail,
                counted: false,
            });
            let m = self.members.len() - 1;
            self.cands[ci as usize].member = m as u32;
            self.pair(target).targets += 1;
            self.select_pair(m, sel_pair);
            self.rechoose.push(slot);
        } else {
            // The new references first, then the old ones go: a pair freed in between could
            // be one of the new ones.
            // (Both new references before either old one goes: the old selection can be the
            // new target, with no other user.)
            let m = self.member_of(slot);
            let old = self.members[m];
            if old.selected != sel_pair {
                self.select_pair(m, sel_pair);
            }
            if old.target != target {
                self.pair(target).targets += 1;
                self.members[m].target = target;
            }
            if old.selected != sel_pair {
                self.unselect_at(old.selected, old.selected_pos);
            }
            if old.target != target {
                self.untarget(old.target);
                self.rechoose.push(slot);
            }
            if cand.culled != kind.culled {
                // Its record comes or goes.
                self.rechoose.push(slot);
            }
        }
        self.pair(sel_pair).resolved = lodi as u8;
        self.note_target_distance(target, surface, in_view, frame);
        let c = &mut self.cands[ci as usize];
        (c.lod, c.sel) = (lodi as u8, selected as u8);
        c.culled = kind.culled;
        // Next look: the nearest threshold (shown next frame: the hysteresis one).
        self.due_between(ci, lo, hi, d);
    }
}

/// What kind of member a look makes of a candidate, and the distances its kind holds between.
#[derive(Debug, Clone, Copy)]
struct Kind {
    /// Detail of a near leaf (else a landmark).
    detail: bool,
    culled: bool,
    lo: f32,
    hi: f32,
}
