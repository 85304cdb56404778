//! The per-frame TLAS: records (split meshes expanded into parts), the instance buffer, its
//! build or its update in place from the last frame's (`TlasUpdates`, with parked records),
//! and the handles that name it.

use super::tlas_slots::SlotKeeper;
use super::*;
use crate::backend::vulkan::device::accel::flags_for;

/// Build flags of the parking BLAS.
const PARKING_FLAGS: vk::BuildAccelerationStructureFlagsKHR =
    vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;

/// When the per-frame TLAS is an update of the last frame's
/// (`VK_BUILD_ACCELERATION_STRUCTURE_MODE_UPDATE_KHR`) instead of a build.
///
/// An update costs a fraction of a build (on the H200, 0.035 against 0.261 ms for the default
/// run's 14,181 records, `docs/GPU.md`) but keeps the last build's tree: it stays correct
/// whatever the records hold, and traces slower as they drift from what was built. So a build
/// is followed by at most [`TlasUpdates::max_updates`] updates, and from half of that on the
/// next frame builds. The manager learns that before it chooses the frame's BLAS builds
/// ([`crate::backend::NextTlas`]) and keeps that frame's GPU work within its budget, so a TLAS
/// build never comes with BLAS builds the budget does not hold.
///
/// With updates on, each record keeps its instance slot from frame to frame whatever its
/// place in the manager's list (`tlas_slots.rs`): a record that leaves parks its slot where it
/// stood, one that joins takes the nearest parked slot (by rings of 64 m cells), and a frame
/// builds instead once too many joined away from where they stand
/// ([`TlasUpdates::max_misplaced`]). Builds spread the parked slots over the records again.
///
/// **Off by default.** Written in list order, updated trees traced 9.5x slower on the H200
/// (the default run's render passes at 1080p: 75 ms p50 with up to 64 updates, 7.9 ms with a
/// build every frame). With stable slots, 76 % of the frames update, the GPU AS time drops
/// from 0.51 to 0.29 ms p50, and the render passes take 8.14 against 7.92 ms p50 (9.42
/// against 8.47 ms p99): about what the AS time saves. But `update` costs 0.3-0.6 ms more on
/// the host, and the AS p99 stays at 0.60 ms (it is set by the build frames; `docs/GPU.md`,
/// "Stable TLAS slots").
///
/// An update needs the same instance count as its build. A build therefore reserves
/// [`TlasUpdates::headroom`] more records than the frame has; the records a frame does not
/// fill are *parked*: mask 0 (no ray ever hits them), a zero transform, and a reference to a
/// one-triangle BLAS the backend keeps (an instance must stay active across updates). A frame
/// with more records than its source's count is built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TlasUpdates {
    /// Update in place between builds (default off). Off: every frame builds its TLAS.
    pub enabled: bool,
    /// Updates after a build before the next build is forced (default 16).
    pub max_updates: u32,
    /// From `max_updates / 2` updates on, a frame whose BLAS builds total at most this many
    /// triangles builds its TLAS; heavier frames keep updating until `max_updates`. Default:
    /// any frame (the manager keeps a frame that is due within its GPU budget,
    /// `NextTlas::Rebuild`).
    pub light_frame_triangles: u64,
    /// Records a build reserves beyond the frame's, as a fraction of them (default 1/8, at
    /// least 64): how many more records the updates that follow may hold.
    pub headroom: f32,
    /// A frame builds instead of updating once more than this fraction of the records
    /// (default 1/256) joined since the last build into a parked slot away from where they
    /// stand (the nearest parked slot, but none in or next to their 64 m cell): each
    /// stretches the updated tree's boxes from that slot to the record, which every ray
    /// between them then visits.
    pub max_misplaced: f32,
}

impl Default for TlasUpdates {
    fn default() -> Self {
        Self {
            enabled: false,
            max_updates: Self::ON.max_updates,
            light_frame_triangles: Self::ON.light_frame_triangles,
            headroom: Self::ON.headroom,
            max_misplaced: Self::ON.max_misplaced,
        }
    }
}

impl TlasUpdates {
    /// Updates in place with the default limits.
    pub const ON: TlasUpdates = TlasUpdates {
        enabled: true,
        max_updates: 16,
        light_frame_triangles: u64::MAX,
        headroom: 0.125,
        max_misplaced: 1.0 / 256.0,
    };

    /// Every frame builds its TLAS (no updates).
    pub const OFF: TlasUpdates = TlasUpdates {
        enabled: false,
        max_updates: 0,
        light_frame_triangles: 0,
        headroom: 0.0,
        max_misplaced: 0.0,
    };
}

/// The TLAS a frame may update from: the slot whose TLAS was built or updated last, with how
/// many instances, and how many updates since its build.
#[derive(Debug, Clone, Copy)]
pub(super) struct TlasSource {
    slot: usize,
    count: u32,
    updates: u32,
}

/// The BLAS of parked TLAS records (`TlasUpdates`): one tiny triangle, never hit (mask 0).
#[derive(Debug)]
pub(super) struct Parking {
    pub(super) accel: AccelStruct,
    pub(super) input: GpuBuffer,
    /// (slot, frame) whose commands build it; None: no frame that ran built it yet (the one
    /// that recorded its build was aborted, or never executed by the engine).
    pub(super) built: Option<(usize, u64)>,
    /// A frame that built it ran (so every later frame may reference it).
    pub(super) confirmed: bool,
}

impl VulkanBackend {
    /// Device address of the primitive-base table of `tlas` (one `u32` per TLAS record, in
    /// record order: 0, or for the extra records of a split mesh's parts the part's first
    /// primitive), or 0 when no record of it is a part. A shader adds the entry of the hit's
    /// record (`gl_InstanceID`) to the hit's primitive id to get the mesh's primitive id, which
    /// [`VulkanBackend::shading_geometry`]'s index buffer is indexed by. Valid while the frame
    /// that built `tlas` is in flight.
    pub fn primitive_bases(&self, tlas: TlasHandle) -> u64 {
        self.slot_of(tlas).map_or(0, |s| s.bases_address)
    }

    /// The TLAS of a handle returned by `build_tlas`, as the ref the renderer traces (its raw
    /// handle is [`TlasRef::raw`]); None once its slot was reused for a later frame
    /// (`frames_in_flight` frames later): a stale handle never resolves to a newer TLAS. A ref
    /// kept past that is stale too: the slot's TLAS is rebuilt then, and
    /// [`VulkanContext::is_live_tlas`] is false for it from its rebuild on. Also None, and its
    /// refs stale, once a BLAS that the frame may name was destroyed (a `begin_frame` after
    /// the frame completed freed it): tracing the TLAS then would read freed memory.
    pub fn tlas(&self, handle: TlasHandle) -> Option<TlasRef> {
        if self.freed_through.is_some_and(|t| handle.frame() <= t) {
            return None;
        }
        self.ctx.tlas_ref(self.slot_of(handle)?.tlas.as_ref()?)
    }

    /// [`VulkanBackend::shading_geometry`] for a record of the TLAS `tlas`, with the TLAS
    /// handle as the generation: [`VulkanError::StaleHandle`] once `tlas`'s slot was reused.
    /// While `tlas` is current, every BLAS its records name is retained (freed BLASes are
    /// destroyed only after the frames that may trace them), so no address in its records can
    /// belong to a newer BLAS. `Ok(None)`: the BLAS is not shaded from these buffers (see
    /// `shading_geometry`), or it was freed after `tlas` was built.
    pub fn shading_geometry_in(
        &self,
        tlas: TlasHandle,
        blas_address: u64,
    ) -> VkResult<Option<(u64, u64)>> {
        self.resolve_tlas(tlas)?;
        Ok(self.shading_geometry(blas_address))
    }

    /// The TLAS of `handle` ([`VulkanBackend::tlas`]), or [`VulkanError::StaleHandle`] once its
    /// slot was reused.
    pub fn resolve_tlas(&self, handle: TlasHandle) -> VkResult<TlasRef> {
        self.tlas(handle).ok_or_else(|| VulkanError::StaleHandle {
            what: "TLAS",
            detail: format!(
                "frame {} (slot {} now holds frame {})",
                handle.frame(),
                handle.slot(),
                self.slots
                    .get(handle.slot() as usize)
                    .map_or(0, |s| s.frame)
            ),
        })
    }

    /// Test support: a copy of the instance records frame `handle` built its TLAS from (the
    /// host-visible instance buffer), while the handle resolves. With `TlasUpdates` on, they
    /// are in slot order, parked slots (mask 0) included.
    #[doc(hidden)]
    pub fn tlas_instance_bytes(&self, handle: TlasHandle) -> Option<Vec<u8>> {
        let s = self.slot_of(handle)?;
        let n = self.expanded_len_of(handle)?;
        s.instances
            .as_ref()?
            .mapped()
            .map(|m| m[..n.min(m.len())].to_vec())
    }

    /// Bytes of instance records of the frame of `handle` (its TLAS's record count).
    fn expanded_len_of(&self, handle: TlasHandle) -> Option<usize> {
        self.slot_of(handle)
            .map(|s| s.records as usize * std::mem::size_of::<TlasInstance>())
    }

    /// Which records the current slot's instance buffer lacks, when it holds an earlier
    /// call's records: `Some((from, listed))` means every record at or after `from`, and the
    /// `listed` ones before it (the deltas since, see `TlasDelta`). `None`: write them all.
    fn stale_records(&self, call: u64) -> Option<(usize, Vec<u32>)> {
        let since = self.slots[self.current].instances_call;
        if since == 0 {
            return None;
        }
        let deltas: Vec<&(u64, usize, Vec<u32>)> =
            self.tlas_history.iter().filter(|d| d.0 > since).collect();
        if deltas.len() as u64 != call - since {
            return None;
        }
        let from = deltas.iter().map(|d| d.1).min().unwrap_or(0);
        let listed = deltas
            .iter()
            .flat_map(|d| d.2.iter().copied())
            .filter(|&i| (i as usize) < from)
            .collect();
        Some((from, listed))
    }

    /// The flags every TLAS of this backend is built with.
    /// Build flags of this backend's BLASes of `class`.
    pub(super) fn blas_flags(&self, class: BlasClass) -> vk::BuildAccelerationStructureFlagsKHR {
        flags_for(class, self.desc.static_blas_prefer)
    }

    fn tlas_build_flags(&self) -> vk::BuildAccelerationStructureFlagsKHR {
        if self.desc.tlas_updates.enabled {
            self.desc.tlas_flags | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE
        } else {
            self.desc.tlas_flags
        }
    }

    /// Whether frame `frame`'s commands in `slot` ran or will run: submitted (own-submit; an
    /// aborted frame is forgotten by `abort_frame`) or executed by the engine.
    fn slot_ran(&self, slot: usize, frame: u64) -> bool {
        let s = &self.slots[slot];
        s.frame == frame
            && (self.desc.recording == Recording::OwnSubmit && s.submitted_value > 0 || s.executed)
    }

    /// What `plan_tlas` will do as far as the frame's builds do not decide it: an update while
    /// the last build is fresh (fewer than half of `max_updates` updates since), else a build.
    /// (A frame planned as an update still builds when its records outgrow the last build or
    /// joined too far from their slots: that is known only once they are placed.)
    pub(super) fn planned_tlas(&self) -> crate::backend::NextTlas {
        use crate::backend::NextTlas;
        let u = self.desc.tlas_updates;
        match self.tlas_source {
            _ if !u.enabled => NextTlas::BuildEveryFrame,
            Some(src) if src.updates < u.max_updates.div_ceil(2) => NextTlas::Update,
            _ => NextTlas::Rebuild,
        }
    }

    /// How this frame's TLAS is made, for `real` records: (instances, the TLAS to update
    /// from). `None`: a build, with the headroom of `TlasUpdates` parked after the records.
    fn plan_tlas(&self, real: u32) -> (u32, Option<TlasSource>) {
        let u = self.desc.tlas_updates;
        if !u.enabled {
            return (real, None);
        }
        if let Some(src) = self.tlas_source {
            let forced = src.updates >= u.max_updates;
            let due = src.updates >= u.max_updates.div_ceil(2)
                && self.frame_build_triangles <= u.light_frame_triangles;
            let prev = &self.slots[src.slot];
            // The source is the last frame's TLAS (built or updated by a frame that ran),
            // untouched since.
            let ran = src.slot == self.current || self.slot_ran(src.slot, prev.frame);
            let intact = prev.tlas.is_some() && prev.tlas_count == src.count;
            if real <= src.count && !forced && !due && ran && intact {
                return (src.count, Some(src));
            }
        }
        (real.saturating_add(self.spare_records(real)), None)
    }

    /// Records a build reserves beyond `real` for the updates after it (`TlasUpdates::headroom`).
    fn spare_records(&self, real: u32) -> u32 {
        let h = self.desc.tlas_updates.headroom.max(0.0);
        ((real as f32 * h).ceil() as u32).max(64)
    }

    /// With updates on: places the frame's records in the instance slots of the last frame's
    /// (`SlotKeeper`), so an update refits each slot to where its record was built. An update
    /// keeps the layout; so does a build while at most twice the headroom is parked, else the
    /// slots are laid out anew. Returns the instance count and the source, which is dropped
    /// when the layout could not be kept.
    fn place_records(
        &mut self,
        keeper: &mut SlotKeeper,
        instances: &[TlasInstance],
        delta: TlasDelta<'_>,
        planned: (u32, Option<TlasSource>),
        parking: u64,
    ) -> (u32, Option<TlasSource>) {
        let _s = tracing::trace_span!("place_records").entered();
        let real = instances.len() as u32;
        let (count, source) = planned;
        if let Some(src) = source {
            if keeper.len() == src.count as usize && keeper.place(instances, delta, parking) {
                // A record that joined far from any parked slot would stretch the updated
                // tree across the map: past the allowance, this frame builds (on the layout
                // just placed), whatever the manager budgeted. Updating once more and
                // building in the next frame (which the manager would budget for) was
                // measured: the stretched trees traced up to 42 ms a frame at 10x density
                // (render passes p99, against 11.5 ms), 10.6 against 8.6 ms at the default
                // density (`docs/GPU.md`, "The next TLAS in the budget").
                let allowed = self.desc.tlas_updates.max_misplaced * count as f32;
                if keeper.misplaced as f32 <= allowed {
                    return (count, source);
                }
                keeper.reset_misplaced();
                keeper.repark(instances, parking);
                return (count, None);
            }
        }
        let spare = self.spare_records(real);
        let kept = keeper.len() >= instances.len()
            && keeper.parked() <= 2 * spare as usize
            && keeper.place(instances, delta, parking);
        if kept {
            keeper.repark(instances, parking);
        } else {
            keeper.lay_out(instances, (real + spare) as usize, parking);
        }
        // A build: the tree is new, nothing is misplaced in it.
        keeper.reset_misplaced();
        (keeper.len() as u32, None)
    }

    /// The parking BLAS's address, built first if no frame that ran built it.
    fn ensure_parking(&mut self, cmd: vk::CommandBuffer) -> BackendResult<u64> {
        let here = (self.current, self.slots[self.current].frame);
        if let Some(p) = &self.parking {
            let ok = p.confirmed
                || p.built == Some(here)
                || p.built
                    .is_some_and(|(slot, frame)| self.slot_ran(slot, frame));
            if ok {
                let address = p.accel.address;
                self.parking.as_mut().expect("checked").confirmed = true;
                return Ok(address);
            }
        }
        if self.parking.is_none() {
            // One small triangle at the origin; u32 indices after the f32x3 positions.
            let mut data = Vec::with_capacity(48);
            for v in [[0.0f32, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, 1e-3, 0.0]] {
                data.extend_from_slice(bytemuck::bytes_of(&v));
            }
            data.extend_from_slice(bytemuck::cast_slice(&[0u32, 1, 2]));
            let mut input = self.create_buffer(
                BufferDesc {
                    name: "parking BLAS input",
                    size: 256,
                    usage: BUILD_INPUT_USAGE,
                    memory: MemoryKind::Upload,
                },
                false,
            )?;
            input.write(0, &data);
            let geom = self.parking_geometry(&input);
            let sizes = self.ctx.blas_sizes(&[geom], PARKING_FLAGS);
            let accel = match self.ctx.create_accel(
                vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL,
                sizes.storage,
                "parking BLAS",
            ) {
                Ok(a) => a,
                Err(e) => {
                    self.destroy(Retired::Buffer(input));
                    return Err(backend_err(e));
                }
            };
            self.allocated += sizes.storage;
            self.parking = Some(Parking {
                accel,
                input,
                built: None,
                confirmed: false,
            });
        }
        let p = self.parking.as_ref().expect("created above");
        let geom = [self.parking_geometry(&p.input)];
        let (dst, address) = (p.accel.raw, p.accel.address);
        let sizes = self.ctx.blas_sizes(&geom, PARKING_FLAGS);
        let align = self.ctx.info().min_scratch_alignment;
        self.ensure_scratch(align_up(sizes.build_scratch, align))?;
        let scratch = self.scratch_alloc(sizes.build_scratch);
        let build = BlasBuildInput {
            geometries: &geom,
            flags: PARKING_FLAGS,
            dst,
            update_from: None,
            scratch_address: scratch,
        };
        // SAFETY: recording; the input buffer is host-written before submission and lives
        // with the BLAS; no frame that ran references this BLAS yet (it was never built by
        // one), so rebuilding it races with nothing; the TLAS barrier orders it before use.
        unsafe { self.ctx.cmd_build_blases(cmd, &[build]) };
        self.parking.as_mut().expect("created above").built = Some(here);
        Ok(address)
    }

    fn parking_geometry(&self, input: &GpuBuffer) -> TriangleGeometry {
        TriangleGeometry {
            vertex_address: input.address,
            vertex_format: vk::Format::R32G32B32_SFLOAT,
            vertex_stride: 12,
            max_vertex: 2,
            index_address: input.address + 36,
            index_type: vk::IndexType::UINT32,
            triangle_count: 1,
            opaque: true,
        }
    }

    /// Debug builds: every record the call may have changed names a live BLAS, one freed
    /// with this frame as its last, or none (address 0: inactive). A record naming a freed BLAS would trace whatever took its
    /// storage since.
    #[cfg(debug_assertions)]
    pub(super) fn check_records(
        &self,
        records: &[TlasInstance],
        delta: TlasDelta<'_>,
    ) -> BackendResult<()> {
        let frame = self.slots[self.current].frame;
        let from = delta.stable.min(records.len());
        let listed = delta
            .changed
            .iter()
            .map(|&i| i as usize)
            .filter(|&i| i < from);
        for index in (from..records.len()).chain(listed) {
            let address = records[index].blas_address;
            // Freed with this frame as its last (retiring until it completes) is fine.
            if address != 0 && !self.is_blas_address_usable(address, frame) {
                return Err(Misuse::UnknownBlasAddress { index, address }.into());
            }
        }
        Ok(())
    }

    pub(super) fn record_tlas(
        &mut self,
        instances: &[TlasInstance],
        delta: TlasDelta<'_>,
    ) -> BackendResult<TlasHandle> {
        self.fault(FaultPoint::BuildTlas)?;
        let cmd = self.cmd()?;
        self.tlas_calls += 1;
        let call = self.tlas_calls;
        self.tlas_history.push_back((
            call,
            delta.stable.min(instances.len()),
            delta.changed.to_vec(),
        ));
        while self.tlas_history.len() > self.slots.len() + 1 {
            self.tlas_history.pop_front();
        }
        // Split meshes add records per part (and a primitive-base table): all are written.
        let mut records = std::mem::take(&mut self.expanded);
        records.clear();
        let mut bases = std::mem::take(&mut self.bases);
        bases.clear();
        let split = !self.split_parts.is_empty();
        if split {
            records.extend_from_slice(instances);
            for r in instances {
                if let Some(parts) = self.split_parts.get(&r.blas_address) {
                    if bases.is_empty() {
                        bases.resize(instances.len(), 0);
                    }
                    records.extend(parts.iter().map(|&(a, _)| TlasInstance {
                        blas_address: a,
                        ..*r
                    }));
                    bases.extend(parts.iter().map(|&(_, first)| first));
                }
            }
        }
        let records_now: &[TlasInstance] = if split { &records } else { instances };
        let s = self.current;
        self.slots[s].bases_address = 0;
        if !bases.is_empty() {
            let bytes = (bases.len() * 4) as u64;
            if self.slots[s].bases.as_ref().is_none_or(|b| b.size < bytes) {
                let buf = self.create_buffer(
                    BufferDesc {
                        name: "TLAS primitive bases",
                        size: bytes.next_power_of_two().max(4096),
                        usage: vk::BufferUsageFlags::STORAGE_BUFFER
                            | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
                        memory: MemoryKind::Upload,
                    },
                    false,
                )?;
                if let Some(old) = self.slots[s].bases.replace(buf) {
                    self.retire_now(Retired::Buffer(old));
                }
            }
            let b = self.slots[s].bases.as_mut().expect("allocated above");
            b.write(0, bytemuck::cast_slice(&bases));
            self.slots[s].bases_address = b.address;
        }
        self.bases = bases;
        let real = records_now.len() as u32;
        let planned = self.plan_tlas(real);
        // Stable slots with updates on; split parts are written in list order (their
        // primitive bases are indexed by slot).
        let keep = self.desc.tlas_updates.enabled && !split;
        let (count, source, keeper_parking) = if keep {
            let parking = self.ensure_parking(cmd)?;
            let mut keeper = std::mem::take(&mut self.slot_keeper);
            let (count, source) =
                self.place_records(&mut keeper, instances, delta, planned, parking);
            self.counters.tlas_slots_joined += u64::from(keeper.joined);
            self.counters.tlas_slots_misplaced += u64::from(keeper.misplaced_now);
            let entry = self.tlas_history.back_mut().expect("pushed above");
            entry.1 = if keeper.all { 0 } else { keeper.len() };
            entry.2.clear();
            entry.2.extend_from_slice(&keeper.written);
            self.slot_keeper = keeper;
            (count, source, parking)
        } else {
            if self.desc.tlas_updates.enabled {
                // Split parts this frame: the next frame with stable slots lays them out anew.
                self.slot_keeper.reset();
            }
            (planned.0, planned.1, 0)
        };
        let flags = self.tlas_build_flags();
        let n = count.max(1);
        let bytes = u64::from(n) * 64;
        if self.slots[s]
            .instances
            .as_ref()
            .is_none_or(|b| b.size < bytes)
        {
            let size = bytes.next_power_of_two().max(64 * 1024);
            let buf = self.create_buffer(
                BufferDesc {
                    name: "TLAS instances",
                    size,
                    usage: BUILD_INPUT_USAGE,
                    memory: MemoryKind::Upload,
                },
                false,
            )?;
            if let Some(old) = self.slots[s].instances.replace(buf) {
                self.retire_now(Retired::Buffer(old));
            }
            self.slots[s].instances_call = 0;
            self.slots[s].parked = (0, 0);
        }
        if self.slots[s].tlas_capacity < n {
            let cap = n.next_power_of_two().max(1024);
            let sizes = self.ctx.tlas_sizes(cap, flags);
            self.reserve(sizes.storage, false)?;
            let tlas = self
                .ctx
                .create_accel(
                    vk::AccelerationStructureTypeKHR::TOP_LEVEL,
                    sizes.storage,
                    &format!("TLAS slot {s}"),
                )
                .map_err(|e| {
                    self.unreserve(sizes.storage, false);
                    backend_err(e)
                })?;
            if let Some(old) = self.slots[s].tlas.replace(tlas) {
                self.retire_now(Retired::Accel(old));
            }
            self.slots[s].tlas_capacity = cap;
            self.slots[s].tlas_sizes = Some((flags, sizes));
        }
        let parking = if keep {
            keeper_parking
        } else if count > real {
            self.ensure_parking(cmd)?
        } else {
            0
        };
        let sizes = match self.slots[s].tlas_sizes {
            Some((f, sizes)) if f == flags => sizes,
            _ => self.ctx.tlas_sizes(count, flags),
        };
        let scratch_bytes = if source.is_some() {
            sizes.update_scratch
        } else {
            sizes.build_scratch
        };
        self.ensure_scratch(align_up(
            scratch_bytes,
            self.ctx.info().min_scratch_alignment,
        ))?;
        let scratch = self.scratch_alloc(scratch_bytes);
        // The slot's buffer holds the records of the call it was last written at (its frame
        // completed: `begin_frame` waited for it): write what changed since, or everything.
        let stale = if split {
            None
        } else {
            self.stale_records(call)
        };
        // With stable slots the buffer holds the keeper's image, parked slots included.
        let records_now: &[TlasInstance] = if keep {
            self.slot_keeper.image()
        } else {
            records_now
        };
        let slot = &mut self.slots[s];
        let ibuf = slot.instances.as_mut().expect("allocated above");
        const RECORD: usize = std::mem::size_of::<TlasInstance>();
        let mut written = match stale {
            None => {
                ibuf.write(0, bytemuck::cast_slice(records_now));
                records_now.len()
            }
            Some((from, listed)) => {
                let from = from.min(records_now.len());
                ibuf.write(from * RECORD, bytemuck::cast_slice(&records_now[from..]));
                for &i in &listed {
                    let i = i as usize;
                    ibuf.write(i * RECORD, bytemuck::bytes_of(&records_now[i]));
                }
                records_now.len() - from + listed.len()
            }
        };
        // Parked records after the frame's: only where the buffer does not hold them already.
        // Each stands where a record of the frame stands, scaled to a point: a cluster of
        // parked instances in one place makes a degenerate subtree that builds and updates
        // slowly (3x the build time on the H200 with them all at the origin).
        let park_at = |i: u32| {
            let mut t = [0.0f32; 12];
            if let Some(r) = records_now.get(i as usize % records_now.len().max(1)) {
                (t[3], t[7], t[11]) = (r.transform[3], r.transform[7], r.transform[11]);
            }
            TlasInstance {
                transform: t,
                blas_address: parking,
                ..bytemuck::Zeroable::zeroed()
            }
        };
        let (had_from, had_to) = slot.parked;
        let mut park = |from: u32, to: u32| {
            for i in from..to {
                ibuf.write(i as usize * RECORD, bytemuck::bytes_of(&park_at(i)));
            }
            written += (to - from) as usize;
        };
        if keep {
            // Parked slots are in the image.
            slot.parked = (0, 0);
        } else {
            if had_from >= had_to || had_to < real || had_from > count {
                park(real, count);
            } else {
                park(real, had_from.clamp(real, count));
                park(had_to.clamp(real, count), count);
            }
            slot.parked = (real, count);
        }
        self.counters.tlas_records_written += written as u64;
        self.counters.tlas_records_built += u64::from(real);
        let slot = &mut self.slots[s];
        let ibuf = slot.instances.as_mut().expect("allocated above");
        slot.instances_call = if split { 0 } else { call };
        let (iaddr, tlas) = (
            ibuf.address,
            slot.tlas.as_ref().expect("allocated above").raw,
        );
        slot.records = if keep { count } else { real };
        slot.tlas_count = count;
        self.tlas_len = real as usize;
        self.expanded = records;
        let from = source.map(|src| {
            self.slots[src.slot]
                .tlas
                .as_ref()
                .expect("checked by plan_tlas")
                .raw
        });
        let (op, updates) = match source {
            Some(src) => {
                self.counters.tlas_updates += 1;
                (CostOp::TlasUpdate, src.updates + 1)
            }
            None => {
                self.counters.tlas_builds += 1;
                (CostOp::Tlas, 0)
            }
        };
        self.tlas_source = Some(TlasSource {
            slot: s,
            count,
            updates,
        });
        // The frame's BLAS builds: beside the TLAS when no record names them (the manager
        // schedules its builds after its records), else before it.
        let beside = self.pending.has_work() && !self.records_name_pending(instances, delta);
        if !beside {
            if self.pending.op.is_some() {
                self.counters.builds_before_tlas += 1;
            }
            self.record_pending_builds(cmd);
        }
        // SAFETY: recording; the barrier orders this frame's refits, the parking BLAS and the
        // builds and compactions when the records name one (and an earlier frame's TLAS build
        // or update, `from`, in submission order) before the TLAS build and the builds and
        // compactions beside it.
        unsafe { self.ctx.cmd_accel_barrier(cmd) };
        // Beside: one timestamp pair around the builds and the TLAS (a timestamp between
        // them would serialize them), the builds recorded first.
        let t = self.timestamp_begin(op, u64::from(count), count);
        if beside {
            if self.pending.op.is_some() {
                self.counters.builds_beside_tlas += 1;
            }
            if let Some(builds) = self.record_builds(cmd, false) {
                self.timed_beside(t, builds);
            }
        }
        // SAFETY: recording; every referenced BLAS is live until its retirement frame (none is
        // built beside this TLAS: checked above), the parking BLAS until the backend is
        // dropped; `from` is only read.
        unsafe {
            self.ctx
                .cmd_build_tlas(cmd, tlas, from, flags, iaddr, count, scratch);
        }
        self.timestamp_end(t);
        if beside {
            self.record_compacted_size_queries(cmd);
        }
        Ok(TlasHandle::new(s as u32, self.slots[s].frame))
    }
}
