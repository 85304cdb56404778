//! The bridge's mesh lifecycle, from hand-made streaming events into a manager on the model
//! backend (geometry required, as on a GPU):
//! - a resident LOD is shared with the manager, not copied (one `Arc`, counted once);
//! - the triangle counts and errors guessed for LODs not yet seen (a world without a manifest)
//!   are replaced when the real LOD arrives;
//! - a mesh leaves the manager once no LOD of it is resident and no instance of it is placed,
//!   and comes back when a LOD arrives again;
//! - far landmarks come and go with their proxy, one manager instance per world instance.

mod common;

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

/// `LevelLoaded` (`load`) or `LevelUnloaded` of `instances`.
fn level_event(level: LevelId, bounds: Aabb, instances: Arc<[Instance]>, load: bool) -> WorldEvent {
    if load {
        WorldEvent::LevelLoaded {
            level,
            bounds,
            instances,
        }
    } else {
        WorldEvent::LevelUnloaded { level, instances }
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

/// A manager on a model backend that requires every BLAS's geometry, and a bridge without a
/// manifest.
fn manager_and_bridge() -> (AsManager<ModelBackend>, WorldBridge) {
    let mut backend = ModelBackend::lavapipe();
    backend.require_geometry = true;
    let m = AsManager::new(Config::default(), backend).unwrap();
    (m, WorldBridge::new(None))
}

#[test]
fn lods_are_shared_guesses_are_replaced_and_unused_meshes_leave() {
    let (mut m, mut bridge) = manager_and_bridge();
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

/// Far landmarks: a leaf's landmark list places its large instances while their level is not
/// loaded (once their mesh is registered); the level's own copy of the instance (same id) is
/// the same manager instance; after the level unloads the instance stays while its proxy is
/// resident, and leaves with the proxy.
#[test]
fn far_landmarks_are_placed_from_their_proxy_until_the_proxy_leaves() {
    use rtstream::streaming::{ProxyId, ProxyNode, ProxyTree};
    let (mut m, mut bridge) = manager_and_bridge();
    let g = grid(8);
    let bounds = Aabb::from_points(&g.positions);
    let tree = ProxyTree {
        nodes: vec![ProxyNode {
            id: ProxyId(0),
            depth: 1,
            cell: [0, 0],
            bounds: Aabb {
                min: Vec3::new(-100.0, 0.0, -100.0),
                max: Vec3::new(100.0, 10.0, 100.0),
            },
            error: 1.0,
            parent: None,
            children: Vec::new(),
            levels: vec![LevelId(0)],
            triangles: g.triangle_count() as u32,
            landmarks: Vec::new(),
        }],
        leaf_of_level: vec![Some(ProxyId(0))],
    };
    bridge.register_proxy_tree(&m, &tree);
    let tower = Instance::new(
        WorldInstanceId(7),
        WorldMeshId(0),
        Mat4::from_translation(Vec3::new(0.0, 0.0, 60.0)),
        &bounds,
        MaterialClass::Opaque,
        Motion::Static,
    );
    let level_instances: Arc<[Instance]> = Arc::from(vec![tower]);

    // The proxy arrives before any LOD of the tower's mesh: the landmark waits.
    bridge.apply(
        &m,
        &[WorldEvent::ProxyLoaded {
            node: ProxyId(0),
            geometry: grid(2),
            landmarks: Arc::from(vec![(LevelId(0), tower)]),
        }],
    );
    frame(&mut m, 0);
    assert_eq!(m.stats().instances, 0, "no mesh yet: nothing placed");
    assert_eq!(bridge.stats().rejected, 0, "waiting is not a rejection");

    // Its mesh registers: the landmark is placed, from the proxy.
    bridge.apply(&m, &[loaded(0, 0.0, &g)]);
    frame(&mut m, 1);
    assert_eq!(m.stats().instances, 1);
    assert_eq!(bridge.stats().far_landmarks, 1);
    let id = bridge.manager_instance(WorldInstanceId(7)).expect("placed");

    // Its level loads: the same instance, not a second one.
    let level = |loaded: bool| {
        if loaded {
            WorldEvent::LevelLoaded {
                level: LevelId(0),
                bounds,
                instances: level_instances.clone(),
            }
        } else {
            WorldEvent::LevelUnloaded {
                level: LevelId(0),
                instances: level_instances.clone(),
            }
        }
    };
    bridge.apply(&m, &[level(true)]);
    frame(&mut m, 2);
    assert_eq!(
        m.stats().instances,
        1,
        "one manager instance per world instance"
    );
    assert_eq!(bridge.manager_instance(WorldInstanceId(7)), Some(id));
    assert_eq!(bridge.stats().far_landmarks, 0, "its level holds it now");

    // The level unloads: the proxy still lists it, so it stays.
    bridge.apply(&m, &[level(false)]);
    frame(&mut m, 3);
    assert_eq!(bridge.manager_instance(WorldInstanceId(7)), Some(id));
    assert_eq!(bridge.stats().far_landmarks, 1);

    // The proxy leaves: so does the landmark.
    bridge.apply(&m, &[WorldEvent::ProxyEvicted { node: ProxyId(0) }]);
    frame(&mut m, 4);
    assert_eq!(m.stats().instances, 0);
    assert_eq!(bridge.manager_instance(WorldInstanceId(7)), None);
    assert_eq!(bridge.stats().rejected, 0);
    m.check_invariants().unwrap();
}

/// The shading table a frame loop keeps ([`rtstream::ShadingTable`]) equals a fresh
/// [`WorldBridge::shading`] on every entry the frame's records name, and holds zero addresses
/// everywhere else, frame after frame while the records change: a camera sweeps a row of
/// instances, so instances enter and leave the TLAS, and a level unloads and another loads
/// (its instances reuse the freed customIndexes). Each update lists the entries it changed,
/// and applying them to the previous version gives the new one.
#[test]
fn a_kept_shading_table_matches_a_fresh_one_on_each_frames_records() {
    let (mut m, mut bridge) = manager_and_bridge();
    let g = grid(4);
    let bounds = Aabb::from_points(&g.positions);
    bridge.apply(&m, &[loaded(0, 0.0, &g)]);
    let row = |first: u32, x0: f32| -> Arc<[Instance]> {
        (0..40)
            .map(|i| {
                Instance::new(
                    WorldInstanceId(first + i),
                    WorldMeshId(0),
                    Mat4::from_translation(Vec3::new(x0 + i as f32 * 40.0, 0.0, 0.0)),
                    &bounds,
                    MaterialClass::Opaque,
                    Motion::Static,
                )
            })
            .collect()
    };
    let (a, b) = (row(0, 0.0), row(100, 0.0));
    let level = |id: u32, instances: &Arc<[Instance]>, load: bool| {
        if load {
            WorldEvent::LevelLoaded {
                level: LevelId(id),
                bounds,
                instances: instances.clone(),
            }
        } else {
            WorldEvent::LevelUnloaded {
                level: LevelId(id),
                instances: instances.clone(),
            }
        }
    };
    bridge.apply(&m, &[level(0, &a, true)]);
    // Geometry answers that differ per BLAS, as the backend's do.
    let geometry = |addr: u64| (addr % 3 != 0).then_some((addr, addr ^ 0xff));
    let mut kept = rtstream::ShadingTable::default();
    let (mut named_max, mut changes) = (0usize, 0usize);
    let mut last_named: Vec<u32> = Vec::new();
    let (mut previous, mut listed, mut named_total) = (Vec::new(), 0usize, 0usize);
    for f in 0..60u64 {
        if f == 30 {
            bridge.apply(&m, &[level(0, &a, false), level(1, &b, true)]);
        }
        let x = (f % 30) as f32 * 50.0;
        let cams = [Viewpoint::new(Vec3::new(x, 2.0, 0.0), Vec3::X)];
        let out = m
            .update(FrameInput {
                frame: f,
                cameras: &cams,
            })
            .unwrap();
        let records = out.instances.to_vec();
        let fresh = bridge.shading(&records, geometry);
        let up = kept.update(&bridge, &records, geometry);
        let table = up.table.to_vec();
        // The changes it lists bring the previous version to this one (what the renderer
        // writes into a frame's instance buffer), and they are fewer than the records.
        common::assert_changes_bring(f, &previous, &table, up.changed);
        assert_eq!(up.serial, f + 1, "one version per update");
        listed += up.changed.len();
        previous = table.clone();
        let named = common::assert_table_matches_fresh(f, &records, &table, &fresh);
        named_max = named_max.max(named.len());
        named_total += named.len();
        changes += usize::from(named != last_named);
        last_named = named;
    }
    assert!(
        named_max >= 3,
        "the TLAS held several instances: {named_max}"
    );
    assert!(changes >= 5, "the records changed across frames: {changes}");
    assert!(
        listed * 2 < named_total,
        "an update lists what changed, not every record: {listed} of {named_total}"
    );
}

/// A kept shading table that skips the records standing where they stood still sees what
/// changed under them: a slot the bridge gave to another instance (another mesh, another
/// colour) while a record keeps its customIndex and BLAS address, a BLAS address whose
/// geometry answer changed, and records that left or moved.
#[test]
fn a_kept_shading_table_sees_reassigned_slots_and_changed_geometry_under_unmoved_records() {
    use rtstream::as_manager::record::TlasInstance;
    use std::cell::Cell;
    let (m, mut bridge) = manager_and_bridge();
    let g = grid(2);
    let bounds = Aabb::from_points(&g.positions);
    let mesh = |id: u32| WorldEvent::MeshLodLoaded {
        mesh: WorldMeshId(id),
        lod: 0,
        lod_count: 1,
        error: 0.0,
        geometry: Arc::clone(&g),
    };
    bridge.apply(&m, &[mesh(0), mesh(1)]);
    let level = |id: u32, mesh: u32, load: bool| {
        let instances: Arc<[Instance]> = (0..4)
            .map(|i| {
                Instance::new(
                    WorldInstanceId(id * 100 + i),
                    WorldMeshId(mesh),
                    Mat4::from_translation(Vec3::new(i as f32 * 10.0, 0.0, 0.0)),
                    &bounds,
                    MaterialClass::Opaque,
                    Motion::Static,
                )
            })
            .collect();
        level_event(LevelId(id), bounds, instances, load)
    };
    bridge.apply(&m, &[level(0, 0, true)]);
    let slots: Vec<u32> = bridge
        .placed_within(Vec3::ZERO, 1000.0)
        .iter()
        .map(|p| p.0)
        .collect();
    assert_eq!(slots.len(), 4, "four instances placed");
    let record = |ci: u32, addr: u64| TlasInstance {
        transform: [0.0; 12],
        custom_index_and_mask: ci | 0xff << 24,
        sbt_offset_and_flags: 0,
        blas_address: addr,
    };
    let answer = Cell::new(1u64);
    let geometry = |addr: u64| Some((addr * 10 + answer.get(), addr * 10 + 5));
    let mut kept = rtstream::ShadingTable::default();
    let mut check = |bridge: &WorldBridge, records: &[TlasInstance], what: &str| {
        let fresh = bridge.shading(records, geometry);
        let up = kept.update(bridge, records, geometry);
        assert_eq!(up.table.len(), fresh.len(), "{what}: one entry per slot");
        for r in records {
            let ci = (r.custom_index_and_mask & 0x00ff_ffff) as usize;
            assert_eq!(up.table[ci], fresh[ci], "{what}: customIndex {ci}");
        }
        for (ci, e) in up.table.iter().enumerate() {
            if !records
                .iter()
                .any(|r| (r.custom_index_and_mask & 0x00ff_ffff) as usize == ci)
            {
                assert_eq!(
                    (e.vertices, e.indices),
                    (0, 0),
                    "{what}: {ci} has no record"
                );
            }
        }
        up.changed.len()
    };
    let records: Vec<_> = slots.iter().map(|&s| record(s, 100 + s as u64)).collect();
    check(&bridge, &records, "first update");
    assert_eq!(
        check(&bridge, &records, "same records"),
        0,
        "nothing changed"
    );
    // The level goes and another, of another mesh, takes its slots; the records stay put.
    bridge.apply(&m, &[level(0, 0, false), level(1, 1, true)]);
    let reused: Vec<u32> = bridge
        .placed_within(Vec3::ZERO, 1000.0)
        .iter()
        .map(|p| p.0)
        .collect();
    assert_eq!(
        {
            let mut a = reused.clone();
            a.sort_unstable();
            a
        },
        {
            let mut b = slots.clone();
            b.sort_unstable();
            b
        },
        "the new level reuses the slots"
    );
    assert!(
        check(&bridge, &records, "slots reassigned") > 0,
        "the colours changed"
    );
    // One address answers with other geometry.
    answer.set(2);
    assert_eq!(
        check(&bridge, &records, "geometry changed"),
        records.len(),
        "every entry's geometry changed"
    );
    // Records leave and the rest move.
    let mut fewer = records[1..].to_vec();
    fewer.reverse();
    check(&bridge, &fewer, "records left and moved");
    check(&bridge, &[], "no records");
    check(&bridge, &records, "records back");
}

#[test]
fn an_empty_world_gets_the_same_one_entry_table_fresh_and_kept() {
    let (_m, bridge) = manager_and_bridge();
    let geometry = |_: u64| None;
    let fresh = bridge.shading(&[], geometry);
    let mut kept = rtstream::ShadingTable::default();
    let up = kept.update(&bridge, &[], geometry);
    assert_eq!(fresh.len(), 1, "a table is never empty");
    assert_eq!(up.table, &fresh[..], "both pad an empty world the same way");
}

/// Instance ids of a baked world (dense from 0) and of glTF levels (from 2^31), and one at the
/// end of the bridge's id table: each is placed once, found by id, removed with its level, and
/// its slot handed out again; a level loading twice places nothing twice.
#[test]
fn baked_and_dynamic_ids_place_and_leave_alike() {
    let (mut m, mut bridge) = manager_and_bridge();
    let g = grid(2);
    let bounds = Aabb::from_points(&g.positions);
    bridge.apply(
        &m,
        &[WorldEvent::MeshLodLoaded {
            mesh: WorldMeshId(0),
            lod: 0,
            lod_count: 1,
            error: 0.0,
            geometry: Arc::clone(&g),
        }],
    );
    bridge.reserve_instances(1000);
    let ids = [
        0,
        7,
        999,
        1000,
        5_000_000,
        (1 << 24) - 1,
        1 << 24,
        1 << 31,
        u32::MAX,
    ];
    let level = |lv: u32, load: bool| {
        let instances: Arc<[Instance]> = ids
            .iter()
            .enumerate()
            .filter(|(k, _)| k % 2 == lv as usize)
            .map(|(k, &id)| {
                Instance::new(
                    WorldInstanceId(id),
                    WorldMeshId(0),
                    Mat4::from_translation(Vec3::new(k as f32 * 10.0, 0.0, 0.0)),
                    &bounds,
                    MaterialClass::Opaque,
                    Motion::Static,
                )
            })
            .collect();
        level_event(LevelId(lv), bounds, instances, load)
    };
    bridge.apply(&m, &[level(0, true), level(1, true), level(0, true)]);
    frame(&mut m, 0);
    assert_eq!(
        m.stats().instances as usize,
        ids.len(),
        "one manager instance per id"
    );
    assert_eq!(bridge.stats().instances, ids.len());
    let placed: Vec<_> = ids
        .iter()
        .map(|&id| {
            bridge
                .manager_instance(WorldInstanceId(id))
                .expect("placed")
        })
        .collect();
    let mut distinct = placed.clone();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(distinct.len(), ids.len(), "distinct manager instances");
    let slots = bridge.placed_within(Vec3::ZERO, f32::INFINITY);
    assert_eq!(slots.len(), ids.len());
    assert!(slots.windows(2).all(|w| w[0].0 < w[1].0), "by slot");
    assert!(bridge.manager_instance(WorldInstanceId(1)).is_none());
    assert!(bridge
        .manager_instance(WorldInstanceId((1 << 31) + 1))
        .is_none());

    // Level 1 leaves: its ids are gone, level 0's stay, and its slots come back.
    bridge.apply(&m, &[level(1, false)]);
    frame(&mut m, 1);
    for (k, &id) in ids.iter().enumerate() {
        let found = bridge.manager_instance(WorldInstanceId(id));
        assert_eq!(found.is_some(), k % 2 == 0, "id {id}");
        if k % 2 == 0 {
            assert_eq!(found, Some(placed[k]), "id {id} kept its instance");
        }
    }
    assert_eq!(m.stats().instances as usize, ids.len().div_ceil(2));
    let before: Vec<u32> = slots.iter().map(|s| s.0).collect();
    bridge.apply(&m, &[level(1, true)]);
    frame(&mut m, 2);
    let after: Vec<u32> = bridge
        .placed_within(Vec3::ZERO, f32::INFINITY)
        .iter()
        .map(|s| s.0)
        .collect();
    assert_eq!(after, before, "the freed slots are handed out again");
    bridge.apply(&m, &[level(0, false), level(1, false)]);
    frame(&mut m, 3);
    assert_eq!(m.stats().instances, 0);
    assert_eq!(bridge.stats().instances, 0);
    assert!(ids
        .iter()
        .all(|&id| bridge.manager_instance(WorldInstanceId(id)).is_none()));
    m.check_invariants().unwrap();
}
