//! Runs of the shared frame driver over sweep points (one device, one reference cache: the
//! ground truth of a path is rendered once for all points), with a progress bar per point.
//! Not every example that includes it uses every item.
#![allow(dead_code)]

use std::sync::Arc;

use anyhow::Context;
use rtstream::as_manager::backend::vulkan::{ContextDesc, VulkanContext};
use rtstream::driver::{self, ReferenceCache, RunConfig, RunReport};

use super::cli;

/// The device every point of a sweep from `base` runs on, with `base`'s validation setting.
pub fn context(base: &RunConfig) -> anyhow::Result<Arc<VulkanContext>> {
    Ok(Arc::new(VulkanContext::new(&ContextDesc {
        validation: base.validation,
        ..ContextDesc::default()
    })?))
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
