//! Generation time of the default world and its description size per instance.
//!
//! `cargo bench -p rtstream-streaming --bench generate` prints criterion's timing of
//! `generate(default_world)` plus one line with the world's figures (instances, levels, bytes per
//! instance, mesh bytes) and one-shot timings of baking it and of generating the 16 km preset
//! (set `RTSTREAM_BENCH_LARGE=0` to skip the latter).

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion};
use rtstream_streaming::{bake, generate, WorldPreset};

fn figures() {
    let preset = WorldPreset::default_world();
    let t = Instant::now();
    let world = match generate(&preset) {
        Ok(w) => w,
        Err(e) => {
            eprintln!("cannot generate the default world: {e}");
            return;
        }
    };
    let gen = t.elapsed();
    let s = world.stats();
    println!(
        "default world: {} levels, {} instances ({} non-opaque = {:.1}%, {} skinned), {} meshes, \
         {} LOD triangles; generated in {:.3} s (one-shot); description {} bytes = {:.1} bytes/instance; \
         mesh data {:.1} MiB",
        s.levels,
        s.instances,
        s.non_opaque,
        100.0 * s.non_opaque as f64 / s.instances as f64,
        s.skinned,
        s.meshes,
        s.mesh_triangles,
        gen.as_secs_f64(),
        world.description_bytes(),
        world.bytes_per_instance(),
        world.mesh_bytes() as f64 / (1 << 20) as f64,
    );
    let dir = std::env::temp_dir().join(format!("rtstream-bench-{}", std::process::id()));
    let t = Instant::now();
    match bake(&world, &dir) {
        Ok(r) => println!(
            "baked: {} level files, {:.1} MiB levels ({:.1} bytes/instance on disk), {:.1} MiB mesh library in {:.3} s",
            r.level_files,
            r.level_bytes as f64 / (1 << 20) as f64,
            r.level_bytes as f64 / s.instances as f64,
            r.mesh_library_bytes as f64 / (1 << 20) as f64,
            t.elapsed().as_secs_f64()
        ),
        Err(e) => eprintln!("bake failed: {e}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
    if std::env::var("RTSTREAM_BENCH_LARGE").as_deref() != Ok("0") {
        let t = Instant::now();
        match generate(&WorldPreset::large_world()) {
            Ok(w) => println!(
                "large world: {} levels, {} instances in {:.3} s (one-shot), {:.1} bytes/instance",
                w.levels.len(),
                w.instance_count(),
                t.elapsed().as_secs_f64(),
                w.bytes_per_instance()
            ),
            Err(e) => eprintln!("cannot generate the large world: {e}"),
        }
    }
}

fn bench(c: &mut Criterion) {
    figures();
    let preset = WorldPreset::default_world();
    let mut group = c.benchmark_group("generate");
    group.sample_size(10);
    group.bench_function("default_world", |b| {
        b.iter(|| black_box(generate(black_box(&preset))))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
