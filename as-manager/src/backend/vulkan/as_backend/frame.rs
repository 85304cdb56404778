//! The frame ring: beginning a frame (waiting for its slot, harvesting queries, retiring what
//! the GPU is done with), scratch and timestamps of the frame being recorded, allocation and
//! destruction, and ending a frame (submitting it).

use super::*;

impl VulkanBackend {
    pub(super) fn slot_of(&self, handle: TlasHandle) -> Option<&Slot> {
        self.slots
            .get(handle.slot() as usize)
            .filter(|s| s.frame == handle.frame())
    }

    /// Engine-recorded: frame `frame` may begin only once the frame that used its slot before
    /// was reported done, and once the previous frame was handed to the engine (`record`).
    pub(super) fn check_slot_done(&self, frame: u64) -> BackendResult<()> {
        if self.desc.recording != Recording::Engine {
            return Ok(());
        }
        if let Some(slot) = self.to_record {
            return Err(BackendError::FrameNotRecorded {
                frame: self.slots[slot].frame,
            });
        }
        let s = &self.slots[(frame % self.slots.len() as u64) as usize];
        if s.submitted_value > 0 && self.engine_done.is_none_or(|d| d < s.frame) {
            return Err(BackendError::FrameInFlight {
                frame,
                waiting_for: s.frame,
            });
        }
        Ok(())
    }

    /// Engine-recorded: records the last frame's work (ended by the manager's `update`) into
    /// the engine's command buffer, as one `vkCmdExecuteCommands`. Call it once per `update`,
    /// before the engine's own commands that trace the frame's TLAS; the work ends with a
    /// barrier that makes the builds visible to ray-query compute, fragment and ray-tracing
    /// shaders.
    ///
    /// `cmd` carries the engine's promises (see [`FrameCmd::from_engine`]): the engine submits
    /// it before the next frame's, and calls [`frame_done`](Self::frame_done) for the frame
    /// only after that submission completed.
    pub fn record(&mut self, cmd: &FrameCmd) -> VkResult<()> {
        cmd.check(&self.ctx)?;
        let slot = self.to_record.take().ok_or_else(|| {
            VulkanError::Unsupported(
                "record: no frame to record (engine-recorded mode, once per update)".into(),
            )
        })?;
        let s = &mut self.slots[slot];
        if cmd.frame() != s.frame {
            self.to_record = Some(slot);
            return Err(VulkanError::Unsupported(format!(
                "record: the command buffer is frame {}'s, the frame to record is {}",
                cmd.frame(),
                s.frame
            )));
        }
        // SAFETY: a FrameCmd is a primary command buffer of this device, recording, outside a
        // render pass (its constructor's contract); the slot's secondary was ended by
        // `end_frame` and is executed once.
        unsafe { self.ctx.device.cmd_execute_commands(cmd.raw(), &[s.cmd]) };
        s.executed = true;
        self.recorded_up_to = Some(s.frame);
        Ok(())
    }

    /// Engine-recorded: the engine's submission of frame `frame` (and every frame before it)
    /// has completed on the GPU. What those frames used may now be freed, rewritten or reused.
    /// Frames reported out of order are fine; the latest counts. A frame not yet handed over
    /// by [`record`](Self::record) cannot have run: the claim counts up to the last frame
    /// recorded (with a warning), so that what later frames use is never freed early. (Own
    /// submission: ignored; the backend's timeline says what completed.)
    pub fn frame_done(&mut self, frame: u64) {
        if self.desc.recording != Recording::Engine {
            return; // the backend's own timeline says what completed
        }
        // Only frames already handed to the engine (`record`) can have completed: a claim
        // past them would free what the frames still to run use.
        let Some(recorded) = self.recorded_up_to else {
            tracing::warn!(frame, "frame_done before any frame was recorded: ignored");
            return;
        };
        if frame > recorded {
            tracing::warn!(frame, recorded, "frame_done past the last recorded frame");
        }
        let frame = frame.min(recorded);
        self.engine_done = Some(self.engine_done.map_or(frame, |d| d.max(frame)));
    }

    /// Who records and submits this backend's frames.
    pub fn recording(&self) -> Recording {
        self.desc.recording
    }

    /// Waits until every submitted frame finished (e.g. before reading a TLAS on another queue
    /// submission, or at shutdown). Engine-recorded: waits for the device to be idle, so the
    /// engine must have submitted every frame it recorded.
    pub fn wait_idle(&mut self) -> VkResult<()> {
        if self.desc.recording == Recording::Engine {
            self.ctx.wait_idle()?;
            let last = self.slots.iter().map(|s| s.frame).max();
            if let Some(last) = last.filter(|_| self.slots.iter().any(|s| s.submitted_value > 0)) {
                self.frame_done(last);
            }
            return Ok(());
        }
        let last = self
            .slots
            .iter()
            .map(|s| s.submitted_value)
            .max()
            .unwrap_or(0);
        self.wait_value(last)
    }

    pub(super) fn wait_value(&self, value: u64) -> VkResult<()> {
        if value == 0 {
            return Ok(());
        }
        self.ctx.wait_timeline(self.timeline, value)
    }

    /// Counts `bytes` as allocated; `limited` allocations (BLAS storage and inputs, what the
    /// manager can answer by evicting) are refused past `memory_limit`.
    pub(super) fn reserve(&mut self, bytes: u64, limited: bool) -> BackendResult<()> {
        if let (Some(limit), true) = (self.desc.memory_limit, limited) {
            if self.blas_allocated + bytes > limit {
                self.counters.oom += 1;
                return Err(BackendError::OutOfDeviceMemory);
            }
        }
        self.allocated += bytes;
        if limited {
            self.blas_allocated += bytes;
        }
        Ok(())
    }

    pub(super) fn unreserve(&mut self, bytes: u64, limited: bool) {
        self.allocated -= bytes;
        if limited {
            self.blas_allocated -= bytes;
        }
    }

    pub(super) fn create_accel(&mut self, size: u64, name: &str) -> BackendResult<AccelStruct> {
        self.reserve(size, true)?;
        let ty = vk::AccelerationStructureTypeKHR::BOTTOM_LEVEL;
        self.ctx
            .create_accel_in(ty, &mut self.accels, size, name)
            .map_err(|e| {
                self.unreserve(size, true);
                backend_err(e)
            })
    }

    pub(super) fn create_buffer(
        &mut self,
        desc: BufferDesc<'_>,
        limited: bool,
    ) -> BackendResult<GpuBuffer> {
        self.reserve(desc.size, limited)?;
        self.ctx.create_buffer(&desc).map_err(|e| {
            self.unreserve(desc.size, limited);
            backend_err(e)
        })
    }

    pub(super) fn destroy(&mut self, r: Retired) {
        let limited = matches!(
            r,
            Retired::BlasAccel(_) | Retired::BlasBuffer(_) | Retired::BlasInput(_)
        );
        match r {
            Retired::Accel(a) | Retired::BlasAccel(a) => {
                self.unreserve(a.size, limited);
                self.ctx.destroy_accel_in(a, &mut self.accels);
            }
            Retired::Buffer(b) | Retired::BlasBuffer(b) => {
                self.unreserve(b.size, limited);
                self.ctx.destroy_buffer(b);
            }
            Retired::BlasInput(r) => {
                self.unreserve(r.size, limited);
                self.inputs.free(&self.ctx, r);
            }
        }
    }

    /// Retires an object against the frame being recorded.
    pub(super) fn retire_now(&mut self, r: Retired) {
        let frame = self.slots[self.current].frame;
        self.retiring.push_back((frame, r));
    }

    /// Reserves `bytes` of the current slot's scratch; returns an aligned device address.
    /// The scratch buffer grows between batches (never within one recorded batch: callers
    /// reserve a batch's total first via `ensure_scratch`).
    pub(super) fn ensure_scratch(&mut self, total: u64) -> BackendResult<()> {
        let s = self.current;
        let used = self.slots[s].scratch_used.total();
        let cap = self.slots[s].scratch.as_ref().map_or(0, |x| x.2);
        if used + total <= cap {
            return Ok(());
        }
        let align = self.ctx.info().min_scratch_alignment;
        let size = (cap * 2).max(total).max(1 << 20);
        let buf = self.create_buffer(
            BufferDesc {
                name: "frame scratch",
                size: size + align,
                usage: vk::BufferUsageFlags::STORAGE_BUFFER
                    | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
                memory: MemoryKind::DeviceLocal,
            },
            false,
        )?;
        let base = align_up(buf.address, align);
        if let Some((old, _, _)) = self.slots[s].scratch.replace((buf, base, size)) {
            // Batches already recorded this frame still use the old buffer.
            self.retire_now(Retired::Buffer(old));
        }
        self.slots[s].scratch_used.clear();
        Ok(())
    }

    pub(super) fn scratch_alloc(&mut self, bytes: u64) -> vk::DeviceAddress {
        let s = &mut self.slots[self.current];
        let (_, base, _) = s
            .scratch
            .as_ref()
            .expect("ensure_scratch before scratch_alloc");
        base + s.scratch_used.push(bytes)
    }

    pub(super) fn cmd(&self) -> BackendResult<vk::CommandBuffer> {
        let s = &self.slots[self.current];
        if s.recording {
            Ok(s.cmd)
        } else {
            Err(Misuse::NotRecording.into())
        }
    }

    pub(super) fn timestamp_begin(&mut self, op: CostOp, units: u64, items: u32) -> Option<u32> {
        let timestamps = self.ctx.info().timestamps;
        let s = &mut self.slots[self.current];
        let first = s.timed.len() as u32 * 2;
        let room = if matches!(op, CostOp::Tlas | CostOp::TlasUpdate) {
            QUERIES_PER_SLOT
        } else {
            QUERIES_PER_SLOT - 2
        };
        if !timestamps || first + 2 > room {
            return None;
        }
        s.timed.push(Timed {
            op,
            units,
            items,
            first,
            beside: None,
        });
        // SAFETY: the slot's command buffer is recording; the query was reset in begin_frame.
        unsafe { s.timestamps.cmd_timestamp(&self.ctx, s.cmd, first) };
        Some(first)
    }

    /// Notes that the pair begun by `first` also times `builds` (op, triangles, BLASes),
    /// recorded beside its batch inside it.
    pub(super) fn timed_beside(&mut self, first: Option<u32>, builds: (CostOp, u64, u32)) {
        if let Some(t) = first.and_then(|f| {
            self.slots[self.current]
                .timed
                .iter_mut()
                .find(|t| t.first == f)
        }) {
            t.beside = Some(builds);
        }
    }

    pub(super) fn timestamp_end(&self, first: Option<u32>) {
        if let Some(first) = first {
            let s = &self.slots[self.current];
            // SAFETY: as in timestamp_begin.
            unsafe { s.timestamps.cmd_timestamp(&self.ctx, s.cmd, first + 1) };
        }
    }

    pub(super) fn read_completed_slot(&mut self, slot: usize) -> VkResult<()> {
        // The frame completed: the results it copied into its readback buffer are there.
        let s = &self.slots[slot];
        let words: &[u64] = bytemuck::cast_slice(s.results.mapped().expect("readback is mapped"));
        let ticks = (!s.timed.is_empty()).then(|| words[..s.timed.len() * 2].to_vec());
        let base = QUERIES_PER_SLOT as usize;
        let sizes = (!s.compact_queries.is_empty())
            .then(|| words[base..base + s.compact_queries.len()].to_vec());
        let s = &mut self.slots[slot];
        if let Some(ticks) = ticks {
            for t in &s.timed {
                let first = t.first as usize;
                let dt = ticks[first + 1].saturating_sub(ticks[first]);
                // Builds beside the batch: reported first, at 0 ms; the batch carries the
                // pair's time, theirs included.
                let builds = t.beside.map(|(op, units, items)| Measurement {
                    op,
                    units,
                    items,
                    gpu_ms: 0.0,
                    beside: true,
                });
                let m = Measurement {
                    op: t.op,
                    units: t.units,
                    items: t.items,
                    gpu_ms: s.timestamps.ticks_to_ms(dt),
                    beside: t.beside.is_some(),
                };
                for m in builds.into_iter().chain([m]) {
                    self.measurements.push(m);
                    if self.log.len() == 256 {
                        self.log.pop_front();
                    }
                    self.log.push_back(m);
                }
            }
        }
        s.timed.clear();
        let queries = std::mem::take(&mut s.compact_queries);
        if let Some(sizes) = sizes {
            for ((h, _), size) in queries.into_iter().zip(sizes) {
                if let Some(e) = self.blases.get_mut(key_of(h)) {
                    e.compacted_size = Some(size);
                }
            }
        }
        Ok(())
    }

    pub(super) fn begin_frame_inner(&mut self, frame: u64) -> VkResult<()> {
        let slot = (frame % self.slots.len() as u64) as usize;
        self.current = slot;
        // Wait for the frame that last used this slot (engine-recorded: `check_slot_done`
        // made sure the engine reported it done), then harvest its queries.
        let value = self.slots[slot].submitted_value;
        let engine = self.desc.recording == Recording::Engine;
        if !engine {
            tracing::trace_span!("wait").in_scope(|| self.wait_value(value))?;
        }
        if value > 0 {
            let done = value - 1;
            self.completed = Some(self.completed.map_or(done, |c| c.max(done)));
            if engine && !self.slots[slot].executed {
                // Never executed: its queries were never written.
                self.slots[slot].timed.clear();
                self.slots[slot].compact_queries.clear();
                self.slots[slot].quality_jobs.clear();
            } else {
                let _s = tracing::trace_span!("harvest").entered();
                self.read_completed_slot(slot)?;
                self.read_quality(slot);
            }
        }
        let reached = if engine {
            self.engine_done.map_or(0, |f| f.saturating_add(1))
        } else if self.desc.deterministic {
            0
        } else {
            // SAFETY: the timeline value is a plain read of our own semaphore.
            unsafe { self.ctx.device.get_semaphore_counter_value(self.timeline) }
                .op("vkGetSemaphoreCounterValue")?
        };
        if reached > 0 {
            self.completed = Some(self.completed.map_or(reached - 1, |c| c.max(reached - 1)));
        }
        let retire = tracing::trace_span!("retire").entered();
        if let Some(done) = self.completed {
            self.retired_shading.retain(|_, &mut (last, _)| last > done);
        }
        let freed_before = self.freed_through;
        while let Some((f, _)) = self.retiring.front() {
            if self.completed.is_some_and(|c| c >= *f) {
                let (f, r) = self.retiring.pop_front().expect("front exists");
                if matches!(r, Retired::BlasAccel(_)) {
                    self.counters.destroyed += 1;
                    self.freed_through = Some(self.freed_through.map_or(f, |t| t.max(f)));
                }
                self.destroy(r);
            } else {
                break;
            }
        }
        if let Some(through) = self
            .freed_through
            .filter(|_| self.freed_through != freed_before)
        {
            // The TLASes of frames up to `through` may name a BLAS just destroyed: their refs
            // go stale, so a renderer refuses them rather than trace freed memory.
            for s in self.slots.iter().filter(|s| s.frame <= through) {
                if let Some(t) = &s.tlas {
                    self.ctx.tlas_rebuilt(t.raw);
                }
            }
        }
        drop(retire);
        let _s = tracing::trace_span!("begin_cmd").entered();
        self.frame_build_triangles = 0;
        let s = &mut self.slots[slot];
        s.frame = frame;
        s.scratch_used.clear();
        s.timestamps.reset(&self.ctx);
        s.compact_pool.reset(&self.ctx);
        s.executed = false;
        let dev = &self.ctx.device;
        // A secondary command buffer (engine-recorded) inherits no render pass: it runs outside
        // one, like the builds it holds.
        let inheritance = vk::CommandBufferInheritanceInfo::default();
        let mut begin = vk::CommandBufferBeginInfo::default()
            .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        if engine {
            begin = begin.inheritance_info(&inheritance);
        }
        // SAFETY: the slot's previous submission completed (waited above, or reported done by
        // the engine), so its command buffer may be reset and re-recorded.
        unsafe {
            dev.reset_command_buffer(s.cmd, vk::CommandBufferResetFlags::empty())
                .op("vkResetCommandBuffer")?;
            dev.begin_command_buffer(s.cmd, &begin)
                .op("vkBeginCommandBuffer")?;
        }
        s.recording = true;
        // Order every earlier submission's AS writes before this frame's AS reads/writes, and
        // the engine's earlier GPU writes of build inputs (its skinning) before our reads.
        // SAFETY: the command buffer is recording, outside a render pass.
        unsafe {
            self.ctx.cmd_accel_barrier(s.cmd);
            self.ctx.cmd_build_input_barrier(s.cmd);
        }
        Ok(())
    }

    pub(super) fn end_and_submit(&mut self, frame: u64) -> BackendResult<()> {
        self.fault(FaultPoint::EndFrame)?;
        let cmd = self.cmd()?;
        let value = frame + 1;
        let engine = self.desc.recording == Recording::Engine;
        // Builds of a frame without a TLAS.
        self.record_pending_builds(cmd);
        let r = (|| {
            let s = &self.slots[self.current];
            // SAFETY: recording; the queries were reset at begin_frame and written by commands
            // recorded before; the results buffer is the slot's, read only after completion.
            unsafe {
                s.timestamps.cmd_copy_results(
                    &self.ctx,
                    cmd,
                    0,
                    s.timed.len() as u32 * 2,
                    &s.results,
                    0,
                    false,
                );
                s.compact_pool.cmd_copy_results(
                    &self.ctx,
                    cmd,
                    0,
                    s.compact_queries.len() as u32,
                    &s.results,
                    u64::from(QUERIES_PER_SLOT) * 8,
                    false,
                );
            }
            // SAFETY: recording; the barriers make the TLAS build visible to later traces, and
            // order this frame's reads of build inputs before the engine's next writes of them.
            unsafe {
                self.ctx.cmd_accel_barrier(cmd);
                self.ctx.cmd_build_input_release(cmd);
                self.ctx
                    .device
                    .end_command_buffer(cmd)
                    .op("vkEndCommandBuffer")?;
            }
            if engine {
                // The engine executes it in its own command buffer (`record`) and submits.
                return Ok(());
            }
            let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd)];
            let signal = [vk::SemaphoreSubmitInfo::default()
                .semaphore(self.timeline)
                .value(value)
                .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
            let submit = [vk::SubmitInfo2::default()
                .command_buffer_infos(&cmds)
                .signal_semaphore_infos(&signal)];
            self.ctx.submit(&submit)
        })();
        let s = &mut self.slots[self.current];
        s.recording = false;
        match r {
            Ok(()) => {
                s.submitted_value = value;
                self.frame_copies.clear();
                if engine {
                    self.to_record = Some(self.current);
                }
                Ok(())
            }
            Err(e) => {
                let e = backend_err(e);
                self.lost |= e == BackendError::DeviceLost;
                Err(e)
            }
        }
    }
}
