//! `set_lod_geometry`: LODs that stream in and out, against a model backend that, like a GPU,
//! needs data to build (`require_geometry`).

use glam::{Affine3A, Vec3};

use super::tests::run_frame;
use crate::backend::model::ModelBackend;
use crate::backend::AsBackend;
use crate::synth::{counts_chain, grid_geometry};
use crate::*;

fn gpu_like() -> AsManager<ModelBackend> {
    let mut b = ModelBackend::lavapipe();
    b.require_geometry = true;
    AsManager::new(Config::default(), b).unwrap()
}

fn data(n: u32) -> LodGeometry {
    LodGeometry::Data(grid_geometry(n, 1.0))
}

/// The 512-triangle mesh of three LODs (counts only) every scenario registers as "m".
fn chain_mesh(m: &AsManager<ModelBackend>) -> MeshId {
    m.register_mesh(MeshDesc::new(
        "m",
        MeshKind::Static,
        1.0,
        counts_chain(512, 3, 0.01),
    ))
    .unwrap()
}

/// Places `mesh` `z` metres ahead of the camera.
fn place_ahead(m: &AsManager<ModelBackend>, mesh: MeshId, z: f32) -> InstanceId {
    m.add_instance(InstanceDesc::new(
        mesh,
        Affine3A::from_translation(Vec3::new(0.0, 0.0, z)),
    ))
    .unwrap()
}

/// The scene most scenarios start from: the [`chain_mesh`] with the LODs of `resident` (LOD,
/// grid cells per side) loaded, placed `z` metres ahead of the camera.
fn chain_ahead(
    m: &AsManager<ModelBackend>,
    resident: &[(usize, u32)],
    z: f32,
) -> (MeshId, InstanceId) {
    let mesh = chain_mesh(m);
    for &(lod, n) in resident {
        m.set_lod_geometry(mesh, lod, data(n)).unwrap();
    }
    (mesh, place_ahead(m, mesh, z))
}

/// A LOD's geometry evicted: its vertex and triangle counts only.
fn counts(vertices: u32, triangles: u32) -> LodGeometry {
    LodGeometry::Counts {
        vertices,
        triangles,
    }
}

const CAM: [Viewpoint; 1] = [Viewpoint {
    position: Vec3::ZERO,
    forward: Vec3::Z,
}];

/// Runs frames `from..to`; returns the last frame's TLAS size.
fn run(m: &mut AsManager<ModelBackend>, from: u64, to: u64) -> usize {
    let mut n = 0;
    for frame in from..to {
        let recs = m
            .update(FrameInput {
                frame,
                cameras: &CAM,
            })
            .expect("no MissingGeometry")
            .instances
            .to_vec();
        for r in &recs {
            assert!(m.backend().is_live_address(r.blas_address));
        }
        n = m.stats().tlas_instances as usize;
    }
    n
}

#[test]
fn builds_only_lods_with_data_and_refines_when_finer_data_arrives() {
    let mut m = gpu_like();
    // Near: the selector wants LOD 0, but only the coarsest (2) is resident.
    let (mesh, inst) = chain_ahead(&m, &[(2, 8)], 4.0);
    assert_eq!(run(&mut m, 0, 4), 1, "shown at the resident LOD");
    assert_eq!(m.instance_lod(inst), Some(2));

    m.set_lod_geometry(mesh, 0, data(16)).unwrap();
    assert_eq!(run(&mut m, 4, 8), 1);
    assert_eq!(m.instance_lod(inst), Some(0), "finer data arrived: refined");

    // LOD 0's data evicted: its BLAS is built and needs no CPU data, so it keeps serving (it
    // would otherwise fall back to the coarse LOD 2 right next to the camera); nothing is
    // built from counts and nothing flickers.
    m.set_lod_geometry(mesh, 0, counts(289, 512)).unwrap();
    let builds_before = m.backend().counters().builds;
    for f in 8..60 {
        assert_eq!(run(&mut m, f, f + 1), 1, "the instance stays visible");
    }
    assert_eq!(
        m.instance_lod(inst),
        Some(0),
        "the built LOD-0 BLAS keeps serving"
    );
    assert_eq!(
        m.backend().counters().builds,
        builds_before,
        "nothing rebuilt"
    );
}

#[test]
fn evicted_lod_is_not_rebuilt_and_falls_back_to_nearest_with_data() {
    let mut m = gpu_like();
    let (mesh, inst) = chain_ahead(&m, &[(1, 12)], 4.0);
    assert_eq!(run(&mut m, 0, 4), 1);
    assert_eq!(
        m.instance_lod(inst),
        Some(1),
        "finer missing: nearest coarser with data"
    );
    // Fly away until released, evict LOD 1, make LOD 0 resident, come back.
    let far = [Viewpoint::new(Vec3::new(10_000.0, 0.0, 0.0), Vec3::Z)];
    for frame in 4..80 {
        run_frame(&mut m, frame, &far);
    }
    assert_eq!(m.stats().blas_count, 0, "released");
    m.set_lod_geometry(mesh, 1, counts(131, 256)).unwrap();
    m.set_lod_geometry(mesh, 0, data(16)).unwrap();
    assert_eq!(run(&mut m, 80, 84), 1);
    assert_eq!(m.instance_lod(inst), Some(0));
}

#[test]
fn no_lod_with_data_means_no_blas_and_no_error() {
    let mut m = gpu_like();
    chain_ahead(&m, &[], 4.0);
    assert_eq!(run(&mut m, 0, 5), 0);
    assert_eq!(m.stats().blas_count, 0);
}

#[test]
fn model_backend_without_data_requirement_uses_counts() {
    let mut m = AsManager::new(Config::default(), ModelBackend::lavapipe()).unwrap();
    assert!(!m.backend().needs_geometry());
    let (_, inst) = chain_ahead(&m, &[], 4.0);
    assert_eq!(run(&mut m, 0, 4), 1);
    assert_eq!(m.instance_lod(inst), Some(0));
}

#[test]
fn set_lod_geometry_validates() {
    let m = gpu_like();
    let mesh = chain_mesh(&m);
    assert!(
        m.set_lod_geometry(mesh, 3, data(4)).is_err(),
        "LOD out of range"
    );
    let bad = GeometryData {
        positions: vec![[0.0; 3]; 3],
        indices: vec![0, 1, 7],
    };
    assert!(
        m.set_lod_geometry(mesh, 0, LodGeometry::Data(std::sync::Arc::new(bad)))
            .is_err(),
        "index out of range"
    );
    assert!(m.set_lod_geometry(mesh, 0, counts(0, 0)).is_err());
    m.unregister_mesh(mesh).unwrap();
    assert!(matches!(
        m.set_lod_geometry(mesh, 0, data(4)),
        Err(AsError::UnknownMesh(_))
    ));
}

fn baseline(policy: PolicyKind) -> AsManager<ModelBackend> {
    let mut b = ModelBackend::lavapipe();
    b.require_geometry = true;
    let cfg = Config {
        policy,
        ..Config::default()
    };
    AsManager::new(cfg, b).unwrap()
}

#[test]
fn naive_builds_exactly_the_loaded_lods_and_shows_the_finest() {
    let mut m = baseline(PolicyKind::Naive);
    // Far away: Naive has no culling and no residency radius.
    let (mesh, _) = chain_ahead(&m, &[(2, 8)], 5000.0);
    assert_eq!(run(&mut m, 0, 3), 1, "shown at the only loaded LOD");
    assert_eq!(
        m.stats().blas_count,
        1,
        "LODs 0 and 1 were never loaded: no BLAS"
    );
    let bytes_coarse = m.stats().blas_bytes;
    // LOD 0 arrives: a second BLAS, and the instance is traced at LOD 0.
    m.set_lod_geometry(mesh, 0, data(16)).unwrap();
    assert_eq!(run(&mut m, 3, 6), 1);
    assert_eq!(m.stats().blas_count, 2);
    assert!(m.stats().blas_bytes > bytes_coarse);
    let rec = run_frame(&mut m, 6, &CAM).instances[0];
    let lod0_addr = rec.blas_address;
    // LOD 0 evicted: its BLAS is released, the instance falls back to LOD 2.
    m.set_lod_geometry(mesh, 0, counts(289, 512)).unwrap();
    assert_eq!(run(&mut m, 7, 10), 1);
    assert_eq!(m.stats().blas_count, 1);
    let rec = run_frame(&mut m, 10, &CAM).instances[0];
    assert_ne!(rec.blas_address, lod0_addr);
    m.check_invariants().unwrap();
}

#[test]
fn seed_builds_the_finest_loaded_lod_and_keeps_it() {
    let mut m = baseline(PolicyKind::SeedR1R2);
    let (mesh, _) = chain_ahead(&m, &[(1, 12), (2, 8)], 5.0);
    assert_eq!(run(&mut m, 0, 6), 1);
    assert_eq!(
        m.stats().blas_count,
        1,
        "one BLAS: LOD 1, the finest loaded"
    );
    let bytes = m.stats().blas_bytes;
    // LOD 1's data leaves: the built BLAS stays (the seed loop never revisits LODs).
    m.set_lod_geometry(mesh, 1, counts(100, 144)).unwrap();
    assert_eq!(run(&mut m, 6, 12), 1);
    assert_eq!((m.stats().blas_count, m.stats().blas_bytes), (1, bytes));
    m.check_invariants().unwrap();
}

/// Geometry in the engine's GPU buffers counts as loaded for a backend that needs data, builds
/// and refits from a device pose; bad addresses are typed errors.
#[test]
fn device_geometry_builds_and_device_poses_refit() {
    let mut m = gpu_like();
    let g = DeviceGeometry {
        vertices: DeviceVertices {
            address: 0x10_0000,
            stride: 8,
            format: VertexFormat::F16x4,
            count: 81,
        },
        indices: DeviceIndices {
            address: 0x20_0000,
            index_type: IndexType::U16,
        },
        triangle_count: 128,
    };
    let lod = |geometry| LodDesc {
        geometry,
        geometric_error: 0.0,
    };
    let mesh = m
        .register_mesh(MeshDesc::new(
            "cloth",
            MeshKind::Skinned,
            1.0,
            vec![lod(LodGeometry::Device(g))],
        ))
        .unwrap();
    let id = place_ahead(&m, mesh, 5.0);
    assert_eq!(run(&mut m, 0, 3), 1, "built from device addresses");
    let pose = DeviceVertices {
        address: 0x30_0000,
        stride: 16,
        format: VertexFormat::F32x3,
        count: 81,
    };
    m.set_skinned_pose_device(id, pose).unwrap();
    let s = run_frame(&mut m, 3, &CAM).stats.clone();
    assert_eq!((s.refits, s.rebuilds), (1, 0));
    // Typed errors: a misaligned pose, a stride smaller than a position, a null index buffer.
    let odd = DeviceVertices {
        address: 0x30_0002,
        ..pose
    };
    assert!(matches!(
        m.set_skinned_pose_device(id, odd),
        Err(AsError::InvalidDevicePose(
            DeviceGeometryError::Misaligned { .. }
        ))
    ));
    let short = DeviceVertices { stride: 8, ..pose };
    assert!(matches!(
        m.set_skinned_pose_device(id, short),
        Err(AsError::InvalidDevicePose(
            DeviceGeometryError::StrideTooSmall { .. }
        ))
    ));
    let null = DeviceGeometry {
        indices: DeviceIndices {
            address: 0,
            ..g.indices
        },
        ..g
    };
    assert_eq!(
        null.validate(),
        Err(DeviceGeometryError::NullAddress("index"))
    );
    assert!(matches!(
        m.register_mesh(MeshDesc::new(
            "bad",
            MeshKind::Static,
            1.0,
            vec![lod(LodGeometry::Device(null))],
        )),
        Err(AsError::InvalidMesh { .. })
    ));
}
