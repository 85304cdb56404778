//! A glTF scene on the GPU: every mesh's BLAS, a TLAS over its node instances, shading data.
//!
//! This is the "everything resident" path (the thin slice, and the reference for managed frames).

use glam::Vec3;
use rtstream_as_manager::backend::vulkan::{SceneMesh, StaticInstance, StaticScene, VulkanContext};
use rtstream_renderer::reference::ReferenceScene;
use rtstream_renderer::InstanceShading;
use rtstream_streaming::{GltfScene, TriMesh};

use crate::error::Result;

/// A glTF scene uploaded and built. Instance `i` of the glTF scene has customIndex `i`.
#[derive(Debug)]
pub struct GpuGltfScene {
    /// The BLASes, the TLAS and the mesh buffers.
    pub accel: StaticScene,
    /// Shading data indexed by customIndex.
    pub shading: Vec<InstanceShading>,
}

impl GpuGltfScene {
    /// Uploads every mesh, builds one BLAS per mesh in one batched build, and a TLAS.
    pub fn build(ctx: &VulkanContext, scene: &GltfScene) -> Result<Self> {
        let meshes: Vec<SceneMesh<'_>> = scene.meshes.iter().map(scene_mesh).collect();
        let instances: Vec<StaticInstance> = scene
            .instances
            .iter()
            .enumerate()
            .map(|(i, inst)| StaticInstance {
                mesh: inst.mesh as u32,
                transform: inst.transform.to_cols_array(),
                custom_index: i as u32,
                mask: 0xff,
            })
            .collect();
        let accel = StaticScene::build(ctx, &meshes, &instances)?;
        let shading = scene
            .instances
            .iter()
            .map(|inst| {
                let gm = &accel.meshes[inst.mesh].geometry;
                InstanceShading {
                    vertices: gm.vertices.address,
                    indices: gm.indices.address,
                    base_color: scene.meshes[inst.mesh].base_color,
                }
            })
            .collect();
        Ok(Self { accel, shading })
    }

    /// Destroys the GPU objects.
    pub fn destroy(self, ctx: &VulkanContext) {
        self.accel.destroy(ctx);
    }
}

/// A glTF mesh as an opaque mesh of a static scene (borrowing its data).
pub fn scene_mesh(m: &TriMesh) -> SceneMesh<'_> {
    SceneMesh {
        name: &m.name,
        positions: &m.positions,
        indices: &m.indices,
        opaque: true,
    }
}

/// The CPU reference BVH of a glTF scene, with instance ids equal to the GPU's customIndex.
pub fn reference_scene(scene: &GltfScene) -> ReferenceScene {
    let meshes: Vec<(&[[f32; 3]], &[u32])> = scene
        .meshes
        .iter()
        .map(|m| (&m.positions[..], &m.indices[..]))
        .collect();
    let instances: Vec<_> = scene
        .instances
        .iter()
        .enumerate()
        .map(|(i, inst)| (inst.mesh, inst.transform, i as u32))
        .collect();
    ReferenceScene::new(&meshes, &instances)
}

/// World-space bounds of every instance of the scene.
pub fn world_bounds(scene: &GltfScene) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for inst in &scene.instances {
        for p in &scene.meshes[inst.mesh].positions {
            let w = inst.transform.transform_point3(Vec3::from(*p));
            lo = lo.min(w);
            hi = hi.max(w);
        }
    }
    (lo, hi)
}
