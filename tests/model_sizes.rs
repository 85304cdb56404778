//! The model backend's size predictions against what the real driver (lavapipe here) reports
//! through vkGetAccelerationStructureBuildSizesKHR, on real meshes (Debian's assimp-testmodels)
//! and generated ones (the streaming generator's meshes and their meshoptimizer LODs).

mod common;

use rtstream::as_manager::backend::model::ModelBackend;
use rtstream::as_manager::backend::vulkan::{VulkanBackend, VulkanBackendDesc};
use rtstream::as_manager::backend::{AsBackend, BlasClass, GeometryRef};

fn walk(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return;
    };
    for e in rd.flatten() {
        let p = e.path();
        if p.is_dir() {
            walk(&p, out);
        } else if p.extension().is_some_and(|x| x == "gltf" || x == "glb") {
            out.push(p);
        }
    }
}

#[test]
fn model_sizes_are_within_10_percent_of_lavapipe() {
    let ctx = common::context();
    let real = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default()).expect("backend");
    let model = ModelBackend::lavapipe();

    // (name, vertices, triangles)
    let mut meshes: Vec<(String, u32, u32)> = Vec::new();
    let mut files = Vec::new();
    walk(std::path::Path::new(common::ASSETS), &mut files);
    files.sort();
    for f in &files {
        if let Ok(scene) = rtstream::streaming::load_gltf(f) {
            for m in scene.meshes {
                meshes.push((
                    format!("{}:{}", f.display(), m.name),
                    m.positions.len() as u32,
                    m.triangle_count() as u32,
                ));
            }
        }
    }
    let real_count = meshes.len();
    let world = rtstream::streaming::generate(&rtstream::streaming::WorldPreset::small(4, 7))
        .expect("generate");
    for m in &world.meshes {
        for (l, lod) in m.lods.iter().enumerate() {
            meshes.push((
                format!("{}/lod{l}", m.name),
                lod.positions.len() as u32,
                (lod.indices.len() / 3) as u32,
            ));
        }
    }
    assert!(
        real_count >= 30,
        "expected the assimp glTF2 meshes, found {real_count}"
    );
    assert!(meshes.len() > real_count + 20);

    let mut worst = (0.0f64, String::new());
    for (name, v, t) in &meshes {
        for class in [BlasClass::Static, BlasClass::Skinned] {
            let g = GeometryRef {
                vertex_count: *v,
                triangle_count: *t,
                positions: None,
                indices: None,
                device_vertices: None,
                device_indices: None,
                opaque: true,
            };
            let truth = real.blas_sizes(&g, class).as_bytes as f64;
            let predicted = model.blas_sizes(&g, class).as_bytes as f64;
            let err = (predicted - truth).abs() / truth;
            if err > worst.0 {
                worst = (
                    err,
                    format!(
                        "{name} ({t} triangles, {class:?}): model {predicted} vs driver {truth}"
                    ),
                );
            }
        }
    }
    eprintln!(
        "{} meshes ({} real); worst relative error {:.4}: {}",
        meshes.len(),
        real_count,
        worst.0,
        worst.1
    );
    assert!(
        worst.0 <= 0.10,
        "worst relative error {:.3}: {}",
        worst.0,
        worst.1
    );
}
