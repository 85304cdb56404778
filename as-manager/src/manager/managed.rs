//! The `Managed` policy's frame: residency through the spatial index, LOD with hysteresis,
//! entry upkeep, culling and assembly. Scheduling and memory are in `schedule.rs`.

use glam::Vec3;

use super::state::{EntryState, NONE};
use super::{AsManager, Visit};
use crate::backend::AsBackend;
use crate::mesh::MeshKind;
use crate::record::{assemble, TlasInstance};
use crate::Result;

impl<B: AsBackend> AsManager<B> {
    pub(crate) fn managed_frame(&mut self) -> Result<()> {
        {
            let _s = tracing::trace_span!("residency").entered();
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
        }
        let _s = tracing::trace_span!("assemble").entered();
        self.assemble_records();
        Ok(())
    }

    /// Visits instances within r2 of any camera; picks LODs; marks request/keep.
    fn residency_pass(&mut self) {
        let r2 = self.config.residency.r2;
        let r1 = self.config.residency.r1;
        let frame = self.frame;
        let Self { grid, visits, cam_pos, .. } = self;
        visits.clear();
        let cams: &[Vec3] = cam_pos;
        grid.query(cams, r2, |e| {
            let c = Vec3::from(e.center);
            let mut d2 = f32::INFINITY;
            for p in cams {
                d2 = d2.min(p.distance_squared(c));
            }
            let center_dist = d2.sqrt();
            let surface_dist = (center_dist - e.radius).max(0.0);
            if surface_dist <= r2 {
                visits.push(Visit {
                    slot: e.slot,
                    center_dist,
                    surface_dist,
                });
            }
        });
        self.stats.instances_visited = self.visits.len() as u32;
        let need_data = self.backend.needs_geometry();
        for vi in 0..self.visits.len() {
            let v = self.visits[vi];
            let Some(inst) = self.t.instances[v.slot as usize].as_mut() else { continue };
            let mesh = self.t.meshes[inst.mesh as usize].as_ref().expect("instance of a live mesh");
            let was_visited = inst.last_visit == frame.wrapping_sub(1);
            let current = if was_visited { inst.lod_target as usize } else { mesh.errors.len() - 1 };
            let lod = self.lod.select(&mesh.errors, inst.scale, v.surface_dist, current, mesh.lod_floor as usize);
            // A GPU builds only from resident data: the nearest LOD that has some.
            let Some(lod) = mesh.with_data(lod, need_data) else { continue };
            inst.lod_target = lod as u8;
            inst.last_visit = frame;
            if !was_visited {
                inst.culled = true;
            }
            let shown = inst.shown;
            let center = inst.center;
            let (mesh_ix, own) = (inst.mesh, inst.own);
            let kind = mesh.kind();
            let tris = mesh.desc.lods[lod].geometry.triangles();
            let mut slot = match kind {
                MeshKind::Static => mesh.lod_entry[lod],
                MeshKind::Skinned if self.t.entry_valid(own) && self.t.entries[own.0 as usize].lod as usize == lod => own.0,
                MeshKind::Skinned => NONE,
            };
            if slot == NONE {
                let owner = if kind == MeshKind::Skinned { v.slot } else { NONE };
                slot = self.t.new_entry(mesh_ix, lod as u8, owner, tris, frame);
                let key = self.t.key(slot);
                match kind {
                    MeshKind::Static => self.t.meshes[mesh_ix as usize].as_mut().expect("live").lod_entry[lod] = slot,
                    MeshKind::Skinned => self.t.instances[v.slot as usize].as_mut().expect("live").own = key,
                }
            }
            let requested = v.surface_dist <= r1;
            let in_view = requested && {
                let mut any = false;
                for (p, f) in self.cam_pos.iter().zip(&self.cam_fwd) {
                    any |= f.dot(center - *p) >= 0.0;
                }
                any
            };
            let e = &mut self.t.entries[slot as usize];
            if requested {
                if e.last_request.wrapping_add(1) < frame || e.last_request > frame {
                    e.streak_start = frame;
                }
                e.last_request = frame;
            }
            e.last_keep = frame;
            if e.dist_frame != frame {
                e.dist_frame = frame;
                e.min_dist = v.surface_dist;
                e.in_view = in_view;
            } else {
                e.min_dist = e.min_dist.min(v.surface_dist);
                e.in_view |= in_view;
            }
            if self.t.entry_valid(shown) {
                self.t.entries[shown.0 as usize].last_keep = frame;
            }
        }
    }

    /// Creation after `create_threshold` requested frames; release after `release_threshold`
    /// unkept frames (and `min_resident_frames` of life); forgetting stale unbuilt entries.
    fn upkeep_entries(&mut self) {
        let frame = self.frame;
        let rc = &self.config.residency;
        let (create, release, min_life) = (rc.create_threshold as u64, rc.release_threshold as u64, rc.min_resident_frames as u64);
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
        let mut culled_count = 0;
        for vi in 0..self.visits.len() {
            let v = self.visits[vi];
            let Some(inst) = self.t.instances[v.slot as usize].as_ref() else { continue };
            let mesh = self.t.meshes[inst.mesh as usize].as_ref().expect("live mesh");
            let target = match mesh.kind() {
                MeshKind::Static => {
                    let s = mesh.lod_entry[inst.lod_target as usize];
                    if s == NONE {
                        (NONE, 0)
                    } else {
                        self.t.key(s)
                    }
                }
                MeshKind::Skinned => inst.own,
            };
            let chosen = if self.t.built(target) {
                target
            } else if self.t.built(inst.shown) && self.t.entries[inst.shown.0 as usize].mesh == inst.mesh {
                inst.shown
            } else if mesh.kind() == MeshKind::Static {
                // nearest built LOD, coarser first
                let t = inst.lod_target as usize;
                let n = mesh.errors.len();
                let order = (t..n).chain((0..t).rev());
                let mut found = (NONE, 0);
                for l in order {
                    let s = mesh.lod_entry[l];
                    if s != NONE && self.t.entries[s as usize].state == EntryState::Built {
                        found = self.t.key(s);
                        break;
                    }
                }
                found
            } else {
                (NONE, 0)
            };
            let was_culled = inst.culled;
            let culled = self.culler.cull(inst.radius, v.center_dist, was_culled);
            let inst = self.t.instances[v.slot as usize].as_mut().expect("live");
            inst.shown = chosen;
            inst.culled = culled;
            if chosen.0 != NONE {
                if culled {
                    culled_count += 1;
                } else {
                    let e = &mut self.t.entries[chosen.0 as usize];
                    e.last_in_tlas = Some(frame);
                    e.last_keep = frame;
                    let h = e.handle.expect("built entry has a handle");
                    self.tlas_list.push((v.slot, self.backend.blas_address(h)));
                }
            }
        }
        self.stats.culled = culled_count;
    }

    /// Writes the records for `tlas_list` (parallel when large).
    pub(crate) fn assemble_records(&mut self) {
        let list = &self.tlas_list;
        let insts = &self.t.instances;
        let a = &self.config.assembly;
        assemble(list.len(), &mut self.records, a.threads, a.parallel_threshold, |i| {
            let (slot, address) = list[i];
            let inst = insts[slot as usize].as_ref().expect("live instance in TLAS list");
            TlasInstance {
                transform: inst.rows,
                custom_index_and_mask: inst.custom_index | ((inst.mask as u32) << 24),
                sbt_offset_and_flags: inst.sbt_offset | ((inst.flags as u32) << 24),
                blas_address: address,
            }
        });
    }
}
