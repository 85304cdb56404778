//! The foundation's end-to-end check: a real glTF mesh into real BLASes and a TLAS, traced by the
//! ray-query shader on lavapipe, compared with the CPU reference caster.

mod common;

use glam::Vec3;
use rtstream::renderer::{Camera, RenderDesc, Renderer};
use rtstream::{reference_scene, world_bounds, GpuGltfScene};

#[test]
fn gpu_hits_match_cpu_reference_on_2cylinder_engine() {
    let path = common::asset("2CylinderEngine-glTF-Binary/2CylinderEngine.glb");
    let scene = rtstream::streaming::load_gltf(&path).expect("engine loads");
    let ctx = common::context();
    let gpu = GpuGltfScene::build(&ctx, &scene).expect("scene builds");
    assert_eq!(gpu.accel.stats.blas_count as usize, scene.meshes.len());
    assert!(gpu.accel.stats.blas_bytes > 0 && gpu.accel.stats.tlas_bytes > 0);

    let (lo, hi) = world_bounds(&scene);
    let mut camera = Camera::framing(lo, hi, Vec3::new(0.7, 0.5, 1.0), 40f32.to_radians());
    // Move in so the engine fills a good part of the square image.
    let c = (lo + hi) * 0.5;
    camera.position = c + (camera.position - c) * 0.6;
    let desc = RenderDesc {
        sun_dir: Vec3::new(0.4, 1.0, 0.3),
        ..RenderDesc::new(128, 128, camera)
    };
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let frame = renderer
        .render(gpu.accel.tlas_ref(), &gpu.shading, &desc)
        .expect("render");

    let cpu = reference_scene(&scene).cast(&camera, desc.width, desc.height);
    let n = cpu.len();
    let mask_agree = frame
        .hits
        .iter()
        .zip(&cpu)
        .filter(|(g, c)| g.is_hit() == c.is_some())
        .count();
    let id_agree = frame
        .hits
        .iter()
        .zip(&cpu)
        .filter(|(g, c)| match c {
            Some(c) => g.instance == c.instance,
            None => !g.is_hit(),
        })
        .count();
    let hit_share = frame.hit_fraction();
    eprintln!(
        "hit mask agreement {:.4}, instance agreement {:.4}, hit share {:.3}",
        mask_agree as f64 / n as f64,
        id_agree as f64 / n as f64,
        hit_share
    );
    assert!(
        hit_share >= 0.10,
        "image is nearly empty: {hit_share:.3} of pixels hit"
    );
    assert!(
        hit_share <= 0.98,
        "image is nearly full: {hit_share:.3} of pixels hit"
    );
    assert!(
        mask_agree as f64 >= 0.995 * n as f64,
        "hit masks agree on only {mask_agree}/{n} pixels"
    );
    assert!(
        id_agree as f64 >= 0.99 * n as f64,
        "hit instances agree on only {id_agree}/{n} pixels"
    );
    // Shadow rays ran: some lit, some shadowed pixels among the hits.
    let shadowed = frame
        .hits
        .iter()
        .filter(|h| h.is_hit() && h.shadowed == 1)
        .count();
    assert!(shadowed > 0 && shadowed < frame.hits.iter().filter(|h| h.is_hit()).count());

    drop(renderer);
    gpu.destroy(&ctx);
}

#[test]
fn bad_paths_and_broken_models_are_typed_errors_naming_the_file() {
    let missing = std::path::Path::new("/nonexistent/rtstream/engine.glb");
    let e = rtstream::streaming::load_gltf(missing).expect_err("missing file");
    assert!(
        matches!(e, rtstream::streaming::StreamingError::Gltf { .. }),
        "{e:?}"
    );
    assert!(
        e.to_string().contains("/nonexistent/rtstream/engine.glb"),
        "{e}"
    );

    for rel in [
        "IndexOutOfRange/IndexOutOfRange.gltf",
        "IndexOutOfRange/AllIndicesOutOfRange.gltf",
        "BoxWithInfinites-glTF-Binary/BoxWithInfinites.glb",
        "MissingBin/BoxTextured.gltf",
        "wrongTypes/badNumber.gltf",
        "wrongTypes/badArray.gltf",
        "RecursiveNodes/RecursiveNodes.gltf",
        "SchemaFailures/sceneWrongType.gltf",
        "IncorrectVertexArrays/Cube.gltf",
    ] {
        let path = common::asset(rel);
        let e = rtstream::streaming::load_gltf(&path).expect_err(rel);
        assert!(
            e.to_string().contains(&*path.to_string_lossy()),
            "{rel}: error does not name the file: {e}"
        );
    }

    // A truncated .glb: the first half of the real engine file.
    let bytes = std::fs::read(common::asset(
        "2CylinderEngine-glTF-Binary/2CylinderEngine.glb",
    ))
    .unwrap();
    let dir = common::temp_path("test");
    std::fs::create_dir_all(&dir).unwrap();
    let truncated = dir.join("truncated.glb");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let e = rtstream::streaming::load_gltf(&truncated).expect_err("truncated glb");
    assert!(e.to_string().contains("truncated.glb"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}
