//! Generates a world preset and bakes it (levels, mesh library, far-field proxies), printing
//! the bake report: files, bytes, and the proxies per quadtree depth (count, triangles, bytes
//! per proxy, error in metres) with their build time.
//!
//! ```text
//! cargo run --release --example bake_report -- [--preset default|small|large] [--seed N]
//!     [--out DIR] [--json]
//! ```

#[path = "support/cli.rs"]
mod cli;

use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use rtstream::streaming::proxy::read_proxies;
use rtstream::streaming::{bake, generate};
use serde::Serialize;

/// Bakes a world and reports what it wrote.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    /// World preset.
    #[arg(long, value_enum, default_value_t = cli::Preset::Default)]
    preset: cli::Preset,
    /// Seed.
    #[arg(long, default_value_t = 0x5EED)]
    seed: u64,
    #[command(flatten)]
    assets: cli::AssetArgs,
    /// Output directory (default: out/world-<preset>-<seed>).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Print the report as JSON on the last line.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Serialize)]
struct Depth {
    depth: u8,
    nodes: usize,
    triangles: u64,
    bytes_per_proxy_mean: f64,
    bytes_per_proxy_max: u64,
    error_m_mean: f64,
    error_m_max: f32,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let preset = cli::world_preset(cli.preset, cli.seed, &cli.assets);
    let dir = cli
        .out
        .unwrap_or_else(|| format!("out/world-{}-{:x}", preset.name, preset.seed).into());
    let t = Instant::now();
    let world = generate(&preset).context("generating the world")?;
    let gen_s = t.elapsed().as_secs_f64();
    let report = bake(&world, &dir).context("baking")?;
    let file = read_proxies(&dir, world.levels.len(), world.meshes.len())?
        .context("no proxy file written")?;
    let mut depths: Vec<Depth> = Vec::new();
    for d in 1..=4u8 {
        let nodes: Vec<usize> = (0..file.tree.nodes.len())
            .filter(|&i| file.tree.nodes[i].depth == d)
            .collect();
        if nodes.is_empty() {
            continue;
        }
        let bytes: Vec<u64> = nodes
            .iter()
            .map(|&i| {
                file.geometry[i]
                    .as_ref()
                    .map_or(0, |g| g.byte_size() as u64)
            })
            .collect();
        depths.push(Depth {
            depth: d,
            nodes: nodes.len(),
            triangles: nodes
                .iter()
                .map(|&i| u64::from(file.tree.nodes[i].triangles))
                .sum(),
            bytes_per_proxy_mean: bytes.iter().sum::<u64>() as f64 / nodes.len() as f64,
            bytes_per_proxy_max: bytes.iter().copied().max().unwrap_or(0),
            error_m_mean: nodes
                .iter()
                .map(|&i| f64::from(file.tree.nodes[i].error))
                .sum::<f64>()
                / nodes.len() as f64,
            error_m_max: nodes
                .iter()
                .map(|&i| file.tree.nodes[i].error)
                .fold(0.0, f32::max),
        });
    }
    println!(
        "{} world (seed {:#x}): {} levels, {} instances, generated in {:.1} s",
        preset.name,
        preset.seed,
        world.levels.len(),
        world.instance_count(),
        gen_s
    );
    println!(
        "baked to {}: {} level files ({:.1} MB), mesh library {:.1} MB, proxies {:.1} MB ({} nodes, {} triangles, {} landmarks listed, built in {:.2} s)",
        dir.display(),
        report.level_files,
        report.level_bytes as f64 / 1e6,
        report.mesh_library_bytes as f64 / 1e6,
        report.proxies.file_bytes as f64 / 1e6,
        report.proxies.nodes,
        report.proxies.triangles,
        report.proxies.landmarks,
        report.proxies.build_us as f64 / 1e6
    );
    println!("depth  blocks  nodes  triangles  bytes/proxy mean  max  error m mean  max");
    for d in &depths {
        println!(
            "{:>5}  {:>4}x{:<2} {:>5}  {:>9}  {:>16.0}  {:>6}  {:>12.2}  {:>6.2}",
            d.depth,
            1 << d.depth,
            1 << d.depth,
            d.nodes,
            d.triangles,
            d.bytes_per_proxy_mean,
            d.bytes_per_proxy_max,
            d.error_m_mean,
            d.error_m_max
        );
    }
    if cli.json {
        println!(
            "{}",
            serde_json::json!({
                "preset": preset.name,
                "seed": preset.seed,
                "levels": world.levels.len(),
                "instances": world.instance_count(),
                "level_bytes": report.level_bytes,
                "mesh_library_bytes": report.mesh_library_bytes,
                "proxy_file_bytes": report.proxies.file_bytes,
                "proxy_nodes": report.proxies.nodes,
                "proxy_triangles": report.proxies.triangles,
                "proxy_landmarks": report.proxies.landmarks,
                "proxy_build_ms": report.proxies.build_us as f64 / 1e3,
                "depths": depths,
            })
        );
    }
    Ok(())
}
