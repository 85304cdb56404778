//! The frame driver end to end on lavapipe: a short deterministic run of every policy on the
//! real backend, scored against the full-world ground truth. Run twice: every figure except
//! the timings is identical. The JSON summary has the documented keys, and the reference holds
//! instances of levels streaming never loaded.

mod common;

use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, FrameRow, RunConfig};
use rtstream::streaming::WorldPreset;

fn config(dir: &std::path::Path) -> RunConfig {
    let mut c = RunConfig {
        eval_every: 20,
        size: (64, 36),
        ..common::driver_run(WorldPreset::small(12, 7), dir, 120)
    };
    // A short stream radius so that part of the map is never loaded.
    c.stream.load_radius = 250.0;
    c.stream.unload_radius = 300.0;
    c
}

/// A row without its timings.
fn untimed(r: &FrameRow) -> FrameRow {
    FrameRow {
        update_ms: 0.0,
        update_cpu_ms: 0.0,
        gpu_as_ms: 0.0,
        gpu_tlas_ms: 0.0,
        ..r.clone()
    }
}

#[test]
fn a_deterministic_run_repeats_exactly_and_scores_against_the_whole_world() {
    let ctx = common::context();
    let dir = common::temp_path("driver");
    let c = config(&dir);
    let mut frames_seen = 0;
    let a = driver::run_on(ctx.clone(), &c, &mut |p| frames_seen = p.frame + 1).unwrap();
    assert_eq!(frames_seen, 120, "progress reports every frame");
    let b = driver::run_on(ctx.clone(), &c, &mut |_| {}).unwrap();
    common::assert_no_validation_messages(&ctx);
    std::fs::remove_dir_all(&dir).ok();

    // Identical figures, timings aside.
    assert_eq!(a.rows.len(), 3 * 120);
    let (ra, rb): (Vec<_>, Vec<_>) = (
        a.rows.iter().map(untimed).collect(),
        b.rows.iter().map(untimed).collect(),
    );
    assert_eq!(ra, rb, "a deterministic run repeats");
    let scored = a.rows.iter().filter(|r| r.score.is_some()).count();
    assert_eq!(scored, 3 * 5, "frames 20..100 scored for every policy");

    // The reference is the whole world, not what streaming loaded.
    let s = &a.summary;
    assert!(s.reference.full_world);
    assert!(
        s.reference.never_loaded_instances > 0,
        "the reference holds instances of never-loaded levels"
    );
    assert!(s.reference.all_geometry_instances > s.reference.instances);

    // The JSON keys.
    let json: serde_json::Value = serde_json::from_str(&a.json()).unwrap();
    for key in [
        "frames",
        "seed",
        "evaluated_frames",
        "reference",
        "policies",
    ] {
        assert!(json.get(key).is_some(), "missing {key}");
    }
    assert_eq!(json["reference"]["full_world"], true);
    assert!(json["reference"]["instances"].as_u64().unwrap() > 0);
    let policies = json["policies"].as_array().unwrap();
    let names: Vec<&str> = policies
        .iter()
        .map(|p| p["policy"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["managed", "naive", "seed"]);
    for p in policies {
        for key in [
            "backend",
            "peak_blas_bytes",
            "p95_blas_bytes",
            "peak_tlas_instances",
            "update_ms_p50",
            "update_ms_p99",
            "update_cpu_ms_p50",
            "update_cpu_ms_p99",
            "gpu_as_ms_p50",
            "gpu_as_ms_p99",
            "gpu_tlas_ms_p99",
            "tlas_update_share",
            "over_budget_frames",
            "hit_mismatch_mean",
            "hit_mismatch_p95",
            "shadow_mismatch_mean",
            "shadow_mismatch_p95",
            "mismatch_by_band",
            "validation_messages",
        ] {
            assert!(p.get(key).is_some(), "{}: missing {key}", p["policy"]);
        }
        // The thread's CPU time is part of the wall time (the two clocks are read a few
        // hundred nanoseconds apart).
        let (wall, cpu) = (
            p["update_ms_p50"].as_f64().unwrap(),
            p["update_cpu_ms_p50"].as_f64().unwrap(),
        );
        assert!(
            cpu > 0.0 && cpu <= wall * 1.05 + 0.01,
            "{}: cpu {cpu} wall {wall}",
            p["policy"]
        );
        assert_eq!(p["mismatch_by_band"].as_array().unwrap().len(), 4);
        assert_eq!(p["over_budget_frames"], 0);
        assert_eq!(p["validation_messages"], 0);
    }
    // The managed policy traces something and is scored with a finite error.
    let managed = &s.policies[0];
    assert!(managed.peak_tlas_instances > 0);
    assert!((0.0..1.0).contains(&managed.hit_mismatch_mean));
    assert_eq!(c.policies[0], PolicyKind::Managed);
}
