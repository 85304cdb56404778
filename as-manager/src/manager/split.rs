//! What the built BLASes are for, now: a diagnostic of where a policy's memory goes (which
//! BLASes an instance record names, which are only asked for, which are kept by the release
//! threshold alone).

use rustc_hash::FxHashSet;
use serde::Serialize;

use super::state::EntryState;
use super::AsManager;
use crate::backend::AsBackend;

/// A count of built BLASes and their bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct SplitPart {
    /// Built BLASes.
    pub count: u32,
    /// Their bytes, as counted against the memory budget (`FrameStats::blas_bytes`).
    pub bytes: u64,
}

impl SplitPart {
    fn add(&mut self, bytes: u64) {
        self.count += 1;
        self.bytes += bytes;
    }
}

/// The built BLASes of the last frame, by what holds them (see [`AsManager::memory_split`]).
/// The first five parts are disjoint and sum to `total`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct MemorySplit {
    /// The frame it describes (the last `update`'s).
    pub frame: u64,
    /// Every built BLAS (`FrameStats::blas_count` and `blas_bytes`).
    pub total: SplitPart,
    /// Static (shared) BLASes that an instance record of the last frame's TLAS names.
    pub in_tlas: SplitPart,
    /// Static BLASes in no record but asked for this frame: an instance targets that LOD and
    /// is culled, or shows another LOD while it waits.
    pub requested: SplitPart,
    /// Static BLASes neither in a record nor asked for, of a mesh that has another LOD in the
    /// TLAS: an LOD the instances left, kept until the release threshold.
    pub superseded: SplitPart,
    /// Static BLASes neither in a record nor asked for, with no LOD of their mesh in the TLAS:
    /// kept by the release threshold alone (the cameras left them).
    pub kept: SplitPart,
    /// Skinned instances' own BLASes.
    pub skinned: SplitPart,
    /// Of the static ones, the far field's proxies (also counted in the parts above).
    pub proxies: SplitPart,
    /// Of the proxies, those an instance record of the last frame's TLAS names.
    pub proxies_in_tlas: SplitPart,
    /// Static BLASes by LOD, finest first (proxies included, as LOD 0).
    pub by_lod: Vec<SplitPart>,
    /// Meshes with at least one static BLAS built.
    pub meshes: u32,
    /// Of them, meshes with more than one LOD built.
    pub meshes_with_several_lods: u32,
}

impl<B: AsBackend> AsManager<B> {
    /// What the built BLASes are for after the last `update`: bytes and counts split by what
    /// holds each one (a record of the TLAS, a request, the release threshold), by LOD and
    /// into skinned and proxy BLASes. A diagnostic: it walks every live BLAS entry, so call it
    /// off the frame path (the examples call it at each new peak of `blas_bytes`).
    pub fn memory_split(&self) -> MemorySplit {
        let frame = self.frame;
        let mut s = MemorySplit {
            frame,
            ..MemorySplit::default()
        };
        let built = || {
            self.tables
                .active
                .iter()
                .map(|&k| &self.tables.entries[k])
                .filter(|e| e.state == EntryState::Built)
        };
        let shown_meshes: FxHashSet<u32> = built()
            .filter(|e| e.owner.is_none() && e.last_in_tlas == Some(frame))
            .map(|e| e.mesh)
            .collect();
        let mut lods_of: rustc_hash::FxHashMap<u32, u32> = Default::default();
        for e in built() {
            s.total.add(e.bytes);
            if e.owner.is_some() {
                s.skinned.add(e.bytes);
                continue;
            }
            *lods_of.entry(e.mesh).or_default() += 1;
            if e.proxy {
                s.proxies.add(e.bytes);
                if e.last_in_tlas == Some(frame) {
                    s.proxies_in_tlas.add(e.bytes);
                }
            }
            let lod = e.lod as usize;
            if s.by_lod.len() <= lod {
                s.by_lod.resize(lod + 1, SplitPart::default());
            }
            s.by_lod[lod].add(e.bytes);
            if e.last_in_tlas == Some(frame) {
                s.in_tlas.add(e.bytes);
            } else if e.last_request == frame {
                s.requested.add(e.bytes);
            } else if shown_meshes.contains(&e.mesh) {
                s.superseded.add(e.bytes);
            } else {
                s.kept.add(e.bytes);
            }
        }
        s.meshes = lods_of.len() as u32;
        s.meshes_with_several_lods = lods_of.values().filter(|&&n| n > 1).count() as u32;
        s
    }
}

#[cfg(test)]
mod tests {
    use glam::{Affine3A, Vec3};

    use super::super::tests::{mesh, run_frame};
    use super::*;
    use crate::backend::model::ModelBackend;
    use crate::synth::counts_chain;
    use crate::{Config, CullMode, InstanceDesc, MeshKind, Viewpoint};

    fn check(m: &AsManager<ModelBackend>, frame: u64) -> MemorySplit {
        let s = m.memory_split();
        let st = m.stats();
        assert_eq!(s.frame, frame);
        assert_eq!(
            (s.total.count, s.total.bytes),
            (st.blas_count, st.blas_bytes),
            "frame {frame}: the split's total is the stats' built BLASes"
        );
        let parts = [s.in_tlas, s.requested, s.superseded, s.kept, s.skinned];
        assert_eq!(parts.iter().map(|p| p.count).sum::<u32>(), s.total.count);
        assert_eq!(parts.iter().map(|p| p.bytes).sum::<u64>(), s.total.bytes);
        let lods: u64 = s.by_lod.iter().map(|p| p.bytes).sum();
        assert_eq!(lods, s.total.bytes - s.skinned.bytes);
        s
    }

    /// An instance seen up close, then from 150 m (a coarser LOD), then from far away: its
    /// BLASes go from in the TLAS to superseded (the LOD it left), then to kept (nothing
    /// near), each released `release_threshold` frames after it was last kept.
    #[test]
    fn the_split_follows_an_lod_change_and_a_departure() {
        let mut c = Config::default();
        c.cull.mode = CullMode::Off;
        let release = c.residency.release_threshold as u64;
        let mut m = AsManager::new(c, ModelBackend::lavapipe()).unwrap();
        let lods = counts_chain(20_000, 4, 5.0 * 0.002);
        let mesh = mesh(&m, "m", MeshKind::Static, 5.0, lods);
        m.add_instance(InstanceDesc::new(mesh, Affine3A::IDENTITY))
            .unwrap();
        let cam = |z: f32| [Viewpoint::new(Vec3::new(0.0, 0.0, -z), Vec3::Z)];
        let mut f = 0;
        let mut step = |m: &mut AsManager<ModelBackend>, z: f32| {
            run_frame(m, f, &cam(z));
            let s = check(m, f);
            f += 1;
            s
        };
        for _ in 0..5 {
            step(&mut m, 8.0);
        }
        let near = step(&mut m, 8.0);
        assert_eq!(near.in_tlas.count, 1, "{near:?}");
        assert_eq!(near.by_lod.first().map(|p| p.count), Some(1), "{near:?}");
        assert_eq!(near.meshes, 1);
        assert_eq!(near.meshes_with_several_lods, 0);

        // From 150 m the instance targets a coarser LOD; once that one shows, the fine one is
        // superseded until released.
        let mut superseded_frames = 0;
        let mut released = false;
        for _ in 0..release + 20 {
            let s = step(&mut m, 150.0);
            assert!(s.in_tlas.count <= 1 && s.kept.count == 0, "{s:?}");
            if s.superseded.count == 1 {
                superseded_frames += 1;
                assert_eq!(s.in_tlas.count, 1, "another LOD of its mesh shows: {s:?}");
                assert_eq!(s.meshes_with_several_lods, 1);
                assert_eq!(s.by_lod[0].count, 1, "the LOD it left: {s:?}");
            } else if superseded_frames > 0 {
                released = true;
                assert_eq!(s.total.count, 1, "only the coarse LOD is left: {s:?}");
                assert_eq!(s.by_lod[0].count, 0, "{s:?}");
                break;
            }
        }
        assert!(released, "the fine LOD was never released");
        assert!(
            (release..=release + 2).contains(&superseded_frames),
            "superseded for {superseded_frames} frames, released after {release}"
        );

        // Far beyond r2: nothing near keeps it, then it goes.
        let s = step(&mut m, 5000.0);
        assert_eq!((s.in_tlas.count, s.kept.count), (0, 1), "{s:?}");
        let mut left = s.total.count;
        for _ in 0..release + 2 {
            left = step(&mut m, 5000.0).total.count;
        }
        assert_eq!(left, 0, "released after the release threshold");
    }
}
