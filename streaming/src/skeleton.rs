//! Skeletons and their animations: joints in parent-before-child order (validated on import),
//! each with a rest pose and an inverse bind matrix, and one looping animation made of linear
//! keyframe channels (glTF's translation/rotation/scale paths). Skinning with them is in
//! [`crate::skin`]; meshes hold them ([`crate::model`]). A module of its own so that neither
//! of those two depends on the other.

use glam::{Mat4, Quat, Vec3, Vec4};

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

    /// Skinning matrices (joint global * inverse bind) at time `t` seconds (looping; a
    /// non-finite time is the animation's start).
    pub fn pose(&self, t: f32) -> Vec<Mat4> {
        let t = if !t.is_finite() {
            0.0
        } else if self.duration > 0.0 {
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
