//! Finer-LOD streaming under the mesh memory budget (see the `world` module header).

use std::collections::HashMap;

use glam::Vec3;

use super::ranges::LevelRanges;
use super::{LodPoint, StreamFocus, World, WorldEvent};
use crate::loader::Job;
use crate::model::WorldMeshId;

impl World {
    pub(super) fn stream_lods(&mut self, cameras: &[StreamFocus], ev: &mut Vec<WorldEvent>) {
        let _span = tracing::trace_span!("lod_stream").entered();
        if cameras.is_empty() {
            return;
        }
        // Effective distance (distance / scale) of each streamed mesh's nearest loaded
        // instance, by mesh id (infinite: no loaded instance): a dense array by mesh, not a
        // hash map (hashing each instance was a tenth of this pass).
        let mut eff = std::mem::take(&mut self.lod_eff);
        self.lod_points
            .nearest_effective(cameras, self.meshes.len(), &mut eff);
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

/// The loaded instances of streamed meshes, as LOD streaming's pass reads them: all levels in
/// one array (`LevelRanges`: one array per level made the pass a chain of cold reads), each
/// level's sorted by mesh, and what lets the pass skip a level or its instances of a mesh.
#[derive(Debug, Default)]
pub(super) struct LodPoints {
    points: LevelRanges<LodPoint>,
    levels: HashMap<u32, LodLevel>,
    /// Per mesh id: loaded instances, and bounds over every instance loaded since the mesh
    /// last had none (the largest radius, the inverse of the largest scale). They only grow
    /// looser while the mesh stays loaded, which keeps them bounds.
    count: Vec<u32>,
    radius: Vec<f32>,
    inv_scale: Vec<f32>,
    /// The pass's scratch, kept to reuse its allocations: (distance, level) in the order
    /// taken, the meshes not settled yet, and the settled ones as bits.
    order: Vec<(f32, u32)>,
    open: Vec<u32>,
    settled: Vec<u64>,
    /// Instances the last pass read.
    #[cfg(test)]
    read: usize,
}

/// A loaded level as the pass sees it: the box of its instances' centres, its meshes as bits
/// (bit `m % 64` of word `m / 64`) and its instances by mesh.
#[derive(Debug)]
struct LodLevel {
    min: Vec3,
    max: Vec3,
    meshes: Vec<u64>,
    /// The level's instances of one mesh each, in the level's points (sorted by mesh).
    groups: Vec<MeshGroup>,
}

/// A level's instances of one mesh: where they are in the level's points, their largest
/// radius and the inverse of their largest scale.
#[derive(Debug, Clone, Copy)]
struct MeshGroup {
    mesh: u32,
    start: u32,
    len: u32,
    radius: f32,
    inv_scale: f32,
}

impl LodLevel {
    /// The nearest camera's distance to the box of centres: at most the distance of any of
    /// the level's instances.
    fn distance(&self, cameras: &[StreamFocus]) -> f32 {
        cameras
            .iter()
            .map(|c| c.position.distance(c.position.clamp(self.min, self.max)))
            .fold(f32::INFINITY, f32::min)
    }
}

/// At most the effective distance of an instance of at most `radius` and at least
/// `1 / inv_scale` scale whose centre is at least `d` from every camera; made a little smaller
/// still for rounding (the instances' distances are taken from their centres, the bound's
/// from a box).
fn lower_bound(d: f32, radius: f32, inv_scale: f32) -> f32 {
    (d - radius).max(0.0) * inv_scale * (1.0 - 1e-4) - 1e-3
}

impl LodPoints {
    /// Adds (or replaces) a level's points.
    pub(super) fn insert(&mut self, level: u32, points: impl Iterator<Item = LodPoint>) {
        self.remove(level);
        let mut points: Vec<LodPoint> = points.collect();
        points.sort_by_key(|p| p.mesh.0);
        if let Some(first) = points.first() {
            let top = points.last().map_or(0, |p| p.mesh.0 as usize) + 1;
            if self.count.len() < top {
                self.count.resize(top, 0);
                self.radius.resize(top, 0.0);
                self.inv_scale.resize(top, f32::INFINITY);
            }
            let mut l = LodLevel {
                min: first.center,
                max: first.center,
                meshes: vec![0; top.div_ceil(64)],
                groups: Vec::new(),
            };
            for (k, p) in points.iter().enumerate() {
                l.min = l.min.min(p.center);
                l.max = l.max.max(p.center);
                let m = p.mesh.0 as usize;
                if self.count[m] == 0 {
                    self.radius[m] = 0.0;
                    self.inv_scale[m] = f32::INFINITY;
                }
                self.count[m] += 1;
                self.radius[m] = self.radius[m].max(p.radius);
                self.inv_scale[m] = self.inv_scale[m].min(1.0 / p.scale);
                l.meshes[m / 64] |= 1 << (m % 64);
                match l.groups.last_mut() {
                    Some(g) if g.mesh == p.mesh.0 => {
                        g.len += 1;
                        g.radius = g.radius.max(p.radius);
                        g.inv_scale = g.inv_scale.min(1.0 / p.scale);
                    }
                    _ => l.groups.push(MeshGroup {
                        mesh: p.mesh.0,
                        start: k as u32,
                        len: 1,
                        radius: p.radius,
                        inv_scale: 1.0 / p.scale,
                    }),
                }
            }
            self.levels.insert(level, l);
        }
        self.points.insert(level, points.into_iter());
    }

    /// Drops a level's points.
    pub(super) fn remove(&mut self, level: u32) {
        if let Some(l) = self.levels.remove(&level) {
            for g in &l.groups {
                self.count[g.mesh as usize] -= g.len;
            }
        }
        self.points.remove(level);
    }

    /// Into `eff` (resized to `meshes`): each mesh's smallest effective distance (distance
    /// to the nearest camera less the instance's radius, over its scale) over the loaded
    /// instances, infinite for a mesh with none.
    ///
    /// Levels are taken nearest first. A mesh is settled once the levels' distance has
    /// passed its minimum so far by more than its largest radius and scale allow: no
    /// instance farther can lower it. A level of settled meshes only is skipped, and so are
    /// a level's instances of a mesh that cannot be nearer than that mesh's minimum so far;
    /// once every loaded mesh is settled the pass stops. The result is the minimum over every
    /// instance, as a pass over all of them gives (tested); only the work differs. A mesh's
    /// nearest instance is usually in the first levels: at 10x the default density the
    /// fly-through's loaded levels hold about 350,000 instances, and a pass over all of them
    /// took 1.2-1.8 ms of a frame on the H100 host's CPU.
    pub(super) fn nearest_effective(
        &mut self,
        cameras: &[StreamFocus],
        meshes: usize,
        eff: &mut Vec<f32>,
    ) {
        eff.clear();
        eff.resize(meshes.max(self.count.len()), f32::INFINITY);
        self.order.clear();
        self.order.extend(
            self.levels
                .iter()
                .map(|(&level, l)| (l.distance(cameras), level)),
        );
        self.order
            .sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        self.open.clear();
        self.open
            .extend((0..self.count.len() as u32).filter(|&m| self.count[m as usize] > 0));
        self.settled.clear();
        self.settled.resize(self.count.len().div_ceil(64), 0);
        #[cfg(test)]
        {
            self.read = 0;
        }
        for &(d, level) in &self.order {
            let (radius, inv_scale, settled) = (&self.radius, &self.inv_scale, &mut self.settled);
            self.open.retain(|&m| {
                let m = m as usize;
                if eff[m] <= lower_bound(d, radius[m], inv_scale[m]) {
                    settled[m / 64] |= 1 << (m % 64);
                    false
                } else {
                    true
                }
            });
            if self.open.is_empty() {
                break;
            }
            let l = &self.levels[&level];
            if l.meshes
                .iter()
                .zip(settled.iter())
                .all(|(m, s)| m & !s == 0)
            {
                continue;
            }
            let points = self.points.level(level);
            for g in &l.groups {
                let m = g.mesh as usize;
                if settled[m / 64] & (1 << (m % 64)) != 0
                    || eff[m] <= lower_bound(d, g.radius, g.inv_scale)
                {
                    continue;
                }
                let at = g.start as usize;
                #[cfg(test)]
                {
                    self.read += g.len as usize;
                }
                fold_nearest(
                    points[at..at + g.len as usize].iter().flatten(),
                    cameras,
                    eff,
                );
            }
        }
        eff.truncate(meshes);
    }

    /// A pass over every loaded instance: the minima the skipping pass must equal.
    #[cfg(test)]
    fn nearest_effective_all(&self, cameras: &[StreamFocus], meshes: usize) -> Vec<f32> {
        let mut all = vec![f32::INFINITY; meshes];
        fold_nearest(self.points.live(), cameras, &mut all);
        all
    }
}

/// The effective distances of `points`, into `eff`'s minima.
fn fold_nearest<'a>(
    points: impl Iterator<Item = &'a LodPoint>,
    cameras: &[StreamFocus],
    eff: &mut [f32],
) {
    for p in points {
        let d = cameras
            .iter()
            .map(|c| ((c.position - p.center).length() - p.radius).max(0.0))
            .fold(f32::INFINITY, f32::min)
            / p.scale;
        let e = &mut eff[p.mesh.0 as usize];
        *e = e.min(d);
    }
}

#[cfg(test)]
mod tests {
    use rand_xoshiro::rand_core::{RngCore, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    use super::*;

    /// A grid of levels (250 m cells) with random instances of random meshes, some of them
    /// large, scaled, overhanging their cell, or of meshes found in one level only; levels
    /// come and go. The skipping pass gives exactly the minima of a pass over every instance,
    /// for cameras inside, between and far outside the levels, and skips most levels.
    #[test]
    fn skipping_levels_gives_the_minima_of_every_instance() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
        let mut unit = move || (rng.next_u32() >> 8) as f32 / (1u32 << 24) as f32;
        let meshes = 122;
        let mut lod = LodPoints::default();
        let level_points = |level: u32, unit: &mut dyn FnMut() -> f32| {
            let (x, z) = ((level % 16) as f32 * 250.0, (level / 16) as f32 * 250.0);
            (0..40)
                .map(|k| {
                    // Meshes 100.. are each in one level only.
                    let mesh = if k == 0 && level < 20 {
                        100 + level
                    } else {
                        (unit() * 100.0) as u32
                    };
                    LodPoint {
                        mesh: WorldMeshId(mesh),
                        center: Vec3::new(
                            x - 20.0 + unit() * 290.0,
                            unit() * 30.0,
                            z - 20.0 + unit() * 290.0,
                        ),
                        radius: if k == 1 { 80.0 } else { unit() * 10.0 },
                        scale: if k == 2 { 3.0 } else { 0.5 + unit() },
                    }
                })
                .collect::<Vec<_>>()
        };
        for level in 0..256 {
            let pts = level_points(level, &mut unit);
            lod.insert(level, pts.into_iter());
        }
        for level in (0..256).step_by(7) {
            lod.remove(level);
        }
        let pts = level_points(21, &mut unit);
        lod.insert(21, pts.into_iter());
        // Mesh 120: a small instance 300 m from the first camera and a huge one 1.5 km away
        // that is nearer by its radius, after a small one in its level; mesh 121: the same by
        // scale. A bound without the radius or the scale of every instance skips them.
        let point = |mesh, x: f32, radius, scale| LodPoint {
            mesh: WorldMeshId(mesh),
            center: Vec3::new(x, 2.0, 1000.0),
            radius,
            scale,
        };
        lod.insert(
            300,
            [point(120, 1300.0, 1.0, 1.0), point(121, 1300.0, 1.0, 1.0)].into_iter(),
        );
        lod.insert(
            301,
            [
                point(120, 2500.0, 1.0, 1.0),
                point(121, 2601.0, 1.0, 1.0),
                point(120, 2500.0, 1400.0, 1.0),
                point(121, 2601.0, 1.0, 16.0),
            ]
            .into_iter(),
        );
        let cameras = [
            vec![StreamFocus {
                position: Vec3::new(1000.0, 2.0, 1000.0),
            }],
            vec![StreamFocus {
                position: Vec3::new(-3000.0, 10.0, 9000.0),
            }],
            vec![
                StreamFocus {
                    position: Vec3::new(130.0, 0.0, 3900.0),
                },
                StreamFocus {
                    position: Vec3::new(3900.0, 5.0, 130.0),
                },
            ],
        ];
        let mut eff = Vec::new();
        for cams in &cameras {
            lod.nearest_effective(cams, meshes, &mut eff);
            let all = lod.nearest_effective_all(cams, meshes);
            assert_eq!(eff, all);
            assert!(eff[..100].iter().all(|d| d.is_finite()), "{eff:?}");
            for (m, d) in eff.iter().enumerate().take(120).skip(100) {
                // The one-level meshes of removed levels have no instance.
                assert_eq!(d.is_finite(), (m - 100) % 7 != 0, "mesh {m}");
            }
            if cams.len() == 1 && cams[0].position.x == 1000.0 {
                assert!((eff[120] - 100.0).abs() < 1e-3, "{}", eff[120]);
                assert!((eff[121] - 100.0).abs() < 1e-3, "{}", eff[121]);
            }
            // Most instances are never read: the pass stopped before their level or skipped it.
            let total = lod.points.live().count();
            assert!(
                lod.read < total / 4,
                "{} of {total} instances read",
                lod.read
            );
        }
    }
}
