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
    fn hysteresis_holds_lod_in_the_band() {
        let s = LodSelector::new(&LodConfig::default());
        let errors = [0.0, 0.1];
        // distance where LOD 1 projects to exactly 1 px
        let d1 = 0.1 * s.k;
        assert_eq!(
            s.select(&errors, 1.0, d1 * 1.1, 0, 0),
            0,
            "inside band: stays fine"
        );
        assert_eq!(
            s.select(&errors, 1.0, d1 * 1.3, 0, 0),
            1,
            "beyond band: coarsens"
        );
        assert_eq!(
            s.select(&errors, 1.0, d1 * 0.9, 1, 0),
            1,
            "inside band: stays coarse"
        );
        assert_eq!(
            s.select(&errors, 1.0, d1 * 0.7, 1, 0),
            0,
            "beyond band: refines"
        );
        assert_eq!(s.select(&errors, 1.0, 0.0, 0, 1), 1, "floor wins");
    }
}
