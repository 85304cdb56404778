//! A frame's command buffer ([`FrameCmd`]) and the own-submit frame loop ([`FrameLoop`]).
//!
//! Everything rtstream records for a frame (the manager's builds through
//! `VulkanBackend::record`, the renderer's passes through `Renderer::record`) goes into one
//! primary command buffer that someone else submits: the engine, or, for simple users and the
//! examples, a [`FrameLoop`]. A [`FrameCmd`] carries the promises that make recording into it
//! safe, so the recording calls themselves need no `unsafe`.

use std::sync::Arc;

use ash::vk;

use crate::backend::vulkan::device::context::{handle_created, handle_destroyed, VulkanContext};
use crate::backend::vulkan::error::{VkResult, VkResultExt, VulkanError};

/// A primary command buffer recording frame `frame`, and what is known to be finished.
#[derive(Debug, Clone, Copy)]
pub struct FrameCmd {
    raw: vk::CommandBuffer,
    frame: u64,
    completed: Option<u64>,
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

    /// Waits until frame `frame` completed (returns at once if it has, or was never submitted).
    pub fn wait(&self, frame: u64) -> VkResult<()> {
        let submitted = self.frames.iter().flatten().any(|&f| f >= frame);
        if !submitted {
            return Ok(());
        }
        self.ctx.wait_timeline(self.timeline, frame + 1)
    }

    /// Begins frame `frame` (frames strictly increasing): waits for the frame that used its
    /// command buffer before, and returns the command buffer, recording.
    pub fn begin(&mut self, frame: u64) -> VkResult<FrameCmd> {
        // A frame begun and never submitted (its recording failed) is abandoned: its command
        // buffer is reset when next used.
        self.recording = None;
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
        self.recording = Some(frame);
        let completed = self.completed()?;
        Ok(FrameCmd {
            raw: cmd,
            frame,
            completed,
        })
    }

    /// Ends and submits `cmd` (from [`begin`](Self::begin)); signals `frame + 1` when done. Does
    /// not wait.
    pub fn submit(&mut self, cmd: FrameCmd) -> VkResult<()> {
        if self.recording != Some(cmd.frame) {
            return Err(VulkanError::Unsupported(format!(
                "FrameLoop::submit of frame {} which is not the one recording",
                cmd.frame
            )));
        }
        self.recording = None;
        let i = (cmd.frame % self.cmds.len() as u64) as usize;
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
