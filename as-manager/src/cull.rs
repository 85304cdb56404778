//! `InstanceCuller`: TLAS instance culling by distance and projected angle, with hysteresis.
//!
//! Instances behind the camera are not culled for being behind: they cast shadows and show in
//! reflections. Only distance and angular size count, measured from the nearest camera.

use crate::config::{CullConfig, CullMode};

/// Precomputed culling thresholds.
#[derive(Debug, Clone, Copy)]
pub struct InstanceCuller {
    mode: CullMode,
    near: f32,
    far: f32,
    far_back: f32,
    tan2: f32,
    tan2_back: f32,
}

impl InstanceCuller {
    /// From a validated config.
    pub fn new(c: &CullConfig) -> Self {
        let t = c.min_angle.tan();
        let tb = (c.min_angle * (1.0 + c.hysteresis)).min(1.5).tan();
        Self {
            mode: c.mode,
            near: c.near_distance,
            far: c.far_distance,
            far_back: c.far_distance * (1.0 - c.hysteresis),
            tan2: t * t,
            tan2_back: tb * tb,
        }
    }

    /// The projected-angle test alone (for far-field proxies, which live beyond any culling
    /// distance by design): culled when small, unless the mode has no angle test.
    pub fn cull_small(&self, radius: f32, center_dist: f32, was_culled: bool) -> bool {
        let tan2 = if was_culled {
            self.tan2_back
        } else {
            self.tan2
        };
        let small = radius * radius < tan2 * center_dist * center_dist;
        match self.mode {
            CullMode::Off | CullMode::Far => false,
            _ => small,
        }
    }

    /// The centre distance beyond which [`InstanceCuller::cull_small`] culls an instance of
    /// bounding `radius` (infinite when the mode never culls for size).
    pub fn small_beyond(&self, radius: f32, was_culled: bool) -> f32 {
        let tan2 = if was_culled {
            self.tan2_back
        } else {
            self.tan2
        };
        match self.mode {
            CullMode::Off | CullMode::Far => f32::INFINITY,
            _ if tan2 > 0.0 => radius / tan2.sqrt(),
            _ => f32::INFINITY,
        }
    }

    /// Whether to cull an instance of bounding `radius` whose centre is `center_dist` from the
    /// nearest camera; `was_culled` applies the hysteresis (a culled instance needs to be
    /// clearly inside the thresholds to come back).
    ///
    /// ```
    /// use rtstream_as_manager::{config::CullConfig, cull::InstanceCuller};
    /// let c = InstanceCuller::new(&CullConfig::default());
    /// assert!(!c.cull(1.0, 50.0, false));
    /// assert!(c.cull(1.0, 400.0, false));   // far
    /// assert!(c.cull(0.1, 100.0, false));   // small: 0.06 degrees
    /// assert!(!c.cull(0.1, 5.0, false));    // within the near distance
    /// ```
    pub fn cull(&self, radius: f32, center_dist: f32, was_culled: bool) -> bool {
        let surface = (center_dist - radius).max(0.0);
        if surface <= self.near {
            return false;
        }
        let (far_d, tan2) = if was_culled {
            (self.far_back, self.tan2_back)
        } else {
            (self.far, self.tan2)
        };
        let far = surface > far_d;
        let small = radius * radius < tan2 * center_dist * center_dist;
        match self.mode {
            CullMode::FarOrSmall => far || small,
            CullMode::FarAndSmall => far && small,
            CullMode::Far => far,
            CullMode::Small => small,
            CullMode::Off => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hysteresis_band_prevents_flicker() {
        let far = CullConfig {
            mode: CullMode::Far,
            ..CullConfig::default()
        };
        let small = CullConfig {
            min_angle: 1f32.to_radians(),
            ..CullConfig::default()
        };
        // Far: just beyond 300 m culled; coming back needs < 270 m. Small: angular radius 1
        // degree at 57.3 m for r = 1, band up to 1.1 degrees. Each: (distance, culled last
        // frame, culled now) for a sphere of radius 1.
        for (config, cases) in [
            (
                far,
                [
                    (302.0, false, true),
                    (290.0, true, true),
                    (290.0, false, false),
                    (260.0, true, false),
                ],
            ),
            (
                small,
                [
                    (60.0, false, true),
                    (55.0, true, true),
                    (55.0, false, false),
                    (50.0, true, false),
                ],
            ),
        ] {
            let c = InstanceCuller::new(&config);
            for (distance, was, culled) in cases {
                assert_eq!(
                    c.cull(1.0, distance, was),
                    culled,
                    "{:?} at {distance} m, culled before: {was}",
                    config.mode
                );
            }
        }
        let and = InstanceCuller::new(&CullConfig {
            mode: CullMode::FarAndSmall,
            ..CullConfig::default()
        });
        assert!(!and.cull(50.0, 400.0, false), "far but big");
        assert!(and.cull(1.0, 400.0, false));
    }

    /// The projected-angle test alone (what `compare` measures): keeps big and near spheres and
    /// one that contains the eye, and culls more as the angle grows.
    #[test]
    fn small_mode_culls_more_as_the_angle_grows() {
        let small = |deg: f32| {
            InstanceCuller::new(&CullConfig {
                mode: CullMode::Small,
                min_angle: deg.to_radians(),
                near_distance: 0.0,
                hysteresis: 0.0,
                ..CullConfig::default()
            })
        };
        // (radius, centre distance): ~5.7 degrees, ~0.57 degrees, a sphere around the eye.
        let spheres = [(1.0, 10.0), (1.0, 100.0), (0.5, 0.0)];
        let keep = |deg: f32| spheres.map(|(r, d)| !small(deg).cull(r, d, false));
        assert_eq!(keep(0.0), [true, true, true]);
        assert_eq!(keep(1.0), [true, false, true]);
        assert_eq!(keep(10.0), [false, false, true]);
    }
}
