//! CPU skinning with a [`Skeleton`] (see [`crate::skeleton`]). [`skin_positions`] deforms one LOD's
//! vertices; [`skin_parallel`] spreads many instances over rayon's pool, which is what the world
//! does each frame for its loaded skinned instances (the manager refits their BLASes from it).

use glam::{Mat4, Vec3};

use crate::model::MeshLod;
pub use crate::skeleton::{Channel, ChannelPath, Joint, Skeleton};

/// The animation time of a skinned instance at world time `time` seconds: every instance gets
/// its own phase, derived from its id, so a crowd does not move in lockstep. The streaming
/// world, the facade's bridge and the ground-truth reference all pose with this.
pub fn animation_time(instance: crate::model::WorldInstanceId, time: f32) -> f32 {
    time + (instance.0 % 97) as f32 * 0.037
}

/// Deforms one LOD's vertices with the given skinning matrices (from [`Skeleton::pose`]) into
/// `out` (mesh space). Static geometry (no skin) is copied unchanged.
pub fn skin_positions(geometry: &MeshLod, matrices: &[Mat4], out: &mut Vec<[f32; 3]>) {
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
    pub geometry: &'a MeshLod,
    /// Animation time in seconds.
    pub time: f32,
    /// Output: deformed mesh-space positions, one per vertex of `geometry`.
    pub positions: Vec<[f32; 3]>,
}

/// Runs every job, split into up to `threads` chunks on rayon's pool (created once per
/// process, not per frame).
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
    use rayon::prelude::*;
    jobs.par_chunks_mut(chunk).for_each(|part| {
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
