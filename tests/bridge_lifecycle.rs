//! The bridge's mesh lifecycle, from hand-made streaming events into a manager on the model
//! backend (geometry required, as on a GPU):
//! - a resident LOD is shared with the manager, not copied (one `Arc`, counted once);
//! - the triangle counts and errors guessed for LODs not yet seen (a world without a manifest)
//!   are replaced when the real LOD arrives;
//! - a mesh leaves the manager once no LOD of it is resident and no instance of it is placed,
//!   and comes back when a LOD arrives again.

use std::sync::Arc;

use glam::{Mat4, Vec3};
use rtstream::as_manager::backend::model::ModelBackend;
use rtstream::as_manager::{AsManager, Config, FrameInput, Viewpoint};
use rtstream::streaming::{
    Aabb, Instance, LevelId, MaterialClass, MeshLod, Motion, WorldEvent, WorldInstanceId,
    WorldMeshId,
};
use rtstream::WorldBridge;

/// An `n` x `n` quad grid of side 4 m.
fn grid(n: u32) -> Arc<MeshLod> {
    let mut positions = Vec::new();
    for z in 0..=n {
        for x in 0..=n {
            positions.push([x as f32 * 4.0 / n as f32, 0.0, z as f32 * 4.0 / n as f32]);
        }
    }
    let mut indices = Vec::new();
    let w = n + 1;
    for z in 0..n {
        for x in 0..n {
            let i = z * w + x;
            indices.extend_from_slice(&[i, i + w, i + 1, i + 1, i + w, i + w + 1]);
        }
    }
    Arc::new(MeshLod {
        positions,
        indices,
        error: 0.0,
        skin: None,
    })
}

fn loaded(lod: u8, error: f32, g: &Arc<MeshLod>) -> WorldEvent {
    WorldEvent::MeshLodLoaded {
        mesh: WorldMeshId(0),
        lod,
        lod_count: 3,
        error,
        geometry: Arc::clone(g),
    }
}

fn frame(m: &mut AsManager<ModelBackend>, f: u64) {
    let cams = [Viewpoint::new(Vec3::ZERO, Vec3::Z)];
    m.update(FrameInput {
        frame: f,
        cameras: &cams,
    })
    .unwrap();
}

#[test]
fn lods_are_shared_guesses_are_replaced_and_unused_meshes_leave() {
    let mut backend = ModelBackend::lavapipe();
    backend.require_geometry = true;
    let mut m = AsManager::new(Config::default(), backend).unwrap();
    let mut bridge = WorldBridge::new(None);
    let (g0, g2) = (grid(32), grid(4));

    // The coarsest LOD arrives first: LOD 0 and 1 are guessed from it.
    bridge.apply(&m, &[loaded(2, 0.5, &g2)]);
    frame(&mut m, 0);
    assert_eq!(m.stats().meshes, 1);
    assert_eq!(bridge.registered_meshes(), 1);
    let (g2_tris, g0_tris) = (g2.triangle_count() as u32, g0.triangle_count() as u32);
    let before = lods_of(&m, &bridge);
    assert_eq!(before[2], (g2_tris, 0.5));
    assert_ne!(before[0].0, g0_tris, "LOD 0 is a guess so far");

    // LOD 0 arrives: its real count and error replace the guess.
    bridge.apply(&m, &[loaded(0, 0.0, &g0)]);
    frame(&mut m, 1);
    let after = lods_of(&m, &bridge);
    assert_eq!(after[0], (g0_tris, 0.0));
    assert_eq!(after[2], (g2_tris, 0.5));
    assert!(after[1].1 <= after[2].1, "errors stay non-decreasing");

    // Shared, not copied: this test, the bridge's resident set and the manager hold the one
    // copy of LOD 0.
    assert_eq!(
        Arc::strong_count(&g0),
        3,
        "the manager shares the streamed LOD"
    );

    // An instance, then its level leaves and both LODs are evicted: the mesh leaves too.
    let inst = Instance::new(
        WorldInstanceId(0),
        WorldMeshId(0),
        Mat4::from_translation(Vec3::new(0.0, 0.0, 10.0)),
        &Aabb::from_points(&g0.positions),
        MaterialClass::Opaque,
        Motion::Static,
    );
    let instances: Arc<[Instance]> = Arc::from(vec![inst]);
    bridge.apply(
        &m,
        &[WorldEvent::LevelLoaded {
            level: LevelId(0),
            bounds: Aabb::from_points(&g0.positions),
            instances: instances.clone(),
        }],
    );
    for f in 2..6 {
        frame(&mut m, f);
    }
    assert_eq!(m.stats().instances, 1);
    assert!(m.stats().blas_count > 0);
    let evict = |lod| WorldEvent::MeshLodEvicted {
        mesh: WorldMeshId(0),
        lod,
    };
    bridge.apply(&m, &[evict(0), evict(2)]);
    frame(&mut m, 6);
    assert_eq!(m.stats().meshes, 1, "an instance is still placed");
    bridge.apply(
        &m,
        &[WorldEvent::LevelUnloaded {
            level: LevelId(0),
            instances,
        }],
    );
    frame(&mut m, 7);
    assert_eq!(
        m.stats().meshes,
        0,
        "nothing resident, nothing placed: unregistered"
    );
    assert_eq!(m.stats().instances, 0);
    assert_eq!(bridge.registered_meshes(), 0);
    assert_eq!(bridge.stats().meshes_released, 1);
    assert_eq!(Arc::strong_count(&g0), 1, "the manager let go of the data");

    // It comes back with its next LOD.
    bridge.apply(&m, &[loaded(1, 0.2, &grid(16))]);
    frame(&mut m, 8);
    assert_eq!(m.stats().meshes, 1);
    m.check_invariants().unwrap();
}

/// The manager's view of the mesh: (triangles, error) per LOD.
fn lods_of(m: &AsManager<ModelBackend>, bridge: &WorldBridge) -> Vec<(u32, f32)> {
    let id = bridge.manager_mesh(WorldMeshId(0)).expect("registered");
    m.mesh_lods(id).expect("applied")
}
