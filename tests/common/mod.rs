//! Shared test set-up: a Vulkan context with validation required, and a check that it stayed silent.

#![allow(dead_code)]

pub mod direct;

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

/// `rtstream-<name>-<pid>` in the system's temporary directory (not created).
pub fn temp_path(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("rtstream-{name}-{}", std::process::id()))
}

/// A small world (`grid` x `grid` levels of the default map, `seed`) generated and baked into a
/// fresh temporary directory ([`temp_path`]); returns the directory and the world's side in
/// metres.
pub fn baked_small(name: &str, grid: u32, seed: u64) -> (std::path::PathBuf, f32) {
    use rtstream::streaming::{bake, generate, WorldPreset};
    let dir = temp_path(name);
    let _ = std::fs::remove_dir_all(&dir);
    let world = generate(&WorldPreset::small(grid, seed)).expect("generate");
    bake(&world, &dir).expect("bake");
    (dir, world.preset.size_m)
}

/// A context with the validation layer required (a missing layer fails the test), checked
/// when it goes out of scope: see [`TestContext`].
pub fn context() -> TestContext {
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
    TestContext(Some(Arc::new(
        VulkanContext::new(&desc).unwrap_or_else(|e| panic!("Vulkan context: {e}")),
    )))
}

/// A flat `n` x `n` grid mesh of `size` metres uploaded to `ctx` (opaque), for the tests that
/// only need some real geometry on the device.
pub fn grid_on_gpu(
    ctx: &VulkanContext,
    n: u32,
    size: f32,
) -> rtstream::as_manager::backend::vulkan::GpuGeometry {
    let g = rtstream::as_manager::synth::grid_geometry(n, size);
    let mesh = rtstream::as_manager::backend::vulkan::SceneMesh {
        name: "grid",
        positions: &g.positions,
        indices: &g.indices,
        opaque: true,
    };
    rtstream::as_manager::backend::vulkan::GpuGeometry::upload(ctx, &mesh)
        .unwrap_or_else(|e| panic!("grid upload: {e}"))
}

/// A test's Vulkan context ([`context`]; it derefs to the `Arc`). When it goes out of scope it
/// fails the test if the validation layer reported anything ([`assert_no_validation_messages`]),
/// unless the test is failing already. Declared first, it is dropped last: everything the test
/// made from it is released, and its validation messages are in, by then. A test checks
/// earlier, at a point of its own, with [`assert_no_validation_messages`].
pub struct TestContext(Option<Arc<VulkanContext>>);

impl TestContext {
    /// The context itself, checked now instead of when the `TestContext` goes out of scope.
    pub fn into_inner(mut self) -> Arc<VulkanContext> {
        let ctx = self
            .0
            .take()
            .expect("a TestContext holds its context until dropped");
        assert_no_validation_messages(&ctx);
        ctx
    }
}

impl std::ops::Deref for TestContext {
    type Target = Arc<VulkanContext>;
    fn deref(&self) -> &Arc<VulkanContext> {
        self.0
            .as_ref()
            .expect("a TestContext holds its context until dropped")
    }
}

impl Drop for TestContext {
    fn drop(&mut self) {
        if let Some(ctx) = &self.0 {
            if !std::thread::panicking() {
                assert_no_validation_messages(ctx);
            }
        }
    }
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

use rtstream::as_manager as rtm;
// `vulkan_properties` loads this file a second time through the harness: two private,
// identical copies, one for each helper module.
#[allow(clippy::duplicate_mod)]
#[path = "../../as-manager/tests/harness/scene.rs"]
mod scene;
#[allow(unused_imports)]
pub use scene::{one_lod, one_lod_mesh, place, update_from};

/// A deterministic run of the frame driver over `frames` frames of `preset`, its world baked
/// into `<dir>/world`, that writes no files (no output directory, no maps); each test sets
/// what else it runs with.
pub fn driver_run(
    preset: rtstream::streaming::WorldPreset,
    dir: &std::path::Path,
    frames: u64,
) -> rtstream::driver::RunConfig {
    rtstream::driver::RunConfig {
        preset,
        world_dir: dir.join("world"),
        frames,
        deterministic: true,
        out_dir: None,
        maps: 0,
        ..rtstream::driver::RunConfig::default()
    }
}

/// A manager of `config` on a Vulkan backend of `desc` on `ctx`.
pub fn manager(
    ctx: &Arc<VulkanContext>,
    desc: VulkanBackendDesc,
    config: rtstream::as_manager::Config,
) -> rtstream::as_manager::AsManager<VulkanBackend> {
    let backend = VulkanBackend::new(ctx.clone(), desc).expect("backend");
    rtstream::as_manager::AsManager::new(config, backend).expect("manager")
}

/// The configuration the Vulkan tests start from: residency radii `r1` and `r2`, a BLAS
/// requested on the first frame that wants it (`create_threshold` 1), and compaction whatever
/// it saves (lavapipe's saves nothing: compact anyway so that the path runs here).
pub fn lavapipe_config(r1: f32, r2: f32) -> rtstream::as_manager::Config {
    let mut c = rtstream::as_manager::Config::default();
    c.residency.r1 = r1;
    c.residency.r2 = r2;
    c.residency.create_threshold = 1;
    c.build.min_compaction_saving = 0.0;
    c
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
        use glam::Vec3;
        use rtstream::as_manager::synth::grid_geometry;
        use rtstream::as_manager::MeshKind;
        let m = manager(ctx, desc, config);
        for k in 0..24u32 {
            let grid = grid_geometry(12 + k % 5, 8.0);
            let mesh = one_lod_mesh(&m, format!("grid{k}"), MeshKind::Static, 6.0, grid);
            let p = Vec3::new(
                (k % per_row) as f32 * 15.0,
                0.0,
                (k / per_row) as f32 * 15.0 + 10.0,
            );
            place(&m, mesh, p, k);
        }
        let base = grid_geometry(16, 5.0);
        let cloth_mesh = one_lod_mesh(&m, "cloth", MeshKind::Skinned, 4.0, base.clone());
        let cloth = place(&m, cloth_mesh, Vec3::new(0.0, 2.0, 5.0), 100);
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

/// The shading table of `records` (indexed by custom index, `len` entries; the rest grey):
/// each record's BLAS's shading buffers on `backend`, which must hold every record's BLAS.
pub fn shading_table(
    backend: &VulkanBackend,
    records: &[rtstream::as_manager::record::TlasInstance],
    len: usize,
) -> Vec<rtstream::renderer::InstanceShading> {
    use rtstream::renderer::InstanceShading;
    let mut table = vec![InstanceShading::colour_only([0.7, 0.7, 0.7, 1.0]); len];
    for r in records {
        let (vertices, indices) = backend
            .shading_geometry(r.blas_address)
            .expect("every record's BLAS is live");
        table[r.custom_index() as usize] = InstanceShading {
            vertices,
            indices,
            base_color: [0.8, 0.6, 0.4, 1.0],
        };
    }
    table
}

/// A kept shading table (`rtstream::ShadingTable`) against a fresh `WorldBridge::shading` of
/// the same records: equal on every entry a record names, zero addresses on every other.
/// Returns the customIndexes the records name (sorted).
pub fn assert_table_matches_fresh(
    frame: u64,
    records: &[rtstream::as_manager::record::TlasInstance],
    table: &[rtstream::renderer::InstanceShading],
    fresh: &[rtstream::renderer::InstanceShading],
) -> Vec<u32> {
    assert_eq!(
        table.len(),
        fresh.len(),
        "frame {frame}: one entry per customIndex"
    );
    let mut named: Vec<u32> = records.iter().map(|r| r.custom_index()).collect();
    named.sort_unstable();
    named.dedup();
    for (ci, (k, f)) in table.iter().zip(fresh).enumerate() {
        if named.binary_search(&(ci as u32)).is_ok() {
            assert_eq!(k, f, "frame {frame}: customIndex {ci} is named by a record");
        } else {
            assert_eq!(
                (k.vertices, k.indices),
                (0, 0),
                "frame {frame}: customIndex {ci} has no record"
            );
        }
    }
    named
}

/// The entries an update listed (`ShadingUpdate::changed`) bring its previous version to
/// this one (what a renderer writes into a frame's instance buffer); entries past the
/// previous version's length are new.
pub fn assert_changes_bring(
    frame: u64,
    previous: &[rtstream::renderer::InstanceShading],
    table: &[rtstream::renderer::InstanceShading],
    changed: &[u32],
) {
    let mut shadow = previous.to_vec();
    shadow.truncate(table.len());
    for &ci in changed {
        if let Some(e) = shadow.get_mut(ci as usize) {
            *e = table[ci as usize];
        }
    }
    let held = shadow.len();
    shadow.extend_from_slice(&table[held..]);
    assert!(
        shadow == table,
        "frame {frame}: the changed entries miss a change"
    );
}

/// The streaming the small-world tests use: a 150 m load radius (200 m unload), loads applied
/// two frames after their request whatever the machine's load (deterministic), 64 MB of
/// meshes.
pub fn small_world_stream() -> rtstream::streaming::StreamConfig {
    rtstream::streaming::StreamConfig {
        load_radius: 150.0,
        unload_radius: 200.0,
        apply_after_frames: Some(2),
        mesh_budget_bytes: 64 << 20,
        ..rtstream::streaming::StreamConfig::default()
    }
}
