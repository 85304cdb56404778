//! The near leaves' detail beyond r2 kept incrementally by the landmark set
//! (`FarFieldConfig::incremental_detail`) against the residency pass that visits it every frame
//! (`incremental_detail: false`): two managers see the same world, cameras and changes, and
//! every frame their TLAS holds the same instances at the same LODs, the same proxies, and
//! the same hand-overs, through walks at any speed, oscillations across r2, a teleport, a
//! second camera, churn and a failed frame.

use std::collections::BTreeMap;

use glam::{Affine3A, Vec3};
use rtstream_stats::Rng;

use super::state::EntryState;
use super::tests::{mesh, proxied_group};
use crate::backend::model::ModelBackend;
use crate::backend::{BackendError, FaultPoint};
use crate::synth::counts_chain;
use crate::*;

const LEAVES: i32 = 12; // 12 x 12 leaves of 100 m: 1.2 km
const LEAF_M: f32 = 100.0;
const PROXY_CI: u32 = 1_000_000;

fn config(incremental: bool) -> Config {
    let mut c = Config {
        freeze_cost_model: true,
        ..Config::default()
    };
    c.far_field.incremental_detail = incremental;
    c.far_field.keep_range = 700.0;
    // Everything queued is built the same frame: the order of equal requests cannot differ.
    c.build.max_primitives = u64::MAX / 4;
    c.build.max_gpu_ms = 1e9;
    c
}

/// One manager and what the test changes in it.
struct Side {
    m: AsManager<ModelBackend>,
    meshes: Vec<MeshId>,
    leaves: Vec<GroupId>,
    /// Per leaf, a mesh of its own (a leaf turning near then waits for its BLASes: the
    /// hand-over keeps its proxy meanwhile).
    houses: Vec<MeshId>,
    live: Vec<InstanceId>,
}

/// A position inside the leaf of `p` (leaves hold their instances' centres, as a level's
/// bounds do), moved by up to 30 m.
fn moved_within_leaf(rng: &mut Rng, p: Vec3) -> Vec3 {
    let (x, z) = ((p.x / LEAF_M).floor(), (p.z / LEAF_M).floor());
    let clamp = |v: f32, cell: f32| v.clamp(cell * LEAF_M + 0.5, (cell + 1.0) * LEAF_M - 0.5);
    Vec3::new(
        clamp(p.x + rng.range(-30.0, 30.0), x),
        0.0,
        clamp(p.z + rng.range(-30.0, 30.0), z),
    )
}

/// A manager and its world; `proxy_data`: the proxies' LOD is data (a backend that builds
/// only from data can build them).
fn side(incremental: bool, proxy_data: bool) -> Side {
    let m = AsManager::new(config(incremental), ModelBackend::lavapipe()).unwrap();
    // Radii from 0.3 to 30 m (the large ones can be landmarks), 1 to 5 LODs; two of them
    // skinned (never candidates: the residency pass visits them beyond r2 in near leaves).
    let meshes: Vec<MeshId> = (0..20)
        .map(|i| {
            let radius = 0.3 + 30.0 * (i as f32 / 19.0).powi(3);
            let kind = if i % 9 == 4 {
                MeshKind::Skinned
            } else {
                MeshKind::Static
            };
            let lods = counts_chain(3000, 1 + i % 5, 0.02 * radius);
            mesh(&m, format!("m{i}"), kind, radius, lods)
        })
        .collect();
    let proxy = |m: &AsManager<ModelBackend>, n: u32| {
        mesh(
            m,
            format!("proxy{n}"),
            MeshKind::Static,
            80.0,
            if proxy_data {
                vec![LodDesc {
                    geometry: LodGeometry::Data(crate::synth::grid_geometry(8, 1.0)),
                    geometric_error: 0.0,
                }]
            } else {
                counts_chain(500, 1, 0.0)
            },
        )
    };
    let mut leaves = Vec::new();
    let mut n = 0;
    for px in 0..LEAVES / 2 {
        for pz in 0..LEAVES / 2 {
            let lo = [px as f32 * 2.0 * LEAF_M, -10.0, pz as f32 * 2.0 * LEAF_M];
            let hi = [lo[0] + 2.0 * LEAF_M, 60.0, lo[2] + 2.0 * LEAF_M];
            let parent = proxied_group(&m, None, (lo, hi), PROXY_CI + n, (proxy(&m, n), 6.0));
            n += 1;
            for (dx, dz) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let lo = [
                    (px * 2 + dx) as f32 * LEAF_M,
                    -10.0,
                    (pz * 2 + dz) as f32 * LEAF_M,
                ];
                let hi = [lo[0] + LEAF_M, 60.0, lo[2] + LEAF_M];
                let own = (proxy(&m, n), 1.5);
                let leaf = proxied_group(&m, Some(parent), (lo, hi), PROXY_CI + n, own);
                n += 1;
                leaves.push(leaf);
            }
        }
    }
    let houses = (0..leaves.len())
        .map(|i| {
            let lods = counts_chain(2000, 3, 0.05);
            mesh(&m, format!("house{i}"), MeshKind::Static, 4.0, lods)
        })
        .collect();
    Side {
        m,
        meshes,
        leaves,
        houses,
        live: Vec::new(),
    }
}

/// The changes both sides see, from one seeded generator.
struct Script {
    rng: Rng,
    next_ci: u32,
}

impl Script {
    fn transform(&mut self) -> Affine3A {
        let side = LEAVES as f32 * LEAF_M;
        let p = Vec3::new(
            self.rng.range(1.0, side - 1.0),
            0.0,
            self.rng.range(1.0, side - 1.0),
        );
        Affine3A::from_scale_rotation_translation(
            Vec3::splat(self.rng.range(0.5, 2.0)),
            glam::Quat::IDENTITY,
            p,
        )
    }

    /// An instance to add: its mesh (`None`: its leaf's own), transform, custom index and
    /// whether it has a leaf.
    fn add(&mut self, meshes: usize) -> (Option<usize>, Affine3A, u32, bool) {
        let mesh = (self.rng.below(3) > 0).then(|| self.rng.below(meshes));
        let t = self.transform();
        let ci = self.next_ci;
        self.next_ci += 1;
        (mesh, t, ci, self.rng.below(6) > 0)
    }
}

impl Side {
    fn add(&mut self, (mesh, t, ci, grouped): (Option<usize>, Affine3A, u32, bool)) {
        let p = t.translation;
        let (x, z) = ((p.x / LEAF_M) as i32, (p.z / LEAF_M) as i32);
        // Leaves were registered per 2x2 block: block-major, then (dx, dz).
        let block = (x / 2) * (LEAVES / 2) + z / 2;
        let leaf = (block * 4 + (x % 2) * 2 + z % 2) as usize;
        let mesh = mesh.map_or(self.houses[leaf], |i| self.meshes[i]);
        let mut d = InstanceDesc::new(mesh, t);
        d.custom_index = ci;
        if grouped {
            d.group = self.leaves.get(leaf).copied();
        }
        self.live.push(self.m.add_instance(d).unwrap());
    }

    /// Prints the state of the instance of custom index `ci` (a failure's context).
    fn describe(&self, ci: u32, cams: &[Viewpoint]) {
        let m = &self.m;
        for slot in 0..m.tables.instances.len() as u32 {
            let Some(ge) = m.grid.get(slot) else { continue };
            if m.templates[slot as usize].custom_index() != ci {
                continue;
            }
            let c = Vec3::from(ge.center);
            let d = cams
                .iter()
                .map(|v| v.position.distance(c))
                .fold(f32::INFINITY, f32::min);
            let h = &ge.data;
            eprintln!(
                "ci {ci}: {d:.1} m, radius {:.1}, leaf {} near {}, member {}, LOD {}, culled {}",
                ge.radius,
                h.group,
                m.far.is_near_leaf(h.group),
                m.landmarks.is_member(slot),
                h.lod_target,
                h.culled
            );
        }
    }

    /// The TLAS of the last frame as (custom index, mesh slot, LOD), sorted.
    fn tlas(&self, records: &[crate::record::TlasInstance]) -> Vec<(u32, u32, u8)> {
        let by_address: BTreeMap<u64, (u32, u8)> = self
            .m
            .tables
            .entries
            .values()
            .filter(|e| e.state == EntryState::Built)
            .map(|e| (e.record_address(&self.m.backend), (e.mesh, e.lod)))
            .collect();
        let mut v: Vec<(u32, u32, u8)> = records
            .iter()
            .map(|r| {
                let (mesh, lod) = by_address
                    .get(&r.blas_address)
                    .copied()
                    .unwrap_or((u32::MAX, u8::MAX));
                (r.custom_index(), mesh, lod)
            })
            .collect();
        v.sort_unstable();
        v
    }
}

/// Where the camera is at `frame`: walks from 1 to 40 m a frame, an oscillation across r2 of
/// a leaf, a teleport, a second camera.
fn cameras(frame: u64) -> Vec<Vec3> {
    let f = frame as f32;
    let c = LEAVES as f32 * LEAF_M * 0.5;
    let at = |t: f32| {
        Vec3::new(
            c + 350.0 * (t * 0.9).sin(),
            0.0,
            c + 300.0 * (t * 0.6).cos(),
        )
    };
    match frame {
        0..=119 => vec![at(f * 0.003)],
        120..=199 => vec![at(0.36 + (f - 120.0) * 0.08)],
        200..=279 => {
            let p = at(6.8);
            vec![p + Vec3::X * if frame % 2 == 0 { 4.0 } else { -4.0 }]
        }
        280..=359 => vec![at(6.8) + Vec3::new(0.5 * (f - 280.0), 0.0, 0.0)],
        360 => vec![Vec3::new(150.0, 0.0, 1050.0)],
        361..=439 => vec![
            Vec3::new(150.0 + 2.0 * (f - 360.0), 0.0, 1050.0),
            at(2.0 + 0.01 * (f - 360.0)),
        ],
        _ => vec![at(3.0 + 0.004 * (f - 440.0))],
    }
}

#[test]
fn kept_detail_matches_the_per_frame_pass_every_frame() {
    compare_kept_and_visited(false);
}

/// The same with LOD data coming and going (a backend that builds only from data): LODs fall
/// back to others, and both sides must fall back alike.
#[test]
fn kept_detail_matches_the_per_frame_pass_with_lod_data_coming_and_going() {
    compare_kept_and_visited(true);
}

/// Gives a LOD data, or takes it away (counts only), on both sides.
fn set_data(sides: [&mut Side; 2], mesh: usize, lod: usize, data: bool) {
    for s in sides {
        let id = s
            .meshes
            .get(mesh)
            .copied()
            .unwrap_or_else(|| s.houses[mesh - s.meshes.len()]);
        let g = if data {
            LodGeometry::Data(crate::synth::grid_geometry(8, 1.0))
        } else {
            LodGeometry::Counts {
                vertices: 81,
                triangles: 128,
            }
        };
        // A mesh has 1 to 5 LODs: a LOD it lacks is refused alike on both sides.
        let _ = s.m.set_lod_geometry(id, lod, g);
    }
}

fn compare_kept_and_visited(data_churn: bool) {
    let mut kept = side(true, data_churn);
    let mut visited = side(false, data_churn);
    let mut script = Script {
        rng: Rng::new(0x00de_7a11),
        next_ci: 0,
    };
    for _ in 0..1500 {
        let a = script.add(kept.meshes.len());
        kept.add(a);
        visited.add(a);
    }
    let all_meshes = kept.meshes.len() + kept.houses.len();
    if data_churn {
        for s in [&mut kept, &mut visited] {
            s.m.backend_mut().require_geometry = true;
        }
        for mesh in 0..all_meshes {
            for lod in 0..5 {
                let data = script.rng.below(3) > 0;
                set_data([&mut kept, &mut visited], mesh, lod, data);
            }
        }
    }
    let (mut detail_seen, mut culled_seen, mut handovers) = (0u64, 0u64, 0u64);
    for frame in 0..520u64 {
        // Churn both sides the same way.
        if frame % 7 == 3 {
            let a = script.add(kept.meshes.len());
            kept.add(a);
            visited.add(a);
            let i = script.rng.below(kept.live.len());
            let (k, v) = (kept.live.swap_remove(i), visited.live.swap_remove(i));
            kept.m.remove_instance(k).unwrap();
            visited.m.remove_instance(v).unwrap();
            let i = script.rng.below(kept.live.len());
            let at = kept.m.tables.instances[kept.live[i].index() as usize]
                .as_ref()
                .unwrap()
                .center;
            let t = Affine3A::from_translation(moved_within_leaf(&mut script.rng, at));
            kept.m.set_transform(kept.live[i], t).unwrap();
            visited.m.set_transform(visited.live[i], t).unwrap();
        }
        if data_churn && frame % 10 == 5 {
            for _ in 0..12 {
                let (mesh, lod) = (script.rng.below(all_meshes), script.rng.below(5));
                let data = script.rng.below(2) == 0;
                set_data([&mut kept, &mut visited], mesh, lod, data);
            }
        }
        if frame == 300 {
            for s in [&mut kept, &mut visited] {
                s.m.backend_mut()
                    .inject_fault(FaultPoint::BuildTlas, BackendError::Other("test".into()));
            }
        }
        let cams: Vec<Viewpoint> = cameras(frame)
            .into_iter()
            .map(|p| Viewpoint::new(p, Vec3::Z))
            .collect();
        let input = FrameInput {
            frame,
            cameras: &cams,
        };
        let a = kept.m.update(input).map(|o| o.instances.to_vec());
        let b = visited.m.update(input).map(|o| o.instances.to_vec());
        match (a, b) {
            (Ok(a), Ok(b)) => {
                let (ta, tb) = (kept.tlas(&a), visited.tlas(&b));
                if ta != tb {
                    for x in ta.iter().filter(|x| !tb.contains(x)).take(4) {
                        kept.describe(x.0, &cams);
                        visited.describe(x.0, &cams);
                    }
                    let only_a: Vec<_> = ta.iter().filter(|x| !tb.contains(x)).take(8).collect();
                    let only_b: Vec<_> = tb.iter().filter(|x| !ta.contains(x)).take(8).collect();
                    panic!(
                        "frame {frame}: {} records kept, {} visited; only kept {only_a:?}, only visited {only_b:?}",
                        ta.len(),
                        tb.len()
                    );
                }
                let s = kept.m.stats();
                detail_seen += u64::from(s.far_detail_instances);
                culled_seen += u64::from(s.culled);
                handovers += kept.m.far.covered_near_count() as u64;
            }
            (Err(_), Err(_)) => assert_eq!(frame, 300, "only the injected frame fails"),
            (a, b) => panic!(
                "frame {frame}: one side failed: {:?} / {:?}",
                a.err(),
                b.err()
            ),
        }
        kept.m.check_invariants().unwrap();
    }
    eprintln!(
        "detail records {detail_seen}, culled {culled_seen}, near leaves handing over {handovers}"
    );
    // The walk exercised what it is about.
    assert!(
        detail_seen > 10_000,
        "{detail_seen} detail records over the run"
    );
    assert!(culled_seen > 0 && handovers > 0);
}
