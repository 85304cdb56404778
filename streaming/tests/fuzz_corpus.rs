//! Stable replay of the fuzz bodies (`rtstream_streaming::fuzz`): the committed corpus and
//! crash inputs (`streaming/fuzz/corpus/<target>/`, `streaming/fuzz/artifacts/<target>/`),
//! the world's own baked files (a small world baked here: manifest, level files, every LOD
//! chunk of the mesh library, the proxy file), every glTF/GLB in Debian's assimp-testmodels,
//! and deterministic mutations of each (truncations and byte flips). A body that panics fails
//! the test with the input's name.

mod common;

use std::path::{Path, PathBuf};

use rand_xoshiro::rand_core::{RngCore, SeedableRng};
use rand_xoshiro::SplitMix64;
use rtstream_streaming::{bake, fuzz, read_manifest};

/// Runs `body` on `data`, naming the input on a panic.
fn run(target: &str, name: &str, body: fn(&[u8]), data: &[u8]) {
    let r = std::panic::catch_unwind(|| body(data));
    assert!(
        r.is_ok(),
        "fuzz body `{target}` panicked on {name} ({} bytes)",
        data.len()
    );
}

/// The input, then `n` truncations and `n` single-byte flips of it (SplitMix positions).
fn with_mutations(target: &str, name: &str, body: fn(&[u8]), data: &[u8], n: usize) {
    run(target, name, body, data);
    if data.is_empty() {
        return;
    }
    let mut rng = SplitMix64::seed_from_u64(0x5EED ^ data.len() as u64);
    let mut next = || rng.next_u64();
    for k in 0..n {
        let cut = (next() % data.len() as u64) as usize;
        run(target, &format!("{name} cut at {cut}"), body, &data[..cut]);
        let mut m = data.to_vec();
        let at = (next() % m.len() as u64) as usize;
        m[at] ^= 1 << (k % 8);
        // Also a length-like field gone huge now and then.
        if k % 4 == 0 && at + 4 <= m.len() {
            m[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        }
        run(target, &format!("{name} flip at {at}"), body, &m);
    }
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    v.sort();
    v
}

fn body(target: &str) -> fn(&[u8]) {
    fuzz::TARGETS
        .iter()
        .find(|(n, _)| *n == target)
        .expect("a fuzz target")
        .1
}

#[test]
fn committed_corpus_and_crash_inputs_replay() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut n = 0;
    for (target, body) in fuzz::TARGETS {
        for kind in ["corpus", "artifacts"] {
            for f in files_in(&root.join(kind).join(target)) {
                run(
                    target,
                    &f.display().to_string(),
                    body,
                    &std::fs::read(&f).unwrap(),
                );
                n += 1;
            }
        }
    }
    assert!(n > 0, "the committed corpus is empty");
}

#[test]
fn baked_files_and_their_mutations_never_panic() {
    let (_, dir) = common::baked_small("fuzz-seeds", 4);
    let manifest = read_manifest(&dir).unwrap();
    let read = |p: &Path| std::fs::read(p).unwrap();
    with_mutations(
        "manifest",
        "manifest",
        body("manifest"),
        &read(&dir.join(bake::MANIFEST_FILE)),
        64,
    );
    for f in files_in(&dir.join("levels")).iter().take(6) {
        with_mutations(
            "level",
            &f.display().to_string(),
            body("level"),
            &read(f),
            32,
        );
    }
    let lib = read(&dir.join(bake::MESH_LIBRARY_FILE));
    let mut chunks = 0;
    for (m, mesh) in manifest.meshes.iter().enumerate().take(24) {
        for (l, e) in mesh.lods.iter().enumerate() {
            let chunk = &lib[e.offset as usize..(e.offset + e.len) as usize];
            with_mutations(
                "mesh_lod",
                &format!("mesh {m} LOD {l}"),
                body("mesh_lod"),
                chunk,
                8,
            );
            chunks += 1;
        }
    }
    assert!(chunks > 10);
    let proxies = read(&dir.join(rtstream_streaming::proxy::PROXY_FILE));
    with_mutations("proxies", "proxies.bin", body("proxies"), &proxies, 24);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn debian_gltf_models_and_their_mutations_never_panic() {
    let root = common::assets();
    assert!(root.exists(), "run scripts/setup.sh (assimp-testmodels)");
    let mut stack = vec![root.clone()];
    let mut n = 0;
    while let Some(d) = stack.pop() {
        for p in files_in(&d) {
            if p.is_dir() {
                stack.push(p);
            } else if matches!(p.extension().and_then(|e| e.to_str()), Some("glb" | "gltf")) {
                let data = std::fs::read(&p).unwrap();
                with_mutations("gltf", &p.display().to_string(), body("gltf"), &data, 6);
                n += 1;
            }
        }
    }
    assert!(n >= 40, "{n} glTF files");
}

/// Writes libFuzzer seeds from a small baked world (2x2 levels, so that the proxy file stays
/// small): `FUZZ_SEED_DIR=/tmp/seeds cargo test -p rtstream-streaming --test fuzz_corpus --
/// --ignored export_seeds` fills `<dir>/<target>/` (docs/RELIABILITY.md).
#[test]
#[ignore = "writes seed files; run by hand before fuzzing"]
fn export_seeds() {
    let out = PathBuf::from(std::env::var("FUZZ_SEED_DIR").expect("FUZZ_SEED_DIR"));
    let (_, dir) = common::baked_small("export-seeds", 2);
    let manifest = read_manifest(&dir).unwrap();
    let put = |target: &str, name: &str, data: &[u8]| {
        let d = out.join(target);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join(name), data).unwrap();
    };
    let read = |p: &Path| std::fs::read(p).unwrap();
    put(
        "manifest",
        "seed-manifest",
        &read(&dir.join(bake::MANIFEST_FILE)),
    );
    for (i, l) in manifest.levels.iter().enumerate() {
        put(
            "level",
            &format!("seed-level-{i}"),
            &read(&dir.join(&l.file)),
        );
    }
    let lib = read(&dir.join(bake::MESH_LIBRARY_FILE));
    for (m, mesh) in manifest.meshes.iter().enumerate().take(16) {
        for (l, e) in mesh.lods.iter().enumerate() {
            let chunk = &lib[e.offset as usize..(e.offset + e.len) as usize];
            put("mesh_lod", &format!("seed-mesh-{m}-lod-{l}"), chunk);
        }
    }
    let proxies = read(&dir.join(rtstream_streaming::proxy::PROXY_FILE));
    put("proxies", "seed-proxies", &proxies);
    let _ = std::fs::remove_dir_all(&dir);
}
