//! The ground truth: the FULL world, built from the generated world itself (never from what
//! streaming loaded or the manager kept). Every opaque instance at LOD 0, no distance limit,
//! skinned instances posed for the frame; the all-geometry variant adds the non-opaque
//! (masked, transparent) instances as opaque.

use std::sync::Arc;
use std::time::Instant;

use rtstream_as_manager::backend::vulkan::{SceneMesh, VulkanContext};
use rtstream_renderer::{SceneInstance, TracedScene};
use rtstream_streaming::skin::{animation_time, skin_positions};
use rtstream_streaming::{GeneratedWorld, Instance, MaterialClass, Motion};

use crate::bridge::mesh_color;
use crate::error::Result;

/// Which reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TruthKind {
    /// Opaque instances only (what the manager is allowed to trace): the headline reference.
    Opaque,
    /// Every instance, non-opaque ones traced as opaque: the cost of the opaque-only rule.
    AllGeometry,
}

/// The world's instances, sorted once, for building references.
#[derive(Debug)]
pub struct GroundTruth {
    world: Arc<GeneratedWorld>,
    /// Static instances (opaque first, then the others).
    statics: Vec<Instance>,
    opaque_statics: usize,
    /// Skinned instances (opaque first, then the others).
    skinned: Vec<Instance>,
    opaque_skinned: usize,
}

/// A reference scene for one frame.
#[derive(Debug)]
pub struct TruthScene {
    /// BLASes, TLAS and shading (customIndex = position in `ids`).
    pub scene: TracedScene,
    /// World instance id of each customIndex.
    pub ids: Vec<u32>,
    /// Wall time of the build, milliseconds.
    pub build_ms: f64,
    /// Triangles traced.
    pub triangles: u64,
}

impl GroundTruth {
    /// Indexes the world's instances.
    pub fn new(world: Arc<GeneratedWorld>) -> Self {
        let all = world
            .levels
            .iter()
            .flat_map(|l| l.instances.iter().copied());
        let (mut skinned, mut statics): (Vec<Instance>, Vec<Instance>) =
            all.partition(|i| i.motion == Motion::Skinned);
        let opaque_first = |i: &Instance| (i.material != MaterialClass::Opaque, i.id.0);
        statics.sort_by_key(opaque_first);
        skinned.sort_by_key(opaque_first);
        let count = |v: &[Instance]| {
            v.iter()
                .filter(|i| i.material == MaterialClass::Opaque)
                .count()
        };
        Self {
            opaque_statics: count(&statics),
            opaque_skinned: count(&skinned),
            world,
            statics,
            skinned,
        }
    }

    /// Instances the reference of `kind` holds.
    pub fn instance_count(&self, kind: TruthKind) -> usize {
        match kind {
            TruthKind::Opaque => self.opaque_statics + self.opaque_skinned,
            TruthKind::AllGeometry => self.statics.len() + self.skinned.len(),
        }
    }

    /// Every instance of the world (opaque or not).
    pub fn world_instances(&self) -> usize {
        self.statics.len() + self.skinned.len()
    }

    /// Builds the reference of `kind` with skinned instances posed at `time` seconds.
    pub fn build(&self, ctx: &VulkanContext, kind: TruthKind, time: f32) -> Result<TruthScene> {
        let started = Instant::now();
        let (statics, skinned) = match kind {
            TruthKind::Opaque => (
                &self.statics[..self.opaque_statics],
                &self.skinned[..self.opaque_skinned],
            ),
            TruthKind::AllGeometry => (&self.statics[..], &self.skinned[..]),
        };
        // Posed LOD-0 positions of every skinned instance (mesh space).
        let mut posed: Vec<Vec<[f32; 3]>> = Vec::with_capacity(skinned.len());
        for inst in skinned {
            let g = &self.world.meshes[inst.mesh.0 as usize].lods[0];
            let mut out = Vec::new();
            match &g.skin {
                Some(s) => {
                    skin_positions(g, &s.skeleton.pose(animation_time(inst.id, time)), &mut out)
                }
                None => out.clone_from(&g.positions),
            }
            posed.push(out);
        }
        // Scene meshes: each static mesh once (LOD 0), then one per skinned instance.
        let mut mesh_slot = vec![u32::MAX; self.world.meshes.len()];
        let mut descs: Vec<SceneMesh<'_>> = Vec::new();
        let mut instances = Vec::with_capacity(statics.len() + skinned.len());
        let mut ids = Vec::with_capacity(instances.capacity());
        let mut triangles = 0u64;
        for inst in statics {
            let mesh = &self.world.meshes[inst.mesh.0 as usize];
            let slot = &mut mesh_slot[inst.mesh.0 as usize];
            if *slot == u32::MAX {
                *slot = descs.len() as u32;
                descs.push(SceneMesh {
                    name: &mesh.name,
                    positions: &mesh.lods[0].positions,
                    indices: &mesh.lods[0].indices,
                    opaque: true,
                });
            }
            triangles += mesh.lods[0].triangle_count() as u64;
            instances.push(SceneInstance {
                mesh: *slot,
                transform: inst.transform,
                base_color: mesh_color(mesh.id, &mesh.name),
            });
            ids.push(inst.id.0);
        }
        for (inst, positions) in skinned.iter().zip(&posed) {
            let mesh = &self.world.meshes[inst.mesh.0 as usize];
            instances.push(SceneInstance {
                mesh: descs.len() as u32,
                transform: inst.transform,
                base_color: mesh_color(mesh.id, &mesh.name),
            });
            descs.push(SceneMesh {
                name: &mesh.name,
                positions,
                indices: &mesh.lods[0].indices,
                opaque: true,
            });
            triangles += mesh.lods[0].triangle_count() as u64;
            ids.push(inst.id.0);
        }
        let scene = TracedScene::reference(ctx, &descs, &instances)?;
        Ok(TruthScene {
            scene,
            ids,
            build_ms: started.elapsed().as_secs_f64() * 1e3,
            triangles,
        })
    }

    /// Whether the reference holds instances of levels that streaming never loaded: the ids of
    /// `kind`'s instances in levels for which `loaded(level index)` is false.
    pub fn instances_outside(&self, kind: TruthKind, loaded: impl Fn(usize) -> bool) -> usize {
        let opaque_only = kind == TruthKind::Opaque;
        self.world
            .levels
            .iter()
            .enumerate()
            .filter(|(i, _)| !loaded(*i))
            .map(|(_, l)| {
                l.instances
                    .iter()
                    .filter(|i| !opaque_only || i.material == MaterialClass::Opaque)
                    .count()
            })
            .sum()
    }
}
