//! The glslc step both shader-carrying crates' build scripts share (`as-manager/build.rs` and
//! `renderer/build.rs` include it with `#[path = "../shader_build.rs"] mod shader_build;`):
//! each shader compiles to `OUT_DIR/<file name>.spv` for Vulkan 1.2, optimised, warnings as
//! errors. The SPIR-V is embedded by the crate, so built binaries need no shader compiler.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The crate's shader directory, relative to its manifest; cargo reruns the build script when
/// anything in it or `GLSLC` changes.
pub const SHADERS: &str = "shaders";

/// Tells cargo what the shaders depend on: the shader directory and `GLSLC`.
pub fn rerun_if_changed() {
    println!("cargo:rerun-if-changed={SHADERS}");
    println!("cargo:rerun-if-env-changed=GLSLC");
}

/// Compiles `path` to `OUT_DIR/<its file name>.spv` with glslc (`GLSLC`, or `glslc` on the
/// path), with `include` as the `#include` directory if given; panics with what to do when
/// glslc is missing or fails.
pub fn compile(path: &Path, include: Option<&Path>) {
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    let name = path.file_name().expect("a shader file").to_string_lossy();
    let spv = out.join(format!("{name}.spv"));
    let mut command = Command::new(&glslc);
    command.args(["--target-env=vulkan1.2", "-O", "-Werror"]);
    if let Some(dir) = include {
        command.arg("-I").arg(dir);
    }
    let status = command.arg(path).arg("-o").arg(&spv).status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => panic!("glslc failed on {} ({s})", path.display()),
        Err(e) => panic!(
            "cannot run the shader compiler `{glslc}` ({e}): run scripts/setup.sh \
             (apt-get install glslc), or set GLSLC to a glslc binary"
        ),
    }
}
