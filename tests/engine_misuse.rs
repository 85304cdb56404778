//! Adversarial tests of the Vulkan backend's engine-recorded mode (`Recording::Engine`: the
//! engine executes the backend's frame in its own command buffer with `record`, submits it, and
//! reports completion with `frame_done`) and of GPU-resident geometry (`device_vertices`,
//! `device_indices`), as an engine that drives the backend directly might misuse them. Each
//! test passes when the backend does the right thing (a correct result, or a clean typed
//! error) with the validation layer silent, and fails on a defect (validation message, panic
//! inside the library, wrong trace, objects destroyed while a frame in flight uses them).
//!
//! The engine here (`Eng`) is a minimal one on the test context's own device and queue: a
//! command pool, a primary command buffer and a fence per frame in flight, and a "gate" (a
//! timeline semaphore the host signals) that holds a submission back on the GPU, so that "in
//! flight" is deterministic on lavapipe.

mod common;

use common::direct::*;

use std::sync::Arc;
use std::time::Duration;

use glam::Vec3;
use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{
    BufferDesc, FrameCmd, GpuBuffer, GpuGeometry, MemoryKind, TlasRef, VulkanBackend,
    VulkanBackendDesc, VulkanContext, BUILD_INPUT_USAGE,
};
use rtstream::as_manager::backend::{
    AsBackend, BackendError, BackendResult, BlasClass, BlasRefit, GeometryRef, TlasDelta,
    TlasHandle,
};
use rtstream::as_manager::record::TlasInstance;
use rtstream::as_manager::synth::grid_geometry;
use rtstream::as_manager::{DeviceIndices, DeviceVertices, IndexType, VertexFormat};
use rtstream::renderer::{Camera, InstanceShading, RenderDesc, Renderer};

// ---------------------------------------------------------------------------------------------
// Helpers.

/// An engine-recorded backend with `frames_in_flight` frames in flight.
fn engine_backend(ctx: &Arc<VulkanContext>, frames_in_flight: u32) -> VulkanBackend {
    VulkanBackend::new(
        ctx.clone(),
        VulkanBackendDesc::engine_recorded(frames_in_flight),
    )
    .expect("backend")
}

/// Device geometry: `vertices` and `indices`, with `vertex_count` and `triangle_count`.
fn dgeom(
    vertices: DeviceVertices,
    indices: DeviceIndices,
    vertex_count: u32,
    triangle_count: u32,
) -> GeometryRef<'static> {
    GeometryRef {
        vertex_count,
        triangle_count,
        positions: None,
        indices: None,
        device_vertices: Some(vertices),
        device_indices: Some(indices),
        opaque: true,
    }
}

/// (custom index, primitive) per pixel of a 24 x 16 view looking down at the origin from 15 m
/// (a grid of 20 m at y = 0 fills most of it) through `tlas`, which must be complete. Shaded
/// by colour only (device geometry in other formats has no shading buffers).
fn trace_tlas(renderer: &mut Renderer, tlas: TlasRef) -> Vec<(u32, u32)> {
    let table = vec![InstanceShading::colour_only([0.7, 0.7, 0.7, 1.0]); 4];
    let cam = Camera::look_at(Vec3::new(0.0, 15.0, -8.0), Vec3::ZERO, 60f32.to_radians());
    let f = renderer
        .render(tlas, &table, &RenderDesc::new(24, 16, cam))
        .expect("trace without device error");
    f.hits.iter().map(|h| (h.instance, h.primitive)).collect()
}

/// A minimal engine on the context's device and queue: a primary command buffer and a fence
/// per frame in flight (frame `f` uses buffer `f % n`), and a gate that holds submissions back
/// on the GPU until the host opens it. Declare it after the backend: dropped first, it opens
/// the gate and waits for the device, so a failing test never hangs in the backend's drop.
struct Eng {
    ctx: Arc<VulkanContext>,
    queue: vk::Queue,
    pool: vk::CommandPool,
    cmds: Vec<vk::CommandBuffer>,
    fences: Vec<vk::Fence>,
    /// The frame last submitted from each command buffer.
    submitted: Vec<Option<u64>>,
    gate: vk::Semaphore,
}

impl Eng {
    fn new(ctx: &Arc<VulkanContext>, n: u32) -> Eng {
        let dev = ctx.device();
        // The context's own queue (single-threaded test: no concurrent submissions).
        let queue = ctx.as_external().queue;
        // SAFETY: valid device and create-infos; everything is destroyed in Drop.
        unsafe {
            let pool = dev
                .create_command_pool(
                    &vk::CommandPoolCreateInfo::default()
                        .queue_family_index(ctx.queue_family())
                        .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                    None,
                )
                .unwrap();
            let cmds = dev
                .allocate_command_buffers(
                    &vk::CommandBufferAllocateInfo::default()
                        .command_pool(pool)
                        .level(vk::CommandBufferLevel::PRIMARY)
                        .command_buffer_count(n),
                )
                .unwrap();
            let fences = (0..n)
                .map(|_| {
                    dev.create_fence(&vk::FenceCreateInfo::default(), None)
                        .unwrap()
                })
                .collect();
            let mut ty = vk::SemaphoreTypeCreateInfo::default()
                .semaphore_type(vk::SemaphoreType::TIMELINE)
                .initial_value(0);
            let gate = dev
                .create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut ty), None)
                .unwrap();
            Eng {
                ctx: ctx.clone(),
                queue,
                pool,
                cmds,
                fences,
                submitted: vec![None; n as usize],
                gate,
            }
        }
    }

    fn slot(&self, frame: u64) -> usize {
        (frame % self.cmds.len() as u64) as usize
    }

    fn is_done(&self, i: usize) -> bool {
        // SAFETY: our own fence.
        unsafe { self.ctx.device().get_fence_status(self.fences[i]) }.unwrap_or(false)
    }

    /// The latest frame such that every submitted frame up to it completed.
    fn completed(&self) -> Option<u64> {
        let (mut done, mut pending) = (None::<u64>, None::<u64>);
        for (i, f) in self.submitted.iter().enumerate() {
            if let Some(f) = *f {
                if self.is_done(i) {
                    done = Some(done.map_or(f, |d| d.max(f)));
                } else {
                    pending = Some(pending.map_or(f, |p| p.min(f)));
                }
            }
        }
        match pending {
            Some(p) => done.filter(|&d| d < p).or(p.checked_sub(1)),
            None => done,
        }
    }

    /// Waits for frame `frame`'s submission (if it is the last one of its buffer).
    fn wait(&self, frame: u64) {
        let i = self.slot(frame);
        if self.submitted[i].is_some() {
            // SAFETY: our own fence, of a submitted batch.
            unsafe {
                self.ctx
                    .device()
                    .wait_for_fences(&[self.fences[i]], true, u64::MAX)
            }
            .unwrap();
        }
    }

    fn wait_all(&self) {
        for (i, f) in self.submitted.iter().enumerate() {
            if f.is_some() {
                // SAFETY: as in `wait`.
                unsafe {
                    self.ctx
                        .device()
                        .wait_for_fences(&[self.fences[i]], true, u64::MAX)
                }
                .unwrap();
            }
        }
    }

    /// Begins frame `frame`'s command buffer (waiting for its previous submission); not
    /// one-time-submit, so that the engine may submit it again.
    fn begin(&self, frame: u64) -> FrameCmd {
        self.wait(frame);
        let cmd = self.cmds[self.slot(frame)];
        // SAFETY: the buffer's last submission completed (waited above).
        unsafe {
            self.ctx
                .device()
                .reset_command_buffer(cmd, vk::CommandBufferResetFlags::empty())
                .unwrap();
            self.ctx
                .device()
                .begin_command_buffer(cmd, &vk::CommandBufferBeginInfo::default())
                .unwrap();
            // SAFETY: a primary of the context's queue family, recording, outside a render
            // pass; the tests break the submission promises on purpose where they say so.
            FrameCmd::from_engine(cmd, frame, self.completed())
        }
    }

    /// Ends `cmd` (from `begin`).
    fn end(&self, cmd: &FrameCmd) {
        // SAFETY: recording since `begin`.
        unsafe { self.ctx.device().end_command_buffer(cmd.raw()) }.unwrap();
    }

    /// Submits the ended command buffer of frame `frame` (again, if it was already); `gated`
    /// holds it back until `open_gate`.
    fn submit_frame(&mut self, frame: u64, gated: bool) {
        let i = self.slot(frame);
        self.wait(frame);
        let dev = self.ctx.device();
        // SAFETY: the fence is not in use (waited above).
        unsafe { dev.reset_fences(&[self.fences[i]]) }.unwrap();
        let cmds = [vk::CommandBufferSubmitInfo::default().command_buffer(self.cmds[i])];
        let wait = [vk::SemaphoreSubmitInfo::default()
            .semaphore(self.gate)
            .value(1)
            .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)];
        let mut submit = vk::SubmitInfo2::default().command_buffer_infos(&cmds);
        if gated {
            submit = submit.wait_semaphore_infos(&wait);
        }
        // SAFETY: one thread submits to the queue here; every handle is valid.
        unsafe { dev.queue_submit2(self.queue, &[submit], self.fences[i]) }.unwrap();
        self.submitted[i] = Some(frame);
    }

    /// Ends and submits `cmd`.
    fn submit(&mut self, cmd: &FrameCmd, gated: bool) {
        self.end(cmd);
        self.submit_frame(cmd.frame(), gated);
    }

    fn gate_open(&self) -> bool {
        // SAFETY: our own semaphore.
        let v = unsafe { self.ctx.device().get_semaphore_counter_value(self.gate) };
        v != Ok(0)
    }

    fn open_gate(&self) {
        if !self.gate_open() {
            signal(self.ctx.device(), self.gate);
        }
    }
}

/// Signals the gate (value 1).
fn signal(device: &rtstream::as_manager::backend::vulkan::ash::Device, gate: vk::Semaphore) {
    // SAFETY: a timeline semaphore of `device`, signalled once from 0 to 1.
    unsafe {
        device.signal_semaphore(&vk::SemaphoreSignalInfo::default().semaphore(gate).value(1))
    }
    .unwrap();
}

impl Drop for Eng {
    fn drop(&mut self) {
        self.open_gate();
        let dev = self.ctx.device();
        // SAFETY: the device is idle after the wait; the objects are ours.
        unsafe {
            let _ = dev.device_wait_idle();
            for f in &self.fences {
                dev.destroy_fence(*f, None);
            }
            dev.destroy_semaphore(self.gate, None);
            dev.destroy_command_pool(self.pool, None);
        }
    }
}

/// One engine frame: reports what completed, begins `frame`, builds a TLAS of `records`, ends,
/// records into the engine's buffer and submits (`gated`: held back). Returns the TLAS.
fn engine_frame(
    b: &mut VulkanBackend,
    eng: &mut Eng,
    frame: u64,
    records: &[TlasInstance],
    gated: bool,
) -> TlasHandle {
    if frame > 0 {
        eng.wait(frame - 1);
    }
    if let Some(c) = eng.completed() {
        b.frame_done(c);
    }
    b.begin_frame(frame).unwrap();
    let t = b.build_tlas(records, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    let cmd = eng.begin(frame);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, gated);
    t
}

/// Waits for every submission and reports the last frame done.
fn finish(b: &mut VulkanBackend, eng: &Eng) {
    eng.wait_all();
    if let Some(last) = eng.submitted.iter().flatten().max() {
        b.frame_done(*last);
    }
}

/// A frame 0 with a static grid BLAS its TLAS names, freed (last used by frame 0) before
/// `end_frame`; `between` runs after `begin_frame`, before the build. Returns its address.
fn frame0_with_freed_blas(b: &mut VulkanBackend, between: impl FnOnce(&mut VulkanBackend)) -> u64 {
    let g = grid_geometry(16, 20.0);
    b.begin_frame(0).unwrap();
    between(b);
    let x = build_one(b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let address = b.blas_address(x);
    b.build_tlas(&[record(address, 0)], TlasDelta::ALL).unwrap();
    b.free_blas(x, 0);
    address
}

/// Frame 0 builds a static grid `x` and a keeper (so that `x`'s storage block stays), runs to
/// completion and is reported done. Frame 1, begun here, names both in its TLAS and frees `x`
/// (last used by frame 1); `misuse` runs right after `begin_frame(1)`. Frame 1's commands reach
/// `x` through its address only (no handle), so destroying it early shows in the counters (and
/// would corrupt the trace on a real GPU) without lavapipe touching a freed object. Returns
/// `x`'s address; frame 1 is left recording, its TLAS built.
fn frame1_naming_a_freed_blas(
    b: &mut VulkanBackend,
    eng: &mut Eng,
    misuse: impl FnOnce(&mut VulkanBackend),
) -> u64 {
    let g = grid_geometry(16, 20.0);
    b.begin_frame(0).unwrap();
    let x = build_one(b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let keep = build_one(b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [
        record(b.blas_address(x), 0),
        record(b.blas_address(keep), 1),
    ];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let cmd = eng.begin(0);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, false);
    eng.wait(0);
    b.frame_done(0);
    b.begin_frame(1).unwrap();
    misuse(b);
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.free_blas(x, 1);
    records[0].blas_address
}

/// After `begin_frame(frame)` returned `r`: if it began, an empty frame recorded into the
/// engine's buffer and submitted.
fn finish_begun(b: &mut VulkanBackend, eng: &mut Eng, frame: u64, r: &BackendResult<()>) {
    if r.is_ok() {
        b.build_tlas(&[], TlasDelta::ALL).unwrap();
        b.end_frame(frame).unwrap();
        let cmd = eng.begin(frame);
        b.record(&cmd).unwrap();
        eng.submit(&cmd, false);
    }
}

// ---------------------------------------------------------------------------------------------
// 1. `record` twice, never, before `end_frame`, into another frame's command buffer.

#[test]
fn recording_a_frame_twice_is_refused() {
    let ctx = common::context();
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 3);
    let mut d = Defects::default();
    let g = grid_geometry(16, 20.0);
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [record(b.blas_address(a), 0)];
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let cmd = eng.begin(0);
    let first = b.record(&cmd);
    let second = b.record(&cmd);
    eprintln!("record: {first:?}, again: {second:?}");
    d.check(first.is_ok(), format!("the first record failed: {first:?}"));
    d.check(
        second.is_err(),
        "a second record of one frame was accepted (its secondary executes twice)",
    );
    eng.submit(&cmd, false);
    finish(&mut b, &eng);
    let hits = trace_tlas(&mut renderer, b.tlas(tlas).unwrap());
    d.check(
        hits_of(&hits, 0) > 200,
        format!("frame 0 traces its grid: {} pixels", hits_of(&hits, 0)),
    );
    for f in 1..4 {
        engine_frame(&mut b, &mut eng, f, &records, false);
    }
    finish(&mut b, &eng);
    drop(eng);
    drop(b);
    drop(renderer);
    d.validation(&ctx);
    d.assert_none();
}

/// A frame ended and never recorded: the next `begin_frame` is refused, typed, with nothing
/// changed; recording it late (then submitting) lets the engine go on, and it traces right.
#[test]
fn a_frame_never_recorded_blocks_the_next_until_recorded() {
    let ctx = common::context();
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 3);
    let mut d = Defects::default();
    let g = grid_geometry(16, 20.0);
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [record(b.blas_address(a), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let r = b.begin_frame(1);
    eprintln!("begin_frame(1) with frame 0 not recorded: {r:?}");
    d.check(
        matches!(r, Err(BackendError::FrameNotRecorded { frame: 0 })),
        format!("begin_frame(1) with frame 0 unrecorded: {r:?}"),
    );
    // Late: record frame 0, then frame 1 begins.
    let cmd = eng.begin(0);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, false);
    let tlas1 = if r.is_ok() {
        // Accepted: finish frame 1 as begun.
        let t = b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(1).unwrap();
        let cmd = eng.begin(1);
        b.record(&cmd).unwrap();
        eng.submit(&cmd, false);
        t
    } else {
        engine_frame(&mut b, &mut eng, 1, &records, false)
    };
    finish(&mut b, &eng);
    let hits = trace_tlas(&mut renderer, b.tlas(tlas1).unwrap());
    d.check(
        hits_of(&hits, 0) > 200,
        format!(
            "frame 1 traces the grid frame 0 built: {} pixels",
            hits_of(&hits, 0)
        ),
    );
    drop(eng);
    drop(b);
    drop(renderer);
    d.validation(&ctx);
    d.assert_none();
}

#[test]
fn record_before_end_frame_is_refused() {
    let ctx = common::context();
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 3);
    let mut d = Defects::default();
    let g = grid_geometry(16, 20.0);
    // Before the first end_frame: frame 0 records.
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [record(b.blas_address(a), 0)];
    let cmd = eng.begin(0);
    let early = b.record(&cmd);
    eprintln!("record before end_frame(0): {early:?}");
    d.check(
        early.is_err(),
        "record during frame 0 (before end_frame) was accepted",
    );
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let on_time = b.record(&cmd);
    d.check(
        on_time.is_ok(),
        format!("record after end_frame(0): {on_time:?}"),
    );
    eng.submit(&cmd, false);
    // Frame 1: record before its end_frame (frame 0's was taken).
    b.begin_frame(1).unwrap();
    let cmd1 = eng.begin(1);
    let early1 = b.record(&cmd1);
    eprintln!("record before end_frame(1): {early1:?}");
    d.check(
        early1.is_err(),
        "record during frame 1 (before end_frame) was accepted: it executes frame 0's secondary again",
    );
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(1).unwrap();
    if early1.is_err() {
        b.record(&cmd1).unwrap();
    }
    eng.submit(&cmd1, false);
    finish(&mut b, &eng);
    let hits = trace_tlas(&mut renderer, b.tlas(tlas).unwrap());
    d.check(
        hits_of(&hits, 0) > 200,
        format!("frame 0 traces its grid: {} pixels", hits_of(&hits, 0)),
    );
    drop(eng);
    drop(b);
    drop(renderer);
    d.validation(&ctx);
    d.assert_none();
}

/// `record` with a `FrameCmd` that says another frame than the one ended: the engine's frame
/// numbering and the backend's disagree (its `completed` and `frame_done` mean other frames).
#[test]
fn record_into_another_frames_command_buffer_is_refused() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 3);
    b.begin_frame(0).unwrap();
    b.build_tlas(&[], TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let cmd = eng.begin(0);
    // SAFETY: the same recording primary, labelled frame 7.
    let other = unsafe { FrameCmd::from_engine(cmd.raw(), 7, None) };
    let r = b.record(&other);
    eprintln!("record of frame 0 into a FrameCmd of frame 7: {r:?}");
    if r.is_err() {
        b.record(&cmd).unwrap();
    }
    eng.submit(&cmd, false);
    finish(&mut b, &eng);
    drop(eng);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    assert!(
        r.is_err(),
        "record accepted a FrameCmd of frame 7 for frame 0 (FrameCmd::frame is never checked)"
    );
}

// ---------------------------------------------------------------------------------------------
// 2. `frame_done` for frames not yet ended, recorded or submitted.

/// Frame 1 reported done while it is still being recorded; the engine then records it and
/// submits it held back. Frame 2's `begin_frame` must not destroy the BLAS frame 1's TLAS names
/// and frees.
#[test]
fn frame_done_before_the_frame_is_recorded_keeps_its_blas() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 4);
    let mut d = Defects::default();
    let address = frame1_naming_a_freed_blas(&mut b, &mut eng, |b| b.frame_done(1));
    b.end_frame(1).unwrap();
    let cmd = eng.begin(1);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, true);
    let before = b.counters().destroyed;
    let r = b.begin_frame(2);
    eprintln!("begin_frame(2) after frame_done(1) during frame 1: {r:?}");
    d.check(
        b.counters().destroyed == before && b.is_blas_address_retained(address),
        format!(
            "begin_frame(2) destroyed the BLAS frame 1's TLAS names while frame 1 waits on the \
             GPU (destroyed {} -> {}; completed_frame {:?})",
            before,
            b.counters().destroyed,
            b.completed_frame()
        ),
    );
    finish_begun(&mut b, &mut eng, 2, &r);
    eng.open_gate();
    finish(&mut b, &eng);
    drop(eng);
    drop(b);
    d.validation(&ctx);
    d.assert_none();
}

/// The same with the BLAS built by the frame reported done early (its build command names the
/// structure): lavapipe then runs a build into a destroyed acceleration structure.
#[test]
fn frame_done_before_the_frame_is_recorded_keeps_the_blas_it_builds() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 4);
    let mut d = Defects::default();
    let address = frame0_with_freed_blas(&mut b, |_| {});
    b.frame_done(0); // Not ended, not recorded, not submitted.
    b.end_frame(0).unwrap();
    let cmd = eng.begin(0);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, true);
    let before = b.counters().destroyed;
    let r = b.begin_frame(1);
    eprintln!("begin_frame(1) after frame_done(0) during frame 0: {r:?}");
    d.check(
        b.counters().destroyed == before && b.is_blas_address_retained(address),
        format!(
            "begin_frame(1) destroyed frame 0's BLAS while frame 0 waits on the GPU \
             (destroyed {} -> {}; completed_frame {:?})",
            before,
            b.counters().destroyed,
            b.completed_frame()
        ),
    );
    finish_begun(&mut b, &mut eng, 1, &r);
    eng.open_gate();
    finish(&mut b, &eng);
    drop(eng);
    drop(b);
    d.validation(&ctx);
    d.assert_none();
}

/// `frame_done(u64::MAX)` right after `begin_frame(1)` (a garbage value): no panic in the
/// library, and the BLAS frame 1 names and frees stays until frame 1 (held back) ran.
#[test]
fn frame_done_u64_max_right_after_begin_is_harmless() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 4);
    let mut d = Defects::default();
    let address = frame1_naming_a_freed_blas(&mut b, &mut eng, |b| b.frame_done(u64::MAX));
    b.end_frame(1).unwrap();
    let cmd = eng.begin(1);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, true);
    let before = b.counters().destroyed;
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| b.begin_frame(2)));
    let text = r.as_ref().err().map(|p| panic_text(p.as_ref()));
    eprintln!(
        "begin_frame(2) after frame_done(u64::MAX): {:?}",
        r.as_ref().map_err(|_| &text)
    );
    d.check(text.is_none(), format!("begin_frame(2) panicked: {text:?}"));
    d.check(
        b.counters().destroyed == before && b.is_blas_address_retained(address),
        format!(
            "frame 1's BLAS destroyed while frame 1 waits on the GPU (destroyed {} -> {})",
            before,
            b.counters().destroyed
        ),
    );
    eng.open_gate();
    eng.wait_all();
    if let Ok(r) = &r {
        finish_begun(&mut b, &mut eng, 2, r);
        eng.wait_all();
    }
    drop(eng);
    drop(b);
    d.validation(&ctx);
    d.assert_none();
}

/// One frame in flight: frame 0 reported done before it was recorded, then submitted held
/// back. `begin_frame(1)` reuses frame 0's slot (its command buffer, scratch, queries): it must
/// answer `FrameInFlight` instead of resetting a command buffer the GPU has not run yet.
#[test]
fn frame_done_before_the_frame_is_recorded_does_not_reuse_its_slot() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 1);
    let mut eng = Eng::new(&ctx, 4);
    let mut d = Defects::default();
    b.begin_frame(0).unwrap();
    b.frame_done(0);
    b.build_tlas(&[], TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let cmd = eng.begin(0);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, true);
    let r = b.begin_frame(1);
    eprintln!(
        "begin_frame(1), 1 frame in flight, frame 0 held back but reported done early: {r:?}"
    );
    d.check(
        matches!(
            r,
            Err(BackendError::FrameInFlight {
                frame: 1,
                waiting_for: 0
            })
        ),
        format!("begin_frame(1) reused the slot of frame 0, which has not run: {r:?}"),
    );
    finish_begun(&mut b, &mut eng, 1, &r);
    eng.open_gate();
    finish(&mut b, &eng);
    drop(eng);
    drop(b);
    d.validation(&ctx);
    d.assert_none();
}

/// `wait_idle` while frame 1 is ended but not yet recorded (the engine waits for its GPU, say
/// at a loading screen, before recording it): frame 1 has not run, so it is not done. Recorded
/// and submitted (held back) afterwards, the BLAS it names and frees must survive frame 2's
/// `begin_frame`.
#[test]
fn wait_idle_before_the_frame_is_recorded_does_not_mark_it_done() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 2);
    let mut eng = Eng::new(&ctx, 4);
    let mut d = Defects::default();
    let address = frame1_naming_a_freed_blas(&mut b, &mut eng, |_| {});
    b.end_frame(1).unwrap();
    b.wait_idle().unwrap();
    eprintln!(
        "completed_frame after wait_idle with frame 1 unrecorded: {:?}",
        b.completed_frame()
    );
    let cmd = eng.begin(1);
    b.record(&cmd).unwrap();
    eng.submit(&cmd, true);
    let before = b.counters().destroyed;
    let r = b.begin_frame(2);
    eprintln!("begin_frame(2): {r:?}");
    d.check(
        b.counters().destroyed == before && b.is_blas_address_retained(address),
        format!(
            "begin_frame(2) destroyed the BLAS frame 1 names while frame 1 waits on the GPU \
             (wait_idle reported the unrecorded frame 1 done; completed_frame {:?})",
            b.completed_frame()
        ),
    );
    finish_begun(&mut b, &mut eng, 2, &r);
    eng.open_gate();
    finish(&mut b, &eng);
    drop(eng);
    drop(b);
    d.validation(&ctx);
    d.assert_none();
}

// ---------------------------------------------------------------------------------------------
// 3. Three frames in flight: submissions out of order, a frame submitted twice.

/// A grid uploaded to the device (f32x3 positions, u32 indices), as an engine's buffers.
struct DeviceGrid {
    gpu: GpuGeometry,
    vertices: u32,
    triangles: u32,
}

impl DeviceGrid {
    fn new(ctx: &VulkanContext, n: u32, size: f32) -> Self {
        Self {
            gpu: common::grid_on_gpu(ctx, n, size),
            vertices: (n + 1) * (n + 1),
            triangles: 2 * n * n,
        }
    }

    fn v(&self) -> DeviceVertices {
        DeviceVertices {
            address: self.gpu.vertices.address,
            stride: 12,
            format: VertexFormat::F32x3,
            count: self.vertices,
        }
    }

    fn i(&self) -> DeviceIndices {
        DeviceIndices {
            address: self.gpu.indices.address,
            index_type: IndexType::U32,
        }
    }

    fn geometry(&self) -> GeometryRef<'static> {
        dgeom(self.v(), self.i(), self.vertices, self.triangles)
    }
}

/// Unusable device geometry in builds (static and skinned) and refits: each is refused, typed,
/// before anything is recorded. An accepted one is a defect and is never submitted (its frame
/// is aborted: the GPU would read through a null or wrong address).
#[test]
fn unusable_device_geometry_is_refused() {
    let ctx = common::context();
    let grid = DeviceGrid::new(&ctx, 8, 20.0);
    let mut b = backend(&ctx);
    let mut d = Defects::default();
    let (v, i, nv, nt) = (grid.v(), grid.i(), grid.vertices, grid.triangles);
    // (what, geometry, whether the CPU side can tell)
    let cases: Vec<(&str, GeometryRef<'static>, bool)> = vec![
        (
            "count below vertex_count",
            dgeom(DeviceVertices { count: nv - 1, ..v }, i, nv, nt),
            true,
        ),
        (
            "stride 8 below f32x3's 12 bytes",
            dgeom(DeviceVertices { stride: 8, ..v }, i, nv, nt),
            true,
        ),
        (
            "stride 14, not a multiple of f32x3's 4-byte component",
            dgeom(DeviceVertices { stride: 14, ..v }, i, nv, nt),
            true,
        ),
        (
            "vertex address 0",
            dgeom(DeviceVertices { address: 0, ..v }, i, nv, nt),
            true,
        ),
        (
            "vertex address not 4-aligned for f32x3",
            dgeom(
                DeviceVertices {
                    address: v.address + 2,
                    ..v
                },
                i,
                nv,
                nt,
            ),
            true,
        ),
        (
            "index address 0",
            dgeom(v, DeviceIndices { address: 0, ..i }, nv, nt),
            true,
        ),
        (
            "u32 index address not 4-aligned",
            dgeom(
                v,
                DeviceIndices {
                    address: i.address + 2,
                    ..i
                },
                nv,
                nt,
            ),
            true,
        ),
        (
            // The index buffer holds 3 x nt u32 = 6 x nt u16: 4 x nt triangles of u16 read
            // 24 x nt bytes, past its 12 x nt. The backend does not know the buffer's size.
            "u16 indices, triangle_count past the buffer",
            dgeom(
                v,
                DeviceIndices {
                    index_type: IndexType::U16,
                    ..i
                },
                nv,
                nt * 4,
            ),
            false,
        ),
    ];
    let mut frame = 0;
    for (what, g, checkable) in &cases {
        for class in [BlasClass::Static, BlasClass::Skinned] {
            b.begin_frame(frame).unwrap();
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                build_one(&mut b, *g, class)
            }));
            match r {
                Err(p) => {
                    d.check(
                        false,
                        format!(
                            "{class:?} build, {what}: panicked: {}",
                            panic_text(p.as_ref())
                        ),
                    );
                    b.abort_frame();
                    b.begin_frame(frame).unwrap();
                }
                Ok(Err(e)) => eprintln!("{class:?} build, {what}: refused: {e:?}"),
                Ok(Ok(h)) => {
                    eprintln!("{class:?} build, {what}: ACCEPTED (frame aborted, not submitted)");
                    if *checkable {
                        d.check(false, format!("{class:?} build, {what}: accepted"));
                    }
                    b.abort_frame();
                    b.begin_frame(frame).unwrap();
                    b.free_blas(h, frame);
                }
            }
            b.build_tlas(&[], TlasDelta::ALL).unwrap();
            b.end_frame(frame).unwrap();
            frame += 1;
        }
    }
    // Refits of a good skinned device BLAS with unusable poses.
    b.begin_frame(frame).unwrap();
    let s = build_one(&mut b, grid.geometry(), BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    frame += 1;
    let refits: Vec<(&str, DeviceVertices)> = vec![
        ("vertex address 0", DeviceVertices { address: 0, ..v }),
        (
            "stride 8 below f32x3's 12 bytes",
            DeviceVertices { stride: 8, ..v },
        ),
        (
            "stride 14, not a multiple of 4",
            DeviceVertices { stride: 14, ..v },
        ),
        (
            "vertex address not 4-aligned",
            DeviceVertices {
                address: v.address + 2,
                ..v
            },
        ),
    ];
    for (what, pose) in refits {
        b.begin_frame(frame).unwrap();
        let r = b.refit_blases(&[BlasRefit {
            blas: s,
            geometry: dgeom(pose, i, nv, nt),
            rebuild: false,
        }]);
        match r {
            Err(e) => eprintln!("refit, {what}: refused: {e:?}"),
            Ok(()) => {
                eprintln!("refit, {what}: ACCEPTED (frame aborted, not submitted)");
                d.check(false, format!("refit, {what}: accepted"));
                b.abort_frame();
                b.begin_frame(frame).unwrap();
            }
        }
        b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(frame).unwrap();
        frame += 1;
    }
    b.wait_idle().unwrap();
    b.free_blas(s, frame);
    drop(b);
    grid.gpu.destroy(&ctx);
    d.validation(&ctx);
    d.assert_none();
}

// ---------------------------------------------------------------------------------------------
// 5. Refits of a device-geometry skinned BLAS in another format, stride, or from the CPU.

/// f32 -> f16 bits for values exact in f16 (normal or zero).
fn f16_bits(v: f32) -> u16 {
    if v == 0.0 {
        return 0;
    }
    let b = v.to_bits();
    let sign = ((b >> 16) & 0x8000) as u16;
    let exp = ((b >> 23) & 0xff) as i32 - 127 + 15;
    let mant = b & 0x7f_ffff;
    assert!(
        (1..31).contains(&exp) && mant & 0x1fff == 0,
        "{v} is not exact in f16"
    );
    sign | ((exp as u16) << 10) | (mant >> 13) as u16
}

/// Positions in `format` (f32x3 or f16x4), `stride` bytes apart.
fn encode(p: &[[f32; 3]], format: VertexFormat, stride: usize) -> Vec<u8> {
    let mut out = vec![0xABu8; (p.len() * stride).next_multiple_of(4)];
    for (i, v) in p.iter().enumerate() {
        let at = &mut out[i * stride..];
        match format {
            VertexFormat::F32x3 => {
                for k in 0..3 {
                    at[4 * k..4 * k + 4].copy_from_slice(&v[k].to_le_bytes());
                }
            }
            VertexFormat::F16x4 => {
                for k in 0..3 {
                    at[2 * k..2 * k + 2].copy_from_slice(&f16_bits(v[k]).to_le_bytes());
                }
                at[6..8].copy_from_slice(&0u16.to_le_bytes());
            }
            VertexFormat::Snorm16x4 => unreachable!("not used here"),
        }
    }
    out
}

fn upload(ctx: &VulkanContext, bytes: &[u8]) -> GpuBuffer {
    let mut b = ctx
        .create_buffer(&BufferDesc {
            name: "engine pose",
            size: bytes.len() as u64,
            usage: BUILD_INPUT_USAGE,
            memory: MemoryKind::Upload,
        })
        .unwrap();
    b.write(0, bytes);
    b
}

/// A skinned BLAS built from the engine's f32x3 positions (stride 12) and u32 indices, then
/// refitted: f16x4 (another format: the backend rebuilds), f16x4 at stride 16 (another
/// stride), CPU positions (mixing), and the engine's f32x3 again. Each frame traces its pose:
/// "away" (64 m along x, out of view) or "home" (the grid under the camera).
#[test]
fn refits_in_another_format_stride_or_from_the_cpu_trace_their_pose() {
    let ctx = common::context();
    let grid = DeviceGrid::new(&ctx, 16, 20.0);
    let home = grid_geometry(16, 20.0);
    let away: Vec<[f32; 3]> = home
        .positions
        .iter()
        .map(|p| [p[0] + 64.0, p[1], p[2]])
        .collect();
    let poses = [
        (
            "f16x4 stride 8, away",
            upload(&ctx, &encode(&away, VertexFormat::F16x4, 8)),
        ),
        (
            "f16x4 stride 16, home",
            upload(&ctx, &encode(&home.positions, VertexFormat::F16x4, 16)),
        ),
        (
            "f32x3 stride 20, away",
            upload(&ctx, &encode(&away, VertexFormat::F32x3, 20)),
        ),
    ];
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let mut b = backend(&ctx);
    let mut d = Defects::default();
    let (nv, nt) = (grid.vertices, grid.triangles);
    b.begin_frame(0).unwrap();
    let build_g = grid.geometry();
    let build_sizes = b.blas_sizes(&build_g, BlasClass::Skinned);
    let s = build_one(&mut b, build_g, BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    let t = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.wait_idle().unwrap();
    let base = trace_tlas(&mut renderer, b.tlas(t).unwrap());
    assert!(hits_of(&base, 0) > 200, "the grid fills the view");
    let f16_sizes = b.blas_sizes(
        &dgeom(
            DeviceVertices {
                address: poses[0].1.address,
                stride: 8,
                format: VertexFormat::F16x4,
                count: nv,
            },
            grid.i(),
            nv,
            nt,
        ),
        BlasClass::Skinned,
    );
    eprintln!("sizes: f32x3 build {build_sizes:?}, f16x4 {f16_sizes:?}");
    d.check(
        f16_sizes.as_bytes <= build_sizes.as_bytes
            && f16_sizes.build_scratch <= build_sizes.build_scratch,
        format!(
            "a rebuild in f16x4 needs more than the f32x3 build's storage or scratch: {f16_sizes:?} > {build_sizes:?}"
        ),
    );
    // (what, refit geometry, expect "home")
    let steps: Vec<(String, GeometryRef<'_>, bool)> = vec![
        (
            poses[0].0.to_string(),
            dgeom(
                DeviceVertices {
                    address: poses[0].1.address,
                    stride: 8,
                    format: VertexFormat::F16x4,
                    count: nv,
                },
                grid.i(),
                nv,
                nt,
            ),
            false,
        ),
        (
            poses[1].0.to_string(),
            dgeom(
                DeviceVertices {
                    address: poses[1].1.address,
                    stride: 16,
                    format: VertexFormat::F16x4,
                    count: nv,
                },
                grid.i(),
                nv,
                nt,
            ),
            true,
        ),
        (
            "CPU positions, away".into(),
            geom(&away, &home.indices),
            false,
        ),
        ("engine f32x3 stride 12, home".into(), grid.geometry(), true),
        (
            poses[2].0.to_string(),
            dgeom(
                DeviceVertices {
                    address: poses[2].1.address,
                    stride: 20,
                    format: VertexFormat::F32x3,
                    count: nv,
                },
                grid.i(),
                nv,
                nt,
            ),
            false,
        ),
        (
            "CPU positions, home".into(),
            geom(&home.positions, &home.indices),
            true,
        ),
    ];
    for (k, (what, g, at_home)) in steps.into_iter().enumerate() {
        let f = k as u64 + 1;
        b.begin_frame(f).unwrap();
        let r = b.refit_blases(&[BlasRefit {
            blas: s,
            geometry: g,
            rebuild: false,
        }]);
        eprintln!("frame {f}: refit {what}: {r:?}");
        d.check(r.is_ok(), format!("refit {what}: {r:?}"));
        let t = b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(f).unwrap();
        b.wait_idle().unwrap();
        let hits = trace_tlas(&mut renderer, b.tlas(t).unwrap());
        let n = hits_of(&hits, 0);
        eprintln!("frame {f}: {n} pixels hit");
        if r.is_ok() {
            if at_home {
                d.check(
                    hits == base,
                    format!(
                        "after the refit {what} the grid should be home: {n} pixels hit, {} built",
                        hits_of(&base, 0)
                    ),
                );
            } else {
                d.check(
                    n == 0,
                    format!("after the refit {what} the grid should be away: {n} pixels hit"),
                );
            }
        }
    }
    b.wait_idle().unwrap();
    drop(b);
    drop(renderer);
    for (_, p) in poses {
        ctx.destroy_buffer(p);
    }
    grid.gpu.destroy(&ctx);
    d.validation(&ctx);
    d.assert_none();
}

// ---------------------------------------------------------------------------------------------
// 6. Dropping with frames in flight in engine mode.

/// Frames 0..2 submitted (frame 2 held back on the GPU), only frame 0 reported done, frame 3
/// ended but never recorded; the backend (and then the context) dropped. The drop must wait
/// for the frames (no validation message about destroying objects in use, and not before the
/// held-back frame's gate opened) and return once the GPU can finish.
#[test]
fn dropping_the_backend_with_engine_frames_in_flight_waits_for_them() {
    let ctx = common::context();
    let mut b = engine_backend(&ctx, 3);
    let mut eng = Eng::new(&ctx, 4);
    let mut d = Defects::default();
    let g = grid_geometry(48, 20.0);
    let mut records = Vec::new();
    for f in 0..4u64 {
        if f == 3 {
            eng.wait(0);
            b.frame_done(0);
        }
        b.begin_frame(f).unwrap();
        let class = if f % 2 == 0 {
            BlasClass::Static
        } else {
            BlasClass::Skinned
        };
        let h = build_one(&mut b, geom(&g.positions, &g.indices), class).unwrap();
        records.push(record(b.blas_address(h), f as u32 % 4));
        if f == 1 {
            // Freed with frames in flight: retiring at the drop.
            b.free_blas(h, f);
            records.pop();
        }
        b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(f).unwrap();
        if f < 3 {
            let cmd = eng.begin(f);
            b.record(&cmd).unwrap();
            eng.submit(&cmd, f == 2);
        }
    }
    let device = ctx.device().clone();
    let gate = eng.gate;
    // Set just before the gate opens: a drop that returns with it unset did not wait for the
    // held-back frame. (The pause only gives a drop that does not wait the time to return
    // first; a drop that waits passes whatever the machine's load.)
    let opened = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let opener = {
        let opened = opened.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(400));
            opened.store(true, std::sync::atomic::Ordering::SeqCst);
            signal(&device, gate);
        })
    };
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| drop(b)));
    let waited = opened.load(std::sync::atomic::Ordering::SeqCst);
    opener.join().unwrap();
    d.check(
        r.is_ok(),
        format!(
            "the drop panicked: {:?}",
            r.as_ref().err().map(|p| panic_text(p.as_ref()))
        ),
    );
    d.check(
        waited,
        "the drop returned before the held-back frame could run",
    );
    eng.wait_all();
    drop(eng);
    d.validation(&ctx);
    // The context last, with its device.
    let ctx = ctx.into_inner();
    let strong = Arc::strong_count(&ctx);
    d.check(
        strong == 1,
        format!("{strong} owners of the context after every user dropped"),
    );
    drop(ctx);
    d.assert_none();
}
