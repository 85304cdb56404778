//! The frame driver shared by the fly-through, the trade-off sweep and the stress examples:
//! world, stream, policies, renders and scoring in one place.
//!
//! Why one file over 600 lines: `run_on` is the frame loop, and a frame's steps (stream, each
//! policy's update and recording, the scored and timed renders, the submission, the maps) read
//! in order in one function; the pieces that stand alone (path, truth, scoring, report, maps)
//! are submodules already, and percentiles come from `rtstream_stats`.
//!
//! One run:
//! - The world is generated from its preset and seed (deterministic), baked to disk once and
//!   streamed from there by loader threads, as a raster engine would stream it
//!   ([`RunConfig::stream`], default radius 1,000 m).
//! - Every policy ([`PolicyKind`]: `managed`, `naive`, `seed`) gets its own manager on its own
//!   [`VulkanBackend`] on the same device, fed the same event stream through its own
//!   [`WorldBridge`]. Sizes are the driver's.
//! - Every `eval_every` frames, each policy's TLAS is rendered and scored against the ground
//!   truth ([`truth::GroundTruth`]: the full world, never what streaming loaded) with the
//!   geometric metrics of [`score`], split by distance band.
//! - [`RunConfig::deterministic`] freezes the cost model, retires at frame minus frames in
//!   flight and applies loader results a fixed number of frames after their request, so every
//!   figure except the timings is identical under any machine load.
//!
//! The result ([`RunReport`]) has a per-frame row per policy ([`FrameRow`], written as CSV) and
//! a summary ([`RunSummary`], serialisable as JSON).

pub mod map;
pub mod path;
pub mod report;
pub mod score;
pub mod truth;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use rtstream_as_manager::backend::vulkan::ash::vk;
use rtstream_as_manager::backend::vulkan::{
    ContextDesc, FrameLoop, Recording, TlasRef, TlasUpdates, Validation, VulkanBackend,
    VulkanBackendDesc, VulkanContext, RECORDED_SETS,
};
use rtstream_as_manager::backend::TlasHandle;
use rtstream_as_manager::{AsManager, Config, FrameInput, MemorySplit, PolicyKind, Viewpoint};
use rtstream_renderer::{side_by_side, Camera, Frame, RenderDesc, Renderer};
use rtstream_stats::Summary;
use rtstream_streaming::{
    bake, generate, read_manifest, GeneratedWorld, StreamConfig, World, WorldPreset,
};

use crate::bridge::{ShadingTable, WorldBridge};
use crate::error::{Error, Result};
pub use path::{CameraPath, PathPoint};
pub use report::{frames_to_coverage, FrameRow, PolicySummary, RunReport, RunSummary};
pub use score::{BandEdges, FrameScore};
use truth::{GroundTruth, TruthKind};

/// What to run.
#[derive(Debug, Clone)]
pub struct RunConfig {
    /// The world (its seed also seeds the camera path).
    pub preset: WorldPreset,
    /// Where the baked world lives (baked there when missing or from another preset).
    pub world_dir: PathBuf,
    /// Frames to run.
    pub frames: u64,
    /// Policies, in the order they are reported.
    pub policies: Vec<PolicyKind>,
    /// The managed policy's configuration; the baselines take its radii and culling, and no
    /// memory budget (they have none).
    pub managed: Config,
    /// Streaming (what a raster engine would load: `load_radius` 1,000 m by default).
    pub stream: StreamConfig,
    /// Score every K-th frame (0: never). Frame 0 is never scored (nothing is built yet).
    pub eval_every: u64,
    /// Image size of scored frames.
    pub size: (u32, u32),
    /// Deterministic mode (see the module docs). Off by default: a real-time run applies
    /// loads as they arrive and learns the device's costs.
    pub deterministic: bool,
    /// Deterministic mode freezes the cost model at the NVIDIA H200 fit
    /// ([`CostModel::nvidia`](rtstream_as_manager::backend::model::CostModel::nvidia)), so the
    /// per-frame GPU budget admits the work an H200 would on any device (lavapipe included)
    /// and runs on both give the same decisions. False keeps `managed.cost_prior`.
    pub gpu_equivalent_costs: bool,
    /// In deterministic mode, loader results are applied this many frames after their request.
    pub stream_delay_frames: u32,
    /// Also score against the all-geometry reference (non-opaque instances as opaque).
    pub all_geometry_reference: bool,
    /// Also run the managed policy with its far field off (`managed-near`), to compare in
    /// the same run.
    pub near_only_too: bool,
    /// How every policy's backend makes its TLAS (default: built every frame).
    pub tlas_updates: TlasUpdates,
    /// Also run the managed policy with its TLAS updated in place between builds
    /// (`managed-tlas-update`: `tlas_updates` if enabled, else `TlasUpdates::ON`), to compare
    /// in the same run.
    pub tlas_updates_too: bool,
    /// Build TLASes with PREFER_FAST_TRACE instead of `VulkanBackendDesc`'s default
    /// (PREFER_FAST_BUILD).
    pub tlas_fast_trace: bool,
    /// Build static BLASes with PREFER_FAST_TRACE instead of `VulkanBackendDesc`'s default
    /// (PREFER_FAST_BUILD).
    pub static_fast_trace: bool,
    /// Output directory for the CSV, summary, pictures and maps (None: write nothing).
    pub out_dir: Option<PathBuf>,
    /// Top-down maps at this many evenly spaced frames.
    pub maps: u32,
    /// Frames in flight per backend.
    pub frames_in_flight: u32,
    /// Render every this many frames on the frame path, unscored, and report frame time
    /// against the passes' GPU time (0: only scored frames are rendered).
    pub render_every: u64,
    /// Render those frames the old, blocking way: wait for the frame, then three passes each
    /// submitted and waited for (for comparison with the pipelined path).
    pub blocking_render: bool,
    /// Validation-layer policy of the device.
    pub validation: Validation,
    /// The stretch of the camera path the run covers, as fractions of it (`(0.0, 1.0)`: the
    /// whole path). A short stretch over many frames is a slow walk.
    pub path_span: (f32, f32),
    /// Teleports instead of a walk: every this many frames the camera jumps to a random
    /// point of the path (seeded by the world's seed) and stays there (None: walk the path).
    pub teleport_every: Option<u64>,
}

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            preset: WorldPreset::default_world(),
            world_dir: PathBuf::from("out/world"),
            frames: 600,
            policies: vec![PolicyKind::Managed, PolicyKind::Naive, PolicyKind::SeedR1R2],
            managed: Config::default(),
            stream: StreamConfig {
                load_radius: 1000.0,
                unload_radius: 1100.0,
                mesh_budget_bytes: 1 << 30,
                ..StreamConfig::default()
            },
            eval_every: 18,
            size: (320, 180),
            deterministic: false,
            stream_delay_frames: 2,
            gpu_equivalent_costs: true,
            all_geometry_reference: true,
            near_only_too: false,
            tlas_updates: TlasUpdates::default(),
            tlas_updates_too: false,
            tlas_fast_trace: false,
            static_fast_trace: false,
            out_dir: None,
            maps: 3,
            frames_in_flight: 2,
            render_every: 0,
            blocking_render: false,
            validation: Validation::Auto,
            path_span: (0.0, 1.0),
            teleport_every: None,
        }
    }
}

/// Where on the path (a fraction) the camera stands after teleport `k` (seeded; teleport 0 is
/// the path's start).
pub fn teleport_fraction(seed: u64, k: u64) -> f32 {
    use rand_xoshiro::rand_core::{RngCore, SeedableRng};
    if k == 0 {
        return 0.0;
    }
    let mut rng = rand_xoshiro::SplitMix64::seed_from_u64(seed);
    let mut z = 0;
    for _ in 0..k {
        z = rng.next_u64();
    }
    (z >> 40) as f32 / (1u64 << 24) as f32
}

/// The short name of a policy, as printed and in JSON.
pub fn policy_name(p: PolicyKind) -> &'static str {
    match p {
        PolicyKind::Managed => "managed",
        PolicyKind::Naive => "naive",
        PolicyKind::SeedR1R2 => "seed",
    }
}

/// The name of the managed policy run with its far field off.
pub const MANAGED_NEAR: &str = "managed-near";

/// The name of the managed policy run with its TLAS updated in place between builds.
pub const MANAGED_TLAS_UPDATE: &str = "managed-tlas-update";

/// Live figures handed to the progress callback after every frame.
#[derive(Debug, Clone)]
pub struct Progress {
    /// The frame just run.
    pub frame: u64,
    /// Frames in the run.
    pub frames: u64,
    /// Levels loaded now.
    pub levels_loaded: usize,
    /// The camera's position this frame.
    pub camera: glam::Vec3,
    /// Per policy: (name, BLAS bytes now, TLAS instances now, last hit mismatch if scored).
    pub policies: Vec<(&'static str, u64, u32, Option<f64>)>,
}

/// A render recorded for scoring, scored once its frame completed.
struct PendingScore {
    frame: u64,
    policy: usize,
    row: usize,
    view: Camera,
    /// customIndex -> instance id at the frame (None: a proxy, or nothing).
    ids: Vec<Option<u32>>,
}

/// The scored renders of a run: those waiting for their frame to complete, the render times
/// of those scored, and the distance bands the scores are split by.
struct Scoring {
    pending: Vec<PendingScore>,
    /// (policy, render ms) of each scored render.
    render_ms: Vec<(usize, f64)>,
    edges: BandEdges,
}

impl Scoring {
    /// Scores the pending renders whose frames completed (`completed`: the latest such frame)
    /// against `cache`'s references, into `rows` and each policy's worst frame.
    fn score_completed(
        &mut self,
        completed: Option<u64>,
        renderers: &mut [Renderer],
        policies: &mut [PolicyRun],
        rows: &mut [FrameRow],
        cache: &ReferenceCache,
    ) -> Result<()> {
        let (ready, wait): (Vec<_>, Vec<_>) = std::mem::take(&mut self.pending)
            .into_iter()
            .partition(|s| completed.is_some_and(|c| c >= s.frame));
        self.pending = wait;
        for s in ready {
            let Some(img) = renderers[s.policy].take(s.frame, completed)? else {
                return Err(Error::InvalidRun(format!(
                    "the render of frame {} was lost (overwritten before it was read)",
                    s.frame
                )));
            };
            self.render_ms.push((s.policy, img.render_ms));
            let p = &mut policies[s.policy];
            for (kind, reference, ref_ids) in &cache.frames[&s.frame] {
                let reference = &**reference;
                let (score, verdicts) = score::score(
                    &img,
                    reference,
                    &s.view,
                    self.edges,
                    |ci| s.ids.get(ci as usize).copied().flatten(),
                    |ci| ref_ids.get(ci as usize).copied(),
                )
                .map_err(Error::InvalidRun)?;
                if *kind == TruthKind::Opaque {
                    rows[s.row].score = Some(score);
                    let worse = p.worst.as_ref().is_none_or(|w| score.hit_mismatch > w.0);
                    if worse {
                        let diff = score::difference_picture(reference, &verdicts);
                        let (w3, pic) = side_by_side(
                            img.width,
                            img.height,
                            &[&img.color, &reference.color, &diff],
                        );
                        p.worst = Some((score.hit_mismatch, s.frame, w3, pic));
                    }
                } else {
                    rows[s.row].score_all_geometry = Some(score);
                }
            }
        }
        Ok(())
    }
}

impl PolicyRun {
    /// What rendering this policy's last frame needs: its TLAS, the shading of its records
    /// and `desc` with the TLAS's primitive bases; None when the TLAS is gone.
    fn render_input(
        &mut self,
        desc: RenderDesc,
    ) -> Option<(TlasRef, rtstream_renderer::ShadingUpdate<'_>, RenderDesc)> {
        let backend = self.manager.backend();
        // Resolved once for the frame: while it resolves, every BLAS its records name is
        // retained, so `shading_geometry` answers for them (`shading_geometry_in` checks the
        // handle for each record).
        let tlas = backend.tlas(self.tlas)?;
        let shading = {
            let _s = tracing::trace_span!("shading_table").entered();
            let changes = self.manager.record_changes();
            self.shading
                .update_changes(&self.bridge, self.manager.records(), changes, |addr| {
                    backend.shading_geometry(addr)
                })
        };
        let desc = RenderDesc {
            primitive_bases: backend.primitive_bases(self.tlas),
            ..desc
        };
        Some((tlas, shading, desc))
    }
}

struct PolicyRun {
    name: &'static str,
    manager: AsManager<VulkanBackend>,
    bridge: WorldBridge,
    /// The last frame's TLAS (its records: `manager.records()`).
    tlas: TlasHandle,
    /// The renderer's shading table, kept across frames (rewritten for each frame's records).
    shading: ShadingTable,
    worst: Option<(f64, u64, u32, Vec<[u8; 4]>)>,
    /// What the BLASes held at the frame of the peak of `blas_bytes` (off the timed path).
    peak_split: Option<MemorySplit>,
}

/// Generates the preset's world and makes sure `dir` holds its bake (a stamp file names the
/// preset; another preset's bake is replaced). Returns the generated world.
pub fn prepare_world(preset: &WorldPreset, dir: &Path) -> Result<GeneratedWorld> {
    let world = generate(preset)?;
    let proxies = rtstream_streaming::proxy::ProxyConfig::default();
    // The stamp names the baked format's version too: a bake of an older format is redone here
    // (reading it would be a `FormatError::Version`), never left for the user to delete.
    let stamp = format!(
        "{} seed={} size={} grid={} instances={} proxies={}x{}/{}/{}-d{} landmarks={} v{} format={}\n",
        preset.name,
        preset.seed,
        preset.size_m,
        preset.grid,
        preset.instances,
        proxies.max_depth,
        proxies.triangles,
        proxies.source_error,
        proxies.method.name(),
        proxies.select_depth,
        proxies.landmark_radius,
        rtstream_streaming::proxy::PROXY_INDEX_VERSION,
        rtstream_streaming::format::VERSION
    );
    let stamp_path = dir.join("preset.txt");
    let current = std::fs::read_to_string(&stamp_path).ok();
    if current.as_deref() != Some(stamp.as_str()) || read_manifest(dir).is_err() {
        tracing::info!(dir = %dir.display(), "baking the world");
        bake(&world, dir)?;
        std::fs::write(&stamp_path, stamp).map_err(|e| Error::Output {
            path: stamp_path.clone(),
            message: e.to_string(),
        })?;
    }
    Ok(world)
}

/// Runs `config` on a new Vulkan context; see the module docs.
pub fn run(config: &RunConfig, progress: &mut dyn FnMut(&Progress)) -> Result<RunReport> {
    let ctx = Arc::new(VulkanContext::new(&ContextDesc {
        validation: config.validation,
        ..ContextDesc::default()
    })?);
    run_on(ctx, config, progress)
}

/// One rendered reference: its kind, the frame, and the world instance id of each customIndex.
type CachedReference = (TruthKind, Arc<Frame>, Arc<Vec<u32>>);

/// Reference frames of a run, kept for further runs over the same world, path, frames and
/// image size (a sweep renders the ground truth once, not once per point).
#[derive(Debug, Default)]
pub struct ReferenceCache {
    key: String,
    frames: std::collections::HashMap<u64, Vec<CachedReference>>,
    build_ms: Vec<f64>,
}

impl ReferenceCache {
    fn key_of(c: &RunConfig) -> String {
        format!(
            "{:?}|{}|{}|{:?}|{}|{}",
            c.preset,
            c.frames,
            c.eval_every,
            c.size,
            c.all_geometry_reference,
            c.stream_delay_frames
        )
    }
}

/// Runs `config` on an existing context.
pub fn run_on(
    ctx: Arc<VulkanContext>,
    config: &RunConfig,
    progress: &mut dyn FnMut(&Progress),
) -> Result<RunReport> {
    run_cached(ctx, config, &mut ReferenceCache::default(), progress)
}

/// Runs `config` on an existing context, taking reference frames from `cache` when it holds
/// them for this world, path and image size (and filling it otherwise).
pub fn run_cached(
    ctx: Arc<VulkanContext>,
    config: &RunConfig,
    cache: &mut ReferenceCache,
    progress: &mut dyn FnMut(&Progress),
) -> Result<RunReport> {
    let key = ReferenceCache::key_of(config);
    if cache.key != key {
        *cache = ReferenceCache {
            key,
            ..ReferenceCache::default()
        };
    }
    if config.policies.is_empty() || config.frames == 0 {
        return Err(Error::InvalidRun("no policy or no frame to run".into()));
    }
    // Before the backends and renderers exist (they were created, then refused).
    if config.frames_in_flight == 0 || config.frames_in_flight > RECORDED_SETS {
        return Err(Error::InvalidRun(format!(
            "frames in flight {} (1 to {RECORDED_SETS})",
            config.frames_in_flight
        )));
    }
    if config.eval_every > 0 || config.render_every > 0 {
        // Before any GPU work: a size the renderer refuses would otherwise fail only at the
        // first render, with the run's buffers still alive.
        let (w, h) = config.size;
        crate::renderer::check_size(w, h).map_err(|e| Error::InvalidRun(e.to_string()))?;
    }
    let started = Instant::now();
    let generated = Arc::new(prepare_world(&config.preset, &config.world_dir)?);
    let truth = GroundTruth::new(generated.clone());
    let stream = StreamConfig {
        apply_after_frames: config.deterministic.then_some(config.stream_delay_frames),
        ..config.stream
    };
    let mut world = World::open(&config.world_dir, stream)?;
    let manifest = world
        .manifest()
        .cloned()
        .ok_or_else(|| Error::InvalidRun("the baked world has no manifest".into()))?;
    let mut path = CameraPath::new(&manifest, config.preset.seed);
    let mut specs: Vec<(PolicyKind, &'static str, bool, TlasUpdates)> = config
        .policies
        .iter()
        .map(|&k| {
            let far = k == PolicyKind::Managed;
            (k, policy_name(k), far, config.tlas_updates)
        })
        .collect();
    if config.near_only_too {
        specs.push((
            PolicyKind::Managed,
            MANAGED_NEAR,
            false,
            config.tlas_updates,
        ));
    }
    if config.tlas_updates_too {
        let on = if config.tlas_updates.enabled {
            config.tlas_updates
        } else {
            TlasUpdates::ON
        };
        specs.push((PolicyKind::Managed, MANAGED_TLAS_UPDATE, true, on));
    }
    const FAST_TRACE: vk::BuildAccelerationStructureFlagsKHR =
        vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
    let mut policies = Vec::new();
    for (kind, name, far, tlas_updates) in specs {
        let mut c = config.managed.clone();
        c.policy = kind;
        c.far_field.enabled &= far;
        c.freeze_cost_model |= config.deterministic;
        if config.deterministic && config.gpu_equivalent_costs {
            c.cost_prior = rtstream_as_manager::backend::model::CostModel::nvidia();
        }
        if kind != PolicyKind::Managed {
            c.memory.blas_bytes = 1 << 50; // the baselines have no budget
        }
        let backend = VulkanBackend::new(
            ctx.clone(),
            VulkanBackendDesc {
                // Every policy's frame work goes into the run's one command buffer per frame.
                recording: Recording::Engine,
                frames_in_flight: config.frames_in_flight,
                deterministic: config.deterministic,
                tlas_updates,
                tlas_flags: if config.tlas_fast_trace {
                    FAST_TRACE
                } else {
                    VulkanBackendDesc::default().tlas_flags
                },
                static_blas_prefer: if config.static_fast_trace {
                    FAST_TRACE
                } else {
                    VulkanBackendDesc::default().static_blas_prefer
                },
                ..VulkanBackendDesc::default()
            },
        )?;
        let far_on = c.far_field.enabled;
        let manager = AsManager::new(c, backend)?;
        let mut bridge = WorldBridge::new(Some(&manifest));
        // The baked world's ids count from 0 over every level's instances.
        bridge.reserve_instances(generated.levels.iter().map(|l| l.instances.len()).sum());
        if let (true, Some(tree)) = (far_on, world.proxy_tree()) {
            bridge.register_proxy_tree(&manager, tree);
        }
        policies.push(PolicyRun {
            name,
            manager,
            bridge,
            tlas: TlasHandle::default(),
            shading: ShadingTable::default(),
            worst: None,
            peak_split: None,
        });
    }
    // One renderer per policy (each keeps its frames in flight), recording into the frame's
    // command buffer; references are rendered apart, blocking, off the frame path.
    let mut renderers = Vec::new();
    if config.eval_every > 0 || config.render_every > 0 {
        // Every customIndex a bridge may hand out (the world's instances and proxies): the
        // instance buffers never grow on the frame path.
        let proxies = world.proxy_tree().map_or(0, |t| t.nodes.len());
        for _ in &policies {
            let mut r = Renderer::new(ctx.clone())?;
            r.reserve_shading(truth.world_instances() + proxies + 1);
            renderers.push(r);
        }
    }
    // The frame loop: one submission per frame holding every policy's work and the scored
    // renders; `begin` waits only for the frame `frames_in_flight` frames back.
    let mut frames = FrameLoop::new(&ctx, config.frames_in_flight)?;
    let mut scoring = Scoring {
        pending: Vec::new(),
        render_ms: Vec::new(),
        edges: BandEdges::new(config.managed.residency.r1, config.managed.residency.r2),
    };
    // Unscored renders on the frame path: (frame, policy) recorded, and the timings.
    let mut pending_renders: Vec<(u64, usize)> = Vec::new();
    let (mut frame_ms, mut passes_ms, mut update0_ms) = (Vec::new(), Vec::new(), Vec::new());
    let map_at: Vec<u64> = (1..=u64::from(config.maps))
        .map(|i| i * config.frames / (u64::from(config.maps) + 1))
        .collect();
    let mut rows: Vec<FrameRow> = Vec::new();
    let mut trail: Vec<Vec3> = Vec::new();
    let mut ever_loaded = vec![false; manifest.levels.len()];
    let mut files = Vec::new();
    // Every timed GPU batch of every policy (`gpu_ops.csv`): what a frame's AS time is made of.
    let mut gpu_ops = String::from("frame,policy,op,items,units,gpu_ms\n");
    for frame in 0..config.frames {
        let (a, b) = config.path_span;
        let t = match config.teleport_every {
            Some(n) => teleport_fraction(config.preset.seed, frame / n.max(1)),
            None => frame as f32 / config.frames.max(1) as f32,
        };
        let cam = path.at_fraction(a + (b - a) * t);
        let frame_start = Instant::now();
        trail.push(cam.position);
        let cams = [rtstream_streaming::StreamFocus::from(cam.position)];
        // Never waits on the loaders, except (deterministic mode) for the loads requested
        // `stream_delay_frames` frames ago.
        let events = world.update(frame, &cams);
        for (i, l) in ever_loaded.iter_mut().enumerate() {
            *l |= world.is_loaded(rtstream_streaming::LevelId(i as u32));
        }
        let time = frame as f32 / 30.0;
        let mcams = [Viewpoint::new(cam.position, cam.forward)];
        let policies_len = policies.len();
        let cmd = frames.begin(frame)?;
        // Read the renders of frames that completed.
        let completed_now = cmd.completed();
        let mut k = 0;
        while k < pending_renders.len() {
            let (f, pi) = pending_renders[k];
            if completed_now.is_some_and(|c| c >= f) {
                // Times only: the frame path presents, it does not read the image back.
                if let Some(t) = renderers[pi].take_times(f, completed_now) {
                    if pi == 0 {
                        passes_ms.push((f, t.iter().sum::<f64>()));
                    }
                }
                pending_renders.swap_remove(k);
            } else {
                k += 1;
            }
        }
        // Score the renders of frames that completed (no wait; before this frame's renders
        // reuse their buffers).
        scoring.score_completed(
            cmd.completed(),
            &mut renderers,
            &mut policies,
            &mut rows,
            cache,
        )?;
        // What has completed: deterministic runs count only the frame `begin` waited for, so
        // that what is freed when does not depend on GPU speed.
        let done = if config.deterministic {
            frame.checked_sub(u64::from(config.frames_in_flight))
        } else {
            cmd.completed()
        };
        for p in policies.iter_mut() {
            if let Some(d) = done {
                p.manager.backend_mut().frame_done(d);
            }
            let max_prims = p.manager.config().build.max_primitives;
            // The bridge's share of the frame path (the profile samples spans that name an
            // update beside the manager's).
            let bridge_span = tracing::trace_span!("bridge_update").entered();
            p.bridge.apply(&p.manager, &events);
            p.bridge.pose_skinned(&p.manager, &world, time, 2);
            drop(bridge_span);
            // Names the policy for a profiler of the manager's spans (examples' `--profile`).
            let _policy = tracing::trace_span!("policy", name = p.name).entered();
            let uploaded = |m: &AsManager<VulkanBackend>| {
                let c = m.backend().counters();
                (
                    c.input_upload_bytes + c.pose_upload_bytes,
                    c.tlas_records_written,
                    c.tlas_updates,
                    c.tlas_slots_joined,
                    c.tlas_slots_misplaced,
                )
            };
            let uploaded_before = uploaded(&p.manager);
            let t = Instant::now();
            let cpu = cpu_time::ThreadTime::now();
            let out = p.manager.update(FrameInput {
                frame,
                cameras: &mcams,
            })?;
            let update_ms = t.elapsed().as_secs_f64() * 1e3;
            let update_cpu_ms = cpu.elapsed().as_secs_f64() * 1e3;
            if rows.len() % policies_len == 0 {
                update0_ms.push((frame, update_ms));
            }
            let row = FrameRow::new(frame, p.name, out.stats, update_ms)
                .with_update_cpu(update_cpu_ms)
                .with_build_budget(max_prims, out.stats);
            p.tlas = out.tlas;
            let uploaded_after = uploaded(&p.manager);
            let mut row = row.with_writes(
                uploaded_after.0 - uploaded_before.0,
                uploaded_after.1 - uploaded_before.1,
            );
            row.tlas_updated = uploaded_after.2 > uploaded_before.2;
            row.tlas_slots_joined = uploaded_after.3 - uploaded_before.3;
            row.tlas_slots_misplaced = uploaded_after.4 - uploaded_before.4;
            if p.peak_split
                .as_ref()
                .is_none_or(|s| row.blas_bytes > s.total.bytes)
            {
                p.peak_split = Some(p.manager.memory_split());
            }
            rows.push(row);
            for m in p.manager.gpu_measurements() {
                gpu_ops.push_str(&format!(
                    "{frame},{},{:?},{},{},{:.5}\n",
                    p.name, m.op, m.items, m.units, m.gpu_ms
                ));
            }
            p.manager.backend_mut().record(&cmd)?;
        }
        let scored = config.eval_every > 0 && frame > 0 && frame % config.eval_every == 0;
        if scored {
            let view = Camera::look_at(cam.position, cam.position + cam.look, 60f32.to_radians());
            let desc = RenderDesc::new(config.size.0, config.size.1, view);
            let kinds: &[TruthKind] = if config.all_geometry_reference {
                &[TruthKind::Opaque, TruthKind::AllGeometry]
            } else {
                &[TruthKind::Opaque]
            };
            if !cache.frames.contains_key(&frame) {
                let mut refs = Vec::new();
                for &kind in kinds {
                    let ts = truth.build(&ctx, kind, time)?;
                    cache.build_ms.push(ts.build_ms);
                    let img = ts.scene.render(&mut renderers[0], &desc)?;
                    ts.scene.destroy(&ctx);
                    refs.push((kind, Arc::new(img), Arc::new(ts.ids)));
                }
                cache.frames.insert(frame, refs);
            }
            let n = policies.len();
            for (pi, p) in policies.iter_mut().enumerate() {
                let Some((tlas, shading, desc)) = p.render_input(desc) else {
                    continue;
                };
                renderers[pi].record_update(&cmd, tlas, shading, &desc)?;
                // The instance behind each customIndex now: the bridge reuses slots later.
                let ids = (0..p.bridge.slot_count())
                    .map(|ci| {
                        p.bridge
                            .slot(ci)
                            .filter(|s| s.proxy.is_none())
                            .map(|s| s.instance.0)
                    })
                    .collect();
                scoring.pending.push(PendingScore {
                    frame,
                    policy: pi,
                    row: rows.len() - n + pi,
                    view,
                    ids,
                });
            }
        }
        let render_now = config.render_every > 0 && frame % config.render_every == 0 && !scored;
        let view = Camera::look_at(cam.position, cam.position + cam.look, 60f32.to_radians());
        let render_desc = RenderDesc::new(config.size.0, config.size.1, view);
        if render_now && !config.blocking_render {
            for (pi, p) in policies.iter_mut().enumerate() {
                // The frame path's rendering work on the host (the profile samples spans
                // that name an update beside the manager's).
                let _s = tracing::trace_span!("record_update").entered();
                let Some((tlas, shading, desc)) = p.render_input(render_desc) else {
                    continue;
                };
                renderers[pi].record_update(&cmd, tlas, shading, &desc)?;
                pending_renders.push((frame, pi));
            }
        }
        frames.submit(cmd)?;
        if render_now && config.blocking_render {
            // The old path: wait for the frame, then three passes, each waited for.
            frames.wait(frame)?;
            for (pi, p) in policies.iter_mut().enumerate() {
                let Some((tlas, shading, desc)) = p.render_input(render_desc) else {
                    continue;
                };
                let img = renderers[pi].render(tlas, shading.table, &desc)?;
                if pi == 0 {
                    passes_ms.push((frame, img.render_ms));
                }
            }
        }
        if render_now {
            frame_ms.push((frame, frame_start.elapsed().as_secs_f64() * 1e3));
        }
        if let (Some(dir), true) = (&config.out_dir, map_at.contains(&frame)) {
            let file = dir.join(format!("map_{frame:05}.png"));
            let p = &policies[0];
            map::draw(
                &file,
                &manifest,
                |l| world.is_loaded(l),
                &p.bridge,
                p.manager.records(),
                &trail,
                cam.position,
                &config.managed,
                config.stream.load_radius,
            )?;
            files.push(file);
        }
        let n = policies.len();
        progress(&Progress {
            frame,
            frames: config.frames,
            levels_loaded: world.stats().loaded_levels,
            camera: cam.position,
            policies: rows[rows.len() - n..]
                .iter()
                .map(|r| {
                    (
                        r.policy,
                        r.blas_bytes,
                        r.tlas_instances,
                        r.score.map(|s| s.hit_mismatch),
                    )
                })
                .collect(),
        });
    }
    frames.wait_all()?;
    let last = config.frames - 1;
    for p in &mut policies {
        p.manager.backend_mut().frame_done(last);
    }
    scoring.score_completed(Some(last), &mut renderers, &mut policies, &mut rows, cache)?;
    drop(frames);
    let never_loaded_instances = truth.instances_outside(TruthKind::Opaque, |i| ever_loaded[i]);
    let validation_messages = ctx.validation_log().failure_count();
    let mut report = RunReport::new(
        config,
        &rows,
        &policies.iter().map(|p| p.name).collect::<Vec<_>>(),
        report::ReferenceInfo {
            instances: truth.instance_count(TruthKind::Opaque),
            all_geometry_instances: truth.instance_count(TruthKind::AllGeometry),
            world_instances: truth.world_instances(),
            never_loaded_instances,
            full_world: true,
            build_ms: Summary::of(cache.build_ms.iter().copied()),
        },
        validation_messages,
        &scoring.render_ms,
        started.elapsed().as_secs_f64(),
        ctx.info().name.clone(),
    );
    for (summary, p) in report.summary.policies.iter_mut().zip(&policies) {
        summary.peak_memory_split = p.peak_split.clone();
    }
    report.rows = rows;
    let st = world.stats();
    (report.summary.lod_reads, report.summary.lod_reads_shared) =
        (st.lod_reads, st.lod_reads_shared);
    if config.render_every > 0 {
        // Steady state: after the first tenth of the run.
        let from = config.frames / 10;
        let later =
            |v: &[(u64, f64)]| Summary::of(v.iter().filter(|(f, _)| *f >= from).map(|(_, x)| *x));
        let rendered: std::collections::HashSet<u64> = frame_ms.iter().map(|(f, _)| *f).collect();
        let updates: Vec<(u64, f64)> = update0_ms
            .into_iter()
            .filter(|(f, _)| rendered.contains(f))
            .collect();
        let (fm, pm) = (later(&frame_ms), later(&passes_ms));
        report.summary.frame_timing = Some(report::FrameTiming {
            mode: if config.blocking_render {
                "blocking"
            } else {
                "pipelined"
            }
            .into(),
            frames_in_flight: config.frames_in_flight,
            size: [config.size.0, config.size.1],
            frame_over_passes_p50: if pm.p50 > 0.0 { fm.p50 / pm.p50 } else { 0.0 },
            frame_ms: fm,
            passes_ms: pm,
            update_ms: later(&updates),
        });
        if let Some(dir) = &config.out_dir {
            // Per frame: the first policy's render passes and the frame time.
            let frame_of: std::collections::HashMap<u64, f64> = frame_ms.iter().copied().collect();
            let mut csv = String::from("frame,passes_ms,frame_ms\n");
            for (f, p) in &passes_ms {
                let t = frame_of.get(f).copied().unwrap_or(f64::NAN);
                csv.push_str(&format!("{f},{p:.4},{t:.4}\n"));
            }
            files.push(write_text(dir, "render_times.csv", &csv)?);
        }
    }
    if let Some(dir) = &config.out_dir {
        files.push(write_text(dir, "gpu_ops.csv", &gpu_ops)?);
        for p in &policies {
            if let Some((_, frame, w3, pic)) = &p.worst {
                let file = dir.join(format!("worst_{}.png", p.name));
                rtstream_renderer::save_rgba_png(&file, *w3, config.size.1, pic)?;
                report.set_worst_frame(p.name, *frame, &file);
                files.push(file);
            }
        }
        files.extend(report.write_files(dir)?);
    }
    report.files = files;
    Ok(report)
}

/// Writes `text` to `dir/name` (making `dir`); the file's path.
fn write_text(dir: &Path, name: &str, text: &str) -> Result<PathBuf> {
    let file = dir.join(name);
    let out = |e: std::io::Error| crate::Error::Output {
        path: file.clone(),
        message: e.to_string(),
    };
    std::fs::create_dir_all(dir).map_err(out)?;
    std::fs::write(&file, text).map_err(out)?;
    Ok(file)
}
