//! Shared test set-up: a Vulkan context with validation required, and a check that it stayed silent.

#![allow(dead_code)]

use std::sync::Arc;

use rtstream::as_manager::backend::vulkan::{
    ContextDesc, Validation, VulkanBackend, VulkanBackendDesc, VulkanContext,
};

/// Debian's assimp-testmodels glTF 2 directory (the world generator's default too).
pub const ASSETS: &str = rtstream::streaming::ASSIMP_GLTF2_DIR;

/// Path of a model in Debian's assimp-testmodels, with a clear failure when it is missing.
pub fn asset(rel: &str) -> std::path::PathBuf {
    let p = std::path::Path::new(ASSETS).join(rel);
    assert!(
        p.exists(),
        "{} is missing: run scripts/setup.sh (it installs Debian's assimp-testmodels)",
        p.display()
    );
    p
}

/// A small world (`grid` x `grid` levels of the default map, `seed`) generated and baked into a
/// fresh temporary directory `rtstream-<name>-<pid>`; returns the directory and the world's side
/// in metres.
pub fn baked_small(name: &str, grid: u32, seed: u64) -> (std::path::PathBuf, f32) {
    use rtstream::streaming::{bake, generate, WorldPreset};
    let dir = std::env::temp_dir().join(format!("rtstream-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let world = generate(&WorldPreset::small(grid, seed)).expect("generate");
    bake(&world, &dir).expect("bake");
    (dir, world.preset.size_m)
}

/// A context with the validation layer required (a missing layer fails the test).
pub fn context() -> Arc<VulkanContext> {
    let _ = tracing_subscriber::fmt()
        .with_test_writer()
        .with_env_filter("warn")
        .try_init();
    let desc = ContextDesc {
        app_name: "rtstream tests".into(),
        validation: Validation::Required,
        require_ray_query: true,
        ..ContextDesc::default()
    };
    Arc::new(VulkanContext::new(&desc).unwrap_or_else(|e| panic!("Vulkan context: {e}")))
}

/// Fails the test if the validation layer reported anything.
pub fn assert_no_validation_messages(ctx: &VulkanContext) {
    let log = ctx.validation_log();
    assert_eq!(
        log.failure_count(),
        0,
        "validation messages:\n{}",
        log.messages().join("\n")
    );
}

/// A mesh's one level of detail: `geometry` itself, exact (geometric error 0).
pub fn one_lod(
    geometry: Arc<rtstream::as_manager::GeometryData>,
) -> Vec<rtstream::as_manager::LodDesc> {
    vec![rtstream::as_manager::LodDesc {
        geometry: rtstream::as_manager::LodGeometry::Data(geometry),
        geometric_error: 0.0,
    }]
}

/// The grid walk both frame-path tests trace, on a manager of their own configuration: 24
/// static grids (6 to 8 m, 12 to 16 cells; custom indices 0 to 23) in rows of `per_row`, 15 m
/// apart from z = 10 m, and a skinned cloth (custom index 100) at (0, 2, 5).
pub struct GridWalk {
    pub m: rtstream::as_manager::AsManager<VulkanBackend>,
    /// The cloth's instance.
    pub cloth: rtstream::as_manager::InstanceId,
    /// The cloth's rest geometry.
    pub base: Arc<rtstream::as_manager::GeometryData>,
}

impl GridWalk {
    pub fn new(
        ctx: &Arc<VulkanContext>,
        desc: VulkanBackendDesc,
        config: rtstream::as_manager::Config,
        per_row: u32,
    ) -> GridWalk {
        use glam::{Affine3A, Vec3};
        use rtstream::as_manager::synth::grid_geometry;
        use rtstream::as_manager::{AsManager, InstanceDesc, MeshDesc, MeshKind};
        let backend = VulkanBackend::new(ctx.clone(), desc).unwrap();
        let m = AsManager::new(config, backend).unwrap();
        for k in 0..24u32 {
            let mesh = m
                .register_mesh(MeshDesc::new(
                    format!("grid{k}"),
                    MeshKind::Static,
                    6.0,
                    one_lod(grid_geometry(12 + k % 5, 8.0)),
                ))
                .unwrap();
            let p = Vec3::new(
                (k % per_row) as f32 * 15.0,
                0.0,
                (k / per_row) as f32 * 15.0 + 10.0,
            );
            let mut d = InstanceDesc::new(mesh, Affine3A::from_translation(p));
            d.custom_index = k;
            m.add_instance(d).unwrap();
        }
        let base = grid_geometry(16, 5.0);
        let cloth_mesh = m
            .register_mesh(MeshDesc::new(
                "cloth",
                MeshKind::Skinned,
                4.0,
                one_lod(base.clone()),
            ))
            .unwrap();
        let mut d = InstanceDesc::new(
            cloth_mesh,
            Affine3A::from_translation(Vec3::new(0.0, 2.0, 5.0)),
        );
        d.custom_index = 100;
        let cloth = m.add_instance(d).unwrap();
        GridWalk { m, cloth, base }
    }

    /// Sets the cloth's pose of frame `frame`: a wave along x of half a metre.
    pub fn pose(&self, frame: u64) {
        let pose: Vec<[f32; 3]> = self
            .base
            .positions
            .iter()
            .map(|p| [p[0], (p[0] + frame as f32 * 0.3).sin() * 0.5, p[2]])
            .collect();
        self.m.set_skinned_pose(self.cloth, Arc::new(pose)).unwrap();
    }
}
