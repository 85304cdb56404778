//! With no usable Vulkan driver, context creation is a typed error that says how to install one.
//! (Its own test binary: it points the loader at a driver list that does not exist.)

use rtstream::as_manager::backend::vulkan::{ContextDesc, Validation, VulkanContext, VulkanError};

#[test]
fn no_driver_is_a_typed_error_with_an_install_hint() {
    // This binary has one test, so no other thread reads the environment meanwhile.
    std::env::set_var("VK_DRIVER_FILES", "/nonexistent/rtstream_icd.json");
    std::env::set_var("VK_ICD_FILENAMES", "/nonexistent/rtstream_icd.json");
    let desc = ContextDesc {
        validation: Validation::Off,
        ..ContextDesc::default()
    };
    let err = VulkanContext::new(&desc).expect_err("no device without a driver");
    match &err {
        VulkanError::NoSuitableDevice { .. } => {}
        other => panic!("unexpected error kind: {other:?}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("bookworm-backports") && msg.contains("scripts/setup.sh"),
        "{msg}"
    );
}
