//! The baked format's figures: bytes per instance of a baked world, and the time to read and
//! decode all of it (the manifest, every level file, every mesh-LOD chunk of the mesh library,
//! one read each, the way the loader threads do), single-threaded, from a warm page cache.
//!
//! `cargo run --release -p rtstream-streaming --example format_load -- [--preset default|small:N]
//! [--reps 5] [--dir DIR] [--asset-dir DIR] [--json]`
//!
//! The world is generated and baked into DIR (a temporary directory by default) first, so the
//! files are in the format of the code being measured.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use rtstream_stats::Samples;
use rtstream_streaming::{bake, format, generate, read_manifest, Aabb, WorldPreset};

/// The baked format's figures: bytes per instance and the time to read a baked world.
#[derive(Debug, Parser)]
#[command(name = "format_load")]
struct Args {
    /// `default`, `large` or `small:N` (an N x N corner of the default map).
    #[arg(long, default_value = "default", value_parser = world_args::parse_preset)]
    preset: WorldPreset,
    /// Timed full reads (the median is reported).
    #[arg(long, default_value_t = 5)]
    reps: usize,
    /// Where to bake (replaced).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    assets: world_args::AssetArgs,
}

#[path = "support/world_args.rs"]
mod world_args;

/// One full read: (seconds for the level files, seconds for the mesh LODs, instances, LODs).
fn read_all(dir: &Path) -> anyhow::Result<(f64, f64, usize, usize)> {
    let manifest = read_manifest(dir)?;
    let bounds: Vec<Aabb> = manifest.meshes.iter().map(|m| m.bounds).collect();
    let t = Instant::now();
    let mut instances = 0;
    for l in &manifest.levels {
        let path = dir.join(&l.file);
        let bytes = std::fs::read(&path).with_context(|| path.display().to_string())?;
        let level = format::decode_level(&bytes, &bounds)?;
        instances += level.instances.len();
    }
    let levels_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let lib = dir.join(rtstream_streaming::bake::MESH_LIBRARY_FILE);
    let mut lods = 0;
    for m in &manifest.meshes {
        for (k, e) in m.lods.iter().enumerate() {
            let mut f = File::open(&lib)?;
            f.seek(SeekFrom::Start(e.offset))?;
            let mut buf = vec![0u8; e.len as usize];
            f.read_exact(&mut buf)?;
            let g = format::decode_lod(&buf, m.id, k)?;
            std::hint::black_box(&g);
            lods += 1;
        }
    }
    Ok((levels_s, t.elapsed().as_secs_f64(), instances, lods))
}

fn dir_bytes(dir: &Path) -> anyhow::Result<u64> {
    let mut total = 0;
    for e in std::fs::read_dir(dir)? {
        let e = e?;
        let md = e.metadata()?;
        total += if md.is_dir() {
            dir_bytes(&e.path())?
        } else {
            md.len()
        };
    }
    Ok(total)
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut preset = args.preset.clone();
    args.assets.apply(&mut preset);
    let dir = args
        .dir
        .unwrap_or_else(|| std::env::temp_dir().join("rtstream-format-load"));
    let _ = std::fs::remove_dir_all(&dir);
    let world = generate(&preset)?;
    let report = bake(&world, &dir)?;
    let instances = world.instance_count();
    let total = dir_bytes(&dir)?;

    let (mut total_s, mut levels_s, mut lods_s) = (Vec::new(), Vec::new(), Vec::new());
    let mut lods = 0;
    for _ in 0..args.reps.max(1) {
        let (l, m, n, k) = read_all(&dir)?;
        anyhow::ensure!(n == instances, "read {n} instances, baked {instances}");
        lods = k;
        levels_s.push(l);
        lods_s.push(m);
        total_s.push(l + m);
    }
    let reps = total_s.clone();
    let out = serde_json::json!({
        "preset": preset.name,
        "format_version": format::VERSION,
        "levels": world.levels.len(),
        "instances": instances,
        "mesh_lods": lods,
        "baked_bytes": total,
        "level_bytes": report.level_bytes,
        "mesh_library_bytes": report.mesh_library_bytes,
        "bytes_per_instance": total as f64 / instances as f64,
        "level_bytes_per_instance": report.level_bytes as f64 / instances as f64,
        "reps": args.reps.max(1),
        "load_s_each": reps,
        "load_s_median": Samples::new(total_s).median(),
        "levels_s_median": Samples::new(levels_s).median(),
        "mesh_lods_s_median": Samples::new(lods_s).median(),
    });
    if args.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}
