//! The landmarks' two steps of the manager's frame: looking at the due candidates (with the
//! residency marks), and choosing what they show (with the records).

use super::look::Look;
use super::*;
use crate::backend::AsBackend;
use crate::manager::state::{EntryKey, EntryState, Tables};
use crate::manager::AsManager;

impl<B: AsBackend> AsManager<B> {
    fn landmark_params(&self) -> Option<LandmarkParams> {
        let f = &self.config.far_field;
        if !self.landmarks.is_active() {
            return None;
        }
        // Landmarks off (the set keeps detail only): nothing subtends enough.
        let keep_tan = if self.landmarks.min_radius().is_finite() {
            f.keep_angle.tan()
        } else {
            f32::INFINITY
        };
        Some(LandmarkParams {
            r2: self.config.residency.r2,
            keep_tan,
            range: f.far_radius.min(f.keep_range),
            frame: self.frame,
            need_data: self.backend.needs_geometry(),
        })
    }

    /// Residency step of the landmarks (after `far_prepare`, before the residency pass): looks
    /// at the due candidates and sets the residency marks of the pairs the landmarks use.
    pub(crate) fn landmarks_residency(&mut self) {
        self.landmarks.examined = 0;
        self.landmarks.waited = 0;
        let Some(p) = self.landmark_params() else {
            self.far.flipped.clear();
            self.tables.mesh_log.stop();
            return;
        };
        self.tables.mesh_log.start();
        let _s = tracing::trace_span!("landmarks").entered();
        // Last frame's near and proxy records go; the landmarks' stay at the front.
        self.records.truncate(self.landmarks.len());
        let Self {
            landmarks,
            grid,
            tables,
            lod,
            culler,
            far,
            cam_pos,
            cam_fwd,
            records,
            ..
        } = self;
        landmarks.advance(cam_pos);
        let collect = tracing::trace_span!("collect_due").entered();
        let mut due = std::mem::take(&mut landmarks.scratch);
        let mut queued = std::mem::take(&mut landmarks.queued_scratch);
        landmarks.collect_due(tables, p.need_data, &mut far.flipped, &mut due, &mut queued);
        // Landmarks whose target is not built yet: their distances are taken every frame (the
        // distances of unbuilt entries are exact; see the module docs), a look only once
        // outside their last look's band; `landmarks_cull` chooses their BLAS again when one
        // of their mesh's changed.
        // (`waiting` is empty unless a frame failed between the two steps.)
        let mut spare = std::mem::take(&mut landmarks.waiting);
        spare.clear();
        let unsettled = std::mem::replace(&mut landmarks.unsettled, spare);
        #[cfg(test)]
        landmarks.waited_unlooked.clear();
        let mut look = Look {
            grid,
            tables,
            lod,
            culler,
            far,
            cams: cam_pos,
            fwds: cam_fwd,
            records,
            p,
        };
        drop(collect);
        let looks = tracing::trace_span!("looks").entered();
        landmarks.warm(&due, &queued);
        // Events name instances (slots) and come first; then the queue's live entries, due by
        // travel alone: a look only if the distance left the last look's band (a look at an
        // event makes the candidate's queued entry stale).
        for &slot in &due {
            if let Some(&ci) = landmarks.index.get(slot as usize) {
                landmarks.look_at(ci, &mut look);
            }
        }
        for &slot in &unsettled {
            if let Some(&ci) = landmarks.index.get(slot as usize) {
                if !landmarks.unsettled_wait(ci, &look) {
                    landmarks.look_at(ci, &mut look);
                }
            }
        }
        landmarks.waiting = unsettled;
        for e in &queued {
            if landmarks.is_live(e) && !landmarks.wait_if_inside(*e, look.cams) {
                landmarks.look_at(e.ci, &mut look);
            }
        }
        landmarks.scratch = due;
        landmarks.queued_scratch = queued;
        for g in landmarks.unready_leaves() {
            far.add_unready(g);
        }
        drop(looks);
        let _marks = tracing::trace_span!("pair_marks").entered();
        // The marks every landmark would set on its target and shown entries.
        let frame = p.frame;
        let odo = landmarks.odo;
        for pair in landmarks.pairs.iter_mut().flatten() {
            if pair.targets == 0 && pair.showing.is_empty() {
                continue;
            }
            let key = match pair_entry(pair, tables) {
                Some(k) => k,
                None if pair.targets > 0 => {
                    // Released since (evicted): the targets ask for it again.
                    let Some(k) = tables.new_lod_entry(pair.mesh, pair.lod, frame) else {
                        continue;
                    };
                    pair.entry = Some(k);
                    k
                }
                None => continue,
            };
            let e = &mut tables.entries[key];
            e.last_keep = frame;
            if pair.targets == 0 {
                continue;
            }
            e.mark_request(frame);
            let (dist, in_view) = if e.state != EntryState::Built && pair.frame == frame {
                (pair.frame_min, pair.frame_in_view)
            } else {
                ((pair.min_key - odo).max(0.0) as f32, pair.in_view)
            };
            e.mark_distance(frame, dist, in_view);
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
            far,
            templates,
            ..
        } = self;
        let address_of = |tables: &Tables, key: Option<EntryKey>| -> u64 {
            match key.and_then(|k| tables.entries.get(k)) {
                Some(e) if e.state == EntryState::Built => e.record_address(&*backend),
                _ => 0,
            }
        };
        // Pairs whose BLAS changed (built, compacted, released): their landmarks choose again.
        // Only the pairs of the meshes logged since the last frame's step can have
        // (`MeshLog`).
        let mut rechoose = std::mem::take(&mut landmarks.rechoose);
        let (mut meshes, mut pairs) = std::mem::take(&mut landmarks.log_scratch);
        let logged = tables.mesh_log.take_cull(&mut meshes);
        landmarks.logged_pairs(logged, &meshes, &mut pairs);
        for &i in &pairs {
            let pair = landmarks.pairs[i as usize].as_mut().expect("a live pair");
            if pair.showing.is_empty() {
                continue;
            }
            let address = address_of(tables, pair_entry(pair, tables));
            if address != pair.address {
                pair.address = address;
                rechoose.extend_from_slice(&pair.showing);
            }
        }
        landmarks.log_scratch = (meshes, pairs);
        #[cfg(debug_assertions)]
        for pair in landmarks.pairs.iter().flatten() {
            let now = address_of(tables, tables.lod_entry(pair.mesh, pair.lod));
            debug_assert!(
                pair.showing.is_empty() || now == pair.address,
                "pair ({}, {}) shows {now:#x}, not {:#x}: a change to its mesh was not logged",
                pair.mesh,
                pair.lod,
                pair.address
            );
        }
        // Landmarks waiting for their target choose again only when a BLAS of their mesh was
        // built, compacted or released since their last choice (the choice reads nothing
        // else); first, in the order they waited.
        let mut waiting = std::mem::take(&mut landmarks.waiting);
        let mut kept = std::mem::take(&mut landmarks.kept_scratch);
        kept.clear();
        let mut order = std::mem::take(&mut landmarks.order_scratch);
        order.clear();
        for &slot in &waiting {
            let Some(c) = landmarks.cand(slot) else {
                continue;
            };
            let chosen = match landmarks.members.get(c.member as usize) {
                Some(m) if c.unsettled && m.chosen != u64::MAX => m.chosen,
                _ => {
                    order.push(slot);
                    continue;
                }
            };
            let epoch = tables
                .meshes
                .get(c.mesh as usize)
                .and_then(|m| m.as_ref())
                .map_or(u64::MAX, |m| m.blas_epoch);
            if epoch <= chosen {
                kept.push(slot);
            } else {
                order.push(slot);
            }
        }
        order.append(&mut rechoose);
        landmarks.warm_members(&order, grid);
        for &slot in &order {
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
            let chosen = tables.choose_shown(mesh, mesh_ix, target, target_lod as usize, hot.shown);
            hot.shown = chosen;
            let unsettled = chosen != target;
            if unsettled {
                landmarks.unsettled.push(slot);
            }
            if let Some(&ci) = landmarks.index.get(slot as usize) {
                let c = &mut landmarks.cands[ci as usize];
                if c.unsettled && !unsettled {
                    // Settled: its looks while unsettled queued nothing (`due_between`).
                    landmarks.now.push(slot);
                }
                c.unsettled = unsettled;
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
            // Detail: out of the TLAS while culled or covered by its leaf's proxy; waiting for
            // its first BLAS, unculled, it holds its leaf's proxy (the hand-over).
            let (culled, group) = landmarks
                .cand(slot)
                .map_or((false, NO_GROUP), |c| (mb.detail && c.culled, c.group));
            landmarks.set_counted(mi, chosen.is_some() && !culled);
            if mb.detail && chosen.is_none() && !culled && group != NO_GROUP {
                far.add_unready(group);
            }
            let hidden = culled || (mb.detail && landmarks.hidden.contains(&group));
            let record = chosen.filter(|_| !hidden).map(|k| TlasInstance {
                blas_address: address_of(tables, Some(k)),
                ..templates[slot as usize]
            });
            landmarks.put_record(mi, record, records);
        }
        // The waiting ones whose mesh's BLASes did not change (and that nothing else made
        // choose) show what they showed; one showing nothing still holds its leaf's proxy.
        for &slot in &kept {
            let Some(&c) = landmarks.cand(slot) else {
                continue;
            };
            let mb = landmarks.members[c.member as usize];
            if mb.chosen == frame {
                continue;
            }
            landmarks.unsettled.push(slot);
            if mb.detail && mb.shown == NONE && !c.culled && c.group != NO_GROUP {
                far.add_unready(c.group);
            }
        }
        waiting.clear();
        landmarks.waiting = waiting;
        landmarks.kept_scratch = kept;
        order.clear();
        landmarks.order_scratch = order;
        landmarks.rechoose = rechoose;
        for pair in landmarks.pairs.iter_mut().flatten() {
            if pair.showing.is_empty() {
                continue;
            }
            let key = pair_entry(pair, tables);
            if let Some(e) = key.and_then(|k| tables.entries.get_mut(k)) {
                if pair.visible > 0 {
                    e.last_in_tlas = Some(frame);
                }
                e.last_keep = frame;
            }
        }
        let detail = self.landmarks.detail_records;
        self.stats.landmark_instances = self.landmarks.len() as u32 - detail;
        self.stats.far_detail_instances = detail;
    }
}

/// A pair's entry: the one it last found while that is still live (a static mesh's LOD has
/// one entry, dropped with the mesh), else its mesh's now, kept for the next frame. The pair
/// scans run every frame over every pair the landmarks use; this one reads no mesh state.
fn pair_entry(pair: &mut PairUse, tables: &Tables) -> Option<EntryKey> {
    if let Some(k) = pair.entry.filter(|&k| tables.entries.contains_key(k)) {
        debug_assert_eq!(
            tables.lod_entry(pair.mesh, pair.lod),
            Some(k),
            "a pair's cached entry is its mesh's"
        );
        return Some(k);
    }
    pair.entry = tables.lod_entry(pair.mesh, pair.lod);
    pair.entry
}
