//! The `Managed` policy's frame: residency through the spatial index, LOD with hysteresis,
//! entry upkeep, culling and assembly. Scheduling and memory are in `schedule.rs`.

use glam::Vec3;

use super::state::{EntryState, Hot, Tables, NONE};
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
            self.far_prepare();
            self.residency_pass();
            self.upkeep_entries();
        }
        {
            let _s = tracing::trace_span!("schedule").entered();
            self.enforce_budget();
            self.schedule_builds(true)?;
            self.schedule_refits(true)?;
            self.schedule_compactions()?;
            self.relax_floors();
        }
        {
            let _s = tracing::trace_span!("cull").entered();
            self.select_and_cull();
            self.far_select();
        }
        let _s = tracing::trace_span!("assemble").entered();
        self.assemble_records();
        self.records.extend_from_slice(&self.far.records);
        Ok(())
    }

    /// Visits instances within r2 of any camera (and the far field's landmarks, see
    /// `FarFieldConfig::keep_angle`); picks LODs; marks request/keep. One pass through the
    /// grid cells near the cameras (the per-instance state lives there).
    fn residency_pass(&mut self) {
        let r2 = self.config.residency.r2;
        let far_on = self.config.far_field.enabled;
        // A far-field group within r2 is near as a whole: its instances beyond r2 are near
        // field too (its proxy is not shown), so the query also covers those groups' boxes.
        let mut boxes = std::mem::take(&mut self.near_boxes);
        if far_on {
            self.far.near_leaf_boxes(&self.cam_pos, r2, &mut boxes);
        } else {
            boxes.clear();
        }
        let keep_tan = self.config.far_field.keep_angle.tan();
        let Self {
            grid,
            visits,
            cam_pos,
            cam_fwd,
            t,
            lod,
            far,
            config,
            frame,
            backend,
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
            t,
            lod,
            visits,
        };
        grid.query_with_boxes(pass.cams, r2, &boxes, |loc, ge| {
            let (d2, beyond_r2) = pass.distance(ge);
            // Beyond r2 only for a near group (no square root for the rejected).
            if beyond_r2 && !far.is_near_leaf(ge.data.group) {
                return;
            }
            pass.visit(loc, ge, d2.sqrt(), beyond_r2, false);
        });
        if far_on && keep_tan > 0.0 {
            // Landmarks: exactly the tall entries the query rejected or never reached.
            let far_radius = config.far_field.far_radius.min(config.far_field.keep_range);
            grid.query_tall(pass.cams, keep_tan * 0.9, far_radius, |loc, ge| {
                let (d2, beyond_r2) = pass.distance(ge);
                if !beyond_r2 || far.is_near_leaf(ge.data.group) {
                    return;
                }
                let d = d2.sqrt();
                // 10 % hysteresis on the angle for a landmark shown last frame.
                let was = ge.data.last_visit == pass.frame.wrapping_sub(1);
                let tan = if was { keep_tan * 0.9 } else { keep_tan };
                if d - ge.radius > far_radius || ge.radius <= tan * d {
                    return;
                }
                pass.visit(loc, ge, d, true, true);
            });
        }
        self.near_boxes = boxes;
        self.stats.instances_visited = self.visits.len() as u32;
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
        let mut i = self.t.active.len();
        while i > 0 {
            i -= 1;
            let slot = self.t.active[i];
            let e = &mut self.t.entries[slot as usize];
            let requested_now = e.last_request == frame;
            let unkept = frame.saturating_sub(e.last_keep);
            match e.state {
                EntryState::Built => {
                    if unkept > release && frame.saturating_sub(e.created) >= min_life {
                        self.release_entry(slot);
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
                    } else if unkept > release || (e.owner != NONE && unkept > 0) {
                        self.t.drop_entry(slot);
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
        let far = self.config.far_field.enabled;
        let r1 = self.config.residency.r1;
        let mut culled_count = 0;
        let (mut within_r1, mut short) = (0u32, 0u32);
        for vi in 0..self.visits.len() {
            let v = self.visits[vi];
            let ge = self.grid.at_mut(v.loc);
            let radius = ge.radius;
            // A landmark stands beside its group's proxy: never covered, never handing over.
            let group = if far && !v.landmark {
                ge.data.group
            } else {
                NONE
            };
            let h = &mut ge.data;
            let t = &mut self.t;
            let mesh = t.meshes[h.mesh as usize].as_ref().expect("live mesh");
            let target = match mesh.kind {
                MeshKind::Static => {
                    let s = mesh.lod_entry[h.lod_target as usize];
                    if s == NONE {
                        (NONE, 0)
                    } else {
                        t.key(s)
                    }
                }
                MeshKind::Skinned => h.own,
            };
            let chosen = if t.built(target) {
                target
            } else if t.built(h.shown) && t.entries[h.shown.0 as usize].mesh == h.mesh {
                h.shown
            } else if mesh.kind == MeshKind::Static {
                // nearest built LOD, coarser first
                let tl = h.lod_target as usize;
                let n = mesh.nlods as usize;
                let mut found = (NONE, 0);
                for l in (tl..n).chain((0..tl).rev()) {
                    let s = mesh.lod_entry[l];
                    if s != NONE && t.entries[s as usize].state == EntryState::Built {
                        found = t.key(s);
                        break;
                    }
                }
                found
            } else {
                (NONE, 0)
            };
            // A landmark passed its own test (the far keep angle, with hysteresis) in the
            // residency pass; the culling angle is the near field's.
            let culled = if v.landmark {
                false
            } else if v.beyond_r2 {
                self.culler.cull_small(radius, v.center_dist, h.culled)
            } else {
                self.culler.cull(radius, v.center_dist, h.culled)
            };
            h.shown = chosen;
            h.culled = culled;
            if !culled && !v.beyond_r2 && v.center_dist - radius <= r1 {
                // Covered: its target LOD or a finer one is shown.
                within_r1 += 1;
                let covered = chosen.0 != NONE
                    && (chosen == target
                        || (mesh.kind == MeshKind::Static
                            && t.entries[chosen.0 as usize].lod <= h.lod_target));
                short += u32::from(!covered);
            }
            if chosen.0 == NONE && !culled && group != NONE {
                self.far.add_unready(group);
            }
            if chosen.0 != NONE {
                if culled {
                    culled_count += 1;
                } else {
                    let e = &mut t.entries[chosen.0 as usize];
                    e.last_in_tlas = Some(frame);
                    e.last_keep = frame;
                    let handle = e.handle.expect("built entry has a handle");
                    self.tlas_list
                        .push((v.loc, self.backend.blas_address(handle)));
                    self.tlas_groups.push(group);
                }
            }
        }
        self.stats.culled = culled_count;
        self.stats.within_r1 = within_r1;
        self.stats.short_of_target = short;
    }

    /// Writes the records for `tlas_list` (parallel when large).
    pub(crate) fn assemble_records(&mut self) {
        let list = &self.tlas_list;
        let grid = &self.grid;
        let a = &self.config.assembly;
        assemble(
            list.len(),
            &mut self.records,
            a.threads,
            a.parallel_threshold,
            |i| {
                let (loc, address) = list[i];
                TlasInstance {
                    blas_address: address,
                    ..grid.at(loc).data.template
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
    t: &'a mut Tables,
    lod: &'a LodSelector,
    visits: &'a mut Vec<Visit>,
}

impl ResidencyPass<'_> {
    /// Squared distance from the nearest camera to the centre, and whether the sphere lies
    /// wholly beyond r2.
    fn distance(&self, ge: &GridEntry<Hot>) -> (f32, bool) {
        let c = Vec3::from(ge.center);
        let d2 = self
            .cams
            .iter()
            .map(|p| p.distance_squared(c))
            .fold(f32::INFINITY, f32::min);
        let reach = self.r2 + ge.radius;
        (d2, d2 > reach * reach)
    }

    /// Picks the instance's LOD by projected error (a `landmark` too), creates its entry, and marks
    /// the entry requested (within r1, beyond r2) and kept.
    fn visit(
        &mut self,
        loc: GridLoc,
        ge: &mut GridEntry<Hot>,
        center_dist: f32,
        beyond_r2: bool,
        landmark: bool,
    ) {
        let (t, frame) = (&mut *self.t, self.frame);
        let c = Vec3::from(ge.center);
        let surface_dist = (center_dist - ge.radius).max(0.0);
        let h = &mut ge.data;
        let mesh = t.meshes[h.mesh as usize]
            .as_ref()
            .expect("instance of a live mesh");
        if landmark && mesh.kind != MeshKind::Static {
            return;
        }
        self.visits.push(Visit {
            loc,
            center_dist,
            beyond_r2,
            landmark,
        });
        let was_visited = h.last_visit == frame.wrapping_sub(1);
        let current = if was_visited {
            h.lod_target as usize
        } else {
            mesh.nlods as usize - 1
        };
        // A landmark picks its LOD by projected error like the near field: its BLAS is still
        // the mesh's shared one for that LOD (memory stays per mesh, not per instance), and
        // the coarsest LOD's silhouette was the far field's largest error (docs/RESULTS.md).
        let lodi = self.lod.select(
            mesh.errors(),
            h.scale,
            surface_dist,
            current,
            mesh.lod_floor as usize,
        );
        // A GPU builds only from resident data: the nearest LOD that has some.
        let built = |l: usize| {
            mesh.kind == MeshKind::Static
                && mesh.lod_entry[l] != NONE
                && t.entries[mesh.lod_entry[l] as usize].state == EntryState::Built
        };
        let Some(lodi) = mesh.with_data(lodi, self.need_data, built) else {
            return;
        };
        h.lod_target = lodi as u8;
        h.last_visit = frame;
        if !was_visited {
            h.culled = true;
        }
        let kind = mesh.kind;
        let tris = mesh.lod_tris[lodi];
        let mut slot = match kind {
            MeshKind::Static => mesh.lod_entry[lodi],
            MeshKind::Skinned
                if t.entry_valid(h.own) && t.entries[h.own.0 as usize].lod as usize == lodi =>
            {
                h.own.0
            }
            MeshKind::Skinned => NONE,
        };
        if slot == NONE {
            let owner = if kind == MeshKind::Skinned {
                ge.slot
            } else {
                NONE
            };
            slot = t.new_entry(h.mesh, lodi as u8, owner, tris, frame);
            match kind {
                MeshKind::Static => {
                    t.meshes[h.mesh as usize].as_mut().expect("live").lod_entry[lodi] = slot
                }
                MeshKind::Skinned => h.own = t.key(slot),
            }
        }
        let requested = surface_dist <= self.r1 || beyond_r2;
        let in_view = requested
            && self
                .cams
                .iter()
                .zip(self.fwds)
                .any(|(p, f)| f.dot(c - *p) >= 0.0);
        let e = &mut t.entries[slot as usize];
        if requested {
            if e.last_request.wrapping_add(1) < frame || e.last_request > frame {
                e.streak_start = frame;
            }
            e.last_request = frame;
        }
        e.last_keep = frame;
        if e.dist_frame != frame {
            e.dist_frame = frame;
            e.min_dist = surface_dist;
            e.in_view = in_view;
        } else {
            e.min_dist = e.min_dist.min(surface_dist);
            e.in_view |= in_view;
        }
        if t.entry_valid(h.shown) {
            t.entries[h.shown.0 as usize].last_keep = frame;
        }
    }
}
