//! Error paths free what they made (lavapipe, validation on). A failure is injected at each
//! step of creating the context, the backend and a one-off BLAS build; afterwards the
//! process-wide count of live Vulkan handles and the context's live buffers are what they were
//! before. One test in its own binary: the handle count is process-wide.

mod common;

use rtstream::as_manager::backend::vulkan::{
    build_blas_now, class_flags, live_vulkan_handles, ContextDesc, Validation, VulkanBackend,
    VulkanBackendDesc, VulkanContext, VulkanError,
};
use rtstream::as_manager::backend::BlasClass;

/// Fails the test unless `result` is the failure injected at `step`.
fn assert_injected<T>(step: &str, result: Result<T, VulkanError>) {
    match result {
        Err(VulkanError::Injected { at }) => assert_eq!(at, step),
        Err(e) => panic!("{step}: unexpected error {e}"),
        Ok(_) => panic!("{step}: the injected failure did not strike"),
    }
}

#[test]
fn every_failed_creation_frees_what_it_made() {
    let before = live_vulkan_handles();
    for step in ["messenger", "device", "command_pool", "allocator"] {
        let desc = ContextDesc {
            app_name: "rtstream leak test".into(),
            validation: Validation::Required,
            require_ray_query: true,
            fail_at: Some(step),
        };
        assert_injected(step, VulkanContext::new(&desc));
        assert_eq!(
            live_vulkan_handles(),
            before,
            "a context that failed at `{step}` left handles alive"
        );
    }

    let ctx = common::context();
    let with_ctx = live_vulkan_handles();
    assert!(with_ctx > before);
    for step in [
        "backend.pool",
        "backend.semaphore",
        "backend.command_buffers",
        "query_pool",
    ] {
        ctx.inject_failure(step);
        assert_injected(
            step,
            VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default()),
        );
        assert_eq!(
            live_vulkan_handles(),
            with_ctx,
            "a backend that failed at `{step}` left handles alive"
        );
    }

    let geom = common::grid_on_gpu(&ctx, 8, 2.0);
    let buffers = ctx.live_buffers();
    ctx.inject_failure("build_blas_now.scratch");
    let flags = class_flags(BlasClass::Static);
    assert!(matches!(
        build_blas_now(&ctx, &geom, flags, "leak test"),
        Err(VulkanError::Injected { .. })
    ));
    assert_eq!(
        ctx.live_buffers(),
        buffers,
        "the BLAS of a failed one-off build is freed"
    );
    // The same calls succeed without a fault, and their objects go away with them.
    let blas = build_blas_now(&ctx, &geom, flags, "leak test").unwrap();
    ctx.destroy_accel(blas);
    geom.destroy(&ctx);
    let backend = VulkanBackend::new(ctx.clone(), VulkanBackendDesc::default()).unwrap();
    drop(backend);
    assert_eq!(live_vulkan_handles(), with_ctx);
    common::assert_no_validation_messages(&ctx);
    drop(ctx);
    assert_eq!(live_vulkan_handles(), before, "the context freed its own");
}
