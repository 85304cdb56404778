//! Compiles the GLSL shaders in `shaders/` (compute and ray-tracing stages) to SPIR-V with
//! glslc (Debian package `glslc`, installed by `scripts/setup.sh`), through the glslc step
//! `as-manager/build.rs` uses too (`shader_build.rs` at the workspace root). The SPIR-V lands in
//! OUT_DIR and is embedded in the binary, so built binaries run where no shader compiler exists
//! (the GPU machine).

#[path = "../shader_build.rs"]
mod shader_build;

use std::path::{Path, PathBuf};

fn main() {
    shader_build::rerun_if_changed();
    let dir = Path::new(shader_build::SHADERS);
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("renderer/shaders exists")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for path in entries {
        let Some(ext) = path.extension().and_then(|e| e.to_str()) else {
            continue;
        };
        if matches!(ext, "comp" | "rgen" | "rmiss" | "rchit") {
            shader_build::compile(&path, Some(dir));
        }
    }
}
