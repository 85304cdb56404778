//! Generates a preset world, bakes it to a directory and streams a camera across it.
//!
//! `cargo run --release -p rtstream-streaming --example bake_world -- [default|large|small:N] [DIR]
//! [--asset-dir DIR]`

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Parser;
use glam::Vec3;
use rtstream_streaming::{
    bake, generate, StreamConfig, StreamFocus, World, WorldEvent, WorldPreset,
};

#[path = "support/world_args.rs"]
mod world_args;

/// Generates a preset world, bakes it and streams a camera across it.
#[derive(Debug, Parser)]
#[command(name = "bake_world")]
struct Args {
    /// `default`, `large` or `small:N` (an N x N corner of the default map).
    #[arg(default_value = "default", value_parser = world_args::parse_preset)]
    preset: WorldPreset,
    /// Where to bake (default: <temp>/rtstream-world).
    dir: Option<PathBuf>,
    #[command(flatten)]
    assets: world_args::AssetArgs,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut preset = args.preset;
    args.assets.apply(&mut preset);
    let dir = args
        .dir
        .unwrap_or_else(|| std::env::temp_dir().join("rtstream-world"));

    let t = Instant::now();
    let world = generate(&preset)?;
    let s = world.stats();
    println!(
        "generated {} levels, {} instances ({} non-opaque, {} skinned), {} meshes in {:.2} s; {:.1} bytes/instance",
        s.levels,
        s.instances,
        s.non_opaque,
        s.skinned,
        s.meshes,
        t.elapsed().as_secs_f64(),
        world.bytes_per_instance()
    );
    let t = Instant::now();
    let report = bake(&world, &dir)?;
    println!(
        "baked to {} in {:.2} s: {report:?}",
        dir.display(),
        t.elapsed().as_secs_f64()
    );

    let mut w = World::open(&dir, StreamConfig::default())?;
    let (lo, hi) = (world.extent.min, world.extent.max);
    let (mut loads, mut unloads, mut lods, mut fails) = (0, 0, 0, 0);
    let t = Instant::now();
    let frames = 200;
    for f in 0..=frames {
        let k = f as f32 / frames as f32;
        let p = Vec3::new(lo.x + (hi.x - lo.x) * k, 2.0, lo.z + (hi.z - lo.z) * k);
        for e in w
            .update_until_idle(f, &[StreamFocus::from(p)], Duration::from_secs(10))
            .unwrap_or_else(|t| t.events)
        {
            match e {
                WorldEvent::LevelLoaded { .. } => loads += 1,
                WorldEvent::LevelUnloaded { .. } => unloads += 1,
                WorldEvent::MeshLodLoaded { .. } => lods += 1,
                WorldEvent::MeshLodEvicted { .. }
                | WorldEvent::ProxyLoaded { .. }
                | WorldEvent::ProxyEvicted { .. } => {}
                WorldEvent::LoadFailed { error, .. } => {
                    fails += 1;
                    eprintln!("load failed: {error}");
                }
            }
        }
    }
    println!(
        "flew across in {:.2} s: {loads} level loads, {unloads} unloads, {lods} LOD loads, {fails} failures; {:?}",
        t.elapsed().as_secs_f64(),
        w.stats()
    );
    Ok(())
}
