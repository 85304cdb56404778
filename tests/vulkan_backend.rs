//! The manager on the real Vulkan backend (lavapipe here), validation layers on: a camera path
//! over a few hundred frames creates, refits, evicts and destroys BLASes; every frame's TLAS is
//! traced by the renderer; a forced out-of-memory is survived. (Split meshes: see
//! `shading_geometry.rs`.)

mod common;

use std::sync::Arc;

use glam::{Affine3A, Vec3};
use rtstream::as_manager::backend::vulkan::{
    VulkanBackend, VulkanBackendDesc, VulkanContext, VulkanError,
};
use rtstream::as_manager::backend::AsBackend;
use rtstream::as_manager::synth::grid_geometry;
use rtstream::as_manager::{
    AsManager, Config, FrameInput, GeometryData, InstanceDesc, InstanceId, LodDesc, LodGeometry,
    MeshDesc, MeshKind, Viewpoint,
};
use rtstream::renderer::{Camera, RenderDesc, Renderer};

/// A 4-LOD chain of displaced grids (finest `n` x `n` quads).
fn chain(n: u32, size: f32) -> Vec<LodDesc> {
    (0..4)
        .map(|i| {
            let g = grid_geometry((n >> i).max(2), size);
            let bumped: Vec<[f32; 3]> = g
                .positions
                .iter()
                .map(|p| [p[0], (p[0] * 0.3).sin() + (p[2] * 0.2).cos(), p[2]])
                .collect();
            LodDesc {
                geometry: LodGeometry::Data(Arc::new(GeometryData {
                    positions: bumped,
                    indices: g.indices.clone(),
                })),
                geometric_error: if i == 0 { 0.0 } else { 0.05 * (1 << i) as f32 },
            }
        })
        .collect()
}

/// A skinned pose: a travelling wave, plus per-vertex scatter of size `scatter` (0: smooth; a few
/// metres: the extreme deformation that degrades refits).
fn pose(base: &GeometryData, t: f32, scatter: f32) -> Arc<Vec<[f32; 3]>> {
    Arc::new(
        base.positions
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let h = (i as u32).wrapping_mul(2_654_435_761);
                let n = |k: u32| ((h.rotate_left(k) & 0xffff) as f32 / 65535.0 - 0.5) * scatter;
                [
                    p[0] + n(3),
                    p[1] + 0.5 * (p[0] * 0.5 + t).sin() + n(11),
                    p[2] + n(19),
                ]
            })
            .collect(),
    )
}

struct Scene {
    manager: AsManager<VulkanBackend>,
    skinned: Vec<(InstanceId, Arc<GeometryData>)>,
}

fn scene(ctx: &Arc<VulkanContext>, desc: VulkanBackendDesc, config: Config) -> Scene {
    let manager = common::manager(ctx, desc, config);
    let mut meshes = Vec::new();
    for (k, n) in [16u32, 20, 24, 28, 32, 36, 40, 44].into_iter().enumerate() {
        meshes.push(
            manager
                .register_mesh(MeshDesc::new(
                    format!("grid{k}"),
                    MeshKind::Static,
                    8.0,
                    chain(n, 10.0),
                ))
                .unwrap(),
        );
    }
    let mut id = 0;
    for x in 0..14 {
        for z in 0..4 {
            let at = Vec3::new(x as f32 * 25.0, 0.0, z as f32 * 25.0);
            common::place(&manager, meshes[(x + z) % meshes.len()], at, id);
            id += 1;
        }
    }
    let skin_base = grid_geometry(20, 6.0);
    let skin_mesh =
        common::one_lod_mesh(&manager, "cloth", MeshKind::Skinned, 6.0, skin_base.clone());
    let mut skinned = Vec::new();
    for k in 0..3 {
        let at = Vec3::new(20.0 + k as f32 * 30.0, 4.0, -15.0);
        skinned.push((
            common::place(&manager, skin_mesh, at, id),
            skin_base.clone(),
        ));
        id += 1;
    }
    Scene { manager, skinned }
}

fn config() -> Config {
    let mut c = common::lavapipe_config(45.0, 60.0);
    c.residency.release_threshold = 6;
    c.residency.min_resident_frames = 2;
    c.residency.cell_size = 25.0;
    c.build.max_gpu_ms = 50.0;
    c.build.max_primitives = 20_000;
    c.cull.far_distance = 80.0;
    c
}

/// Renders `frame`'s TLAS at a tiny size; returns the hit customIndices.
fn render(
    scene: &mut Scene,
    renderer: &mut Renderer,
    tlas: rtstream::as_manager::backend::TlasHandle,
    records: &[rtstream::as_manager::record::TlasInstance],
    eye: Vec3,
) -> Vec<u32> {
    let backend = scene.manager.backend_mut();
    backend.wait_idle().expect("frame completes");
    let table = common::shading_table(backend, records, 64);
    let traced = backend.tlas(tlas).expect("TLAS of this frame");
    let cam = Camera::look_at(
        eye + Vec3::new(0.0, 12.0, -30.0),
        eye + Vec3::new(0.0, 0.0, 20.0),
        60f32.to_radians(),
    );
    let frame = renderer
        .render(traced, &table, &RenderDesc::new(24, 16, cam))
        .expect("trace without device error");
    frame
        .hits
        .iter()
        .filter(|h| h.is_hit())
        .map(|h| h.instance)
        .collect()
}

/// Renders the frame (`render`) and checks that every hit is on an instance its TLAS holds;
/// returns the hits. `what` names the frame in the failure.
fn render_hits_in_tlas(
    scene: &mut Scene,
    renderer: &mut Renderer,
    tlas: rtstream::as_manager::backend::TlasHandle,
    records: &[rtstream::as_manager::record::TlasInstance],
    eye: Vec3,
    what: &str,
) -> usize {
    let live: std::collections::HashSet<u32> = records.iter().map(|r| r.custom_index()).collect();
    let hits = render(scene, renderer, tlas, records, eye);
    assert!(
        hits.iter().all(|h| live.contains(h)),
        "{what}: a hit on an instance not in the TLAS"
    );
    hits.len()
}

#[test]
fn camera_path_creates_refits_evicts_and_destroys_with_every_frame_traced() {
    let ctx = common::context();
    let mut config = config();
    config.memory.blas_bytes = 900 << 10; // tight: forces LOD fallbacks / evictions
    let mut s = scene(&ctx, VulkanBackendDesc::default(), config.clone());
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let (mut peak, mut evictions, mut releases, mut refits, mut rebuilds, mut traced_hits) =
        (0u64, 0, 0, 0, 0, 0usize);
    let frames = 260u64;
    for frame in 0..frames {
        // Fly along x, then teleport back to the start for the last frames.
        let x = if frame < 220 {
            -40.0 + frame as f32 * 1.8
        } else {
            0.0
        };
        let eye = Vec3::new(x, 2.0, 30.0);
        let amplitude = if (30..70).contains(&frame) { 4.0 } else { 0.0 };
        for (id, base) in &s.skinned {
            s.manager
                .set_skinned_pose(*id, pose(base, frame as f32 * 0.2, amplitude))
                .unwrap();
        }
        let cams = [Viewpoint::new(eye, Vec3::Z)];
        let out = s
            .manager
            .update(FrameInput {
                frame,
                cameras: &cams,
            })
            .expect("frame never fails");
        let (tlas, records, stats) = (out.tlas, out.instances.to_vec(), out.stats.clone());
        assert!(
            stats.blas_bytes + stats.retiring_bytes <= config.memory.blas_bytes,
            "frame {frame}: {} + {} bytes over the {} budget",
            stats.blas_bytes,
            stats.retiring_bytes,
            config.memory.blas_bytes
        );
        peak = peak.max(stats.blas_bytes);
        evictions += stats.evictions + stats.lod_fallbacks;
        releases += stats.releases;
        refits += stats.refits;
        rebuilds += stats.rebuilds;
        traced_hits += render_hits_in_tlas(
            &mut s,
            &mut renderer,
            tlas,
            &records,
            eye,
            &format!("frame {frame}"),
        );
    }
    let c = s.manager.backend().counters();
    eprintln!("counters {c:?}; peak {peak} B; evictions+fallbacks {evictions}; releases {releases}; refits {refits}; rebuilds {rebuilds}; hits {traced_hits}");
    assert!(c.built > 20, "{c:?}");
    assert!(c.refits > 100 && refits > 100, "{c:?}");
    assert!(
        c.rebuilds > 0 && rebuilds > 0,
        "the large deformation must trigger rebuilds: {c:?}"
    );
    assert!(c.destroyed > 10, "{c:?}");
    assert!(
        c.compactions > 5,
        "static BLASes are compacted after their size query: {c:?}"
    );
    assert!(
        releases > 0 && evictions > 0,
        "releases {releases}, evictions {evictions}"
    );
    assert!(traced_hits > 1000, "the traced frames should see geometry");
}

#[test]
fn forced_out_of_memory_is_survived() {
    let ctx = common::context();
    let mut config = config();
    config.memory.blas_bytes = 64 << 20; // the manager thinks it has plenty...
    let desc = VulkanBackendDesc {
        memory_limit: Some(1 << 20),
        ..VulkanBackendDesc::default()
    }; // ...the device has not
    let mut s = scene(&ctx, desc, config);
    let (mut ooms, mut tlas_instances) = (0, 0);
    for frame in 0..80u64 {
        let eye = Vec3::new(frame as f32 * 3.0, 2.0, 30.0);
        for (id, base) in &s.skinned {
            s.manager
                .set_skinned_pose(*id, pose(base, frame as f32 * 0.2, 0.0))
                .unwrap();
        }
        let out = common::update_from(&mut s.manager, frame, Viewpoint::new(eye, Vec3::Z))
            .expect("OOM never fails a frame");
        ooms += out.stats.oom_events;
        tlas_instances += out.stats.tlas_instances;
        assert!(s.manager.backend().blas_allocated_bytes() <= 1 << 20);
    }
    let c = s.manager.backend().counters();
    eprintln!("oom events {ooms}, backend {c:?}, tlas instances summed {tlas_instances}");
    assert!(ooms > 0 && c.oom > 0, "the limit must have been hit");
    assert!(
        tlas_instances > 0,
        "frames still traced something after OOM"
    );
    assert!(s.manager.backend_mut().completed_frame().is_some());
}

/// The streamed path: a small baked world streamed by loader threads along a camera path, fed
/// through the WorldBridge into the manager on the real backend; every frame's TLAS is traced.
#[test]
fn streamed_camera_path_on_vulkan() {
    use rtstream::streaming::{StreamConfig, World};
    let ctx = common::context();
    let (dir, size) = common::baked_small("vk-stream", 6, 7);
    let mut world = World::open(
        &dir,
        StreamConfig {
            load_radius: 80.0,
            unload_radius: 110.0,
            loader_threads: 2,
            ..StreamConfig::default()
        },
    )
    .expect("open");
    let mut bridge = rtstream::WorldBridge::new(world.manifest());
    let mut config = Config::default();
    config.residency.r1 = 60.0;
    config.residency.r2 = 75.0;
    config.residency.release_threshold = 10;
    config.build.max_gpu_ms = 100.0;
    config.build.min_compaction_saving = 0.0;
    let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default()).expect("backend");
    let mut m = AsManager::new(config, backend).expect("manager");
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let frames = 200u64;
    let mut hits = 0usize;
    for frame in 0..frames {
        let t = frame as f32 / frames as f32;
        let pos = Vec3::new(size * (0.05 + 0.9 * t), 2.0, size * (0.05 + 0.9 * t));
        let events = world
            .update_until_idle(frame, &[pos.into()], std::time::Duration::from_secs(10))
            .expect("streaming settles");
        bridge.apply(&m, &events);
        bridge.pose_skinned(&m, &world, frame as f32 / 30.0, 1);
        let fwd = Vec3::new(1.0, 0.0, 1.0).normalize();
        let out = common::update_from(&mut m, frame, Viewpoint::new(pos, fwd)).expect("update");
        let (tlas, records) = (out.tlas, out.instances.to_vec());
        m.backend_mut().wait_idle().expect("frame completes");
        let shading = bridge.shading(&records, |a| m.backend().shading_geometry(a));
        let traced = m.backend().tlas(tlas).expect("TLAS");
        let cam = Camera::look_at(pos, pos + fwd, 60f32.to_radians());
        let f = renderer
            .render(traced, &shading, &RenderDesc::new(16, 12, cam))
            .expect("trace without device error");
        hits += f.hits.iter().filter(|h| h.is_hit()).count();
    }
    let c = m.backend().counters();
    eprintln!("streamed: {c:?}, hits {hits}");
    assert!(
        c.built > 20 && c.compactions > 5 && c.destroyed > 5 && c.refits > 0,
        "{c:?}"
    );
    assert!(hits > 1000, "the streamed world is visible");
    drop(renderer);
    drop(m);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A TLAS handle names its slot and its frame: once the slot is reused for a later frame the
/// old handle resolves to nothing (it used to return the newer TLAS), and so do its primitive
/// bases and the shading lookup through it.
#[test]
fn a_stale_tlas_handle_resolves_to_nothing() {
    let ctx = common::context();
    // Deterministic retirement: a handle also goes stale once a BLAS its frame names is
    // destroyed, and without it that happens as soon as the GPU finishes the frame (the LOD
    // chain's first, coarse BLAS is freed when the finer one replaces it), so which handles
    // resolve would depend on GPU speed. With it, only slot reuse and the retirement schedule
    // decide, and two frames stay in flight.
    let backend = VulkanBackend::new(
        ctx.clone(),
        VulkanBackendDesc {
            frames_in_flight: 2,
            deterministic: true,
            ..VulkanBackendDesc::default()
        },
    )
    .unwrap();
    let mut m = AsManager::new(config(), backend).unwrap();
    let mesh = m
        .register_mesh(MeshDesc::new("grid", MeshKind::Static, 4.0, chain(8, 4.0)))
        .unwrap();
    m.add_instance(InstanceDesc::new(
        mesh,
        Affine3A::from_translation(Vec3::new(0.0, 0.0, 10.0)),
    ))
    .unwrap();
    let cams = [Viewpoint::new(Vec3::ZERO, Vec3::Z)];
    let mut handles = Vec::new();
    for frame in 0..6 {
        let out = m
            .update(FrameInput {
                frame,
                cameras: &cams,
            })
            .unwrap();
        let (tlas, address) = (out.tlas, out.instances.first().map(|r| r.blas_address));
        handles.push((tlas, address));
        // The current frame's handle resolves; every handle of a frame whose slot was reused
        // does not.
        assert!(m.backend().tlas(tlas).is_some(), "frame {frame}");
        for (f, (h, address)) in handles.iter().enumerate() {
            let reused = (f as u64) + 2 <= frame;
            assert_eq!(
                m.backend().tlas(*h).is_none(),
                reused,
                "frame {frame}: handle of frame {f}"
            );
            // The shading lookup of that frame's records takes the same generation.
            if let Some(a) = address {
                let shading = m.backend().shading_geometry_in(*h, *a);
                assert_eq!(
                    matches!(shading, Err(VulkanError::StaleHandle { what: "TLAS", .. })),
                    reused,
                    "frame {frame}: shading lookup through frame {f}'s TLAS"
                );
                if f as u64 == frame {
                    assert!(shading.unwrap().is_some(), "this frame's record is shaded");
                }
            }
            if reused {
                assert_eq!(m.backend().primitive_bases(*h), 0);
            }
        }
    }
}

/// The managed frame schedules its builds and compactions after its records, so the backend
/// records them beside its TLAS (no barrier between: the TLAS names none of them; they show
/// from the next frame). The naive baseline builds before its records, which name the new
/// BLASes: its builds go first, then a barrier, then the TLAS. Both trace only what their
/// TLAS holds, the compacted copies included.
#[test]
fn builds_run_beside_the_tlas_unless_a_record_names_one() {
    let ctx = common::context();
    for (policy, beside) in [
        (rtstream::as_manager::PolicyKind::Managed, true),
        (rtstream::as_manager::PolicyKind::Naive, false),
    ] {
        let mut config = config();
        config.policy = policy;
        // Lavapipe's compacted sizes save little: compact whatever saves anything.
        config.build.min_compaction_saving = 0.0;
        let mut s = scene(&ctx, VulkanBackendDesc::default(), config);
        let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
        let (mut hits_total, mut built_frames) = (0usize, 0u64);
        for frame in 0..40u64 {
            let eye = Vec3::new(-40.0 + frame as f32 * 2.0, 2.0, 30.0);
            let cams = [Viewpoint::new(eye, Vec3::Z)];
            let out = s
                .manager
                .update(FrameInput {
                    frame,
                    cameras: &cams,
                })
                .expect("frame never fails");
            let (tlas, records) = (out.tlas, out.instances.to_vec());
            built_frames += u64::from(out.stats.builds > 0);
            hits_total += render_hits_in_tlas(
                &mut s,
                &mut renderer,
                tlas,
                &records,
                eye,
                &format!("{policy:?} frame {frame}"),
            );
        }
        let c = s.manager.backend().counters();
        assert!(built_frames > 0, "{policy:?}: {c:?}");
        if beside {
            assert_eq!(
                (c.builds_beside_tlas, c.builds_before_tlas),
                (built_frames, 0),
                "{policy:?}: {c:?}"
            );
            // Every compaction was recorded beside a TLAS, and the frames after traced the
            // copies (the hits above).
            assert!(c.compactions > 0, "{policy:?}: {c:?}");
            assert_eq!(
                c.compactions_beside_tlas, c.compactions,
                "{policy:?}: {c:?}"
            );
        } else {
            assert_eq!(
                (c.builds_beside_tlas, c.builds_before_tlas),
                (0, built_frames),
                "{policy:?}: {c:?}"
            );
        }
        assert!(hits_total > 100, "{policy:?}: {hits_total} hits");
    }
}

/// An engine that drives the backend itself may compact a BLAS and name the compacted copy in
/// the same frame's TLAS. The copy then runs before that TLAS, behind a barrier and timed on
/// its own, not beside it (`records_name_pending`); synchronization validation reports a copy
/// and a TLAS build left unordered. The copy is traced in that frame and the next (two frames
/// in flight) and hits what the original hit.
///
/// The original is freed as last used by the frame before, the last whose TLAS named it,
/// although the compacting frame's copy reads it: the backend holds it until that frame
/// completes. (It destroyed it at once: a validation error, and lavapipe crashed running the
/// copy.)
#[test]
fn a_compaction_named_by_its_own_frames_tlas_runs_before_it() {
    use rtstream::as_manager::backend::{BlasBuild, BlasClass, CostOp, GeometryRef, TlasDelta};
    use rtstream::as_manager::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};
    let ctx = common::context();
    // Deterministic retirement: the original's free counts from the copy's frame, and without
    // it the original is destroyed as soon as the GPU finishes that frame, which makes that
    // frame's TLAS handle stale before the test traces it whenever the GPU is quick.
    let mut b = VulkanBackend::new(
        ctx.clone(),
        VulkanBackendDesc {
            frames_in_flight: 2,
            deterministic: true,
            ..VulkanBackendDesc::default()
        },
    )
    .unwrap();
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(24, 20.0);
    let geometry = GeometryRef {
        vertex_count: g.positions.len() as u32,
        triangle_count: (g.indices.len() / 3) as u32,
        positions: Some(&g.positions),
        indices: Some(&g.indices),
        device_vertices: None,
        device_indices: None,
        opaque: true,
    };
    let sizes = b.blas_sizes(&geometry, BlasClass::Static);
    let record = |address: u64| {
        TlasInstance::new(
            &Affine3A::IDENTITY,
            0,
            0xff,
            0,
            INSTANCE_FORCE_OPAQUE,
            address,
        )
    };
    // Looks down at the grid (y = 0) from 15 m, so that most pixels hit it.
    let trace = |b: &mut VulkanBackend, renderer: &mut Renderer, tlas, records: &[TlasInstance]| {
        b.wait_idle().expect("frames complete");
        let table = common::shading_table(b, records, 4);
        let traced = b.tlas(tlas).expect("TLAS of a frame in flight");
        let cam = Camera::look_at(Vec3::new(0.0, 15.0, -8.0), Vec3::ZERO, 60f32.to_radians());
        let f = renderer
            .render(traced, &table, &RenderDesc::new(24, 16, cam))
            .expect("trace without device error");
        f.hits
            .iter()
            .map(|h| (h.instance, h.primitive))
            .collect::<Vec<_>>()
    };
    // Frame 0 builds the BLAS (compactable) and traces it.
    b.begin_frame(0).unwrap();
    let original = b
        .build_blases(&[BlasBuild {
            geometry,
            class: BlasClass::Static,
            sizes,
        }])
        .unwrap()[0];
    // Its TLAS names it: the build goes first.
    let records = [record(b.blas_address(original))];
    let tlas0 = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let before = trace(&mut b, &mut renderer, tlas0, &records);
    let hit = before.iter().filter(|h| h.0 == 0).count();
    assert!(hit > 200, "the grid fills the view: {hit} of 384 pixels");
    // Frames until its compacted size is read (a slot's queries are read when it is reused).
    let mut frame = 1;
    while b.compacted_size(original).is_none() {
        assert!(frame < 8, "the compacted size is read within a few frames");
        b.begin_frame(frame).unwrap();
        b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(frame).unwrap();
        frame += 1;
    }
    let beside_before = b.counters().compactions_beside_tlas;
    // The compacting frame's TLAS names the copy; the next frame frees the original, and
    // both are recorded before either is waited for.
    b.begin_frame(frame).unwrap();
    let copy = b.compact_blas(original).unwrap();
    let copied = [record(b.blas_address(copy))];
    assert_ne!(copied[0].blas_address, records[0].blas_address);
    let tlas_named = b.build_tlas(&copied, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    // Named by no TLAS since frame - 1; the copy in `frame` reads it all the same.
    b.free_blas(original, frame - 1);
    b.begin_frame(frame + 1).unwrap();
    let tlas_next = b
        .build_tlas(
            &copied,
            TlasDelta {
                stable: 1,
                changed: &[],
            },
        )
        .unwrap();
    b.end_frame(frame + 1).unwrap();
    let c = b.counters();
    assert_eq!(c.compactions, 1, "{c:?}");
    assert_eq!(
        c.compactions_beside_tlas, beside_before,
        "the named copy did not run beside the TLAS: {c:?}"
    );
    // Both frames trace the copy as frame 0 traced the original, hit for hit.
    assert_eq!(trace(&mut b, &mut renderer, tlas_named, &copied), before);
    assert_eq!(trace(&mut b, &mut renderer, tlas_next, &copied), before);
    // It was timed on its own, not inside the TLAS's pair (read once its slot is reused).
    b.begin_frame(frame + 2).unwrap();
    b.build_tlas(
        &copied,
        TlasDelta {
            stable: 1,
            changed: &[],
        },
    )
    .unwrap();
    b.end_frame(frame + 2).unwrap();
    let timed = b
        .take_measurements()
        .into_iter()
        .filter(|m| m.op == CostOp::Compact)
        .collect::<Vec<_>>();
    assert_eq!(timed.len(), 1, "{timed:?}");
    assert!(!timed[0].beside, "{timed:?}");
    drop(renderer);
    drop(b);
}
