//! A rendered frame: colour, per-pixel hit records, PNG output.

use std::path::Path;

use crate::error::{RenderError, Result};

/// One pixel's hit record, as the shader writes it.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PixelHit {
    /// The hit instance's customIndex, or [`PixelHit::MISS`].
    pub instance: u32,
    /// Triangle index within the instance's BLAS, or [`PixelHit::MISS`].
    pub primitive: u32,
    /// Shadow bit: 1 when less than half of the sun disk is visible (the sun is blocked, or the
    /// surface faces away from it), else 0. Always 0 for a miss.
    pub shadowed: u32,
    /// Ray distance as f32 bits (-1.0 for a miss).
    pub t_bits: u32,
}

impl PixelHit {
    /// The `instance`/`primitive` value of a miss.
    pub const MISS: u32 = u32::MAX;

    /// Whether the primary ray hit something.
    pub fn is_hit(&self) -> bool {
        self.instance != Self::MISS
    }

    /// Ray distance (negative for a miss).
    pub fn t(&self) -> f32 {
        f32::from_bits(self.t_bits)
    }
}

/// Per-pass wall times (submit to completion) and ray counts of one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PassStats {
    /// Primary-visibility pass, milliseconds.
    pub primary_ms: f64,
    /// Sun-shadow pass, milliseconds.
    pub shadow_ms: f64,
    /// Ambient-occlusion + shading pass, milliseconds.
    pub ao_shade_ms: f64,
    /// Primary rays traced (one per pixel).
    pub primary_rays: u64,
    /// Shadow rays traced (hits facing the sun x samples toward its disk).
    pub shadow_rays: u64,
    /// Ambient-occlusion rays traced.
    pub ao_rays: u64,
}

impl PassStats {
    /// Rays per second of each pass as (primary, shadow, AO), in millions.
    pub fn mrays_per_s(&self) -> (f64, f64, f64) {
        let rate = |rays: u64, ms: f64| {
            if ms > 0.0 {
                rays as f64 / ms / 1e3
            } else {
                0.0
            }
        };
        (
            rate(self.primary_rays, self.primary_ms),
            rate(self.shadow_rays, self.shadow_ms),
            rate(self.ao_rays, self.ao_shade_ms),
        )
    }
}

/// A rendered frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGBA8 pixels, row-major.
    pub color: Vec<[u8; 4]>,
    /// Per-pixel hit records, row-major.
    pub hits: Vec<PixelHit>,
    /// Per-pixel visible share of the sun disk (0 for misses and surfaces facing away).
    pub sun_visibility: Vec<f32>,
    /// Per-pixel unoccluded share of the hemisphere (1 when AO is off or for misses).
    pub ambient: Vec<f32>,
    /// Per-pixel world-space shading normal of the primary hit, facing the camera (zero for
    /// misses). Geometric metrics use it for the grazing angle.
    pub normals: Vec<[f32; 3]>,
    /// Wall time of all passes (submit to completion), milliseconds.
    pub render_ms: f64,
    /// Per-pass times and ray counts.
    pub passes: PassStats,
}

impl Frame {
    /// Share of pixels whose primary ray hit geometry.
    pub fn hit_fraction(&self) -> f64 {
        self.hits.iter().filter(|h| h.is_hit()).count() as f64 / self.hits.len().max(1) as f64
    }

    /// The shadow mask, row-major: true where the pixel's shadow bit is set.
    pub fn shadow_mask(&self) -> Vec<bool> {
        self.hits.iter().map(|h| h.shadowed != 0).collect()
    }

    /// Writes the colour image as PNG (creating parent directories).
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<()> {
        save_rgba_png(path, self.width, self.height, &self.color)
    }

    /// Writes the hit buffer as a PNG: each instance in its own colour (hashed from its
    /// customIndex), misses black.
    pub fn save_instance_png(&self, path: impl AsRef<Path>) -> Result<()> {
        let px: Vec<[u8; 4]> = self
            .hits
            .iter()
            .map(|h| {
                if !h.is_hit() {
                    return [0, 0, 0, 255];
                }
                let x = h.instance.wrapping_mul(0x9e37_79b9).rotate_left(13) ^ 0x5bd1_e995;
                let x = x.wrapping_mul(0x85eb_ca6b);
                [
                    64 + (x >> 24) as u8 % 192,
                    64 + (x >> 16) as u8 % 192,
                    64 + (x >> 8) as u8 % 192,
                    255,
                ]
            })
            .collect();
        save_rgba_png(path, self.width, self.height, &px)
    }

    /// Writes the shadow mask as a greyscale PNG (white: shadowed, grey: lit, black: miss).
    pub fn save_shadow_png(&self, path: impl AsRef<Path>) -> Result<()> {
        let px: Vec<[u8; 4]> = self
            .hits
            .iter()
            .map(|h| match (h.is_hit(), h.shadowed != 0) {
                (false, _) => [0, 0, 0, 255],
                (true, true) => [255, 255, 255, 255],
                (true, false) => [96, 96, 96, 255],
            })
            .collect();
        save_rgba_png(path, self.width, self.height, &px)
    }
}

/// Places equally sized RGBA8 images side by side with 4-pixel white gaps; returns the total
/// width and the pixels (row-major).
pub fn side_by_side(width: u32, height: u32, images: &[&[[u8; 4]]]) -> (u32, Vec<[u8; 4]>) {
    const GAP: u32 = 4;
    let n = images.len().max(1) as u32;
    let total = width * n + GAP * (n - 1);
    let mut out = vec![[255u8; 4]; (total * height) as usize];
    for (k, img) in images.iter().enumerate() {
        let x0 = k as u32 * (width + GAP);
        for y in 0..height {
            let src = &img[(y * width) as usize..((y + 1) * width) as usize];
            let at = (y * total + x0) as usize;
            out[at..at + width as usize].copy_from_slice(src);
        }
    }
    (total, out)
}

/// Writes RGBA8 pixels (row-major) as a PNG, creating parent directories.
pub fn save_rgba_png(
    path: impl AsRef<Path>,
    width: u32,
    height: u32,
    pixels: &[[u8; 4]],
) -> Result<()> {
    let path = path.as_ref();
    let err = |source| RenderError::Image {
        path: path.to_owned(),
        source,
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| err(image::ImageError::IoError(e)))?;
    }
    image::save_buffer(
        path,
        bytemuck::cast_slice(pixels),
        width,
        height,
        image::ColorType::Rgba8,
    )
    .map_err(err)
}
