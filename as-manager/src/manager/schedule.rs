//! Build scheduling (`BuildBudget`), skinned refits and compaction. The memory budget they
//! build within (LOD fallback, eviction, OOM back-off) is in `memory.rs`.

use std::sync::Arc;

use super::journal::{CompactUndo, RefitUndo};
use super::state::{EntryKey, EntryState};
use super::AsManager;
use crate::backend::model::CostModel;
use crate::backend::{
    AsBackend, BackendError, BlasBuild, BlasClass, BlasRefit, CostOp, GeometryRef, NextTlas,
};

/// GPU ms of a frame's TLAS (`tlas`) with its builds and compactions (`work`): side by side
/// when they run beside it (`CostModel::beside`: the managed frame), else one after the other.
pub(crate) fn tlas_with_work_ms(costs: &CostModel, beside: bool, tlas: f64, work: f64) -> f64 {
    if beside {
        costs.beside(tlas, work)
    } else {
        tlas + work
    }
}
use crate::mesh::{DeviceVertices, LodGeometry, MeshKind};
use crate::quality::RefitQuality;
use crate::Result;

/// A skinned instance's pose: CPU positions (copied by the backend) or the engine's GPU buffer.
#[derive(Debug, Clone)]
enum PoseSrc {
    Cpu(Arc<Vec<[f32; 3]>>),
    Device(DeviceVertices),
}

/// One admitted build, with what it needs from the mesh (kept alive by `Arc`).
struct Admitted {
    entry: EntryKey,
    geometry: LodGeometry,
    pose: Option<PoseSrc>,
    class: BlasClass,
    opaque: bool,
}

/// A refit: (entry, geometry, pose, rebuild, opaque).
type RefitJob = (EntryKey, LodGeometry, Option<PoseSrc>, bool, bool);

/// The pose of instance `owner`, if it has one.
fn pose_of(tables: &super::state::Tables, owner: Option<u32>) -> Option<PoseSrc> {
    let i = tables.instances.get(owner? as usize)?.as_ref()?;
    match (&i.pose, i.device_pose) {
        (_, Some(d)) => Some(PoseSrc::Device(d)),
        (Some(p), None) => Some(PoseSrc::Cpu(p.clone())),
        (None, None) => None,
    }
}

fn geometry_ref<'a>(
    g: &'a LodGeometry,
    pose: Option<&'a PoseSrc>,
    opaque: bool,
) -> GeometryRef<'a> {
    let data = g.data();
    let device = g.device();
    let vertex_count = g.vertices();
    // A pose whose vertex count differs from the LOD's is ignored (rest pose instead).
    let (positions, device_vertices) = match pose {
        Some(PoseSrc::Cpu(p)) if p.len() as u32 == vertex_count => (Some(p.as_slice()), None),
        Some(PoseSrc::Device(d)) if d.count == vertex_count => (None, Some(*d)),
        _ => (data.map(|d| d.positions()), device.map(|d| d.vertices)),
    };
    GeometryRef {
        vertex_count,
        triangle_count: g.triangles(),
        positions,
        indices: data.map(|d| d.indices()),
        device_vertices,
        device_indices: device.map(|d| d.indices),
        opaque,
    }
}

impl<B: AsBackend> AsManager<B> {
    /// Build priority: lower is sooner. Distance, minus a bonus when in view, minus aging.
    fn priority(&self, key: EntryKey) -> f32 {
        let e = &self.tables.entries[key];
        let b = &self.config.build;
        let dist = if e.dist_frame == self.frame {
            e.min_dist
        } else {
            e.min_dist + self.config.residency.r2
        };
        let bonus = if e.in_view { b.in_view_bonus } else { 0.0 };
        dist - bonus - b.aging_per_frame * self.frame.saturating_sub(e.queued_since) as f32
    }

    /// Sets aside the GPU ms of this frame's TLAS and refits (`gpu_reserved_ms`) and what the
    /// builds may take (`build_room_ms`). The TLAS is estimated from the larger of the
    /// instances visited within r2 and the records (last frame's before this frame's are
    /// assembled: `records_known` false), and the builds are counted after it; once the
    /// managed frame has assembled its records, the builds, which that TLAS does not name, run
    /// beside it ([`CostModel::builds_beside`]) within what the refits and compactions leave.
    pub(crate) fn reserve_gpu(&mut self, records_known: bool) {
        let tlas_op = match self.backend.next_tlas() {
            NextTlas::Update => CostOp::TlasUpdate,
            NextTlas::BuildEveryFrame | NextTlas::Rebuild => CostOp::Tlas,
        };
        // The instances visited within r2 may all show once built (a frame's builds make the
        // next frames' TLAS larger): the TLAS is counted at the larger size.
        let visited = self.costs.estimate_batch(tlas_op, self.visits.len() as u64);
        let known = if records_known {
            self.records.len() as u64
        } else {
            u64::from(self.prev_tlas_instances)
        };
        let tlas = visited.max(self.costs.estimate_batch(tlas_op, known));
        // This frame's refits when they are scheduled already (the managed frame), else last
        // frame's.
        let refit_prims = if self.stats.refit_primitives > 0 {
            self.stats.refit_primitives
        } else {
            self.prev_refit_prims
        };
        let refits = if refit_prims > 0 {
            self.costs.estimate_batch(CostOp::Refit, refit_prims)
        } else {
            0.0
        };
        self.gpu_reserved_ms = tlas + refits;
        self.reserved_tlas_ms = tlas;
        let max = f64::from(self.config.build.max_gpu_ms);
        self.builds_beside = records_known;
        self.build_room_ms = if records_known {
            self.costs.builds_beside(tlas, max - refits)
        } else {
            (max - self.gpu_reserved_ms).max(0.0)
        };
    }

    /// Builds queued entries within the per-frame budget (`budgeted`), memory permitting.
    pub(crate) fn schedule_builds(&mut self, budgeted: bool) -> Result<()> {
        // (proxy, priority, entry), and the bytes of the built proxies, in one pass over the
        // entries (whether an entry is a proxy is its own flag: no mesh is read).
        let count_proxies = budgeted && self.config.far_field.enabled;
        let mut proxy_bytes: u64 = 0;
        let mut queue: Vec<(bool, f32, EntryKey)> = Vec::new();
        for &s in &self.tables.active {
            let e = &self.tables.entries[s];
            match e.state {
                EntryState::Queued => queue.push((e.proxy, self.priority(s), s)),
                EntryState::Built if count_proxies && e.proxy => proxy_bytes += e.bytes,
                _ => {}
            }
        }
        // Far-field proxies first, within their share of the budget; then near detail.
        queue.sort_by(|a, b| {
            b.0.cmp(&a.0)
                .then(a.1.total_cmp(&b.1))
                // Ties by key: slotmap orders keys by slot, the order the hand-written slot
                // table broke ties in (any fixed order would do: runs must be deterministic).
                .then(a.2.cmp(&b.2))
        });
        let proxy_ms_max = f64::from(self.config.far_field.build_share.clamp(0.0, 1.0));
        let mut proxy_ms = 0.0f64;
        let mut detail_admitted = 0usize;
        let b = self.config.build.clone();
        // Builds leave the compaction headroom free.
        let build_budget =
            (self.budget() as f64 * (1.0 - self.config.memory.compaction_headroom as f64)) as u64;
        let (mut prims, mut ms, mut bytes) = (0u64, 0f64, 0u64);
        // The GPU budget covers all acceleration-structure work: builds get what the TLAS,
        // the refits and the compactions leave (`reserve_gpu`). A backend that updates its
        // TLAS in place says whether this frame's is an update or a build; a build after
        // updates takes no build that the budget does not hold (the frames after it update,
        // so nothing starves), which keeps the rebuild and the builds apart.
        let progress = self.backend.next_tlas() != NextTlas::Rebuild;
        // The builds are one batch: its fixed cost is the static one once any static build
        // is in it, else the skinned one (counted as the first item of each class goes).
        let mut batch_fixed = 0.0f64;
        let build_ms = self.build_room_ms;
        let mut admitted: Vec<Admitted> = Vec::new();
        let mut sizes = Vec::new();
        for &(proxy, prio, key) in &queue {
            if budgeted && admitted.len() >= b.max_builds as usize {
                // The host's share: each build costs the driver's recording and the backend's
                // planning. Past the cap only the first proxy and the first near item of the
                // frame still go (progress); proxies come first in the queue, so past the
                // first near item nothing else can.
                let first = progress
                    && if proxy {
                        proxy_ms == 0.0
                    } else {
                        detail_admitted == 0
                    };
                if !first {
                    if proxy {
                        continue;
                    }
                    break;
                }
            }
            let (mesh_ix, lod, owner, tris) = {
                let e = &self.tables.entries[key];
                (e.mesh, e.lod as usize, e.owner, e.triangles)
            };
            let mesh = self.tables.meshes[mesh_ix as usize]
                .as_ref()
                .expect("live mesh");
            let kind = mesh.kind();
            let class = if kind == MeshKind::Skinned {
                BlasClass::Skinned
            } else {
                BlasClass::Static
            };
            let geometry = mesh.desc.lods[lod].geometry.clone();
            if !geometry.is_buildable() && self.backend.needs_geometry() {
                // Its data was evicted since it was queued: wait for it (or another LOD).
                self.tables.entries[key].state = EntryState::Idle;
                continue;
            }
            let opaque = mesh.desc.opaque;
            let nlods = mesh.nlods as usize;
            let pose = pose_of(&self.tables, owner);
            let op = if class == BlasClass::Skinned {
                CostOp::BuildSkinned
            } else {
                CostOp::BuildStatic
            };
            let fixed_more = (self.costs.batch_fixed(op) - batch_fixed).max(0.0);
            let est = self.costs.estimate(op, tris as u64) + fixed_more;
            let size = self
                .backend
                .blas_sizes(&geometry_ref(&geometry, pose.as_ref(), opaque), class);
            let oversized = !proxy && (tris as u64 > b.max_primitives || est > b.max_gpu_ms as f64);
            if budgeted && proxy {
                // Proxies: their share of what the build budget leaves past the batch's fixed
                // cost (which the batch pays once, whoever is in it); the first one of a frame
                // always goes, so the far field builds even when the TLAS and refits take it
                // all.
                let units_ms = est - fixed_more;
                let room = (build_ms - batch_fixed.max(self.costs.batch_fixed(op))).max(0.0);
                if (proxy_ms > 0.0 || !progress) && proxy_ms + units_ms > proxy_ms_max * room {
                    continue;
                }
                if !progress && ms + est > build_ms {
                    continue;
                }
            } else if budgeted {
                if oversized && (detail_admitted > 0 || !progress) {
                    continue;
                }
                // The first detail item always goes (progress even when the TLAS and refits
                // take the whole budget); later ones only within what is left.
                if (detail_admitted > 0 || !progress)
                    && (prims + tris as u64 > b.max_primitives || ms + est > build_ms)
                {
                    continue;
                }
            }
            if budgeted {
                // A proxy only takes memory that is free, and only while the proxies in use
                // stay within their share of the budget: it never evicts, so near detail keeps
                // the memory it needs (and evicts proxies last when it must).
                let share = f64::from(self.config.far_field.memory_share.clamp(0.0, 1.0));
                if proxy
                    && (self.memory_in_use() + bytes + size.as_bytes > build_budget
                        || (proxy_bytes + size.as_bytes) as f64 > share * build_budget as f64)
                {
                    continue;
                }
                if self.memory_in_use() + bytes + size.as_bytes > build_budget {
                    // Coarser LOD first, then evict what matters less.
                    if kind == MeshKind::Static && lod + 1 < nlods {
                        let m = self.tables.meshes[mesh_ix as usize].as_mut().expect("live");
                        if (m.lod_floor as usize) <= lod {
                            m.lod_floor = lod as u8 + 1;
                            m.floor_since = self.frame;
                            self.landmarks.mesh_changed(mesh_ix);
                            if !self.floors.contains(&mesh_ix) {
                                self.floors.push(mesh_ix);
                            }
                            self.stats.lod_fallbacks += 1;
                        }
                        self.tables.entries[key].state = EntryState::Idle;
                        continue;
                    }
                    let dist = self.tables.entries[key].min_dist;
                    if !self.make_room(bytes + size.as_bytes, Some(dist), build_budget, false) {
                        self.stats.memory_refused += 1;
                        continue;
                    }
                }
                let _ = prio;
                if proxy {
                    proxy_ms += est - fixed_more;
                    proxy_bytes += size.as_bytes;
                } else {
                    detail_admitted += 1;
                }
                self.stats.oversized_admitted |= oversized;
            }
            prims += tris as u64;
            ms += est;
            batch_fixed += fixed_more;
            bytes += size.as_bytes;
            admitted.push(Admitted {
                entry: key,
                geometry,
                pose,
                class,
                opaque,
            });
            sizes.push(size);
            if budgeted && oversized {
                break;
            }
        }
        self.stats.queued = (queue.len() - admitted.len()) as u32;
        if admitted.is_empty() {
            return Ok(());
        }
        let builds: Vec<BlasBuild<'_>> = admitted
            .iter()
            .zip(&sizes)
            .map(|(a, s)| BlasBuild {
                geometry: geometry_ref(&a.geometry, a.pose.as_ref(), a.opaque),
                class: a.class,
                sizes: *s,
            })
            .collect();
        match self.backend.build_blases(&builds) {
            Ok(handles) => {
                drop(builds);
                for ((a, s), handle) in admitted.iter().zip(&sizes).zip(handles) {
                    let frame = self.frame;
                    let pose_version = if a.class == BlasClass::Skinned {
                        let owner = self.tables.entries[a.entry].owner.expect("skinned: owned");
                        self.tables.instances[owner as usize]
                            .as_ref()
                            .map_or(0, |i| i.pose_version)
                    } else {
                        0
                    };
                    // CPU quality needs CPU positions; a BLAS built from the GPU is measured
                    // on the GPU (`take_refit_quality`).
                    let quality = match (a.class, a.geometry.data()) {
                        (BlasClass::Skinned, Some(d)) => {
                            let g = geometry_ref(&a.geometry, a.pose.as_ref(), a.opaque);
                            g.positions.map(|p| RefitQuality::at_build(p, d.indices()))
                        }
                        _ => None,
                    };
                    let e = &mut self.tables.entries[a.entry];
                    e.state = EntryState::Built;
                    e.handle = Some(handle);
                    e.address = self.backend.blas_address(handle);
                    e.bytes = s.as_bytes;
                    e.sizes = *s;
                    e.created = frame;
                    e.refit.refit_frame = frame;
                    e.refit.pose_version = pose_version;
                    e.refit.quality = quality;
                    e.refit.last_ratio = 1.0;
                    e.refit.gpu_ratio = None;
                    e.needs_compaction = a.class == BlasClass::Static;
                    if e.needs_compaction {
                        self.compact_pending.push(a.entry);
                    }
                    self.live_bytes += s.as_bytes;
                    self.built_count += 1;
                    self.journal.built.push((a.entry, handle));
                    // Beside the TLAS, the BLAS shows from the next frame on: its mesh's
                    // landmarks choose again then (they chose this frame already).
                    let shows_from = frame.saturating_add(u64::from(self.builds_beside));
                    self.tables.blas_changed(a.entry, shows_from);
                    tracing::trace!(entry = ?a.entry, bytes = s.as_bytes, "blas built");
                }
                self.stats.builds = admitted.len() as u32;
                self.stats.build_primitives = prims;
                self.stats.build_estimated_ms = ms as f32;
                Ok(())
            }
            Err(BackendError::OutOfDeviceMemory) => {
                let failed: u64 = sizes.iter().map(|s| s.as_bytes).sum();
                self.on_oom(failed);
                Ok(())
            }
            Err(e) => Err(e.into()),
        }
    }

    /// Refits dirty skinned BLASes oldest first within the refit budget; rebuilds those whose
    /// measured quality ratio exceeds the bound.
    pub(crate) fn schedule_refits(&mut self, budgeted: bool) -> Result<()> {
        self.take_gpu_quality();
        let mut dirty: Vec<(u64, EntryKey)> = Vec::new();
        for &s in &self.tables.active {
            let e = &self.tables.entries[s];
            let Some(owner) = e.owner else { continue };
            if e.state != EntryState::Built {
                continue;
            }
            if let Some(inst) = self.tables.instances[owner as usize].as_ref() {
                if inst.pose_version > e.refit.pose_version {
                    dirty.push((e.refit.refit_frame, s));
                }
            }
        }
        if dirty.is_empty() {
            return Ok(());
        }
        dirty.sort_unstable();
        let bound = self.config.build.rebuild_quality_bound;
        let max = self.config.build.max_refit_primitives;
        let mut prims = 0u64;
        let mut jobs: Vec<RefitJob> = Vec::new();
        for &(_, s) in &dirty {
            let e = &self.tables.entries[s];
            let tris = e.triangles as u64;
            if budgeted && !jobs.is_empty() && prims + tris > max {
                continue;
            }
            let mesh = self.tables.meshes[e.mesh as usize]
                .as_ref()
                .expect("live mesh");
            let geometry = mesh.desc.lods[e.lod as usize].geometry.clone();
            if !geometry.is_buildable() && self.backend.needs_geometry() {
                continue; // LOD data evicted: keep the last refit until it is back or released
            }
            let pose = pose_of(&self.tables, e.owner);
            let mut rebuild = false;
            let mut ratio = e.refit.last_ratio;
            match (&e.refit.quality, &pose, geometry.data()) {
                (Some(q), Some(PoseSrc::Cpu(p)), Some(d)) if p.len() == d.positions().len() => {
                    ratio = q.ratio(p, d.indices());
                    rebuild = ratio > bound;
                }
                // Posed on the GPU: the backend's latest measurement (frames late).
                (_, Some(PoseSrc::Device(_)), _) => {
                    if let Some(r) = e.refit.gpu_ratio {
                        ratio = r;
                        rebuild = r > bound;
                    }
                }
                _ => {}
            }
            prims += tris;
            let e = &mut self.tables.entries[s];
            self.journal.refitted.push(RefitUndo {
                entry: s,
                before: e.refit.clone(),
            });
            e.refit.last_ratio = if rebuild { 1.0 } else { ratio };
            if rebuild {
                e.refit.gpu_ratio = None;
            }
            self.stats.worst_refit_quality = self.stats.worst_refit_quality.max(e.refit.last_ratio);
            jobs.push((s, geometry, pose, rebuild, mesh.desc.opaque));
            if budgeted && prims >= max {
                break;
            }
        }
        let refits: Vec<BlasRefit<'_>> = jobs
            .iter()
            .map(|(s, g, p, rebuild, opaque)| BlasRefit {
                blas: self.tables.entries[*s].handle.expect("built"),
                geometry: geometry_ref(g, p.as_ref(), *opaque),
                rebuild: *rebuild,
            })
            .collect();
        match self.backend.refit_blases(&refits) {
            Ok(()) => {}
            Err(BackendError::OutOfDeviceMemory) => {
                self.on_oom(0);
                return Ok(());
            }
            Err(e) => return Err(e.into()),
        }
        drop(refits);
        let frame = self.frame;
        for (s, g, p, rebuild, _) in jobs {
            let owner = self.tables.entries[s].owner.expect("refitted: owned");
            let version = self.tables.instances[owner as usize]
                .as_ref()
                .map_or(0, |i| i.pose_version);
            let e = &mut self.tables.entries[s];
            e.refit.pose_version = version;
            e.refit.refit_frame = frame;
            if rebuild {
                self.stats.rebuilds += 1;
                if let (Some(PoseSrc::Cpu(p)), Some(d)) = (&p, g.data()) {
                    e.refit.quality = Some(RefitQuality::at_build(p, d.indices()));
                }
            } else {
                self.stats.refits += 1;
            }
            self.stats.refit_primitives += e.triangles as u64;
        }
        Ok(())
    }

    /// Takes the backend's GPU refit-quality measurements (skinned BLASes posed on the GPU) and
    /// keeps each BLAS's latest; `schedule_refits` rebuilds on it. Late by the frames in flight,
    /// like compacted sizes.
    fn take_gpu_quality(&mut self) {
        let reports = self.backend.take_refit_quality();
        if reports.is_empty() {
            return;
        }
        // One pass over the built skinned entries, not one per report.
        let by_handle: rustc_hash::FxHashMap<_, EntryKey> = self
            .tables
            .active
            .iter()
            .filter_map(|&s| {
                let e = &self.tables.entries[s];
                let skinned = e.owner.is_some() && e.state == EntryState::Built;
                skinned.then_some((e.handle?, s))
            })
            .collect();
        for (h, ratio) in reports {
            if let Some(&s) = by_handle.get(&h) {
                let e = &mut self.tables.entries[s];
                e.refit.gpu_ratio = Some(ratio);
                self.stats.worst_refit_quality = self.stats.worst_refit_quality.max(ratio);
            }
        }
    }

    /// Compacts built static BLASes whose compacted size is known, within the per-frame
    /// compaction budget and the memory budget (the copy coexists with the original until
    /// the original retires).
    pub(crate) fn schedule_compactions(&mut self) -> Result<()> {
        if self.compact_pending.is_empty() {
            return Ok(());
        }
        let b = &self.config.build;
        // Compaction takes what the GPU budget has left after builds, refits and the TLAS.
        // Beside the TLAS, the compactions join the builds there (the backend records them
        // together, docs/GPU.md): what they add is what they make the pair longer by.
        let builds = self.stats.build_estimated_ms as f64;
        let refits = self.gpu_reserved_ms - self.reserved_tlas_ms;
        let (beside, tlas) = (self.builds_beside, self.reserved_tlas_ms);
        let tlas_and_builds = tlas_with_work_ms(&self.costs, beside, tlas, builds);
        let left = b.max_gpu_ms as f64 - refits - tlas_and_builds;
        let extra = |costs: &CostModel, ms: f64| {
            tlas_with_work_ms(costs, beside, tlas, builds + ms) - tlas_and_builds
        };
        let (max_n, max_ms) = (b.max_compactions, b.max_compaction_ms as f64);
        let mut pending = std::mem::take(&mut self.compact_pending);
        let mut failure: Option<BackendError> = None;
        let mut done = 0u32;
        let mut ms = 0.0;
        pending.retain(|&key| {
            if failure.is_some() {
                return true;
            }
            if !self.tables.built(Some(key)) {
                return false;
            }
            let e = &self.tables.entries[key];
            // Listed twice (a rolled-back frame's builds are listed again when built again),
            // or compacted already: its handle is a copy, maybe made earlier in this loop.
            if !e.needs_compaction {
                return false;
            }
            let handle = e.handle.expect("built");
            let Some(size) = self.backend.compacted_size(handle) else {
                return true;
            };
            let keep = 1.0 - f64::from(self.config.build.min_compaction_saving);
            if size > 0 && size as f64 > e.bytes as f64 * keep {
                self.tables.entries[key].needs_compaction = false;
                return false; // nothing worth saving (e.g. lavapipe)
            }
            // Each compaction is a command of its own.
            let est = self.costs.estimate_batch(CostOp::Compact, e.bytes);
            let over = ms + est > max_ms || extra(&self.costs, ms + est) > left;
            if done >= max_n || max_ms.min(left) <= 0.0 || (done > 0 && over) {
                return true;
            }
            if self.memory_in_use() + size > self.budget() {
                return true;
            }
            match self.backend.compact_blas(handle) {
                Ok(new) => {
                    let frame = self.frame;
                    let e = &mut self.tables.entries[key];
                    // The source is freed when the frame commits (a failed frame keeps it).
                    self.journal.compacted.push(CompactUndo {
                        entry: key,
                        old: handle,
                        old_bytes: e.bytes,
                        new,
                    });
                    self.retiring.push_back((frame, e.bytes));
                    self.retiring_bytes += e.bytes;
                    self.live_bytes = self.live_bytes - e.bytes + size;
                    e.bytes = size;
                    e.handle = Some(new);
                    e.address = self.backend.blas_address(new);
                    e.needs_compaction = false;
                    // Beside the TLAS the copy shows from the next frame (see the builds).
                    self.tables
                        .blas_changed(key, frame.saturating_add(u64::from(self.builds_beside)));
                    done += 1;
                    ms += est;
                    false
                }
                Err(BackendError::OutOfDeviceMemory) => true,
                Err(e) => {
                    failure.get_or_insert(e);
                    true
                }
            }
        });
        if let Some(e) = failure {
            self.compact_pending = pending;
            return Err(e.into());
        }
        self.stats.compactions = done;
        self.compaction_estimated_ms = ms;
        self.compact_pending = pending;
        Ok(())
    }
}
