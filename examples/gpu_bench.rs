//! GPU acceleration-structure benchmark: BLAS build throughput (FAST_TRACE vs FAST_BUILD, batched
//! vs one build per call), compaction ratios, refit vs rebuild, TLAS build times — all from GPU
//! timestamps, on whatever device the context picks (lavapipe here, NVIDIA on the GPU machine).
//! `--recording-only` measures instead the host's cost of recording builds (the driver's CPU
//! time in vkCmdBuildAccelerationStructuresKHR, which the manager pays inside `update`).
//!
//! ```text
//! cargo run --release --example gpu_bench -- [--quick] [--models DIR] [--total-tris N] [--reps N]
//!     [--max-instances N] [--trace WxH] [--trace-png DIR] [--markdown] [--recording-only]
//! ```
//! Prints one JSON object per measurement on stdout (a [`Record`], its `kind` first);
//! `--markdown` adds tables on stderr.
//!
//! Why one file over 600 lines: seven measurements run in order, each printing its records
//! (the `Record` types are at the top) and its Markdown table; split by measurement, one run
//! would be read across seven files.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::ensure;
use clap::Parser;
use serde::Serialize;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{
    build_blas_now, compaction_sizes, time_blas_builds, time_build_recording,
    time_refit_vs_rebuild, time_tlas_beside_builds, time_tlas_build, time_tlas_update, ContextDesc,
    GpuGeometry, SceneMesh, StaticInstance, StaticScene, TriangleGeometry, Validation,
    VulkanBackend, VulkanBackendDesc, VulkanContext,
};
use rtstream::as_manager::backend::CostOp;
use rtstream::as_manager::{
    AsManager, Config, FrameInput, GeometryData, InstanceDesc, LodDesc, LodGeometry, MeshDesc,
    MeshKind, Viewpoint,
};
use rtstream::stats::{nearest_rank, Samples};

#[path = "support/cli.rs"]
mod cli;

struct Mesh {
    name: String,
    positions: Vec<[f32; 3]>,
    indices: Vec<u32>,
}

impl Mesh {
    fn desc(&self) -> SceneMesh<'_> {
        SceneMesh {
            name: &self.name,
            positions: &self.positions,
            indices: &self.indices,
            opaque: true,
        }
    }
}

/// A displaced grid of about `tris` triangles (terrain-like; `phase` poses it).
fn grid(tris: usize, phase: f32) -> Mesh {
    let n = ((tris / 2) as f64).sqrt().ceil().max(1.0) as u32;
    let mut positions = Vec::with_capacity(((n + 1) * (n + 1)) as usize);
    for j in 0..=n {
        for i in 0..=n {
            let (x, z) = (i as f32 / n as f32 * 100.0, j as f32 / n as f32 * 100.0);
            let y = (x * 0.21 + phase).sin() * 3.0
                + (z * 0.17 - phase).cos() * 2.0
                + ((x + z) * 0.9).sin() * 0.3;
            positions.push([x, y, z]);
        }
    }
    let mut indices = Vec::with_capacity((n * n * 6) as usize);
    for j in 0..n {
        for i in 0..n {
            let a = j * (n + 1) + i;
            let (b, c) = (a + 1, a + n + 1);
            indices.extend([a, c, b, b, c, c + 1]);
        }
    }
    indices.truncate(tris.max(1) * 3);
    Mesh {
        name: format!("grid{tris}"),
        positions,
        indices,
    }
}

/// GPU acceleration-structure benchmark (GPU timestamps; JSON lines on stdout).
#[derive(Debug, Parser)]
#[command(name = "gpu_bench")]
struct Args {
    /// Fewer triangles and repetitions: `--total-tris 1000000 --reps 3` unless given.
    #[arg(long)]
    quick: bool,
    /// Directory of glTF models whose meshes join the compaction figures.
    #[arg(long, value_name = "DIR")]
    models: Option<PathBuf>,
    /// Triangles per BLAS-build measurement (default 4,000,000; 1,000,000 with `--quick`;
    /// 1 to 100,000,000: the manager measurement uploads a copy of a 100k-triangle mesh per
    /// 100k triangles).
    #[arg(long, value_name = "N", value_parser = count(1, MAX_TOTAL_TRIS))]
    total_tris: Option<usize>,
    /// Timed repetitions; the median is reported (default 5; 3 with `--quick`; 1 to 10,000).
    #[arg(long, value_name = "N", value_parser = count(1, MAX_REPS))]
    reps: Option<usize>,
    /// The largest TLAS measured, in instances.
    #[arg(long, value_name = "N", default_value_t = 1_000_000)]
    max_instances: usize,
    /// Also trace a ~100k-instance scene at WxH with a FAST_TRACE and a FAST_BUILD TLAS.
    #[arg(long = "trace", value_name = "WxH", value_parser = cli::parse_size)]
    trace_size: Option<(u32, u32)>,
    /// Write the traced frames as PNGs into this directory.
    #[arg(long, value_name = "DIR")]
    trace_png: Option<PathBuf>,
    /// Also print Markdown tables on stderr.
    #[arg(long)]
    markdown: bool,
    /// Accepted for symmetry with the other examples: the output is always JSON.
    #[arg(long, hide = true)]
    json: bool,
    /// Only the host's cost of recording BLAS builds (the driver's CPU time in
    /// vkCmdBuildAccelerationStructuresKHR, by flags, batch size and call), then stop.
    #[arg(long)]
    recording_only: bool,
    /// Only a frame's TLAS beside BLAS builds it does not reference: alone, after a barrier,
    /// without one, and in one call (GPU time, by TLAS size and batch), then stop.
    #[arg(long)]
    beside_only: bool,
}

/// The most triangles `--total-tris` takes.
const MAX_TOTAL_TRIS: u64 = 100_000_000;
/// The most repetitions `--reps` takes.
const MAX_REPS: u64 = 10_000;

/// `value_parser` of a `usize` count from `min` to `max`.
fn count(min: u64, max: u64) -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(min..=max)
}

impl Args {
    fn total_tris(&self) -> usize {
        self.total_tris
            .unwrap_or(if self.quick { 1_000_000 } else { 4_000_000 })
    }

    fn reps(&self) -> usize {
        self.reps.unwrap_or(if self.quick { 3 } else { 5 })
    }
}

/// One measurement, printed as one JSON line. Times are rounded as the tables show them
/// ([`round_to`]).
#[derive(Debug, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
enum Record<'a> {
    Device {
        name: &'a str,
        #[serde(rename = "type")]
        device_type: String,
        driver: &'a str,
        scratch_align: u64,
        max_primitives: u64,
        max_storage_buffer_range: u64,
    },
    BlasBuild {
        tris_per_blas: u32,
        blas_count: usize,
        flags: &'a str,
        mode: &'a str,
        gpu_ms: f64,
        mtris_per_s: f64,
        bytes_per_blas: u64,
    },
    Compaction {
        mesh: &'a str,
        triangles: usize,
        original_bytes: u64,
        compacted_bytes: u64,
        ratio: f64,
    },
    CompactionTotal {
        meshes: usize,
        original_bytes: u64,
        compacted_bytes: u64,
        ratio: f64,
        copy_gpu_ms: f64,
    },
    Refit {
        triangles: u32,
        refit_gpu_ms: f64,
        rebuild_gpu_ms: f64,
        rebuild_over_refit: f64,
    },
    TlasBuild {
        instances: usize,
        flags: &'a str,
        gpu_ms: f64,
        bytes: u64,
    },
    TlasUpdate {
        instances: usize,
        build_ms: f64,
        update_ms: f64,
        build_over_update: f64,
    },
    Sizes {
        triangles: u32,
        vertices: u32,
        class: &'a str,
        as_bytes: u64,
        build_scratch: u64,
        update_scratch: u64,
    },
    ManagerThroughput {
        /// `own`: the backend on the context that created the device; `external`: on a
        /// context imported with `VulkanContext::from_external` (the engine's path).
        device_path: &'a str,
        blas: usize,
        triangles: u64,
        raw_batched_gpu_ms: f64,
        manager_gpu_ms: f64,
        manager_update_wall_ms: f64,
        throughput_ratio: f64,
    },
    /// Host milliseconds of recording a build call (median), apart from the GPU's time.
    BuildRecording {
        tris_per_blas: u32,
        blas_count: usize,
        flags: &'a str,
        first_call_ms: f64,
        second_call_ms: f64,
        update_ms: Option<f64>,
    },
    /// GPU ms of a TLAS beside BLAS builds it does not reference (medians).
    Beside {
        tlas_records: usize,
        tris_per_blas: u32,
        blas_count: usize,
        builds_ms: f64,
        tlas_ms: f64,
        serial_ms: f64,
        no_barrier_ms: f64,
        one_call_ms: f64,
        tlas_first_ms: f64,
        tlas_first_mid_ms: f64,
        builds_first_ms: f64,
        builds_first_mid_ms: f64,
    },
    TlasTrace {
        flags: &'a str,
        instances: usize,
        width: u32,
        height: u32,
        tlas_build_gpu_ms: f64,
        frame_ms: f64,
        primary_ms: f64,
        shadow_ms: f64,
        ao_shade_ms: f64,
        hit_fraction: f64,
    },
}

impl Record<'_> {
    fn print(&self) -> anyhow::Result<()> {
        println!("{}", serde_json::to_string(self)?);
        Ok(())
    }
}

/// `x` rounded to `places` decimals (the precision the figures were always printed with).
/// The host's cost of recording BLAS builds, small meshes as the fly-through builds them, by
/// flags and batch size: the first call in a fresh command buffer, a second one in the same
/// command buffer, and an update in place where the flags allow it.
fn recording_costs(
    ctx: &VulkanContext,
    device: &str,
    reps: usize,
    md: &mut Vec<String>,
) -> anyhow::Result<()> {
    use vk::BuildAccelerationStructureFlagsKHR as F;
    md.push(format!("\n### Host cost of recording BLAS builds — {device}\n\nWall ms of one vkCmdBuildAccelerationStructuresKHR call on the CPU, median of {reps}:\n\n| triangles/BLAS | BLASes | flags | first call ms | second call ms | update ms |\n|---:|---:|---|---:|---:|---:|"));
    let variants = [
        ("FAST_BUILD", F::PREFER_FAST_BUILD),
        (
            "FAST_BUILD+COMPACTION",
            F::PREFER_FAST_BUILD | F::ALLOW_COMPACTION,
        ),
        (
            "FAST_TRACE+COMPACTION",
            F::PREFER_FAST_TRACE | F::ALLOW_COMPACTION,
        ),
        ("FAST_BUILD+UPDATE", F::PREFER_FAST_BUILD | F::ALLOW_UPDATE),
    ];
    for tris in [500usize, 5_000] {
        let g = GpuGeometry::upload(ctx, &grid(tris, 0.0).desc())?;
        for count in [1usize, 2, 8] {
            for (name, flags) in variants {
                let c = time_build_recording(ctx, &vec![&g; count], flags, reps)?;
                Record::BuildRecording {
                    tris_per_blas: g.triangle_count(),
                    blas_count: count,
                    flags: name,
                    first_call_ms: round_to(c.first_call_ms, 4),
                    second_call_ms: round_to(c.second_call_ms, 4),
                    update_ms: c.update_ms.map(|u| round_to(u, 4)),
                }
                .print()?;
                md.push(format!(
                    "| {} | {count} | {name} | {:.4} | {:.4} | {} |",
                    g.triangle_count(),
                    c.first_call_ms,
                    c.second_call_ms,
                    c.update_ms.map_or("—".into(), |u| format!("{u:.4}"))
                ));
            }
        }
        g.destroy(ctx);
    }
    Ok(())
}

/// A frame's TLAS beside BLAS builds it does not reference (FAST_BUILD TLAS, FAST_BUILD +
/// COMPACTION BLASes: the manager's defaults), by TLAS size and batch: each alone, the batch
/// then a barrier then the TLAS, the two calls without the barrier, and one call.
fn beside_builds(
    ctx: &VulkanContext,
    device: &str,
    reps: usize,
    md: &mut Vec<String>,
) -> anyhow::Result<()> {
    use vk::BuildAccelerationStructureFlagsKHR as F;
    md.push(format!("\n### A TLAS beside BLAS builds it does not reference — {device}\n\nGPU ms, median of {reps} submits x 8 (each way timed alone, in rotating order, a barrier after each):\n\n| TLAS records | triangles/BLAS | BLASes | builds alone | TLAS alone | builds, barrier, TLAS | no barrier | one call | TLAS, timestamp, builds (to the timestamp) | builds, timestamp, TLAS (to the timestamp) |\n|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"));
    let small = GpuGeometry::upload(ctx, &grid(1_000, 0.0).desc())?;
    let blas = build_blas_now(ctx, &small, F::PREFER_FAST_TRACE, "beside bench blas")?;
    for n in [13_000usize, 104_000] {
        let transforms = grid_transforms(n);
        for tris in [500usize, 5_000] {
            let g = GpuGeometry::upload(ctx, &grid(tris, 0.0).desc())?;
            for count in [1usize, 2, 8] {
                let r = time_tlas_beside_builds(
                    ctx,
                    &blas,
                    &transforms,
                    &vec![&g; count],
                    F::PREFER_FAST_BUILD | F::ALLOW_COMPACTION,
                    F::PREFER_FAST_BUILD,
                    reps,
                )?;
                Record::Beside {
                    tlas_records: n,
                    tris_per_blas: g.triangle_count(),
                    blas_count: count,
                    builds_ms: round_to(r.builds_ms, 4),
                    tlas_ms: round_to(r.tlas_ms, 4),
                    serial_ms: round_to(r.serial_ms, 4),
                    no_barrier_ms: round_to(r.no_barrier_ms, 4),
                    one_call_ms: round_to(r.one_call_ms, 4),
                    tlas_first_ms: round_to(r.tlas_first_ms, 4),
                    tlas_first_mid_ms: round_to(r.tlas_first_mid_ms, 4),
                    builds_first_ms: round_to(r.builds_first_ms, 4),
                    builds_first_mid_ms: round_to(r.builds_first_mid_ms, 4),
                }
                .print()?;
                md.push(format!(
                    "| {n} | {} | {count} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} ({:.3}) | {:.3} ({:.3}) |",
                    g.triangle_count(),
                    r.builds_ms,
                    r.tlas_ms,
                    r.serial_ms,
                    r.no_barrier_ms,
                    r.one_call_ms,
                    r.tlas_first_ms,
                    r.tlas_first_mid_ms,
                    r.builds_first_ms,
                    r.builds_first_mid_ms
                ));
            }
            g.destroy(ctx);
        }
    }
    ctx.destroy_accel(blas);
    small.destroy(ctx);
    Ok(())
}

fn round_to(x: f64, places: i32) -> f64 {
    let k = 10f64.powi(places);
    (x * k).round() / k
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (total_tris, reps) = (args.total_tris(), args.reps());
    let shared = Arc::new(VulkanContext::new(&ContextDesc {
        validation: Validation::Off,
        ..Default::default()
    })?);
    let ctx = &*shared;
    let info = ctx.info().clone();
    eprintln!("device: {} ({:?}), {}", info.name, info.kind, info.driver);
    Record::Device {
        name: &info.name,
        device_type: format!("{:?}", info.kind),
        driver: &info.driver,
        scratch_align: info.min_scratch_alignment,
        max_primitives: info.max_primitive_count,
        max_storage_buffer_range: info.max_storage_buffer_range,
    }
    .print()?;
    let mut md = Vec::new();
    let fast_trace = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION;
    let fast_build = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE;

    if args.beside_only {
        beside_builds(ctx, &info.name, reps.max(10), &mut md)?;
        if args.markdown {
            eprintln!("{}", md.join("\n"));
        }
        return Ok(());
    }
    if args.recording_only {
        recording_costs(ctx, &info.name, reps.max(20), &mut md)?;
        if args.markdown {
            eprintln!("{}", md.join("\n"));
        }
        return Ok(());
    }

    // 1. BLAS build throughput.
    md.push(format!(
        "### BLAS build throughput — {} ({:?})\n\n| triangles/BLAS | BLASes | flags | mode | GPU ms | M tris/s | bytes/tri |\n|---:|---:|---|---|---:|---:|---:|",
        info.name, info.kind
    ));
    for size in [1_000usize, 10_000, 100_000, 1_000_000] {
        let mesh = grid(size, 0.0);
        let g = GpuGeometry::upload(ctx, &mesh.desc())?;
        let count = (total_tris / size).clamp(1, 4096);
        for (fname, flags) in [("FAST_TRACE", fast_trace), ("FAST_BUILD", fast_build)] {
            for batched in [true, false] {
                let (ms, bytes) = time_blas_builds(ctx, &vec![&g; count], flags, batched, reps)?;
                let tris = f64::from(g.triangle_count()) * count as f64;
                let mode = if batched { "batched" } else { "per_call" };
                Record::BlasBuild {
                    tris_per_blas: g.triangle_count(),
                    blas_count: count,
                    flags: fname,
                    mode,
                    gpu_ms: round_to(ms, 4),
                    mtris_per_s: round_to(tris / ms / 1e3, 2),
                    bytes_per_blas: bytes,
                }
                .print()?;
                md.push(format!(
                    "| {} | {count} | {fname} | {mode} | {ms:.3} | {:.1} | {:.1} |",
                    g.triangle_count(),
                    tris / ms / 1e3,
                    bytes as f64 / f64::from(g.triangle_count())
                ));
            }
        }
        g.destroy(ctx);
    }

    // 2. Compaction ratios: real models (if given) and generated meshes.
    let mut meshes: Vec<Mesh> = Vec::new();
    if let Some(dir) = &args.models {
        let mut files: Vec<_> = std::fs::read_dir(dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        files.sort();
        for f in files
            .into_iter()
            .filter(|f| f.extension().is_some_and(|e| e == "glb" || e == "gltf"))
        {
            match rtstream::streaming::load_gltf(&f) {
                Ok(scene) => {
                    let stem = f
                        .file_stem()
                        .unwrap_or_default()
                        .to_string_lossy()
                        .into_owned();
                    meshes.extend(scene.meshes.into_iter().map(|m| Mesh {
                        name: format!("{stem}/{}", m.name),
                        positions: m.positions,
                        indices: m.indices,
                    }));
                }
                Err(e) => eprintln!("skipping {}: {e}", f.display()),
            }
        }
    }
    meshes.extend([1_000usize, 10_000, 100_000].map(|s| grid(s, 0.0)));
    let geoms: Vec<GpuGeometry> = meshes
        .iter()
        .map(|m| GpuGeometry::upload(ctx, &m.desc()))
        .collect::<Result<_, _>>()?;
    let c = compaction_sizes(ctx, &geoms)?;
    md.push(format!("\n### Compaction (FAST_TRACE + ALLOW_COMPACTION) — {}\n\n| mesh | triangles | original bytes | compacted bytes | ratio |\n|---|---:|---:|---:|---:|", info.name));
    let (mut so, mut sc) = (0u64, 0u64);
    for (m, &(o, k)) in meshes.iter().zip(&c.sizes) {
        let tris = m.indices.len() / 3;
        so += o;
        sc += k;
        Record::Compaction {
            mesh: &m.name,
            triangles: tris,
            original_bytes: o,
            compacted_bytes: k,
            ratio: round_to(k as f64 / o as f64, 4),
        }
        .print()?;
        if tris >= 1_000 {
            md.push(format!(
                "| {} | {tris} | {o} | {k} | {:.3} |",
                m.name,
                k as f64 / o as f64
            ));
        }
    }
    Record::CompactionTotal {
        meshes: meshes.len(),
        original_bytes: so,
        compacted_bytes: sc,
        ratio: round_to(sc as f64 / so as f64, 4),
        copy_gpu_ms: round_to(c.copy_gpu_ms, 4),
    }
    .print()?;
    md.push(format!("| **all {} meshes** (incl. those < 1k triangles) | | {so} | {sc} | **{:.3}** |\n\nAll compacting copies together: {:.3} ms GPU.", meshes.len(), sc as f64 / so as f64, c.copy_gpu_ms));
    for g in geoms {
        g.destroy(ctx);
    }

    // 3. Refit vs rebuild of a deforming mesh.
    md.push(format!("\n### Refit vs rebuild (FAST_BUILD + ALLOW_UPDATE) — {}\n\n| triangles | refit GPU ms | rebuild GPU ms | rebuild / refit |\n|---:|---:|---:|---:|", info.name));
    for size in [10_000usize, 100_000] {
        let mut g = GpuGeometry::upload(ctx, &grid(size, 0.0).desc())?;
        let (r, b) = time_refit_vs_rebuild(
            ctx,
            &mut g,
            &mut |k| grid(size, k as f32 * 0.37).positions,
            reps,
        )?;
        Record::Refit {
            triangles: g.triangle_count(),
            refit_gpu_ms: round_to(r, 4),
            rebuild_gpu_ms: round_to(b, 4),
            rebuild_over_refit: round_to(b / r, 2),
        }
        .print()?;
        md.push(format!(
            "| {} | {r:.3} | {b:.3} | {:.2} |",
            g.triangle_count(),
            b / r
        ));
        g.destroy(ctx);
    }

    // 4. TLAS builds over a grid of instances of one small BLAS.
    md.push(format!("\n### TLAS build — {}\n\n| instances | flags | GPU ms | bytes | bytes/instance |\n|---:|---|---:|---:|---:|", info.name));
    let small = GpuGeometry::upload(ctx, &grid(1_000, 0.0).desc())?;
    let blas = build_blas_now(
        ctx,
        &small,
        vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
        "tlas bench blas",
    )?;
    for n in [1_000usize, 10_000, 100_000, 1_000_000]
        .into_iter()
        .filter(|&n| n <= args.max_instances)
    {
        let transforms = grid_transforms(n);
        for (fname, flags) in [
            (
                "FAST_TRACE",
                vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
            ),
            (
                "FAST_BUILD",
                vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
            ),
        ] {
            let (ms, bytes) = time_tlas_build(ctx, &blas, &transforms, flags, reps)?;
            Record::TlasBuild {
                instances: n,
                flags: fname,
                gpu_ms: round_to(ms, 4),
                bytes,
            }
            .print()?;
            md.push(format!(
                "| {n} | {fname} | {ms:.3} | {bytes} | {:.1} |",
                bytes as f64 / n as f64
            ));
        }
    }
    // 4b. TLAS update in place against a rebuild (PREFER_FAST_TRACE | ALLOW_UPDATE, every
    // instance moved between updates).
    md.push(format!("\n### TLAS update vs rebuild (FAST_TRACE + ALLOW_UPDATE, every instance moved) — {}\n\n| instances | build GPU ms | update GPU ms | build / update |\n|---:|---:|---:|---:|", info.name));
    for n in [1_000usize, 10_000, 100_000]
        .into_iter()
        .filter(|&n| n <= args.max_instances)
    {
        let transforms = grid_transforms(n);
        let (build_ms, update_ms) = time_tlas_update(ctx, &blas, &transforms, reps)?;
        let ratio = build_ms / update_ms.max(1e-6);
        Record::TlasUpdate {
            instances: n,
            build_ms: round_to(build_ms, 4),
            update_ms: round_to(update_ms, 4),
            build_over_update: round_to(ratio, 2),
        }
        .print()?;
        md.push(format!(
            "| {n} | {build_ms:.3} | {update_ms:.3} | {ratio:.2} |"
        ));
    }
    ctx.destroy_accel(blas);
    small.destroy(ctx);

    // 5. Reported sizes (no builds): the data the model backend's size model is fitted to.
    md.push(format!("\n### vkGetAccelerationStructureBuildSizesKHR — {}\n\n| triangles | vertices | class | AS bytes | build scratch | update scratch |\n|---:|---:|---|---:|---:|---:|", info.name));
    for tris in [12u32, 100, 1_000, 10_000, 100_000, 1_000_000] {
        let verts = tris / 2 + 2;
        let g = TriangleGeometry {
            vertex_address: 0,
            vertex_format: vk::Format::R32G32B32_SFLOAT,
            index_type: vk::IndexType::UINT32,
            vertex_stride: 12,
            max_vertex: verts - 1,
            index_address: 0,
            triangle_count: tris,
            opaque: true,
        };
        for (class, flags) in [("static", fast_trace), ("skinned", fast_build)] {
            let s = ctx.blas_sizes(&[g], flags);
            Record::Sizes {
                triangles: tris,
                vertices: verts,
                class,
                as_bytes: s.storage,
                build_scratch: s.build_scratch,
                update_scratch: s.update_scratch,
            }
            .print()?;
            md.push(format!(
                "| {tris} | {verts} | {class} | {} | {} | {} |",
                s.storage, s.build_scratch, s.update_scratch
            ));
        }
    }

    // 6. Builds admitted through the manager vs one raw batched build of the same geometry.
    let (mesh_tris, meshes_n) = (100_000usize, (total_tris / 100_000).max(2));
    let grid_mesh = grid(mesh_tris, 0.0);
    // Distinct buffers per BLAS, as the manager's path has (no cache-hot shared input).
    let copies: Vec<GpuGeometry> = (0..meshes_n)
        .map(|_| GpuGeometry::upload(ctx, &grid_mesh.desc()))
        .collect::<Result<_, _>>()?;
    let copy_refs: Vec<&GpuGeometry> = copies.iter().collect();
    // The engine's path: a second context imported from this one's device, instance, queue and
    // allocator (`from_external`), measured in the same runs as the context's own path.
    let imported = Arc::new(VulkanContext::from_external(shared.as_external())?);
    let paths = [("own", shared.clone()), ("external", imported.clone())];
    let mut raw_ms = Vec::new();
    let mut mgr_ms = vec![Vec::new(); paths.len()];
    let mut mgr_wall = vec![Vec::new(); paths.len()];
    let data = Arc::new(GeometryData {
        positions: grid_mesh.positions.clone(),
        indices: grid_mesh.indices.clone(),
    });
    for _ in 0..reps.max(3) {
        raw_ms.push(time_blas_builds(ctx, &copy_refs, fast_trace, true, 1)?.0);
        for (k, (_, path_ctx)) in paths.iter().enumerate() {
            let (ms, wall) = manager_build_ms(path_ctx.clone(), &data, meshes_n)?;
            mgr_ms[k].push(ms);
            mgr_wall[k].push(wall);
        }
    }
    drop(copy_refs);
    for g in copies {
        g.destroy(ctx);
    }
    let med = |v: &[f64]| Samples::new(v.to_vec()).median();
    let raw = med(&raw_ms);
    let tris = (mesh_tris * meshes_n) as f64;
    md.push(format!("\n### Builds through the manager vs one raw batched build — {}\n\n{meshes_n} static BLASes of {mesh_tris} triangles (FAST_TRACE + ALLOW_COMPACTION), one frame, median of {} runs (wall: that `update`'s CPU time — residency, schedule, uploads, recording — plus submit and wait):\n\n| path | GPU ms | M tris/s | manager / raw | wall ms |\n|---|---:|---:|---:|---:|\n| raw batched build | {raw:.3} | {:.1} | | |", info.name, reps.max(3), tris / raw / 1e3));
    for (k, (name, _)) in paths.iter().enumerate() {
        let (mgr, wall) = (med(&mgr_ms[k]), med(&mgr_wall[k]));
        Record::ManagerThroughput {
            device_path: name,
            blas: meshes_n,
            triangles: (mesh_tris * meshes_n) as u64,
            raw_batched_gpu_ms: round_to(raw, 4),
            manager_gpu_ms: round_to(mgr, 4),
            manager_update_wall_ms: round_to(wall, 3),
            throughput_ratio: round_to(raw / mgr, 4),
        }
        .print()?;
        md.push(format!(
            "| through `AsManager::update`, {name} device | {mgr:.3} | {:.1} | **{:.3}** | {wall:.1} |",
            tris / mgr / 1e3,
            raw / mgr
        ));
    }
    drop(paths);
    drop(imported);

    // 7. TLAS flags: trace time of the same scene with a FAST_TRACE vs a FAST_BUILD TLAS.
    if let Some((w, h)) = args.trace_size {
        let meshes_data: Vec<Mesh> = (0..4).map(|k| grid(1_000 << k, k as f32)).collect();
        let descs: Vec<SceneMesh<'_>> = meshes_data.iter().map(Mesh::desc).collect();
        let side = 316usize; // ~100k instances
        let instances: Vec<StaticInstance> = (0..side * side)
            .map(|i| {
                let (x, z) = ((i % side) as f32 * 30.0, (i / side) as f32 * 30.0);
                let m = glam::Mat4::from_scale_rotation_translation(
                    glam::Vec3::splat(0.25),
                    glam::Quat::from_rotation_y(i as f32),
                    glam::Vec3::new(x, 0.0, z),
                );
                StaticInstance {
                    mesh: (i % 4) as u32,
                    transform: m.to_cols_array(),
                    custom_index: (i % 4) as u32,
                    mask: 0xff,
                }
            })
            .collect();
        let mut renderer = rtstream::renderer::Renderer::new(shared.clone())?;
        md.push(format!("\n### TLAS flags: trace time — {}\n\n{} instances of 4 meshes (1k–8k triangles), {w}x{h}, primary + hard shadow + 1 AO ray per pixel ({:?} path), median of {} frames:\n\n| TLAS flags | TLAS build ms (GPU) | frame ms (wall) | primary ms | shadow ms | AO+shade ms |\n|---|---:|---:|---:|---:|---:|", info.name, instances.len(), renderer.path(), reps));
        for (fname, flags) in [
            (
                "FAST_TRACE",
                vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
            ),
            (
                "FAST_BUILD",
                vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD,
            ),
        ] {
            let scene = StaticScene::build_with_tlas_flags(ctx, &descs, &instances, flags)?;
            let shading: Vec<rtstream::renderer::InstanceShading> = scene
                .meshes
                .iter()
                .map(|m| rtstream::renderer::InstanceShading {
                    vertices: m.geometry.vertices.address,
                    indices: m.geometry.indices.address,
                    base_color: [0.7, 0.7, 0.7, 1.0],
                })
                .collect();
            let cam = rtstream::renderer::Camera::look_at(
                glam::Vec3::new(-200.0, 400.0, -200.0),
                glam::Vec3::new(4000.0, 0.0, 4000.0),
                50f32.to_radians(),
            );
            let desc = rtstream::renderer::RenderDesc::new(w, h, cam);
            renderer.render(scene.tlas_ref(), &shading, &desc)?; // warm-up
            let mut frames = Vec::new();
            for _ in 0..reps {
                frames.push(renderer.render(scene.tlas_ref(), &shading, &desc)?);
            }
            frames.sort_by(|a, b| a.render_ms.total_cmp(&b.render_ms));
            let f = &frames[nearest_rank(frames.len(), 0.5)]; // the median frame
            let tlas_ms = time_tlas_build(
                ctx,
                &scene.meshes[0].blas,
                &instances.iter().map(|i| i.transform).collect::<Vec<_>>(),
                flags,
                reps,
            )?
            .0;
            Record::TlasTrace {
                flags: fname,
                instances: instances.len(),
                width: w,
                height: h,
                tlas_build_gpu_ms: round_to(tlas_ms, 4),
                frame_ms: round_to(f.render_ms, 3),
                primary_ms: round_to(f.passes.primary_ms, 3),
                shadow_ms: round_to(f.passes.shadow_ms, 3),
                ao_shade_ms: round_to(f.passes.ao_shade_ms, 3),
                hit_fraction: round_to(f.hit_fraction(), 3),
            }
            .print()?;
            md.push(format!(
                "| {fname} | {tlas_ms:.3} | {:.3} | {:.3} | {:.3} | {:.3} |",
                f.render_ms, f.passes.primary_ms, f.passes.shadow_ms, f.passes.ao_shade_ms
            ));
            if let Some(out) = &args.trace_png {
                f.save_png(out.join(format!("tlas_{fname}.png")))?;
            }
            scene.destroy(ctx);
        }
    }

    if args.markdown {
        eprintln!("\n{}", md.join("\n"));
    }
    Ok(())
}

/// One frame of `meshes_n` distinct static BLASes admitted through `AsManager::update` on a
/// backend on `ctx`: (GPU ms of the builds from the backend's timestamps, wall ms of that
/// `update` plus submit and wait).
fn manager_build_ms(
    ctx: Arc<VulkanContext>,
    data: &Arc<GeometryData>,
    meshes_n: usize,
) -> anyhow::Result<(f64, f64)> {
    let mut config = Config::default();
    config.residency.create_threshold = 0;
    config.residency.r1 = 5_000.0;
    config.residency.r2 = 6_000.0;
    config.cull.far_distance = 10_000.0;
    config.build.max_primitives = u64::MAX / 4;
    config.build.max_gpu_ms = 1e9;
    config.memory.blas_bytes = 64 << 30;
    // The raw batch's flags (FAST_TRACE + ALLOW_COMPACTION), not the backend's default.
    let backend = VulkanBackend::new(
        ctx,
        VulkanBackendDesc {
            static_blas_prefer: vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
            ..VulkanBackendDesc::default()
        },
    )?;
    let mut manager = AsManager::new(config, backend)?;
    for k in 0..meshes_n {
        // Distinct meshes (same geometry): one BLAS each, as in the raw batch.
        let mesh = manager.register_mesh(MeshDesc::new(
            format!("m{k}"),
            MeshKind::Static,
            80.0,
            vec![LodDesc {
                geometry: LodGeometry::Data(data.clone()),
                geometric_error: 0.0,
            }],
        ))?;
        manager.add_instance(InstanceDesc::new(
            mesh,
            glam::Affine3A::from_translation(glam::Vec3::new(k as f32 * 10.0, 0.0, 50.0)),
        ))?;
    }
    let cams = [Viewpoint::new(glam::Vec3::ZERO, glam::Vec3::Z)];
    let t0 = std::time::Instant::now();
    let out = manager.update(FrameInput {
        frame: 0,
        cameras: &cams,
    })?;
    let built = out.stats.builds;
    manager.backend_mut().wait_idle()?;
    let wall = t0.elapsed().as_secs_f64() * 1e3;
    // The next frames harvest frame 0's timestamps.
    for frame in 1..3 {
        manager.update(FrameInput {
            frame,
            cameras: &cams,
        })?;
    }
    // Frame 0's builds ran beside its TLAS (empty: a BLAS built in frame N is named from
    // N+1), timed as one pair that the TLAS's measurement carries (`Measurement::beside`;
    // the builds report 0). The pair counts against the manager: an empty TLAS is its
    // whole overhead. Later frames' TLASes have no builds beside them.
    let ms: f64 = manager
        .backend()
        .measurement_log()
        .filter(|m| m.op == CostOp::BuildStatic || (m.op == CostOp::Tlas && m.beside))
        .map(|m| m.gpu_ms)
        .sum();
    ensure!(
        ms > 0.0,
        "no GPU time measured for the manager's {meshes_n} builds"
    );
    ensure!(
        built as usize == meshes_n,
        "the manager admitted {built} of {meshes_n} builds in one frame"
    );
    Ok((ms, wall))
}

/// `n` instance transforms on a square grid 120 m apart (the TLAS measurements' instances).
fn grid_transforms(n: usize) -> Vec<[f32; 16]> {
    let side = (n as f64).sqrt().ceil() as usize;
    (0..n)
        .map(|i| {
            let at = glam::Vec3::new((i % side) as f32 * 120.0, 0.0, (i / side) as f32 * 120.0);
            glam::Mat4::from_translation(at).to_cols_array()
        })
        .collect()
}
