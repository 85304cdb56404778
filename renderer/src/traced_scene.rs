//! Reference mode: a scene traced with every instance, the finest LOD and no culling, built once
//! per evaluated frame from meshes and instances ([`StaticScene`] under the hood), so a managed
//! frame can be compared with the same camera against it.

use glam::Mat4;
use rtstream_as_manager::backend::vulkan::{SceneMesh, StaticInstance, StaticScene, VulkanContext};

use crate::error::Result;
use crate::frame::Frame;
use crate::reference::ReferenceScene;
use crate::renderer::{InstanceShading, RenderDesc, Renderer};

/// One placement of a mesh in a [`TracedScene`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneInstance {
    /// Index into the scene's meshes.
    pub mesh: u32,
    /// Object-to-world transform.
    pub transform: Mat4,
    /// Linear RGBA base colour.
    pub base_color: [f32; 4],
}

/// Meshes with their BLASes and a TLAS over (a subset of) the instances. Instance `i` always has
/// customIndex `i`, whatever subset is traced, so frames of different subsets compare directly
/// with [`FrameMetrics::compare`](crate::FrameMetrics::compare).
#[derive(Debug)]
pub struct TracedScene {
    /// BLASes, TLAS and mesh buffers.
    pub accel: StaticScene,
    /// Shading data of every instance (traced or not), indexed by customIndex.
    pub shading: Vec<InstanceShading>,
    /// Instances in the TLAS.
    pub traced_instances: usize,
}

impl TracedScene {
    /// The reference: every instance, the meshes as given (the finest LOD), no culling.
    pub fn reference(
        ctx: &VulkanContext,
        meshes: &[SceneMesh<'_>],
        instances: &[SceneInstance],
    ) -> Result<Self> {
        Self::subset(ctx, meshes, instances, |_| true)
    }

    /// A TLAS over the instances `keep` accepts (e.g. the survivors of a culler).
    pub fn subset(
        ctx: &VulkanContext,
        meshes: &[SceneMesh<'_>],
        instances: &[SceneInstance],
        keep: impl Fn(usize) -> bool,
    ) -> Result<Self> {
        debug_assert!(instances.len() < 1 << 24, "customIndex has 24 bits");
        let descs: Vec<StaticInstance> = instances
            .iter()
            .enumerate()
            .filter(|(i, _)| keep(*i))
            .map(|(i, inst)| StaticInstance {
                mesh: inst.mesh,
                transform: inst.transform.to_cols_array(),
                custom_index: i as u32,
                mask: 0xff,
            })
            .collect();
        let accel = StaticScene::build(ctx, meshes, &descs)?;
        let shading = instances
            .iter()
            .map(|inst| {
                let gm = &accel.meshes[inst.mesh as usize];
                InstanceShading {
                    vertices: gm.geometry.vertices.address,
                    indices: gm.geometry.indices.address,
                    base_color: inst.base_color,
                }
            })
            .collect();
        Ok(Self {
            accel,
            shading,
            traced_instances: descs.len(),
        })
    }

    /// Renders the scene.
    pub fn render(&self, renderer: &mut Renderer, desc: &RenderDesc) -> Result<Frame> {
        renderer.render(self.accel.tlas_ref(), &self.shading, desc)
    }

    /// Destroys the GPU objects, once the device has finished what it was given (frames
    /// recorded with [`Renderer::record`] may still trace the scene).
    pub fn destroy(self, ctx: &VulkanContext) {
        if let Err(e) = ctx.wait_idle() {
            tracing::warn!(error = %e, "TracedScene::destroy: waiting for the device failed");
        }
        self.accel.destroy(ctx);
    }
}

/// The CPU reference caster's BVH over the same meshes and instances (ids = instance indices).
pub fn cpu_reference(meshes: &[SceneMesh<'_>], instances: &[SceneInstance]) -> ReferenceScene {
    let m: Vec<(&[[f32; 3]], &[u32])> = meshes.iter().map(|m| (m.positions, m.indices)).collect();
    let i: Vec<(usize, Mat4, u32)> = instances
        .iter()
        .enumerate()
        .map(|(i, inst)| (inst.mesh as usize, inst.transform, i as u32))
        .collect();
    ReferenceScene::new(&m, &i)
}
