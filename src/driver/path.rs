//! The camera path of a run: seeded, deterministic, across the map.

use glam::Vec3;
use rand_xoshiro::rand_core::{RngCore, SeedableRng};
use rand_xoshiro::SplitMix64;
use rtstream_streaming::{Aabb, Manifest};

/// A fly-through path: an S along one of the map's diagonals at driving speed, a few metres
/// above what stands in the level under the camera (smoothed). The seed picks the diagonal,
/// its direction and the S's phase and amplitude; seed 0x5EED is the documented default run.
#[derive(Debug, Clone)]
pub struct CameraPath {
    extent: Aabb,
    flip_x: bool,
    flip_z: bool,
    phase: f32,
    amplitude: f32,
    /// (XZ bounds, top) of every level, to fly above it.
    tops: Vec<(Aabb, f32)>,
    altitude: Option<f32>,
}

/// A camera for one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathPoint {
    /// Eye position.
    pub position: Vec3,
    /// Horizontal direction of travel.
    pub forward: Vec3,
    /// View direction (forward, tilted down a little).
    pub look: Vec3,
}

impl CameraPath {
    /// A path over `manifest`'s map for `seed`.
    pub fn new(manifest: &Manifest, seed: u64) -> Self {
        // The seed scrambled into a few independent choices: SplitMix64's first output (the
        // same bits as the hand-written scramble this replaced, so paths did not move).
        let h = SplitMix64::seed_from_u64(seed).next_u64();
        let unit = |shift: u32| ((h >> shift) & 0xffff) as f32 / 65535.0;
        let default_run = seed == 0x5EED;
        Self {
            extent: manifest.extent,
            flip_x: !default_run && h & 1 == 1,
            flip_z: !default_run && h & 2 == 2,
            phase: if default_run {
                0.0
            } else {
                unit(8) * std::f32::consts::TAU
            },
            amplitude: if default_run {
                0.08
            } else {
                0.04 + 0.06 * unit(24)
            },
            tops: manifest
                .levels
                .iter()
                .map(|l| (l.bounds, l.bounds.max.y))
                .collect(),
            altitude: None,
        }
    }

    fn ground(&self, t: f32) -> Vec3 {
        let (min, max) = (self.extent.min, self.extent.max);
        let s = max - min;
        let u = 0.08 + 0.84 * t;
        let x = if self.flip_x { 1.0 - u } else { u };
        let z = u + self.amplitude * (t * std::f32::consts::TAU + self.phase).sin();
        let z = if self.flip_z { 1.0 - z } else { z };
        Vec3::new(min.x + s.x * x, 1.8, min.z + s.z * z)
    }

    /// The camera at `frame` of `frames`. Call in frame order: the altitude is smoothed.
    pub fn at(&mut self, frame: u64, frames: u64) -> PathPoint {
        self.at_fraction(frame as f32 / frames.max(1) as f32)
    }

    /// The camera at fraction `t` (0..1) of the path. Call with increasing `t`: the altitude
    /// is smoothed.
    pub fn at_fraction(&mut self, t: f32) -> PathPoint {
        let p = self.ground(t);
        let ahead = self.ground((t + 0.01).min(1.0)) - p;
        let forward = Vec3::new(ahead.x, 0.0, ahead.z).normalize_or(Vec3::Z);
        let top = self
            .tops
            .iter()
            .find(|(b, _)| b.min.x <= p.x && p.x <= b.max.x && b.min.z <= p.z && p.z <= b.max.z)
            .map_or(p.y, |(_, top)| top + 4.0);
        let y = self
            .altitude
            .map_or(top, |a| a + (top - a) * 0.05)
            .max(top - 6.0);
        self.altitude = Some(y);
        let position = Vec3::new(p.x, y, p.z);
        let look = (forward * 10.0 - Vec3::Y * 3.0).normalize();
        PathPoint {
            position,
            forward,
            look,
        }
    }
}
