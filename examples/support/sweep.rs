//! Runs of the shared frame driver over sweep points (one device, one reference cache: the
//! ground truth of a path is rendered once for all points), with a progress bar per point.
//! Not every example that includes it uses every item.
#![allow(dead_code)]

use std::sync::Arc;

use anyhow::Context;
use rtstream::as_manager::backend::vulkan::{ContextDesc, VulkanContext};
use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, ReferenceCache, RunConfig, RunReport};

use super::cli;

/// What a sweep's summary reports about the sweep as a whole, flattened into its JSON under
/// these names: the device, the frames of each point, the frames over the BLAS budget summed
/// over the points, and the device's validation messages.
#[derive(Debug, serde::Serialize)]
pub struct Totals {
    pub device: String,
    pub frames: u64,
    pub over_budget_frames: u64,
    pub validation_messages: u64,
}

impl Totals {
    /// The totals of the points run from `base` on `ctx` (`reports`, at least one; each
    /// point's first policy).
    pub fn of(ctx: &VulkanContext, base: &RunConfig, reports: &[RunReport]) -> Self {
        Self {
            device: reports[0].summary.policies[0].backend.clone(),
            frames: base.frames,
            over_budget_frames: reports
                .iter()
                .map(|r| r.summary.policies[0].over_budget_frames)
                .sum(),
            validation_messages: ctx.validation_log().failure_count(),
        }
    }
}

/// The configuration every point of a sweep of the managed policy starts from: the command
/// line's (`run`), the managed policy alone, scored against the opaque ground truth only, and
/// no files from the driver (no maps, no output directory: the sweep writes its own summary).
pub fn managed_base(run: &cli::RunArgs) -> anyhow::Result<RunConfig> {
    let mut base = run.run_config()?;
    base.policies = vec![PolicyKind::Managed];
    base.maps = 0;
    base.all_geometry_reference = false;
    base.out_dir = None;
    Ok(base)
}

/// The device every point of a sweep from `base` runs on, with `base`'s validation setting.
pub fn context(base: &RunConfig) -> anyhow::Result<Arc<VulkanContext>> {
    Ok(Arc::new(VulkanContext::new(&ContextDesc {
        validation: base.validation,
        ..ContextDesc::default()
    })?))
}

/// One sweep point per value: `base` changed by `set`, titled with what `set` returns.
pub fn points<T>(
    base: &RunConfig,
    values: &[T],
    set: impl Fn(&mut RunConfig, &T) -> String,
) -> Vec<(String, RunConfig)> {
    values
        .iter()
        .map(|v| {
            let mut c = base.clone();
            let title = set(&mut c, v);
            (title, c)
        })
        .collect()
}

/// Runs every `(title, config)` in order on `ctx` and returns their reports.
pub fn run_points(
    ctx: &Arc<VulkanContext>,
    points: &[(String, RunConfig)],
    quiet: bool,
) -> anyhow::Result<Vec<RunReport>> {
    let mut cache = ReferenceCache::default();
    let mut reports = Vec::with_capacity(points.len());
    for (i, (title, config)) in points.iter().enumerate() {
        eprintln!("[{}/{}] {title}", i + 1, points.len());
        let (bar, mut progress) = cli::progress_bar(config.frames, quiet);
        let report = driver::run_cached(ctx.clone(), config, &mut cache, &mut progress)
            .with_context(|| format!("sweep point {title}"))?;
        bar.finish_and_clear();
        reports.push(report);
    }
    Ok(reports)
}
