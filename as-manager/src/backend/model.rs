//! A backend without a GPU: sizes and costs from a fitted model, frames in flight simulated.
//!
//! The coefficients are plain structs ([`SizeModel`], [`CostModel`]) so each driver gets its
//! own preset. `lavapipe()` holds what the lead measured on Mesa lavapipe (2 cores, 2026-11);
//! `nvidia()` is fitted to the H200 runs in docs/GPU.md, `lavapipe()` to lavapipe's reports.
//!
//! ```
//! use rtstream_as_manager::backend::{AsBackend, BlasClass, GeometryRef};
//! use rtstream_as_manager::backend::model::ModelBackend;
//! let b = ModelBackend::lavapipe();
//! let g = GeometryRef { vertex_count: 600, triangle_count: 1000, positions: None, indices: None,
//!     device_vertices: None, device_indices: None, opaque: true };
//! let s = b.blas_sizes(&g, BlasClass::Static);
//! assert!(s.as_bytes >= 100_000);
//! ```

use std::collections::VecDeque;

use rustc_hash::FxHashMap;

pub use super::calibration::{BatchCosts, CostFits, CostModel, OpFit, SizeModel, SizeSample};
use super::{
    AsBackend, BackendError, BackendResult, BlasBuild, BlasClass, BlasHandle, BlasRefit, BlasSizes,
    CostOp, FaultPoint, FrameOrder, GeometryRef, Measurement, Misuse, NextTlas, TlasDelta,
    TlasHandle,
};
use crate::record::TlasInstance;

#[derive(Debug, Clone)]
struct ModelBlas {
    bytes: u64,
    class: BlasClass,
    triangles: u32,
    built_frame: u64,
    /// Last frame whose TLAS referenced it.
    last_tlas: Option<u64>,
}

/// Counters the model backend keeps (for tests and examples).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ModelCounters {
    /// Lifetime violations the model saw: a TLAS record of a BLAS that is not live, a free
    /// whose `last_used_frame` is older than a TLAS that used the BLAS, or a BLAS destroyed
    /// before every frame that used it completed. Always 0 for a correct manager.
    pub lifetime_violations: u64,
    /// BLAS builds recorded.
    pub builds: u64,
    /// Refits recorded.
    pub refits: u64,
    /// Rebuilds in place recorded.
    pub rebuilds: u64,
    /// Compactions recorded.
    pub compactions: u64,
    /// BLASes destroyed (retired after their last frame completed).
    pub destroyed: u64,
    /// `build_blases` calls.
    pub build_calls: u64,
    /// Peak of live + retiring BLAS bytes.
    pub peak_bytes: u64,
    /// Simulated OOM failures returned.
    pub oom_failures: u64,
    /// TLASes recorded beside the frame's builds (no record named one of them).
    pub builds_beside_tlas: u64,
    /// Compactions recorded beside the frame's TLAS (with its builds).
    pub compactions_beside_tlas: u64,
}

/// The GPU-less backend.
#[derive(Debug)]
pub struct ModelBackend {
    /// Sizes it reports.
    pub sizes: SizeModel,
    /// Costs it "measures".
    pub costs: CostModel,
    /// Frames in flight: frame `n` completes when frame `n + frames_in_flight` begins.
    pub frames_in_flight: u64,
    /// Simulated device memory for BLASes: allocations beyond it fail with OOM.
    pub device_bytes: Option<u64>,
    /// Report lost device on the next call.
    pub lose_device: bool,
    /// Faults armed by [`ModelBackend::inject_fault`], each striking once.
    pub faults: Vec<(FaultPoint, BackendError)>,
    /// Behave like a real GPU about data: [`AsBackend::needs_geometry`] returns this, and a
    /// build of counts-only geometry fails with [`BackendError::MissingGeometry`] (default
    /// `false`: counts are enough for a model).
    pub require_geometry: bool,
    /// Model TLAS updates in place as the Vulkan backend makes them (`TlasUpdates`): after a
    /// build, at most this many updates, the next build due from half of them on in a frame
    /// whose BLAS builds total at most `light_frame_triangles`. 0 (the default): every frame
    /// builds its TLAS.
    pub tlas_max_updates: u32,
    /// See `tlas_max_updates` (default: any frame, as the Vulkan backend's).
    pub light_frame_triangles: u64,
    /// Updates since the last TLAS build (`None`: no TLAS yet).
    tlas_updates_since: Option<u32>,
    /// BLAS triangles built this frame.
    frame_build_triangles: u64,
    /// GPU ms of the current frame's builds (the TLAS may run beside them), and where their
    /// measurements are.
    frame_build_ms: f64,
    frame_build_measurements: Vec<usize>,
    blases: FxHashMap<BlasHandle, ModelBlas>,
    retiring: VecDeque<(u64, BlasHandle)>,
    next_handle: u64,
    frame: u64,
    completed: Option<u64>,
    live_bytes: u64,
    retiring_bytes: u64,
    measurements: Vec<Measurement>,
    counters: ModelCounters,
    tlas_instances: usize,
    /// This frame's TLAS marks (BLAS, its previous mark), undone by `abort_frame`.
    tlas_marks: Vec<(BlasHandle, Option<u64>)>,
    /// The last `build_tlas` call's records, and how many of them name each BLAS: kept up to
    /// date through the calls' `TlasDelta`, so a frame costs what changed.
    records: Vec<TlasInstance>,
    refs: RecordRefs,
    /// The frame order the calls follow (what `Misuse` refuses), as the Vulkan backend's.
    order: FrameOrder,
}

/// How many records name each BLAS (handles are dense: a count per handle), the handles named
/// at all, and the records naming no handle ever made.
#[derive(Debug, Default)]
struct RecordRefs {
    counts: Vec<u32>,
    /// Position of each named handle in `named` (`u32::MAX`: not named).
    pos: Vec<u32>,
    named: Vec<u64>,
    unknown: u64,
}

impl RecordRefs {
    fn add(&mut self, address: u64, made: u64) {
        let h = address >> 8;
        if address & 0xff != 0 || h >= made {
            self.unknown += 1;
            return;
        }
        let h = h as usize;
        if self.counts.len() <= h {
            self.counts.resize(h + 1, 0);
            self.pos.resize(h + 1, u32::MAX);
        }
        if self.counts[h] == 0 {
            self.pos[h] = self.named.len() as u32;
            self.named.push(h as u64);
        }
        self.counts[h] += 1;
    }

    fn remove(&mut self, address: u64, made: u64) {
        let h = address >> 8;
        if address & 0xff != 0 || h >= made {
            self.unknown -= 1;
            return;
        }
        let h = h as usize;
        self.counts[h] -= 1;
        if self.counts[h] == 0 {
            let at = self.pos[h] as usize;
            self.named.swap_remove(at);
            if let Some(&moved) = self.named.get(at) {
                self.pos[moved as usize] = at as u32;
            }
            self.pos[h] = u32::MAX;
        }
    }
}

impl ModelBackend {
    /// The model's timings of a frame's batches, (op, units, items) each; empty ones skipped.
    /// Returns their GPU ms.
    fn measure_batches<const N: usize>(&mut self, batches: [(CostOp, u64, u32); N]) -> f64 {
        let mut total = 0.0;
        for (op, units, items) in batches {
            if units > 0 {
                let gpu_ms = self.costs.estimate_batch(op, units);
                total += gpu_ms;
                self.measurements.push(Measurement {
                    op,
                    units,
                    items,
                    gpu_ms,
                    beside: false,
                });
            }
        }
        total
    }

    /// A backend with the given models and 2 frames in flight.
    pub fn new(sizes: SizeModel, costs: CostModel) -> Self {
        Self {
            sizes,
            costs,
            frames_in_flight: 2,
            device_bytes: None,
            lose_device: false,
            faults: Vec::new(),
            require_geometry: false,
            tlas_max_updates: 0,
            light_frame_triangles: u64::MAX,
            tlas_updates_since: None,
            frame_build_triangles: 0,
            frame_build_ms: 0.0,
            frame_build_measurements: Vec::new(),
            blases: FxHashMap::default(),
            retiring: VecDeque::new(),
            next_handle: 1,
            frame: 0,
            completed: None,
            live_bytes: 0,
            retiring_bytes: 0,
            measurements: Vec::new(),
            counters: ModelCounters::default(),
            tlas_instances: 0,
            tlas_marks: Vec::new(),
            records: Vec::new(),
            refs: RecordRefs::default(),
            order: FrameOrder::default(),
        }
    }

    /// Brings `records` and `record_refs` to `instances`, writing what `delta` does not
    /// promise unchanged (in debug builds, checks the promise).
    fn track_records(&mut self, instances: &[TlasInstance], delta: TlasDelta<'_>) {
        let stable = delta.stable.min(instances.len()).min(self.records.len());
        #[cfg(debug_assertions)]
        {
            let mut listed = vec![false; stable];
            for &i in delta.changed {
                if let Some(l) = listed.get_mut(i as usize) {
                    *l = true;
                }
            }
            for (i, listed) in listed.iter().enumerate() {
                assert!(
                    *listed || self.records[i] == instances[i],
                    "TlasDelta: record {i} changed but is not listed"
                );
            }
        }
        // New uses first, then the old ones go: a BLAS named before and after keeps its count
        // above zero.
        let made = self.next_handle;
        let refs = &mut self.refs;
        for &i in delta.changed {
            let i = i as usize;
            if i < stable {
                refs.add(instances[i].blas_address, made);
                refs.remove(self.records[i].blas_address, made);
                self.records[i] = instances[i];
            }
        }
        for r in &instances[stable..] {
            refs.add(r.blas_address, made);
        }
        for r in &self.records[stable..] {
            refs.remove(r.blas_address, made);
        }
        self.records.truncate(stable);
        self.records.extend_from_slice(&instances[stable..]);
    }

    /// Lavapipe presets.
    pub fn lavapipe() -> Self {
        Self::new(SizeModel::lavapipe(), CostModel::lavapipe())
    }

    /// NVIDIA (H200, driver 580) presets, fitted to docs/GPU.md.
    pub fn nvidia() -> Self {
        Self::new(SizeModel::nvidia(), CostModel::nvidia())
    }

    /// Counters so far.
    pub fn counters(&self) -> &ModelCounters {
        &self.counters
    }

    /// BLASes alive (not yet destroyed), including retiring ones.
    pub fn live_blas_count(&self) -> usize {
        self.blases.len()
    }

    /// Bytes of BLASes not yet destroyed.
    pub fn allocated_bytes(&self) -> u64 {
        self.live_bytes + self.retiring_bytes
    }

    /// Whether a handle is alive (built and not destroyed).
    pub fn is_live(&self, h: BlasHandle) -> bool {
        self.blases.contains_key(&h)
    }

    /// Whether a device address from [`AsBackend::blas_address`] names a live BLAS.
    pub fn is_live_address(&self, address: u64) -> bool {
        address & 0xff == 0 && self.blases.contains_key(&BlasHandle(address >> 8))
    }

    /// Instances in the last TLAS.
    pub fn tlas_instances(&self) -> usize {
        self.tlas_instances
    }

    /// Arms a fault: the next call at `at` fails with `error` (`DeviceLost` stays, as a
    /// real loss would).
    pub fn inject_fault(&mut self, at: FaultPoint, error: BackendError) {
        self.faults.push((at, error));
    }

    fn lost(&self) -> BackendResult<()> {
        if self.lose_device {
            Err(BackendError::DeviceLost)
        } else {
            Ok(())
        }
    }

    /// `lost`, then an armed fault at `at`.
    fn check(&mut self, at: FaultPoint) -> BackendResult<()> {
        self.lost()?;
        if let Some(i) = self.faults.iter().position(|(p, _)| *p == at) {
            let (_, e) = self.faults.remove(i);
            self.lose_device |= e == BackendError::DeviceLost;
            return Err(e);
        }
        Ok(())
    }

    fn fits(&self, extra: u64) -> bool {
        self.device_bytes
            .is_none_or(|cap| self.allocated_bytes() + extra <= cap)
    }

    fn alloc(&mut self, b: ModelBlas) -> BlasHandle {
        let h = BlasHandle(self.next_handle);
        self.next_handle += 1;
        self.live_bytes += b.bytes;
        self.blases.insert(h, b);
        self.counters.peak_bytes = self.counters.peak_bytes.max(self.allocated_bytes());
        h
    }
}

impl AsBackend for ModelBackend {
    fn begin_frame(&mut self, frame: u64) -> BackendResult<()> {
        self.lost()?;
        self.order.may_begin(frame)?;
        self.order.begun(frame);
        self.frame = frame;
        self.frame_build_triangles = 0;
        self.frame_build_ms = 0.0;
        self.frame_build_measurements.clear();
        self.tlas_marks.clear();
        if frame >= self.frames_in_flight {
            let done = frame - self.frames_in_flight;
            self.completed = Some(self.completed.map_or(done, |c| c.max(done)));
        }
        while let Some(&(last, h)) = self.retiring.front() {
            if self.completed.is_some_and(|c| c >= last) {
                self.retiring.pop_front();
                if let Some(b) = self.blases.remove(&h) {
                    self.retiring_bytes -= b.bytes;
                    self.counters.destroyed += 1;
                    if b.last_tlas
                        .is_some_and(|t| self.completed.is_none_or(|c| c < t))
                    {
                        self.counters.lifetime_violations += 1;
                    }
                }
            } else {
                break;
            }
        }
        Ok(())
    }

    fn completed_frame(&self) -> Option<u64> {
        self.completed
    }

    fn blas_sizes(&self, g: &GeometryRef<'_>, class: BlasClass) -> BlasSizes {
        self.sizes
            .blas_sizes(g.vertex_count, g.triangle_count, class)
    }

    fn needs_geometry(&self) -> bool {
        self.require_geometry
    }

    fn build_blases(&mut self, builds: &[BlasBuild<'_>]) -> BackendResult<Vec<BlasHandle>> {
        self.order.recording()?;
        self.check(FaultPoint::BuildBlases)?;
        // Indices as CPU slices or in the engine's GPU buffer (`LodGeometry::Device`).
        let missing =
            |b: &BlasBuild<'_>| b.geometry.indices.is_none() && b.geometry.device_indices.is_none();
        if self.require_geometry && builds.iter().any(missing) {
            return Err(BackendError::MissingGeometry);
        }
        let total: u64 = builds.iter().map(|b| b.sizes.as_bytes).sum();
        if !self.fits(total) {
            self.counters.oom_failures += 1;
            return Err(BackendError::OutOfDeviceMemory);
        }
        self.counters.build_calls += 1;
        let mut out = Vec::with_capacity(builds.len());
        let (mut st, mut sk) = (0u64, 0u64);
        let (mut n_st, mut n_sk) = (0u32, 0u32);
        for b in builds {
            let t = b.geometry.triangle_count;
            match b.class {
                BlasClass::Static => {
                    st += t as u64;
                    n_st += 1;
                }
                BlasClass::Skinned => {
                    sk += t as u64;
                    n_sk += 1;
                }
            }
            let frame = self.frame;
            out.push(self.alloc(ModelBlas {
                bytes: b.sizes.as_bytes,
                class: b.class,
                triangles: t,
                built_frame: frame,
                last_tlas: None,
            }));
            self.counters.builds += 1;
        }
        self.frame_build_triangles += st + sk;
        let before = self.measurements.len();
        self.frame_build_ms += self.measure_batches([
            (CostOp::BuildStatic, st, n_st),
            (CostOp::BuildSkinned, sk, n_sk),
        ]);
        self.frame_build_measurements
            .extend(before..self.measurements.len());
        Ok(out)
    }

    fn refit_blases(&mut self, refits: &[BlasRefit<'_>]) -> BackendResult<()> {
        if !refits.is_empty() {
            self.order.may_refit()?;
        }
        for (i, r) in refits.iter().enumerate() {
            if refits[..i].iter().any(|q| q.blas == r.blas) {
                return Err(Misuse::DuplicateRefit(r.blas).into());
            }
        }
        self.check(FaultPoint::RefitBlases)?;
        let (mut rf, mut rb) = (0u64, 0u64);
        let (mut n_rf, mut n_rb) = (0u32, 0u32);
        for r in refits {
            let b = self
                .blases
                .get(&r.blas)
                .ok_or(Misuse::UnknownBlas(r.blas))?;
            debug_assert_eq!(b.class, BlasClass::Skinned);
            if r.rebuild {
                rb += b.triangles as u64;
                n_rb += 1;
                self.counters.rebuilds += 1;
            } else {
                rf += b.triangles as u64;
                n_rf += 1;
                self.counters.refits += 1;
            }
        }
        let _ = self.measure_batches([(CostOp::Refit, rf, n_rf), (CostOp::BuildSkinned, rb, n_rb)]);
        Ok(())
    }

    fn compacted_size(&mut self, blas: BlasHandle) -> Option<u64> {
        let b = self.blases.get(&blas)?;
        if b.class != BlasClass::Static || self.completed.is_none_or(|c| c < b.built_frame) {
            return None;
        }
        Some(
            self.sizes
                .round(b.bytes as f64 * self.sizes.compaction_ratio)
                .min(b.bytes),
        )
    }

    fn compact_blas(&mut self, blas: BlasHandle) -> BackendResult<BlasHandle> {
        self.order.recording()?;
        self.check(FaultPoint::CompactBlas)?;
        let size = self
            .compacted_size(blas)
            .ok_or(Misuse::CompactedSizeUnknown(blas))?;
        if !self.fits(size) {
            self.counters.oom_failures += 1;
            return Err(BackendError::OutOfDeviceMemory);
        }
        let src = self.blases[&blas].clone();
        let frame = self.frame;
        let h = self.alloc(ModelBlas {
            bytes: size,
            built_frame: frame,
            last_tlas: None,
            ..src
        });
        self.counters.compactions += 1;
        let gpu_ms = self.costs.estimate_batch(CostOp::Compact, src.bytes);
        // As the Vulkan backend records them: with the frame's builds, beside the TLAS when
        // no record names the copy (`build_tlas`).
        self.frame_build_ms += gpu_ms;
        self.frame_build_measurements.push(self.measurements.len());
        self.measurements.push(Measurement {
            op: CostOp::Compact,
            units: src.bytes,
            items: 1,
            gpu_ms,
            beside: false,
        });
        Ok(h)
    }

    fn free_blas(&mut self, blas: BlasHandle, last_used_frame: u64) {
        if let Some(b) = self.blases.get(&blas) {
            if b.last_tlas.is_some_and(|t| t > last_used_frame) {
                self.counters.lifetime_violations += 1;
            }
            self.live_bytes -= b.bytes;
            self.retiring_bytes += b.bytes;
            // Ordered by frame, as the Vulkan backend keeps it: a failed frame's BLASes retire
            // against an older frame than frees already queued (the property test found the
            // FIFO holding them behind a newer entry while the manager counted them gone).
            let i = self
                .retiring
                .partition_point(|&(f, _)| f <= last_used_frame);
            self.retiring.insert(i, (last_used_frame, blas));
        }
    }

    fn blas_address(&self, blas: BlasHandle) -> u64 {
        // Device addresses are 256-byte aligned and never 0 for a live BLAS.
        blas.0 << 8
    }

    fn build_tlas(
        &mut self,
        instances: &[TlasInstance],
        delta: TlasDelta<'_>,
    ) -> BackendResult<TlasHandle> {
        self.order.may_build_tlas()?;
        self.check(FaultPoint::BuildTlas)?;
        self.order.tlas_built();
        self.tlas_instances = instances.len();
        let frame = self.frame;
        self.track_records(instances, delta);
        // Every BLAS the records name is used by this frame (a dead one is a violation per
        // record naming it): one look per BLAS, not per record.
        self.counters.lifetime_violations += self.refs.unknown;
        let mut names_new = false;
        for &h in &self.refs.named {
            match self.blases.get_mut(&BlasHandle(h)) {
                Some(b) => {
                    names_new |= b.built_frame == frame;
                    self.tlas_marks.push((BlasHandle(h), b.last_tlas));
                    b.last_tlas = Some(frame);
                }
                None => {
                    self.counters.lifetime_violations += u64::from(self.refs.counts[h as usize])
                }
            }
        }
        let units = instances.len() as u64;
        let op = match self.next_tlas() {
            NextTlas::BuildEveryFrame => CostOp::Tlas,
            NextTlas::Update => CostOp::TlasUpdate,
            NextTlas::Rebuild => {
                let forced = self.tlas_updates_since >= Some(self.tlas_max_updates);
                if forced || self.frame_build_triangles <= self.light_frame_triangles {
                    CostOp::Tlas
                } else {
                    CostOp::TlasUpdate
                }
            }
        };
        if self.tlas_max_updates > 0 {
            self.tlas_updates_since = match op {
                CostOp::TlasUpdate => self.tlas_updates_since.map(|n| n + 1),
                _ => Some(0),
            };
        }
        // As the Vulkan backend records it: beside the frame's builds when no record names
        // one of them, in one timestamp pair (the TLAS's measurement covers both, the
        // builds' are 0).
        let own = self.costs.estimate_batch(op, units);
        let beside = self.frame_build_ms > 0.0 && !names_new;
        let gpu_ms = if beside {
            if self.frame_build_triangles > 0 {
                self.counters.builds_beside_tlas += 1;
            }
            for &i in &self.frame_build_measurements {
                if let Some(m) = self.measurements.get_mut(i) {
                    m.gpu_ms = 0.0;
                    m.beside = true;
                    if m.op == CostOp::Compact {
                        self.counters.compactions_beside_tlas += 1;
                    }
                }
            }
            self.costs.beside(own, self.frame_build_ms)
        } else {
            own
        };
        self.measurements.push(Measurement {
            op,
            units,
            items: instances.len() as u32,
            gpu_ms,
            beside,
        });
        Ok(TlasHandle::new(0, self.frame))
    }

    fn next_tlas(&self) -> NextTlas {
        match self.tlas_updates_since {
            _ if self.tlas_max_updates == 0 => NextTlas::BuildEveryFrame,
            Some(n) if n < self.tlas_max_updates.div_ceil(2) => NextTlas::Update,
            _ => NextTlas::Rebuild,
        }
    }

    fn end_frame(&mut self, frame: u64) -> BackendResult<()> {
        self.order.may_end(frame)?;
        self.check(FaultPoint::EndFrame)?;
        self.order.ended(frame);
        Ok(())
    }

    fn abort_frame(&mut self) {
        self.order.aborted();
        // An update needs a TLAS that ran: the next one is built.
        if self.tlas_max_updates > 0 {
            self.tlas_updates_since = None;
        }
        // The frame's TLAS was never submitted: it used nothing.
        for (h, prev) in self.tlas_marks.drain(..).rev() {
            if let Some(b) = self.blases.get_mut(&h) {
                b.last_tlas = prev;
            }
        }
    }

    fn take_measurements(&mut self) -> Vec<Measurement> {
        std::mem::take(&mut self.measurements)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lavapipe_sizes_and_retirement() {
        let mut b = ModelBackend::lavapipe();
        let g = GeometryRef {
            vertex_count: 10,
            triangle_count: 10_000,
            positions: None,
            indices: None,
            device_vertices: None,
            device_indices: None,
            opaque: true,
        };
        let s = b.blas_sizes(&g, BlasClass::Static);
        assert!((s.as_bytes as f64 - 1_040_256.0).abs() < 512.0);
        b.begin_frame(0).unwrap();
        let h = b
            .build_blases(&[BlasBuild {
                geometry: g,
                class: BlasClass::Static,
                sizes: s,
            }])
            .unwrap();
        b.end_frame(0).unwrap();
        b.free_blas(h[0], 0);
        assert_eq!(b.allocated_bytes(), s.as_bytes, "still in flight");
        b.begin_frame(1).unwrap();
        assert!(b.is_live(h[0]));
        b.end_frame(1).unwrap();
        b.begin_frame(2).unwrap();
        assert!(!b.is_live(h[0]));
        assert_eq!(b.allocated_bytes(), 0);
    }

    /// The model refuses what breaks the frame order as the Vulkan backend does, and lets an
    /// aborted frame's number begin again.
    #[test]
    fn frame_order_misuse_is_refused_typed() {
        let mut b = ModelBackend::lavapipe();
        let g = GeometryRef {
            vertex_count: 10,
            triangle_count: 100,
            positions: None,
            indices: None,
            device_vertices: None,
            device_indices: None,
            opaque: true,
        };
        let refused = |r: BackendResult<()>, m: Misuse| assert_eq!(r, Err(m.into()));
        refused(b.end_frame(0), Misuse::NotRecording);
        refused(
            b.begin_frame(u64::MAX),
            Misuse::FrameNumberTooLarge(u64::MAX),
        );
        b.begin_frame(0).unwrap();
        refused(b.begin_frame(1), Misuse::StillRecording { frame: 0 });
        let sizes = b.blas_sizes(&g, BlasClass::Skinned);
        let h = b.build_blases(&[BlasBuild {
            geometry: g,
            class: BlasClass::Skinned,
            sizes,
        }]);
        let h = h.unwrap()[0];
        let refit = BlasRefit {
            blas: h,
            geometry: g,
            rebuild: false,
        };
        refused(b.refit_blases(&[refit, refit]), Misuse::DuplicateRefit(h));
        b.build_tlas(&[], TlasDelta::ALL).unwrap();
        refused(
            b.build_tlas(&[], TlasDelta::ALL).map(|_| ()),
            Misuse::TlasAlreadyBuilt,
        );
        refused(b.refit_blases(&[refit]), Misuse::RefitAfterTlas);
        refused(
            b.end_frame(1),
            Misuse::WrongFrame {
                frame: 1,
                recording: 0,
            },
        );
        b.end_frame(0).unwrap();
        refused(
            b.begin_frame(0),
            Misuse::FrameNotIncreasing { frame: 0, last: 0 },
        );
        // A frame that fails is aborted; its number begins again.
        b.begin_frame(1).unwrap();
        b.abort_frame();
        b.begin_frame(1).unwrap();
        b.build_tlas(&[], TlasDelta::ALL).unwrap();
        b.end_frame(1).unwrap();
    }
}
