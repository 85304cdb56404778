//! The main job: the open-world fly-through. Generates the default 4 km world (or reuses
//! `out/world/`), streams it with loader threads, flies a camera across the map and feeds the
//! world's events to three managers on the same events: ours (`Managed`, on the chosen backend)
//! and the baselines `Naive` and `SeedR1R2` (model backend). Prints a side-by-side table and
//! renders a few frames from our TLAS (Vulkan backend) with a reference frame for the image error.
//!
//! ```text
//! cargo run --release --example flythrough -- [--frames 600] [--backend vulkan|model]
//!     [--world out/world] [--renders 3] [--json]
//! ```

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::Vec3;
use rtstream::as_manager::backend::model::ModelBackend;
use rtstream::as_manager::backend::vulkan::{
    ContextDesc, MeshDesc as VkMeshDesc, VulkanBackend, VulkanBackendDesc, VulkanContext,
};
use rtstream::as_manager::{AsManager, Camera, Config, FrameInput, FrameStats, PolicyKind};
use rtstream::renderer::{
    Camera as ViewCamera, FrameMetrics, RenderDesc, Renderer, SceneInstance, TracedScene,
};
use rtstream::streaming::{bake, generate, read_manifest, StreamConfig, World, WorldPreset};
use rtstream::WorldBridge;

type Res<T> = Result<T, Box<dyn std::error::Error>>;

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

struct Args {
    frames: u64,
    vulkan: bool,
    world: PathBuf,
    renders: u32,
    json: bool,
    size: (u32, u32),
}

fn args() -> Res<Args> {
    let mut a = Args {
        frames: 600,
        vulkan: true,
        world: PathBuf::from("out/world"),
        renders: 3,
        json: false,
        size: (640, 360),
    };
    let mut it = std::env::args().skip(1);
    while let Some(x) = it.next() {
        match x.as_str() {
            "--frames" => a.frames = it.next().ok_or("--frames N")?.parse()?,
            "--backend" => match it.next().as_deref() {
                Some("vulkan") => a.vulkan = true,
                Some("model") => a.vulkan = false,
                _ => return Err("--backend vulkan|model".into()),
            },
            "--world" => a.world = it.next().ok_or("--world DIR")?.into(),
            "--renders" => a.renders = it.next().ok_or("--renders N")?.parse()?,
            "--json" => a.json = true,
            "--size" => {
                let v = it.next().ok_or("--size WxH")?;
                let (w, h) = v.split_once('x').ok_or("--size WxH")?;
                a.size = (w.parse()?, h.parse()?);
            }
            "--help" | "-h" => {
                println!("flythrough [--frames N] [--backend vulkan|model] [--world DIR] [--renders N] [--size WxH] [--json]");
                std::process::exit(0);
            }
            other => return Err(format!("unknown argument {other:?} (try --help)").into()),
        }
    }
    Ok(a)
}

/// Per-policy figures over the run.
#[derive(Debug, Default, Clone)]
struct Tally {
    name: &'static str,
    peak_blas: u32,
    peak_bytes: u64,
    peak_tlas: u32,
    update_ms: Vec<f64>,
    builds: u64,
    frames: u64,
}

impl Tally {
    fn add(&mut self, s: &FrameStats, ms: f64) {
        self.peak_blas = self.peak_blas.max(s.blas_count);
        self.peak_bytes = self.peak_bytes.max(s.blas_bytes);
        self.peak_tlas = self.peak_tlas.max(s.tlas_instances);
        self.update_ms.push(ms);
        self.builds += s.builds as u64;
        self.frames += 1;
    }
    fn mean(&self) -> f64 {
        self.update_ms.iter().sum::<f64>() / self.update_ms.len().max(1) as f64
    }
    fn median(&self) -> f64 {
        let mut v = self.update_ms.clone();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    }
    fn builds_per_frame(&self) -> f64 {
        self.builds as f64 / self.frames.max(1) as f64
    }
}

/// A path across the map: a gentle S along the diagonal at walking-to-driving speed, eye height.
fn path(extent_min: Vec3, extent_max: Vec3, frame: u64, frames: u64) -> (Vec3, Vec3) {
    let at = |t: f32| {
        let s = extent_max - extent_min;
        let x = extent_min.x + s.x * (0.08 + 0.84 * t);
        let z =
            extent_min.z + s.z * (0.08 + 0.84 * t) + s.z * 0.08 * (t * std::f32::consts::TAU).sin();
        Vec3::new(x, 1.8, z)
    };
    let t = frame as f32 / frames.max(1) as f32;
    let p = at(t);
    let ahead = at((t + 0.01).min(1.0)) - p;
    let fwd = Vec3::new(ahead.x, 0.0, ahead.z).normalize_or(Vec3::Z);
    (p, fwd)
}

fn open_world(dir: &PathBuf) -> Res<World> {
    let t = Instant::now();
    if read_manifest(dir).is_ok() {
        eprintln!("world: reusing {}", dir.display());
    } else {
        eprintln!("world: generating the default 4 km world (110k instances) ...");
        let world = generate(&WorldPreset::default_world())?;
        eprintln!(
            "world: generated {} levels, {} instances in {:.1} s; baking to {} ...",
            world.levels.len(),
            world.instance_count(),
            t.elapsed().as_secs_f64(),
            dir.display()
        );
        let r = bake(&world, dir)?;
        eprintln!(
            "world: baked {} level files, {:.0} MB levels + {:.0} MB meshes in {:.1} s",
            r.level_files,
            r.level_bytes as f64 / 1e6,
            r.mesh_library_bytes as f64 / 1e6,
            t.elapsed().as_secs_f64()
        );
    }
    let cfg = StreamConfig {
        loader_threads: 2,
        ..StreamConfig::default()
    };
    Ok(World::open(dir, cfg)?)
}

enum Ours {
    Vulkan(AsManager<VulkanBackend>, Arc<VulkanContext>),
    Model(AsManager<ModelBackend>),
}

fn run() -> Res<()> {
    let a = args()?;
    let mut world = open_world(&a.world)?;
    let manifest = world
        .manifest()
        .cloned()
        .ok_or("baked world has no manifest")?;
    let (emin, emax) = (manifest.extent.min, manifest.extent.max);

    let mut ours = if a.vulkan {
        let ctx = Arc::new(VulkanContext::new(&ContextDesc::default())?);
        let info = ctx.info().clone();
        eprintln!("device: {} ({:?}, {})", info.name, info.kind, info.driver);
        let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default())?;
        Ours::Vulkan(AsManager::new(Config::default(), backend)?, ctx)
    } else {
        Ours::Model(AsManager::new(Config::default(), ModelBackend::lavapipe())?)
    };
    let mut bridge = WorldBridge::new(Some(&manifest));
    let baseline = |p| {
        AsManager::new(
            Config {
                policy: p,
                ..Config::default()
            },
            ModelBackend::lavapipe(),
        )
    };
    let mut naive = baseline(PolicyKind::Naive)?;
    let mut seed = baseline(PolicyKind::SeedR1R2)?;
    let mut naive_bridge = WorldBridge::new(Some(&manifest)).counts_only();
    let mut seed_bridge = WorldBridge::new(Some(&manifest)).counts_only();
    let mut tallies = [
        Tally {
            name: if a.vulkan {
                "ours (Managed, vulkan)"
            } else {
                "ours (Managed, model)"
            },
            ..Tally::default()
        },
        Tally {
            name: "Naive (model)",
            ..Tally::default()
        },
        Tally {
            name: "SeedR1R2 (model)",
            ..Tally::default()
        },
    ];
    let render_at: Vec<u64> = (1..=a.renders as u64)
        .map(|i| i * a.frames / (a.renders as u64 + 1))
        .collect();
    let mut renderer = match &ours {
        Ours::Vulkan(_, ctx) if a.renders > 0 => Some(Renderer::new(ctx.clone())?),
        _ => None,
    };
    let mut renders = Vec::new();
    let mut reference = None;
    let started = Instant::now();
    let mut last_report = Instant::now();
    let mut alt: Option<f32> = None;
    for frame in 0..a.frames {
        let (ground, fwd) = path(emin, emax, frame, a.frames);
        // Fly a few metres above what stands in the level under the camera (smoothed).
        let top = manifest
            .levels
            .iter()
            .find(|l| {
                l.bounds.min.x <= ground.x
                    && ground.x <= l.bounds.max.x
                    && l.bounds.min.z <= ground.z
                    && ground.z <= l.bounds.max.z
            })
            .map_or(ground.y, |l| l.bounds.max.y + 4.0);
        let y = alt.map_or(top, |a| a + (top - a) * 0.05).max(top - 6.0);
        alt = Some(y);
        let pos = Vec3::new(ground.x, y, ground.z);
        let look = (fwd * 10.0 - Vec3::Y * 3.0).normalize();
        // Stream: let the loaders catch up a little each frame (a real engine renders meanwhile).
        let events = world.update_until_idle(frame, &[pos.into()], Duration::from_millis(40));
        bridge.apply_any(&ours, &events);
        naive_bridge.apply(&naive, &events);
        seed_bridge.apply(&seed, &events);
        let time = frame as f32 / 30.0;
        let cams = [Camera::new(pos, fwd)];
        let input = FrameInput {
            frame,
            cameras: &cams,
        };
        match &mut ours {
            Ours::Vulkan(m, ctx) => {
                bridge.pose_skinned(m, &world, time, 2);
                let t = Instant::now();
                let out = m.update(input)?;
                let ms = t.elapsed().as_secs_f64() * 1e3;
                tallies[0].add(out.stats, ms);
                let (tlas, records) = (out.tlas, out.instances.to_vec());
                if let (Some(r), true) = (renderer.as_mut(), render_at.contains(&frame)) {
                    m.backend_mut().wait_idle()?;
                    let raw = m.backend().tlas(tlas).ok_or("no TLAS")?;
                    let shading =
                        bridge.shading(&records, |addr| m.backend().shading_geometry(addr));
                    let view = ViewCamera::look_at(pos, pos + look, 60f32.to_radians());
                    let desc = RenderDesc::new(a.size.0, a.size.1, view);
                    let img = r.render(raw, &shading, &desc)?;
                    let file = format!("out/flythrough_{frame:04}.png");
                    img.save_png(&file)?;
                    eprintln!(
                        "  frame {frame}: {} TLAS instances, {}x{} traced in {:.1} ms, {:.0}% hits -> {file}",
                        records.len(),
                        img.width,
                        img.height,
                        img.render_ms,
                        img.hit_fraction() * 100.0
                    );
                    if Some(&frame) == render_at.last() {
                        let fm = reference_frame(&bridge, ctx, r, pos, look, &img)?;
                        m.record_evaluation(fm.into());
                        reference = Some(fm);
                    }
                    renders.push((frame, file, img));
                }
            }
            Ours::Model(m) => {
                bridge.pose_skinned(m, &world, time, 2);
                let t = Instant::now();
                let out = m.update(input)?;
                tallies[0].add(out.stats, t.elapsed().as_secs_f64() * 1e3);
            }
        }
        for (i, m) in [(1, &mut naive), (2, &mut seed)] {
            let t = Instant::now();
            let out = m.update(FrameInput {
                frame,
                cameras: &cams,
            })?;
            tallies[i].add(out.stats, t.elapsed().as_secs_f64() * 1e3);
        }
        if last_report.elapsed() > Duration::from_secs(5) || frame + 1 == a.frames {
            last_report = Instant::now();
            let s = world.stats();
            eprintln!(
                "frame {}/{} ({:.0} s): levels {} loaded, {} instances; ours {} BLAS, naive {} BLAS",
                frame + 1, a.frames, started.elapsed().as_secs_f64(), s.loaded_levels, s.loaded_instances,
                tallies[0].peak_blas, tallies[1].peak_blas
            );
        }
    }

    let metrics = reference;
    if let Ours::Vulkan(m, _) = &mut ours {
        m.backend_mut().wait_idle()?;
    }

    let bs = bridge.stats();
    println!(
        "fly-through: {} frames over the {:.1} km map, {:.0} s",
        a.frames,
        (emax.x - emin.x) / 1000.0,
        started.elapsed().as_secs_f64()
    );
    println!(
        "bridge: {} meshes, {} instances live, {} non-opaque skipped, {} load failures, {} LOD swaps",
        bs.meshes, bs.instances, bs.skipped_not_opaque, bs.load_failures, bs.lod_swaps
    );
    println!(
        "{:<24} {:>10} {:>12} {:>10} {:>12} {:>12} {:>12}",
        "policy", "peak BLAS", "peak MB", "peak TLAS", "mean upd ms", "median ms", "builds/frame"
    );
    for t in &tallies {
        println!(
            "{:<24} {:>10} {:>12.1} {:>10} {:>12.2} {:>12.2} {:>12.2}",
            t.name,
            t.peak_blas,
            t.peak_bytes as f64 / 1e6,
            t.peak_tlas,
            t.mean(),
            t.median(),
            t.builds_per_frame()
        );
    }
    if a.json {
        let pol: Vec<String> = tallies
            .iter()
            .map(|t| format!(
                "{{\"policy\":\"{}\",\"peak_blas\":{},\"peak_blas_bytes\":{},\"peak_tlas_instances\":{},\"mean_update_ms\":{:.3},\"median_update_ms\":{:.3},\"builds_per_frame\":{:.3}}}",
                t.name, t.peak_blas, t.peak_bytes, t.peak_tlas, t.mean(), t.median(), t.builds_per_frame()))
            .collect();
        let m = metrics.map_or("null".into(), |m| {
            format!(
                "{{\"primary_mismatch\":{:.5},\"shadow_mismatch\":{:.5},\"psnr_db\":{:.2}}}",
                m.primary_mismatch, m.shadow_mismatch, m.psnr_db
            )
        });
        let rs: Vec<String> = renders
            .iter()
            .map(|(f, _, img): &(u64, String, rtstream::renderer::Frame)| {
                format!(
                    "{{\"frame\":{f},\"width\":{},\"height\":{},\"render_ms\":{:.3},\"primary_ms\":{:.3},\"shadow_ms\":{:.3},\"ao_shade_ms\":{:.3}}}",
                    img.width, img.height, img.render_ms, img.passes.primary_ms, img.passes.shadow_ms, img.passes.ao_shade_ms
                )
            })
            .collect();
        println!(
            "{{\"frames\":{},\"seconds\":{:.1},\"load_failures\":{},\"policies\":[{}],\"renders\":[{}],\"image_error\":{}}}",
            a.frames, started.elapsed().as_secs_f64(), bs.load_failures, pol.join(","), rs.join(","), m
        );
    }
    Ok(())
}

trait ApplyAny {
    fn apply_any(&mut self, ours: &Ours, events: &[rtstream::streaming::WorldEvent]);
}

impl ApplyAny for WorldBridge {
    fn apply_any(&mut self, ours: &Ours, events: &[rtstream::streaming::WorldEvent]) {
        match ours {
            Ours::Vulkan(m, _) => self.apply(m, events),
            Ours::Model(m) => self.apply(m, events),
        }
    }
}

/// Reference of a rendered frame: every placed instance within 300 m at its finest resident
/// LOD, nothing culled; returns the image error of `img` against it.
fn reference_frame(
    bridge: &WorldBridge,
    ctx: &Arc<VulkanContext>,
    r: &mut Renderer,
    pos: Vec3,
    look: Vec3,
    img: &rtstream::renderer::Frame,
) -> Res<FrameMetrics> {
    let near = bridge.placed_within(pos, 300.0);
    let mut mesh_ids = Vec::new();
    let mut geoms = Vec::new();
    let mut instances = Vec::new();
    let mut ref_ci = Vec::new();
    for (ci, mesh, transform) in near {
        let Some(g) = bridge.finest_resident(mesh) else {
            continue;
        };
        let mi = match mesh_ids.iter().position(|&x| x == mesh) {
            Some(i) => i,
            None => {
                mesh_ids.push(mesh);
                geoms.push(g);
                mesh_ids.len() - 1
            }
        };
        let base_color = bridge.slot(ci).map_or([0.5; 4], |s| s.base_color);
        instances.push(SceneInstance {
            mesh: mi as u32,
            transform,
            base_color,
        });
        ref_ci.push(ci);
    }
    let names: Vec<String> = mesh_ids.iter().map(|m| format!("mesh{}", m.0)).collect();
    let descs: Vec<VkMeshDesc<'_>> = geoms
        .iter()
        .zip(&names)
        .map(|(g, n)| VkMeshDesc {
            name: n,
            positions: &g.positions,
            indices: &g.indices,
            opaque: true,
        })
        .collect();
    eprintln!(
        "reference: {} instances of {} meshes within 300 m (finest resident LOD)",
        instances.len(),
        descs.len()
    );
    let scene = TracedScene::reference(ctx, &descs, &instances)?;
    let view = ViewCamera::look_at(pos, pos + look, 60f32.to_radians());
    let mut ref_img = scene.render(r, &RenderDesc::new(img.width, img.height, view))?;
    ref_img.save_png("out/flythrough_reference.png")?;
    // Name the reference's hits by the managed frame's customIndex, then compare directly.
    for h in &mut ref_img.hits {
        if h.is_hit() {
            h.instance = ref_ci.get(h.instance as usize).copied().unwrap_or(u32::MAX);
        }
    }
    let fm = FrameMetrics::compare(img, &ref_img)?;
    let diff = rtstream::renderer::difference_image(img, &ref_img)?;
    let (w3, picture) = rtstream::renderer::side_by_side(
        img.width,
        img.height,
        &[&img.color, &ref_img.color, &diff],
    );
    rtstream::renderer::save_rgba_png("out/flythrough_compare.png", w3, img.height, &picture)?;
    eprintln!(
        "  vs reference: primary mismatch {:.2}%, shadow mismatch {:.2}%, PSNR {:.1} dB -> out/flythrough_compare.png (managed | reference | difference)",
        fm.primary_mismatch * 100.0,
        fm.shadow_mismatch * 100.0,
        fm.psnr_db
    );
    scene.destroy(ctx);
    Ok(fm)
}
