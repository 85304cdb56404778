//! Finer-LOD streaming under the mesh memory budget (see the `world` module header).

use super::{StreamFocus, World, WorldEvent};
use crate::loader::Job;
use crate::model::WorldMeshId;

impl World {
    pub(super) fn stream_lods(&mut self, cameras: &[StreamFocus], ev: &mut Vec<WorldEvent>) {
        let _span = tracing::trace_span!("lod_stream").entered();
        if cameras.is_empty() {
            return;
        }
        // Effective distance (distance / scale) of each streamed mesh's nearest loaded
        // instance, by mesh id (infinite: no loaded instance). Every loaded instance is
        // looked at each frame: a dense array by mesh, not a hash map (hashing each instance
        // was a tenth of this pass), and the instances of all levels in one array
        // (`ranges::LevelRanges`), not one per level.
        let mut eff = std::mem::take(&mut self.lod_eff);
        eff.clear();
        eff.resize(self.meshes.len(), f32::INFINITY);
        for p in self.lod_points.live() {
            let d = cameras
                .iter()
                .map(|c| ((c.position - p.center).length() - p.radius).max(0.0))
                .fold(f32::INFINITY, f32::min)
                / p.scale;
            let e = &mut eff[p.mesh.0 as usize];
            *e = e.min(d);
        }
        self.shed_finer(&eff, ev);
        let angle = self.config.lod_error_angle;
        let mut requests: Vec<(f32, WorldMeshId, usize)> = Vec::new();
        for (i, &d) in eff.iter().enumerate().filter(|(_, d)| d.is_finite()) {
            let m = WorldMeshId(i as u32);
            let slot = &mut self.meshes[m.0 as usize];
            let want = slot.desired(d, angle);
            let keep = slot.desired(d / self.config.lod_evict_factor, angle);
            // Evict a finer LOD that is finer than needed even closer up.
            for k in 0..slot.coarsest() {
                if k < keep && slot.resident[k].take().is_some() {
                    self.mesh_bytes -= slot.lods[k].0;
                    ev.push(WorldEvent::MeshLodEvicted {
                        mesh: m,
                        lod: k as u8,
                    });
                }
            }
            let finest = slot.finest_resident().unwrap_or(slot.coarsest());
            if want < finest && slot.pending.is_none() && !slot.failed[want] {
                requests.push((d, m, want));
            }
        }
        requests.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (d, m, lod) in requests {
            if self.in_flight - self.landmark_in_flight >= self.config.max_in_flight {
                break;
            }
            let bytes = self.meshes[m.0 as usize].lods[lod].0;
            if !self.make_room(bytes, d, &eff, ev) {
                continue;
            }
            let ticket = self.new_ticket();
            self.meshes[m.0 as usize].pending = Some((lod, ticket));
            self.in_flight_bytes += bytes;
            self.in_flight += 1;
            self.pool.submit(Job::Lod {
                mesh: m,
                lod,
                ticket,
            });
        }
        self.lod_eff = eff;
    }

    /// Coarsest LODs arrive with their levels and are never refused; when they push resident
    /// plus in-flight bytes over the budget (finer LODs admitted while those levels were still
    /// loading), finer LODs go, farthest mesh first, until the total fits again (or nothing
    /// finer is left: the budget is then below what the load radius holds).
    fn shed_finer(&mut self, eff: &[f32], ev: &mut Vec<WorldEvent>) {
        let budget = self.config.mesh_budget_bytes;
        if self.mesh_bytes + self.in_flight_bytes <= budget {
            return;
        }
        let mut victims = self.finer_lods(eff, None);
        // Farthest first; at equal distance the finest (largest) LOD first, in id order.
        victims.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.2.cmp(&b.2)).then(a.1.cmp(&b.1)));
        self.evict_until_fits(victims, 0, ev);
    }

    /// The resident LODs finer than the coarsest of the streamed meshes (farther than `beyond`
    /// when given), as (mesh distance, mesh, LOD), in mesh and LOD order.
    fn finer_lods(&self, eff: &[f32], beyond: Option<f32>) -> Vec<(f32, WorldMeshId, usize)> {
        let mut victims = Vec::new();
        for (i, s) in self.meshes.iter().enumerate() {
            if !s.streamed {
                continue;
            }
            let m = WorldMeshId(i as u32);
            let md = eff.get(i).copied().unwrap_or(f32::INFINITY);
            if beyond.is_some_and(|d| md <= d) {
                continue;
            }
            for k in 0..s.coarsest() {
                if s.resident[k].is_some() {
                    victims.push((md, m, k));
                }
            }
        }
        victims
    }

    /// Evicts `victims` in their order until resident plus in-flight plus `bytes` fit the budget.
    fn evict_until_fits(
        &mut self,
        victims: Vec<(f32, WorldMeshId, usize)>,
        bytes: usize,
        ev: &mut Vec<WorldEvent>,
    ) {
        let budget = self.config.mesh_budget_bytes;
        for (_, m, k) in victims {
            if self.mesh_bytes + self.in_flight_bytes + bytes <= budget {
                break;
            }
            let s = &mut self.meshes[m.0 as usize];
            if s.resident[k].take().is_some() {
                self.mesh_bytes -= s.lods[k].0;
                ev.push(WorldEvent::MeshLodEvicted {
                    mesh: m,
                    lod: k as u8,
                });
            }
        }
    }

    /// Evicts finer LODs of meshes farther than `d` (farthest first) until `bytes` fit the budget.
    fn make_room(&mut self, bytes: usize, d: f32, eff: &[f32], ev: &mut Vec<WorldEvent>) -> bool {
        let budget = self.config.mesh_budget_bytes;
        if self.mesh_bytes + self.in_flight_bytes + bytes <= budget {
            return true;
        }
        let mut victims = self.finer_lods(eff, Some(d));
        // Evict only if that makes enough room; evicting for a request that still does not fit
        // would make the victims re-request and thrash.
        let freeable: usize = victims
            .iter()
            .map(|&(_, m, k)| self.meshes[m.0 as usize].lods[k].0)
            .sum();
        if self.mesh_bytes + self.in_flight_bytes + bytes > budget + freeable {
            return false;
        }
        victims.sort_by(|a, b| b.0.total_cmp(&a.0));
        self.evict_until_fits(victims, bytes, ev);
        self.mesh_bytes + self.in_flight_bytes + bytes <= budget
    }
}
