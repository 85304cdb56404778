//! Pinhole camera and primary-ray generation (the same formula as `shaders/common.glsl`).

use glam::Vec3;

/// A pinhole camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Eye position (world space).
    pub position: Vec3,
    /// Unit view direction.
    pub forward: Vec3,
    /// Approximate up direction (made orthogonal to `forward`).
    pub up: Vec3,
    /// Vertical field of view in radians.
    pub fov_y: f32,
}

impl Camera {
    /// A camera at `eye` looking at `target`, Y up.
    pub fn look_at(eye: Vec3, target: Vec3, fov_y: f32) -> Self {
        let forward = (target - eye).normalize_or(Vec3::NEG_Z);
        Self {
            position: eye,
            forward,
            up: Vec3::Y,
            fov_y,
        }
    }

    /// Orthonormal (right, up, forward).
    pub fn basis(&self) -> (Vec3, Vec3, Vec3) {
        let f = self.forward.normalize_or(Vec3::NEG_Z);
        let mut r = f.cross(self.up);
        if r.length_squared() < 1e-12 {
            r = f.cross(Vec3::Z);
        }
        let r = r.normalize();
        (r, r.cross(f), f)
    }

    /// Origin and unit direction of the primary ray through pixel (x, y)'s centre.
    pub fn primary_ray(&self, x: u32, y: u32, width: u32, height: u32) -> (Vec3, Vec3) {
        let (r, u, f) = self.basis();
        let t = (self.fov_y * 0.5).tan();
        let aspect = width as f32 / height as f32;
        let nx = (x as f32 + 0.5) / width as f32 * 2.0 - 1.0;
        let ny = -((y as f32 + 0.5) / height as f32 * 2.0 - 1.0);
        let d = (f + r * (nx * t * aspect) + u * (ny * t)).normalize();
        (self.position, d)
    }

    /// Frames an axis-aligned box: looks at its centre from direction `from` (need not be unit),
    /// far enough that the bounding sphere fills the view.
    pub fn framing(min: Vec3, max: Vec3, from: Vec3, fov_y: f32) -> Self {
        let c = (min + max) * 0.5;
        let radius = ((max - min) * 0.5).length().max(1e-3);
        let dist = radius / (fov_y * 0.5).sin();
        Self::look_at(c + from.normalize_or(Vec3::Z) * dist, c, fov_y)
    }
}
