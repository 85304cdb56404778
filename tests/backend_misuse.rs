//! Adversarial tests of the Vulkan backend's direct API (`AsBackend` on `VulkanBackend`), as an
//! engine that drives it without the manager might call it. Each test passes when the backend
//! does the right thing (a correct result, or a clean `Err(BackendError::..)`) with the
//! validation layer silent, and fails on a defect (validation message, panic inside the
//! library, wrong trace, dangling shading data).

mod common;

use common::direct::*;

use glam::Vec3;
use rtstream::as_manager::backend::vulkan::VulkanBackend;
use rtstream::as_manager::backend::{
    AsBackend, BackendResult, BlasBuild, BlasClass, BlasHandle, BlasRefit, Misuse, TlasDelta,
    TlasHandle,
};
use rtstream::as_manager::record::TlasInstance;
use rtstream::as_manager::synth::grid_geometry;
use rtstream::renderer::{Camera, RenderDesc, Renderer};

/// Frames `from..from + n`, each building a TLAS of `records`; returns the next frame.
fn frames(b: &mut VulkanBackend, from: u64, n: u64, records: &[TlasInstance]) -> u64 {
    for f in from..from + n {
        b.begin_frame(f).unwrap();
        b.build_tlas(records, TlasDelta::ALL).unwrap();
        b.end_frame(f).unwrap();
    }
    from + n
}

/// Frames until `blas`'s compacted size is read; returns the next frame.
fn until_compactable(
    b: &mut VulkanBackend,
    mut frame: u64,
    blas: BlasHandle,
    records: &[TlasInstance],
) -> u64 {
    while b.compacted_size(blas).is_none() {
        assert!(frame < 16, "the compacted size is read within a few frames");
        frame = frames(b, frame, 1, records);
    }
    frame
}

/// (custom index, primitive) per pixel of a 24 x 16 view looking down at the origin from 15 m
/// (a grid of 20 m at y = 0 fills most of it), after every frame completed.
fn trace(
    b: &mut VulkanBackend,
    renderer: &mut Renderer,
    tlas: TlasHandle,
    records: &[TlasInstance],
) -> Vec<(u32, u32)> {
    b.wait_idle().expect("frames complete");
    let table = common::shading_table(b, records, 4);
    let traced = b.tlas(tlas).expect("TLAS of a frame in flight");
    let cam = Camera::look_at(Vec3::new(0.0, 15.0, -8.0), Vec3::ZERO, 60f32.to_radians());
    let f = renderer
        .render(traced, &table, &RenderDesc::new(24, 16, cam))
        .expect("trace without device error");
    f.hits.iter().map(|h| (h.instance, h.primitive)).collect()
}

// ---------------------------------------------------------------------------------------------
// 1. A refit in the frame of the BLAS's build.

/// A refit (`rebuild` false) or rebuild of a skinned BLAS in its build's frame moves it 1 km
/// away, out of view: `build_blases` is recorded lazily (with the TLAS), `refit_blases` at
/// once, and the refit must still run after the build (or be refused), so that the frame
/// traces the moved pose and shades from it.
fn refit_in_the_frame_of_its_build(rebuild: bool) {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(16, 20.0);
    let moved: Vec<[f32; 3]> = g
        .positions
        .iter()
        .map(|p| [p[0] + 1000.0, p[1], p[2]])
        .collect();
    b.begin_frame(0).unwrap();
    let h = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    let refit = b.refit_blases(&[BlasRefit {
        blas: h,
        geometry: geom(&moved, &g.indices),
        rebuild,
    }]);
    eprintln!("refit (rebuild {rebuild}) in the build's frame: {refit:?}");
    let records = [record(b.blas_address(h), 0)];
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let hits = trace(&mut b, &mut renderer, tlas, &records);
    let mut d = Defects::default();
    if refit.is_ok() {
        d.check(
            b.shading_positions(records[0].blas_address).as_deref() == Some(&moved[..]),
            "the shading reads the refit's pose",
        );
        let on = hits_of(&hits, 0);
        d.check(
            on == 0,
            format!("the frame's TLAS traces the build's pose, not the refit's: {on} of 384 pixels hit the grid where it no longer is"),
        );
    }
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

#[test]
fn a_refit_in_the_frame_of_its_build_waits_for_the_build() {
    refit_in_the_frame_of_its_build(false);
}

#[test]
fn a_rebuild_in_the_frame_of_its_build_is_what_the_tlas_traces() {
    refit_in_the_frame_of_its_build(true);
}

// ---------------------------------------------------------------------------------------------
// 2. Compactions.

/// Builds a static grid in frame 0 (named by its TLAS) and runs frames until it is
/// compactable. Returns (grid handle, its records, frame 0's hits, next frame).
fn compactable_grid(
    b: &mut VulkanBackend,
    renderer: &mut Renderer,
    g: &rtstream::as_manager::GeometryData,
) -> (BlasHandle, [TlasInstance; 1], Vec<(u32, u32)>, u64) {
    b.begin_frame(0).unwrap();
    let original = build_one(b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [record(b.blas_address(original), 0)];
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let before = trace(b, renderer, tlas, &records);
    assert!(hits_of(&before, 0) > 200, "the grid fills the view");
    let frame = until_compactable(b, 1, original, &records);
    (original, records, before, frame)
}

#[test]
fn compacting_one_blas_twice_in_a_frame_gives_two_shadable_copies() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(24, 20.0);
    let (original, _records, before, frame) = compactable_grid(&mut b, &mut renderer, &g);
    let mut d = Defects::default();
    b.begin_frame(frame).unwrap();
    let c1 = b.compact_blas(original).unwrap();
    let c2 = b.compact_blas(original);
    eprintln!("second compaction of one source in a frame: {c2:?}");
    assert!(refused(&c2, Misuse::AlreadyCompacted(original)), "{c2:?}");
    let Ok(c2) = c2 else {
        // Refused cleanly: fine.
        b.build_tlas(&[record(b.blas_address(c1), 0)], TlasDelta::ALL)
            .unwrap();
        b.end_frame(frame).unwrap();
        b.wait_idle().unwrap();
        drop(renderer);
        drop(b);
        return;
    };
    let (a1, a2) = (b.blas_address(c1), b.blas_address(c2));
    let named = [record(a2, 0)];
    let tlas = b.build_tlas(&named, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    b.free_blas(original, frame);
    d.check(
        b.shading_positions(a1).as_deref() == Some(&g.positions[..]),
        "first copy: shading_positions equals the mesh",
    );
    d.check(
        b.shading_positions(a2).as_deref() == Some(&g.positions[..]),
        format!(
            "second copy: shading_positions is {:?} instead of the mesh's {} positions",
            b.shading_positions(a2).map(|p| p.len()),
            g.positions.len()
        ),
    );
    d.check(
        trace(&mut b, &mut renderer, tlas, &named) == before,
        "second copy traces as the original",
    );
    // The first copy goes; the second must keep its shading data.
    b.free_blas(c1, frame);
    let shading_before = b.shading_geometry(a2);
    let next = frames(&mut b, frame + 1, 3, &named);
    b.wait_idle().unwrap();
    let shading_after = b.shading_geometry(a2);
    eprintln!("second copy's shading buffers: {shading_before:x?} then {shading_after:x?}; input bytes live: {}",
        shading_after.and_then(|(v, _)| b.input_buffer_bytes(v)).is_some());
    d.check(
        shading_after.is_none_or(|(v, _)| b.input_buffer_bytes(v).is_some()),
        "after the first copy was freed, the second copy's shading_geometry points at freed input memory",
    );
    b.begin_frame(next).unwrap();
    let tlas = b.build_tlas(&named, TlasDelta::ALL).unwrap();
    b.end_frame(next).unwrap();
    d.check(
        trace(&mut b, &mut renderer, tlas, &named) == before,
        "second copy still traces as the original",
    );
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

/// A compacted copy reports its compacted size at once, so it may be compacted in the frame
/// that records it (copy of a copy that has not run yet).
#[test]
fn a_compacted_copy_compacts_again_in_its_own_frame() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(24, 20.0);
    let (original, _records, before, frame) = compactable_grid(&mut b, &mut renderer, &g);
    let mut d = Defects::default();
    b.begin_frame(frame).unwrap();
    let c1 = b.compact_blas(original).unwrap();
    eprintln!(
        "compacted size of the copy in its own frame: {:?}",
        b.compacted_size(c1)
    );
    let c2 = b.compact_blas(c1);
    eprintln!("compaction of a copy in its own frame: {c2:?}");
    assert!(refused(&c2, Misuse::CompactionOfPending(c1)), "{c2:?}");
    let Ok(c2) = c2 else {
        b.build_tlas(&[record(b.blas_address(c1), 0)], TlasDelta::ALL)
            .unwrap();
        b.end_frame(frame).unwrap();
        b.wait_idle().unwrap();
        drop(renderer);
        drop(b);
        common::assert_no_validation_messages(&ctx);
        return;
    };
    let named = [record(b.blas_address(c2), 0)];
    let tlas = b.build_tlas(&named, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    b.free_blas(original, frame);
    b.free_blas(c1, frame);
    d.check(
        b.shading_positions(named[0].blas_address).as_deref() == Some(&g.positions[..]),
        "copy of the copy: shading_positions equals the mesh",
    );
    d.check(
        trace(&mut b, &mut renderer, tlas, &named) == before,
        "copy of the copy traces as the original",
    );
    frames(&mut b, frame + 1, 3, &named);
    b.wait_idle().unwrap();
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

/// Compacting a compacted copy in a later frame (the copy has run).
#[test]
fn a_compacted_copy_compacts_again_in_a_later_frame() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(24, 20.0);
    let (original, _records, before, frame) = compactable_grid(&mut b, &mut renderer, &g);
    let mut d = Defects::default();
    b.begin_frame(frame).unwrap();
    let c1 = b.compact_blas(original).unwrap();
    let named1 = [record(b.blas_address(c1), 0)];
    b.build_tlas(&named1, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    b.free_blas(original, frame);
    let frame = frames(&mut b, frame + 1, 3, &named1);
    b.begin_frame(frame).unwrap();
    let c2 = b.compact_blas(c1);
    eprintln!("compaction of a copy in a later frame: {c2:?}");
    let Ok(c2) = c2 else {
        b.build_tlas(&named1, TlasDelta::ALL).unwrap();
        b.end_frame(frame).unwrap();
        b.wait_idle().unwrap();
        drop(renderer);
        drop(b);
        common::assert_no_validation_messages(&ctx);
        return;
    };
    let named = [record(b.blas_address(c2), 0)];
    let tlas = b.build_tlas(&named, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    b.free_blas(c1, frame);
    d.check(
        b.shading_positions(named[0].blas_address).as_deref() == Some(&g.positions[..]),
        "copy of the copy: shading_positions equals the mesh",
    );
    d.check(
        trace(&mut b, &mut renderer, tlas, &named) == before,
        "copy of the copy traces as the original",
    );
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

/// Compacting the same original again in a later frame (the first copy took its inputs).
#[test]
fn compacting_an_original_again_in_a_later_frame_gives_a_shadable_copy() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(24, 20.0);
    let (original, records, before, frame) = compactable_grid(&mut b, &mut renderer, &g);
    let mut d = Defects::default();
    b.begin_frame(frame).unwrap();
    let c1 = b.compact_blas(original).unwrap();
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    let frame = frames(&mut b, frame + 1, 2, &records);
    b.begin_frame(frame).unwrap();
    let c2 = b.compact_blas(original);
    eprintln!("second compaction of an original, a later frame: {c2:?}");
    let Ok(c2) = c2 else {
        b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(frame).unwrap();
        b.wait_idle().unwrap();
        drop(renderer);
        drop(b);
        common::assert_no_validation_messages(&ctx);
        return;
    };
    let named = [record(b.blas_address(c2), 0)];
    let tlas = b.build_tlas(&named, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    d.check(
        b.shading_positions(named[0].blas_address).as_deref() == Some(&g.positions[..]),
        format!(
            "second copy: shading_positions is {:?} (len) instead of the mesh",
            b.shading_positions(named[0].blas_address).map(|p| p.len())
        ),
    );
    d.check(
        trace(&mut b, &mut renderer, tlas, &named) == before,
        "second copy traces as the original",
    );
    // The first copy (which owns the inputs) goes: the second must keep shading.
    b.free_blas(c1, frame);
    b.free_blas(original, frame);
    let frame = frames(&mut b, frame + 1, 3, &named);
    b.wait_idle().unwrap();
    let shading = b.shading_geometry(named[0].blas_address);
    d.check(
        shading.is_none_or(|(v, _)| b.input_buffer_bytes(v).is_some()),
        "after the first copy was freed, the second copy's shading_geometry points at freed input memory",
    );
    frames(&mut b, frame, 1, &named);
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

// ---------------------------------------------------------------------------------------------
// 3. A TLAS record naming a freed BLAS.

/// A record naming a BLAS freed (and destroyed) frames ago is refused in debug builds, typed,
/// before anything is recorded; the frame goes on with the records fixed. (Once a new BLAS has
/// taken the freed one's storage, its address names the new BLAS: no backend can tell.)
#[test]
#[cfg(debug_assertions)]
fn a_tlas_record_of_a_freed_blas_is_refused() {
    use rtstream::as_manager::backend::{BackendError, Misuse};
    let ctx = common::context();
    let mut b = backend(&ctx);
    let g = grid_geometry(8, 20.0);
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let keep = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let stale = b.blas_address(a);
    let both = [record(stale, 0), record(b.blas_address(keep), 1)];
    b.build_tlas(&both, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.free_blas(a, 0);
    let kept = [record(b.blas_address(keep), 1)];
    let frame = frames(&mut b, 1, 4, &kept);
    b.wait_idle().unwrap();
    assert!(!b.is_blas_address_usable(stale, frame), "destroyed by now");
    b.begin_frame(frame).unwrap();
    let r = b.build_tlas(&[kept[0], record(stale, 0)], TlasDelta::ALL);
    assert_eq!(
        r,
        Err(BackendError::Misuse(Misuse::UnknownBlasAddress {
            index: 1,
            address: stale
        }))
    );
    // Nothing was recorded: the same frame builds its TLAS from good records.
    b.build_tlas(&kept, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
}

// ---------------------------------------------------------------------------------------------
// 4. Frame-order misuse.

#[test]
fn a_second_tlas_in_a_frame_is_refused_or_keeps_the_first() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(8, 20.0);
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let first = [record(b.blas_address(a), 0)];
    let second = [record(b.blas_address(a), 1)];
    let t1 = b.build_tlas(&first, TlasDelta::ALL).unwrap();
    let t2 = b.build_tlas(&second, TlasDelta::ALL);
    eprintln!("second build_tlas in a frame: {t2:?} (first {t1:?})");
    assert!(refused(&t2, Misuse::TlasAlreadyBuilt), "{t2:?}");
    b.end_frame(0).unwrap();
    let mut d = Defects::default();
    if let Ok(t2) = t2 {
        let h1 = trace(&mut b, &mut renderer, t1, &first);
        let h2 = trace(&mut b, &mut renderer, t2, &second);
        d.check(
            t1 != t2,
            format!("both calls returned the same handle {t1:?}"),
        );
        d.check(
            hits_of(&h1, 0) > 100 && hits_of(&h1, 1) == 0,
            format!(
                "the first call's handle traces the second call's records: custom 0: {}, custom 1: {} pixels",
                hits_of(&h1, 0),
                hits_of(&h1, 1)
            ),
        );
        d.check(
            hits_of(&h2, 1) > 100,
            "the second handle traces its records",
        );
    }
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

#[test]
fn begin_frame_while_a_frame_is_recording_is_refused() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(16, 8.0);
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let again = b.begin_frame(0);
    eprintln!("begin_frame(0) twice: {again:?}");
    let mut d = Defects::default();
    d.check(
        refused(&again, Misuse::StillRecording { frame: 0 }),
        format!("begin_frame(0) while frame 0 records: {again:?}"),
    );
    // Either way, the frame goes on: a second build, a TLAS naming both.
    let c = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [
        record_at(b.blas_address(a), 0, -5.0),
        record_at(b.blas_address(c), 1, 5.0),
    ];
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let hits = trace(&mut b, &mut renderer, tlas, &records);
    d.check(
        hits_of(&hits, 0) > 20 && hits_of(&hits, 1) > 20,
        format!(
            "both BLASes traced: {} and {} pixels",
            hits_of(&hits, 0),
            hits_of(&hits, 1)
        ),
    );
    frames(&mut b, 1, 2, &records);
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

#[test]
fn end_frame_without_begin_frame_is_refused() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let before_any = b.end_frame(0);
    eprintln!("end_frame before any begin_frame: {before_any:?}");
    frames(&mut b, 0, 1, &[]);
    let twice = b.end_frame(0);
    eprintln!("end_frame(0) twice: {twice:?}");
    let tlas = b.build_tlas(&[], TlasDelta::ALL);
    eprintln!("build_tlas outside a frame: {tlas:?}");
    let g = grid_geometry(4, 4.0);
    let build = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static);
    eprintln!("build_blases outside a frame: {build:?}");
    frames(&mut b, 1, 2, &[]);
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    for r in [&before_any, &twice, &tlas.map(|_| ()), &build.map(|_| ())] {
        assert!(refused(r, Misuse::NotRecording), "{r:?}");
    }
}

#[test]
fn end_frame_with_another_frame_number_is_refused() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    b.begin_frame(0).unwrap();
    b.build_tlas(&[], TlasDelta::ALL).unwrap();
    let r = b.end_frame(1);
    eprintln!("begin_frame(0) .. end_frame(1): {r:?}");
    if r.is_err() {
        b.end_frame(0).unwrap();
    }
    frames(&mut b, 1, 3, &[]);
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    assert!(
        refused(
            &r,
            Misuse::WrongFrame {
                frame: 1,
                recording: 0
            }
        ),
        "end_frame(1) during frame 0: {r:?}"
    );
}

/// Frame `again` begun (after frames up to `last`) with a big build that its TLAS names and
/// that is freed at once (last used by this frame): the next `begin_frame` must not destroy it
/// while the frame runs. Returns begin_frame(again)'s result.
fn rerun_frame_number(again: u64, last: u64) -> BackendResult<()> {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let next = frames(&mut b, 0, last + 1, &[]);
    b.wait_idle().unwrap();
    let r = b.begin_frame(again);
    eprintln!("begin_frame({again}) after frame {last}: {r:?}");
    if r.is_ok() {
        let g = grid_geometry(8, 20.0);
        let x = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
        b.build_tlas(&[record(b.blas_address(x), 0)], TlasDelta::ALL)
            .unwrap();
        b.free_blas(x, again);
        let e = b.end_frame(again);
        eprintln!("end_frame({again}): {e:?}");
        let destroyed = b.counters().destroyed;
        // The next frame: the timeline already passed `again + 1`.
        b.begin_frame(next).unwrap();
        let now = b.counters().destroyed;
        eprintln!(
            "completed_frame after begin_frame({next}): {:?}; the frame's BLAS destroyed at once: {}",
            b.completed_frame(),
            now > destroyed
        );
        b.build_tlas(&[], TlasDelta::ALL).unwrap();
        b.end_frame(next).unwrap();
    }
    let _ = b.wait_idle();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    r
}

#[test]
fn a_frame_number_that_goes_backwards_is_refused() {
    let r = rerun_frame_number(1, 3);
    assert!(
        refused(&r, Misuse::FrameNotIncreasing { frame: 1, last: 3 }),
        "begin_frame(1) after frame 3: {r:?}"
    );
}

#[test]
fn a_repeated_frame_number_is_refused() {
    let r = rerun_frame_number(3, 3);
    assert!(
        refused(&r, Misuse::FrameNotIncreasing { frame: 3, last: 3 }),
        "begin_frame(3) after frame 3: {r:?}"
    );
}

// ---------------------------------------------------------------------------------------------
// 5. Bad geometry.

#[test]
fn an_index_past_the_vertices_is_refused() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let positions = [
        [0.0f32, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 1.0],
    ];
    let indices = [0u32, 1, 2, 1, 3, 1_000_000];
    b.begin_frame(0).unwrap();
    let r = build_one(&mut b, geom(&positions, &indices), BlasClass::Static);
    eprintln!("static build with index 1000000 of 4 vertices: {r:?}");
    let s = build_one(&mut b, geom(&positions, &indices), BlasClass::Skinned);
    eprintln!("skinned build with index 1000000 of 4 vertices: {s:?}");
    let records: Vec<_> = [&r, &s]
        .iter()
        .enumerate()
        .filter_map(|(i, h)| {
            h.as_ref()
                .ok()
                .map(|h| record(b.blas_address(*h), i as u32))
        })
        .collect();
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    for r in [&r, &s] {
        assert!(
            refused(r, Misuse::InvalidGeometry("an index past the vertices")),
            "a build with an index past the vertex count (the GPU reads past the positions): {r:?}"
        );
    }
}

#[test]
fn a_geometry_without_triangles_is_refused_or_built_empty() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let positions = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    let indices: [u32; 0] = [];
    b.begin_frame(0).unwrap();
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        build_one(&mut b, geom(&positions, &indices), BlasClass::Static)
    }));
    let msg = r.as_ref().err().map(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default()
    });
    eprintln!(
        "static build of 0 triangles: {:?}",
        r.as_ref().map_err(|_| &msg)
    );
    let s = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        build_one(&mut b, geom(&positions, &indices), BlasClass::Skinned)
    }));
    let smsg = s.as_ref().err().map(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default()
    });
    eprintln!(
        "skinned build of 0 triangles: {:?}",
        s.as_ref().map_err(|_| &smsg)
    );
    let mut records = Vec::new();
    for (i, h) in [&r, &s].into_iter().enumerate() {
        if let Ok(Ok(h)) = h {
            records.push(record(b.blas_address(*h), i as u32));
        }
    }
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    frames(&mut b, 1, 2, &records);
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    assert!(
        msg.is_none() && smsg.is_none(),
        "build_blases panicked: static {msg:?}, skinned {smsg:?}"
    );
    for r in [r, s] {
        let r = r.expect("no panic");
        assert!(
            refused(&r, Misuse::InvalidGeometry("no triangles or no vertices")),
            "{r:?}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// 6. Frees in the frame of a BLAS's own commands.

#[test]
fn a_blas_freed_in_its_build_frame_is_kept_until_the_frame_completes() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(16, 20.0);
    // Freed before the TLAS (so never named).
    b.begin_frame(0).unwrap();
    let a = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let s = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    b.free_blas(a, 0);
    b.free_blas(s, 0);
    b.build_tlas(&[], TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    // Named by its frame's TLAS, freed after it, before end_frame.
    b.begin_frame(1).unwrap();
    let c = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Static).unwrap();
    let records = [record(b.blas_address(c), 0)];
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.free_blas(c, 1);
    b.end_frame(1).unwrap();
    let hits = trace(&mut b, &mut renderer, tlas, &records);
    let next = frames(&mut b, 2, 3, &[]);
    b.wait_idle().unwrap();
    frames(&mut b, next, 1, &[]);
    let destroyed = b.counters().destroyed;
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    assert!(
        hits_of(&hits, 0) > 200,
        "the frame traced the BLAS it freed after its TLAS"
    );
    assert_eq!(destroyed, 3);
}

#[test]
fn a_skinned_blas_freed_in_the_frame_of_its_refit_is_kept_until_the_frame_completes() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let g = grid_geometry(16, 20.0);
    let raised: Vec<[f32; 3]> = g
        .positions
        .iter()
        .map(|p| [p[0], p[1] + 1.0, p[2]])
        .collect();
    b.begin_frame(0).unwrap();
    let s = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.begin_frame(1).unwrap();
    b.refit_blases(&[BlasRefit {
        blas: s,
        geometry: geom(&raised, &g.indices),
        rebuild: false,
    }])
    .unwrap();
    // The caller says frame 0's TLAS was its last use; the refit in frame 1 still reads it.
    b.free_blas(s, 0);
    b.build_tlas(&[], TlasDelta::ALL).unwrap();
    b.end_frame(1).unwrap();
    frames(&mut b, 2, 3, &[]);
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
}

// ---------------------------------------------------------------------------------------------
// 7. Other assumptions.

/// More triangles than the index slice holds: the GPU reads indices past the upload.
fn triangle_count_past_the_indices(class: BlasClass) {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let g = grid_geometry(4, 4.0);
    let mut bad = geom(&g.positions, &g.indices);
    bad.triangle_count *= 64;
    b.begin_frame(0).unwrap();
    let r = build_one(&mut b, bad, class);
    eprintln!("{class:?} build, triangle_count 64x the indices: {r:?}");
    let records: Vec<_> = r.iter().map(|h| record(b.blas_address(*h), 0)).collect();
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    assert!(
        refused(
            &r,
            Misuse::InvalidGeometry("fewer indices than 3 x triangle_count")
        ),
        "{r:?}"
    );
}

#[test]
fn a_static_triangle_count_past_the_indices_is_refused() {
    triangle_count_past_the_indices(BlasClass::Static);
}

#[test]
fn a_skinned_triangle_count_past_the_indices_is_refused() {
    triangle_count_past_the_indices(BlasClass::Skinned);
}

/// `BlasBuild::sizes` from another (smaller) geometry: the backend trusts them for the
/// structure's storage. The undersized BLAS takes the storage a freed small one left just
/// before a live BLAS, which must keep tracing as built.
#[test]
fn a_build_with_too_small_sizes_is_refused_or_sized_right() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let small = grid_geometry(1, 20.0);
    let big = grid_geometry(32, 20.0);
    let small_g = geom(&small.positions, &small.indices);
    let big_g = geom(&big.positions, &big.indices);
    let small_sizes = b.blas_sizes(&small_g, BlasClass::Static);
    let big_sizes = b.blas_sizes(&big_g, BlasClass::Static);
    eprintln!("sizes: 2 triangles {small_sizes:?}, 2048 triangles {big_sizes:?}");
    // Frame 0: a small BLAS, then a big one after it in the storage arena.
    b.begin_frame(0).unwrap();
    let hs = b
        .build_blases(&[
            BlasBuild {
                geometry: small_g,
                class: BlasClass::Static,
                sizes: small_sizes,
            },
            BlasBuild {
                geometry: big_g,
                class: BlasClass::Static,
                sizes: big_sizes,
            },
        ])
        .unwrap();
    let (p, victim) = (hs[0], hs[1]);
    let (pa, va) = (b.blas_address(p), b.blas_address(victim));
    let records = [record(va, 0)];
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    let before = trace(&mut b, &mut renderer, tlas, &records);
    assert!(hits_of(&before, 0) > 200);
    b.free_blas(p, 0);
    let frame = frames(&mut b, 1, 3, &records);
    b.wait_idle().unwrap();
    // The undersized build.
    b.begin_frame(frame).unwrap();
    let r = b.build_blases(&[BlasBuild {
        geometry: big_g,
        class: BlasClass::Static,
        sizes: small_sizes,
    }]);
    eprintln!(
        "build of 2048 triangles with the sizes of 2: {r:?}; small BLAS at {pa:#x}, victim at {va:#x}, undersized at {:#x}",
        r.as_ref().map_or(0, |h| b.blas_address(h[0]))
    );
    let tlas = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(frame).unwrap();
    let after = trace(&mut b, &mut renderer, tlas, &records);
    let mut d = Defects::default();
    d.check(
        after == before,
        format!(
            "the live BLAS next to the undersized one was overwritten: {} pixels hit it, {} before",
            hits_of(&after, 0),
            hits_of(&before, 0)
        ),
    );
    // Refused, or built at the geometry's own size: then it traces as the first build did.
    if let Ok(h) = &r {
        let mine = [record(b.blas_address(h[0]), 0)];
        let next = frame + 1;
        b.begin_frame(next).unwrap();
        let tlas = b.build_tlas(&mine, TlasDelta::ALL).unwrap();
        b.end_frame(next).unwrap();
        let own = trace(&mut b, &mut renderer, tlas, &mine);
        d.check(
            own == before,
            format!(
                "the build given too small sizes traces {} pixels, {} expected",
                hits_of(&own, 0),
                hits_of(&before, 0)
            ),
        );
    }
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

/// A refit recorded after the frame's TLAS: the TLAS was built over the old bounds.
#[test]
fn a_refit_after_the_frames_tlas_is_refused_or_seen_by_it() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let mut renderer = Renderer::new(ctx.clone()).expect("renderer");
    let g = grid_geometry(16, 20.0);
    // 8 m along x: half of it outside the TLAS's box of the old pose.
    let moved: Vec<[f32; 3]> = g
        .positions
        .iter()
        .map(|p| [p[0] + 8.0, p[1], p[2]])
        .collect();
    b.begin_frame(0).unwrap();
    let s = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.begin_frame(1).unwrap();
    let tlas1 = b.build_tlas(&records, TlasDelta::ALL).unwrap();
    let r = b.refit_blases(&[BlasRefit {
        blas: s,
        geometry: geom(&moved, &g.indices),
        rebuild: false,
    }]);
    eprintln!("refit after build_tlas: {r:?}");
    assert!(refused(&r, Misuse::RefitAfterTlas), "{r:?}");
    b.end_frame(1).unwrap();
    let mut d = Defects::default();
    if r.is_ok() {
        let h1 = trace(&mut b, &mut renderer, tlas1, &records);
        b.begin_frame(2).unwrap();
        let tlas2 = b.build_tlas(&records, TlasDelta::ALL).unwrap();
        b.end_frame(2).unwrap();
        let h2 = trace(&mut b, &mut renderer, tlas2, &records);
        d.check(
            h1 == h2,
            format!(
                "frame 1 traces the refitted BLAS through the old pose's TLAS box: {} pixels hit against {} once a TLAS is built over it",
                hits_of(&h1, 0),
                hits_of(&h2, 0)
            ),
        );
    }
    drop(renderer);
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}

/// A refit whose geometry says non-opaque, of a BLAS built opaque: an update must keep the
/// build's geometry flags.
#[test]
fn a_refit_with_other_opacity_is_refused_or_rebuilds() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let g = grid_geometry(8, 20.0);
    b.begin_frame(0).unwrap();
    let s = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.begin_frame(1).unwrap();
    let mut other = geom(&g.positions, &g.indices);
    other.opaque = false;
    let rebuilds = b.counters().rebuilds;
    let r = b.refit_blases(&[BlasRefit {
        blas: s,
        geometry: other,
        rebuild: false,
    }]);
    eprintln!("refit with opaque false of an opaque build: {r:?}");
    r.expect("a refit with other flags rebuilds");
    assert_eq!(b.counters().rebuilds, rebuilds + 1, "rebuilt, not updated");
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(1).unwrap();
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
}

/// The same BLAS twice in one `refit_blases` call (two updates of one structure in one
/// vkCmdBuildAccelerationStructuresKHR).
#[test]
fn one_blas_twice_in_a_refit_call_is_refused_or_serialized() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let g = grid_geometry(8, 20.0);
    let raised: Vec<[f32; 3]> = g
        .positions
        .iter()
        .map(|p| [p[0], p[1] + 1.0, p[2]])
        .collect();
    b.begin_frame(0).unwrap();
    let s = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    b.begin_frame(1).unwrap();
    let r = b.refit_blases(&[
        BlasRefit {
            blas: s,
            geometry: geom(&raised, &g.indices),
            rebuild: false,
        },
        BlasRefit {
            blas: s,
            geometry: geom(&g.positions, &g.indices),
            rebuild: false,
        },
    ]);
    eprintln!("one BLAS twice in a refit call: {r:?}");
    assert!(refused(&r, Misuse::DuplicateRefit(s)), "{r:?}");
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(1).unwrap();
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
}

/// Several refits of one CPU-posed skinned BLAS in one frame advance its pose ring by more
/// than one: the ring of `frames_in_flight + 1` assumes one per frame. Checks that the pose
/// the shading reads for an earlier frame in flight is not overwritten by the host.
#[test]
fn several_refits_a_frame_leave_the_poses_of_frames_in_flight_alone() {
    let ctx = common::context();
    let mut b = backend(&ctx);
    let g = grid_geometry(8, 20.0);
    let pose = |k: u32| -> Vec<[f32; 3]> {
        g.positions
            .iter()
            .map(|p| [p[0], p[1] + k as f32, p[2]])
            .collect()
    };
    b.begin_frame(0).unwrap();
    let s = build_one(&mut b, geom(&g.positions, &g.indices), BlasClass::Skinned).unwrap();
    let records = [record(b.blas_address(s), 0)];
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(0).unwrap();
    // Frame 1: two refits; the shading of frame 1 reads pose 2.
    let mut d = Defects::default();
    let (p1, p2, p3) = (pose(1), pose(2), pose(3));
    b.begin_frame(1).unwrap();
    for p in [&p1, &p2] {
        b.refit_blases(&[BlasRefit {
            blas: s,
            geometry: geom(p, &g.indices),
            rebuild: false,
        }])
        .unwrap();
    }
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    let frame1_shading = b.shading_geometry(records[0].blas_address).unwrap();
    b.end_frame(1).unwrap();
    // Frame 2 (frame 1 may still be in flight: begin_frame(2) waits for frame 0 only).
    b.begin_frame(2).unwrap();
    for p in [&p3, &p3] {
        b.refit_blases(&[BlasRefit {
            blas: s,
            geometry: geom(p, &g.indices),
            rebuild: false,
        }])
        .unwrap();
    }
    let frame1_pose_now = b
        .input_buffer_bytes(frame1_shading.0)
        .map(|bytes| bytemuck::pod_collect_to_vec::<u8, [f32; 3]>(&bytes[..p2.len() * 12]));
    d.check(
        frame1_pose_now.as_deref() == Some(&p2[..]),
        format!(
            "frame 1's shading pose (in flight) was overwritten by frame 2's refits: y = {:?}",
            frame1_pose_now.as_ref().map(|p| p[0][1])
        ),
    );
    b.build_tlas(&records, TlasDelta::ALL).unwrap();
    b.end_frame(2).unwrap();
    b.wait_idle().unwrap();
    drop(b);
    common::assert_no_validation_messages(&ctx);
    d.assert_none();
}
