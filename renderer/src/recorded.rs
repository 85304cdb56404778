//! The pipelined renderer: [`Renderer::record`] puts a frame's three passes into the frame's
//! command buffer (one submission per frame, made by the engine or a `FrameLoop`, and no wait
//! per pass); [`Renderer::take`] reads the frame back once it has completed.
//!
//! Each frame in flight has its own output buffers, instance buffer, timestamps and descriptor
//! set (up to [`RECORDED_SETS`] frames in flight), so frame `n` never writes what a frame still
//! in flight reads. Pass times come from GPU timestamps, not from the host.

use rtstream_as_manager::backend::vulkan::{
    ash::vk, read_timer, Bound, BufferDesc, FrameCmd, MemoryKind, Pass, PassTimer, QueryKind,
    QueryPool, TlasRef, RECORDED_SETS,
};

use crate::error::{RenderError, Result};
use crate::frame::Frame;
use crate::renderer::{
    check_tlas, push_constants, read_frame, shading_table, validate, InstanceShading, Tracer,
};
use crate::shading::{write_table, ShadingUpdate, TableState};
use crate::slot::RenderSlot;
use crate::{RenderDesc, Renderer};

/// Timestamps a recorded frame takes: one before the passes and one after each.
const TIMESTAMPS: usize = 4;

/// Readback buffers, their bytes per pixel: colour, hits, surface, light.
const OUTPUTS: [(&str, u64); 4] = [
    ("render color", 4),
    ("render hits", 16),
    ("render surface", 16),
    ("render light", 16),
];

impl Renderer {
    /// Records the three passes of `desc` over `tlas` into `cmd` (after the manager's work for
    /// the frame, so the passes see this frame's builds). Returns at once; read the frame with
    /// [`take`](Self::take) once `cmd`'s submission has completed.
    ///
    /// Fails, recording nothing, when the frame that used this frame's resources
    /// (`cmd.frame() - RECORDED_SETS`) has not completed, or when the frame was recorded already
    /// ([`RenderError::FrameInFlight`]); when `cmd` cannot be recorded into (another device's,
    /// or submitted or abandoned already: [`VulkanError::FrameCmdUnusable`]); and when `tlas`
    /// is not live on the renderer's device: destroyed, another device's, or stale, its TLAS
    /// destroyed or built again since ([`RenderError::InvalidRequest`]). `tlas` must stay
    /// alive until the frame completes (the manager's TLAS of the frame does).
    ///
    /// [`VulkanError::FrameCmdUnusable`]: rtstream_as_manager::backend::vulkan::VulkanError::FrameCmdUnusable
    pub fn record(
        &mut self,
        cmd: &FrameCmd,
        tlas: TlasRef,
        instances: &[InstanceShading],
        desc: &RenderDesc,
    ) -> Result<()> {
        self.record_table(cmd, tlas, instances, None, desc)
    }

    /// [`record`](Self::record) for a shading table kept across frames: writes into the
    /// frame's instance buffer only the entries changed since that buffer was last written
    /// (the changes of `update` and of the versions recorded into the other frames' buffers
    /// since), not the whole table. Falls back to the whole table when `update` does not
    /// follow the version recorded last (see [`ShadingUpdate`]). Fails as `record` does.
    pub fn record_update(
        &mut self,
        cmd: &FrameCmd,
        tlas: TlasRef,
        update: ShadingUpdate<'_>,
        desc: &RenderDesc,
    ) -> Result<()> {
        self.record_table(cmd, tlas, update.table, Some(&update), desc)
    }

    /// Makes each recorded frame's instance buffer hold at least `entries` shading entries
    /// from its first frame on. A table that outgrows its buffer gets one twice as large, in
    /// the frame that needs it: an allocation of several megabytes (about 14 ms on the H100
    /// host, for each of the frames in flight) on the frame path. A frame loop that knows how
    /// many customIndexes it may hand out (say the world's instances and proxies) reserves
    /// them before its first frame. Takes effect for buffers made after the call.
    pub fn reserve_shading(&mut self, entries: usize) {
        self.reserved_entries = entries;
    }

    /// Shading entries written into the instance buffer by the last frame recorded (the
    /// whole table, or what changed: see [`record_update`](Self::record_update)).
    pub fn shading_entries_written(&self) -> usize {
        self.table_written
    }

    fn record_table(
        &mut self,
        cmd: &FrameCmd,
        tlas: TlasRef,
        instances: &[InstanceShading],
        update: Option<&ShadingUpdate<'_>>,
        desc: &RenderDesc,
    ) -> Result<()> {
        validate(desc)?;
        cmd.check(&self.ctx)?;
        check_tlas(&self.ctx, tlas)?;
        let n = RECORDED_SETS as usize;
        let i = (cmd.frame() % RECORDED_SETS as u64) as usize;
        while self.slots.len() < n {
            let k = self.slots.len();
            let timer = QueryPool::new(
                &self.ctx,
                QueryKind::Timestamp,
                4,
                &format!("render slot {k} passes"),
            )?;
            let times = match self.ctx.create_buffer(&BufferDesc {
                name: "render pass times",
                size: TIMESTAMPS as u64 * 16,
                usage: vk::BufferUsageFlags::TRANSFER_DST,
                memory: MemoryKind::Readback,
            }) {
                Ok(b) => b,
                Err(e) => {
                    timer.destroy(&self.ctx);
                    return Err(e.into());
                }
            };
            self.slots.push(RenderSlot {
                times,
                frame: None,
                taken: true,
                size: (0, 0),
                outputs: Vec::new(),
                instances: None,
                table: TableState::fresh(),
                timer,
            });
        }
        if let Some(f) = self.slots[i].frame {
            if f >= cmd.frame() || !cmd.is_done(f) {
                return Err(RenderError::FrameInFlight {
                    frame: cmd.frame(),
                    waiting_for: f,
                });
            }
        }
        // Every buffer's view of the table moves to this version (the other frames' buffers
        // keep its changes for their next write) before anything below can fail.
        self.chain
            .advance(self.slots.iter_mut().map(|s| &mut s.table), update);
        let ctx = self.ctx.clone();
        let (w, h) = (desc.width, desc.height);
        let pixels = u64::from(w) * u64::from(h);
        let slot = &mut self.slots[i];
        // The slot's last frame completed: its buffers and queries are free to reuse.
        if slot.size != (w, h) {
            for b in slot.outputs.drain(..) {
                ctx.destroy_buffer(b);
            }
            for (name, bytes) in OUTPUTS {
                slot.outputs.push(ctx.create_buffer(&BufferDesc {
                    name,
                    size: pixels * bytes,
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                    memory: MemoryKind::Readback,
                })?);
            }
            slot.size = (w, h);
        }
        let bytes: &[u8] = bytemuck::cast_slice(shading_table(instances));
        if slot
            .instances
            .as_ref()
            .is_none_or(|b| (b.size as usize) < bytes.len())
        {
            if let Some(b) = slot.instances.take() {
                ctx.destroy_buffer(b);
            }
            let reserved = self.reserved_entries * std::mem::size_of::<InstanceShading>();
            slot.instances = Some(
                ctx.create_buffer(&BufferDesc {
                    name: "render instances",
                    size: (bytes.len() as u64)
                        .next_power_of_two()
                        .max(reserved as u64),
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                    memory: MemoryKind::Upload,
                })?,
            );
            slot.table = TableState::fresh();
        }
        let ibuf = slot.instances.as_mut().expect("allocated above");
        self.table_written = write_table(ibuf, &mut slot.table, instances);
        slot.timer.reset(&ctx);
        // Availability words at zero until this frame's timestamps are copied (see `take`).
        slot.times.write(0, &[0; TIMESTAMPS * 16]);
        let mut push = push_constants(desc);
        let pushes: Vec<_> = (0..3u32)
            .map(|pass| {
                push.size[2] = pass;
                push
            })
            .collect();
        let (grid, rays) = ([w.div_ceil(8), h.div_ceil(8), 1], [w, h, 1]);
        let outputs = &slot.outputs;
        // The table's own length: the buffer is reused and may be longer, and the shader
        // shades a customIndex past `length()` magenta.
        let bound = [
            Bound::AccelRaw(tlas.raw()),
            Bound::Buffer(&outputs[0]),
            Bound::Buffer(&outputs[1]),
            Bound::BufferPrefix(
                slot.instances.as_ref().expect("allocated above"),
                bytes.len() as u64,
            ),
            Bound::Buffer(&outputs[2]),
            Bound::Buffer(&outputs[3]),
        ];
        let tracer = self.tracer.as_mut().expect("tracer lives until drop");
        let g = match tracer {
            Tracer::Query(_) => grid,
            Tracer::Pipeline(_) => rays,
        };
        let passes: Vec<Pass<'_>> = pushes
            .iter()
            .map(|p| Pass {
                push: bytemuck::bytes_of(p),
                grid: g,
            })
            .collect();
        let timer = Some(PassTimer {
            queries: &slot.timer,
            results: &slot.times,
        });
        match tracer {
            Tracer::Query(p) => p.record(&ctx, cmd, &bound, &passes, timer)?,
            Tracer::Pipeline(p) => p.record(&ctx, cmd, &bound, &passes, timer)?,
        }
        slot.frame = Some(cmd.frame());
        slot.taken = false;
        Ok(())
    }

    /// The GPU times (ms) of the three passes of `frame`, once it has completed, without
    /// reading the image back (an engine presents its image; it does not read it back). The
    /// frame's image is dropped: a later [`take`](Self::take) of it returns `None`. `None` as
    /// for [`take`](Self::take).
    pub fn take_times(&mut self, frame: u64, completed: Option<u64>) -> Option<[f64; 3]> {
        let slot = self.completed_slot(frame, completed)?;
        slot.taken = true;
        Some(pass_times(slot))
    }

    /// The frame recorded for `frame`, once it has completed (`completed` is the latest frame
    /// whose submission completed, e.g. `FrameLoop::completed`). Pass times are GPU time
    /// (timestamps).
    ///
    /// `None` while it is in flight, when it was taken already or overwritten by a later
    /// frame, and when its commands never ran: a frame recorded and never submitted (an
    /// abandoned recording), or a `completed` that claims more than the GPU did. Besides
    /// `completed`, the frame's last command, the copy of its pass timestamps, marks them
    /// available where the renderer looks (zeroed when the frame was recorded): a claim
    /// `completed` makes that the GPU has not kept is caught there; `completed` stays what
    /// makes the image's memory safe to read.
    pub fn take(&mut self, frame: u64, completed: Option<u64>) -> Result<Option<Frame>> {
        let Some(slot) = self.completed_slot(frame, completed) else {
            return Ok(None);
        };
        let times = pass_times(slot);
        let (w, h) = slot.size;
        let o = &slot.outputs;
        let f = read_frame(w, h, [&o[0], &o[1], &o[2], &o[3]], times);
        slot.taken = true;
        Ok(Some(f))
    }
}

impl Renderer {
    /// The untaken slot that recorded `frame`, if `completed` says the frame completed and
    /// its timestamps were copied (its commands ran).
    fn completed_slot(
        &mut self,
        frame: u64,
        completed: Option<u64>,
    ) -> Option<&mut crate::slot::RenderSlot> {
        if completed.is_none_or(|c| c < frame) {
            return None;
        }
        self.slots
            .iter_mut()
            .find(|s| s.frame == Some(frame) && !s.taken)
            .filter(|s| read_timer(&s.times, TIMESTAMPS).is_some())
    }
}

/// The passes' GPU times of a completed slot: its timestamps were copied into `times` on the GPU.
fn pass_times(slot: &RenderSlot) -> [f64; 3] {
    let t = read_timer(&slot.times, TIMESTAMPS).unwrap_or_else(|| vec![0; TIMESTAMPS]);
    let ms = |a: usize, b: usize| slot.timer.ticks_to_ms(t[b].saturating_sub(t[a]));
    [ms(0, 1), ms(1, 2), ms(2, 3)]
}
