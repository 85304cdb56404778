//! Scoring a frame against the ground truth (pure Rust over two [`Frame`]s).
//!
//! - **Geometric primary mismatch** (the headline): hit versus miss differs, or both hit and
//!   the ray distances differ by more than the larger of 1% and the pixel's footprint at the
//!   reference distance divided by the grazing factor (|cos θ| of the reference surface,
//!   floored at 0.1). A coarser LOD on grazing terrain, or a proxy standing for many
//!   instances, is not wrong where it is in the right place.
//! - **Identity mismatch**: the hit's world instance differs (a proxy has no instance, so it
//!   always counts here). Reported beside, never the headline.
//! - **Shadow mismatch**: over pixels whose primary hit agrees geometrically, the share whose
//!   shadow bit differs.
//! - **AO difference**: mean absolute difference of the unoccluded share over those pixels.
//! - **PSNR** over the colours (both images use the same per-mesh colours).
//! - Everything split by the distance band of the reference hit (the managed hit where the
//!   reference misses; pixels where both miss belong to no band).

use rtstream_renderer::metrics::{color_rmse, psnr};
use rtstream_renderer::{Camera, Frame};
use serde::Serialize;

/// Distance bands: `[0, e0)`, `[e0, e1)`, `[e1, e2)`, `[e2, ∞)` metres of ray distance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BandEdges(pub [f32; 3]);

impl BandEdges {
    /// 0–r1, r1–r2, r2–1 km, beyond.
    pub fn new(r1: f32, r2: f32) -> Self {
        Self([r1, r2, 1000f32.max(r2)])
    }

    /// Band index of a distance.
    pub fn band(&self, t: f32) -> usize {
        self.0.iter().take_while(|&&e| t >= e).count()
    }

    /// Names of the four bands, e.g. "0-200m".
    pub fn names(&self) -> [String; 4] {
        let [a, b, c] = self.0;
        [
            format!("0-{a:.0}m"),
            format!("{a:.0}-{b:.0}m"),
            format!("{b:.0}-{c:.0}m"),
            format!(">{c:.0}m"),
        ]
    }
}

/// Counts of one distance band of one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct BandCounts {
    /// Pixels in the band.
    pub pixels: u64,
    /// Of which the primary hit disagrees geometrically.
    pub hit_mismatched: u64,
    /// Pixels whose primary hit agrees (both hit): the shadow denominator.
    pub agreeing_hits: u64,
    /// Of which the shadow bit differs.
    pub shadow_mismatched: u64,
}

/// One frame's error against the reference.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct FrameScore {
    /// Pixels compared.
    pub pixels: u64,
    /// Share of pixels whose primary hit disagrees geometrically.
    pub hit_mismatch: f64,
    /// Share of pixels whose hit instance differs (misses and proxies have no instance).
    pub identity_mismatch: f64,
    /// Share of agreeing hit pixels whose shadow bit differs.
    pub shadow_mismatch: f64,
    /// Mean |AO managed − AO reference| over agreeing hit pixels.
    pub ao_difference: f64,
    /// RMSE of the RGB channels in [0, 1].
    pub color_rmse: f64,
    /// PSNR in dB (infinite for identical colours).
    pub psnr_db: f64,
    /// Per distance band.
    pub bands: [BandCounts; 4],
}

/// Per-pixel verdict, for the difference picture.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelVerdict {
    /// Both miss.
    Sky,
    /// The primary hit agrees and so does the shadow.
    Agree,
    /// The primary hit agrees, the shadow bit differs.
    ShadowDiffers,
    /// The managed frame misses what the reference hits.
    Missing,
    /// The managed frame hits where the reference misses, or at a different distance.
    Wrong,
}

/// Compares `managed` with `reference`, both rendered from `camera`. `managed_id` and
/// `reference_id` map each frame's customIndex to a world instance id (None: no instance,
/// e.g. a proxy). Returns the score and the per-pixel verdicts.
pub fn score(
    managed: &Frame,
    reference: &Frame,
    camera: &Camera,
    edges: BandEdges,
    managed_id: impl Fn(u32) -> Option<u32>,
    reference_id: impl Fn(u32) -> Option<u32>,
) -> Result<(FrameScore, Vec<PixelVerdict>), String> {
    let (w, h) = (reference.width, reference.height);
    let n = (w as usize) * (h as usize);
    if managed.width != w || managed.height != h || managed.hits.len() != n {
        return Err(format!(
            "frames differ in size: {}x{} vs {w}x{h}",
            managed.width, managed.height
        ));
    }
    let has_normals = reference.normals.len() == n;
    // One pixel's footprint per metre of distance (vertical).
    let footprint_per_m = 2.0 * (camera.fov_y * 0.5).tan() / h.max(1) as f32;
    let mut bands = [BandCounts::default(); 4];
    let mut verdicts = Vec::with_capacity(n);
    let (mut hit_bad, mut id_bad, mut agree, mut shadow_bad) = (0u64, 0u64, 0u64, 0u64);
    let mut ao_sum = 0.0f64;
    for i in 0..n {
        let (m, r) = (&managed.hits[i], &reference.hits[i]);
        let ids = (
            m.is_hit().then(|| managed_id(m.instance)).flatten(),
            r.is_hit().then(|| reference_id(r.instance)).flatten(),
        );
        if ids.0 != ids.1 || (ids.0.is_none() && m.is_hit() != r.is_hit()) {
            id_bad += 1;
        }
        let verdict = match (m.is_hit(), r.is_hit()) {
            (false, false) => PixelVerdict::Sky,
            (false, true) => PixelVerdict::Missing,
            (true, false) => PixelVerdict::Wrong,
            (true, true) => {
                let (tm, tr) = (m.t(), r.t());
                let (x, y) = ((i % w as usize) as u32, (i / w as usize) as u32);
                let cos = if has_normals {
                    let (_, dir) = camera.primary_ray(x, y, w, h);
                    let nr = glam::Vec3::from(reference.normals[i]);
                    nr.dot(-dir).abs().max(0.1)
                } else {
                    1.0
                };
                let tol = (0.01 * tr).max(footprint_per_m * tr / cos);
                if (tm - tr).abs() > tol {
                    PixelVerdict::Wrong
                } else if (m.shadowed != 0) != (r.shadowed != 0) {
                    PixelVerdict::ShadowDiffers
                } else {
                    PixelVerdict::Agree
                }
            }
        };
        let t_band = if r.is_hit() { r.t() } else { m.t() };
        if verdict != PixelVerdict::Sky {
            let b = &mut bands[edges.band(t_band)];
            b.pixels += 1;
            match verdict {
                PixelVerdict::Missing | PixelVerdict::Wrong => {
                    b.hit_mismatched += 1;
                    hit_bad += 1;
                }
                PixelVerdict::Agree | PixelVerdict::ShadowDiffers => {
                    b.agreeing_hits += 1;
                    agree += 1;
                    let ao = |f: &Frame| f.ambient.get(i).copied().unwrap_or(1.0) as f64;
                    ao_sum += (ao(managed) - ao(reference)).abs();
                    if verdict == PixelVerdict::ShadowDiffers {
                        b.shadow_mismatched += 1;
                        shadow_bad += 1;
                    }
                }
                PixelVerdict::Sky => {}
            }
        }
        verdicts.push(verdict);
    }
    let rmse = color_rmse(&managed.color, &reference.color);
    let nf = n.max(1) as f64;
    Ok((
        FrameScore {
            pixels: n as u64,
            hit_mismatch: hit_bad as f64 / nf,
            identity_mismatch: id_bad as f64 / nf,
            shadow_mismatch: shadow_bad as f64 / agree.max(1) as f64,
            ao_difference: ao_sum / agree.max(1) as f64,
            color_rmse: rmse,
            psnr_db: psnr(rmse),
            bands,
        },
        verdicts,
    ))
}

/// The difference picture: red where the managed frame misses what the reference hits, orange
/// where it hits wrongly, yellow where only the shadow differs, elsewhere a dimmed copy of the
/// reference.
pub fn difference_picture(reference: &Frame, verdicts: &[PixelVerdict]) -> Vec<[u8; 4]> {
    verdicts
        .iter()
        .zip(&reference.color)
        .map(|(v, c)| match v {
            PixelVerdict::Missing => [230, 20, 20, 255],
            PixelVerdict::Wrong => [255, 140, 0, 255],
            PixelVerdict::ShadowDiffers => [240, 230, 40, 255],
            PixelVerdict::Sky | PixelVerdict::Agree => [c[0] / 3, c[1] / 3, c[2] / 3, 255],
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use rtstream_renderer::{PassStats, PixelHit};

    /// Rows of a 1080-row image: the given hits on the top row, sky elsewhere (so a pixel's
    /// footprint is that of a 1080p frame).
    const ROWS: u32 = 1080;

    fn frame(hits: &[(u32, f32, u32)]) -> Frame {
        let w = hits.len();
        let n = w * ROWS as usize;
        let mut all: Vec<PixelHit> = hits
            .iter()
            .map(|&(instance, t, shadowed)| PixelHit {
                instance,
                primitive: 0,
                shadowed,
                t_bits: if instance == PixelHit::MISS {
                    -1.0f32
                } else {
                    t
                }
                .to_bits(),
            })
            .collect();
        all.resize(
            n,
            PixelHit {
                instance: PixelHit::MISS,
                primitive: PixelHit::MISS,
                shadowed: 0,
                t_bits: (-1.0f32).to_bits(),
            },
        );
        Frame {
            width: w as u32,
            height: ROWS,
            color: vec![[100, 100, 100, 255]; n],
            hits: all,
            sun_visibility: vec![1.0; n],
            ambient: vec![1.0; n],
            normals: vec![[0.0, 0.0, -1.0]; n],
            render_ms: 0.0,
            passes: PassStats::default(),
        }
    }

    /// A share of all pixels as a pixel count.
    fn count(share: f64, s: &FrameScore) -> u64 {
        (share * s.pixels as f64).round() as u64
    }

    const MISS: u32 = PixelHit::MISS;

    fn cam() -> Camera {
        Camera::look_at(Vec3::ZERO, Vec3::Z, 60f32.to_radians())
    }

    #[test]
    fn geometric_mismatch_counts_distance_and_presence_not_identity() {
        let reference = frame(&[(1, 100.0, 0), (2, 100.0, 0), (3, 100.0, 0), (MISS, 0.0, 0)]);
        // Same place, another id (a proxy); 0.5% off; 10% off; a hit where the sky was.
        let managed = frame(&[(9, 100.0, 0), (2, 100.5, 0), (3, 110.0, 0), (4, 50.0, 0)]);
        let (s, v) = score(
            &managed,
            &reference,
            &cam(),
            BandEdges::new(200.0, 250.0),
            Some,
            Some,
        )
        .unwrap();
        assert_eq!(v[0], PixelVerdict::Agree);
        assert_eq!(v[1], PixelVerdict::Agree);
        assert_eq!(v[2], PixelVerdict::Wrong);
        assert_eq!(v[3], PixelVerdict::Wrong);
        assert_eq!(count(s.hit_mismatch, &s), 2);
        assert_eq!(count(s.identity_mismatch, &s), 2, "pixels 0 and 3");
        assert_eq!(s.bands[0].pixels, 4);
    }

    #[test]
    fn grazing_surfaces_get_a_wider_tolerance() {
        let mut reference = frame(&[(1, 1000.0, 0)]);
        let managed = frame(&[(1, 1010.5, 0)]);
        let edges = BandEdges::new(200.0, 250.0);
        // Facing the camera: 1.05% off is wrong (the footprint at 1 km is 1.07 m).
        let (s, _) = score(&managed, &reference, &cam(), edges, Some, Some).unwrap();
        assert_eq!(count(s.hit_mismatch, &s), 1);
        // At grazing incidence (cos floored at 0.1) the footprint is 10.7 m: 10.5 m is within.
        reference.normals[0] = [1.0, 0.0, 0.0]; // perpendicular to the ray
        let (s, _) = score(&managed, &reference, &cam(), edges, Some, Some).unwrap();
        assert_eq!(s.hit_mismatch, 0.0);
    }

    #[test]
    fn shadows_count_over_agreeing_hits_and_bands_split_by_distance() {
        let reference = frame(&[(1, 10.0, 1), (2, 220.0, 0), (3, 600.0, 0), (MISS, 0.0, 0)]);
        let managed = frame(&[(1, 10.0, 0), (2, 220.0, 0), (MISS, 0.0, 0), (MISS, 0.0, 0)]);
        let edges = BandEdges::new(200.0, 250.0);
        let (s, v) = score(&managed, &reference, &cam(), edges, Some, Some).unwrap();
        assert_eq!(v[0], PixelVerdict::ShadowDiffers);
        assert_eq!(v[2], PixelVerdict::Missing);
        assert!(
            (s.shadow_mismatch - 0.5).abs() < 1e-9,
            "1 of 2 agreeing hits"
        );
        assert_eq!(s.bands[0].shadow_mismatched, 1);
        assert_eq!(s.bands[1].pixels, 1);
        assert_eq!(s.bands[2].hit_mismatched, 1);
        assert_eq!(s.bands[3].pixels, 0);
        assert_eq!(edges.band(1500.0), 3);
    }

    #[test]
    fn size_mismatch_is_an_error() {
        let a = frame(&[(1, 1.0, 0)]);
        let b = frame(&[(1, 1.0, 0), (1, 1.0, 0)]);
        let edges = BandEdges::new(200.0, 250.0);
        assert!(score(&a, &b, &cam(), edges, Some, Some).is_err());
    }
}
