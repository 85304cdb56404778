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
    /// 1 when the sun is blocked (or the surface faces away from it), else 0.
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
    /// Wall time of the dispatch (submit to completion), milliseconds.
    pub render_ms: f64,
}

impl Frame {
    /// Share of pixels whose primary ray hit geometry.
    pub fn hit_fraction(&self) -> f64 {
        self.hits.iter().filter(|h| h.is_hit()).count() as f64 / self.hits.len().max(1) as f64
    }

    /// Writes the colour image as PNG (creating parent directories).
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<()> {
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
            bytemuck::cast_slice(&self.color),
            self.width,
            self.height,
            image::ColorType::Rgba8,
        )
        .map_err(err)
    }
}
