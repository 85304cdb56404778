//! What a run reports: per-frame rows (CSV) and a summary (JSON), both serde-serialised.
//!
//! Why one file over 600 lines: the row and summary types are the CSV and JSON schemas, each
//! defined once with its serde derive, and the summary is computed from all of them.

use std::path::{Path, PathBuf};

use rtstream_as_manager::{FrameStats, MemorySplit};
use rtstream_stats::Summary;
use serde::Serialize;

use super::score::{BandEdges, FrameScore};
use super::RunConfig;
use crate::error::{Error, Result};

/// One policy's figures of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRow {
    /// Frame number.
    pub frame: u64,
    /// Policy name (`managed`, `naive`, `seed`).
    pub policy: &'static str,
    /// Built BLASes.
    pub blas_count: u32,
    /// Bytes of built BLASes (driver sizes, compacted where compacted).
    pub blas_bytes: u64,
    /// Bytes of freed BLASes a frame in flight may still use.
    pub retiring_bytes: u64,
    /// The policy's memory budget.
    pub memory_budget: u64,
    /// TLAS instances.
    pub tlas_instances: u32,
    /// Instances with a BLAS that culling left out of the TLAS.
    pub culled: u32,
    /// BLAS builds this frame.
    pub builds: u32,
    /// Triangles built this frame.
    pub build_primitives: u64,
    /// Skinned refits this frame.
    pub refits: u32,
    /// Skinned rebuilds this frame (refit quality past its bound).
    pub rebuilds: u32,
    /// Triangles refitted this frame.
    pub refit_primitives: u64,
    /// Worst measured refit quality this frame (SAH-cost ratio to a fresh build; 1 = fresh).
    pub worst_refit_quality: f32,
    /// Compactions this frame.
    pub compactions: u32,
    /// Memory evictions this frame.
    pub evictions: u32,
    /// Far-field proxy records in the TLAS.
    pub proxy_instances: u32,
    /// Bytes of those proxies' BLASes.
    pub proxy_blas_bytes: u64,
    /// Far-field leaf groups whose detail a proxy stands for (a change marks a hand-over).
    pub far_groups_covered: u32,
    /// LOD fallbacks for memory this frame.
    pub lod_fallbacks: u32,
    /// Builds refused for memory (see `FrameStats::memory_refused`).
    pub memory_refused: u32,
    /// Unculled instances within r1 (managed policy).
    pub within_r1: u32,
    /// Of those, instances short of their target LOD (0: full coverage).
    pub short_of_target: u32,
    /// The build budget in triangles.
    pub build_budget: u64,
    /// Whether this frame's admitted builds exceeded the build budget (allowed only for one
    /// oversized item alone).
    pub over_build_budget: bool,
    /// Far-field landmark records in the TLAS.
    pub landmark_instances: u32,
    /// Landmark candidates looked at this frame.
    pub landmarks_examined: u32,
    /// Queued landmark candidates found still inside their band (they only waited again).
    pub landmarks_waited: u32,
    /// Bytes of new geometry (vertices, indices, skinned poses) copied from the CPU into
    /// upload buffers by this frame's `update` (the copies `update`'s time includes).
    pub geometry_upload_bytes: u64,
    /// TLAS instance records the backend wrote this frame (the others were unchanged in the
    /// frame slot's buffer; see `TlasDelta`).
    pub tlas_records_written: u64,
    /// Wall time of `update` (policy and Vulkan recording), ms.
    pub update_ms: f64,
    /// CPU time of the thread that called `update`, during it, ms: the wall time less what
    /// the thread waited for (the scheduler giving its core to another process, page faults
    /// served from disk). Work `update` hands to rayon's pool (record assembly above
    /// `AssemblyConfig::parallel_threshold` records) is not in it.
    pub update_cpu_ms: f64,
    /// GPU acceleration-structure ms measured by the backend (received this frame).
    pub gpu_as_ms: f64,
    /// Of `gpu_as_ms`, the TLAS's build or update.
    pub gpu_tlas_ms: f64,
    /// The backend updated this frame's TLAS from the last frame's instead of building it.
    pub tlas_updated: bool,
    /// With TLAS updates on: records that took an instance slot another record held (see
    /// `VulkanCounters::tlas_slots_joined`).
    pub tlas_slots_joined: u64,
    /// Of them, those placed away from where they stand.
    pub tlas_slots_misplaced: u64,
    /// Error against the opaque ground truth, on scored frames.
    pub score: Option<FrameScore>,
    /// Error against the all-geometry ground truth, on scored frames.
    pub score_all_geometry: Option<FrameScore>,
}

impl FrameRow {
    /// A row from a frame's stats.
    pub fn new(frame: u64, policy: &'static str, s: &FrameStats, update_ms: f64) -> Self {
        Self {
            frame,
            policy,
            blas_count: s.blas_count,
            blas_bytes: s.blas_bytes,
            retiring_bytes: s.retiring_bytes,
            memory_budget: s.memory_budget,
            tlas_instances: s.tlas_instances,
            culled: s.culled,
            builds: s.builds,
            build_primitives: s.build_primitives,
            refits: s.refits,
            rebuilds: s.rebuilds,
            refit_primitives: s.refit_primitives,
            worst_refit_quality: s.worst_refit_quality,
            compactions: s.compactions,
            evictions: s.evictions,
            proxy_instances: s.proxy_instances,
            proxy_blas_bytes: s.proxy_blas_bytes,
            far_groups_covered: s.far_groups_covered,
            lod_fallbacks: s.lod_fallbacks,
            memory_refused: s.memory_refused,
            within_r1: s.within_r1,
            short_of_target: s.short_of_target,
            landmark_instances: s.landmark_instances,
            landmarks_examined: s.landmarks_examined,
            landmarks_waited: s.landmarks_waited,
            geometry_upload_bytes: 0,
            tlas_records_written: 0,
            build_budget: u64::MAX,
            over_build_budget: false,
            update_ms,
            update_cpu_ms: update_ms,
            gpu_as_ms: s.measured_gpu_ms,
            gpu_tlas_ms: s.measured_tlas_ms,
            tlas_updated: false,
            tlas_slots_joined: 0,
            tlas_slots_misplaced: 0,
            score: None,
            score_all_geometry: None,
        }
    }

    /// Sets the CPU time of `update`'s thread during it (see `update_cpu_ms`).
    pub fn with_update_cpu(mut self, ms: f64) -> Self {
        self.update_cpu_ms = ms;
        self
    }

    /// Sets the build budget the frame ran under and whether its builds exceeded it (one
    /// oversized item admitted alone does not).
    pub fn with_build_budget(mut self, max_primitives: u64, s: &FrameStats) -> Self {
        self.build_budget = max_primitives;
        self.over_build_budget =
            s.build_primitives > max_primitives && !(s.oversized_admitted && s.builds == 1);
        self
    }

    /// Sets the bytes of new geometry this frame's `update` copied and the TLAS records it
    /// wrote.
    pub fn with_writes(mut self, geometry_bytes: u64, tlas_records: u64) -> Self {
        self.geometry_upload_bytes = geometry_bytes;
        self.tlas_records_written = tlas_records;
        self
    }

    /// Whether the policy's BLAS memory (retiring included) exceeded its budget.
    pub fn over_budget(&self) -> bool {
        self.blas_bytes + self.retiring_bytes > self.memory_budget
    }
}

/// The flat CSV form of a row.
#[derive(Debug, Serialize)]
struct CsvRow {
    frame: u64,
    policy: &'static str,
    blas_count: u32,
    blas_bytes: u64,
    retiring_bytes: u64,
    over_budget: bool,
    tlas_instances: u32,
    builds: u32,
    build_primitives: u64,
    refits: u32,
    compactions: u32,
    evictions: u32,
    proxy_instances: u32,
    proxy_blas_bytes: u64,
    far_groups_covered: u32,
    lod_fallbacks: u32,
    memory_refused: u32,
    within_r1: u32,
    short_of_target: u32,
    over_build_budget: bool,
    landmark_instances: u32,
    landmarks_examined: u32,
    landmarks_waited: u32,
    geometry_upload_bytes: u64,
    tlas_records_written: u64,
    update_ms: f64,
    update_cpu_ms: f64,
    gpu_as_ms: f64,
    gpu_tlas_ms: f64,
    tlas_updated: bool,
    tlas_slots_joined: u64,
    tlas_slots_misplaced: u64,
    hit_mismatch: Option<f64>,
    identity_mismatch: Option<f64>,
    shadow_mismatch: Option<f64>,
    ao_difference: Option<f64>,
    psnr_db: Option<f64>,
    band0_hit_mismatch: Option<f64>,
    band1_hit_mismatch: Option<f64>,
    band2_hit_mismatch: Option<f64>,
    band3_hit_mismatch: Option<f64>,
    all_geometry_hit_mismatch: Option<f64>,
    all_geometry_shadow_mismatch: Option<f64>,
}

/// Error of one distance band over the scored frames.
#[derive(Debug, Clone, Serialize)]
pub struct BandSummary {
    /// The band, e.g. "250-1000m".
    pub band: String,
    /// Mean share of the frame's pixels that fall in the band.
    pub pixel_share: f64,
    /// Mean share of the frame's pixels mismatched in this band (sums over bands to the
    /// frame's hit mismatch).
    pub hit_mismatch_mean: f64,
    /// Mismatched pixels of the band over its pixels (pooled over frames).
    pub hit_mismatch_in_band: f64,
    /// Shadow mismatch within the band (pooled over its agreeing hits).
    pub shadow_mismatch_in_band: f64,
}

/// Error figures over the scored frames against one reference.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ErrorSummary {
    /// Geometric hit mismatch per frame.
    pub hit_mismatch: Summary,
    /// Instance-identity mismatch per frame.
    pub identity_mismatch: Summary,
    /// Shadow mismatch per frame.
    pub shadow_mismatch: Summary,
    /// AO difference per frame.
    pub ao_difference: Summary,
    /// PSNR per frame, dB.
    pub psnr_db: Summary,
    /// Frame with the largest hit mismatch.
    pub worst_frame: Option<u64>,
}

impl ErrorSummary {
    fn of<'a>(scores: impl Iterator<Item = (u64, &'a FrameScore)> + Clone) -> Self {
        let worst = scores
            .clone()
            .max_by(|a, b| a.1.hit_mismatch.total_cmp(&b.1.hit_mismatch))
            .map(|(f, _)| f);
        Self {
            hit_mismatch: Summary::of(scores.clone().map(|(_, s)| s.hit_mismatch)),
            identity_mismatch: Summary::of(scores.clone().map(|(_, s)| s.identity_mismatch)),
            shadow_mismatch: Summary::of(scores.clone().map(|(_, s)| s.shadow_mismatch)),
            ao_difference: Summary::of(scores.clone().map(|(_, s)| s.ao_difference)),
            psnr_db: Summary::of(scores.map(|(_, s)| s.psnr_db)),
            worst_frame: worst,
        }
    }
}

/// One policy over the run (the keys of `--json`).
#[derive(Debug, Clone, Serialize)]
pub struct PolicySummary {
    /// `managed`, `naive` or `seed`.
    pub policy: &'static str,
    /// The backend and device, e.g. "vulkan (llvmpipe ...)".
    pub backend: String,
    /// Peak bytes of built BLASes.
    pub peak_blas_bytes: u64,
    /// 95th percentile of BLAS bytes over frames.
    pub p95_blas_bytes: u64,
    /// Peak built BLASes.
    pub peak_blas_count: u32,
    /// What the BLASes were for at the first frame of the peak of `blas_bytes`
    /// ([`AsManager::memory_split`](rtstream_as_manager::AsManager::memory_split)).
    pub peak_memory_split: Option<MemorySplit>,
    /// Peak TLAS instances.
    pub peak_tlas_instances: u32,
    /// Peak far-field proxy records in the TLAS.
    pub peak_proxy_instances: u32,
    /// Peak bytes of the proxies' BLASes in the TLAS.
    pub peak_proxy_blas_bytes: u64,
    /// 95th percentile of TLAS instances.
    pub p95_tlas_instances: u32,
    /// `update` wall time (policy and Vulkan recording), median.
    pub update_ms_p50: f64,
    /// `update` wall time, 99th percentile.
    pub update_ms_p99: f64,
    /// CPU time of the thread that called `update`, during it (`FrameRow::update_cpu_ms`),
    /// median: on a shared machine, less of the other processes' load.
    pub update_cpu_ms_p50: f64,
    /// CPU time of the thread that called `update`, during it, 99th percentile.
    pub update_cpu_ms_p99: f64,
    /// Peak far-field landmark records in the TLAS.
    pub peak_landmark_instances: u32,
    /// Landmark candidates looked at per frame, median (the landmarks are kept incrementally).
    pub landmarks_examined_p50: f64,
    /// Landmark candidates looked at per frame, 99th percentile.
    pub landmarks_examined_p99: f64,
    /// New geometry copied from the CPU per frame (vertices, indices, skinned poses), mean MB
    /// (`update`'s time includes these copies; the examples' `--profile` shows them apart).
    pub geometry_upload_mb_per_frame: f64,
    /// TLAS instance records written over those built from, over the run (1: every record
    /// every frame; the landmarks' records persist in the frame slots' buffers).
    pub tlas_records_written_share: f64,
    /// GPU acceleration-structure ms per frame, median.
    pub gpu_as_ms_p50: f64,
    /// GPU acceleration-structure ms per frame, 99th percentile.
    pub gpu_as_ms_p99: f64,
    /// Of it, the TLAS's build or update, median and 99th percentile.
    pub gpu_tlas_ms_p50: f64,
    /// (See `gpu_tlas_ms_p50`.)
    pub gpu_tlas_ms_p99: f64,
    /// Share of the frames whose TLAS was updated from the last frame's (`TlasUpdates`).
    pub tlas_update_share: f64,
    /// Render time of the scored frames, median ms.
    pub render_ms_p50: f64,
    /// BLAS builds per frame, mean.
    pub builds_per_frame: f64,
    /// Frames whose BLAS memory (retiring included) exceeded the policy's budget.
    pub over_budget_frames: u64,
    /// Mean geometric hit mismatch against the opaque ground truth.
    pub hit_mismatch_mean: f64,
    /// Its per-frame 95th percentile.
    pub hit_mismatch_p95: f64,
    /// Mean shadow mismatch (over agreeing hits).
    pub shadow_mismatch_mean: f64,
    /// Its per-frame 95th percentile.
    pub shadow_mismatch_p95: f64,
    /// Error per distance band of the reference hit.
    pub mismatch_by_band: Vec<BandSummary>,
    /// Every error figure against the opaque ground truth.
    pub error: ErrorSummary,
    /// The same against the all-geometry ground truth (non-opaque as opaque), if scored.
    pub error_all_geometry: Option<ErrorSummary>,
    /// The worst frame's picture (managed | reference | difference), if written.
    pub worst_frame_png: Option<PathBuf>,
    /// Validation messages of the run (the policies share a device: the same number).
    pub validation_messages: u64,
}

/// The ground truth of the run.
#[derive(Debug, Clone, Serialize)]
pub struct ReferenceInfo {
    /// Instances in the opaque reference.
    pub instances: usize,
    /// Instances in the all-geometry reference.
    pub all_geometry_instances: usize,
    /// Instances in the world.
    pub world_instances: usize,
    /// Opaque reference instances in levels that streaming never loaded during the run.
    pub never_loaded_instances: usize,
    /// Built from the whole world (always true: never from what streaming loaded).
    pub full_world: bool,
    /// Build time of one reference scene, ms.
    pub build_ms: Summary,
}

/// The summary of a run (`summary.json`, and the last stdout line with `--json`).
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    /// Frames run.
    pub frames: u64,
    /// World and path seed.
    pub seed: u64,
    /// World preset.
    pub preset: String,
    /// Device the run used.
    pub device: String,
    /// Deterministic mode.
    pub deterministic: bool,
    /// Streaming load radius, metres.
    pub stream_radius: f32,
    /// Frames scored.
    pub evaluated_frames: usize,
    /// Image size of scored frames.
    pub size: [u32; 2],
    /// Distance bands (metres of ray distance).
    pub bands: [String; 4],
    /// The ground truth.
    pub reference: ReferenceInfo,
    /// One entry per policy.
    pub policies: Vec<PolicySummary>,
    /// Validation messages of the run.
    pub validation_messages: u64,
    /// Wall time of the run, seconds.
    pub seconds: f64,
    /// Frame timing when frames were rendered on the frame path (`RunConfig::render_every`).
    pub frame_timing: Option<FrameTiming>,
    /// Baked mesh LODs the loaders read from the mesh library (`StreamStats::lod_reads`).
    pub lod_reads: u64,
    /// LOD loads answered with a LOD still held instead of a read
    /// (`StreamStats::lod_reads_shared`).
    pub lod_reads_shared: u64,
}

/// Wall time per frame against the GPU time of its render passes, over the frames rendered on
/// the frame path (`RunConfig::render_every`), after the first tenth of the run.
#[derive(Debug, Clone, Serialize)]
pub struct FrameTiming {
    /// "pipelined" (one submission per frame, no wait per pass) or "blocking" (wait for the
    /// frame, then three passes each submitted and waited for).
    pub mode: String,
    /// Frames in flight of the pipelined mode.
    pub frames_in_flight: u32,
    /// Rendered image size.
    pub size: [u32; 2],
    /// Wall time of a frame (streaming, every policy's update and recording, rendering).
    pub frame_ms: Summary,
    /// The three passes' time: GPU timestamps (pipelined) or submit-to-completion wall time of
    /// each pass (blocking).
    pub passes_ms: Summary,
    /// The first policy's `update` (CPU, recording included).
    pub update_ms: Summary,
    /// Median frame time over median pass time (1.0: the frame costs what its passes cost).
    pub frame_over_passes_p50: f64,
}

/// Rows and summary of a run, and the files written.
#[derive(Debug, Clone)]
pub struct RunReport {
    /// The summary.
    pub summary: RunSummary,
    /// Every policy's row of every frame, in frame order.
    pub rows: Vec<FrameRow>,
    /// Files written.
    pub files: Vec<PathBuf>,
}

fn band_summaries(scores: &[&FrameScore], edges: BandEdges) -> Vec<BandSummary> {
    let names = edges.names();
    let n = scores.len().max(1) as f64;
    (0..4)
        .map(|b| {
            let share = |f: &dyn Fn(&FrameScore) -> u64| {
                scores
                    .iter()
                    .map(|s| f(s) as f64 / s.pixels.max(1) as f64)
                    .sum::<f64>()
                    / n
            };
            let total = |f: &dyn Fn(&FrameScore) -> u64| scores.iter().map(|s| f(s)).sum::<u64>();
            let pixels = total(&|s| s.bands[b].pixels);
            let agreeing = total(&|s| s.bands[b].agreeing_hits);
            BandSummary {
                band: names[b].clone(),
                pixel_share: share(&|s| s.bands[b].pixels),
                hit_mismatch_mean: share(&|s| s.bands[b].hit_mismatched),
                hit_mismatch_in_band: total(&|s| s.bands[b].hit_mismatched) as f64
                    / pixels.max(1) as f64,
                shadow_mismatch_in_band: total(&|s| s.bands[b].shadow_mismatched) as f64
                    / agreeing.max(1) as f64,
            }
        })
        .collect()
}

impl RunReport {
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        config: &RunConfig,
        rows: &[FrameRow],
        policies: &[&'static str],
        reference: ReferenceInfo,
        validation_messages: u64,
        render_ms: &[(usize, f64)],
        seconds: f64,
        device: String,
    ) -> Self {
        let edges = BandEdges::new(config.managed.residency.r1, config.managed.residency.r2);
        let mut summaries = Vec::new();
        let mut evaluated = 0;
        for (pi, &name) in policies.iter().enumerate() {
            let mine: Vec<&FrameRow> = rows.iter().filter(|r| r.policy == name).collect();
            let bytes = Summary::of(mine.iter().map(|r| r.blas_bytes as f64));
            let tlas = Summary::of(mine.iter().map(|r| f64::from(r.tlas_instances)));
            let update = Summary::of(mine.iter().map(|r| r.update_ms));
            let update_cpu = Summary::of(mine.iter().map(|r| r.update_cpu_ms));
            let gpu = Summary::of(mine.iter().map(|r| r.gpu_as_ms));
            let gpu_tlas = Summary::of(mine.iter().map(|r| r.gpu_tlas_ms));
            let examined = Summary::of(mine.iter().map(|r| f64::from(r.landmarks_examined)));
            let scored: Vec<(u64, &FrameScore)> = mine
                .iter()
                .filter_map(|r| r.score.as_ref().map(|s| (r.frame, s)))
                .collect();
            evaluated = evaluated.max(scored.len());
            let all: Vec<(u64, &FrameScore)> = mine
                .iter()
                .filter_map(|r| r.score_all_geometry.as_ref().map(|s| (r.frame, s)))
                .collect();
            let error = ErrorSummary::of(scored.iter().copied());
            let only: Vec<&FrameScore> = scored.iter().map(|(_, s)| *s).collect();
            summaries.push(PolicySummary {
                policy: name,
                backend: format!("vulkan ({device})"),
                peak_blas_bytes: mine.iter().map(|r| r.blas_bytes).max().unwrap_or(0),
                p95_blas_bytes: bytes.p95 as u64,
                peak_blas_count: mine.iter().map(|r| r.blas_count).max().unwrap_or(0),
                peak_memory_split: None,
                peak_tlas_instances: mine.iter().map(|r| r.tlas_instances).max().unwrap_or(0),
                peak_proxy_instances: mine.iter().map(|r| r.proxy_instances).max().unwrap_or(0),
                peak_proxy_blas_bytes: mine.iter().map(|r| r.proxy_blas_bytes).max().unwrap_or(0),
                p95_tlas_instances: tlas.p95 as u32,
                update_ms_p50: update.p50,
                update_ms_p99: update.p99,
                update_cpu_ms_p50: update_cpu.p50,
                update_cpu_ms_p99: update_cpu.p99,
                peak_landmark_instances: mine
                    .iter()
                    .map(|r| r.landmark_instances)
                    .max()
                    .unwrap_or(0),
                landmarks_examined_p50: examined.p50,
                landmarks_examined_p99: examined.p99,
                geometry_upload_mb_per_frame: mine
                    .iter()
                    .map(|r| r.geometry_upload_bytes as f64)
                    .sum::<f64>()
                    / 1e6
                    / mine.len().max(1) as f64,
                tlas_records_written_share: mine
                    .iter()
                    .map(|r| r.tlas_records_written as f64)
                    .sum::<f64>()
                    / mine
                        .iter()
                        .map(|r| f64::from(r.tlas_instances))
                        .sum::<f64>()
                        .max(1.0),
                gpu_as_ms_p50: gpu.p50,
                gpu_as_ms_p99: gpu.p99,
                gpu_tlas_ms_p50: gpu_tlas.p50,
                gpu_tlas_ms_p99: gpu_tlas.p99,
                tlas_update_share: mine.iter().filter(|r| r.tlas_updated).count() as f64
                    / mine.len().max(1) as f64,
                render_ms_p50: Summary::of(
                    render_ms
                        .iter()
                        .filter(|(i, _)| *i == pi)
                        .map(|(_, ms)| *ms),
                )
                .p50,
                builds_per_frame: mine.iter().map(|r| f64::from(r.builds)).sum::<f64>()
                    / mine.len().max(1) as f64,
                over_budget_frames: mine.iter().filter(|r| r.over_budget()).count() as u64,
                hit_mismatch_mean: error.hit_mismatch.mean,
                hit_mismatch_p95: error.hit_mismatch.p95,
                shadow_mismatch_mean: error.shadow_mismatch.mean,
                shadow_mismatch_p95: error.shadow_mismatch.p95,
                mismatch_by_band: band_summaries(&only, edges),
                error,
                error_all_geometry: (!all.is_empty()).then(|| ErrorSummary::of(all.into_iter())),
                worst_frame_png: None,
                validation_messages,
            });
        }
        Self {
            summary: RunSummary {
                frames: config.frames,
                seed: config.preset.seed,
                preset: config.preset.name.clone(),
                device,
                deterministic: config.deterministic,
                stream_radius: config.stream.load_radius,
                evaluated_frames: evaluated,
                size: [config.size.0, config.size.1],
                bands: edges.names(),
                reference,
                policies: summaries,
                validation_messages,
                seconds,
                frame_timing: None,
                lod_reads: 0,
                lod_reads_shared: 0,
            },
            rows: Vec::new(),
            files: Vec::new(),
        }
    }

    pub(crate) fn set_worst_frame(&mut self, name: &str, frame: u64, file: &Path) {
        for p in &mut self.summary.policies {
            if p.policy == name && p.error.worst_frame == Some(frame) {
                p.worst_frame_png = Some(file.to_owned());
            }
        }
    }

    /// The summary as one line of JSON.
    pub fn json(&self) -> String {
        serde_json::to_string(&self.summary).expect("the summary serialises")
    }

    /// Writes `frames.csv` and `summary.json` into `dir`; returns their paths.
    pub fn write_files(&self, dir: &Path) -> Result<Vec<PathBuf>> {
        let out = |path: &Path, e: &dyn std::fmt::Display| Error::Output {
            path: path.to_owned(),
            message: e.to_string(),
        };
        std::fs::create_dir_all(dir).map_err(|e| out(dir, &e))?;
        let csv_path = dir.join("frames.csv");
        let mut w = csv::Writer::from_path(&csv_path).map_err(|e| out(&csv_path, &e))?;
        for r in &self.rows {
            let s = r.score.as_ref();
            let band = |b: usize| s.map(|s| s.bands[b].hit_mismatched as f64 / s.pixels as f64);
            w.serialize(CsvRow {
                frame: r.frame,
                policy: r.policy,
                blas_count: r.blas_count,
                blas_bytes: r.blas_bytes,
                retiring_bytes: r.retiring_bytes,
                over_budget: r.over_budget(),
                tlas_instances: r.tlas_instances,
                builds: r.builds,
                build_primitives: r.build_primitives,
                refits: r.refits,
                compactions: r.compactions,
                evictions: r.evictions,
                proxy_instances: r.proxy_instances,
                proxy_blas_bytes: r.proxy_blas_bytes,
                far_groups_covered: r.far_groups_covered,
                lod_fallbacks: r.lod_fallbacks,
                memory_refused: r.memory_refused,
                within_r1: r.within_r1,
                short_of_target: r.short_of_target,
                over_build_budget: r.over_build_budget,
                landmark_instances: r.landmark_instances,
                landmarks_examined: r.landmarks_examined,
                landmarks_waited: r.landmarks_waited,
                geometry_upload_bytes: r.geometry_upload_bytes,
                tlas_records_written: r.tlas_records_written,
                update_ms: r.update_ms,
                update_cpu_ms: r.update_cpu_ms,
                gpu_as_ms: r.gpu_as_ms,
                gpu_tlas_ms: r.gpu_tlas_ms,
                tlas_updated: r.tlas_updated,
                tlas_slots_joined: r.tlas_slots_joined,
                tlas_slots_misplaced: r.tlas_slots_misplaced,
                hit_mismatch: s.map(|s| s.hit_mismatch),
                identity_mismatch: s.map(|s| s.identity_mismatch),
                shadow_mismatch: s.map(|s| s.shadow_mismatch),
                ao_difference: s.map(|s| s.ao_difference),
                psnr_db: s.map(|s| s.psnr_db),
                band0_hit_mismatch: band(0),
                band1_hit_mismatch: band(1),
                band2_hit_mismatch: band(2),
                band3_hit_mismatch: band(3),
                all_geometry_hit_mismatch: r.score_all_geometry.map(|s| s.hit_mismatch),
                all_geometry_shadow_mismatch: r.score_all_geometry.map(|s| s.shadow_mismatch),
            })
            .map_err(|e| out(&csv_path, &e))?;
        }
        w.flush().map_err(|e| out(&csv_path, &e))?;
        let json_path = dir.join("summary.json");
        let json = serde_json::to_string_pretty(&self.summary).map_err(|e| out(&json_path, &e))?;
        std::fs::write(&json_path, json).map_err(|e| out(&json_path, &e))?;
        Ok(vec![csv_path, json_path])
    }
}

/// Frames to full coverage after each teleport of a run with
/// [`RunConfig::teleport_every`]` = every`, for one policy: the number of frames after the
/// teleport until every unculled instance within r1 shows its target LOD or finer and keeps
/// doing so until the next teleport (streaming brings levels and finer LODs in over the first
/// frames, and each may set a finer target). `None`: not covered when the next teleport came
/// (or nothing was within r1 at the end).
pub fn frames_to_coverage(rows: &[FrameRow], policy: &str, every: u64) -> Vec<Option<u64>> {
    let rows: Vec<&FrameRow> = rows.iter().filter(|r| r.policy == policy).collect();
    rows.chunks(every.max(1) as usize)
        .map(|seg| {
            let last = seg.last()?;
            if last.short_of_target > 0 || last.within_r1 == 0 {
                return None;
            }
            Some(
                seg.iter()
                    .rposition(|r| r.short_of_target > 0)
                    .map_or(0, |i| i as u64 + 1),
            )
        })
        .collect()
}
