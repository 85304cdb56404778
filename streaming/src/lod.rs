//! LOD chains from meshoptimizer's simplifier.
//!
//! Each LOD is simplified from the previous one towards half its triangles with
//! `meshopt::simplify` (topology-preserving, absolute error so the reported error is in mesh-space
//! metres). When that cannot reach ~half (closed small meshes, locked borders), the sloppy
//! simplifier is tried; when neither reduces to at most [`MAX_RATIO`] of the previous count the
//! chain stops. The error of LOD k is the sum of the reported errors of the steps 1..=k, an upper
//! bound of its distance to LOD0, so errors are monotone by construction. Every LOD gets its own
//! compact vertex buffer (unused vertices dropped, skin weights carried along).

use std::sync::Arc;

use meshopt::SimplifyOptions;

use crate::model::{MeshLod, SkinWeights};

/// A LOD is kept only if it has at most this fraction of the previous LOD's triangles.
pub const MAX_RATIO: f32 = 0.55;
/// No LOD is made below this many triangles.
pub const MIN_TRIANGLES: usize = 8;
/// At most this many LODs per mesh.
pub const MAX_LODS: usize = 8;

/// Builds the LOD chain of a triangle mesh; LOD0 is the input itself (compacted).
///
/// The caller must have validated the input (finite positions, indices in range, multiple of 3).
///
/// ```
/// use rtstream_streaming::{build_lod_chain, procedural};
/// let (positions, indices) = procedural::grid_terrain(32, 10.0, 0.0, 7);
/// let chain = build_lod_chain(positions, indices, None);
/// assert!(chain.len() > 2);
/// for w in chain.windows(2) {
///     assert!(w[1].triangle_count() * 2 <= w[0].triangle_count() + w[0].triangle_count() / 10);
///     assert!(w[1].error >= w[0].error);
/// }
/// ```
pub fn build_lod_chain(
    positions: Vec<[f32; 3]>,
    indices: Vec<u32>,
    skin: Option<SkinWeights>,
) -> Vec<MeshLod> {
    let lod0 = compact(&positions, &indices, skin.as_ref(), 0.0);
    let mut chain = vec![lod0];
    while chain.len() < MAX_LODS {
        let Some(prev) = chain.last() else { break };
        let prev_tris = prev.triangle_count();
        if prev_tris < MIN_TRIANGLES * 2 {
            break;
        }
        let target = (prev_tris / 2) * 3;
        let max_tris = (prev_tris as f32 * MAX_RATIO) as usize;
        let mut err = 0.0f32;
        let mut idx = meshopt::simplify_decoder(
            &prev.indices,
            &prev.positions,
            target,
            f32::MAX,
            SimplifyOptions::ErrorAbsolute,
            Some(&mut err),
        );
        if idx.len() / 3 > max_tris {
            err = 0.0;
            idx = meshopt::simplify_sloppy_decoder(
                &prev.indices,
                &prev.positions,
                target,
                f32::MAX,
                Some(&mut err),
            );
            // Sloppy reports a relative error; convert to mesh units.
            err *= meshopt::simplify_scale_decoder(&prev.positions);
        }
        let tris = idx.len() / 3;
        if tris > max_tris || tris < MIN_TRIANGLES || !err.is_finite() {
            break;
        }
        let error = prev.error + err.max(0.0);
        let next = compact(&prev.positions, &idx, prev.skin.as_ref(), error);
        chain.push(next);
    }
    chain
}

/// Keeps only the vertices the index buffer uses (in first-use order) and remaps the indices.
pub(crate) fn compact(
    positions: &[[f32; 3]],
    indices: &[u32],
    skin: Option<&SkinWeights>,
    error: f32,
) -> MeshLod {
    let mut remap = vec![u32::MAX; positions.len()];
    let mut out_pos = Vec::new();
    let mut order = Vec::new();
    let mut out_idx = Vec::with_capacity(indices.len());
    for &i in indices {
        let slot = &mut remap[i as usize];
        if *slot == u32::MAX {
            *slot = out_pos.len() as u32;
            out_pos.push(positions[i as usize]);
            order.push(i as usize);
        }
        out_idx.push(*slot);
    }
    let skin = skin.map(|s| SkinWeights {
        joints: order.iter().map(|&i| s.joints[i]).collect(),
        weights: order.iter().map(|&i| s.weights[i]).collect(),
        skeleton: Arc::clone(&s.skeleton),
    });
    MeshLod {
        positions: out_pos,
        indices: out_idx,
        error,
        skin,
    }
}
