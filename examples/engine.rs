//! The thin slice: a real glTF mesh into real BLASes and a TLAS, traced by a ray-query compute
//! shader (primary, shadow and ambient-occlusion rays), written as a PNG.
//!
//! ```text
//! cargo run --release --example engine -- [--model PATH] [--out out/engine.png] [--size WxH] [--json]
//! ```

use std::path::PathBuf;
use std::sync::Arc;

use glam::Vec3;
use rtstream::as_manager::backend::vulkan::{ContextDesc, VulkanContext};
use rtstream::renderer::{Camera, RenderDesc, Renderer};
use rtstream::{world_bounds, GpuGltfScene};

const DEFAULT_MODEL: &str =
    "/usr/share/assimp/models/glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb";

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Err(e) = run() {
        eprintln!("error: {e}");
        let mut source = std::error::Error::source(&*e);
        while let Some(s) = source {
            eprintln!("  caused by: {s}");
            source = s.source();
        }
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut model = PathBuf::from(DEFAULT_MODEL);
    let mut out = PathBuf::from("out/engine.png");
    let (mut width, mut height) = (1280u32, 720u32);
    let mut json = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--model" => model = args.next().ok_or("--model needs a path")?.into(),
            "--out" => out = args.next().ok_or("--out needs a path")?.into(),
            "--size" => {
                let s = args.next().ok_or("--size needs WxH")?;
                let (w, h) = s.split_once('x').ok_or("--size needs WxH")?;
                (width, height) = (w.parse()?, h.parse()?);
            }
            "--json" => json = true,
            "-h" | "--help" => {
                println!("usage: engine [--model PATH] [--out PNG] [--size WxH] [--json]");
                return Ok(());
            }
            other => return Err(format!("unknown argument {other:?} (try --help)").into()),
        }
    }

    let scene = rtstream::streaming::load_gltf(&model)?;
    let ctx = Arc::new(VulkanContext::new(&ContextDesc::default())?);
    let info = ctx.info().clone();
    eprintln!(
        "device: {} ({:?}, {}): {}",
        info.name, info.kind, info.driver, info.reason
    );

    let gpu = GpuGltfScene::build(&ctx, &scene)?;
    let s = gpu.accel.stats;
    let (lo, hi) = world_bounds(&scene);
    let camera = Camera::framing(lo, hi, Vec3::new(0.7, 0.5, 1.0), 40f32.to_radians());
    let desc = RenderDesc {
        sun_dir: Vec3::new(0.4, 1.0, 0.3),
        ..RenderDesc::new(width, height, camera)
    };
    let mut renderer = Renderer::new(ctx.clone())?;
    // The first dispatch of a new pipeline pays for shader compilation: warm up, then time.
    renderer.render(
        gpu.accel.tlas.raw,
        &gpu.shading,
        &RenderDesc {
            width: 64,
            height: 36,
            ..desc
        },
    )?;
    let frame = renderer.render(gpu.accel.tlas.raw, &gpu.shading, &desc)?;
    frame.save_png(&out)?;

    let p = frame.passes;
    let rays = (p.primary_rays + p.shadow_rays + p.ao_rays) as f64;
    if json {
        println!(
            "{{\"model\":{:?},\"device\":{:?},\"meshes\":{},\"instances\":{},\"triangles\":{},\"blas_bytes\":{},\"blas_scratch_bytes\":{},\"tlas_bytes\":{},\"tlas_scratch_bytes\":{},\"build_ms\":{:.3},\"width\":{},\"height\":{},\"render_ms\":{:.3},\"hit_fraction\":{:.4},\"mrays_per_s\":{:.3}}}",
            model.display().to_string(), info.name, s.blas_count, scene.instances.len(), s.triangles,
            s.blas_bytes, s.blas_scratch_bytes, s.tlas_bytes, s.tlas_scratch_bytes, s.build_ms,
            width, height, frame.render_ms, frame.hit_fraction(), rays / frame.render_ms / 1e3
        );
    }
    eprintln!(
        "{}: {} meshes, {} instances, {} triangles; BLAS {} B (scratch {} B), TLAS {} B (scratch {} B); build {:.1} ms",
        model.display(), s.blas_count, scene.instances.len(), s.triangles, s.blas_bytes,
        s.blas_scratch_bytes, s.tlas_bytes, s.tlas_scratch_bytes, s.build_ms
    );
    eprintln!(
        "rendered {}x{} in {:.1} ms ({:.2} M rays/s, {:.1}% pixels hit) -> {}",
        width,
        height,
        frame.render_ms,
        rays / frame.render_ms / 1e3,
        frame.hit_fraction() * 100.0,
        out.display()
    );
    drop(renderer);
    gpu.destroy(&ctx);
    let failures = ctx.validation_log().failure_count();
    if failures > 0 {
        return Err(format!("{failures} validation messages").into());
    }
    Ok(())
}
