//! The TLAS instance buffers on Vulkan (lavapipe, validation on) hold exactly the manager's
//! records every frame, although the backend writes only the records that changed since a
//! slot's last use (`TlasDelta`: the far field's landmarks lead the records and persist), and
//! with updates on each record keeps its instance slot from frame to frame. Three
//! frames in flight, a walk that keeps landmarks joining, leaving and changing LOD, instances
//! added, moved and removed, and a failed frame.
//!
//! And the TLAS updated in place from the last frame's (`TlasUpdates`, opt-in) traces
//! what a TLAS built every frame traces, hit for hit, while records join, leave and move.

mod common;

use glam::{Affine3A, Quat, Vec3};
use rtstream::as_manager::backend::vulkan::{TlasUpdates, VulkanBackend, VulkanBackendDesc};
use rtstream::as_manager::backend::{AsBackend, BackendError, FaultPoint, NextTlas};
use rtstream::as_manager::record::TlasInstance;
use rtstream::as_manager::synth::grid_geometry;
use rtstream::as_manager::{
    AsManager, Config, FrameInput, InstanceDesc, InstanceId, LodDesc, LodGeometry, MeshDesc,
    MeshId, MeshKind, Viewpoint,
};
use rtstream::renderer::{Camera, RenderDesc, Renderer};
use rtstream_stats::Rng;
use std::collections::HashMap;

/// Where a record stands (its translation's bits).
fn place_key(r: &TlasInstance) -> [u32; 3] {
    [3, 7, 11].map(|i| r.transform[i].to_bits())
}

/// Four meshes of 3 LODs with data, 4 to 40 m across.
fn tiles(m: &AsManager<VulkanBackend>) -> Vec<MeshId> {
    (0..4u32)
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
        .collect()
}

#[test]
fn instance_buffers_hold_the_records_while_only_changes_are_written() {
    let ctx = common::context();
    let desc = VulkanBackendDesc {
        frames_in_flight: 3,
        tlas_updates: TlasUpdates::ON,
        ..VulkanBackendDesc::default()
    };
    let config = Config {
        freeze_cost_model: true,
        ..Config::default()
    };
    let mut m = common::manager(&ctx, desc, config);
    let meshes = tiles(&m);
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
    let mut last_records: Option<(u64, Vec<TlasInstance>)> = None;
    let mut unlisted = 0usize;
    let (mut stayed, mut kept, mut shifted, mut kept_shifted) = (0usize, 0usize, 0usize, 0usize);
    let mut before: HashMap<(u32, [u32; 3]), usize> = HashMap::new();
    let mut listed_before = before.clone();
    // What the backend said of each frame's TLAS before its builds (`next_tlas`, which the
    // manager's budget relies on), against what the frame made: (said, built, updated).
    let mut plans: HashMap<NextTlas, (u32, u32, u32)> = HashMap::new();
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
        let said = m.backend().next_tlas();
        let made = |m: &AsManager<VulkanBackend>| {
            let c = m.backend().counters();
            (c.tlas_builds, c.tlas_updates)
        };
        let (built_before, updated_before) = made(&m);
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
        // The output's record changes (`RecordChanges`) against the last successful frame's
        // records: every record below `stable` that `changed` does not list stands as it stood.
        let c = out.changes;
        assert_eq!(c.frame, frame);
        assert!(c.is_well_formed(), "frame {frame}: {c:?}");
        let expected_since = if frame == 91 {
            None
        } else {
            frame.checked_sub(1)
        };
        assert_eq!(
            c.since, expected_since,
            "frame {frame}: compared with the last success"
        );
        if let (Some(since), Some((f, prev))) = (c.since, &last_records) {
            assert_eq!(since, *f);
            for (i, r) in out.instances.iter().enumerate().take(c.stable) {
                if !c.may_differ(i) {
                    assert_eq!(
                        Some(r),
                        prev.get(i),
                        "frame {frame}: record {i} is unlisted"
                    );
                    unlisted += 1;
                }
            }
        }
        last_records = Some((frame, out.instances.to_vec()));
        max_landmarks = max_landmarks.max(out.stats.landmark_instances);
        let (built, updated) = made(&m);
        let tally = plans.entry(said).or_default();
        tally.0 += 1;
        tally.1 += (built - built_before) as u32;
        tally.2 += (updated - updated_before) as u32;
        let got = m
            .backend()
            .tlas_instance_bytes(tlas)
            .expect("the frame's TLAS resolves");
        // With updates on, records keep their instance slots (`TlasUpdates`): the buffer holds
        // the frame's records, each once, in any order, and parked slots (mask 0) between.
        let slots: Vec<TlasInstance> = bytemuck::pod_collect_to_vec(&got);
        let wanted: Vec<TlasInstance> = bytemuck::pod_collect_to_vec(&want);
        let mut live: Vec<&[u8]> = got
            .chunks(64)
            .zip(&slots)
            .filter(|(_, r)| r.mask() != 0)
            .map(|(b, _)| b)
            .collect();
        let mut listed: Vec<&[u8]> = want.chunks(64).collect();
        live.sort_unstable();
        listed.sort_unstable();
        assert!(
            live == listed,
            "frame {frame}: the instance buffer's records differ from the manager's"
        );
        let parking: Vec<u64> = slots
            .iter()
            .filter(|r| r.mask() == 0)
            .map(|r| r.blas_address)
            .collect();
        assert!(
            parking.windows(2).all(|w| w[0] == w[1]),
            "frame {frame}: parked slots on more than one BLAS"
        );
        // A record shown last frame too (same instance, same place) keeps its slot.
        let now: HashMap<(u32, [u32; 3]), usize> = slots
            .iter()
            .enumerate()
            .filter(|(_, r)| r.mask() != 0)
            .map(|(i, r)| ((r.custom_index(), place_key(r)), i))
            .collect();
        let listed_now: HashMap<(u32, [u32; 3]), usize> = wanted
            .iter()
            .enumerate()
            .map(|(i, r)| ((r.custom_index(), place_key(r)), i))
            .collect();
        for (k, i) in &listed_now {
            if let (Some(a), Some(b)) = (before.get(k), now.get(k)) {
                stayed += 1;
                kept += usize::from(a == b);
                // Its place in the manager's list changed, not its slot.
                if listed_before.get(k).is_some_and(|j| j != i) {
                    shifted += 1;
                    kept_shifted += usize::from(a == b);
                }
            }
        }
        before = now;
        listed_before = listed_now;
        frames_compared += 1;
        assert_eq!(
            bytemuck::cast_slice::<_, u8>(m.records()),
            &want[..],
            "records() are the frame's"
        );
        assert_eq!(m.record_changes().map(|c| c.frame), Some(frame));
    }
    assert!(
        unlisted > 10_000,
        "the changes leave most landmark records unlisted: {unlisted}"
    );
    // Slots are laid out anew only when too many are parked or the records outgrow them (a
    // failed frame keeps them: the next call matches every record by its place).
    assert!(
        stayed > 10_000 && kept * 100 >= stayed * 99,
        "{kept} of {stayed} records that stayed kept their slots"
    );
    assert!(
        shifted > 1_000 && kept_shifted * 100 >= shifted * 99,
        "{kept_shifted} of {shifted} records that moved in the list kept their slots"
    );
    let c = m.backend().counters();
    assert!(
        c.tlas_slots_joined * 10 < c.tlas_records_built,
        "{} records took another's slot, of {}",
        c.tlas_slots_joined,
        c.tlas_records_built
    );
    assert!(
        frames_compared >= 150 && max_landmarks >= 100,
        "{frames_compared} {max_landmarks}"
    );
    // A frame said to rebuild built; most of those said to update did (the others' records
    // outgrew the last build or joined too far from their slots, found only once placed).
    let rebuilds = plans.get(&NextTlas::Rebuild).copied().unwrap_or_default();
    let updates = plans.get(&NextTlas::Update).copied().unwrap_or_default();
    assert!(
        rebuilds.0 >= 5 && rebuilds.1 == rebuilds.0 && rebuilds.2 == 0,
        "frames said to rebuild: {rebuilds:?} (frames, builds, updates)"
    );
    assert!(
        updates.0 >= 100 && updates.2 * 10 >= updates.0 * 8,
        "frames said to update: {updates:?} (frames, builds, updates)"
    );
    assert!(!plans.contains_key(&NextTlas::BuildEveryFrame), "{plans:?}");
    // Most frames updated their TLAS from the last frame's.
    assert!(
        c.tlas_updates > c.tlas_builds && c.tlas_builds >= 2,
        "{} updates, {} builds",
        c.tlas_updates,
        c.tlas_builds
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

/// Two managers see the same world and walk: one updates its TLAS in place between builds,
/// the other builds it every frame. Every frame's trace agrees pixel for pixel (instance,
/// triangle, distance), and the shown records agree but for their BLAS addresses.
#[test]
fn tlas_updates_trace_what_builds_trace() {
    let ctx = common::context();
    let config = Config {
        freeze_cost_model: true,
        ..Config::default()
    };
    let manager = |tlas_updates| {
        let desc = VulkanBackendDesc {
            frames_in_flight: 2,
            tlas_updates,
            ..VulkanBackendDesc::default()
        };
        common::manager(&ctx, desc, config.clone())
    };
    // Long update runs (no early build in light frames), and every frame built.
    let updating = TlasUpdates {
        max_updates: 24,
        light_frame_triangles: 0,
        ..TlasUpdates::ON
    };
    let mut ms = [manager(updating), manager(TlasUpdates::OFF)];
    let meshes: Vec<Vec<MeshId>> = ms.iter().map(tiles).collect();
    let mut rng = Rng::new(0x0b5e55);
    let mut live: Vec<[InstanceId; 2]> = Vec::new();
    let place = |ms: &[AsManager<VulkanBackend>; 2], rng: &mut Rng, k: u32| {
        let t = Affine3A::from_scale_rotation_translation(
            Vec3::splat(rng.range(0.5, 1.5)),
            Quat::IDENTITY,
            Vec3::new(
                rng.range(-600.0, 600.0),
                rng.range(0.0, 30.0),
                rng.range(-600.0, 600.0),
            ),
        );
        let mesh = rng.below(4);
        [0, 1].map(|i| {
            let mut d = InstanceDesc::new(meshes[i][mesh], t);
            d.custom_index = k;
            ms[i].add_instance(d).unwrap()
        })
    };
    for k in 0..400 {
        live.push(place(&ms, &mut rng, k));
    }
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let (mut hits, mut differing, mut next_index) = (0usize, 0usize, 400u32);
    for frame in 0..72u64 {
        if frame % 6 == 3 {
            // Churn: adds, moves and removes, the same in both.
            for _ in 0..6 {
                live.push(place(&ms, &mut rng, next_index));
                next_index += 1;
                let i = rng.below(live.len());
                let t = Affine3A::from_translation(Vec3::new(
                    rng.range(-600.0, 600.0),
                    rng.range(0.0, 30.0),
                    rng.range(-600.0, 600.0),
                ));
                for (m, id) in ms.iter().zip(live[i]) {
                    m.set_transform(id, t).unwrap();
                }
                let j = rng.below(live.len());
                for (m, id) in ms.iter().zip(live.swap_remove(j)) {
                    m.remove_instance(id).unwrap();
                }
            }
        }
        // A walk at 9 m a frame, turning.
        let t = frame as f32 * 0.02;
        let eye = Vec3::new(500.0 * t.sin(), 2.0, 500.0 * (t * 0.7).cos() - 250.0);
        let cams = [Viewpoint::new(eye, Vec3::X)];
        let cam = Camera::look_at(
            eye + Vec3::new(0.0, 40.0, -60.0),
            eye + Vec3::new(0.0, 0.0, 60.0),
            70f32.to_radians(),
        );
        let mut seen = Vec::new();
        for m in &mut ms {
            let out = m
                .update(FrameInput {
                    frame,
                    cameras: &cams,
                })
                .unwrap();
            let (tlas, records) = (out.tlas, out.instances.to_vec());
            let shown: Vec<_> = records
                .iter()
                .map(|r| (r.custom_index(), r.transform))
                .collect();
            let backend = m.backend_mut();
            backend.wait_idle().unwrap();
            let table = common::shading_table(backend, &records, next_index as usize);
            let traced = backend.tlas(tlas).expect("this frame's TLAS");
            let image = renderer
                .render(traced, &table, &RenderDesc::new(48, 32, cam))
                .expect("trace");
            seen.push((shown, image.hits));
        }
        assert!(
            seen[0].0 == seen[1].0,
            "frame {frame}: the shown records differ"
        );
        // The two trees differ, and so do their instance transforms in the last bits: only
        // ties (a triangle edge, surfaces within float noise) may trace otherwise.
        let (a, b) = (&seen[0].1, &seen[1].1);
        for (p, (x, y)) in a.iter().zip(b).enumerate() {
            if (x.instance, x.primitive) == (y.instance, y.primitive) {
                continue;
            }
            differing += 1;
            assert!(
                x.is_hit() && y.is_hit() && (x.t() - y.t()).abs() <= 1e-3 * x.t().max(1.0),
                "frame {frame}, pixel {p}: the updated TLAS traces otherwise: {x:?} vs {y:?}"
            );
        }
        hits += a.iter().filter(|h| h.is_hit()).count();
    }
    let (u, b) = (ms[0].backend().counters(), ms[1].backend().counters());
    assert!(
        u.tlas_updates >= 50 && u.tlas_builds >= 3,
        "{} updates, {} builds",
        u.tlas_updates,
        u.tlas_builds
    );
    assert_eq!((b.tlas_updates, b.tlas_builds), (0, 72));
    assert!(
        hits > 72 * 200,
        "the traces should see geometry: {hits} hits"
    );
    assert!(differing * 1000 < hits, "{differing} ties of {hits} hits");
    for m in &mut ms {
        m.backend_mut().wait_idle().unwrap();
    }
}
