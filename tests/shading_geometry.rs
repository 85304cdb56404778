//! What a shader reads through the backend's shading lookups, checked pixel by pixel against the
//! CPU reference caster on lavapipe with validation on, frames in flight:
//! - a skinned BLAS that is not refitted keeps shading with its last pose while other skinned
//!   BLASes refit every frame (the pose used to live in the frame's upload arena, which the
//!   next use of the slot recycled);
//! - a mesh split into several BLASes reports and shades the mesh's own triangles on every
//!   part (part records reused the mesh's customIndex with part-relative primitive ids).

mod common;

use std::sync::Arc;

use glam::{Mat4, Vec3};
use rtstream::as_manager::backend::vulkan::{VulkanBackend, VulkanBackendDesc, VulkanContext};
use rtstream::as_manager::backend::TlasHandle;
use rtstream::as_manager::record::TlasInstance;
use rtstream::as_manager::synth::grid_geometry;
use rtstream::as_manager::{AsManager, Config, FrameInput, GeometryData, MeshKind, Viewpoint};
use rtstream::renderer::reference::ReferenceScene;
use rtstream::renderer::{Camera, Frame, InstanceShading, RenderDesc, Renderer};

/// A bumpy `n` x `n` grid of side `size`: every triangle has its own normal.
fn bumpy(n: u32, size: f32, phase: f32) -> Arc<GeometryData> {
    let g = grid_geometry(n, size);
    Arc::new(GeometryData {
        positions: g
            .positions
            .iter()
            .map(|p| {
                [
                    p[0],
                    (p[0] * 0.9 + phase).sin() * 0.8 + (p[2] * 1.3 - phase).cos() * 0.6,
                    p[2],
                ]
            })
            .collect(),
        indices: g.indices.clone(),
    })
}

fn face_normal(pos: &[[f32; 3]], idx: &[u32], prim: u32, m: Mat4) -> Vec3 {
    let v = |k: usize| m.transform_point3(Vec3::from(pos[idx[3 * prim as usize + k] as usize]));
    (v(1) - v(0)).cross(v(2) - v(0)).normalize()
}

/// A manager on a Vulkan backend (`desc`) that builds what it sees from the first frame.
fn manager(ctx: &Arc<VulkanContext>, desc: VulkanBackendDesc) -> AsManager<VulkanBackend> {
    let mut config = Config::default();
    config.residency.create_threshold = 1;
    common::manager(ctx, desc, config)
}

/// Frame `frame` seen from `cams`: its TLAS and instance records.
fn update(
    m: &mut AsManager<VulkanBackend>,
    frame: u64,
    cams: &[Viewpoint],
) -> (TlasHandle, Vec<TlasInstance>) {
    let out = m
        .update(FrameInput {
            frame,
            cameras: cams,
        })
        .unwrap();
    (out.tlas, out.instances.to_vec())
}

/// Renders `tlas` with real shading addresses from the backend.
fn render(
    m: &mut AsManager<VulkanBackend>,
    renderer: &mut Renderer,
    tlas: TlasHandle,
    records: &[TlasInstance],
    cam: Camera,
    size: u32,
) -> Frame {
    let backend = m.backend_mut();
    backend.wait_idle().expect("frame completes");
    let mut table = vec![InstanceShading::colour_only([1.0; 4]); 8];
    for r in records {
        let (v, i) = backend.shading_geometry(r.blas_address).expect("live BLAS");
        table[r.custom_index() as usize] = InstanceShading {
            vertices: v,
            indices: i,
            base_color: [1.0; 4],
        };
    }
    let traced = backend.tlas(tlas).expect("TLAS of the last frame");
    let desc = RenderDesc {
        primitive_bases: backend.primitive_bases(tlas),
        ..RenderDesc::new(size, size, cam)
    };
    renderer.render(traced, &table, &desc).expect("render")
}

/// Pixels where GPU and CPU hit the same instance: (count, same primitive, normal agrees).
fn agreement(
    frame: &Frame,
    reference: &ReferenceScene,
    cam: &Camera,
    size: u32,
    normal_of: impl Fn(u32, u32) -> Vec3,
) -> (usize, usize, usize) {
    let cpu = reference.cast(cam, size, size);
    let (mut n, mut same_prim, mut same_normal) = (0, 0, 0);
    for (i, (g, c)) in frame.hits.iter().zip(&cpu).enumerate() {
        let Some(c) = c else { continue };
        if !g.is_hit() || g.instance != c.instance {
            continue;
        }
        n += 1;
        same_prim += usize::from(g.primitive == c.primitive);
        let expect = normal_of(c.instance, c.primitive);
        let got = Vec3::from(frame.normals[i]);
        same_normal += usize::from(got.dot(expect).abs() > 0.99);
    }
    (n, same_prim, same_normal)
}

/// More than 97 % of the `n` hit pixels report the reference's triangle (`same_prim`, failing
/// with "`same_prim`/`n` `prim_what`") and shade with its normal (`same_normal`).
fn assert_most_agree(n: usize, same_prim: usize, same_normal: usize, prim_what: &str) {
    assert!(
        same_prim as f64 > 0.97 * n as f64,
        "{same_prim}/{n} {prim_what}"
    );
    assert!(
        same_normal as f64 > 0.97 * n as f64,
        "{same_normal}/{n} pixels shade with the right normal"
    );
}

#[test]
fn an_unrefitted_skinned_blas_shades_with_its_last_pose_while_others_refit() {
    let ctx = common::context();
    let mut m = manager(&ctx, VulkanBackendDesc::default());
    let base = bumpy(16, 6.0, 0.0);
    let mesh = common::one_lod_mesh(&m, "cloth", MeshKind::Skinned, 5.0, base.clone());
    // A (custom index 0) holds one pose; B (1) gets a new pose every frame.
    let at = [Vec3::new(-4.0, 0.0, 12.0), Vec3::new(4.0, 0.0, 12.0)];
    let ids: Vec<_> = (0..)
        .zip(at)
        .map(|(k, p)| common::place(&m, mesh, p, k))
        .collect();
    let pose_a = Arc::new(bumpy(16, 6.0, 1.7).positions.clone());
    m.set_skinned_pose(ids[0], pose_a.clone()).unwrap();
    let cams = [Viewpoint::new(Vec3::new(0.0, 6.0, 0.0), Vec3::Z)];
    let mut last = None;
    let mut pose_b = Arc::new(Vec::new());
    for frame in 0..12u64 {
        pose_b = Arc::new(bumpy(16, 6.0, 0.4 * frame as f32).positions.clone());
        m.set_skinned_pose(ids[1], pose_b.clone()).unwrap();
        // No wait: frames stay in flight, each slot is reused every other frame.
        last = Some(update(&mut m, frame, &cams));
    }
    let c = m.backend().counters();
    assert!(c.refits + c.rebuilds >= 8, "B refits every frame: {c:?}");
    let (tlas, records) = last.unwrap();
    assert_eq!(records.len(), 2);
    let a_address = records
        .iter()
        .find(|r| r.custom_index() == 0)
        .unwrap()
        .blas_address;
    assert_eq!(
        m.backend().shading_positions(a_address).as_deref(),
        Some(&pose_a[..]),
        "A's shading positions are its pose"
    );

    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    let cam = Camera::look_at(Vec3::new(0.0, 9.0, 2.0), Vec3::new(0.0, 0.0, 12.0), 0.9);
    let size = 96;
    let frame = render(&mut m, &mut renderer, tlas, &records, cam, size);
    let poses = [pose_a.clone(), pose_b.clone()];
    let reference = ReferenceScene::new(
        &[
            (&poses[0][..], &base.indices[..]),
            (&poses[1][..], &base.indices[..]),
        ],
        &[
            (0, Mat4::from_translation(at[0]), 0),
            (1, Mat4::from_translation(at[1]), 1),
        ],
    );
    let (n, same_prim, same_normal) = agreement(&frame, &reference, &cam, size, |inst, prim| {
        face_normal(
            &poses[inst as usize],
            &base.indices,
            prim,
            Mat4::from_translation(at[inst as usize]),
        )
    });
    assert!(n > 1000, "both cloths fill the view ({n} pixels)");
    assert_most_agree(n, same_prim, same_normal, "same triangle");
}

#[test]
fn a_split_mesh_reports_and_shades_its_own_triangles_on_every_part() {
    let ctx = common::context();
    // A 64 KiB part cap: a 40x40-quad grid (3,200 triangles, ~330 KB of BLAS on lavapipe) splits.
    let desc = VulkanBackendDesc {
        max_part_bytes: 64 << 10,
        ..VulkanBackendDesc::default()
    };
    let mut m = manager(&ctx, desc);
    let g = bumpy(40, 20.0, 0.3);
    let mesh = common::one_lod_mesh(&m, "big", MeshKind::Static, 15.0, g.clone());
    let at = Vec3::new(0.0, 0.0, 20.0);
    common::place(&m, mesh, at, 0);
    let cams = [Viewpoint::new(Vec3::ZERO, Vec3::Z)];
    let mut last = None;
    for frame in 0..4 {
        last = Some(update(&mut m, frame, &cams));
    }
    let (tlas, records) = last.unwrap();
    assert_eq!(
        records.len(),
        1,
        "the manager sees one instance of one BLAS"
    );
    let parts = m.stats().tlas_instances;
    assert!(
        parts > 1,
        "the stats count the real TLAS, one record per part ({parts})"
    );
    assert_eq!(m.backend().counters().split_meshes, 1);
    assert_ne!(m.backend().primitive_bases(tlas), 0);

    let mut renderer = Renderer::new(ctx.clone()).unwrap();
    // Straight down at the whole grid: every part is hit.
    let cam = Camera::look_at(
        Vec3::new(0.0, 30.0, 20.0),
        Vec3::new(0.0, 0.0, 20.001),
        60f32.to_radians(),
    );
    let size = 96;
    let frame = render(&mut m, &mut renderer, tlas, &records, cam, size);
    let reference = ReferenceScene::new(
        &[(&g.positions[..], &g.indices[..])],
        &[(0, Mat4::from_translation(at), 0)],
    );
    let (n, same_prim, same_normal) = agreement(&frame, &reference, &cam, size, |_, prim| {
        face_normal(&g.positions, &g.indices, prim, Mat4::from_translation(at))
    });
    let total = (size * size) as usize;
    eprintln!(
        "split mesh: {parts} parts; {same_prim}/{n} hit pixels report the mesh's triangle, \
         {same_normal}/{n} shade with its normal (CPU reference)"
    );
    assert!(n > total / 3, "the grid fills the view ({n} pixels)");
    assert_most_agree(
        n,
        same_prim,
        same_normal,
        "pixels report the mesh's triangle",
    );
}
