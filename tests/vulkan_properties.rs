//! The property tests' state machine on the Vulkan backend (lavapipe, validation with
//! synchronization checks on, frames in flight): random registrations, removals, moves,
//! teleports, budget changes, rejected inputs, skipped frames and injected backend faults
//! (failed calls, out of device memory, device lost)
//! keep every invariant after every frame, and the validation layer stays silent. A smaller
//! run than the model backend's 10,000 (`VK_PROPTEST_CASES`, default 200): each case creates
//! real BLASes and TLASes.

mod common;

use proptest::prelude::*;
use proptest::test_runner::{Config as RunnerConfig, TestRunner};
use rtstream::as_manager::backend::vulkan::{VulkanBackend, VulkanBackendDesc};

use rtstream::as_manager as rtm;
#[path = "../as-manager/tests/harness/mod.rs"]
mod harness;
use harness::{config, op, shrunk_config, Harness, Op};

#[test]
fn invariants_hold_on_the_vulkan_backend() {
    let ctx = common::context();
    let cases = std::env::var("VK_PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(200);
    let mut runner = TestRunner::new(RunnerConfig {
        cases,
        failure_persistence: None,
        ..RunnerConfig::default()
    });
    let strategy = (config(), prop::collection::vec(op(), 1..40));
    let frames = std::cell::Cell::new(0u64);
    let faults = std::cell::Cell::new(0u32);
    let work = std::cell::Cell::new((0u64, 0u64));
    let ooms = std::cell::Cell::new(0u64);
    runner
        .run(&strategy, |(cfg, ops)| {
            let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default())
                .map_err(|e| TestCaseError::fail(format!("backend: {e}")))?;
            let mut h = Harness::new(cfg, backend);
            for o in ops {
                h.apply(o)?;
            }
            h.drain()?;
            frames.set(frames.get() + h.frame);
            faults.set(faults.get() + h.retried);
            let (b, t) = work.get();
            work.set((b + h.builds, t + h.tlas_instances));
            ooms.set(ooms.get() + h.ooms_seen);
            let log = ctx.validation_log();
            prop_assert_eq!(log.failure_count(), 0, "{}", log.messages().join("\n"));
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
    let (frames, faults, (builds, instances)) = (frames.get(), faults.get(), work.get());
    let ooms = ooms.get();
    eprintln!("{cases} cases, {frames} frame numbers, {builds} BLAS builds, {instances} TLAS instances, {faults} failed frames retried, {ooms} out-of-memory events");
    assert!(builds > u64::from(cases), "{builds} builds");
    assert!(frames > u64::from(cases), "{frames} frames");
}

/// Found by the random run: 22 instances of an 8,000-triangle mesh and four small ones in a
/// 500 KB budget, r1 == r2, thresholds 0. The BLAS storage stays within the budget; the input
/// buffers the backend keeps for shading are outside it.
#[test]
fn regression_blas_storage_within_budget_with_inputs_outside_it() {
    let ctx = common::context();
    let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default()).unwrap();
    let mut h = Harness::new(shrunk_config(93.77278, 93.77278), backend);
    let mut ops = vec![Op::Add {
        mesh: 4,
        n: 22,
        x: 0.0,
        z: 0.0,
    }];
    for _ in 0..4 {
        ops.push(Op::Add {
            mesh: 0,
            n: 1,
            x: 0.0,
            z: 0.0,
        });
    }
    ops.push(Op::Walk {
        dx: 0.0,
        dz: 0.0,
        frames: 40,
    });
    for o in ops {
        h.apply(o).unwrap();
    }
    assert!(h.builds > 0);
}
