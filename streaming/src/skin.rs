//! Skeletons, animations and CPU skinning.
//!
//! A [`Skeleton`] holds joints in parent-before-child order (validated on import), each with a
//! rest pose and an inverse bind matrix, and one looping animation made of linear keyframe
//! channels (glTF's translation/rotation/scale paths). [`skin_positions`] deforms one LOD's
//! vertices; [`skin_parallel`] spreads many instances over scoped threads, which is what the world
//! does each frame for its loaded skinned instances (the manager refits their BLASes from it).

use glam::{Mat4, Quat, Vec3, Vec4};

use crate::model::LodGeometry;

/// Which property a channel animates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum ChannelPath {
    /// `values` are (x, y, z, 0).
    Translation = 0,
    /// `values` are quaternions (x, y, z, w).
    Rotation = 1,
    /// `values` are (x, y, z, 0).
    Scale = 2,
}

/// One joint of a skeleton.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Joint {
    /// Parent joint, always of a smaller index; `None` for roots.
    pub parent: Option<u16>,
    /// Rest translation relative to the parent.
    pub translation: Vec3,
    /// Rest rotation relative to the parent.
    pub rotation: Quat,
    /// Rest scale relative to the parent.
    pub scale: Vec3,
    /// Mesh space to joint space at bind time.
    pub inverse_bind: Mat4,
}

/// Linear keyframes of one joint property.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Animated joint.
    pub joint: u16,
    /// Animated property.
    pub path: ChannelPath,
    /// Strictly increasing key times in seconds.
    pub times: Vec<f32>,
    /// One value per key.
    pub values: Vec<Vec4>,
}

/// Joints plus one looping animation.
#[derive(Debug, Clone, PartialEq)]
pub struct Skeleton {
    /// Parent-before-child joints.
    pub joints: Vec<Joint>,
    /// Transform applied above the root joints (non-joint ancestors in the source file).
    pub root: Mat4,
    /// Animation channels.
    pub channels: Vec<Channel>,
    /// Animation length in seconds (it loops); 0 for a still pose.
    pub duration: f32,
}

impl Skeleton {
    /// Validates the invariants the skinning relies on; returns a reason when broken.
    pub fn validate(&self) -> Result<(), String> {
        for (i, j) in self.joints.iter().enumerate() {
            if let Some(p) = j.parent {
                if usize::from(p) >= i {
                    return Err(format!("joint {i} has parent {p}, not before it"));
                }
            }
            if !j.inverse_bind.is_finite() || !j.translation.is_finite() || !j.rotation.is_finite()
            {
                return Err(format!("joint {i} has non-finite rest pose"));
            }
        }
        for (k, c) in self.channels.iter().enumerate() {
            if usize::from(c.joint) >= self.joints.len() {
                return Err(format!(
                    "channel {k} targets joint {} (out of range)",
                    c.joint
                ));
            }
            if c.times.is_empty() || c.times.len() != c.values.len() {
                return Err(format!(
                    "channel {k}: {} times, {} values",
                    c.times.len(),
                    c.values.len()
                ));
            }
            if c.times.iter().any(|t| !t.is_finite()) || c.times.windows(2).any(|w| w[1] < w[0]) {
                return Err(format!("channel {k}: key times not increasing"));
            }
            if c.values.iter().any(|v| !v.is_finite()) {
                return Err(format!("channel {k}: non-finite key value"));
            }
        }
        if !self.duration.is_finite() || self.duration < 0.0 {
            return Err("non-finite animation duration".into());
        }
        Ok(())
    }

    /// Skinning matrices (joint global * inverse bind) at time `t` seconds (looping).
    pub fn pose(&self, t: f32) -> Vec<Mat4> {
        let t = if self.duration > 0.0 {
            t.rem_euclid(self.duration)
        } else {
            0.0
        };
        let mut trs: Vec<(Vec3, Quat, Vec3)> = self
            .joints
            .iter()
            .map(|j| (j.translation, j.rotation, j.scale))
            .collect();
        for c in &self.channels {
            let v = sample(c, t);
            let e = &mut trs[usize::from(c.joint)];
            match c.path {
                ChannelPath::Translation => e.0 = v.truncate(),
                ChannelPath::Rotation => e.1 = Quat::from_vec4(v).normalize(),
                ChannelPath::Scale => e.2 = v.truncate(),
            }
        }
        let mut global: Vec<Mat4> = Vec::with_capacity(self.joints.len());
        for (j, (s_t, s_r, s_s)) in self.joints.iter().zip(trs) {
            let local = Mat4::from_scale_rotation_translation(s_s, s_r, s_t);
            let parent = j.parent.map_or(self.root, |p| global[usize::from(p)]);
            global.push(parent * local);
        }
        global
            .iter()
            .zip(&self.joints)
            .map(|(g, j)| *g * j.inverse_bind)
            .collect()
    }
}

fn sample(c: &Channel, t: f32) -> Vec4 {
    let n = c.times.len();
    if t <= c.times[0] {
        return c.values[0];
    }
    if t >= c.times[n - 1] {
        return c.values[n - 1];
    }
    let k = c.times.partition_point(|&x| x <= t).clamp(1, n - 1);
    let (t0, t1) = (c.times[k - 1], c.times[k]);
    let f = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
    let (a, b) = (c.values[k - 1], c.values[k]);
    if c.path == ChannelPath::Rotation {
        Quat::from_vec4(a)
            .normalize()
            .slerp(Quat::from_vec4(b).normalize(), f)
            .into()
    } else {
        a.lerp(b, f)
    }
}

/// The animation time of a skinned instance at world time `time` seconds: every instance gets
/// its own phase, derived from its id, so a crowd does not move in lockstep. The streaming
/// world, the facade's bridge and the ground-truth reference all pose with this.
pub fn animation_time(instance: crate::model::InstanceId, time: f32) -> f32 {
    time + (instance.0 % 97) as f32 * 0.037
}

/// Deforms one LOD's vertices with the given skinning matrices (from [`Skeleton::pose`]) into
/// `out` (mesh space). Static geometry (no skin) is copied unchanged.
pub fn skin_positions(geometry: &LodGeometry, matrices: &[Mat4], out: &mut Vec<[f32; 3]>) {
    out.clear();
    let Some(skin) = &geometry.skin else {
        out.extend_from_slice(&geometry.positions);
        return;
    };
    out.reserve(geometry.positions.len());
    for ((p, j), w) in geometry
        .positions
        .iter()
        .zip(&skin.joints)
        .zip(&skin.weights)
    {
        let p = Vec3::from(*p);
        let mut acc = Vec3::ZERO;
        for k in 0..4 {
            if w[k] != 0.0 {
                if let Some(m) = matrices.get(usize::from(j[k])) {
                    acc += w[k] * m.transform_point3(p);
                }
            }
        }
        out.push(acc.to_array());
    }
}

/// One skinning task: a LOD, the animation time, and where the deformed positions go.
#[derive(Debug)]
pub struct SkinJob<'a> {
    /// The geometry to deform (must carry [`crate::SkinWeights`] to move).
    pub geometry: &'a LodGeometry,
    /// Animation time in seconds.
    pub time: f32,
    /// Output: deformed mesh-space positions, one per vertex of `geometry`.
    pub positions: Vec<[f32; 3]>,
}

/// Runs every job, spread over up to `threads` scoped threads.
///
/// ```
/// use rtstream_streaming::{procedural, skin::{skin_parallel, SkinJob}};
/// let mesh = procedural::character(0);
/// let mut jobs: Vec<SkinJob> = (0..8)
///     .map(|i| SkinJob { geometry: &mesh.lods[0], time: i as f32 * 0.1, positions: Vec::new() })
///     .collect();
/// skin_parallel(&mut jobs, 2);
/// assert_eq!(jobs[3].positions.len(), mesh.lods[0].positions.len());
/// ```
pub fn skin_parallel(jobs: &mut [SkinJob<'_>], threads: usize) {
    let _span = tracing::trace_span!("skin", jobs = jobs.len()).entered();
    let threads = threads.max(1);
    let chunk = jobs.len().div_ceil(threads).max(1);
    std::thread::scope(|s| {
        for part in jobs.chunks_mut(chunk) {
            s.spawn(move || {
                for job in part {
                    let m = job
                        .geometry
                        .skin
                        .as_ref()
                        .map(|sk| sk.skeleton.pose(job.time))
                        .unwrap_or_default();
                    skin_positions(job.geometry, &m, &mut job.positions);
                }
            });
        }
    });
}
