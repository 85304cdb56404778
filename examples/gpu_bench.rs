//! GPU acceleration-structure benchmark: BLAS build throughput (FAST_TRACE vs FAST_BUILD, batched
//! vs one build per call), compaction ratios, refit vs rebuild, TLAS build times — all from GPU
//! timestamps, on whatever device the context picks (lavapipe here, NVIDIA on the GPU machine).
//!
//! ```text
//! cargo run --release --example gpu_bench -- [--quick] [--models DIR] [--total-tris N] [--reps N] [--markdown]
//! ```
//! Prints one JSON object per measurement on stdout; `--markdown` adds tables on stderr.

use std::path::PathBuf;
use std::sync::Arc;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{
    build_blas_now, compaction_sizes, time_blas_builds, time_refit_vs_rebuild, time_tlas_build,
    ContextDesc, GpuGeometry, InstanceDesc as SceneInstance, MeshDesc, StaticScene,
    TriangleGeometry, Validation, VulkanBackend, VulkanBackendDesc, VulkanContext,
};
use rtstream::as_manager::backend::CostOp;
use rtstream::as_manager::{
    AsManager, Camera, Config, FrameInput, GeometryData, InstanceDesc, LodDesc, LodGeometry,
    MeshKind,
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
    trace_size: Option<(u32, u32)>,
    trace_png: Option<PathBuf>,
}

fn parse() -> BoxResult<Args> {
    let mut a = Args {
        models: None,
        total_tris: 4_000_000,
        markdown: false,
        reps: 5,
        max_instances: 1_000_000,
        trace_size: None,
        trace_png: None,
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
            "--trace" => {
                let v = it.next().ok_or("--trace WxH")?;
                let (w, h) = v.split_once('x').ok_or("--trace WxH")?;
                a.trace_size = Some((w.parse()?, h.parse()?));
            }
            "--trace-png" => a.trace_png = Some(it.next().ok_or("--trace-png DIR")?.into()),
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
    let shared = Arc::new(VulkanContext::new(&ContextDesc {
        validation: Validation::Off,
        ..Default::default()
    })?);
    let ctx = &*shared;
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
        let g = GpuGeometry::upload(ctx, &mesh.desc())?;
        let count = (args.total_tris / size).clamp(1, 4096);
        for (fname, flags) in [("FAST_TRACE", fast_trace), ("FAST_BUILD", fast_build)] {
            for batched in [true, false] {
                let (ms, bytes) =
                    time_blas_builds(ctx, &vec![&g; count], flags, batched, args.reps)?;
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
            args.reps,
        )?;
        println!("{{\"kind\":\"refit\",\"triangles\":{},\"refit_gpu_ms\":{r:.4},\"rebuild_gpu_ms\":{b:.4},\"rebuild_over_refit\":{:.2}}}", g.triangle_count(), b / r);
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
            let (ms, bytes) = time_tlas_build(ctx, &blas, &transforms, flags, args.reps)?;
            println!("{{\"kind\":\"tlas_build\",\"instances\":{n},\"flags\":\"{fname}\",\"gpu_ms\":{ms:.4},\"bytes\":{bytes}}}");
            md.push(format!(
                "| {n} | {fname} | {ms:.3} | {bytes} | {:.1} |",
                bytes as f64 / n as f64
            ));
        }
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
            println!("{{\"kind\":\"sizes\",\"triangles\":{tris},\"vertices\":{verts},\"class\":\"{class}\",\"as_bytes\":{},\"build_scratch\":{},\"update_scratch\":{}}}", s.storage, s.build_scratch, s.update_scratch);
            md.push(format!(
                "| {tris} | {verts} | {class} | {} | {} | {} |",
                s.storage, s.build_scratch, s.update_scratch
            ));
        }
    }

    // 6. Builds admitted through the manager vs one raw batched build of the same geometry.
    let (mesh_tris, meshes_n) = (100_000usize, (args.total_tris / 100_000).max(2));
    let grid_mesh = grid(mesh_tris, 0.0);
    // Distinct buffers per BLAS, as the manager's path has (no cache-hot shared input).
    let copies: Vec<GpuGeometry> = (0..meshes_n)
        .map(|_| GpuGeometry::upload(ctx, &grid_mesh.desc()))
        .collect::<Result<_, _>>()?;
    let copy_refs: Vec<&GpuGeometry> = copies.iter().collect();
    let mut raw_ms = Vec::new();
    let mut mgr_ms = Vec::new();
    let mut mgr_wall = Vec::new();
    let data = Arc::new(GeometryData {
        positions: grid_mesh.positions.clone(),
        indices: grid_mesh.indices.clone(),
    });
    for _ in 0..args.reps.max(3) {
        raw_ms.push(time_blas_builds(ctx, &copy_refs, fast_trace, true, 1)?.0);
        let mut config = Config::default();
        config.residency.create_threshold = 0;
        config.residency.r1 = 5_000.0;
        config.residency.r2 = 6_000.0;
        config.cull.far_distance = 10_000.0;
        config.build.max_primitives = u64::MAX / 4;
        config.build.max_gpu_ms = 1e9;
        config.memory.blas_bytes = 64 << 30;
        let backend = VulkanBackend::new(shared.clone(), VulkanBackendDesc::default())?;
        let manager = AsManager::new(config, backend)?;
        for k in 0..meshes_n {
            // Distinct meshes (same geometry): one BLAS each, as in the raw batch.
            let mesh = manager.register_mesh(rtstream::as_manager::MeshDesc::new(
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
        let mut manager = manager;
        let cams = [Camera::new(glam::Vec3::ZERO, glam::Vec3::Z)];
        let t0 = std::time::Instant::now();
        let out = manager.update(FrameInput {
            frame: 0,
            cameras: &cams,
        })?;
        let built = out.stats.builds;
        manager.backend_mut().wait_idle()?;
        mgr_wall.push(t0.elapsed().as_secs_f64() * 1e3);
        // The next frame harvests frame 0's timestamps.
        manager.update(FrameInput {
            frame: 1,
            cameras: &cams,
        })?;
        manager.update(FrameInput {
            frame: 2,
            cameras: &cams,
        })?;
        let ms: f64 = manager
            .backend()
            .measurement_log()
            .filter(|m| m.op == CostOp::BuildStatic)
            .map(|m| m.gpu_ms)
            .sum();
        if built as usize != meshes_n {
            return Err(
                format!("the manager admitted {built} of {meshes_n} builds in one frame").into(),
            );
        }
        mgr_ms.push(ms);
    }
    drop(copy_refs);
    for g in copies {
        g.destroy(ctx);
    }
    let med = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (raw, mgr, wall) = (med(raw_ms), med(mgr_ms), med(mgr_wall));
    let tris = (mesh_tris * meshes_n) as f64;
    println!("{{\"kind\":\"manager_throughput\",\"blas\":{meshes_n},\"triangles\":{tris},\"raw_batched_gpu_ms\":{raw:.4},\"manager_gpu_ms\":{mgr:.4},\"manager_update_wall_ms\":{wall:.3},\"throughput_ratio\":{:.4}}}", raw / mgr);
    md.push(format!("\n### Builds through the manager vs one raw batched build — {}\n\n{meshes_n} static BLASes of {mesh_tris} triangles (FAST_TRACE + ALLOW_COMPACTION), one frame, median of {} runs:\n\n| path | GPU ms | M tris/s |\n|---|---:|---:|\n| raw batched build | {raw:.3} | {:.1} |\n| through `AsManager::update` (VulkanBackend) | {mgr:.3} | {:.1} |\n\nManager / raw throughput: **{:.3}**. Wall time of that `update` (CPU: residency, schedule, uploads, recording; plus submit and wait): {wall:.1} ms.", info.name, args.reps.max(3), tris / raw / 1e3, tris / mgr / 1e3, raw / mgr));

    // 7. TLAS flags: trace time of the same scene with a FAST_TRACE vs a FAST_BUILD TLAS.
    if let Some((w, h)) = args.trace_size {
        let meshes_data: Vec<Mesh> = (0..4).map(|k| grid(1_000 << k, k as f32)).collect();
        let descs: Vec<MeshDesc<'_>> = meshes_data.iter().map(Mesh::desc).collect();
        let side = 316usize; // ~100k instances
        let instances: Vec<SceneInstance> = (0..side * side)
            .map(|i| {
                let (x, z) = ((i % side) as f32 * 30.0, (i / side) as f32 * 30.0);
                let m = glam::Mat4::from_scale_rotation_translation(
                    glam::Vec3::splat(0.25),
                    glam::Quat::from_rotation_y(i as f32),
                    glam::Vec3::new(x, 0.0, z),
                );
                SceneInstance {
                    mesh: (i % 4) as u32,
                    transform: m.to_cols_array(),
                    custom_index: (i % 4) as u32,
                    mask: 0xff,
                }
            })
            .collect();
        let mut renderer = rtstream::renderer::Renderer::new(shared.clone())?;
        md.push(format!("\n### TLAS flags: trace time — {}\n\n{} instances of 4 meshes (1k–8k triangles), {w}x{h}, primary + hard shadow + 1 AO ray per pixel ({:?} path), median of {} frames:\n\n| TLAS flags | TLAS build ms (GPU) | frame ms (wall) | primary ms | shadow ms | AO+shade ms |\n|---|---:|---:|---:|---:|---:|", info.name, instances.len(), renderer.path(), args.reps));
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
            renderer.render(scene.tlas.raw, &shading, &desc)?; // warm-up
            let mut frames = Vec::new();
            for _ in 0..args.reps {
                frames.push(renderer.render(scene.tlas.raw, &shading, &desc)?);
            }
            frames.sort_by(|a, b| a.render_ms.total_cmp(&b.render_ms));
            let f = &frames[frames.len() / 2];
            let tlas_ms = time_tlas_build(
                ctx,
                &scene.meshes[0].blas,
                &instances.iter().map(|i| i.transform).collect::<Vec<_>>(),
                flags,
                args.reps,
            )?
            .0;
            println!("{{\"kind\":\"tlas_trace\",\"flags\":\"{fname}\",\"instances\":{},\"width\":{w},\"height\":{h},\"tlas_build_gpu_ms\":{tlas_ms:.4},\"frame_ms\":{:.3},\"primary_ms\":{:.3},\"shadow_ms\":{:.3},\"ao_shade_ms\":{:.3},\"hit_fraction\":{:.3}}}", instances.len(), f.render_ms, f.passes.primary_ms, f.passes.shadow_ms, f.passes.ao_shade_ms, f.hit_fraction());
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
