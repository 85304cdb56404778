//! With feature `vulkan`: compiles the backend's GLSL compute shaders in `shaders/` (the GPU
//! refit-quality pass) to SPIR-V with glslc, as `renderer/build.rs` does for the renderer's.
//! The SPIR-V lands in OUT_DIR and is embedded, so built binaries need no shader compiler.
//! Without the feature the crate is pure Rust and nothing runs.

use std::path::PathBuf;
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-changed=shaders");
    println!("cargo:rerun-if-env-changed=GLSLC");
    if std::env::var_os("CARGO_FEATURE_VULKAN").is_none() {
        return;
    }
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    let name = "refit_quality.comp";
    let path = PathBuf::from("shaders").join(name);
    let spv = out.join(format!("{name}.spv"));
    let status = Command::new(&glslc)
        .args(["--target-env=vulkan1.2", "-O", "-Werror"])
        .arg(&path)
        .arg("-o")
        .arg(&spv)
        .status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => panic!("glslc failed on {} ({s})", path.display()),
        Err(e) => panic!(
            "cannot run the shader compiler `{glslc}` ({e}): run scripts/setup.sh \
             (apt-get install glslc), or set GLSLC to a glslc binary"
        ),
    }
}
