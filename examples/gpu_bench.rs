//! GPU acceleration-structure benchmark: BLAS build throughput (FAST_TRACE vs FAST_BUILD, batched
//! vs one build per call), compaction ratios, refit vs rebuild, TLAS build times — all from GPU
//! timestamps, on whatever device the context picks (lavapipe here, NVIDIA on the GPU machine).
//!
//! ```text
//! cargo run --release --example gpu_bench -- [--quick] [--models DIR] [--total-tris N] [--reps N] [--markdown]
//! ```
//! Prints one JSON object per measurement on stdout; `--markdown` adds tables on stderr.

use std::path::PathBuf;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{
    build_blas_now, compaction_sizes, time_blas_builds, time_refit_vs_rebuild, time_tlas_build,
    ContextDesc, GpuGeometry, MeshDesc, Validation, VulkanContext,
};

type BoxResult<T> = Result<T, Box<dyn std::error::Error>>;

struct Mesh {
    name: String,
    positions: Vec<[f32; 3]>,
    indices: Vec<u32>,
}

impl Mesh {
    fn desc(&self) -> MeshDesc<'_> {
        MeshDesc {
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

struct Args {
    models: Option<PathBuf>,
    total_tris: usize,
    markdown: bool,
    reps: usize,
    max_instances: usize,
}

fn parse() -> BoxResult<Args> {
    let mut a = Args {
        models: None,
        total_tris: 4_000_000,
        markdown: false,
        reps: 5,
        max_instances: 1_000_000,
    };
    let mut it = std::env::args().skip(1);
    while let Some(s) = it.next() {
        match s.as_str() {
            "--quick" => {
                a.total_tris = 1_000_000;
                a.reps = 3;
            }
            "--models" => a.models = Some(it.next().ok_or("--models DIR")?.into()),
            "--total-tris" => a.total_tris = it.next().ok_or("--total-tris N")?.parse()?,
            "--reps" => a.reps = it.next().ok_or("--reps N")?.parse()?,
            "--max-instances" => a.max_instances = it.next().ok_or("--max-instances N")?.parse()?,
            "--markdown" => a.markdown = true,
            "--json" => {}
            "-h" | "--help" => {
                println!("usage: gpu_bench [--quick] [--models DIR] [--total-tris N] [--reps N] [--max-instances N] [--markdown]");
                std::process::exit(0);
            }
            other => return Err(format!("unknown argument {other:?}").into()),
        }
    }
    Ok(a)
}

fn main() -> BoxResult<()> {
    let args = parse()?;
    let ctx = VulkanContext::new(&ContextDesc {
        validation: Validation::Off,
        ..Default::default()
    })?;
    let info = ctx.info().clone();
    eprintln!("device: {} ({:?}), {}", info.name, info.kind, info.driver);
    println!(
        "{{\"kind\":\"device\",\"name\":{:?},\"type\":\"{:?}\",\"driver\":{:?},\"scratch_align\":{},\"max_primitives\":{},\"max_storage_buffer_range\":{}}}",
        info.name, info.kind, info.driver, info.min_scratch_alignment, info.max_primitive_count, info.max_storage_buffer_range
    );
    let mut md = Vec::new();
    let fast_trace = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_COMPACTION;
    let fast_build = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_BUILD
        | vk::BuildAccelerationStructureFlagsKHR::ALLOW_UPDATE;

    // 1. BLAS build throughput.
    md.push(format!(
        "### BLAS build throughput — {} ({:?})\n\n| triangles/BLAS | BLASes | flags | mode | GPU ms | M tris/s | bytes/tri |\n|---:|---:|---|---|---:|---:|---:|",
        info.name, info.kind
    ));
    for size in [1_000usize, 10_000, 100_000, 1_000_000] {
        let mesh = grid(size, 0.0);
        let g = GpuGeometry::upload(&ctx, &mesh.desc())?;
        let count = (args.total_tris / size).clamp(1, 4096);
        for (fname, flags) in [("FAST_TRACE", fast_trace), ("FAST_BUILD", fast_build)] {
            for batched in [true, false] {
                let (ms, bytes) = time_blas_builds(&ctx, &g, count, flags, batched, args.reps)?;
                let tris = f64::from(g.triangle_count()) * count as f64;
                let mode = if batched { "batched" } else { "per_call" };
                println!(
                    "{{\"kind\":\"blas_build\",\"tris_per_blas\":{},\"blas_count\":{count},\"flags\":\"{fname}\",\"mode\":\"{mode}\",\"gpu_ms\":{ms:.4},\"mtris_per_s\":{:.2},\"bytes_per_blas\":{bytes}}}",
                    g.triangle_count(), tris / ms / 1e3
                );
                md.push(format!(
                    "| {} | {count} | {fname} | {mode} | {ms:.3} | {:.1} | {:.1} |",
                    g.triangle_count(),
                    tris / ms / 1e3,
                    bytes as f64 / f64::from(g.triangle_count())
                ));
            }
        }
        g.destroy(&ctx);
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
        .map(|m| GpuGeometry::upload(&ctx, &m.desc()))
        .collect::<Result<_, _>>()?;
    let c = compaction_sizes(&ctx, &geoms)?;
    md.push(format!("\n### Compaction (FAST_TRACE + ALLOW_COMPACTION) — {}\n\n| mesh | triangles | original bytes | compacted bytes | ratio |\n|---|---:|---:|---:|---:|", info.name));
    let (mut so, mut sc) = (0u64, 0u64);
    for (m, &(o, k)) in meshes.iter().zip(&c.sizes) {
        let tris = m.indices.len() / 3;
        so += o;
        sc += k;
        println!("{{\"kind\":\"compaction\",\"mesh\":{:?},\"triangles\":{tris},\"original_bytes\":{o},\"compacted_bytes\":{k},\"ratio\":{:.4}}}", m.name, k as f64 / o as f64);
        if tris >= 1_000 {
            md.push(format!(
                "| {} | {tris} | {o} | {k} | {:.3} |",
                m.name,
                k as f64 / o as f64
            ));
        }
    }
    println!("{{\"kind\":\"compaction_total\",\"meshes\":{},\"original_bytes\":{so},\"compacted_bytes\":{sc},\"ratio\":{:.4},\"copy_gpu_ms\":{:.4}}}", meshes.len(), sc as f64 / so as f64, c.copy_gpu_ms);
    md.push(format!("| **all {} meshes** (incl. those < 1k triangles) | | {so} | {sc} | **{:.3}** |\n\nAll compacting copies together: {:.3} ms GPU.", meshes.len(), sc as f64 / so as f64, c.copy_gpu_ms));
    for g in geoms {
        g.destroy(&ctx);
    }

    // 3. Refit vs rebuild of a deforming mesh.
    md.push(format!("\n### Refit vs rebuild (FAST_BUILD + ALLOW_UPDATE) — {}\n\n| triangles | refit GPU ms | rebuild GPU ms | rebuild / refit |\n|---:|---:|---:|---:|", info.name));
    for size in [10_000usize, 100_000] {
        let mut g = GpuGeometry::upload(&ctx, &grid(size, 0.0).desc())?;
        let (r, b) = time_refit_vs_rebuild(
            &ctx,
            &mut g,
            &mut |k| grid(size, k as f32 * 0.37).positions,
            args.reps,
        )?;
        println!("{{\"kind\":\"refit\",\"triangles\":{},\"refit_gpu_ms\":{r:.4},\"rebuild_gpu_ms\":{b:.4},\"rebuild_over_refit\":{:.2}}}", g.triangle_count(), b / r);
        md.push(format!(
            "| {} | {r:.3} | {b:.3} | {:.2} |",
            g.triangle_count(),
            b / r
        ));
        g.destroy(&ctx);
    }

    // 4. TLAS builds over a grid of instances of one small BLAS.
    md.push(format!("\n### TLAS build — {}\n\n| instances | flags | GPU ms | bytes | bytes/instance |\n|---:|---|---:|---:|---:|", info.name));
    let small = GpuGeometry::upload(&ctx, &grid(1_000, 0.0).desc())?;
    let blas = build_blas_now(
        &ctx,
        &small,
        vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE,
        "tlas bench blas",
    )?;
    for n in [1_000usize, 10_000, 100_000, 1_000_000]
        .into_iter()
        .filter(|&n| n <= args.max_instances)
    {
        let side = (n as f64).sqrt().ceil() as usize;
        let transforms: Vec<[f32; 16]> = (0..n)
            .map(|i| {
                glam::Mat4::from_translation(glam::Vec3::new(
                    (i % side) as f32 * 120.0,
                    0.0,
                    (i / side) as f32 * 120.0,
                ))
                .to_cols_array()
            })
            .collect();
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
            let (ms, bytes) = time_tlas_build(&ctx, &blas, &transforms, flags, args.reps)?;
            println!("{{\"kind\":\"tlas_build\",\"instances\":{n},\"flags\":\"{fname}\",\"gpu_ms\":{ms:.4},\"bytes\":{bytes}}}");
            md.push(format!(
                "| {n} | {fname} | {ms:.3} | {bytes} | {:.1} |",
                bytes as f64 / n as f64
            ));
        }
    }
    ctx.destroy_accel(blas);
    small.destroy(&ctx);
    if args.markdown {
        eprintln!("\n{}", md.join("\n"));
    }
    Ok(())
}
