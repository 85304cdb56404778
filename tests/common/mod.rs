//! Shared test set-up: a Vulkan context with validation required, and a check that it stayed silent.

#![allow(dead_code)]

use std::sync::Arc;

use rtstream::as_manager::backend::vulkan::{ContextDesc, Validation, VulkanContext};

/// Debian's assimp-testmodels glTF 2 directory (the world generator's default too).
pub const ASSETS: &str = rtstream::streaming::ASSIMP_GLTF2_DIR;

/// Path of a model in Debian's assimp-testmodels, with a clear failure when it is missing.
pub fn asset(rel: &str) -> std::path::PathBuf {
    let p = std::path::Path::new(ASSETS).join(rel);
    assert!(
        p.exists(),
        "{} is missing: run scripts/setup.sh (it installs Debian's assimp-testmodels)",
        p.display()
    );
    p
}

/// A context with the validation layer required (a missing layer fails the test).
pub fn context() -> Arc<VulkanContext> {
    let _ = tracing_subscriber::fmt()
        .with_test_writer()
        .with_env_filter("warn")
        .try_init();
    let desc = ContextDesc {
        app_name: "rtstream tests".into(),
        validation: Validation::Required,
        require_ray_query: true,
        ..ContextDesc::default()
    };
    Arc::new(VulkanContext::new(&desc).unwrap_or_else(|e| panic!("Vulkan context: {e}")))
}

/// Fails the test if the validation layer reported anything.
pub fn assert_no_validation_messages(ctx: &VulkanContext) {
    let log = ctx.validation_log();
    assert_eq!(
        log.failure_count(),
        0,
        "validation messages:\n{}",
        log.messages().join("\n")
    );
}
