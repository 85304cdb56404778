//! Failed frames on the real backend (lavapipe, validation on, frames in flight): a fault
//! injected at each point of a frame's GPU work makes `update` return a typed error; the
//! manager rolls the frame back, the same frame number is retried and succeeds, and nothing the
//! failed frame recorded is ever submitted or waited on. Device lost reaches the caller and
//! stays.

mod common;

use std::sync::Arc;

use glam::Vec3;
use rtstream::as_manager::backend::vulkan::{FaultPoint, VulkanBackendDesc, VulkanError};
use rtstream::as_manager::backend::BackendError;
use rtstream::as_manager::{AsError, FrameInput, Viewpoint};

type Scene = common::GridWalk;

fn scene(ctx: &Arc<rtstream::as_manager::backend::vulkan::VulkanContext>) -> Scene {
    let mut c = common::lavapipe_config(60.0, 80.0);
    // A few builds a frame, so that every frame of the walk has GPU work.
    c.build.max_primitives = 3_000;
    Scene::new(ctx, VulkanBackendDesc::default(), c, 6)
}

/// Frame `frame`: a new pose, a camera walking along the rows. Returns the frame's TLAS
/// records plus its builds (a frame's builds show from the next frame on).
fn update(s: &mut Scene, frame: u64) -> Result<usize, AsError> {
    s.pose(frame);
    let cams = [Viewpoint::new(
        Vec3::new(frame as f32 * 0.8, 3.0, 0.0),
        Vec3::new(0.0, 0.0, 1.0),
    )];
    s.m.update(FrameInput {
        frame,
        cameras: &cams,
    })
    .map(|o| o.instances.len() + o.stats.builds as usize)
}

#[test]
fn a_failed_frame_rolls_back_and_its_number_is_retried() {
    let ctx = common::context();
    let mut s = scene(&ctx);
    let points = [
        FaultPoint::BuildBlases,
        FaultPoint::RefitBlases,
        FaultPoint::CompactBlas,
        FaultPoint::BuildTlas,
        FaultPoint::EndFrame,
    ];
    let mut struck = Vec::new();
    let mut frame = 0u64;
    for &point in &points {
        s.m.backend_mut()
            .inject_fault(point, BackendError::Other(format!("injected at {point:?}")));
        // Run until the fault strikes (the frame reaches that point with work to do).
        loop {
            assert!(frame < 400, "{point:?} never struck");
            match update(&mut s, frame) {
                Ok(_) => {
                    s.m.check_invariants().unwrap();
                    frame += 1;
                }
                Err(e) => {
                    assert!(
                        matches!(&e, AsError::Backend(BackendError::Other(m)) if m.contains("injected")),
                        "{point:?}: {e}"
                    );
                    s.m.check_invariants()
                        .unwrap_or_else(|e| panic!("after a failed frame at {point:?}: {e}"));
                    // The same frame number again.
                    let n = update(&mut s, frame)
                        .unwrap_or_else(|e| panic!("retry of frame {frame} after {point:?}: {e}"));
                    assert!(n > 0);
                    struck.push((point, frame));
                    frame += 1;
                    break;
                }
            }
        }
    }
    assert_eq!(struck.len(), points.len(), "{struck:?}");
    // Frames in flight keep going; every BLAS the manager counts is live in the backend.
    for _ in 0..20 {
        update(&mut s, frame).unwrap();
        s.m.check_invariants().unwrap();
        frame += 1;
    }
    s.m.backend_mut().wait_idle().unwrap();
    let stats = s.m.stats().clone();
    assert_eq!(
        s.m.backend().live_blas_count(),
        stats.blas_count as usize,
        "no BLAS of a failed frame leaks"
    );
    let c = s.m.backend().counters();
    assert!(c.compactions > 0 && c.refits + c.rebuilds > 0, "{c:?}");
}

/// A frame that fails after recording compactions leaves each compacted BLAS's original
/// shading from its own vertices: the copy, never submitted, is freed, and the original,
/// restored, is traced and shaded on (and compacted again later). Every static grid's shading
/// positions are checked against its mesh in the frames after.
#[test]
fn a_failed_frame_with_compactions_leaves_the_originals_shading_intact() {
    use rtstream::as_manager::synth::grid_geometry;
    let ctx = common::context();
    let mut s = scene(&ctx);
    let mut frame = 0u64;
    // Fail frames at their end until one of them had recorded compactions.
    loop {
        assert!(frame < 200, "no failed frame compacted");
        let before = s.m.backend().counters().compactions;
        s.m.backend_mut()
            .inject_fault(FaultPoint::EndFrame, BackendError::Other("injected".into()));
        update(&mut s, frame).expect_err("the injected fault strikes at the frame's end");
        let compacted = s.m.backend().counters().compactions > before;
        update(&mut s, frame).unwrap_or_else(|e| panic!("retry of frame {frame}: {e}"));
        frame += 1;
        if compacted {
            break;
        }
    }
    let mut checked = 0usize;
    for f in frame..frame + 30 {
        s.pose(f);
        let cams = [Viewpoint::new(
            Vec3::new(f as f32 * 0.8, 3.0, 0.0),
            Vec3::new(0.0, 0.0, 1.0),
        )];
        let records =
            s.m.update(FrameInput {
                frame: f,
                cameras: &cams,
            })
            .unwrap()
            .instances
            .to_vec();
        let b = s.m.backend();
        // A BLAS compacted this frame is named by this frame's records and already freed
        // (retiring until the frame completes): only live ones are looked up.
        for r in records
            .iter()
            .filter(|r| r.custom_index() < 24 && b.is_live_blas_address(r.blas_address))
        {
            let k = r.custom_index();
            let want = grid_geometry(12 + k % 5, 8.0);
            let got = b
                .shading_positions(r.blas_address)
                .unwrap_or_else(|| panic!("frame {f}: grid {k}'s BLAS has no shading"));
            assert_eq!(
                got, want.positions,
                "frame {f}: grid {k} shades from another mesh's vertices"
            );
            checked += 1;
        }
    }
    assert!(checked > 100, "{checked} records checked");
}

#[test]
fn a_vulkan_error_reaches_the_caller_typed() {
    let ctx = common::context();
    let mut s = scene(&ctx);
    // The device layer fails the next BLAS creation (as a driver error would, not a fault the
    // backend stages): `update` returns the `VulkanError` itself, not its text.
    ctx.inject_failure("create_accel_in");
    let mut frame = 0u64;
    let e = loop {
        assert!(frame < 100, "no BLAS was created");
        match update(&mut s, frame) {
            Ok(_) => frame += 1,
            Err(e) => break e,
        }
    };
    match &e {
        AsError::Backend(BackendError::Vulkan(f)) => assert!(
            matches!(f.error(), VulkanError::Injected { at } if *at == "create_accel_in"),
            "{e}"
        ),
        other => panic!("expected the typed Vulkan error, got {other:?}"),
    }
    assert_eq!(
        e.to_string(),
        vulkan_text(&e),
        "the text is the Vulkan error's own"
    );
    // The frame rolled back; its number runs again.
    s.m.check_invariants().unwrap();
    update(&mut s, frame).unwrap();
    for f in frame + 1..frame + 10 {
        update(&mut s, f).unwrap();
    }
    s.m.check_invariants().unwrap();
}

/// The text of the Vulkan error inside `e`, as the backend layer prints it.
fn vulkan_text(e: &AsError) -> String {
    match e {
        AsError::Backend(BackendError::Vulkan(f)) => format!("backend: {}", f.error()),
        _ => String::new(),
    }
}

#[test]
fn device_lost_reaches_the_caller_and_stays() {
    let ctx = common::context();
    let mut s = scene(&ctx);
    for frame in 0..5 {
        update(&mut s, frame).unwrap();
    }
    s.m.backend_mut()
        .inject_fault(FaultPoint::CompactBlas, BackendError::DeviceLost);
    let mut lost_at = None;
    for frame in 5..100 {
        if let Err(e) = update(&mut s, frame) {
            assert_eq!(e, AsError::Backend(BackendError::DeviceLost));
            lost_at = Some(frame);
            break;
        }
    }
    let f = lost_at.expect("a compaction ran and lost the device");
    for frame in [f, f + 1] {
        assert_eq!(
            update(&mut s, frame).unwrap_err(),
            AsError::Backend(BackendError::DeviceLost),
            "every later frame reports the lost device"
        );
    }
}
