//! The far-field hand-over, rendered: a slow walk on lavapipe, every frame scored against the
//! full-world ground truth. The geometric mismatch between r2 and 1 km stays low over the walk
//! (a hole left by a hand-over raises it); on the frames where a group's proxy gives way to its
//! detail (or back) it never exceeds twice its mean over the frames around them, nor on average
//! the other frames' by half, and stepping into one changes the image no more than the walk's
//! ordinary frame-to-frame change. The memory budget holds
//! with the proxies in it.

mod common;

use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, FrameRow, RunConfig};
use rtstream::streaming::WorldPreset;

/// Share of all pixels whose hit disagrees in the r2–1 km band.
fn far_band(r: &FrameRow) -> f64 {
    let s = r.score.as_ref().expect("every frame is scored");
    s.bands[2].hit_mismatched as f64 / s.pixels.max(1) as f64
}

#[test]
fn a_slow_walk_across_r2_hands_over_without_popping() {
    let ctx = common::context();
    let dir = common::temp_path("handover");
    let frames = 160;
    let mut c = RunConfig {
        policies: vec![PolicyKind::Managed],
        eval_every: 1,
        size: (256, 144),
        all_geometry_reference: false,
        // About 1.5 m a frame along the path's diagonal.
        path_span: (0.25, 0.45),
        ..common::driver_run(WorldPreset::small(16, 11), &dir, frames)
    };
    // A budget the near field fills: the proxies must fit beside the detail.
    c.managed.memory.blas_bytes = 24 << 20;
    // A tight build budget: detail arrives over several frames, so a hand-over that did not
    // wait for it would leave holes.
    c.managed.build.max_primitives = 20_000;
    let report = driver::run_on(ctx.clone(), &c, &mut |_| {}).unwrap();
    common::assert_no_validation_messages(&ctx);
    std::fs::remove_dir_all(&dir).ok();

    let rows: Vec<&FrameRow> = report.rows.iter().filter(|r| r.score.is_some()).collect();
    assert_eq!(rows.len() as u64, frames - 1, "frames 1.. are scored");
    assert!(
        rows.iter().all(|r| !r.over_budget()),
        "the budget holds with proxies"
    );
    assert!(
        rows.iter().any(|r| r.proxy_instances > 0),
        "the far field shows proxies on this walk"
    );
    // The start-up: streaming applies the first loads two frames after their request, and the
    // tight build budget takes until about frame 8 to build the first far field (landmarks
    // and proxies); the far band is 3-5x its walking level until then. A hand-over during that
    // backlog is not a pop, so the comparisons below start after it.
    const START_UP: u64 = 10;
    let is_handover =
        |i: usize| i > 0 && rows[i - 1].far_groups_covered != rows[i].far_groups_covered;
    let (mut handover, mut other) = (Vec::new(), Vec::new());
    let (mut step_handover, mut step_other) = (Vec::new(), Vec::new());
    for (i, r) in rows.iter().enumerate().filter(|(_, r)| r.frame >= START_UP) {
        let step = far_band(r) - far_band(rows[i - 1]);
        if is_handover(i) {
            handover.push(far_band(r));
            step_handover.push(step);
        } else {
            other.push(far_band(r));
            step_other.push(step.abs());
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let walk_mean = mean(&[handover.as_slice(), &other].concat());
    eprintln!(
        "{} hand-over frames after the start-up; r2-1 km mismatch: walk mean {:.3} %, hand-over \
         frames {:.3} % (worst {:.3} %), others {:.3} %; mean step into a hand-over {:+.3} %, \
         mean |step| elsewhere {:.3} %",
        handover.len(),
        100.0 * walk_mean,
        100.0 * mean(&handover),
        100.0 * handover.iter().copied().fold(0.0, f64::max),
        100.0 * mean(&other),
        100.0 * mean(&step_handover),
        100.0 * mean(&step_other),
    );
    assert!(
        handover.len() >= 3,
        "the walk crosses r2 of several groups after the start-up ({} hand-over frames)",
        handover.len()
    );
    assert!(
        walk_mean > 0.0,
        "the far band is scored (proxies are not exact)"
    );
    // The level: a hand-over that dropped a near group's part beyond r2, or left a hole until
    // detail arrived, raises the whole walk (such a hole measured 1.8 % at 128x72; the walk is about 0.08 %).
    assert!(
        walk_mean <= 0.002,
        "r2-1 km mismatch {:.3} % over the walk",
        100.0 * walk_mean
    );
    // The far band's level moves along the path with what lies beyond r2 (18 to 67 mismatched
    // pixels a frame at this size on ordinary frames), so "twice its mean" is taken around each
    // hand-over frame: the ordinary frames within `NEAR` frames of it. At 128x72 a frame held
    // 3-13 such pixels and single frames were at the noise floor (one hand-over frame reached
    // 2.6x its neighbours with 13 pixels; at this size the same frame is 0.7x); a group's
    // forced pop for one frame added about 5 pixels there. (`as-manager` far_tests check at
    // every frame that no group shows twice or not at all.)
    const NEAR: u64 = 8;
    for (i, r) in rows.iter().enumerate() {
        if r.frame < START_UP || !is_handover(i) {
            continue;
        }
        let around: Vec<f64> = rows
            .iter()
            .enumerate()
            .filter(|(j, o)| {
                o.frame >= START_UP && !is_handover(*j) && o.frame.abs_diff(r.frame) <= NEAR
            })
            .map(|(_, o)| far_band(o))
            .collect();
        assert!(
            !around.is_empty(),
            "frame {}: no ordinary frame near it",
            r.frame
        );
        assert!(
            far_band(r) <= 2.0 * mean(&around),
            "frame {}: r2-1 km mismatch {:.3} % on a hand-over frame, {:.3} % around it",
            r.frame,
            100.0 * far_band(r),
            100.0 * mean(&around)
        );
    }
    assert!(
        mean(&handover) <= 1.5 * mean(&other),
        "hand-over frames average {:.3} %, the others {:.3} %",
        100.0 * mean(&handover),
        100.0 * mean(&other)
    );
    // No systematic step up into a hand-over: on average it changes the image no more than
    // the walk's ordinary frame-to-frame change.
    assert!(
        mean(&step_handover) <= mean(&step_other),
        "the far band steps by {:+.3} % into a hand-over frame on average, |{:.3}| % elsewhere",
        100.0 * mean(&step_handover),
        100.0 * mean(&step_other)
    );
}
