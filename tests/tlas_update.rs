//! The TLAS update-in-place measurement (`time_tlas_update`, used by `gpu_bench`) is valid
//! Vulkan on lavapipe with validation on: a build with ALLOW_UPDATE, then updates in place from
//! moved instances, each timed by GPU timestamps, and everything it made is freed.

mod common;

use rtstream::as_manager::backend::vulkan::ash::vk;
use rtstream::as_manager::backend::vulkan::{build_blas_now, time_tlas_update};

#[test]
fn a_tlas_updates_in_place_and_both_are_timed() {
    let ctx = common::context();
    let geom = common::grid_on_gpu(&ctx, 4, 1.0);
    let flags = vk::BuildAccelerationStructureFlagsKHR::PREFER_FAST_TRACE;
    let blas = build_blas_now(&ctx, &geom, flags, "update test blas").unwrap();
    let buffers = ctx.live_buffers();
    let transforms: Vec<[f32; 16]> = (0..300)
        .map(|i| {
            let at = glam::Vec3::new((i % 20) as f32 * 10.0, 0.0, (i / 20) as f32 * 10.0);
            glam::Mat4::from_translation(at).to_cols_array()
        })
        .collect();
    let (build_ms, update_ms) = time_tlas_update(&ctx, &blas, &transforms, 2).unwrap();
    // Timestamps of work this small may tick zero apart: only their validity is asserted, never
    // a duration (no test depends on timing).
    assert!(
        build_ms >= 0.0 && build_ms.is_finite(),
        "build {build_ms} ms"
    );
    assert!(
        update_ms >= 0.0 && update_ms.is_finite(),
        "update {update_ms} ms"
    );
    assert_eq!(
        ctx.live_buffers(),
        buffers,
        "the measurement freed what it made"
    );
    ctx.destroy_accel(blas);
    geom.destroy(&ctx);
    common::assert_no_validation_messages(&ctx);
}
