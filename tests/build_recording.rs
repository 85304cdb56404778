//! The host-cost measurement of recording BLAS builds (`time_build_recording`, used by
//! `gpu_bench --recording-only`) is valid Vulkan on lavapipe with validation on: two build
//! calls of disjoint BLASes in one command buffer, then an update in place where the flags
//! allow it, and everything it made is freed.

mod common;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::time_build_recording;

#[test]
fn build_calls_and_an_update_are_timed_on_the_host() {
    let ctx = common::context();
    let geom = common::grid_on_gpu(&ctx, 4, 1.0);
    let buffers = ctx.live_buffers();
    use vk::BuildAccelerationStructureFlagsKHR as F;
    for (flags, updates) in [
        (F::PREFER_FAST_BUILD | F::ALLOW_COMPACTION, false),
        (F::PREFER_FAST_BUILD | F::ALLOW_UPDATE, true),
    ] {
        let c = time_build_recording(&ctx, &[&geom, &geom, &geom], flags, 2).unwrap();
        // Only validity is asserted, never a duration (no test depends on timing).
        for ms in [c.first_call_ms, c.second_call_ms] {
            assert!(ms >= 0.0 && ms.is_finite(), "{ms} ms");
        }
        assert_eq!(c.update_ms.is_some(), updates, "{flags:?}");
        assert!(c.update_ms.is_none_or(|u| u >= 0.0 && u.is_finite()));
    }
    assert_eq!(
        ctx.live_buffers(),
        buffers,
        "the measurement freed what it made"
    );
    geom.destroy(&ctx);
    common::assert_no_validation_messages(&ctx);
}
