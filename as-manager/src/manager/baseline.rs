//! The comparison policies behind the same API: `Naive` and `SeedR1R2`.

use super::state::{EntryState, NONE};
use super::AsManager;
use crate::backend::AsBackend;
use crate::config::{CullConfig, CullMode};
use crate::cull::InstanceCuller;
use crate::mesh::MeshKind;
use crate::Result;

impl<B: AsBackend> AsManager<B> {
    /// Naive: every LOD of a static mesh gets a BLAS as soon as it is registered.
    pub(crate) fn naive_register_mesh(&mut self, mesh: u32) {
        let m = self.t.meshes[mesh as usize]
            .as_ref()
            .expect("just registered");
        if m.kind() != MeshKind::Static {
            return;
        }
        let tris: Vec<u32> = m.desc.lods.iter().map(|l| l.geometry.triangles()).collect();
        for (lod, t) in tris.into_iter().enumerate() {
            let s = self.t.new_entry(mesh, lod as u8, NONE, t, self.frame);
            self.t.entries[s as usize].state = EntryState::Queued;
            self.t.meshes[mesh as usize]
                .as_mut()
                .expect("live")
                .lod_entry[lod] = s;
        }
    }

    /// Naive: a skinned instance gets its LOD-0 BLAS at once.
    pub(crate) fn naive_add_instance(&mut self, slot: u32) {
        let inst = self.t.instances[slot as usize]
            .as_ref()
            .expect("just added");
        let m = self.t.meshes[inst.mesh as usize].as_ref().expect("live");
        if m.kind() != MeshKind::Skinned {
            return;
        }
        let (mesh, t) = (inst.mesh, m.desc.lods[0].geometry.triangles());
        let s = self.t.new_entry(mesh, 0, slot, t, self.frame);
        self.t.entries[s as usize].state = EntryState::Queued;
        let key = self.t.key(s);
        self.grid.get_mut(slot).expect("indexed").data.own = key;
    }

    /// Naive frame: build everything queued (no budget), refit everything, no culling: every
    /// instance with a built LOD-0 BLAS goes into the TLAS.
    pub(crate) fn naive_frame(&mut self) -> Result<()> {
        self.schedule_builds(false)?;
        self.schedule_refits(false)?;
        self.tlas_list.clear();
        for slot in 0..self.t.instances.len() {
            let Some(inst) = self.t.instances[slot].as_ref() else {
                continue;
            };
            let m = self.t.meshes[inst.mesh as usize].as_ref().expect("live");
            let loc = self.grid.loc(slot as u32).expect("indexed");
            let key = match m.kind() {
                MeshKind::Static => (
                    m.lod_entry[0],
                    if m.lod_entry[0] == NONE {
                        0
                    } else {
                        self.t.entries[m.lod_entry[0] as usize].generation
                    },
                ),
                MeshKind::Skinned => self.grid.at(loc).data.own,
            };
            if self.t.built(key) {
                let e = &mut self.t.entries[key.0 as usize];
                e.last_in_tlas = Some(self.frame);
                let addr = self.backend.blas_address(e.handle.expect("built"));
                self.tlas_list.push((loc, addr));
            }
        }
        self.stats.instances_visited = self.live_instances;
        self.assemble_records();
        Ok(())
    }

    /// Seed: drop an instance's reference to its (mesh, LOD 0) BLAS; free it at zero.
    pub(crate) fn seed_drop_ref(&mut self, slot: u32) {
        self.t.instances[slot as usize]
            .as_mut()
            .expect("live")
            .seed_has = false;
        let h = &mut self.grid.get_mut(slot).expect("indexed").data;
        let key = h.shown;
        h.shown = (NONE, 0);
        if self.t.entry_valid(key) {
            let e = &mut self.t.entries[key.0 as usize];
            e.refs = e.refs.saturating_sub(1);
            if e.refs == 0 {
                self.release_entry(key.0);
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
        let n = self.t.instances.len();
        for ci in 0..self.cam_pos.len() {
            let cam = self.cam_pos[ci];
            for inst in self.t.instances.iter_mut().flatten() {
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
            let Some(inst) = self.t.instances[slot].as_ref() else {
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
                let m = self.t.meshes[mesh_ix as usize].as_ref().expect("live");
                let tris = m.desc.lods[0].geometry.triangles();
                let s = match m.kind() {
                    MeshKind::Static if m.lod_entry[0] != NONE => m.lod_entry[0],
                    MeshKind::Static => {
                        let s = self.t.new_entry(mesh_ix, 0, NONE, tris, frame);
                        self.t.meshes[mesh_ix as usize]
                            .as_mut()
                            .expect("live")
                            .lod_entry[0] = s;
                        s
                    }
                    MeshKind::Skinned => self.t.new_entry(mesh_ix, 0, slot as u32, tris, frame),
                };
                let e = &mut self.t.entries[s as usize];
                e.refs += 1;
                if e.state == EntryState::Idle {
                    e.state = EntryState::Queued;
                }
                let key = self.t.key(s);
                let owned = self.t.entries[s as usize].owner != NONE;
                self.t.instances[slot].as_mut().expect("live").seed_has = true;
                let h = &mut self.grid.get_mut(slot as u32).expect("indexed").data;
                h.shown = key;
                if owned {
                    h.own = key;
                }
            } else if inst.seed_has && stale {
                self.seed_drop_ref(slot as u32);
            }
        }
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
            let Some(inst) = self.t.instances[slot].as_ref() else {
                continue;
            };
            if !inst.seed_has {
                continue;
            }
            let loc = self.grid.loc(slot as u32).expect("indexed");
            let shown = self.grid.at(loc).data.shown;
            if !self.t.built(shown) {
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
            let e = &mut self.t.entries[shown.0 as usize];
            e.last_in_tlas = Some(frame);
            let addr = self.backend.blas_address(e.handle.expect("built"));
            self.tlas_list.push((loc, addr));
        }
        self.stats.culled = culled;
        self.stats.instances_visited = self.live_instances;
        self.assemble_records();
        Ok(())
    }
}
