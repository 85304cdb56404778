//! The BLAS memory budget: what a build may evict (eviction order, proxies last), the LOD
//! floors that fall back to coarser LODs under pressure, and the back-off after the backend
//! answered out of memory.

use super::state::{EntryKey, EntryState};
use super::AsManager;
use crate::backend::AsBackend;

impl<B: AsBackend> AsManager<B> {
    /// Eviction order: not near any camera this frame first, then farthest, then least
    /// recently in the TLAS. Larger is evicted first.
    /// Far-field proxies come last, whatever their distance.
    fn eviction_score(&self, key: EntryKey) -> (bool, bool, f32, u64) {
        let e = &self.tables.entries[key];
        let proxy = e.proxy;
        let near = e.dist_frame == self.frame;
        let age = self.frame - e.last_in_tlas.unwrap_or(0).min(self.frame);
        (
            !proxy,
            !near,
            if near { e.min_dist } else { f32::INFINITY },
            age,
        )
    }

    /// Evicts built entries scoring worse than `than` (or any when `None`) until `need` more
    /// bytes fit under the budget, counting bytes already retiring as soon-free. Returns
    /// whether `need` fits now (not counting retiring bytes: those still occupy memory).
    /// Entries younger than `min_resident_frames` are spared for a build (no thrash), not for
    /// a budget that is already exceeded (`hard`).
    pub(super) fn make_room(
        &mut self,
        need: u64,
        than: Option<f32>,
        budget: u64,
        hard: bool,
    ) -> bool {
        if self.memory_in_use() + need <= budget {
            return true;
        }
        if self.live_bytes + need <= budget {
            return false; // wait for in-flight frees
        }
        let min_life = if hard {
            0
        } else {
            self.config.residency.min_resident_frames as u64
        };
        let mut cands: Vec<(bool, bool, f32, u64, EntryKey)> = self
            .tables
            .active
            .iter()
            .copied()
            .filter(|&s| {
                let e = &self.tables.entries[s];
                e.state == EntryState::Built && self.frame.saturating_sub(e.created) >= min_life
            })
            .map(|s| {
                let (detail, far, d, age) = self.eviction_score(s);
                (detail, far, d, age, s)
            })
            .filter(|&(_, far, d, _, _)| than.is_none_or(|t| far || d > t))
            .collect();
        cands.sort_by(|a, b| {
            b.0.cmp(&a.0)
                .then(b.1.cmp(&a.1))
                .then(b.2.total_cmp(&a.2))
                .then(b.3.cmp(&a.3))
        });
        for (detail, _, _, _, s) in cands {
            if self.live_bytes + need <= budget {
                break;
            }
            self.release_entry(s);
            self.stats.evictions += 1;
            if !detail {
                self.stats.proxies_evicted += 1;
            }
        }
        self.memory_in_use() + need <= budget
    }

    /// After a budget cut or an OOM: evict until the built bytes fit.
    pub(crate) fn enforce_budget(&mut self) {
        if self.live_bytes > self.budget() {
            self.make_room(0, None, self.budget(), true);
        }
    }

    /// The device ran out of memory below our budget: cap the budget at what is in use now
    /// (minus 10%), or — when little is held — at what is held plus half of the batch that
    /// failed, so a first batch too large for the device is retried at half size instead of
    /// starving the frame; then evict down to it. The queue retries on later frames.
    pub(super) fn on_oom(&mut self, failed_bytes: u64) {
        self.stats.oom_events += 1;
        self.oom_frame = self.frame;
        let in_use = self.memory_in_use();
        let cap = ((in_use as f64 * 0.9) as u64).max(in_use + failed_bytes / 2);
        self.oom_cap = Some(self.oom_cap.map_or(cap, |c| c.min(cap)).max(1));
        tracing::warn!(cap, "backend out of memory; budget capped");
        self.enforce_budget();
    }

    /// Lowers memory-fallback LOD floors again once memory is comfortably under budget.
    pub(crate) fn relax_floors(&mut self) {
        if self.floors.is_empty() || self.memory_in_use() as f64 > 0.75 * self.budget() as f64 {
            return;
        }
        let frame = self.frame;
        let meshes = &mut self.tables.meshes;
        let landmarks = &mut self.landmarks;
        self.floors.retain(|&m| {
            let Some(Some(mesh)) = meshes.get_mut(m as usize) else {
                return false;
            };
            if frame.saturating_sub(mesh.floor_since) >= 60 {
                mesh.lod_floor = mesh.lod_floor.saturating_sub(1);
                mesh.floor_since = frame;
                landmarks.mesh_changed(m);
            }
            mesh.lod_floor > 0
        });
    }
}
