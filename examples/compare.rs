//! A managed frame next to its reference, with the difference image: one PNG a person can look
//! at, plus the accuracy metrics and per-pass timings.
//!
//! The "managed" frame traces only the instances that the manager's culler keeps with its
//! projected-angle test alone (UE5's small-object test, `--angle` degrees); the reference traces
//! every instance at the finest LOD. The picture is `managed | reference | difference` (red: the primary hit's instance
//! differs, yellow: only the shadow bit differs, elsewhere the colour difference x4). Beside it,
//! `<out>_ids.png` (the reference's hit buffer, one colour per instance) and `<out>_shadow.png`
//! (its shadow mask).
//!
//! ```text
//! cargo run --release --example compare -- [--size WxH] [--angle DEG] [--out out/compare.png]
//!     [--rows N] [--cols N] [--soft DEG] [--shadow-samples N] [--ao-samples N]
//!     [--path rq|rt] [--asset-dir DIR] [--json]
//! ```

use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;

use rtstream::as_manager::backend::vulkan::{ContextDesc, VulkanContext};
use rtstream::renderer::{
    difference_image, save_rgba_png, Frame, FrameMetrics, PassStats, RenderDesc, RenderPath,
    Renderer, TracedScene,
};

#[path = "support/cli.rs"]
mod cli;
#[path = "support/eval.rs"]
mod eval;

use eval::{try_kept_by_culler, DemoWorldDesc, EvalWorld};

fn main() -> anyhow::Result<()> {
    cli::init_tracing_at("info");
    run()
}

/// One render's pass times and ray rates (the `--json` object's `passes`).
fn passes_json(p: &PassStats) -> serde_json::Value {
    let (a, b, c) = p.mrays_per_s();
    serde_json::json!({
        "primary_ms": p.primary_ms,
        "shadow_ms": p.shadow_ms,
        "ao_shade_ms": p.ao_shade_ms,
        "primary_rays": p.primary_rays,
        "shadow_rays": p.shadow_rays,
        "ao_rays": p.ao_rays,
        "primary_mrays_per_s": a,
        "shadow_mrays_per_s": b,
        "ao_mrays_per_s": c,
    })
}

/// A managed frame next to its reference, with the difference image.
#[derive(Debug, Parser)]
#[command(name = "compare")]
struct Args {
    /// Image size, WxH.
    #[arg(long, default_value = "640x360", value_parser = cli::parse_size)]
    size: (u32, u32),
    /// Projected-angle culling threshold of the managed frame, degrees (0 to below 90; 0 culls
    /// nothing).
    #[arg(long, default_value_t = 1.0, value_parser = cli::angle_deg)]
    angle: f32,
    /// The PNG written (`<out>_ids.png` and `<out>_shadow.png` beside it).
    #[arg(long, default_value = "out/compare.png")]
    out: PathBuf,
    /// Rows of models, each 1.6 times as far as the last (default 6; 1 to 32, and rows x
    /// cols at most 10,000).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=MAX_ROWS))]
    rows: Option<u32>,
    /// Models per row (default 6; 1 to 10,000, and rows x cols at most 10,000).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=i64::from(eval::MAX_DEMO_MODELS)))]
    cols: Option<u32>,
    /// Angular radius of the sun (soft shadows), degrees (0: hard shadows; below 57.3, one
    /// radian).
    #[arg(long, default_value_t = 0.0, value_parser = sun_radius_deg)]
    soft: f32,
    /// Shadow rays per pixel (at most 1,024).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(0..=MAX_SAMPLES))]
    shadow_samples: u32,
    /// Ambient-occlusion rays per pixel (at most 1,024).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(0..=MAX_SAMPLES))]
    ao_samples: u32,
    /// Render path: ray query (`rq`) or the ray-tracing pipeline (`rt`); default: the device's.
    #[arg(long, value_parser = parse_path)]
    path: Option<RenderPath>,
    /// Print the figures as one JSON object on stdout.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    assets: cli::AssetArgs,
}

/// The most rows of models: the last of 32 rows is 5 m x 1.6^31, about 10,000 km away (far
/// beyond a pixel).
const MAX_ROWS: i64 = 32;

/// The renderer's most shadow or AO samples a pixel (`rtstream_renderer`'s
/// `renderer::MAX_SAMPLES`, in a private module).
const MAX_SAMPLES: i64 = 1024;

/// `value_parser` of `--soft`: the renderer's sun radius is from 0 to below one radian.
fn sun_radius_deg(s: &str) -> Result<f32, String> {
    let v = cli::finite_non_negative_f32(s)?;
    if v.to_radians() < 1.0 {
        Ok(v)
    } else {
        Err(format!(
            "must be from 0 to below {:.2} degrees (one radian), not {s}",
            1f32.to_degrees()
        ))
    }
}

fn parse_path(s: &str) -> Result<RenderPath, String> {
    match s {
        "rq" => Ok(RenderPath::RayQuery),
        "rt" => Ok(RenderPath::RayTracingPipeline),
        other => Err(format!("rq or rt, not {other:?}")),
    }
}

fn run() -> anyhow::Result<()> {
    let args = Args::parse();
    let (width, height) = args.size;
    let (angle_deg, out, json, path) = (args.angle, args.out, args.json, args.path);
    let (soft_deg, shadow_samples, ao_samples) = (args.soft, args.shadow_samples, args.ao_samples);
    let mut world_desc = DemoWorldDesc::default();
    world_desc.rows = args.rows.unwrap_or(world_desc.rows);
    world_desc.columns = args.cols.unwrap_or(world_desc.columns);
    world_desc.validate()?;
    let asset_dir = args.assets.asset_dir.unwrap_or_else(eval::asset_dir);

    let world = EvalWorld::demo_in(&asset_dir, &world_desc)?;
    let camera = EvalWorld::demo_camera();
    let keep = try_kept_by_culler(
        camera.position,
        &world.bounding_spheres(),
        angle_deg.to_radians(),
    )?;
    let ctx = Arc::new(VulkanContext::new(&ContextDesc::default())?);
    let info = ctx.info().clone();
    eprintln!(
        "device: {} ({:?}, {}): {}",
        info.name, info.kind, info.driver, info.reason
    );
    let mut renderer = match path {
        Some(p) => Renderer::with_path(ctx.clone(), p)?,
        None => Renderer::new(ctx.clone())?,
    };
    let meshes = world.mesh_descs();
    let reference = TracedScene::reference(&ctx, &meshes, &world.instances)?;
    let managed = TracedScene::subset(&ctx, &meshes, &world.instances, |i| keep[i])?;
    let desc = RenderDesc {
        sun_radius: soft_deg.to_radians(),
        shadow_samples,
        ao_samples,
        ao_radius: 1.5,
        ..RenderDesc::new(width, height, camera)
    };
    // The first dispatch of a new pipeline pays for shader compilation: warm up, then time.
    reference.render(
        &mut renderer,
        &RenderDesc {
            width: 64,
            height: 36,
            ..desc
        },
    )?;
    let ref_frame: Frame = reference.render(&mut renderer, &desc)?;
    let frame: Frame = managed.render(&mut renderer, &desc)?;
    let metrics = FrameMetrics::compare(&frame, &ref_frame)?;
    let diff = difference_image(&frame, &ref_frame)?;
    let (w3, picture) =
        rtstream::renderer::side_by_side(width, height, &[&frame.color, &ref_frame.color, &diff]);
    save_rgba_png(&out, w3, height, &picture)?;
    // The reference frame's hit buffer (instances coloured) and shadow mask, beside the picture.
    let stem = out.with_extension("");
    ref_frame.save_instance_png(format!("{}_ids.png", stem.display()))?;
    ref_frame.save_shadow_png(format!("{}_shadow.png", stem.display()))?;

    // Shadow samples only apply to a sun disk (--soft > 0); hard shadows trace one ray.
    let shadow_samples = if soft_deg > 0.0 {
        shadow_samples.max(1)
    } else {
        1
    };
    let r = &ref_frame.passes;
    let (pa, pb, pc) = r.mrays_per_s();
    eprintln!(
        "world: {} meshes, {} instances ({} traced after culling at {angle_deg} deg), {} instanced triangles",
        world.meshes.len(),
        world.instances.len(),
        managed.traced_instances,
        world.instanced_triangles()
    );
    eprintln!(
        "reference {width}x{height} on {:?}: {:.1} ms (primary {:.1} ms {pa:.2} Mrays/s, shadow {:.1} ms {pb:.2} Mrays/s, AO+shade {:.1} ms {pc:.2} Mrays/s)",
        renderer.path(), ref_frame.render_ms, r.primary_ms, r.shadow_ms, r.ao_shade_ms
    );
    eprintln!(
        "managed vs reference: primary mismatch {:.4}, shadow mismatch {:.4}, colour RMSE {:.4}, PSNR {:.2} dB -> {}",
        metrics.primary_mismatch, metrics.shadow_mismatch, metrics.color_rmse, metrics.psnr_db,
        out.display()
    );
    if json {
        // serde_json writes a non-finite PSNR (identical images) as null.
        let summary = serde_json::json!({
            "device": info.name,
            "path": format!("{:?}", renderer.path()),
            "width": width,
            "height": height,
            "instances": world.instances.len(),
            "traced_instances": managed.traced_instances,
            "instanced_triangles": world.instanced_triangles(),
            "cull_angle_deg": angle_deg,
            "sun_radius_deg": soft_deg,
            "shadow_samples": shadow_samples,
            "ao_samples": ao_samples,
            "reference": {
                "render_ms": ref_frame.render_ms,
                "passes": passes_json(&ref_frame.passes),
            },
            "managed": {
                "render_ms": frame.render_ms,
                "passes": passes_json(&frame.passes),
            },
            "metrics": {
                "primary_mismatch": metrics.primary_mismatch,
                "shadow_mismatch": metrics.shadow_mismatch,
                "color_rmse": metrics.color_rmse,
                "psnr_db": metrics.psnr_db,
            },
        });
        println!("{summary}");
    }
    drop(renderer);
    reference.destroy(&ctx);
    managed.destroy(&ctx);
    let failures = ctx.validation_log().failure_count();
    if failures > 0 {
        anyhow::bail!("{failures} validation messages");
    }
    Ok(())
}
