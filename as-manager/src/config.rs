//! Validated configuration: one sub-struct per policy.

use crate::backend::model::CostModel;
use crate::{AsError, Result};

/// Which policy drives `update`. The baselines run behind the same API for comparisons.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum PolicyKind {
    /// The manager's policies: spatial-index residency, LOD, budgets, culling with hysteresis.
    #[default]
    Managed,
    /// A BLAS for every registered LOD, built at once, no budget, no culling (what crashed the
    /// shipped game).
    Naive,
    /// The seeds' published loop: two passes over every instance per camera with r1/r2 and the
    /// create/release thresholds, no budgets, UE-style OR culling over every instance.
    SeedR1R2,
}

/// Residency radii (world units, distance from a camera to an instance's bounding sphere) and
/// frame thresholds.
#[derive(Debug, Clone, PartialEq)]
pub struct ResidencyConfig {
    /// Within r1 an instance requests its BLAS.
    pub r1: f32,
    /// Within r2 an instance keeps its BLAS (r1 <= r2). Only instances within r2 of a camera
    /// can be in the TLAS.
    pub r2: f32,
    /// A BLAS is created after being requested on this many consecutive frames.
    pub create_threshold: u32,
    /// A BLAS is released once nothing kept it for more than this many frames.
    pub release_threshold: u32,
    /// Managed only: a built BLAS lives at least this many frames (no thrashing even when
    /// r1 == r2 and the thresholds are zero).
    pub min_resident_frames: u32,
    /// Spatial index cell size (world units).
    pub cell_size: f32,
}

impl Default for ResidencyConfig {
    fn default() -> Self {
        Self {
            r1: 200.0,
            r2: 250.0,
            create_threshold: 2,
            release_threshold: 30,
            min_resident_frames: 8,
            cell_size: 64.0,
        }
    }
}

/// LOD selection by projected geometric error.
#[derive(Debug, Clone, PartialEq)]
pub struct LodConfig {
    /// The coarsest LOD whose error projects to at most this many pixels is chosen.
    pub max_pixel_error: f32,
    /// Vertical resolution the error is projected to.
    pub screen_height_px: f32,
    /// Vertical field of view, radians.
    pub vertical_fov: f32,
    /// Relative band: switch to a coarser LOD only when its error is below
    /// `max_pixel_error / (1 + hysteresis)`, to a finer one when the current is above
    /// `max_pixel_error * (1 + hysteresis)`.
    pub hysteresis: f32,
}

impl Default for LodConfig {
    fn default() -> Self {
        Self {
            max_pixel_error: 1.0,
            screen_height_px: 1080.0,
            vertical_fov: 60f32.to_radians(),
            hysteresis: 0.25,
        }
    }
}

/// Per-frame build, compaction and refit budgets.
#[derive(Debug, Clone, PartialEq)]
pub struct BuildBudget {
    /// Triangles admitted for BLAS builds per frame.
    pub max_primitives: u64,
    /// Estimated GPU milliseconds of all acceleration-structure work per frame: the TLAS build
    /// and the refits (estimated from the previous frame) are set aside first, builds get what
    /// they leave, and compactions what builds leave (at most `max_compaction_ms`). One build
    /// larger than the whole budget is admitted alone; each frame admits at least one build of
    /// near detail and one far-field proxy, so neither starves when the TLAS and refits take
    /// the whole budget. Default 0.45 ms: with the H200's cost model, 0.5 put the fly-through's
    /// GPU AS p99 at 0.503 ms (the estimates' residuals), 0.45 at 0.483 ms with the same builds
    /// per frame and the same image error (docs/GPU.md).
    pub max_gpu_ms: f32,
    /// BLAS builds admitted per frame, whatever their GPU cost: recording a build costs the
    /// host too (the driver's `vkCmdBuildAccelerationStructuresKHR` and the backend's planning,
    /// about 25 µs a build on the H200's host), and many small builds fit the GPU budget. The
    /// first near item and the first proxy of a frame go past it, as past the GPU budget.
    pub max_builds: u32,
    /// Priority gained per frame of waiting (world units of distance), so nothing starves.
    pub aging_per_frame: f32,
    /// Priority bonus (world units) for an item some camera looks towards.
    pub in_view_bonus: f32,
    /// Compactions per frame.
    pub max_compactions: u32,
    /// Estimated GPU milliseconds of compaction copies per frame.
    pub max_compaction_ms: f32,
    /// Triangles refitted per frame (skinned), oldest first.
    pub max_refit_primitives: u64,
    /// Rebuild a skinned BLAS when its refit quality ratio (summed leaf/node surface area
    /// relative to the root, against the last build) exceeds this.
    pub rebuild_quality_bound: f32,
    /// Compact a static BLAS only when the compacted copy saves at least this share of its
    /// bytes (0.03 by default; lavapipe saves nothing, NVIDIA ~16%). 0 compacts always.
    pub min_compaction_saving: f32,
}

impl Default for BuildBudget {
    fn default() -> Self {
        Self {
            max_primitives: 200_000,
            max_gpu_ms: 0.45,
            max_builds: u32::MAX,
            aging_per_frame: 2.0,
            in_view_bonus: 50.0,
            max_compactions: 8,
            max_compaction_ms: 0.25,
            max_refit_primitives: 200_000,
            rebuild_quality_bound: 1.5,
            min_compaction_saving: 0.03,
        }
    }
}

/// BLAS memory budget.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryBudget {
    /// Bytes of BLAS storage (including compaction copies and freed-but-in-flight BLASes).
    pub blas_bytes: u64,
    /// Fraction of the budget that builds leave free so compaction (which needs the original
    /// and the copy at once) can still run when memory is full.
    pub compaction_headroom: f32,
}

impl Default for MemoryBudget {
    fn default() -> Self {
        Self {
            blas_bytes: 512 << 20,
            compaction_headroom: 0.1,
        }
    }
}

/// How distance and angle culling combine (like UE5's modes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum CullMode {
    /// Cull if far OR small (UE's default).
    #[default]
    FarOrSmall,
    /// Cull only if far AND small.
    FarAndSmall,
    /// Distance only.
    Far,
    /// Projected angle only.
    Small,
    /// No culling.
    Off,
}

/// Instance culling for the TLAS.
#[derive(Debug, Clone, PartialEq)]
pub struct CullConfig {
    /// Combination of the two tests.
    pub mode: CullMode,
    /// "Far": distance from the camera to the bounding sphere beyond this.
    pub far_distance: f32,
    /// "Small": angular radius of the bounding sphere below this (radians). Default 0.5°: with
    /// the far field's landmarks it takes the default run from 0.39 % to 0.29 % hit mismatch
    /// for 4 % more TLAS instances and no memory (1° is UE5's default; `docs/RESULTS.md`).
    pub min_angle: f32,
    /// Nothing within this distance is culled.
    pub near_distance: f32,
    /// Relative margin: a culled instance comes back only once it passes the thresholds
    /// tightened by this fraction (no flicker).
    pub hysteresis: f32,
}

impl Default for CullConfig {
    fn default() -> Self {
        Self {
            mode: CullMode::FarOrSmall,
            far_distance: 300.0,
            min_angle: 0.5f32.to_radians(),
            near_distance: 10.0,
            hysteresis: 0.1,
        }
    }
}

/// The far field: beyond r2, group proxies stand for their instances (see
/// `AsManager::register_group`). Only the `Managed` policy uses it.
#[derive(Debug, Clone, PartialEq)]
pub struct FarFieldConfig {
    /// Show proxies at all.
    pub enabled: bool,
    /// Proxies farther than this from every camera (to their bounds) are not shown.
    pub far_radius: f32,
    /// A coarser node's proxy is shown once its error projects to at most this many pixels
    /// (with `LodConfig`'s resolution and field of view); nearer, its children are shown.
    pub max_pixel_error: f32,
    /// A leaf group turns "far" (proxy) beyond r2 plus this many metres and "near" (detail)
    /// within r2: the hysteresis of the hand-over.
    pub handover_margin: f32,
    /// Proxies of groups within r2 plus this many metres are built ahead, so a group that
    /// leaves r2 finds its proxy ready.
    pub lookahead: f32,
    /// A node whose proxy the cut wants has its children's proxies built ahead (they replace
    /// it as the cameras come nearer) once its error projects to more than this share of
    /// `max_pixel_error`; 1 builds no child ahead. Default 0.75: on the default fly-through
    /// (`docs/RESULTS.md`, "What the peak holds") 0.5 held 18.6 MB of proxies for 5.0 MB in the
    /// TLAS, 0.75 holds 12.0 MB at the same error in every distance band, 1 holds 9.5 MB at
    /// +0.001 points beyond r2 (320x180 scoring on lavapipe; a 48 px cut is 8 px there).
    pub refine_ahead: f32,
    /// Share of the per-frame build budget proxies may use (they are built first, so the far
    /// field keeps up while near detail streams; detail takes the rest).
    pub build_share: f32,
    /// Share of the BLAS memory budget proxies may hold; they never evict to get it.
    pub memory_share: f32,
    /// The "far keep angle" (radians, 0 = off): a static instance beyond r2 (and within
    /// `far_radius`) whose bounding sphere subtends more than this stays in the TLAS beside the
    /// proxies as a **landmark** — a tower 600 m away keeps its own silhouette instead of the
    /// proxy's simplified one. A landmark picks its LOD by projected error like the near field
    /// and uses the mesh's shared BLAS for that LOD, so the cost is TLAS instances, not memory.
    /// This angle alone decides landmarks (the culling angle is the near field's). Candidates
    /// are indexed in coarse cells sorted by size, so the per-frame cost follows the landmarks
    /// near enough to qualify, not the world's size.
    /// Default 0.75°: with the proxies that keep their buildings (`ProxyMethod::Select` in
    /// `rtstream-streaming`), the default fly-through at 1080p on an H100 scores 0.27 % hit
    /// mismatch against the full world with 9,072 TLAS records, against 0.16 % with 14,184 at
    /// 0.5° and 0.47 % with 7,012 at 1° (`docs/RESULTS.md`, "Proxies that keep their
    /// buildings"; older charts there cover 0.25–4°). In a world ten times as dense, 0.75°
    /// scores 0.03 % with 62,428 records and 1° 0.08 % with 41,123: dense worlds can set 1°.
    pub keep_angle: f32,
    /// Landmarks farther than this from every camera (to their bounding sphere) are left to the
    /// proxies: a landmark draw distance. How many landmarks qualify grows with how far the
    /// world reaches (a 70 m tower subtends 0.5° out to 8 km), and each costs `update` time
    /// and a TLAS instance. Default 3 km: on the H200, the large world's accuracy is the same as
    /// unlimited (0.44 % hit mismatch) at 0.59x its `update` time (11.1 ms vs 18.8 ms p50, both
    /// side by side with the baselines), and the default world's 4 km map barely reaches past
    /// it: the same TLAS and figures as unlimited (`docs/RESULTS.md`).
    pub keep_range: f32,
    /// The detail of near leaves beyond r2 (a leaf within r2 shows all its instances, also
    /// those beyond it) is kept incrementally with the landmarks: each static instance is
    /// looked at when the cameras may have crossed one of its thresholds (r2, its LOD's switch
    /// points, the culling angle) or on an event, not every frame. `false`: the residency pass
    /// visits it every frame, the reference the tests compare with. Default `true`.
    pub incremental_detail: bool,
}

impl Default for FarFieldConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            far_radius: f32::INFINITY,
            max_pixel_error: 48.0,
            handover_margin: 25.0,
            lookahead: 150.0,
            refine_ahead: 0.75,
            build_share: 0.5,
            memory_share: 0.5,
            keep_angle: 0.75f32.to_radians(),
            keep_range: 3000.0,
            incremental_detail: true,
        }
    }
}

/// TLAS record assembly.
#[derive(Debug, Clone, PartialEq)]
pub struct AssemblyConfig {
    /// Records are written by several threads at and above this count.
    pub parallel_threshold: usize,
    /// Threads for parallel assembly (>= 1).
    pub threads: usize,
}

impl Default for AssemblyConfig {
    fn default() -> Self {
        Self {
            parallel_threshold: 32_768,
            threads: std::thread::available_parallelism().map_or(2, |n| n.get().min(8)),
        }
    }
}

/// The manager's configuration; [`Config::validate`] runs in [`crate::AsManager::new`].
///
/// ```
/// use rtstream_as_manager::Config;
/// let mut c = Config::default();
/// assert!(c.validate().is_ok());
/// c.residency.r1 = 500.0; // r1 > r2
/// assert!(c.validate().is_err());
/// ```
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Config {
    /// Policy driving `update`.
    pub policy: PolicyKind,
    /// Residency radii and thresholds.
    pub residency: ResidencyConfig,
    /// LOD selection.
    pub lod: LodConfig,
    /// Build/compaction/refit budgets.
    pub build: BuildBudget,
    /// Memory budget.
    pub memory: MemoryBudget,
    /// Instance culling.
    pub cull: CullConfig,
    /// Far-field proxies.
    pub far_field: FarFieldConfig,
    /// Assembly.
    pub assembly: AssemblyConfig,
    /// Prior GPU cost model; measured timings refine it unless `freeze_cost_model` is set.
    pub cost_prior: CostModel,
    /// Keep the cost model at `cost_prior`: build admission never follows live GPU timings, so
    /// with the same inputs every frame's decisions are the same under any machine load (the
    /// deterministic runs of the examples and tests set it). Off by default: interactive runs
    /// learn the device's real costs.
    pub freeze_cost_model: bool,
}

fn pos(v: f32) -> bool {
    v.is_finite() && v > 0.0
}

fn nonneg(v: f32) -> bool {
    v.is_finite() && v >= 0.0
}

impl Config {
    /// Checks ranges: finite values, 0 < r1 <= r2, positive budgets, 0 < fov < pi, ...
    pub fn validate(&self) -> Result<()> {
        let (r, l, f) = (&self.residency, &self.lod, &self.far_field);
        let (b, c) = (&self.build, &self.cull);
        let h = self.memory.compaction_headroom;
        // Each rule with the error it gives, in the order that decides which error a
        // configuration with several faults reports.
        let rules = [
            (
                pos(r.r1) && pos(r.r2),
                "residency.r1/r2 must be finite and > 0",
            ),
            (r.r1 <= r.r2, "residency.r1 must be <= r2"),
            (
                pos(r.cell_size),
                "residency.cell_size must be finite and > 0",
            ),
            (
                r.create_threshold <= 1_000_000 && r.release_threshold <= 1_000_000,
                "thresholds must be <= 1e6 frames",
            ),
            (pos(l.max_pixel_error), "lod.max_pixel_error must be > 0"),
            (pos(l.screen_height_px), "lod.screen_height_px must be > 0"),
            (
                pos(l.vertical_fov) && l.vertical_fov < std::f32::consts::PI,
                "lod.vertical_fov must be in (0, pi)",
            ),
            (nonneg(l.hysteresis), "lod.hysteresis must be >= 0"),
            (
                f.far_radius > 0.0 && !f.far_radius.is_nan(),
                "far_field.far_radius must be > 0",
            ),
            (
                pos(f.max_pixel_error),
                "far_field.max_pixel_error must be > 0",
            ),
            (
                nonneg(f.handover_margin) && nonneg(f.lookahead),
                "far_field.handover_margin and lookahead must be >= 0",
            ),
            (
                (0.0..=1.0).contains(&f.build_share) && (0.0..=1.0).contains(&f.memory_share),
                "far_field.build_share and memory_share must be in [0, 1]",
            ),
            (
                (0.0..=1.0).contains(&f.refine_ahead),
                "far_field.refine_ahead must be in [0, 1]",
            ),
            (
                nonneg(f.keep_angle) && f.keep_angle < std::f32::consts::FRAC_PI_2,
                "far_field.keep_angle must be in [0, pi/2)",
            ),
            (
                f.keep_range > 0.0 && !f.keep_range.is_nan(),
                "far_field.keep_range must be > 0",
            ),
            (b.max_primitives > 0, "build.max_primitives must be > 0"),
            (pos(b.max_gpu_ms), "build.max_gpu_ms must be > 0"),
            (b.max_builds > 0, "build.max_builds must be > 0"),
            (
                nonneg(b.aging_per_frame) && nonneg(b.in_view_bonus),
                "build.aging/in_view_bonus must be >= 0",
            ),
            (
                nonneg(b.max_compaction_ms),
                "build.max_compaction_ms must be >= 0",
            ),
            (
                b.rebuild_quality_bound.is_finite() && b.rebuild_quality_bound >= 1.0,
                "build.rebuild_quality_bound must be >= 1",
            ),
            (
                (0.0..1.0).contains(&b.min_compaction_saving),
                "build.min_compaction_saving must be in [0, 1)",
            ),
            (self.memory.blas_bytes > 0, "memory.blas_bytes must be > 0"),
            (
                h.is_finite() && (0.0..0.9).contains(&h),
                "memory.compaction_headroom must be in [0, 0.9)",
            ),
            (pos(c.far_distance), "cull.far_distance must be > 0"),
            (
                nonneg(c.min_angle) && c.min_angle < std::f32::consts::FRAC_PI_2,
                "cull.min_angle must be in [0, pi/2)",
            ),
            (nonneg(c.near_distance), "cull.near_distance must be >= 0"),
            (
                nonneg(c.hysteresis) && c.hysteresis < 1.0,
                "cull.hysteresis must be in [0, 1)",
            ),
            (self.assembly.threads >= 1, "assembly.threads must be >= 1"),
        ];
        if let Some((_, what)) = rules.iter().find(|(ok, _)| !ok) {
            return Err(AsError::InvalidConfig(what.to_string()));
        }
        self.cost_prior.validate()
    }

    /// The seeds' parameters for the `SeedR1R2` baseline.
    pub fn seed_r1r2() -> Self {
        Self {
            policy: PolicyKind::SeedR1R2,
            ..Self::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_valid_and_bad_values_rejected() {
        assert!(Config::default().validate().is_ok());
        let mut c = Config::default();
        c.residency.r2 = f32::NAN;
        assert!(matches!(c.validate(), Err(AsError::InvalidConfig(_))));
        let mut c = Config::default();
        c.build.max_primitives = 0;
        assert!(c.validate().is_err());
        let mut c = Config::default();
        c.residency.r1 = c.residency.r2;
        assert!(c.validate().is_ok(), "r1 == r2 is allowed");
    }
}
