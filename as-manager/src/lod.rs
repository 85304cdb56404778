//! `LodSelector`: LOD by projected geometric error, with hysteresis.

use crate::config::LodConfig;

/// Projects geometric errors to pixels and picks LODs.
#[derive(Debug, Clone, Copy)]
pub struct LodSelector {
    /// Pixels per world unit at distance 1: `screen_height / (2 tan(fov / 2))`.
    k: f32,
    threshold: f32,
    coarsen_below: f32,
    refine_above: f32,
}

impl LodSelector {
    /// From a validated config.
    pub fn new(c: &LodConfig) -> Self {
        Self {
            k: c.screen_height_px / (2.0 * (c.vertical_fov * 0.5).tan()),
            threshold: c.max_pixel_error,
            coarsen_below: c.max_pixel_error / (1.0 + c.hysteresis),
            refine_above: c.max_pixel_error * (1.0 + c.hysteresis),
        }
    }

    /// Pixel error of a world-space error at `distance` (to the bounding sphere).
    pub fn pixels(&self, world_error: f32, distance: f32) -> f32 {
        world_error * self.k / distance.max(1e-3)
    }

    fn coarsest_within(&self, errors: &[f32], scale: f32, distance: f32, limit: f32) -> usize {
        // pixels(e * scale, d) <= limit without a division per LOD
        let rhs = limit * distance.max(1e-3);
        let ks = self.k * scale;
        let mut best = 0;
        for (i, &e) in errors.iter().enumerate() {
            if e * ks <= rhs {
                best = i;
            } else {
                break;
            }
        }
        best
    }

    /// The distances between which [`LodSelector::select`] (from `current`, the floor fixed)
    /// answers as it does at `distance`: the nearest switch point below it (`-inf`: none) and
    /// the nearest above it (`inf`: none). An incremental caller looks again only once the
    /// distance may have left it. Needs non-decreasing errors (`MeshDesc::validate`).
    pub fn stable_band(
        &self,
        errors: &[f32],
        scale: f32,
        current: usize,
        distance: f32,
    ) -> (f32, f32) {
        let current = current.min(errors.len() - 1);
        let ks = self.k * scale;
        let (mut below, mut above) = (f32::NEG_INFINITY, f32::INFINITY);
        let mut switch_at = |e: f32, limit: f32| {
            let at = e * ks / limit;
            if at <= distance {
                below = below.max(at);
            }
            if at >= distance {
                above = above.min(at);
            }
        };
        // Coarser: coarsest_within(coarsen_below) steps at each coarser error.
        for &e in &errors[current + 1..] {
            switch_at(e, self.coarsen_below);
        }
        // Finer below errors[current] / refine_above; there, coarsest_within(threshold)
        // steps at each finer error.
        switch_at(errors[current], self.refine_above);
        if errors[current] * ks > self.refine_above * distance {
            for &e in &errors[1..=current] {
                switch_at(e, self.threshold);
            }
        }
        (below, above)
    }

    /// The LOD for an instance now at `current`, `errors` finest first (mesh space), `scale`
    /// the instance's largest scale, `floor` the finest LOD allowed (memory fallback).
    ///
    /// ```
    /// use rtstream_as_manager::{config::LodConfig, lod::LodSelector};
    /// let s = LodSelector::new(&LodConfig::default());
    /// let errors = [0.0, 0.01, 0.04, 0.16];
    /// assert_eq!(s.select(&errors, 1.0, 1.0, 0, 0), 0);
    /// assert_eq!(s.select(&errors, 1.0, 10_000.0, 0, 0), 3);
    /// ```
    pub fn select(
        &self,
        errors: &[f32],
        scale: f32,
        distance: f32,
        current: usize,
        floor: usize,
    ) -> usize {
        let current = current.min(errors.len() - 1);
        let coarser = self.coarsest_within(errors, scale, distance, self.coarsen_below);
        let lod = if coarser > current {
            coarser
        } else if errors[current] * self.k * scale > self.refine_above * distance.max(1e-3) {
            self.coarsest_within(errors, scale, distance, self.threshold)
        } else {
            current
        };
        lod.max(floor).min(errors.len() - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn select_is_constant_within_its_stable_band() {
        let s = LodSelector::new(&LodConfig::default());
        let errors = [0.0, 0.02, 0.1, 0.5, 2.0];
        let mut checked = 0;
        for scale in [0.5f32, 1.0, 3.0] {
            for current in 0..errors.len() {
                for floor in 0..=current {
                    for i in 1..400 {
                        let d = 1.02f32.powi(i * 2);
                        let r = s.select(&errors, scale, d, current, floor);
                        let (lo, hi) = s.stable_band(&errors, scale, current, d);
                        assert!(lo <= d && d <= hi, "{lo} {d} {hi}");
                        let (lo, hi) = (lo.max(0.0), hi.min(1e6));
                        for t in [0.001f32, 0.1, 0.5, 0.9, 0.999] {
                            for d2 in [d + t * (lo - d), d + t * (hi - d)] {
                                assert_eq!(
                                    s.select(&errors, scale, d2, current, floor),
                                    r,
                                    "current {current} floor {floor} scale {scale}: {d} -> {d2} (band {lo}..{hi})"
                                );
                                checked += 1;
                            }
                        }
                    }
                }
            }
        }
        assert!(checked > 10_000);
        // Just past a known switch the answer changes: from LOD 1, coarsening to 2 at
        // 0.1 * k / coarsen_below.
        let at = 0.1 * s.k / s.coarsen_below;
        let (_, hi) = s.stable_band(&errors, 1.0, 1, at * 0.9);
        assert!((hi - at).abs() < 1e-3 * at, "{hi} vs {at}");
        assert_eq!(s.select(&errors, 1.0, at * 1.001, 1, 0), 2);
    }

    #[test]
    fn hysteresis_holds_lod_in_the_band() {
        let s = LodSelector::new(&LodConfig::default());
        let errors = [0.0, 0.1];
        // distance where LOD 1 projects to exactly 1 px
        let d1 = 0.1 * s.k;
        // (distance / d1, current LOD, selected LOD)
        for (at, current, selected, why) in [
            (1.1, 0, 0, "inside band: stays fine"),
            (1.3, 0, 1, "beyond band: coarsens"),
            (0.9, 1, 1, "inside band: stays coarse"),
            (0.7, 1, 0, "beyond band: refines"),
        ] {
            assert_eq!(
                s.select(&errors, 1.0, d1 * at, current, 0),
                selected,
                "{why}"
            );
        }
        assert_eq!(s.select(&errors, 1.0, 0.0, 0, 1), 1, "floor wins");
    }
}
