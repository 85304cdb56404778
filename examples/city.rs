//! City: the dense preset (ten times the default map's instance density, towers 2x to 8x
//! taller, many small props) walked with each culling mode of the managed policy, culling off
//! included, over the same path in one run. Reports how many TLAS instances culling removes
//! and what that costs in image error against the full-world ground truth; charts TLAS
//! instances against error. Runs on the real backend through the shared driver and sweep code.
//!
//! ```text
//! cargo run --release --example city -- --help
//! cargo run --release --example city -- --deterministic --json
//! ```

#[path = "support/charts.rs"]
mod charts;
#[path = "support/cli.rs"]
mod cli;
#[path = "support/sweep.rs"]
mod sweep;

use rtstream::as_manager::CullMode;
use rtstream::streaming::WorldPreset;
use serde::Serialize;

#[derive(Debug, Serialize)]
struct Mode {
    cull: String,
    tlas_instances_mean: f64,
    culled_mean: f64,
    removed_share: f64,
    peak_blas_mb: f64,
    update_ms_p50: f64,
    #[serde(flatten)]
    figures: cli::PolicyFigures,
}

#[derive(Debug, Serialize)]
struct Summary {
    #[serde(flatten)]
    totals: sweep::Totals,
    instances: usize,
    instances_per_km2: f64,
    default_instances_per_km2: f64,
    modes: Vec<Mode>,
}

fn main() -> anyhow::Result<()> {
    let cli = cli::ExampleCli::<cli::NoFlags>::start(
        "The dense city under each culling mode: TLAS instances removed and the error it costs.",
        "out/city",
    );
    let mut base = sweep::managed_base(&cli.run)?;
    cli.run.use_preset(&mut base, WorldPreset::city());
    let preset = base.preset.clone();
    let km2 = f64::from(preset.size_m).powi(2) / 1e6;
    let density = f64::from(preset.instances) / km2;
    let d = WorldPreset::default_world();
    let default_density = f64::from(d.instances) / (f64::from(d.size_m).powi(2) / 1e6);
    let modes = [
        ("far or small (default)", CullMode::FarOrSmall),
        ("far and small", CullMode::FarAndSmall),
        ("far only", CullMode::Far),
        ("small only", CullMode::Small),
        ("off", CullMode::Off),
    ];
    let points = sweep::points(&base, &modes, |c, (name, mode)| {
        c.managed.cull.mode = *mode;
        format!("cull {name}")
    });
    let ctx = sweep::context(&base)?;
    let world = rtstream::driver::prepare_world(&base.preset, &base.world_dir)?;
    let instances = world.instance_count();
    eprintln!(
        "city: {instances} instances on {km2:.2} km2 ({density:.0}/km2, {:.1}x the default map's {default_density:.0}/km2)",
        density / default_density
    );
    let reports = sweep::run_points(&ctx, &points, cli.output.quiet)?;
    let mut out = Vec::new();
    for ((name, _), r) in modes.iter().zip(&reports) {
        let p = &r.summary.policies[0];
        let rows = cli::managed_rows(&r.rows);
        let tlas = cli::mean(&rows, |x| f64::from(x.tlas_instances));
        let culled = cli::mean(&rows, |x| f64::from(x.culled));
        out.push(Mode {
            cull: (*name).into(),
            tlas_instances_mean: tlas,
            culled_mean: culled,
            removed_share: culled / (tlas + culled).max(1.0),
            peak_blas_mb: p.peak_blas_bytes as f64 / (1 << 20) as f64,
            update_ms_p50: p.update_ms_p50,
            figures: p.into(),
        });
    }
    let summary = Summary {
        totals: sweep::Totals::of(&ctx, &base, &reports),
        instances,
        instances_per_km2: density,
        default_instances_per_km2: default_density,
        modes: out,
    };
    println!(
        "{:<24} {:>10} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9}",
        "culling", "TLAS inst", "culled", "removed", "peak MB", "upd ms", "hit %", "shadow %"
    );
    for m in &summary.modes {
        println!(
            "{:<24} {:>10.0} {:>8.0} {:>7.1}% {:>8.1} {:>8.3} {:>8.2} {:>9.2}",
            m.cull,
            m.tlas_instances_mean,
            m.culled_mean,
            m.removed_share * 100.0,
            m.peak_blas_mb,
            m.update_ms_p50,
            m.figures.hit_mismatch_mean * 100.0,
            m.figures.shadow_mismatch_mean * 100.0
        );
    }
    println!(
        "frames over budget {}; validation messages {}",
        summary.totals.over_budget_frames, summary.totals.validation_messages
    );
    std::fs::create_dir_all(&cli.run.out)?;
    let point = |m: &Mode| charts::Point {
        x: m.tlas_instances_mean,
        y: m.figures.hit_mismatch_mean * 100.0,
        label: m.cull.clone(),
    };
    let files = charts::scatter(
        &cli.run.out.join("culling"),
        "City: TLAS instances against hit mismatch, by culling mode",
        "mean TLAS instances",
        "hit mismatch, %",
        false,
        &[
            charts::Series {
                name: "default culling".into(),
                role: charts::Role::Default,
                points: summary.modes.iter().take(1).map(point).collect(),
            },
            charts::Series {
                name: "other modes".into(),
                role: charts::Role::Sweep,
                points: summary.modes.iter().skip(1).map(point).collect(),
            },
        ],
    )?;
    cli.output.finish(&cli.run.out, "city", &summary, &files)
}
