//! The command line shared by the examples that run the frame driver (`flythrough`,
//! `tradeoff`, the stress runs): one `--help` style, one mapping onto `RunConfig`.
//! Included with `#[path = "support/cli.rs"] mod cli;`; not every example uses every item.
#![allow(dead_code)]

use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::{Args, CommandFactory, FromArgMatches, Parser, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use rtstream::as_manager::backend::vulkan::TlasUpdates;
use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, FrameRow, PolicySummary, Progress, RunConfig, RunReport};
use rtstream::streaming::WorldPreset;

/// World presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Preset {
    /// The shipped game's map: 4 km, 3,136 levels, 110k instances.
    Default,
    /// A 16x16-level corner of it (for tests and quick looks).
    Small,
    /// 16 km, 1.76M instances.
    Large,
    /// A dense city: 1.14 km, ten times the default's density (90k instances), tall buildings.
    City,
    /// 3x3 levels (214 m) with 603 generated skinned characters.
    Crowd,
}

/// Policies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Policy {
    /// The manager.
    Managed,
    /// A BLAS for every loaded LOD, no culling.
    Naive,
    /// The seeds' two-pass r1/r2 loop.
    Seed,
}

impl From<Policy> for PolicyKind {
    fn from(p: Policy) -> Self {
        match p {
            Policy::Managed => PolicyKind::Managed,
            Policy::Naive => PolicyKind::Naive,
            Policy::Seed => PolicyKind::SeedR1R2,
        }
    }
}

/// Arguments of a driver run.
#[derive(Debug, Clone, Args)]
pub struct RunArgs {
    /// World and camera-path seed.
    #[arg(long, default_value_t = 0x5EED)]
    pub seed: u64,
    /// World preset.
    #[arg(long, value_enum, default_value_t = Preset::Default)]
    pub preset: Preset,
    /// The generator's asset directory.
    #[command(flatten)]
    pub assets: AssetArgs,
    /// Where the baked world is kept (default: out/world-<preset>-<seed>).
    #[arg(long)]
    pub world: Option<PathBuf>,
    /// Instances of the world (terrain included) on the preset's map instead of its own count:
    /// `--instances 1100000` is the default map at ten times its density.
    #[arg(long)]
    pub instances: Option<u32>,
    /// Districts of distinct assets, D x D levels each (`WorldPreset::districts`): every
    /// district has its own copy of each opaque static mesh, so a BLAS per loaded mesh costs
    /// what it does in an open world with regional assets (0: one shared library).
    #[arg(long, default_value_t = 0)]
    pub districts: u32,
    /// Frames to run (1 to 100,000,000).
    #[arg(long, default_value_t = 600, value_parser = clap::value_parser!(u64).range(1..=MAX_FRAMES))]
    pub frames: u64,
    /// Policies to run side by side (comma-separated).
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [Policy::Managed, Policy::Naive, Policy::Seed])]
    pub policy: Vec<Policy>,
    /// BLAS memory budget of the managed policy, MB.
    #[arg(long, value_parser = finite_positive_f64)]
    pub budget_mb: Option<f64>,
    /// Residency radius r1 (request), metres.
    #[arg(long, value_parser = finite_positive_f32)]
    pub r1: Option<f32>,
    /// Residency radius r2 (keep), metres.
    #[arg(long, value_parser = finite_positive_f32)]
    pub r2: Option<f32>,
    /// Culling angle, degrees (projected angular radius below which an instance is culled;
    /// 0 to 90 exclusive, 0: no instance is culled for its size).
    #[arg(long, value_parser = angle_deg)]
    pub cull_angle: Option<f32>,
    /// Culling distance, metres.
    #[arg(long, value_parser = finite_positive_f32)]
    pub cull_distance: Option<f32>,
    /// LOD pixel error.
    #[arg(long, value_parser = finite_positive_f32)]
    pub lod_px: Option<f32>,
    /// Frames a BLAS that nothing keeps stays built before it is released
    /// (`ResidencyConfig::release_threshold`).
    #[arg(long)]
    pub release_frames: Option<u32>,
    /// Estimated GPU ms of BLAS builds admitted per frame.
    #[arg(long, value_parser = finite_positive_f32)]
    pub max_build_ms: Option<f32>,
    /// Triangles admitted for BLAS builds per frame.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_build_tris: Option<u64>,
    /// BLAS builds admitted per frame (`BuildBudget::max_builds`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_builds: Option<u32>,
    /// Streaming load radius, metres (what a raster engine would load).
    #[arg(long, default_value_t = 1000.0, value_parser = finite_positive_f32)]
    pub stream_radius: f32,
    /// Streaming loads in flight at most (`StreamConfig::max_in_flight`, default 64): how many
    /// finer LODs streaming can be fetching at once. With distinct meshes (`--districts`) at
    /// the fly-through's speed, the default holds LODs back (docs/STRESS.md).
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub loads_in_flight: Option<usize>,
    /// Score every K-th frame against the full-world ground truth (0: never). The default
    /// scores 33 frames of the 600.
    #[arg(long, default_value_t = 18)]
    pub eval_every: u64,
    /// Size of scored (and rendered) frames, WxH.
    #[arg(long, default_value = "320x180", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Also render every K-th frame on the frame path, unscored, and report frame time
    /// against the render passes' GPU time (0: off).
    #[arg(long, default_value_t = 0)]
    pub render_every: u64,
    /// Render those frames the old, blocking way (wait for the frame, then three passes each
    /// submitted and waited for), to compare with the pipelined path.
    #[arg(long)]
    pub blocking_render: bool,
    /// Frames in flight (1 to 4).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=4))]
    pub frames_in_flight: u32,
    /// Deterministic: freeze the cost model, retire at frame minus frames in flight, apply
    /// loads a fixed number of frames after their request. Every figure but the timings is
    /// then identical under any load.
    #[arg(long)]
    pub deterministic: bool,
    /// Far-field proxies beyond r2 (the managed policy).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub far_field: bool,
    /// Also run the managed policy with its far field off (`managed-near`) in the same run.
    #[arg(long)]
    pub compare_far_field: bool,
    /// Also run the managed policy with its TLAS updated in place between builds
    /// (`managed-tlas-update`) beside the policies' TLAS built every frame, in the same run.
    #[arg(long)]
    pub compare_tlas_updates: bool,
    /// Every policy updates its TLAS in place, at most this many times after a build (0, the
    /// default: a build every frame; see `TlasUpdates`).
    #[arg(long, default_value_t = 0)]
    pub tlas_max_updates: u32,
    /// With `--tlas-max-updates`: the fraction of the records that may join an updated TLAS
    /// in a parked slot away from where they stand before a frame builds
    /// (`TlasUpdates::max_misplaced`; default 1/256; 0 to 1).
    #[arg(long, value_parser = fraction_f32)]
    pub tlas_max_misplaced: Option<f32>,
    /// Build every policy's TLAS with PREFER_FAST_TRACE instead of the backend's default
    /// PREFER_FAST_BUILD (to compare build and trace times).
    #[arg(long)]
    pub tlas_fast_trace: bool,
    /// Build every policy's static BLASes with PREFER_FAST_TRACE instead of the backend's
    /// default PREFER_FAST_BUILD (to compare build and trace times).
    #[arg(long)]
    pub static_fast_trace: bool,
    /// Far-field cut: a proxy is shown once its error projects under this many pixels.
    #[arg(long, value_parser = finite_positive_f32)]
    pub far_px: Option<f32>,
    /// Far keep angle in degrees (0: off): a static instance beyond r2 that subtends more
    /// stays in the TLAS beside the proxies (a landmark); below 90.
    #[arg(long, value_parser = angle_deg)]
    pub far_keep_angle: Option<f32>,
    /// Far keep range in metres: no landmark farther than this (default: unlimited; `inf`
    /// says so explicitly).
    #[arg(long, value_parser = positive_f32_or_inf)]
    pub far_keep_range: Option<f32>,
    /// Skip the all-geometry reference (non-opaque as opaque).
    #[arg(long)]
    pub opaque_only: bool,
    /// Output directory (CSV, summary.json, maps, worst frames).
    #[arg(long, default_value = "out/flythrough")]
    pub out: PathBuf,
    /// Top-down maps at this many frames (0 to 1,000).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(0..=1_000))]
    pub maps: u32,
}

/// The most frames `--frames` takes (a run of 600 frames is the default; this is days of
/// frames at 60 Hz, and keeps the driver's frame arithmetic far from overflowing).
pub const MAX_FRAMES: u64 = 100_000_000;

/// Parses `WxH`: a size the renderer takes (`rtstream::renderer::check_size`), so that a size it
/// refuses fails on the command line, before any GPU work.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once('x').ok_or("expected WxH, e.g. 320x180")?;
    let w: u32 = w.parse().map_err(|e| format!("width: {e}"))?;
    let h: u32 = h.parse().map_err(|e| format!("height: {e}"))?;
    rtstream::renderer::check_size(w, h).map_err(|e| e.to_string())?;
    Ok((w, h))
}

/// Parses a number (`nan`, `inf` and `-inf` included, which the callers then refuse).
fn parse_number<T: std::str::FromStr>(s: &str) -> Result<T, String>
where
    T::Err: std::fmt::Display,
{
    s.trim().parse::<T>().map_err(|e| format!("{s:?}: {e}"))
}

/// Parses a number that `ok` accepts; otherwise the error says it `must` be what it is not.
fn checked<T>(s: &str, ok: impl Fn(T) -> bool, must: &str) -> Result<T, String>
where
    T: std::str::FromStr + Copy,
    T::Err: std::fmt::Display,
{
    let v: T = parse_number(s)?;
    if ok(v) {
        Ok(v)
    } else {
        Err(format!("must be {must}, not {s}"))
    }
}

/// `value_parser` of a flag that takes a finite number greater than 0 (a radius, a distance, a
/// budget).
pub fn finite_positive_f32(s: &str) -> Result<f32, String> {
    checked(
        s,
        |v: f32| v.is_finite() && v > 0.0,
        "a finite number greater than 0",
    )
}

/// [`finite_positive_f32`] for an `f64` flag.
pub fn finite_positive_f64(s: &str) -> Result<f64, String> {
    checked(
        s,
        |v: f64| v.is_finite() && v > 0.0,
        "a finite number greater than 0",
    )
}

/// `value_parser` of a flag that takes a finite number of at least 0 (0 meaning "off" or
/// "none").
pub fn finite_non_negative_f32(s: &str) -> Result<f32, String> {
    checked(
        s,
        |v: f32| v.is_finite() && v >= 0.0,
        "a finite number of at least 0",
    )
}

/// `value_parser` of a number greater than 0 where `inf` means "unlimited" (NaN refused).
pub fn positive_f32_or_inf(s: &str) -> Result<f32, String> {
    checked(
        s,
        |v: f32| v > 0.0,
        "a number greater than 0 (or inf: unlimited)",
    )
}

/// `value_parser` of a fraction: a number from 0 to 1.
pub fn fraction_f32(s: &str) -> Result<f32, String> {
    checked(
        s,
        |v: f32| (0.0..=1.0).contains(&v),
        "a fraction from 0 to 1",
    )
}

/// `value_parser` of an angle in degrees from 0 (inclusive: "off") to 90 (exclusive), what the
/// manager's angle thresholds accept (`Config::validate`: `[0, pi/2)` in radians).
pub fn angle_deg(s: &str) -> Result<f32, String> {
    checked(
        s,
        |v: f32| v.is_finite() && v >= 0.0 && v.to_radians() < std::f32::consts::FRAC_PI_2,
        "an angle in degrees from 0 to below 90",
    )
}

/// `--asset-dir`, for every example that generates a world (flattened into [`RunArgs`] and into
/// the examples with a command line of their own): the streaming crate's examples' type, one
/// definition for both (the streaming crate cannot see the facade's examples).
#[path = "../../streaming/examples/support/world_args.rs"]
mod world_args;
pub use world_args::AssetArgs;

/// A world preset with its seed and, optionally, another asset directory.
pub fn world_preset(preset: Preset, seed: u64, assets: &AssetArgs) -> WorldPreset {
    let mut p = match preset {
        Preset::Default => WorldPreset::default_world(),
        Preset::Small => WorldPreset::small(16, seed),
        Preset::Large => WorldPreset::large_world(),
        Preset::City => WorldPreset::city(),
        Preset::Crowd => WorldPreset::crowd(600),
    };
    p.seed = seed;
    assets.apply(&mut p);
    p
}

/// Output flags every driver example takes.
#[derive(Debug, Clone, Args)]
pub struct OutputArgs {
    /// Print the summary as one JSON object on the last line of stdout.
    #[arg(long)]
    pub json: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// The command line of a driver example: the driver's flags ([`RunArgs`]), the example's own
/// (`E`; [`NoFlags`] for none) and the output flags ([`OutputArgs`]), in that order in `--help`.
#[derive(Debug, Parser)]
#[command(version)]
pub struct ExampleCli<E: Args> {
    #[command(flatten)]
    pub run: RunArgs,
    #[command(flatten)]
    pub own: E,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// An example without flags of its own.
#[derive(Debug, Clone, Args)]
pub struct NoFlags {}

impl<E: Args> ExampleCli<E> {
    /// What a driver example's `main` starts with: logs to stderr ([`init_tracing`]), parses the
    /// command line with `about` as the example's description in `--help` (exiting on a bad
    /// one, as `Parser::parse` does), and writes to `default_out` unless `--out` says otherwise.
    pub fn start(about: &'static str, default_out: &str) -> Self {
        init_tracing();
        let mut command = Self::command().about(about);
        let mut cli = Self::from_arg_matches(&command.get_matches_mut())
            .unwrap_or_else(|e| e.format(&mut command).exit());
        cli.run.default_out(default_out);
        cli
    }
}

impl OutputArgs {
    /// Writes `summary` as `<out>/<name>.json`, lists the files written, and prints the JSON as
    /// the last stdout line with `--json`.
    pub fn finish(
        &self,
        out: &std::path::Path,
        name: &str,
        summary: &impl serde::Serialize,
        files: &[PathBuf],
    ) -> anyhow::Result<()> {
        let json = serde_json::to_string(summary)?;
        std::fs::write(out.join(format!("{name}.json")), &json)?;
        for f in files {
            eprintln!("wrote {}", f.display());
        }
        if self.json {
            println!("{json}");
        }
        Ok(())
    }
}

impl RunArgs {
    /// Replaces the fly-through's default output directory with `dir` (an explicit `--out`
    /// stays).
    pub fn default_out(&mut self, dir: &str) {
        if self.out.as_path() == std::path::Path::new("out/flythrough") {
            self.out = dir.into();
        }
    }

    /// Runs `config` on `preset` instead of `--preset` (an example with a world of its own),
    /// with `--seed`, `--asset-dir` and `--world` (default `out/world-<name>-<seed>`) applied.
    pub fn use_preset(&self, config: &mut RunConfig, preset: WorldPreset) {
        let mut preset = WorldPreset {
            seed: self.seed,
            ..preset
        };
        if self.districts > 0 {
            preset.districts = self.districts;
            preset.name = format!("{}-d{}", preset.name, self.districts);
        }
        self.assets.apply(&mut preset);
        config.world_dir = self.world.clone().unwrap_or_else(|| {
            PathBuf::from(format!("out/world-{}-{:x}", preset.name, preset.seed))
        });
        config.preset = preset;
    }

    /// The world preset.
    pub fn world_preset(&self) -> WorldPreset {
        let mut p = world_preset(self.preset, self.seed, &self.assets);
        if let Some(n) = self.instances {
            p.instances = n;
            p.name = format!("{}-{n}", p.name);
        }
        if self.districts > 0 {
            p.districts = self.districts;
            p.name = format!("{}-d{}", p.name, self.districts);
        }
        p
    }

    /// The driver configuration.
    pub fn run_config(&self) -> anyhow::Result<RunConfig> {
        let preset = self.world_preset();
        let mut c = RunConfig {
            world_dir: self.world.clone().unwrap_or_else(|| {
                PathBuf::from(format!("out/world-{}-{:x}", preset.name, preset.seed))
            }),
            preset,
            frames: self.frames,
            policies: self.policy.iter().map(|&p| p.into()).collect(),
            eval_every: self.eval_every,
            size: self.size,
            render_every: self.render_every,
            blocking_render: self.blocking_render,
            frames_in_flight: self.frames_in_flight,
            deterministic: self.deterministic,
            all_geometry_reference: !self.opaque_only,
            near_only_too: self.compare_far_field,
            tlas_updates_too: self.compare_tlas_updates,
            tlas_fast_trace: self.tlas_fast_trace,
            static_fast_trace: self.static_fast_trace,
            out_dir: Some(self.out.clone()),
            maps: self.maps,
            ..RunConfig::default()
        };
        if self.tlas_max_updates > 0 {
            c.tlas_updates = TlasUpdates {
                max_updates: self.tlas_max_updates,
                max_misplaced: self
                    .tlas_max_misplaced
                    .unwrap_or(TlasUpdates::ON.max_misplaced),
                ..TlasUpdates::ON
            };
        }
        c.stream.load_radius = self.stream_radius;
        c.stream.unload_radius = self.stream_radius + 100.0;
        if let Some(n) = self.loads_in_flight {
            c.stream.max_in_flight = n;
        }
        let m = &mut c.managed;
        if let Some(mb) = self.budget_mb {
            m.memory.blas_bytes = (mb * 1024.0 * 1024.0) as u64;
        }
        if let Some(r) = self.r1 {
            m.residency.r1 = r;
        }
        if let Some(r) = self.r2 {
            m.residency.r2 = r;
        }
        if let Some(a) = self.cull_angle {
            m.cull.min_angle = a.to_radians();
        }
        if let Some(d) = self.cull_distance {
            m.cull.far_distance = d;
        }
        if let Some(px) = self.lod_px {
            m.lod.max_pixel_error = px;
        }
        if let Some(n) = self.release_frames {
            m.residency.release_threshold = n;
        }
        m.far_field.enabled = self.far_field;
        if let Some(px) = self.far_px {
            m.far_field.max_pixel_error = px;
        }
        if let Some(a) = self.far_keep_angle {
            m.far_field.keep_angle = a.to_radians();
        }
        if let Some(r) = self.far_keep_range {
            m.far_field.keep_range = r;
        }
        if let Some(ms) = self.max_build_ms {
            m.build.max_gpu_ms = ms;
        }
        if let Some(t) = self.max_build_tris {
            m.build.max_primitives = t;
        }
        if let Some(n) = self.max_builds {
            m.build.max_builds = n;
        }
        if c.policies.is_empty() {
            bail!("--policy needs at least one policy");
        }
        m.validate().context("the managed configuration")?;
        Ok(c)
    }
}

/// Logs to stderr, `RUST_LOG` or warnings.
pub fn init_tracing() {
    init_tracing_at("warn");
}

/// Logs to stderr, `RUST_LOG` or `default` (a filter such as `"info"`).
pub fn init_tracing_at(default: &str) {
    install_tracing(None::<tracing_subscriber::layer::Identity>, default);
}

/// [`init_tracing`] plus an extra layer that sees every span at any level (a profiler), and
/// no events.
pub fn init_tracing_with<L>(extra: Option<L>)
where
    L: tracing_subscriber::Layer<tracing_subscriber::Registry> + Send + Sync + 'static,
{
    install_tracing(extra, "warn");
}

/// Events to stderr through `RUST_LOG` or `default`, and `extra` for every span.
fn install_tracing<L>(extra: Option<L>, default: &str)
where
    L: tracing_subscriber::Layer<tracing_subscriber::Registry> + Send + Sync + 'static,
{
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    use tracing_subscriber::Layer;
    let spans = tracing_subscriber::filter::filter_fn(|m| m.is_span());
    tracing_subscriber::registry()
        .with(extra.map(|l| l.with_filter(spans)))
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_filter(
                    tracing_subscriber::EnvFilter::try_from_default_env()
                        .unwrap_or_else(|_| default.into()),
                ),
        )
        .init();
}

/// A progress bar that shows each policy's memory and TLAS size and the last error.
pub fn progress_bar(frames: u64, quiet: bool) -> (ProgressBar, impl FnMut(&Progress)) {
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(frames)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{bar:30} {pos}/{len} frames {elapsed_precise} eta {eta} {msg}",
        )
        .expect("a valid template"),
    );
    let b = bar.clone();
    let mut last_err: Vec<Option<f64>> = Vec::new();
    let update = move |p: &Progress| {
        b.set_position(p.frame + 1);
        last_err.resize(p.policies.len(), None);
        let mut msg = format!("{} levels", p.levels_loaded);
        for (i, (name, bytes, tlas, err)) in p.policies.iter().enumerate() {
            if err.is_some() {
                last_err[i] = *err;
            }
            msg.push_str(&format!(
                " | {name} {:.0} MB {tlas} inst{}",
                *bytes as f64 / 1e6,
                last_err[i].map_or(String::new(), |e| format!(" {:.2}%", e * 100.0))
            ));
        }
        b.set_message(msg);
    };
    (bar, update)
}

/// Runs the frame driver on `config` behind a progress bar (hidden with `quiet`), cleared when
/// the run succeeded; `on_frame` sees each frame's progress before the bar does.
pub fn run_with_progress(
    config: &RunConfig,
    quiet: bool,
    mut on_frame: impl FnMut(&Progress),
) -> anyhow::Result<RunReport> {
    let (bar, mut progress) = progress_bar(config.frames, quiet);
    let report = driver::run(config, &mut |p| {
        on_frame(p);
        progress(p);
    })?;
    bar.finish_and_clear();
    Ok(report)
}

/// What every stress example reports of a policy's run, flattened into its JSON under these
/// names: frames over the BLAS budget, the mean image error against the full-world ground
/// truth, and the validation messages.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct PolicyFigures {
    pub over_budget_frames: u64,
    pub hit_mismatch_mean: f64,
    pub shadow_mismatch_mean: f64,
    pub validation_messages: u64,
}

impl From<&PolicySummary> for PolicyFigures {
    fn from(p: &PolicySummary) -> Self {
        Self {
            over_budget_frames: p.over_budget_frames,
            hit_mismatch_mean: p.hit_mismatch_mean,
            shadow_mismatch_mean: p.shadow_mismatch_mean,
            validation_messages: p.validation_messages,
        }
    }
}

/// The managed policy's rows of a run's per-frame table.
pub fn managed_rows(rows: &[FrameRow]) -> Vec<&FrameRow> {
    rows.iter().filter(|r| r.policy == "managed").collect()
}

/// `f` of each row against its frame number: a chart series.
pub fn per_frame(rows: &[&FrameRow], f: impl Fn(&FrameRow) -> f64) -> Vec<(f64, f64)> {
    rows.iter().map(|r| (r.frame as f64, f(r))).collect()
}

/// The mean of `f` over `rows` (0 for no rows).
pub fn mean(rows: &[&FrameRow], f: impl Fn(&FrameRow) -> f64) -> f64 {
    rows.iter().map(|r| f(r)).sum::<f64>() / rows.len().max(1) as f64
}
