//! Image-difference metrics between a managed frame and its reference (pure Rust).
//!
//! - **Primary-hit mismatch**: share of pixels whose primary hit *instance* differs (a miss is its
//!   own "instance"). Instance identity, not primitive: a hit on a coarser LOD of the same
//!   instance is a match.
//! - **Shadow mismatch**: share of pixels whose shadow bit differs.
//! - **Colour error**: RMSE over the RGB channels scaled to [0, 1], and PSNR in dB
//!   (`f64::INFINITY` for identical images).

use crate::error::{RenderError, Result};
use crate::frame::{Frame, PixelHit};

/// How far a managed frame is from its reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameMetrics {
    /// Pixels compared.
    pub pixels: u64,
    /// Share of pixels whose primary-hit instance differs (0..=1).
    pub primary_mismatch: f64,
    /// Share of pixels whose shadow bit differs (0..=1).
    pub shadow_mismatch: f64,
    /// RMSE of the RGB channels in [0, 1].
    pub color_rmse: f64,
    /// Peak signal-to-noise ratio in dB (peak 1.0); infinite when the colours are identical.
    pub psnr_db: f64,
}

impl From<FrameMetrics> for rtstream_as_manager::ImageError {
    fn from(m: FrameMetrics) -> Self {
        Self {
            primary_mismatch: m.primary_mismatch,
            shadow_mismatch: m.shadow_mismatch,
            color_rmse: m.color_rmse,
            psnr_db: m.psnr_db,
        }
    }
}

impl FrameMetrics {
    /// Compares two frames whose customIndex values name the same instances (e.g. both TLASes
    /// were built with the instance's stable id as customIndex).
    pub fn compare(managed: &Frame, reference: &Frame) -> Result<Self> {
        Self::compare_mapped(managed, reference, |c| c, |c| c)
    }

    /// Compares two frames whose TLASes number instances differently: `managed_id` and
    /// `reference_id` map each frame's customIndex to a stable instance id (e.g. the manager's
    /// slot to the world's instance id; every LOD of an instance maps to the same id).
    pub fn compare_mapped(
        managed: &Frame,
        reference: &Frame,
        managed_id: impl Fn(u32) -> u32,
        reference_id: impl Fn(u32) -> u32,
    ) -> Result<Self> {
        check_sizes(managed, reference)?;
        let n = managed.hits.len();
        let id = |h: &PixelHit, f: &dyn Fn(u32) -> u32| h.is_hit().then(|| f(h.instance));
        let mut primary = 0u64;
        let mut shadow = 0u64;
        for (m, r) in managed.hits.iter().zip(&reference.hits) {
            if id(m, &managed_id) != id(r, &reference_id) {
                primary += 1;
            }
            if (m.shadowed != 0) != (r.shadowed != 0) {
                shadow += 1;
            }
        }
        let rmse = color_rmse(&managed.color, &reference.color);
        Ok(Self {
            pixels: n as u64,
            primary_mismatch: primary as f64 / n.max(1) as f64,
            shadow_mismatch: shadow as f64 / n.max(1) as f64,
            color_rmse: rmse,
            psnr_db: psnr(rmse),
        })
    }

    /// Whether the frames are identical by every metric.
    pub fn is_exact(&self) -> bool {
        self.primary_mismatch == 0.0 && self.shadow_mismatch == 0.0 && self.color_rmse == 0.0
    }
}

fn check_sizes(a: &Frame, b: &Frame) -> Result<()> {
    let n = a.width as usize * a.height as usize;
    if a.width != b.width
        || a.height != b.height
        || a.hits.len() != n
        || b.hits.len() != n
        || a.color.len() != n
        || b.color.len() != n
    {
        return Err(RenderError::FrameMismatch(
            a.width, a.height, b.width, b.height,
        ));
    }
    Ok(())
}

/// RMSE of the RGB channels of two equally long RGBA8 images, in [0, 1] units.
pub fn color_rmse(a: &[[u8; 4]], b: &[[u8; 4]]) -> f64 {
    let n = a.len().min(b.len());
    if n == 0 {
        return 0.0;
    }
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| {
            (0..3)
                .map(|c| {
                    let d = (f64::from(p[c]) - f64::from(q[c])) / 255.0;
                    d * d
                })
                .sum::<f64>()
        })
        .sum();
    (sum / (3 * n) as f64).sqrt()
}

/// PSNR in dB for an RMSE in [0, 1] units (peak 1.0); infinite for 0.
pub fn psnr(rmse: f64) -> f64 {
    if rmse <= 0.0 {
        f64::INFINITY
    } else {
        -20.0 * rmse.log10()
    }
}

/// A picture of where two frames differ: red where the primary-hit instance differs, yellow where
/// only the shadow bit differs, elsewhere the colour difference amplified 4x over a dimmed copy
/// of the reference.
pub fn difference_image(managed: &Frame, reference: &Frame) -> Result<Vec<[u8; 4]>> {
    check_sizes(managed, reference)?;
    Ok(managed
        .hits
        .iter()
        .zip(&reference.hits)
        .zip(managed.color.iter().zip(&reference.color))
        .map(|((m, r), (mc, rc))| {
            let same_instance =
                m.is_hit() == r.is_hit() && (!m.is_hit() || m.instance == r.instance);
            if !same_instance {
                [255, 0, 0, 255]
            } else if (m.shadowed != 0) != (r.shadowed != 0) {
                [255, 220, 0, 255]
            } else {
                let mut out = [0u8, 0, 0, 255];
                for c in 0..3 {
                    let d = (i32::from(mc[c]) - i32::from(rc[c])).unsigned_abs() * 4;
                    out[c] = (u32::from(rc[c]) / 4 + d).min(255) as u8;
                }
                out
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::PassStats;

    fn frame(hits: &[(u32, u32)], colors: &[u8]) -> Frame {
        let n = hits.len();
        Frame {
            width: n as u32,
            height: 1,
            color: colors.iter().map(|&c| [c, c, c, 255]).collect(),
            hits: hits
                .iter()
                .map(|&(instance, shadowed)| PixelHit {
                    instance,
                    primitive: if instance == PixelHit::MISS {
                        PixelHit::MISS
                    } else {
                        0
                    },
                    shadowed,
                    t_bits: 1.0f32.to_bits(),
                })
                .collect(),
            sun_visibility: vec![1.0; n],
            ambient: vec![1.0; n],
            normals: vec![[0.0, 1.0, 0.0]; n],
            render_ms: 0.0,
            passes: PassStats::default(),
        }
    }

    #[test]
    fn identical_frames_have_zero_error() {
        let a = frame(
            &[(0, 0), (1, 1), (PixelHit::MISS, 0), (2, 0)],
            &[10, 20, 30, 40],
        );
        let m = FrameMetrics::compare(&a, &a.clone()).unwrap();
        assert!(m.is_exact(), "{m:?}");
        assert_eq!(m.psnr_db, f64::INFINITY);
        assert_eq!(m.pixels, 4);
    }

    #[test]
    fn counts_instance_and_shadow_mismatches() {
        let r = frame(
            &[(0, 0), (1, 1), (PixelHit::MISS, 0), (2, 0)],
            &[0, 0, 0, 0],
        );
        // Pixel 1: a different primitive of the same instance (a coarser LOD) is a match, but
        // its shadow bit differs. Pixel 2: a hit where the reference missed. Pixel 3: same.
        let mut m = frame(&[(0, 0), (1, 0), (5, 0), (2, 0)], &[0, 0, 0, 0]);
        m.hits[1].primitive = 77;
        let x = FrameMetrics::compare(&m, &r).unwrap();
        assert_eq!(x.primary_mismatch, 0.25);
        assert_eq!(x.shadow_mismatch, 0.25);
        assert_eq!(x.color_rmse, 0.0);
    }

    #[test]
    fn mapped_ids_compare_instances_not_custom_indices() {
        let r = frame(&[(10, 0), (11, 0)], &[0, 0]);
        let m = frame(&[(0, 0), (2, 0)], &[0, 0]);
        // The managed TLAS numbers instance 10 as 0 and instance 11 as 1 (2 is some other one).
        let x = FrameMetrics::compare_mapped(&m, &r, |c| c + 10, |c| c).unwrap();
        assert_eq!(x.primary_mismatch, 0.5);
    }

    #[test]
    fn rmse_and_psnr_follow_the_definitions() {
        let a = frame(&[(0, 0), (0, 0)], &[0, 0]);
        let b = frame(&[(0, 0), (0, 0)], &[255, 0]);
        let x = FrameMetrics::compare(&a, &b).unwrap();
        assert!((x.color_rmse - 0.5f64.sqrt()).abs() < 1e-12);
        assert!((x.psnr_db - 3.0103).abs() < 1e-3, "{}", x.psnr_db);
        // More difference, lower PSNR.
        let c = frame(&[(0, 0), (0, 0)], &[255, 255]);
        let y = FrameMetrics::compare(&a, &c).unwrap();
        assert!(y.color_rmse > x.color_rmse && y.psnr_db < x.psnr_db);
        assert_eq!(y.psnr_db, 0.0);
    }

    #[test]
    fn size_mismatch_is_an_error() {
        let a = frame(&[(0, 0)], &[0]);
        let b = frame(&[(0, 0), (0, 0)], &[0, 0]);
        assert!(matches!(
            FrameMetrics::compare(&a, &b),
            Err(RenderError::FrameMismatch(..))
        ));
        assert!(difference_image(&a, &b).is_err());
    }

    #[test]
    fn difference_image_marks_each_kind() {
        let r = frame(&[(0, 0), (1, 1), (2, 0)], &[100, 100, 100]);
        let m = frame(&[(9, 0), (1, 0), (2, 0)], &[100, 100, 110]);
        let d = difference_image(&m, &r).unwrap();
        assert_eq!(d[0], [255, 0, 0, 255]);
        assert_eq!(d[1], [255, 220, 0, 255]);
        assert_eq!(d[2], [25 + 40, 25 + 40, 25 + 40, 255]);
    }
}
