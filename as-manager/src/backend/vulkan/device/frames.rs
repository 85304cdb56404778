//! A frame's command buffer ([`FrameCmd`]) and the own-submit frame loop ([`FrameLoop`]).
//!
//! Everything rtstream records for a frame (the manager's builds through
//! `VulkanBackend::record`, the renderer's passes through `Renderer::record`) goes into one
//! primary command buffer that someone else submits: the engine, or, for simple users and the
//! examples, a [`FrameLoop`]. A [`FrameCmd`] carries the promises that make recording into it
//! safe, so the recording calls themselves need no `unsafe`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use ash::vk;

use crate::backend::vulkan::device::context::{handle_created, handle_destroyed, VulkanContext};
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

/// A primary command buffer recording frame `frame`, and what is known to be finished.
///
/// Neither `Copy` nor `Clone`: [`FrameLoop::submit`] takes it, so no copy outlives the
/// submission. One from a [`FrameLoop`] also knows its device and whether its command buffer
/// still records it: recording into it once it was submitted, or abandoned by a later
/// [`FrameLoop::begin`], or on another device, is [`VulkanError::FrameCmdUnusable`].
///
/// ```compile_fail,E0382
/// # fn f(frames: &mut rtstream_as_manager::backend::vulkan::FrameLoop) {
/// let cmd = frames.begin(0).unwrap();
/// let kept = cmd; // moves: the FrameCmd is not Copy
/// frames.submit(cmd).unwrap();
/// # }
/// ```
#[derive(Debug)]
pub struct FrameCmd {
    raw: vk::CommandBuffer,
    frame: u64,
    completed: Option<u64>,
    /// The device it belongs to (null: the engine's, taken on trust).
    device: vk::Device,
    /// A loop's command buffer: its state (the ticket of the `begin` recording it, 0 when
    /// none) and this recording's ticket.
    owner: Option<(Arc<AtomicU64>, u64)>,
}

impl FrameCmd {
    /// Wraps the engine's command buffer for frame `frame`; `completed` is the latest frame
    /// whose submission has completed on the GPU (None: none yet).
    ///
    /// # Safety
    /// - `raw` is a primary command buffer of the device the recording objects live on, from a
    ///   pool of the context's queue family, in the recording state and outside a render pass;
    /// - the engine submits it once, in frame order, to a queue of that family (a frame run
    ///   before an earlier one would trace BLASes the earlier one builds; run twice, its
    ///   queries would be written without a reset);
    /// - every frame up to `completed` really has completed on the GPU (and every frame later
    ///   reported through `frame_done` calls).
    pub unsafe fn from_engine(raw: vk::CommandBuffer, frame: u64, completed: Option<u64>) -> Self {
        Self {
            raw,
            frame,
            completed,
            device: vk::Device::null(),
            owner: None,
        }
    }

    /// The raw command buffer (for the engine's own commands).
    pub fn raw(&self) -> vk::CommandBuffer {
        self.raw
    }

    /// The frame it records.
    pub fn frame(&self) -> u64 {
        self.frame
    }

    /// The latest frame known to have completed on the GPU.
    pub fn completed(&self) -> Option<u64> {
        self.completed
    }

    /// Whether frame `frame` has completed.
    pub fn is_done(&self, frame: u64) -> bool {
        self.completed.is_some_and(|c| c >= frame)
    }

    /// Whether its command buffer still records this frame: always for an engine's (its
    /// promise), and for a loop's until it is submitted or abandoned by a later `begin`.
    pub fn is_recording(&self) -> bool {
        self.owner
            .as_ref()
            .is_none_or(|(state, ticket)| state.load(Ordering::Acquire) == *ticket)
    }

    /// Refuses, with [`VulkanError::FrameCmdUnusable`], a command buffer that `ctx` cannot
    /// record into: one of another device, or one no longer recording this frame. Every
    /// recording call checks it before it records anything.
    pub fn check(&self, ctx: &VulkanContext) -> VkResult<()> {
        let why = if self.device != vk::Device::null() && self.device != ctx.device.handle() {
            "belongs to another device"
        } else if !self.is_recording() {
            "is no longer recording it (submitted, or abandoned by a later begin)"
        } else {
            return Ok(());
        };
        Err(VulkanError::FrameCmdUnusable {
            frame: self.frame,
            why,
        })
    }
}

/// The own-submit frame loop: `frames_in_flight` primary command buffers and one timeline
/// semaphore (frame `n` signals `n + 1`). [`begin`](Self::begin) waits only for the frame that
/// used the same command buffer before (`n - frames_in_flight`), never for the GPU as a whole;
/// [`submit`](Self::submit) submits the frame once, without waiting.
#[derive(Debug)]
pub struct FrameLoop {
    pool: vk::CommandPool,
    cmds: Vec<vk::CommandBuffer>,
    timeline: vk::Semaphore,
    /// Frame last submitted from each command buffer (None: never).
    frames: Vec<Option<u64>>,
    /// Each command buffer's state, shared with its `FrameCmd`: the ticket of the `begin`
    /// recording it, 0 when none.
    states: Vec<Arc<AtomicU64>>,
    /// The next `begin`'s ticket (from 1).
    next_ticket: u64,
    recording: Option<u64>,
    ctx: Arc<VulkanContext>,
}

impl FrameLoop {
    /// A loop with `frames_in_flight` (at least 1) frames in flight on `ctx`'s queue.
    pub fn new(ctx: &Arc<VulkanContext>, frames_in_flight: u32) -> VkResult<Self> {
        let n = frames_in_flight.max(1);
        let dev = &ctx.device;
        let info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(ctx.queue_family())
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: valid device and create-info; destroyed in Drop (or by the guard).
        let pool = unsafe { dev.create_command_pool(&info, None) }.op("vkCreateCommandPool")?;
        handle_created();
        let pool = scopeguard::guard(pool, |p| {
            // SAFETY: nothing from it was submitted.
            unsafe { dev.destroy_command_pool(p, None) };
            handle_destroyed();
        });
        let mut type_info = vk::SemaphoreTypeCreateInfo::default()
            .semaphore_type(vk::SemaphoreType::TIMELINE)
            .initial_value(0);
        // SAFETY: as above.
        let timeline = unsafe {
            dev.create_semaphore(
                &vk::SemaphoreCreateInfo::default().push_next(&mut type_info),
                None,
            )
        }
        .op("vkCreateSemaphore")?;
        handle_created();
        let timeline = scopeguard::guard(timeline, |t| {
            // SAFETY: never used.
            unsafe { dev.destroy_semaphore(t, None) };
            handle_destroyed();
        });
        // SAFETY: the pool was just created.
        let cmds = unsafe {
            dev.allocate_command_buffers(
                &vk::CommandBufferAllocateInfo::default()
                    .command_pool(*pool)
                    .level(vk::CommandBufferLevel::PRIMARY)
                    .command_buffer_count(n),
            )
        }
        .op("vkAllocateCommandBuffers")?;
        ctx.set_name(*timeline, "FrameLoop timeline");
        for (i, c) in cmds.iter().enumerate() {
            ctx.set_name(*c, &format!("FrameLoop frame {i}"));
        }
        Ok(Self {
            timeline: scopeguard::ScopeGuard::into_inner(timeline),
            pool: scopeguard::ScopeGuard::into_inner(pool),
            frames: vec![None; cmds.len()],
            states: (0..cmds.len())
                .map(|_| Arc::new(AtomicU64::new(0)))
                .collect(),
            next_ticket: 1,
            cmds,
            recording: None,
            ctx: ctx.clone(),
        })
    }

    /// Frames in flight.
    pub fn frames_in_flight(&self) -> u32 {
        self.cmds.len() as u32
    }

    /// The latest frame whose submission completed (a read of the timeline; no wait).
    pub fn completed(&self) -> VkResult<Option<u64>> {
        // SAFETY: a plain read of our own timeline semaphore.
        let v = unsafe { self.ctx.device.get_semaphore_counter_value(self.timeline) }
            .op("vkGetSemaphoreCounterValue")?;
        Ok(v.checked_sub(1))
    }

    /// Waits until frame `frame` completed: returns at once if no frame at or after it was
    /// submitted; for a frame never submitted (abandoned), waits for the first submitted after
    /// it (the value its submission signals: waiting for a value no submission signals is
    /// legal, but the validation layer reports it).
    pub fn wait(&self, frame: u64) -> VkResult<()> {
        match self.frames.iter().flatten().filter(|&&f| f >= frame).min() {
            Some(&first) => self.ctx.wait_timeline(self.timeline, first + 1),
            None => Ok(()),
        }
    }

    /// Begins frame `frame` (frames strictly increasing): waits for the frame that used its
    /// command buffer before, and returns the command buffer, recording.
    pub fn begin(&mut self, frame: u64) -> VkResult<FrameCmd> {
        // A frame begun and never submitted (its recording failed) is abandoned: its command
        // buffer is reset when next used, and its FrameCmd no longer records.
        if let Some(f) = self.recording.take() {
            self.states[(f % self.cmds.len() as u64) as usize].store(0, Ordering::Release);
        }
        if frame == u64::MAX {
            return Err(VulkanError::Unsupported(
                "FrameLoop::begin(u64::MAX): frame + 1 is its timeline value".into(),
            ));
        }
        // After the last submitted frame (the timeline only goes up; an abandoned frame's
        // number may begin again).
        if let Some(&last) = self.frames.iter().flatten().max().filter(|&&l| frame <= l) {
            return Err(VulkanError::Unsupported(format!(
                "FrameLoop::begin({frame}) after frame {last}: frames must increase"
            )));
        }
        let i = (frame % self.cmds.len() as u64) as usize;
        if let Some(prev) = self.frames[i] {
            if prev >= frame {
                return Err(VulkanError::Unsupported(format!(
                    "FrameLoop::begin({frame}) after frame {prev}: frames must increase"
                )));
            }
            self.wait(prev)?;
        }
        let cmd = self.cmds[i];
        // SAFETY: the command buffer's last submission completed (waited above).
        unsafe {
            self.ctx
                .device
                .reset_command_buffer(cmd, vk::CommandBufferResetFlags::empty())
                .op("vkResetCommandBuffer")?;
            self.ctx
                .device
                .begin_command_buffer(
                    cmd,
                    &vk::CommandBufferBeginInfo::default()
                        .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
                )
                .op("vkBeginCommandBuffer")?;
        }
        let completed = self.completed()?;
        let ticket = self.next_ticket;
        self.next_ticket += 1;
        self.states[i].store(ticket, Ordering::Release);
        self.recording = Some(frame);
        Ok(FrameCmd {
            raw: cmd,
            frame,
            completed,
            device: self.ctx.device.handle(),
            owner: Some((self.states[i].clone(), ticket)),
        })
    }

    /// Ends and submits `cmd` (from this loop's [`begin`](Self::begin), the frame it records
    /// now); signals `frame + 1` when done. Does not wait. Another loop's `FrameCmd`, or one
    /// abandoned by a later `begin`, is [`VulkanError::FrameCmdUnusable`] (and is dropped).
    pub fn submit(&mut self, cmd: FrameCmd) -> VkResult<()> {
        let i = (cmd.frame % self.cmds.len() as u64) as usize;
        let ours = cmd
            .owner
            .as_ref()
            .is_some_and(|(state, _)| Arc::ptr_eq(state, &self.states[i]));
        if !ours || cmd.raw != self.cmds[i] {
            return Err(VulkanError::FrameCmdUnusable {
                frame: cmd.frame,
                why: "is not this loop's",
            });
        }
        if !cmd.is_recording() || self.recording != Some(cmd.frame) {
            return Err(VulkanError::FrameCmdUnusable {
                frame: cmd.frame,
                why: "is no longer recording it (submitted, or abandoned by a later begin)",
            });
        }
        self.recording = None;
        self.states[i].store(0, Ordering::Release);
        // SAFETY: the command buffer is recording (begun by `begin`).
        unsafe { self.ctx.device.end_command_buffer(cmd.raw) }.op("vkEndCommandBuffer")?;
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(cmd.raw)];
        let signal = [vk::SemaphoreSubmitInfo::default()
            .semaphore(self.timeline)
            .value(cmd.frame + 1)
            .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        let submit = [vk::SubmitInfo2::default()
            .command_buffer_infos(&cmds)
            .signal_semaphore_infos(&signal)];
        self.ctx.submit(&submit)?;
        self.frames[i] = Some(cmd.frame);
        Ok(())
    }

    /// Waits for every submitted frame.
    pub fn wait_all(&self) -> VkResult<()> {
        match self.frames.iter().flatten().max() {
            Some(&last) => self.wait(last),
            None => Ok(()),
        }
    }
}

impl Drop for FrameLoop {
    fn drop(&mut self) {
        if let Err(e) = self.wait_all() {
            tracing::error!("FrameLoop drop: waiting for the frames failed: {e}");
            // SAFETY: nothing else to do but wait for the device before destroying.
            let _ = unsafe { self.ctx.device.device_wait_idle() };
        }
        // SAFETY: every submission completed (waited above); the objects are ours.
        unsafe {
            self.ctx.device.destroy_command_pool(self.pool, None);
            self.ctx.device.destroy_semaphore(self.timeline, None);
        }
        handle_destroyed();
        handle_destroyed();
    }
}
