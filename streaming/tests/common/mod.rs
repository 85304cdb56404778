//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use rtstream_streaming::{
    bake, generate, GeneratedWorld, LevelId, ProxyId, StreamFocus, StreamingError, World,
    WorldEvent, WorldMeshId, WorldPreset, ASSIMP_GLTF2_DIR,
};

/// The assimp-testmodels glTF2 directory; fails the test with a clear message when missing.
pub fn assets() -> PathBuf {
    let dir = PathBuf::from(ASSIMP_GLTF2_DIR);
    assert!(
        dir.join("2CylinderEngine-glTF-Binary/2CylinderEngine.glb").is_file(),
        "missing test assets under {}: install Debian's assimp-testmodels (apt-get install assimp-testmodels)",
        dir.display()
    );
    dir
}

/// A fresh, empty scratch directory for this test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rtstream-test-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch dir");
    dir
}

/// Generates a small world (grid x grid levels of the default map's density) and bakes it.
pub fn baked_small(name: &str, grid: u32) -> (GeneratedWorld, PathBuf) {
    assets();
    let world = generate(&WorldPreset::small(grid, 7)).expect("generate");
    let dir = scratch(name);
    bake(&world, &dir).expect("bake");
    (world, dir)
}

/// What a `LoadFailed` event names (see [`WorldEvent::LoadFailed`]), and its error.
#[derive(Debug, Clone)]
pub struct Failure {
    pub level: Option<LevelId>,
    pub mesh: Option<(WorldMeshId, u8)>,
    pub proxy: Option<ProxyId>,
    pub error: Arc<StreamingError>,
}

/// The `LoadFailed` events among `events`, in order.
pub fn failures(events: &[WorldEvent]) -> impl Iterator<Item = Failure> + '_ {
    events.iter().filter_map(|e| match e {
        WorldEvent::LoadFailed {
            level,
            mesh,
            proxy,
            error,
        } => Some(Failure {
            level: *level,
            mesh: *mesh,
            proxy: *proxy,
            error: error.clone(),
        }),
        _ => None,
    })
}

pub const SETTLE: Duration = Duration::from_secs(30);

/// Frame `frame` of `w` seen from `focus`, run until the loaders are idle (at most [`SETTLE`]).
pub fn settle(w: &mut World, frame: u64, focus: &[StreamFocus]) -> Vec<WorldEvent> {
    w.update_until_idle(frame, focus, SETTLE)
        .expect("streaming settles")
}
