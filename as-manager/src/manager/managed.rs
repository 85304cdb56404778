//! The `Managed` policy's frame: residency through the spatial index, LOD with hysteresis,
//! entry upkeep, culling and assembly. Scheduling and memory are in `schedule.rs`.

use glam::Vec3;

use super::state::{EntryState, InstanceHot, Tables, NO_GROUP};
use super::{AsManager, Visit};
use crate::backend::AsBackend;
use crate::lod::LodSelector;
use crate::mesh::MeshKind;
use crate::record::{assemble, TlasInstance};
use crate::spatial::{GridEntry, GridLoc};

use crate::Result;

impl<B: AsBackend> AsManager<B> {
    pub(crate) fn managed_frame(&mut self) -> Result<()> {
        {
            let _s = tracing::trace_span!("residency").entered();
            {
                let _s = tracing::trace_span!("far_prepare").entered();
                self.far_prepare();
            }
            self.landmarks_residency();
            {
                let _s = tracing::trace_span!("near").entered();
                self.residency_pass();
            }
            {
                let _s = tracing::trace_span!("upkeep").entered();
                self.upkeep_entries();
            }
        }
        {
            let _s = tracing::trace_span!("schedule").entered();
            self.enforce_budget();
            self.schedule_refits(true)?;
            self.relax_floors();
        }
        {
            let _s = tracing::trace_span!("cull").entered();
            {
                let _s = tracing::trace_span!("near_cull").entered();
                self.select_and_cull();
            }
            self.landmarks_cull();
            {
                let _s = tracing::trace_span!("far_select").entered();
                self.far_select();
            }
        }
        {
            let _s = tracing::trace_span!("assemble").entered();
            self.assemble_records();
            self.records.extend_from_slice(&self.far.records);
        }
        // The builds and compactions come after the records: this frame's TLAS names none of
        // their BLASes (they enter the next frame's), so the backend records the builds beside
        // it, with no barrier between (docs/GPU.md, "A TLAS beside the frame's builds"), and
        // the GPU budget counts the two side by side.
        let _s = tracing::trace_span!("builds").entered();
        self.reserve_gpu(true);
        self.schedule_builds(true)?;
        self.schedule_compactions()
    }

    /// Visits instances within r2 of any camera (and beyond it in near far-field leaves);
    /// picks LODs; marks request/keep. One pass through the grid cells near the cameras (the
    /// per-instance state lives there). The landmarks beyond are `landmarks.rs`'s.
    fn residency_pass(&mut self) {
        let r2 = self.config.residency.r2;
        let far_on = self.config.far_field.enabled;
        // A far-field group within r2 is near as a whole: its instances beyond r2 are near
        // field too (its proxy is not shown). The landmark set keeps that detail
        // (`FarFieldConfig::incremental_detail`) but for the instances it does not track,
        // visited below from their leaves' lists; otherwise the query also covers those
        // groups' boxes.
        let kept = self.landmarks.detail();
        let mut boxes = std::mem::take(&mut self.near_boxes);
        let mut leaves = std::mem::take(&mut self.near_leaves_beyond);
        boxes.clear();
        leaves.clear();
        if far_on && kept {
            self.far.near_leaves_beyond(&self.cam_pos, r2, &mut leaves);
        } else if far_on {
            self.far.near_leaf_boxes(&self.cam_pos, r2, &mut boxes);
        }
        let Self {
            grid,
            visits,
            cam_pos,
            cam_fwd,
            tables,
            lod,
            far,
            config,
            frame,
            backend,
            landmarks,
            ..
        } = self;
        visits.clear();
        let mut pass = ResidencyPass {
            cams: cam_pos,
            fwds: cam_fwd,
            r1: config.residency.r1,
            r2,
            frame: *frame,
            need_data: backend.needs_geometry(),
            tables,
            lod,
            visits,
        };
        grid.query_with_boxes(pass.cams, r2, &boxes, |loc, grid_entry| {
            let (d2, beyond_r2) = pass.distance(grid_entry);
            // Beyond r2 only for a near group (no square root for the rejected), and not
            // when the landmark set keeps that detail.
            if beyond_r2 && (kept || !far.is_near_leaf(grid_entry.data.group)) {
                return;
            }
            debug_assert!(
                !landmarks.is_member(grid_entry.slot),
                "a landmark is never near"
            );
            pass.visit(loc, grid_entry, d2.sqrt(), beyond_r2);
        });
        // The near leaves' instances beyond r2 that the set does not track (skinned ones).
        for &g in &leaves {
            for &slot in landmarks.others_of(g) {
                let Some(loc) = grid.loc(slot) else { continue };
                let grid_entry = grid.at_mut(loc);
                let (d2, beyond_r2) = pass.distance(grid_entry);
                if beyond_r2 {
                    pass.visit(loc, grid_entry, d2.sqrt(), true);
                }
            }
        }
        self.near_boxes = boxes;
        self.near_leaves_beyond = leaves;
        self.stats.instances_visited = self.visits.len() as u32 + self.landmarks.examined;
        self.stats.landmarks_examined = self.landmarks.examined;
        self.stats.landmarks_waited = self.landmarks.waited;
    }

    /// Creation after `create_threshold` requested frames; release after `release_threshold`
    /// unkept frames (and `min_resident_frames` of life); forgetting stale unbuilt entries.
    fn upkeep_entries(&mut self) {
        let frame = self.frame;
        let rc = &self.config.residency;
        let (create, release, min_life) = (
            rc.create_threshold as u64,
            rc.release_threshold as u64,
            rc.min_resident_frames as u64,
        );
        let mut i = self.tables.active.len();
        while i > 0 {
            i -= 1;
            let key = self.tables.active[i];
            let e = &mut self.tables.entries[key];
            let requested_now = e.last_request == frame;
            let unkept = frame.saturating_sub(e.last_keep);
            match e.state {
                EntryState::Built => {
                    if unkept > release && frame.saturating_sub(e.created) >= min_life {
                        self.release_entry(key);
                        self.stats.releases += 1;
                    }
                }
                EntryState::Queued => {
                    if !requested_now {
                        e.state = EntryState::Idle;
                    }
                }
                EntryState::Idle => {
                    if requested_now && frame - e.streak_start + 1 >= create.max(1) {
                        e.state = EntryState::Queued;
                        e.queued_since = frame;
                    } else if unkept > release || (e.owner.is_some() && unkept > 0) {
                        self.tables.drop_entry(key);
                    }
                }
            }
        }
    }

    /// Picks the BLAS each visited instance shows (target if built, else the previous one,
    /// else the nearest built LOD: no holes while a finer LOD builds) and culls.
    fn select_and_cull(&mut self) {
        let frame = self.frame;
        self.tlas_list.clear();
        self.tlas_groups.clear();
        self.tlas_far_leaf_entries = 0;
        let far = self.config.far_field.enabled;
        let r1 = self.config.residency.r1;
        let mut culled_count = 0;
        let (mut within_r1, mut short) = (0u32, 0u32);
        for vi in 0..self.visits.len() {
            let v = self.visits[vi];
            let grid_entry = self.grid.at_mut(v.loc);
            let (radius, slot) = (grid_entry.radius, grid_entry.slot);
            let group = if far { grid_entry.data.group } else { NO_GROUP };
            let hot = &mut grid_entry.data;
            if !v.ready {
                // Nothing of it can show: it holds its leaf's proxy, and counts as new (culled)
                // once a LOD can.
                hot.culled = true;
                if group != NO_GROUP {
                    self.far.add_unready(group);
                }
                if !v.beyond_r2 && v.center_dist - radius <= r1 {
                    within_r1 += 1;
                    short += 1;
                }
                continue;
            }
            let tables = &mut self.tables;
            let mesh = tables.meshes[hot.mesh as usize]
                .as_ref()
                .expect("live mesh");
            let target = match mesh.kind {
                MeshKind::Static => mesh.lod_entry[hot.lod_target as usize],
                MeshKind::Skinned => hot.own,
            };
            let chosen =
                tables.choose_shown(mesh, hot.mesh, target, hot.lod_target as usize, hot.shown);
            let culled = if v.beyond_r2 {
                self.culler.cull_small(radius, v.center_dist, hot.culled)
            } else {
                self.culler.cull(radius, v.center_dist, hot.culled)
            };
            hot.shown = chosen;
            hot.culled = culled;
            if !culled && !v.beyond_r2 && v.center_dist - radius <= r1 {
                // Covered: its target LOD or a finer one is shown.
                within_r1 += 1;
                let covered = chosen.is_some_and(|k| {
                    chosen == target
                        || (mesh.kind == MeshKind::Static
                            && tables.entries[k].lod <= hot.lod_target)
                });
                short += u32::from(!covered);
            }
            if chosen.is_none() && !culled && group != NO_GROUP {
                self.far.add_unready(group);
            }
            if let Some(chosen) = chosen {
                if culled {
                    culled_count += 1;
                } else {
                    let e = &mut tables.entries[chosen];
                    e.last_in_tlas = Some(frame);
                    e.last_keep = frame;
                    self.tlas_list.push((slot, e.record_address(&self.backend)));
                    self.tlas_groups.push((group != NO_GROUP).then_some(group));
                    self.tlas_far_leaf_entries +=
                        u32::from(group != NO_GROUP && !self.far.is_near_leaf(group));
                }
            }
        }
        self.stats.culled = culled_count;
        self.stats.within_r1 = within_r1;
        self.stats.short_of_target = short;
    }

    /// Writes the records for `tlas_list` (parallel when large).
    /// (After the landmarks' records, which stay from frame to frame.)
    pub(crate) fn assemble_records(&mut self) {
        self.records.truncate(self.landmarks.len());
        let list = &self.tlas_list;
        let templates = &self.templates;
        let a = &self.config.assembly;
        assemble(
            list.len(),
            &mut self.records,
            a.threads,
            a.parallel_threshold,
            |i| {
                let (slot, address) = list[i];
                TlasInstance {
                    blas_address: address,
                    ..templates[slot as usize]
                }
            },
        );
    }
}

/// The residency pass's view of the manager while the grid is borrowed.
struct ResidencyPass<'a> {
    cams: &'a [Vec3],
    fwds: &'a [Vec3],
    r1: f32,
    r2: f32,
    frame: u64,
    need_data: bool,
    tables: &'a mut Tables,
    lod: &'a LodSelector,
    visits: &'a mut Vec<Visit>,
}

impl ResidencyPass<'_> {
    /// Squared distance from the nearest camera to the centre, and whether the sphere lies
    /// wholly beyond r2.
    fn distance(&self, grid_entry: &GridEntry<InstanceHot>) -> (f32, bool) {
        let c = Vec3::from(grid_entry.center);
        let d2 = self
            .cams
            .iter()
            .map(|p| p.distance_squared(c))
            .fold(f32::INFINITY, f32::min);
        let reach = self.r2 + grid_entry.radius;
        (d2, d2 > reach * reach)
    }

    /// Picks the instance's LOD by projected error, creates its entry, and marks
    /// the entry requested (within r1, beyond r2) and kept.
    fn visit(
        &mut self,
        loc: GridLoc,
        grid_entry: &mut GridEntry<InstanceHot>,
        center_dist: f32,
        beyond_r2: bool,
    ) {
        let (tables, frame) = (&mut *self.tables, self.frame);
        let c = Vec3::from(grid_entry.center);
        let surface_dist = (center_dist - grid_entry.radius).max(0.0);
        let hot = &mut grid_entry.data;
        let mesh = tables.meshes[hot.mesh as usize]
            .as_ref()
            .expect("instance of a live mesh");
        self.visits.push(Visit {
            loc,
            center_dist,
            beyond_r2,
            ready: true,
        });
        let was_visited = hot.last_visit == frame.wrapping_sub(1);
        let current = if was_visited {
            hot.lod_target as usize
        } else {
            mesh.nlods as usize - 1
        };
        let lodi = self.lod.select(
            mesh.errors(),
            hot.scale,
            surface_dist,
            current,
            mesh.lod_floor as usize,
        );
        // A GPU builds only from resident data: the nearest LOD that has some.
        let built = |l: usize| mesh.kind == MeshKind::Static && tables.built(mesh.lod_entry[l]);
        let Some(lodi) = mesh.with_data(lodi, self.need_data, built) else {
            self.visits.last_mut().expect("pushed above").ready = false;
            return;
        };
        hot.lod_target = lodi as u8;
        hot.last_visit = frame;
        if !was_visited {
            hot.culled = true;
        }
        let kind = mesh.kind;
        let tris = mesh.lod_tris[lodi];
        let existing = match kind {
            MeshKind::Static => mesh.lod_entry[lodi],
            MeshKind::Skinned => hot.own.filter(|&k| {
                tables
                    .entries
                    .get(k)
                    .is_some_and(|e| e.lod as usize == lodi)
            }),
        };
        let key = existing.unwrap_or_else(|| {
            let owner = (kind == MeshKind::Skinned).then_some(grid_entry.slot);
            let key = tables.new_entry(hot.mesh, lodi as u8, owner, tris, frame);
            match kind {
                MeshKind::Static => {
                    tables.meshes[hot.mesh as usize]
                        .as_mut()
                        .expect("live")
                        .lod_entry[lodi] = Some(key)
                }
                MeshKind::Skinned => hot.own = Some(key),
            }
            key
        });
        let requested = surface_dist <= self.r1 || beyond_r2;
        let in_view = requested
            && self
                .cams
                .iter()
                .zip(self.fwds)
                .any(|(p, f)| f.dot(c - *p) >= 0.0);
        let e = &mut tables.entries[key];
        if requested {
            e.mark_request(frame);
        }
        e.last_keep = frame;
        e.mark_distance(frame, surface_dist, in_view);
        if let Some(shown) = hot.shown.and_then(|k| tables.entries.get_mut(k)) {
            shown.last_keep = frame;
        }
    }
}
