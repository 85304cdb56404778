//! The TLAS instance buffers on Vulkan (lavapipe, validation on) hold exactly the manager's
//! records every frame, although the backend writes only the records that changed since a
//! slot's last use (`TlasDelta`: the far field's landmarks lead the records and persist). Three
//! frames in flight, a walk that keeps landmarks joining, leaving and changing LOD, instances
//! added, moved and removed, and a failed frame.

mod common;

use glam::{Affine3A, Quat, Vec3};
use rtstream::as_manager::backend::vulkan::{VulkanBackend, VulkanBackendDesc};
use rtstream::as_manager::backend::{BackendError, FaultPoint};
use rtstream::as_manager::synth::grid_geometry;
use rtstream::as_manager::{
    AsManager, Config, FrameInput, InstanceDesc, InstanceId, LodDesc, LodGeometry, MeshDesc,
    MeshKind, Viewpoint,
};
use rtstream_stats::Rng;

#[test]
fn instance_buffers_hold_the_records_while_only_changes_are_written() {
    let ctx = common::context();
    let desc = VulkanBackendDesc {
        frames_in_flight: 3,
        ..VulkanBackendDesc::default()
    };
    let config = Config {
        freeze_cost_model: true,
        ..Config::default()
    };
    let mut m = common::manager(&ctx, desc, config);
    // Four meshes of 3 LODs with data, 4 to 40 m across.
    let meshes: Vec<_> = (0..4u32)
        .map(|i| {
            let size = 8.0 + 24.0 * i as f32;
            let lods = (0..3u32)
                .map(|l| LodDesc {
                    geometry: LodGeometry::Data(grid_geometry(8 >> l, size)),
                    geometric_error: [0.0, 0.02, 0.1][l as usize] * size,
                })
                .collect();
            m.register_mesh(MeshDesc::new(
                format!("tile{i}"),
                MeshKind::Static,
                size * 0.75,
                lods,
            ))
            .unwrap()
        })
        .collect();
    let mut rng = Rng::new(0x7d17a);
    let place = |m: &AsManager<VulkanBackend>, rng: &mut Rng, k: u32| -> InstanceId {
        let t = Affine3A::from_scale_rotation_translation(
            Vec3::splat(rng.range(0.5, 1.5)),
            Quat::IDENTITY,
            Vec3::new(rng.range(-1500.0, 1500.0), 0.0, rng.range(-1500.0, 1500.0)),
        );
        let mut d = InstanceDesc::new(meshes[rng.below(meshes.len())], t);
        d.custom_index = k;
        m.add_instance(d).unwrap()
    };
    let mut live: Vec<InstanceId> = (0..600).map(|k| place(&m, &mut rng, k)).collect();
    let (mut frames_compared, mut max_landmarks) = (0, 0);
    for frame in 0..160u64 {
        if frame % 20 == 10 {
            // Churn: adds, moves and removes.
            for k in 0..5 {
                live.push(place(&m, &mut rng, 10_000 + frame as u32 * 10 + k));
                let i = rng.below(live.len());
                let t = Affine3A::from_translation(Vec3::new(
                    rng.range(-1500.0, 1500.0),
                    0.0,
                    rng.range(-1500.0, 1500.0),
                ));
                m.set_transform(live[i], t).unwrap();
                let j = rng.below(live.len());
                m.remove_instance(live.swap_remove(j)).unwrap();
            }
        }
        if frame == 90 {
            m.backend_mut()
                .inject_fault(FaultPoint::EndFrame, BackendError::Other("test".into()));
        }
        // A walk at 12 m a frame, turning.
        let t = frame as f32 * 0.01;
        let cam = Vec3::new(1200.0 * t.sin(), 2.0, 1200.0 * (t * 0.7).cos() - 600.0);
        let cams = [Viewpoint::new(cam, Vec3::X)];
        let out = match m.update(FrameInput {
            frame,
            cameras: &cams,
        }) {
            Ok(out) => out,
            Err(e) => {
                assert_eq!(frame, 90, "only the injected fault fails a frame: {e}");
                continue;
            }
        };
        let (tlas, want) = (
            out.tlas,
            bytemuck::cast_slice::<_, u8>(out.instances).to_vec(),
        );
        max_landmarks = max_landmarks.max(out.stats.landmark_instances);
        let got = m
            .backend()
            .tlas_instance_bytes(tlas)
            .expect("the frame's TLAS resolves");
        assert_eq!(got.len(), want.len(), "frame {frame}: record count");
        assert!(got == want, "frame {frame}: the instance buffer differs");
        frames_compared += 1;
    }
    let c = m.backend().counters();
    assert!(
        frames_compared >= 150 && max_landmarks >= 100,
        "{frames_compared} {max_landmarks}"
    );
    // The landmarks stayed: far fewer records were written than built from.
    assert!(
        c.tlas_records_written * 2 < c.tlas_records_built,
        "{} written of {}",
        c.tlas_records_written,
        c.tlas_records_built
    );
    m.backend_mut().wait_idle().unwrap();
}
