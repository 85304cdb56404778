//! `RefitQuality`: how much refits have degraded a skinned BLAS, measured on the CPU.
//!
//! A refit keeps the hierarchy's topology and only grows boxes. At build time the triangles are
//! sorted by the Morton code of their centroids and cut into fixed leaves of [`LEAF`] triangles
//! and nodes of [`NODE`] leaves (a stand-in for the builder's hierarchy). The metric is the
//! summed surface area of those leaf and node boxes divided by the root box's area (the SAH
//! cost shape, scale-free); the quality ratio is that metric for the current positions over
//! the metric at the last build. 1.0 = as good as built; a rebuild resets the grouping.

use glam::Vec3A;

/// Triangles per leaf.
pub const LEAF: usize = 4;
/// Leaves per node.
pub const NODE: usize = 8;

#[derive(Debug, Clone, Copy)]
struct Aabb {
    min: Vec3A,
    max: Vec3A,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: Vec3A::splat(f32::INFINITY),
        max: Vec3A::splat(f32::NEG_INFINITY),
    };
    fn grow(&mut self, p: Vec3A) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    fn merge(&mut self, o: &Aabb) {
        self.min = self.min.min(o.min);
        self.max = self.max.max(o.max);
    }
    fn area(&self) -> f32 {
        let d = (self.max - self.min).max(Vec3A::ZERO);
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }
}

fn spread(mut v: u32) -> u32 {
    v &= 0x3ff;
    v = (v | (v << 16)) & 0x030000ff;
    v = (v | (v << 8)) & 0x0300f00f;
    v = (v | (v << 4)) & 0x030c30c3;
    (v | (v << 2)) & 0x09249249
}

/// The build-time grouping of one skinned BLAS and its metric at that build.
#[derive(Debug, Clone)]
pub struct RefitQuality {
    /// Triangle order (indices into the triangle list) at the last build.
    order: Vec<u32>,
    built_metric: f32,
}

impl RefitQuality {
    /// Groups triangles for `positions` (as at a build) and records the metric.
    pub fn at_build(positions: &[[f32; 3]], indices: &[u32]) -> Self {
        let tris = indices.len() / 3;
        let mut bounds = Aabb::EMPTY;
        let centroid = |t: usize| -> Vec3A {
            let p = |k: usize| Vec3A::from(positions[indices[3 * t + k] as usize]);
            (p(0) + p(1) + p(2)) / 3.0
        };
        for t in 0..tris {
            bounds.grow(centroid(t));
        }
        let ext = (bounds.max - bounds.min).max(Vec3A::splat(1e-12));
        let mut keyed: Vec<(u32, u32)> = (0..tris)
            .map(|t| {
                let q = (centroid(t) - bounds.min) / ext * 1023.0;
                let code =
                    spread(q.x as u32) | (spread(q.y as u32) << 1) | (spread(q.z as u32) << 2);
                (code, t as u32)
            })
            .collect();
        keyed.sort_unstable();
        let order: Vec<u32> = keyed.into_iter().map(|(_, t)| t).collect();
        let built_metric = metric(&order, positions, indices);
        Self {
            order,
            built_metric,
        }
    }

    /// Quality ratio (>= ~1; larger is worse) of a refit to `positions`.
    pub fn ratio(&self, positions: &[[f32; 3]], indices: &[u32]) -> f32 {
        let m = metric(&self.order, positions, indices);
        if self.built_metric > 0.0 {
            m / self.built_metric
        } else {
            1.0
        }
    }
}

/// Summed leaf + node box area over the root box area.
fn metric(order: &[u32], positions: &[[f32; 3]], indices: &[u32]) -> f32 {
    let mut root = Aabb::EMPTY;
    let mut sum = 0.0f32;
    for node in order.chunks(LEAF * NODE) {
        let mut nb = Aabb::EMPTY;
        for leaf in node.chunks(LEAF) {
            let mut lb = Aabb::EMPTY;
            for &t in leaf {
                for k in 0..3 {
                    lb.grow(Vec3A::from(positions[indices[3 * t as usize + k] as usize]));
                }
            }
            sum += lb.area();
            nb.merge(&lb);
        }
        sum += nb.area();
        root.merge(&nb);
    }
    let ra = root.area();
    if ra > 0.0 {
        sum / ra
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize) -> (Vec<[f32; 3]>, Vec<u32>) {
        let mut p = Vec::new();
        let mut ix = Vec::new();
        for z in 0..=n {
            for x in 0..=n {
                p.push([x as f32, 0.0, z as f32]);
            }
        }
        let w = (n + 1) as u32;
        for z in 0..n as u32 {
            for x in 0..n as u32 {
                let a = z * w + x;
                ix.extend([a, a + 1, a + w, a + 1, a + w + 1, a + w]);
            }
        }
        (p, ix)
    }

    #[test]
    fn rigid_motion_keeps_quality_and_scrambling_degrades_it() {
        let (p, ix) = grid(32);
        let q = RefitQuality::at_build(&p, &ix);
        let moved: Vec<[f32; 3]> = p
            .iter()
            .map(|v| [v[0] * 2.0 + 5.0, v[1], v[2] * 2.0])
            .collect();
        assert!((q.ratio(&moved, &ix) - 1.0).abs() < 1e-3);
        // fold the grid: far-apart vertices swap places
        let folded: Vec<[f32; 3]> = p
            .iter()
            .enumerate()
            .map(|(i, v)| {
                if i % 2 == 0 {
                    [32.0 - v[0], v[1], 32.0 - v[2]]
                } else {
                    *v
                }
            })
            .collect();
        assert!(q.ratio(&folded, &ix) > 2.0);
        let q2 = RefitQuality::at_build(&folded, &ix);
        assert!((q2.ratio(&folded, &ix) - 1.0).abs() < 1e-6);
    }
}
