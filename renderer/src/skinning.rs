//! Minimal CPU linear-blend skinning, for tests and examples that need a deforming mesh in a
//! given pose (the streaming crate owns real glTF skins; the manager refits skinned BLASes).

use glam::{Mat4, Vec3};

/// Skins `positions` (bind pose) with up to four joints per vertex:
/// `p' = sum_k weights[v][k] * joint_matrices[joints[v][k]] * p`. Weights need not be normalised
/// (they are divided by their sum); a vertex with zero total weight stays where it is.
///
/// # Panics
/// If the slices differ in length or a joint index is out of range (a broken contract).
pub fn linear_blend(
    positions: &[[f32; 3]],
    joints: &[[u16; 4]],
    weights: &[[f32; 4]],
    joint_matrices: &[Mat4],
) -> Vec<[f32; 3]> {
    assert_eq!(positions.len(), joints.len(), "one joint set per vertex");
    assert_eq!(positions.len(), weights.len(), "one weight set per vertex");
    positions
        .iter()
        .zip(joints.iter().zip(weights))
        .map(|(p, (j, w))| {
            let p = Vec3::from(*p);
            let total: f32 = w.iter().sum();
            if total <= 0.0 {
                return p.to_array();
            }
            let mut out = Vec3::ZERO;
            for k in 0..4 {
                if w[k] != 0.0 {
                    out += joint_matrices[j[k] as usize].transform_point3(p) * (w[k] / total);
                }
            }
            out.to_array()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_pose_keeps_positions_and_blends_halfway() {
        let pos = [[1.0, 2.0, 3.0], [0.0, 1.0, 0.0]];
        let joints = [[0, 1, 0, 0], [0, 1, 0, 0]];
        let weights = [[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]];
        let m = [Mat4::IDENTITY, Mat4::from_translation(Vec3::X * 2.0)];
        let out = linear_blend(&pos, &joints, &weights, &m);
        assert_eq!(out[0], [1.0, 2.0, 3.0]);
        assert_eq!(out[1], [1.0, 1.0, 0.0]);
    }
}
