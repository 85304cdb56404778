//! The renderer's passes on lavapipe with validation on: agreement with the CPU reference
//! caster on a multi-instance world, ray-query vs ray-tracing-pipeline paths, soft shadows and
//! AO, skinned silhouettes, and metrics against the reference under growing culling.

mod common;
#[path = "../examples/support/eval.rs"]
mod eval;

use eval::{kept_by_culler, DemoWorldDesc, EvalWorld};
use std::sync::Arc;

use glam::{Mat4, Vec3};
use rtstream::as_manager::backend::vulkan::{SceneMesh, VulkanContext};
use rtstream::renderer::reference::{CpuHit, ReferenceScene};
use rtstream::renderer::skinning::linear_blend;
use rtstream::renderer::{
    Camera, Frame, FrameMetrics, RenderDesc, RenderPath, Renderer, SceneInstance, TracedScene,
};

const W: u32 = 128;
const H: u32 = 96;

fn small_world() -> EvalWorld {
    EvalWorld::demo(&DemoWorldDesc {
        rows: 3,
        columns: 3,
        first_row: 6.0,
        row_growth: 1.8,
    })
    .expect("demo world loads")
}

/// Runs `test` on the small world's reference scene (every instance, the finest LODs) on a
/// fresh context; then destroys the scene (what `test` made is dropped by then), and the
/// context checks its validation messages.
fn on_reference_scene(test: impl FnOnce(&EvalWorld, &Arc<VulkanContext>, &TracedScene)) {
    let world = small_world();
    let ctx = common::context();
    let scene = TracedScene::reference(&ctx, &world.mesh_descs(), &world.instances).unwrap();
    test(&world, &ctx, &scene);
    scene.destroy(&ctx);
}

/// Share of pixels whose primary hit instance agrees with the CPU caster (miss == miss).
fn cpu_agreement(frame: &Frame, cpu: &[Option<CpuHit>]) -> f64 {
    let same = frame
        .hits
        .iter()
        .zip(cpu)
        .filter(|(g, c)| match c {
            Some(c) => g.instance == c.instance,
            None => !g.is_hit(),
        })
        .count();
    same as f64 / cpu.len() as f64
}

#[test]
fn ray_query_hits_match_cpu_reference_on_a_multi_instance_world() {
    on_reference_scene(|world, ctx, scene| {
        let mut renderer = Renderer::new(ctx.clone()).unwrap();
        assert_eq!(renderer.path(), RenderPath::RayQuery);
        let camera = EvalWorld::demo_camera();
        let desc = RenderDesc {
            sun_radius: 1.5f32.to_radians(),
            shadow_samples: 4,
            ao_samples: 2,
            ao_radius: 1.5,
            ..RenderDesc::new(W, H, camera)
        };
        let frame = scene.render(&mut renderer, &desc).unwrap();
        let cpu = world.cpu_reference().cast(&camera, W, H);
        let agree = cpu_agreement(&frame, &cpu);
        let distinct: std::collections::HashSet<u32> = frame
            .hits
            .iter()
            .filter(|h| h.is_hit())
            .map(|h| h.instance)
            .collect();
        eprintln!(
            "{} instances, {} distinct hit; agreement with CPU {:.5}; passes {:?}",
            world.instances.len(),
            distinct.len(),
            agree,
            frame.passes
        );
        assert!(
            distinct.len() >= 20,
            "too few instances visible: {}",
            distinct.len()
        );
        assert!(agree >= 0.995, "RQ vs CPU agreement {agree:.5} < 0.995");
        assert!(frame.hit_fraction() > 0.3 && frame.hit_fraction() < 0.95);

        // Soft shadows give penumbrae (fractional sun visibility); AO darkens somewhere.
        let fractional = frame
            .sun_visibility
            .iter()
            .filter(|&&v| v > 0.0 && v < 1.0)
            .count();
        let occluded = frame
            .ambient
            .iter()
            .zip(&frame.hits)
            .filter(|(a, h)| h.is_hit() && **a < 1.0)
            .count();
        assert!(fractional > 0, "no penumbra pixels");
        assert!(occluded > 0, "AO found no occlusion");
        let shadowed = frame.shadow_mask().iter().filter(|&&s| s).count();
        assert!(shadowed > 0, "no shadowed pixels");
        let p = frame.passes;
        assert_eq!(p.primary_rays, u64::from(W * H));
        assert!(p.shadow_rays > 0 && p.ao_rays > 0);

        // Any resolution: one that is not a multiple of the 8x8 workgroup.
        let (w, h) = (61, 37);
        let odd = scene
            .render(&mut renderer, &RenderDesc::new(w, h, camera))
            .unwrap();
        assert_eq!(
            (odd.hits.len(), odd.color.len()),
            ((w * h) as usize, (w * h) as usize)
        );
        let agree_odd = cpu_agreement(&odd, &world.cpu_reference().cast(&camera, w, h));
        assert!(agree_odd >= 0.995, "{w}x{h}: agreement {agree_odd:.5}");
    });
}

#[test]
fn ray_query_and_ray_tracing_pipeline_paths_agree() {
    on_reference_scene(|_, ctx, scene| {
        assert!(ctx.info().ray_tracing_pipeline, "lavapipe has RT pipelines");
        let desc = RenderDesc {
            sun_radius: 1.0f32.to_radians(),
            shadow_samples: 2,
            ..RenderDesc::new(W, H, EvalWorld::demo_camera())
        };
        let mut rq = Renderer::with_path(ctx.clone(), RenderPath::RayQuery).unwrap();
        let mut rt = Renderer::with_path(ctx.clone(), RenderPath::RayTracingPipeline).unwrap();
        assert_eq!(rt.path(), RenderPath::RayTracingPipeline);
        let a = scene.render(&mut rq, &desc).unwrap();
        let b = scene.render(&mut rt, &desc).unwrap();
        let n = a.hits.len() as f64;
        let same_hit = a
            .hits
            .iter()
            .zip(&b.hits)
            .filter(|(x, y)| x.instance == y.instance && x.primitive == y.primitive)
            .count() as f64
            / n;
        let m = FrameMetrics::compare(&b, &a).unwrap();
        eprintln!("RQ vs RT: hit buffers equal on {same_hit:.5} of pixels; {m:?}");
        assert!(
            same_hit >= 0.999,
            "RQ and RT hit buffers agree on {same_hit:.5}"
        );
        assert!(m.shadow_mismatch <= 0.001, "{m:?}");
        assert!(m.color_rmse < 0.01, "{m:?}");
    });
}

#[test]
fn metrics_are_zero_for_identical_frames_and_grow_with_the_culling_angle() {
    let world = small_world();
    let ctx = common::context();
    let meshes = world.mesh_descs();
    let camera = EvalWorld::demo_camera();
    let desc = RenderDesc::new(W, H, camera);
    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    let reference = TracedScene::reference(&ctx, &meshes, &world.instances).unwrap();
    let ref_frame = reference.render(&mut renderer, &desc).unwrap();
    let again = reference.render(&mut renderer, &desc).unwrap();
    let zero = FrameMetrics::compare(&again, &ref_frame).unwrap();
    assert!(zero.is_exact(), "identical frames differ: {zero:?}");
    assert_eq!(zero.psnr_db, f64::INFINITY);
    reference.destroy(&ctx);

    let spheres = world.bounding_spheres();
    let mut last: Option<(FrameMetrics, usize)> = None;
    for deg in [0.5f32, 1.0, 2.0, 4.0, 8.0] {
        let keep = kept_by_culler(camera.position, &spheres, deg.to_radians());
        let managed = TracedScene::subset(&ctx, &meshes, &world.instances, |i| keep[i]).unwrap();
        let frame = managed.render(&mut renderer, &desc).unwrap();
        let m = FrameMetrics::compare(&frame, &ref_frame).unwrap();
        eprintln!(
            "cull angle {deg:>4} deg: {:>4}/{} instances traced; {m:?}",
            managed.traced_instances,
            world.instances.len()
        );
        if let Some((prev, prev_traced)) = last {
            assert!(managed.traced_instances <= prev_traced);
            assert!(
                m.primary_mismatch >= prev.primary_mismatch,
                "primary mismatch fell: {prev:?} -> {m:?}"
            );
            assert!(
                m.color_rmse >= prev.color_rmse - 1e-4,
                "colour error fell: {prev:?} -> {m:?}"
            );
        }
        last = Some((m, managed.traced_instances));
        managed.destroy(&ctx);
    }
    let (m, _) = last.unwrap();
    assert!(
        m.primary_mismatch > 0.01,
        "8 degrees culls visible things: {m:?}"
    );
    assert!(m.shadow_mismatch > 0.0 && m.color_rmse > 0.0 && m.psnr_db.is_finite());
}

/// A vertical cylinder (radius 0.25, height 2, closed), skinned to two joints: joint 0 holds the
/// lower half, joint 1 the upper half, blended around y = 1.
struct SkinnedMesh {
    bind: Vec<[f32; 3]>,
    indices: Vec<u32>,
    joints: Vec<[u16; 4]>,
    weights: Vec<[f32; 4]>,
}

fn two_bone_cylinder() -> SkinnedMesh {
    let (seg, rings) = (24u32, 20u32);
    let mut pos = Vec::new();
    let mut joints = Vec::new();
    let mut weights = Vec::new();
    for r in 0..=rings {
        let y = 2.0 * r as f32 / rings as f32;
        let w1 = ((y - 0.8) / 0.4).clamp(0.0, 1.0);
        for s in 0..seg {
            let a = s as f32 / seg as f32 * std::f32::consts::TAU;
            pos.push([0.25 * a.cos(), y, 0.25 * a.sin()]);
            joints.push([0, 1, 0, 0]);
            weights.push([1.0 - w1, w1, 0.0, 0.0]);
        }
    }
    let mut idx = Vec::new();
    for r in 0..rings {
        for s in 0..seg {
            let (a, b) = (r * seg + s, r * seg + (s + 1) % seg);
            let (c, d) = (a + seg, b + seg);
            idx.extend([a, c, b, b, c, d]);
        }
    }
    // Caps.
    for (y, w1, ring) in [(0.0f32, 0.0f32, 0u32), (2.0, 1.0, rings)] {
        let centre = pos.len() as u32;
        pos.push([0.0, y, 0.0]);
        joints.push([0, 1, 0, 0]);
        weights.push([1.0 - w1, w1, 0.0, 0.0]);
        for s in 0..seg {
            idx.extend([centre, ring * seg + s, ring * seg + (s + 1) % seg]);
        }
    }
    SkinnedMesh {
        bind: pos,
        indices: idx,
        joints,
        weights,
    }
}

#[test]
fn skinned_silhouette_follows_the_pose_and_matches_cpu_skinning() {
    let SkinnedMesh {
        bind,
        indices: idx,
        joints,
        weights,
    } = two_bone_cylinder();
    let bend = |deg: f32| {
        let pivot = Vec3::new(0.0, 1.0, 0.0);
        [
            Mat4::IDENTITY,
            Mat4::from_translation(pivot)
                * Mat4::from_rotation_z(deg.to_radians())
                * Mat4::from_translation(-pivot),
        ]
    };
    let ctx = common::context();
    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    let camera = Camera::look_at(Vec3::new(0.0, 1.0, 5.0), Vec3::new(0.0, 1.0, 0.0), 0.8);
    let desc = RenderDesc {
        ao_samples: 0,
        ..RenderDesc::new(96, 96, camera)
    };
    let mut masks = Vec::new();
    for deg in [0.0f32, 60.0] {
        let posed = linear_blend(&bind, &joints, &weights, &bend(deg));
        let meshes = [SceneMesh {
            name: "skinned cylinder",
            positions: &posed,
            indices: &idx,
            opaque: true,
        }];
        let inst = [SceneInstance {
            mesh: 0,
            transform: Mat4::IDENTITY,
            base_color: [0.8, 0.6, 0.4, 1.0],
        }];
        let scene = TracedScene::reference(&ctx, &meshes, &inst).unwrap();
        let frame = scene.render(&mut renderer, &desc).unwrap();
        scene.destroy(&ctx);
        let cpu = ReferenceScene::new(&[(&posed, &idx)], &[(0, Mat4::IDENTITY, 0)]).cast(
            &camera,
            desc.width,
            desc.height,
        );
        let agree = cpu_agreement(&frame, &cpu);
        eprintln!(
            "pose {deg} deg: hit share {:.3}, agreement with CPU skinning {agree:.5}",
            frame.hit_fraction()
        );
        assert!(agree >= 0.995, "pose {deg}: agreement {agree:.5}");
        assert!(frame.hit_fraction() > 0.03);
        masks.push(frame.hits.iter().map(|h| h.is_hit()).collect::<Vec<_>>());
    }
    let differ = masks[0]
        .iter()
        .zip(&masks[1])
        .filter(|(a, b)| a != b)
        .count();
    let share = differ as f64 / masks[0].len() as f64;
    eprintln!("silhouettes differ on {share:.4} of pixels");
    assert!(
        share > 0.02,
        "the bent pose looks like the straight one ({share:.4})"
    );
}

/// The pipelined renderer (`Renderer::record` into a `FrameLoop`'s command buffers, three
/// frames in flight, read back with `take`) renders what the blocking one renders, on both
/// paths, with GPU pass times; a fourth-newest frame's resources are not reused before it is
/// done.
#[test]
fn recorded_frames_equal_blocking_frames_on_both_paths() {
    use rtstream::as_manager::backend::vulkan::FrameLoop;
    on_reference_scene(|_, ctx, scene| {
        for path in [RenderPath::RayQuery, RenderPath::RayTracingPipeline] {
            let mut r = Renderer::with_path(ctx.clone(), path).unwrap();
            let mut frames = FrameLoop::new(ctx, 3).unwrap();
            let base = EvalWorld::demo_camera();
            let desc_of = |f: u64| {
                let mut c = base;
                c.position += Vec3::new(0.2 * f as f32, 0.0, 0.0);
                RenderDesc::new(W, H, c)
            };
            let mut recorded = Vec::new();
            for f in 0..8u64 {
                let cmd = frames.begin(f).unwrap();
                while let Some(img) = r.take(recorded.len() as u64, cmd.completed()).unwrap() {
                    recorded.push(img);
                }
                r.record(&cmd, scene.accel.tlas_ref(), &scene.shading, &desc_of(f))
                    .unwrap();
                frames.submit(cmd).unwrap();
            }
            frames.wait_all().unwrap();
            while let Some(img) = r.take(recorded.len() as u64, Some(7)).unwrap() {
                recorded.push(img);
            }
            assert_eq!(recorded.len(), 8, "{path:?}: every frame reads back");
            for (f, img) in recorded.iter().enumerate() {
                let blocking = scene.render(&mut r, &desc_of(f as u64)).unwrap();
                assert_eq!(img.hits, blocking.hits, "{path:?} frame {f}");
                assert_eq!(img.color, blocking.color, "{path:?} frame {f}");
                assert!(img.passes.primary_ms > 0.0, "{path:?}: GPU pass times");
            }
            drop(frames);
            drop(r);
        }
    });
}

/// A shading table kept across frames and recorded with `record_update` (three frames in
/// flight, so each frame's instance buffer misses the two versions written into the others)
/// renders what a whole table renders, frame after frame, while one visible instance changes
/// colour each frame, the table grows, and a version is skipped; only the changed entries are
/// written once every buffer holds the table.
#[test]
fn recorded_table_updates_render_what_whole_tables_render() {
    use rtstream::as_manager::backend::vulkan::{FrameLoop, RECORDED_SETS};
    use rtstream::renderer::ShadingUpdate;
    on_reference_scene(|_, ctx, scene| {
        let mut r = Renderer::with_path(ctx.clone(), RenderPath::for_device(ctx).unwrap()).unwrap();
        let desc = RenderDesc::new(W, H, EvalWorld::demo_camera());
        let first = scene.render(&mut r, &desc).unwrap();
        let mut visible: Vec<u32> = first
            .hits
            .iter()
            .map(|h| h.instance)
            .filter(|&i| i != rtstream::renderer::PixelHit::MISS)
            .collect();
        visible.sort_unstable();
        visible.dedup();
        assert!(visible.len() >= 3, "the camera sees several instances");
        let mut table = scene.shading.clone();
        // Spare entries no instance names, so a quarter of the table is more than a frame's
        // changes of three buffers.
        table.resize(table.len() * 8, table[0]);
        let frames_n = 12u64;
        let mut tables = Vec::new();
        let mut frames = FrameLoop::new(ctx, RECORDED_SETS).unwrap();
        let mut recorded = Vec::new();
        let mut written = Vec::new();
        let mut serial = 0u64;
        for f in 0..frames_n {
            // One visible instance changes colour; the one changed last frame keeps its own.
            let ci = visible[f as usize % visible.len()] as usize;
            let c = [
                (f as f32 * 0.37) % 1.0,
                1.0 - (f as f32 * 0.21) % 1.0,
                0.1,
                1.0,
            ];
            table[ci].base_color = c;
            let mut changed = vec![ci as u32];
            if f == 5 {
                table.push(table[0]);
            }
            if f == 8 {
                // A version skipped: the renderer cannot chain and writes whole tables.
                serial += 1;
                changed.clear();
            }
            serial += 1;
            let cmd = frames.begin(f).unwrap();
            while let Some(img) = r.take(recorded.len() as u64, cmd.completed()).unwrap() {
                recorded.push(img);
            }
            let update = ShadingUpdate {
                table: &table,
                changed: &changed,
                table_id: 7,
                serial,
            };
            r.record_update(&cmd, scene.accel.tlas_ref(), update, &desc)
                .unwrap();
            written.push(r.shading_entries_written());
            tables.push(table.clone());
            frames.submit(cmd).unwrap();
        }
        frames.wait_all().unwrap();
        while let Some(img) = r.take(recorded.len() as u64, Some(frames_n - 1)).unwrap() {
            recorded.push(img);
        }
        assert_eq!(recorded.len(), frames_n as usize, "every frame reads back");
        let sets = RECORDED_SETS as usize;
        for (f, img) in recorded.iter().enumerate() {
            let whole = r.render(scene.accel.tlas_ref(), &tables[f], &desc).unwrap();
            let differ = img
                .color
                .iter()
                .zip(&whole.color)
                .filter(|(a, b)| a != b)
                .count();
            assert_eq!(differ, 0, "frame {f}: pixels differ from the whole table's");
            let n = tables[f].len();
            if f < sets || (8..8 + sets).contains(&f) {
                assert_eq!(
                    written[f], n,
                    "frame {f}: a buffer new or off the chain is whole"
                );
            } else {
                // This frame's change and the other buffers' since (the growth adds one).
                assert!(
                    written[f] <= sets + 1,
                    "frame {f}: wrote {} of {n} entries",
                    written[f]
                );
            }
        }
        assert!(
            recorded[0].color != recorded[sets].color,
            "the colour changes show in the image"
        );
    });
}
