//! Compiles the GLSL compute shaders in `shaders/` to SPIR-V with glslc (Debian package `glslc`,
//! installed by `scripts/setup.sh`). The SPIR-V lands in OUT_DIR and is embedded in the binary,
//! so built binaries run where no shader compiler exists (the GPU machine).

use std::path::PathBuf;
use std::process::Command;

fn main() {
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let dir = PathBuf::from("shaders");
    println!("cargo:rerun-if-changed=shaders");
    let glslc = std::env::var("GLSLC").unwrap_or_else(|_| "glslc".into());
    let mut entries: Vec<_> = std::fs::read_dir(&dir)
        .expect("renderer/shaders exists")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for path in entries {
        let Some(ext) = path.extension().and_then(|e| e.to_str()) else {
            continue;
        };
        if !matches!(ext, "comp" | "rgen" | "rmiss" | "rchit") {
            continue;
        }
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let spv = out.join(format!("{name}.spv"));
        let status = Command::new(&glslc)
            .args(["--target-env=vulkan1.2", "-O", "-Werror", "-I"])
            .arg(&dir)
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
}
