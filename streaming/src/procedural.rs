//! Procedural meshes for the generated world: terrain tiles, rocks, buildings, trees, grass,
//! glass panes and skinned characters, plus the deterministic random source the generator uses.
//!
//! Everything here is a pure function of its seed. Meshes are in metres, centred on the origin in
//! X/Z and standing on Y = 0 (terrain tiles are centred on Y = 0).

use std::collections::HashMap;
use std::f32::consts::{PI, TAU};
use std::sync::Arc;

use glam::{Mat4, Quat, Vec3, Vec4};

use crate::lod::build_lod_chain;
use crate::model::{Aabb, Mesh, SkinWeights, WorldMeshId};
use crate::skeleton::{Channel, ChannelPath, Joint, Skeleton};

/// The generator's random source (shared with as-manager's synthetic world, in `rtstream-stats`).
pub use rtstream_stats::Rng;

/// The generator's seeding: the state starts at `seed ^ 0x9E37_79B9_7F4A_7C15`, as the
/// hand-written SplitMix64 this replaced did (so generated worlds did not change).
pub fn seeded(seed: u64) -> Rng {
    Rng::new(seed ^ 0x9E37_79B9_7F4A_7C15)
}

type Geometry = (Vec<[f32; 3]>, Vec<u32>);

fn hash2(x: i32, z: i32, seed: u64) -> f32 {
    let mut r = seeded(seed ^ ((x as u32 as u64) << 32 | z as u32 as u64));
    r.f32()
}

fn value_noise(x: f32, z: f32, seed: u64) -> f32 {
    let (xi, zi) = (x.floor() as i32, z.floor() as i32);
    let (fx, fz) = (x - xi as f32, z - zi as f32);
    let s = |t: f32| t * t * (3.0 - 2.0 * t);
    let (sx, sz) = (s(fx), s(fz));
    let a = hash2(xi, zi, seed);
    let b = hash2(xi + 1, zi, seed);
    let c = hash2(xi, zi + 1, seed);
    let d = hash2(xi + 1, zi + 1, seed);
    let top = a + (b - a) * sx;
    let bot = c + (d - c) * sx;
    top + (bot - top) * sz
}

/// A square heightfield tile of `n` x `n` quads and side `size` metres, heights up to `amplitude`.
pub fn grid_terrain(n: u32, size: f32, amplitude: f32, seed: u64) -> Geometry {
    let n = n.max(1);
    let mut pos = Vec::with_capacity(((n + 1) * (n + 1)) as usize);
    for j in 0..=n {
        for i in 0..=n {
            let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
            let h = amplitude
                * (value_noise(u * 4.0, v * 4.0, seed) * 0.7
                    + value_noise(u * 13.0, v * 13.0, seed ^ 1) * 0.3);
            pos.push([(u - 0.5) * size, h, (v - 0.5) * size]);
        }
    }
    let mut idx = Vec::with_capacity((n * n * 6) as usize);
    for j in 0..n {
        for i in 0..n {
            let a = j * (n + 1) + i;
            let (b, c, d) = (a + 1, a + n + 1, a + n + 2);
            idx.extend_from_slice(&[a, c, b, b, c, d]);
        }
    }
    (pos, idx)
}

fn icosphere(subdivisions: u32) -> Geometry {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut pos: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| Vec3::from(*p).normalize())
    .collect();
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut next = Vec::with_capacity(tris.len() * 4);
        let mut midpoint = |a: u32, b: u32, pos: &mut Vec<Vec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                pos.push(((pos[a as usize] + pos[b as usize]) * 0.5).normalize());
                (pos.len() - 1) as u32
            })
        };
        for [a, b, c] in tris {
            let ab = midpoint(a, b, &mut pos);
            let bc = midpoint(b, c, &mut pos);
            let ca = midpoint(c, a, &mut pos);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    (
        pos.iter().map(|p| p.to_array()).collect(),
        tris.into_iter().flatten().collect(),
    )
}

/// A lumpy rock about `size` metres across.
pub fn rock(seed: u64, size: f32) -> Geometry {
    let (mut pos, idx) = icosphere(3);
    let stretch = {
        let mut r = seeded(seed);
        Vec3::new(r.range(0.7, 1.3), r.range(0.4, 0.9), r.range(0.7, 1.3))
    };
    for p in &mut pos {
        let v = Vec3::from(*p);
        let n = value_noise(v.x * 2.0 + 7.0, v.z * 2.0 + v.y * 3.0, seed) * 0.35
            + value_noise(v.x * 6.0, v.y * 6.0 + v.z * 2.0, seed ^ 5) * 0.12;
        let q = v * (0.75 + n) * stretch * size * 0.5;
        *p = [q.x, q.y.max(-0.1 * size) + 0.25 * size * stretch.y, q.z];
    }
    (pos, idx)
}

fn push_quad_grid(pos: &mut Vec<[f32; 3]>, idx: &mut Vec<u32>, o: Vec3, u: Vec3, v: Vec3, n: u32) {
    let base = pos.len() as u32;
    for j in 0..=n {
        for i in 0..=n {
            let p = o + u * (i as f32 / n as f32) + v * (j as f32 / n as f32);
            pos.push(p.to_array());
        }
    }
    for j in 0..n {
        for i in 0..n {
            let a = base + j * (n + 1) + i;
            let (b, c, d) = (a + 1, a + n + 1, a + n + 2);
            idx.extend_from_slice(&[a, b, c, b, d, c]);
        }
    }
}

fn push_box(pos: &mut Vec<[f32; 3]>, idx: &mut Vec<u32>, min: Vec3, max: Vec3, n: u32) {
    let d = max - min;
    let (x, y, z) = (Vec3::X * d.x, Vec3::Y * d.y, Vec3::Z * d.z);
    push_quad_grid(pos, idx, min, y, x, n); // -Z
    push_quad_grid(pos, idx, min + z, x, y, n); // +Z
    push_quad_grid(pos, idx, min, z, y, n); // -X
    push_quad_grid(pos, idx, min + x, y, z, n); // +X
    push_quad_grid(pos, idx, min + y, z, x, n); // +Y
    push_quad_grid(pos, idx, min, x, z, n); // -Y
}

/// A building of a few stacked, set-back boxes with tessellated facades.
pub fn building(seed: u64) -> Geometry {
    let mut r = seeded(seed);
    let (mut pos, mut idx) = (Vec::new(), Vec::new());
    let mut half = Vec3::new(r.range(5.0, 12.0), 0.0, r.range(5.0, 12.0));
    let mut y = 0.0;
    for _ in 0..1 + r.below(3) {
        let h = r.range(4.0, 14.0);
        push_box(
            &mut pos,
            &mut idx,
            Vec3::new(-half.x, y, -half.z),
            Vec3::new(half.x, y + h, half.z),
            6,
        );
        y += h;
        half *= r.range(0.55, 0.85);
    }
    (pos, idx)
}

fn cylinder(radius: f32, height: f32, segments: u32, rings: u32) -> Geometry {
    let (mut pos, mut idx) = (Vec::new(), Vec::new());
    for j in 0..=rings {
        let y = height * j as f32 / rings as f32;
        for i in 0..segments {
            let a = TAU * i as f32 / segments as f32;
            pos.push([radius * a.cos(), y, radius * a.sin()]);
        }
    }
    for j in 0..rings {
        for i in 0..segments {
            let a = j * segments + i;
            let b = j * segments + (i + 1) % segments;
            idx.extend_from_slice(&[a, a + segments, b, b, a + segments, b + segments]);
        }
    }
    (pos, idx)
}

/// A tree: a trunk and crossed foliage cards (an alpha-masked material in the world).
pub fn tree(seed: u64) -> Geometry {
    let mut r = seeded(seed);
    let h = r.range(6.0, 14.0);
    let (mut pos, mut idx) = cylinder(r.range(0.2, 0.4), h * 0.6, 10, 6);
    let w = r.range(2.0, 4.0);
    for k in 0..4 {
        let a = PI * k as f32 / 4.0;
        let u = Vec3::new(a.cos(), 0.0, a.sin()) * 2.0 * w;
        push_quad_grid(
            &mut pos,
            &mut idx,
            Vec3::new(0.0, h * 0.35, 0.0) - u * 0.5,
            u,
            Vec3::Y * h * 0.65,
            4,
        );
    }
    (pos, idx)
}

/// A patch of grass blades (a world-position-offset material in the world).
pub fn grass(seed: u64) -> Geometry {
    let mut r = seeded(seed);
    let (mut pos, mut idx) = (Vec::new(), Vec::new());
    for _ in 0..48 {
        let o = Vec3::new(r.range(-1.5, 1.5), 0.0, r.range(-1.5, 1.5));
        let a = r.range(0.0, TAU);
        let u = Vec3::new(a.cos(), 0.0, a.sin()) * 0.08;
        push_quad_grid(&mut pos, &mut idx, o, u, Vec3::Y * r.range(0.3, 0.8), 2);
    }
    (pos, idx)
}

/// A glass pane (a transparent material in the world).
pub fn glass_pane(seed: u64) -> Geometry {
    let mut r = seeded(seed);
    let (w, h) = (r.range(1.0, 4.0), r.range(1.0, 3.0));
    let (mut pos, mut idx) = (Vec::new(), Vec::new());
    push_quad_grid(
        &mut pos,
        &mut idx,
        Vec3::new(-w / 2.0, 0.0, 0.0),
        Vec3::X * w,
        Vec3::Y * h,
        8,
    );
    (pos, idx)
}

/// A skinned character: a segmented body on a three-joint spine with a looping sway animation,
/// its LOD chain already built. `seed` varies proportions and gait.
pub fn character(seed: u64) -> Mesh {
    let mut r = seeded(seed);
    let height = r.range(1.6, 2.0);
    let (pos, idx) = cylinder(r.range(0.2, 0.3), height, 16, 24);
    let seg = height / 3.0;
    let joints: Vec<Joint> = (0..3u16)
        .map(|j| Joint {
            parent: j.checked_sub(1),
            translation: Vec3::new(0.0, if j == 0 { 0.0 } else { seg }, 0.0),
            rotation: Quat::IDENTITY,
            scale: Vec3::ONE,
            inverse_bind: Mat4::from_translation(Vec3::new(0.0, -seg * f32::from(j), 0.0)),
        })
        .collect();
    let amp = r.range(0.15, 0.35);
    let period = r.range(1.0, 2.0);
    let times: Vec<f32> = (0..=8).map(|k| period * k as f32 / 8.0).collect();
    let channels = (1..3u16)
        .map(|j| Channel {
            joint: j,
            path: ChannelPath::Rotation,
            times: times.clone(),
            values: times
                .iter()
                .map(|t| {
                    Vec4::from(Quat::from_rotation_z(
                        amp * (TAU * t / period + f32::from(j)).sin(),
                    ))
                })
                .collect(),
        })
        .collect();
    let skeleton = Arc::new(Skeleton {
        joints,
        root: Mat4::IDENTITY,
        channels,
        duration: period,
    });
    let (mut jw, mut ww) = (Vec::new(), Vec::new());
    for p in &pos {
        let s = (p[1] / seg).clamp(0.0, 2.999);
        let j = s.floor();
        let f = s - j;
        let j0 = j as u16;
        let j1 = (j0 + 1).min(2);
        // Blend across the joint boundary for a smooth bend.
        let w1 = ((f - 0.5).max(0.0) * 2.0 * 0.5).min(0.5);
        jw.push([j0, j1, 0, 0]);
        ww.push([1.0 - w1, w1, 0.0, 0.0]);
    }
    let bounds = Aabb::from_points(&pos);
    let skin = SkinWeights {
        joints: jw,
        weights: ww,
        skeleton,
    };
    Mesh {
        id: WorldMeshId(0),
        name: format!("character{seed}"),
        bounds,
        lods: build_lod_chain(pos, idx, Some(skin))
            .into_iter()
            .map(Arc::new)
            .collect(),
    }
}
