//! The evaluation scene of `compare` and `tests/render_passes.rs`: a multi-instance world built
//! from real assets (Debian's assimp-testmodels), and the instances the manager's culler keeps.
//! A test fixture, not rtstream's API: included with `#[path = "support/eval.rs"] mod eval;`
//! (from `tests/`, `#[path = "../examples/support/eval.rs"]`); not every user uses every item.
#![allow(dead_code)]

use std::path::PathBuf;

use glam::{Mat4, Quat, Vec3};
use rtstream::as_manager::backend::vulkan::SceneMesh;
use rtstream::as_manager::config::{Config, CullConfig, CullMode};
use rtstream::as_manager::cull::InstanceCuller;
use rtstream::renderer::reference::ReferenceScene;
use rtstream::renderer::{cpu_reference, Camera, SceneInstance};
use rtstream::streaming::{load_gltf, GltfScene, TriMesh, ASSIMP_GLTF2_DIR};
use rtstream::{Error, Result};

/// The asset directory: `RTSTREAM_ASSETS` when set (e.g. a copy carried to the GPU machine,
/// which has no assimp-testmodels), else Debian's ([`ASSIMP_GLTF2_DIR`]). The world
/// generator's `--asset-dir` defaults to the same variable, so one setting serves both.
pub fn asset_dir() -> PathBuf {
    std::env::var_os("RTSTREAM_ASSETS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(ASSIMP_GLTF2_DIR))
}

/// A world of meshes and instances (instance `i` has customIndex `i` when traced).
#[derive(Debug, Clone, Default)]
pub struct EvalWorld {
    /// The meshes.
    pub meshes: Vec<TriMesh>,
    /// The instances.
    pub instances: Vec<SceneInstance>,
}

/// The most models [`EvalWorld::demo`] places (`rows * columns`): 10,000 models are about
/// 300,000 instances, which lavapipe builds and traces in well under a minute.
pub const MAX_DEMO_MODELS: u32 = 10_000;

/// Layout of [`EvalWorld::demo`].
#[derive(Debug, Clone, Copy)]
pub struct DemoWorldDesc {
    /// Rows of models, each farther away than the last (distance grows geometrically).
    pub rows: u32,
    /// Models per row.
    pub columns: u32,
    /// Distance of the first row from the origin (metres along -z).
    pub first_row: f32,
    /// Each row is this many times farther than the previous one.
    pub row_growth: f32,
}

impl DemoWorldDesc {
    /// Checks the layout: at least one row and one column, at most [`MAX_DEMO_MODELS`] models,
    /// finite positive distances, and a farthest row at a finite distance.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: String| Err(Error::InvalidRun(format!("demo world: {what}")));
        if self.rows == 0 || self.columns == 0 {
            return bad(format!(
                "{} rows of {} models (at least one of each)",
                self.rows, self.columns
            ));
        }
        if u64::from(self.rows) * u64::from(self.columns) > u64::from(MAX_DEMO_MODELS) {
            return bad(format!(
                "{} rows of {} models is more than {MAX_DEMO_MODELS} models",
                self.rows, self.columns
            ));
        }
        let pos = |v: f32| v.is_finite() && v > 0.0;
        if !(pos(self.first_row) && pos(self.row_growth)) {
            return bad(format!(
                "first row at {} m, growing {}x a row (finite and > 0)",
                self.first_row, self.row_growth
            ));
        }
        let far = self.farthest_row();
        if !(far * 4.0 + 50.0).is_finite() {
            return bad(format!(
                "the last of {} rows is at {far} m (not a finite distance)",
                self.rows
            ));
        }
        Ok(())
    }

    /// Distance of the last row.
    fn farthest_row(&self) -> f32 {
        let mut far = self.first_row;
        for _ in 1..self.rows {
            far *= self.row_growth;
        }
        far
    }
}

impl Default for DemoWorldDesc {
    fn default() -> Self {
        Self {
            rows: 6,
            columns: 6,
            first_row: 5.0,
            row_growth: 1.6,
        }
    }
}

/// The meshes of a glTF file, scaled so the whole model's largest extent is `size` and placed
/// on the ground (min y = 0), centred on x/z. Returns (first mesh index, per-node instances).
fn add_model(world: &mut EvalWorld, scene: &GltfScene, size: f32) -> (u32, Vec<(u32, Mat4)>) {
    let (lo, hi) = rtstream::world_bounds(scene);
    let ext = (hi - lo).max_element().max(1e-6);
    let s = size / ext;
    let centre = Vec3::new((lo.x + hi.x) * 0.5, lo.y, (lo.z + hi.z) * 0.5);
    let normalize = Mat4::from_scale(Vec3::splat(s)) * Mat4::from_translation(-centre);
    let first = world.meshes.len() as u32;
    world.meshes.extend(scene.meshes.iter().cloned());
    let nodes = scene
        .instances
        .iter()
        .map(|i| (first + i.mesh as u32, normalize * i.transform))
        .collect();
    (first, nodes)
}

fn ground(size: f32) -> TriMesh {
    let h = size * 0.5;
    TriMesh {
        name: "ground".into(),
        positions: vec![[-h, 0.0, -h], [h, 0.0, -h], [h, 0.0, h], [-h, 0.0, h]],
        normals: Vec::new(),
        indices: vec![0, 2, 1, 0, 3, 2],
        base_color: [0.45, 0.5, 0.4, 1.0],
        material: rtstream_streaming::MaterialClass::Opaque,
        skin: None,
    }
}

fn palette(k: u32) -> [f32; 4] {
    const P: [[f32; 4]; 6] = [
        [0.8, 0.3, 0.25, 1.0],
        [0.3, 0.6, 0.85, 1.0],
        [0.9, 0.75, 0.3, 1.0],
        [0.45, 0.75, 0.4, 1.0],
        [0.7, 0.45, 0.8, 1.0],
        [0.85, 0.85, 0.85, 1.0],
    ];
    P[k as usize % P.len()]
}

impl EvalWorld {
    /// A ground plane and rows of 2CylinderEngines, boxes and morph cubes at growing distances
    /// along -z (a camera at [`EvalWorld::demo_camera`] sees near and far models at once).
    pub fn demo(desc: &DemoWorldDesc) -> Result<Self> {
        Self::demo_in(&asset_dir(), desc)
    }

    /// [`EvalWorld::demo`] with the models read from `dir` (a copy of assimp-testmodels' glTF2
    /// directory) instead of [`asset_dir`].
    pub fn demo_in(dir: &std::path::Path, desc: &DemoWorldDesc) -> Result<Self> {
        desc.validate()?;
        let engine = load_gltf(dir.join("2CylinderEngine-glTF-Binary/2CylinderEngine.glb"))?;
        let cube = load_gltf(dir.join("BoxTextured-glTF/BoxTextured.gltf"))?;
        let morph = load_gltf(
            dir.join("glTF-Sample-Models/AnimatedMorphCube-glTF/AnimatedMorphCube.gltf"),
        )?;
        let mut world = Self::default();
        let far = desc.farthest_row();
        world.meshes.push(ground(far * 4.0 + 50.0));
        world.instances.push(SceneInstance {
            mesh: 0,
            transform: Mat4::IDENTITY,
            base_color: [0.45, 0.5, 0.4, 1.0],
        });
        let models = [
            add_model(&mut world, &engine, 3.0).1,
            add_model(&mut world, &cube, 1.2).1,
            add_model(&mut world, &morph, 1.6).1,
        ];
        let mut dist = desc.first_row;
        for row in 0..desc.rows {
            // Spread the row over about the same view angle at every distance.
            let half_width = dist * 0.7;
            for col in 0..desc.columns {
                let k = row * desc.columns + col;
                let u = if desc.columns > 1 {
                    col as f32 / (desc.columns - 1) as f32 * 2.0 - 1.0
                } else {
                    0.0
                };
                let at = Vec3::new(u * half_width, 0.0, -dist);
                let kind = (row + col) as usize % models.len();
                let spin = Quat::from_rotation_y(k as f32 * 0.7);
                let place = Mat4::from_rotation_translation(spin, at);
                for &(mesh, node) in &models[kind] {
                    world.instances.push(SceneInstance {
                        mesh,
                        transform: place * node,
                        base_color: palette(row * 7 + col),
                    });
                }
            }
            dist *= desc.row_growth;
        }
        Ok(world)
    }

    /// The camera the demo world is laid out for.
    pub fn demo_camera() -> Camera {
        Camera::look_at(
            Vec3::new(0.0, 4.5, 2.0),
            Vec3::new(0.0, 0.0, -22.0),
            55f32.to_radians(),
        )
    }

    /// The meshes as upload descriptions (opaque).
    pub fn mesh_descs(&self) -> Vec<SceneMesh<'_>> {
        self.meshes.iter().map(rtstream::scene_mesh).collect()
    }

    /// World-space bounding sphere (centre, radius) of every instance (of its mesh's local AABB).
    pub fn bounding_spheres(&self) -> Vec<(Vec3, f32)> {
        self.instances
            .iter()
            .map(|inst| {
                let (lo, hi) = self.meshes[inst.mesh as usize].bounds();
                let c = inst.transform.transform_point3((lo + hi) * 0.5);
                let (scale, _, _) = inst.transform.to_scale_rotation_translation();
                (c, (hi - lo).length() * 0.5 * scale.abs().max_element())
            })
            .collect()
    }

    /// The CPU reference caster over every instance.
    pub fn cpu_reference(&self) -> ReferenceScene {
        cpu_reference(&self.mesh_descs(), &self.instances)
    }

    /// Triangles over all instances.
    pub fn instanced_triangles(&self) -> u64 {
        self.instances
            .iter()
            .map(|i| self.meshes[i.mesh as usize].triangle_count() as u64)
            .sum()
    }
}

/// The instances the manager's culler ([`InstanceCuller`], the one `AsManager` runs) keeps when
/// it tests projected angle only (`CullMode::Small`, UE5's small-object test
/// `R^2 / |c - e|^2 < tan^2(angle)`) at `angle` radians from `eye`, for one frame: no near
/// distance, no hysteresis. An instance whose sphere contains the eye is always kept. Returns
/// the keep mask, one entry per `(centre, radius)` sphere.
///
/// # Panics
/// On an angle the manager's configuration refuses (see [`try_kept_by_culler`]).
pub fn kept_by_culler(eye: Vec3, spheres: &[(Vec3, f32)], angle: f32) -> Vec<bool> {
    try_kept_by_culler(eye, spheres, angle).expect("a valid culling angle")
}

/// [`kept_by_culler`], or the manager's configuration error when it refuses `angle` (NaN,
/// infinite, negative, or not below pi/2: `Config::validate`).
pub fn try_kept_by_culler(eye: Vec3, spheres: &[(Vec3, f32)], angle: f32) -> Result<Vec<bool>> {
    let cull = CullConfig {
        mode: CullMode::Small,
        min_angle: angle,
        near_distance: 0.0,
        hysteresis: 0.0,
        ..CullConfig::default()
    };
    // The culler checks nothing itself: the manager's configuration does, for the culler it
    // runs.
    Config {
        cull: cull.clone(),
        ..Config::default()
    }
    .validate()?;
    let culler = InstanceCuller::new(&cull);
    Ok(spheres
        .iter()
        .map(|&(c, r)| !culler.cull(r, c.distance(eye), false))
        .collect())
}
