//! Stability where methods fail, on the real backend (lavapipe, validation on, frames in
//! flight), through the shared frame driver in deterministic mode (every figure but timings is
//! the same under any machine load). Shortened versions of the `teleport_storm` and
//! `memory_budget` examples:
//! - a teleport every 30 frames: every frame within the build budget and the memory budget;
//!   every teleport reaches full coverage (every unculled instance within r1 shows its target
//!   LOD or finer) before the next one; the TLAS is empty only on the first frames after a
//!   teleport, while the new place's first builds are on their way;
//! - BLAS budgets from below the smallest coarsest LOD within r1 to above what r1 asks for:
//!   never exceeded; the TLAS is never empty once the budget holds the smallest coarsest LOD;
//!   below it, nothing is shown and the budget is reported exhausted, without a panic.
//!
//! Figures are printed (`--nocapture`) for docs/RELIABILITY.md.

mod common;

use rtstream::as_manager::backend::vulkan::Validation;
use rtstream::as_manager::PolicyKind;
use rtstream::driver::{self, FrameRow, RunConfig};
use rtstream::streaming::WorldPreset;

fn config(name: &str, frames: u64) -> RunConfig {
    let dir = common::temp_path(&format!("stress-{name}"));
    let mut c = RunConfig {
        policies: vec![PolicyKind::Managed],
        eval_every: 0,
        validation: Validation::Required,
        ..common::driver_run(WorldPreset::small(8, 7), &dir, frames)
    };
    c.stream.load_radius = 300.0;
    c.stream.unload_radius = 350.0;
    c
}

fn managed(rows: &[FrameRow]) -> Vec<&FrameRow> {
    rows.iter().filter(|r| r.policy == "managed").collect()
}

#[test]
fn teleport_every_30_frames_holds_the_budgets_and_recovers_coverage() {
    let mut c = config("teleport", 300);
    c.teleport_every = Some(30);
    let report = driver::run(&c, &mut |_| {}).expect("run");
    let rows = managed(&report.rows);
    assert_eq!(rows.len(), 300);
    let p = &report.summary.policies[0];
    assert_eq!(p.validation_messages, 0);
    assert_eq!(p.over_budget_frames, 0);
    for r in &rows {
        assert!(
            !r.over_build_budget,
            "frame {}: {} > {}",
            r.frame, r.build_primitives, r.build_budget
        );
        assert!(!r.over_budget(), "frame {}", r.frame);
    }
    let coverage = driver::frames_to_coverage(&report.rows, "managed", 30);
    assert_eq!(coverage.len(), 10);
    let to_coverage: Vec<u64> = coverage
        .iter()
        .enumerate()
        .map(|(k, c)| c.unwrap_or_else(|| panic!("teleport {k}: not covered within 30 frames")))
        .collect();
    // Frames with instances in view within r1 and an empty TLAS, per teleport.
    let empty_frames: Vec<usize> = rows
        .chunks(30)
        .map(|seg| {
            seg.iter()
                .filter(|r| r.within_r1 > 0 && r.tlas_instances == 0)
                .count()
        })
        .collect();
    let worst = *to_coverage.iter().max().unwrap();
    eprintln!(
        "teleport storm: frames to full coverage per teleport {to_coverage:?} (worst {worst}); \
         frames with an empty TLAS while instances were within r1 {empty_frames:?}; \
         peak build triangles {} (budget {})",
        rows.iter().map(|r| r.build_primitives).max().unwrap(),
        rows[0].build_budget
    );
    assert!(empty_frames.iter().all(|&e| e <= 2), "{empty_frames:?}");
    let _ = std::fs::remove_dir_all(c.world_dir.parent().unwrap());
}

#[test]
fn budgets_below_what_r1_asks_for_are_never_exceeded() {
    let mut peak_unlimited = 0;
    let mut lines = Vec::new();
    for (i, budget) in [u64::MAX >> 8, 32 << 20, 4 << 20, 1 << 20, 64 << 10, 64]
        .into_iter()
        .enumerate()
    {
        let mut c = config(&format!("budget{i}"), 120);
        c.managed.memory.blas_bytes = budget;
        let report = driver::run(&c, &mut |_| {}).expect("run");
        let rows = managed(&report.rows);
        let p = &report.summary.policies[0];
        assert_eq!(p.validation_messages, 0, "budget {budget}");
        assert_eq!(p.over_budget_frames, 0, "budget {budget}");
        let peak = rows
            .iter()
            .map(|r| r.blas_bytes + r.retiring_bytes)
            .max()
            .unwrap();
        if i == 0 {
            peak_unlimited = peak;
        }
        let empty_after_warmup = rows
            .iter()
            .skip(10)
            .filter(|r| r.within_r1 > 0 && r.tlas_instances == 0)
            .count();
        let short = rows
            .iter()
            .skip(10)
            .map(|r| r.short_of_target)
            .max()
            .unwrap();
        let evictions: u32 = rows.iter().map(|r| r.evictions).sum();
        let refused = rows.iter().filter(|r| r.memory_refused > 0).count();
        lines.push(format!(
            "budget {budget}: peak {peak} B, max short of target {short}, evictions {evictions}, \
             frames with builds refused for memory {refused}, \
             frames with an empty TLAS after frame 10 {empty_after_warmup}"
        ));
        if budget >= 32 << 20 {
            assert_eq!(refused, 0, "budget {budget}");
        }
        if budget >= 1 << 20 {
            // Room for the coarsest LODs near the camera: something is always shown.
            assert_eq!(empty_after_warmup, 0, "budget {budget}");
        }
        if budget == 64 {
            // Below any BLAS: nothing is shown, nothing is built, no panic, no error.
            let shown: Vec<_> = rows
                .iter()
                .filter(|r| r.blas_bytes > 0 || r.tlas_instances > 0)
                .map(|r| (r.frame, r.blas_bytes, r.tlas_instances, r.proxy_instances))
                .take(5)
                .collect();
            assert!(shown.is_empty(), "{shown:?}");
            // ... and reported: every instance within r1 is short of its target, and the
            // builds tried are refused for memory.
            assert!(rows.iter().all(|r| r.short_of_target == r.within_r1));
            assert!(refused > 0);
        }
        let _ = std::fs::remove_dir_all(c.world_dir.parent().unwrap());
    }
    eprintln!("{}", lines.join("\n"));
    assert!(
        peak_unlimited > 32 << 20 || peak_unlimited > 4 << 20,
        "r1 asks for {peak_unlimited} B"
    );
}
