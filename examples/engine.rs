//! The thin slice: a real glTF mesh through the manager ([`AsManager`] on the Vulkan backend)
//! into real BLASes and a TLAS, traced by a ray-query compute shader (primary, shadow and
//! ambient-occlusion rays), written as a PNG.
//!
//! Every glTF mesh is registered with the manager (one LOD: the file's own triangles) and every
//! node instance is added with customIndex = its index in the scene; `update` runs frame by frame
//! until everything near the camera is built (residency radii sized to the model, so all of it
//! is near), then the manager's TLAS is rendered with a shading table built from its records.
//!
//! ```text
//! cargo run --release --example engine -- [--model PATH] [--out out/engine.png] [--size WxH] [--json]
//! ```

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Parser;
use glam::{Affine3A, Vec3};
use rtstream::as_manager::backend::vulkan::{
    ContextDesc, VulkanBackend, VulkanBackendDesc, VulkanContext,
};
use rtstream::as_manager::backend::{AsBackend, BlasClass, GeometryRef};
use rtstream::as_manager::{
    AsManager, Config, FrameInput, GeometryData, InstanceDesc, LodDesc, LodGeometry, MeshDesc,
    MeshKind, Viewpoint,
};
use rtstream::renderer::{Camera, InstanceShading, RenderDesc, Renderer};
use rtstream::streaming::GltfScene;
use rtstream::world_bounds;

#[path = "support/cli.rs"]
mod cli;

const DEFAULT_MODEL: &str =
    "/usr/share/assimp/models/glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb";

/// Frames `update` may take to build everything before the example gives up.
const MAX_FRAMES: u64 = 2_000;

/// The thin slice: a glTF model through the manager's BLASes and TLAS, ray traced to a PNG.
#[derive(Debug, Parser)]
#[command(name = "engine")]
struct Args {
    /// The glTF (.gltf / .glb) model.
    #[arg(long, default_value = DEFAULT_MODEL)]
    model: PathBuf,
    /// The PNG written.
    #[arg(long, default_value = "out/engine.png")]
    out: PathBuf,
    /// Image size, WxH.
    #[arg(long, default_value = "1280x720", value_parser = cli::parse_size)]
    size: (u32, u32),
    /// Also print a JSON line of the figures on stdout.
    #[arg(long)]
    json: bool,
}

fn main() -> anyhow::Result<()> {
    cli::init_tracing_at("info");
    run(Args::parse())
}

/// Mesh-space bounding sphere (centre of the AABB, farthest vertex).
fn bounding_sphere(positions: &[[f32; 3]]) -> ([f32; 3], f32) {
    let (lo, hi) = positions.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(Vec3::from(*p)), hi.max(Vec3::from(*p))),
    );
    let c = (lo + hi) * 0.5;
    let r = positions
        .iter()
        .map(|p| Vec3::from(*p).distance(c))
        .fold(0.0f32, f32::max);
    (c.into(), r.max(1e-3))
}

/// The manager's configuration for one model seen from `eye`: residency radii that take the
/// whole model in (the thin slice shows all of it), LOD and culling projected to the image.
fn config(scene: &GltfScene, eye: Vec3, height: u32, fov_y: f32) -> Config {
    let (lo, hi) = world_bounds(scene);
    let reach = (0..8)
        .map(|k| {
            let corner = Vec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            );
            corner.distance(eye)
        })
        .fold(0.0f32, f32::max);
    let mut c = Config::default();
    c.residency.r1 = reach * 1.5;
    c.residency.r2 = reach * 2.0;
    c.residency.cell_size = (reach * 0.25).max(1.0);
    c.cull.far_distance = c.residency.r2;
    c.lod.screen_height_px = height as f32;
    c.lod.vertical_fov = fov_y;
    // Same inputs, same frames: build admission follows the prior, not this machine's timings.
    c.freeze_cost_model = true;
    c
}

fn run(args: Args) -> anyhow::Result<()> {
    let Args {
        model,
        out,
        size: (width, height),
        json,
    } = args;
    let scene = rtstream::streaming::load_gltf(&model)
        .with_context(|| format!("loading {}", model.display()))?;
    let ctx = Arc::new(VulkanContext::new(&ContextDesc::default())?);
    let info = ctx.info().clone();
    eprintln!(
        "device: {} ({:?}, {}): {}",
        info.name, info.kind, info.driver, info.reason
    );

    let (lo, hi) = world_bounds(&scene);
    let view = Camera::framing(lo, hi, Vec3::new(0.7, 0.5, 1.0), 40f32.to_radians());
    let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default())?;
    let mut manager = AsManager::new(config(&scene, view.position, height, view.fov_y), backend)?;

    // Register the meshes (one LOD each) and place the node instances, customIndex = index.
    let mut blas_scratch_bytes = 0u64;
    let mut meshes = Vec::with_capacity(scene.meshes.len());
    for m in &scene.meshes {
        let sizes = manager.backend().blas_sizes(
            &GeometryRef {
                vertex_count: m.positions.len() as u32,
                triangle_count: (m.indices.len() / 3) as u32,
                positions: Some(&m.positions),
                indices: Some(&m.indices),
                device_vertices: None,
                device_indices: None,
                opaque: true,
            },
            BlasClass::Static,
        );
        blas_scratch_bytes += sizes.build_scratch;
        let (center, radius) = bounding_sphere(&m.positions);
        let mut desc = MeshDesc::new(
            m.name.clone(),
            MeshKind::Static,
            radius,
            vec![LodDesc {
                geometry: LodGeometry::Data(Arc::new(GeometryData {
                    positions: m.positions.clone(),
                    indices: m.indices.clone(),
                })),
                geometric_error: 0.0,
            }],
        );
        desc.bounds_center = center;
        meshes.push(manager.register_mesh(desc)?);
    }
    for (i, inst) in scene.instances.iter().enumerate() {
        let mut d = InstanceDesc::new(meshes[inst.mesh], Affine3A::from_mat4(inst.transform));
        d.custom_index = i as u32;
        manager.add_instance(d)?;
    }

    // Frames until nothing near the camera waits for a build.
    let cameras = [Viewpoint::new(view.position, view.forward)];
    let start = Instant::now();
    let mut frame = 0u64;
    let (tlas, records, stats) = loop {
        let out = manager.update(FrameInput {
            frame,
            cameras: &cameras,
        })?;
        let s = out.stats;
        if s.queued == 0 && s.short_of_target == 0 && s.builds == 0 && s.blas_count > 0 {
            break (out.tlas, out.instances.to_vec(), s.clone());
        }
        frame += 1;
        if frame >= MAX_FRAMES {
            bail!(
                "{} BLASes still queued after {frame} frames (memory refused: {})",
                s.queued,
                s.memory_refused
            );
        }
    };
    manager.backend_mut().wait_idle()?;
    let build_ms = start.elapsed().as_secs_f64() * 1e3;
    let frames = frame + 1;

    // The renderer's shading table, indexed by customIndex.
    let backend = manager.backend();
    let mut shading: Vec<InstanceShading> = scene
        .instances
        .iter()
        .map(|inst| InstanceShading::colour_only(scene.meshes[inst.mesh].base_color))
        .collect();
    for r in &records {
        let (vertices, indices) = backend
            .shading_geometry(r.blas_address)
            .context("a TLAS record's BLAS is not live")?;
        let e = &mut shading[r.custom_index() as usize];
        e.vertices = vertices;
        e.indices = indices;
    }
    let traced = backend.resolve_tlas(tlas)?;
    let desc = RenderDesc {
        sun_dir: Vec3::new(0.4, 1.0, 0.3),
        primitive_bases: backend.primitive_bases(tlas),
        ..RenderDesc::new(width, height, view)
    };
    let mut renderer = Renderer::new(ctx.clone())?;
    // The first dispatch of a new pipeline pays for shader compilation: warm up, then time.
    renderer.render(
        traced,
        &shading,
        &RenderDesc {
            width: 64,
            height: 36,
            ..desc
        },
    )?;
    let image = renderer.render(traced, &shading, &desc)?;
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    image.save_png(&out)?;

    let p = image.passes;
    let rays = (p.primary_rays + p.shadow_rays + p.ao_rays) as f64;
    let triangles: usize = scene.meshes.iter().map(|m| m.indices.len() / 3).sum();
    if json {
        let line = serde_json::json!({
            "model": model.display().to_string(),
            "device": info.name,
            "meshes": stats.blas_count,
            "instances": scene.instances.len(),
            "tlas_instances": stats.tlas_instances,
            "culled": stats.culled,
            "triangles": triangles,
            "blas_bytes": stats.blas_bytes,
            "blas_scratch_bytes": blas_scratch_bytes,
            "frames": frames,
            "build_ms": build_ms,
            "width": width,
            "height": height,
            "render_ms": image.render_ms,
            "hit_fraction": image.hit_fraction(),
            "mrays_per_s": rays / image.render_ms / 1e3,
        });
        println!("{line}");
    }
    eprintln!(
        "{}: {} meshes, {} instances ({} in the TLAS, {} culled), {} triangles; BLAS {} B (scratch {} B); built by the manager in {} frames, {:.1} ms",
        model.display(), stats.blas_count, scene.instances.len(), stats.tlas_instances,
        stats.culled, triangles, stats.blas_bytes, blas_scratch_bytes, frames, build_ms
    );
    eprintln!(
        "rendered {}x{} in {:.1} ms ({:.2} M rays/s, {:.1}% pixels hit) -> {}",
        width,
        height,
        image.render_ms,
        rays / image.render_ms / 1e3,
        image.hit_fraction() * 100.0,
        out.display()
    );
    drop(renderer);
    drop(manager);
    let failures = ctx.validation_log().failure_count();
    if failures > 0 {
        bail!("{failures} validation messages");
    }
    Ok(())
}
