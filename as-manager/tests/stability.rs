//! Where a method fails and that the policy holds there.
//!
//! 1. r1 == r2 with zero thresholds: a camera oscillating across the radius makes
//!    `SeedR1R2` create and destroy a BLAS every other frame; the `Managed` defaults (r2 > r1,
//!    thresholds, minimum life) build once.
//! 2. Extreme skinned deformation: refits degrade the hierarchy; the measured quality ratio
//!    triggers rebuilds and stays within the configured bound; mild motion only refits.

use std::sync::Arc;

use glam::{Affine3A, Vec3};
use rtstream_as_manager::backend::model::ModelBackend;
use rtstream_as_manager::synth::{counts_chain, grid_geometry};
use rtstream_as_manager::*;

use rtstream_as_manager as rtm;
mod harness;

/// Runs frame `frame` seen from `cam` and returns its statistics.
fn frame_stats(m: &mut AsManager<ModelBackend>, frame: u64, cam: Viewpoint) -> FrameStats {
    harness::update_from(m, frame, cam).unwrap().stats.clone()
}

fn oscillate(config: Config, frames: u64) -> (u64, u64) {
    let r = config.residency.r1;
    let mut m = AsManager::new(config, ModelBackend::lavapipe()).unwrap();
    let mesh = m
        .register_mesh(MeshDesc::new(
            "rock",
            MeshKind::Static,
            1.0,
            counts_chain(2000, 1, 0.0),
        ))
        .unwrap();
    m.add_instance(InstanceDesc::new(mesh, Affine3A::IDENTITY))
        .unwrap();
    let (mut builds, mut releases) = (0, 0);
    for f in 0..frames {
        // approach (10 frames well inside r1), then the distance to the bounding sphere
        // alternates r - 0.5 and r + 0.5
        let d = if f < 10 {
            r - 10.0
        } else {
            1.0 + r + if f % 2 == 0 { -0.5 } else { 0.5 }
        };
        let s = frame_stats(&mut m, f, Viewpoint::new(Vec3::new(d, 0.0, 0.0), -Vec3::X));
        builds += s.builds as u64;
        releases += s.releases as u64;
    }
    (builds, releases)
}

#[test]
fn r1_equals_r2_zero_thresholds_thrashes_seed_not_managed() {
    let frames = 200;
    let mut seed = Config::seed_r1r2();
    seed.residency.r1 = 100.0;
    seed.residency.r2 = 100.0;
    seed.residency.create_threshold = 0;
    seed.residency.release_threshold = 0;
    let (b, r) = oscillate(seed.clone(), frames);
    eprintln!(
        "oscillation across r1 +-0.5 m, {frames} frames: seed (r1 == r2, thresholds 0) {:.0} creates + destroys per 100 frames",
        (b + r) as f64 * 100.0 / frames as f64
    );
    // a create and a destroy every two frames once oscillating
    assert!(
        b >= (frames - 10) / 2 && r >= (frames - 10) / 2 - 1,
        "seed: {b} builds, {r} releases"
    );

    let mut managed = Config::default();
    managed.residency.r1 = 100.0;
    let (b, r) = oscillate(managed, frames);
    eprintln!("  managed defaults: {b} creates, {r} destroys in {frames} frames");
    assert_eq!((b, r), (1, 0), "managed defaults");

    // Even with the seed's degenerate parameters the managed policy's minimum life bounds it.
    let degenerate = Config {
        policy: PolicyKind::Managed,
        ..seed
    };
    let (b, r) = oscillate(degenerate.clone(), frames);
    let bound = frames / (degenerate.residency.min_resident_frames as u64 + 1) + 1;
    eprintln!(
        "  managed with the seed's radii and thresholds: {:.1} creates + destroys per 100 frames (bound {bound} each per {frames})",
        (b + r) as f64 * 100.0 / frames as f64
    );
    assert!(
        b <= bound && r <= bound,
        "managed degenerate: {b} builds, {r} releases, bound {bound}"
    );
}

#[test]
fn extreme_skinned_deformation_triggers_rebuilds_within_bound() {
    let config = Config::default();
    let bound = config.build.rebuild_quality_bound;
    let mut m = AsManager::new(config, ModelBackend::lavapipe()).unwrap();
    let geo = grid_geometry(24, 2.0);
    let mesh = harness::one_lod_mesh(&m, "cloth", MeshKind::Skinned, 2.0, geo.clone());
    let id = harness::place(&m, mesh, Vec3::new(0.0, 0.0, 10.0), 0);
    let mut frame = 0;
    let mut step = |m: &mut AsManager<ModelBackend>| {
        frame += 1;
        frame_stats(m, frame - 1, Viewpoint::new(Vec3::ZERO, Vec3::Z))
    };
    for _ in 0..3 {
        step(&mut m);
    }
    // Mild motion (a travelling wave): refits only.
    let (mut refits, mut rebuilds) = (0, 0);
    for k in 0..60 {
        let t = k as f32 * 0.1;
        let p: Vec<[f32; 3]> = geo
            .positions
            .iter()
            .map(|v| [v[0], 0.1 * (v[0] * 4.0 + t).sin(), v[2]])
            .collect();
        m.set_skinned_pose(id, Arc::new(p)).unwrap();
        let s = step(&mut m);
        refits += s.refits;
        rebuilds += s.rebuilds;
        assert!(s.worst_refit_quality <= bound);
    }
    eprintln!("skinned, mild wave, 60 frames: {refits} refits, {rebuilds} rebuilds");
    assert_eq!((refits, rebuilds), (60, 0));
    // Extreme: vertices progressively swirl around the centre by an angle growing with
    // distance (triangles stretch across the mesh).
    let (mut refits, mut rebuilds, mut worst) = (0, 0, 1.0f32);
    for k in 0..60 {
        let twist = k as f32 * 0.15;
        let p: Vec<[f32; 3]> = geo
            .positions
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let a = twist * (1.0 + (i % 7) as f32);
                let (s, c) = a.sin_cos();
                [
                    v[0] * c - v[2] * s,
                    0.3 * ((i % 5) as f32) * (k as f32 * 0.05),
                    v[0] * s + v[2] * c,
                ]
            })
            .collect();
        m.set_skinned_pose(id, Arc::new(p)).unwrap();
        let s = step(&mut m);
        refits += s.refits;
        rebuilds += s.rebuilds;
        worst = worst.max(s.worst_refit_quality);
        assert!(
            s.worst_refit_quality <= bound,
            "quality {} over bound {bound}",
            s.worst_refit_quality
        );
    }
    eprintln!(
        "skinned, extreme swirl, 60 frames: {refits} refits, {rebuilds} rebuilds, worst refit quality {worst:.2} (bound {bound})"
    );
    assert!(
        rebuilds >= 3,
        "extreme deformation must trigger rebuilds: {rebuilds}"
    );
    assert!(refits > 0, "and not every frame needs one: {refits} refits");
    assert_eq!(m.backend().counters().rebuilds, rebuilds as u64);
}
