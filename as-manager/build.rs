//! With feature `vulkan`: compiles the backend's GLSL compute shader in `shaders/` (the GPU
//! refit-quality pass) to SPIR-V with glslc, through the glslc step `renderer/build.rs` uses
//! too (`shader_build.rs` at the workspace root). The SPIR-V lands in OUT_DIR and is embedded,
//! so built binaries need no shader compiler. Without the feature the crate is pure Rust and
//! nothing runs.

#[path = "../shader_build.rs"]
mod shader_build;

use std::path::Path;

fn main() {
    shader_build::rerun_if_changed();
    if std::env::var_os("CARGO_FEATURE_VULKAN").is_none() {
        return;
    }
    shader_build::compile(
        &Path::new(shader_build::SHADERS).join("refit_quality.comp"),
        None,
    );
}
