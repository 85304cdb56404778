//! A CPU reference ray caster (a binned-SAH BVH over world-space triangles), used to check the
//! GPU's hits. Correctness over speed; it is meant for small test images.

use glam::{Mat4, Vec3};

use crate::camera::Camera;

/// One hit of the reference caster.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CpuHit {
    /// The instance's id (what the GPU reports as customIndex).
    pub instance: u32,
    /// Triangle index within the instance's mesh.
    pub primitive: u32,
    /// Ray distance.
    pub t: f32,
}

#[derive(Debug, Clone, Copy)]
struct Tri {
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
    instance: u32,
    primitive: u32,
}

#[derive(Debug, Clone, Copy)]
struct Node {
    min: Vec3,
    max: Vec3,
    /// Leaf: first triangle; inner: left child (right = left + 1).
    start: u32,
    /// Leaf: triangle count (> 0); inner: 0.
    count: u32,
}

/// A BVH over the triangles of a set of mesh instances.
#[derive(Debug, Default)]
pub struct ReferenceScene {
    tris: Vec<Tri>,
    nodes: Vec<Node>,
}

impl ReferenceScene {
    /// Builds the BVH. `meshes[i] = (positions, indices)`; `instances = (mesh, transform, id)`.
    pub fn new(meshes: &[(&[[f32; 3]], &[u32])], instances: &[(usize, Mat4, u32)]) -> Self {
        let mut tris = Vec::new();
        for &(mesh, m, id) in instances {
            let (pos, idx) = meshes[mesh];
            for (p, t) in idx.chunks_exact(3).enumerate() {
                let v = |k: usize| m.transform_point3(Vec3::from(pos[t[k] as usize]));
                let (v0, v1, v2) = (v(0), v(1), v(2));
                tris.push(Tri {
                    v0,
                    e1: v1 - v0,
                    e2: v2 - v0,
                    instance: id,
                    primitive: p as u32,
                });
            }
        }
        let mut s = Self {
            tris,
            nodes: Vec::new(),
        };
        if !s.tris.is_empty() {
            s.nodes.push(Node {
                min: Vec3::ZERO,
                max: Vec3::ZERO,
                start: 0,
                count: s.tris.len() as u32,
            });
            s.split(0);
        }
        s
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.tris.len()
    }

    fn bounds(&self, start: u32, count: u32) -> (Vec3, Vec3) {
        self.tris[start as usize..(start + count) as usize]
            .iter()
            .fold(
                (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                |(lo, hi), t| {
                    let (a, b, c) = (t.v0, t.v0 + t.e1, t.v0 + t.e2);
                    (lo.min(a).min(b).min(c), hi.max(a).max(b).max(c))
                },
            )
    }

    fn split(&mut self, root: usize) {
        let mut stack = vec![root];
        while let Some(ni) = stack.pop() {
            let Node { start, count, .. } = self.nodes[ni];
            let (lo, hi) = self.bounds(start, count);
            self.nodes[ni].min = lo;
            self.nodes[ni].max = hi;
            if count <= 4 {
                continue;
            }
            let range = start as usize..(start + count) as usize;
            let centroid = |t: &Tri| t.v0 + (t.e1 + t.e2) / 3.0;
            let (clo, chi) = self.tris[range.clone()].iter().fold(
                (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                |(a, b), t| (a.min(centroid(t)), b.max(centroid(t))),
            );
            let ext = chi - clo;
            let axis = if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            };
            if ext[axis] <= 0.0 {
                continue; // all centroids coincide: keep as a leaf
            }
            // Binned SAH along the widest axis.
            const BINS: usize = 12;
            let mut bin_count = [0u32; BINS];
            let mut bin_box = [(Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)); BINS];
            let bin_of = |t: &Tri| {
                (((centroid(t)[axis] - clo[axis]) / ext[axis] * BINS as f32) as usize).min(BINS - 1)
            };
            for t in &self.tris[range.clone()] {
                let b = bin_of(t);
                bin_count[b] += 1;
                let (a, bb, c) = (t.v0, t.v0 + t.e1, t.v0 + t.e2);
                bin_box[b].0 = bin_box[b].0.min(a).min(bb).min(c);
                bin_box[b].1 = bin_box[b].1.max(a).max(bb).max(c);
            }
            let area = |(a, b): (Vec3, Vec3)| {
                let d = (b - a).max(Vec3::ZERO);
                d.x * d.y + d.y * d.z + d.z * d.x
            };
            let merge = |x: (Vec3, Vec3), y: (Vec3, Vec3)| (x.0.min(y.0), x.1.max(y.1));
            let mut best = (f32::INFINITY, 0usize);
            for split in 1..BINS {
                let (mut lb, mut rb) = (
                    (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                    (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                );
                let (mut lc, mut rc) = (0u32, 0u32);
                for b in 0..split {
                    lb = merge(lb, bin_box[b]);
                    lc += bin_count[b];
                }
                for b in split..BINS {
                    rb = merge(rb, bin_box[b]);
                    rc += bin_count[b];
                }
                if lc == 0 || rc == 0 {
                    continue;
                }
                let cost = area(lb) * lc as f32 + area(rb) * rc as f32;
                if cost < best.0 {
                    best = (cost, split);
                }
            }
            if best.1 == 0 {
                continue;
            }
            let slice = &mut self.tris[range];
            let mut i = 0;
            let mut j = slice.len();
            while i < j {
                if bin_of(&slice[i]) < best.1 {
                    i += 1;
                } else {
                    j -= 1;
                    slice.swap(i, j);
                }
            }
            let left = self.nodes.len();
            self.nodes.push(Node {
                min: Vec3::ZERO,
                max: Vec3::ZERO,
                start,
                count: i as u32,
            });
            self.nodes.push(Node {
                min: Vec3::ZERO,
                max: Vec3::ZERO,
                start: start + i as u32,
                count: count - i as u32,
            });
            self.nodes[ni].start = left as u32;
            self.nodes[ni].count = 0;
            stack.push(left);
            stack.push(left + 1);
        }
    }

    /// Closest hit along the ray within (t_min, t_max), both faces counted.
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Option<CpuHit> {
        if self.nodes.is_empty() {
            return None;
        }
        let inv = dir.recip();
        let mut best: Option<CpuHit> = None;
        let mut t_best = t_max;
        let mut stack = vec![0usize];
        while let Some(ni) = stack.pop() {
            let n = self.nodes[ni];
            let t0 = (n.min - origin) * inv;
            let t1 = (n.max - origin) * inv;
            let tn = t0.min(t1).max_element();
            let tf = t0.max(t1).min_element();
            if tn > tf || tf < t_min || tn > t_best {
                continue;
            }
            if n.count > 0 {
                for tri in &self.tris[n.start as usize..(n.start + n.count) as usize] {
                    // Möller–Trumbore.
                    let p = dir.cross(tri.e2);
                    let det = tri.e1.dot(p);
                    if det.abs() < 1e-12 {
                        continue;
                    }
                    let inv_det = 1.0 / det;
                    let s = origin - tri.v0;
                    let u = s.dot(p) * inv_det;
                    if !(0.0..=1.0).contains(&u) {
                        continue;
                    }
                    let q = s.cross(tri.e1);
                    let v = dir.dot(q) * inv_det;
                    if v < 0.0 || u + v > 1.0 {
                        continue;
                    }
                    let t = tri.e2.dot(q) * inv_det;
                    if t > t_min && t < t_best {
                        t_best = t;
                        best = Some(CpuHit {
                            instance: tri.instance,
                            primitive: tri.primitive,
                            t,
                        });
                    }
                }
            } else {
                stack.push(n.start as usize);
                stack.push(n.start as usize + 1);
            }
        }
        best
    }

    /// Casts one primary ray per pixel; row-major, `None` for a miss.
    pub fn cast(&self, camera: &Camera, width: u32, height: u32) -> Vec<Option<CpuHit>> {
        let mut out = Vec::with_capacity((width * height) as usize);
        for y in 0..height {
            for x in 0..width {
                let (o, d) = camera.primary_ray(x, y, width, height);
                out.push(self.intersect(o, d, 0.0, f32::INFINITY));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hits_a_quad_and_misses_beside_it() {
        let pos = [
            [-1.0, -1.0, 0.0],
            [1.0, -1.0, 0.0],
            [1.0, 1.0, 0.0],
            [-1.0, 1.0, 0.0],
        ];
        let idx = [0, 1, 2, 0, 2, 3];
        let s = ReferenceScene::new(
            &[(&pos, &idx)],
            &[(0, Mat4::from_translation(Vec3::new(0.0, 0.0, -5.0)), 7)],
        );
        let hit = s
            .intersect(Vec3::ZERO, Vec3::NEG_Z, 0.0, f32::INFINITY)
            .expect("hit");
        assert_eq!(hit.instance, 7);
        assert!((hit.t - 5.0).abs() < 1e-5);
        assert!(s
            .intersect(Vec3::new(3.0, 0.0, 0.0), Vec3::NEG_Z, 0.0, f32::INFINITY)
            .is_none());
    }

    #[test]
    fn bvh_agrees_with_brute_force() {
        // A grid of small triangles at varying depths; compare the BVH against a linear scan.
        let mut pos = Vec::new();
        let mut idx = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                let (x, y, z) = (
                    i as f32 * 0.3,
                    j as f32 * 0.3,
                    -((i * 7 + j * 3) % 11) as f32 - 1.0,
                );
                let b = pos.len() as u32;
                pos.extend([[x, y, z], [x + 0.25, y, z], [x, y + 0.25, z + 0.1]]);
                idx.extend([b, b + 1, b + 2]);
            }
        }
        let s = ReferenceScene::new(&[(&pos, &idx)], &[(0, Mat4::IDENTITY, 0)]);
        let brute = ReferenceScene {
            tris: s.tris.clone(),
            nodes: vec![Node {
                min: Vec3::splat(-1e9),
                max: Vec3::splat(1e9),
                start: 0,
                count: s.tris.len() as u32,
            }],
        };
        let cam = Camera::look_at(Vec3::new(3.0, 3.0, 8.0), Vec3::new(3.0, 3.0, -5.0), 0.9);
        let (a, b) = (s.cast(&cam, 48, 48), brute.cast(&cam, 48, 48));
        assert_eq!(a, b);
        assert!(a.iter().filter(|h| h.is_some()).count() > 100);
    }
}
