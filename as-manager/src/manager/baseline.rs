//! The comparison policies behind the same API: `Naive` and `SeedR1R2`.

use super::state::{EntryKey, EntryState};
use super::AsManager;
use crate::backend::AsBackend;
use crate::config::{CullConfig, CullMode};
use crate::cull::InstanceCuller;
use crate::mesh::MeshKind;
use crate::Result;

impl<B: AsBackend> AsManager<B> {
    /// The finest LOD of a mesh that is loaded: it holds data, or the backend needs none (the
    /// model backend counts every LOD as loaded).
    pub(crate) fn finest_loaded(&self, mesh: u32) -> Option<usize> {
        let m = self.tables.meshes[mesh as usize].as_ref()?;
        let need = self.backend.needs_geometry();
        (0..m.nlods as usize).find(|&l| !need || m.desc.lods[l].geometry.is_buildable())
    }

    /// Naive: a BLAS for every loaded LOD of every static mesh (built as soon as the LOD
    /// loads, released when its data is evicted), and one for each skinned instance at its
    /// mesh's finest loaded LOD.
    fn naive_residency(&mut self) {
        let need = self.backend.needs_geometry();
        let frame = self.frame;
        for mesh in 0..self.tables.meshes.len() as u32 {
            let Some(m) = self.tables.meshes[mesh as usize].as_ref() else {
                continue;
            };
            if m.kind() != MeshKind::Static || m.proxy {
                continue;
            }
            let lods: Vec<(bool, Option<EntryKey>, u32)> = (0..m.nlods as usize)
                .map(|l| {
                    let g = &m.desc.lods[l].geometry;
                    (!need || g.is_buildable(), m.lod_entry[l], g.triangles())
                })
                .collect();
            for (lod, (loaded, entry, tris)) in lods.into_iter().enumerate() {
                match (loaded, entry) {
                    (true, None) => {
                        let key = self.tables.new_entry(mesh, lod as u8, None, tris, frame);
                        self.tables.entries[key].state = EntryState::Queued;
                        self.tables.meshes[mesh as usize]
                            .as_mut()
                            .expect("live")
                            .lod_entry[lod] = Some(key);
                    }
                    (false, Some(key)) => {
                        self.release_entry(key);
                        self.stats.releases += 1;
                    }
                    // Queued entries whose data came back after a miss: queue again.
                    (true, Some(key)) if self.tables.entries[key].state == EntryState::Idle => {
                        self.tables.entries[key].state = EntryState::Queued;
                    }
                    _ => {}
                }
            }
        }
        for slot in 0..self.tables.instances.len() as u32 {
            let Some(inst) = self.tables.instances[slot as usize].as_ref() else {
                continue;
            };
            let mesh = inst.mesh;
            let m = self.tables.meshes[mesh as usize].as_ref().expect("live");
            if m.kind() != MeshKind::Skinned {
                continue;
            }
            let own = self.grid.get(slot).expect("indexed").data.own;
            if let Some((key, e)) = own.and_then(|k| Some((k, self.tables.entries.get(k)?))) {
                // Not built and its data is gone: start again at the finest loaded LOD.
                if e.state != EntryState::Idle {
                    continue;
                }
                self.release_entry(key);
            }
            let Some(lod) = self.finest_loaded(mesh) else {
                continue;
            };
            let tris = self.tables.meshes[mesh as usize]
                .as_ref()
                .expect("live")
                .desc
                .lods[lod]
                .geometry
                .triangles();
            let key = self
                .tables
                .new_entry(mesh, lod as u8, Some(slot), tris, frame);
            self.tables.entries[key].state = EntryState::Queued;
            self.grid.get_mut(slot).expect("indexed").data.own = Some(key);
        }
    }

    /// Naive frame: a BLAS for every loaded LOD, build everything queued (no budget), refit
    /// everything, no culling: every instance goes into the TLAS at the finest LOD of its mesh
    /// with a built BLAS (skinned: its own).
    pub(crate) fn naive_frame(&mut self) -> Result<()> {
        self.naive_residency();
        self.reserve_gpu(false);
        self.schedule_builds(false)?;
        self.schedule_refits(false)?;
        self.tlas_list.clear();
        for slot in 0..self.tables.instances.len() {
            let Some(inst) = self.tables.instances[slot].as_ref() else {
                continue;
            };
            let m = self.tables.meshes[inst.mesh as usize]
                .as_ref()
                .expect("live");
            let loc = self.grid.loc(slot as u32).expect("indexed");
            let key = match m.kind() {
                MeshKind::Static => m.lod_entry[..m.nlods as usize]
                    .iter()
                    .copied()
                    .find(|&k| self.tables.built(k))
                    .flatten(),
                MeshKind::Skinned => self.grid.at(loc).data.own,
            };
            if let Some(key) = key.filter(|&k| self.tables.built(Some(k))) {
                let e = &mut self.tables.entries[key];
                e.last_in_tlas = Some(self.frame);
                let addr = e.record_address(&self.backend);
                self.tlas_list.push((slot as u32, addr));
            }
        }
        self.stats.instances_visited = self.live_instances;
        self.assemble_records();
        Ok(())
    }

    /// Seed: drop an instance's reference to its (mesh, LOD 0) BLAS; free it at zero.
    pub(crate) fn seed_drop_ref(&mut self, slot: u32) {
        self.tables.instances[slot as usize]
            .as_mut()
            .expect("live")
            .seed_has = false;
        let hot = &mut self.grid.get_mut(slot).expect("indexed").data;
        let Some(key) = hot.shown.take() else {
            return;
        };
        if let Some(e) = self.tables.entries.get_mut(key) {
            e.refs = e.refs.saturating_sub(1);
            if e.refs == 0 {
                self.release_entry(key);
                self.stats.releases += 1;
            }
        }
    }

    /// The seeds' loop: per camera, one pass over every instance marking request (d < r1) and
    /// keep (d < r2) frames; then one pass creating (requested within CreateThreshold frames)
    /// and releasing (not kept for more than ReleaseThreshold frames); then UE-style culling
    /// over every instance. No budgets.
    pub(crate) fn seed_frame(&mut self) -> Result<()> {
        let frame = self.frame;
        let rc = self.config.residency.clone();
        let n = self.tables.instances.len();
        for ci in 0..self.cam_pos.len() {
            let cam = self.cam_pos[ci];
            for inst in self.tables.instances.iter_mut().flatten() {
                let d = (cam.distance(inst.center) - inst.radius).max(0.0);
                if d < rc.r1 {
                    inst.seed_request = Some(frame);
                }
                if d < rc.r2 {
                    inst.seed_keep = Some(frame);
                }
            }
        }
        for slot in 0..n {
            let Some(inst) = self.tables.instances[slot].as_ref() else {
                continue;
            };
            let recent = inst
                .seed_request
                .is_some_and(|f| frame - f <= rc.create_threshold as u64);
            let stale = inst
                .seed_keep
                .is_none_or(|f| frame - f > rc.release_threshold as u64);
            if recent && !inst.seed_has {
                let mesh_ix = inst.mesh;
                // The finest LOD loaded now (the loop never looks at LODs again).
                let Some(lod) = self.finest_loaded(mesh_ix) else {
                    continue;
                };
                let m = self.tables.meshes[mesh_ix as usize].as_ref().expect("live");
                let tris = m.desc.lods[lod].geometry.triangles();
                let key = match (m.kind(), m.lod_entry[lod]) {
                    (MeshKind::Static, Some(key)) => key,
                    (MeshKind::Static, None) => {
                        let key = self.tables.new_entry(mesh_ix, lod as u8, None, tris, frame);
                        self.tables.meshes[mesh_ix as usize]
                            .as_mut()
                            .expect("live")
                            .lod_entry[lod] = Some(key);
                        key
                    }
                    (MeshKind::Skinned, _) => {
                        self.tables
                            .new_entry(mesh_ix, lod as u8, Some(slot as u32), tris, frame)
                    }
                };
                let e = &mut self.tables.entries[key];
                e.refs += 1;
                if e.state == EntryState::Idle {
                    e.state = EntryState::Queued;
                }
                let owned = e.owner.is_some();
                self.tables.instances[slot].as_mut().expect("live").seed_has = true;
                let hot = &mut self.grid.get_mut(slot as u32).expect("indexed").data;
                hot.shown = Some(key);
                if owned {
                    hot.own = Some(key);
                }
            } else if inst.seed_has && stale {
                self.seed_drop_ref(slot as u32);
            } else if inst.seed_has {
                // Its BLAS was never built and its data left: take the finest loaded LOD
                // at the next create pass.
                let shown = self.grid.get(slot as u32).expect("indexed").data.shown;
                let idle = shown
                    .and_then(|k| self.tables.entries.get(k))
                    .is_some_and(|e| e.state == EntryState::Idle);
                if idle {
                    self.seed_drop_ref(slot as u32);
                }
            }
        }
        self.reserve_gpu(false);
        self.schedule_builds(false)?;
        self.schedule_refits(false)?;
        let culler = InstanceCuller::new(&CullConfig {
            hysteresis: 0.0,
            mode: CullMode::FarOrSmall,
            ..self.config.cull.clone()
        });
        self.tlas_list.clear();
        let mut culled = 0;
        for slot in 0..n {
            let Some(inst) = self.tables.instances[slot].as_ref() else {
                continue;
            };
            if !inst.seed_has {
                continue;
            }
            let loc = self.grid.loc(slot as u32).expect("indexed");
            let Some(shown) = self.grid.at(loc).data.shown else {
                continue;
            };
            if !self.tables.built(Some(shown)) {
                continue;
            }
            let mut d2 = f32::INFINITY;
            for c in &self.cam_pos {
                d2 = d2.min(c.distance_squared(inst.center));
            }
            if culler.cull(inst.radius, d2.sqrt(), false) {
                culled += 1;
                continue;
            }
            let e = &mut self.tables.entries[shown];
            e.last_in_tlas = Some(frame);
            let addr = e.record_address(&self.backend);
            self.tlas_list.push((slot as u32, addr));
        }
        self.stats.culled = culled;
        self.stats.instances_visited = self.live_instances;
        self.assemble_records();
        Ok(())
    }
}
