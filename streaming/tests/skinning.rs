//! Skinning: glTF2/simple_skin's skin and animation, and generated characters.

mod common;

use glam::Vec3;
use rtstream_streaming::procedural;
use rtstream_streaming::skin::{skin_parallel, skin_positions, SkinJob};
use rtstream_streaming::{build_lod_chain, load_gltf};

#[test]
fn simple_skin_bends_its_upper_vertices() {
    let dir = common::assets();
    let scene = load_gltf(dir.join("simple_skin/simple_skin.gltf")).expect("simple_skin");
    assert_eq!(scene.meshes.len(), 1);
    let m = &scene.meshes[0];
    let skin = m.skin.clone().expect("skin");
    assert_eq!(skin.skeleton.joints.len(), 2);
    assert_eq!(skin.skeleton.joints[1].parent, Some(0));
    assert!(skin.skeleton.duration > 5.0, "{}", skin.skeleton.duration);
    let chain = build_lod_chain(m.positions.clone(), m.indices.clone(), Some(skin.clone()));
    let lod0 = &chain[0];
    assert!(lod0.skin.is_some());

    // At t = 0 the animation's rotation is the identity: the whole strip moves rigidly (by the
    // file's bind offset: its inverse bind matrices shift x by -0.5).
    let mut rest = Vec::new();
    skin_positions(lod0, &skin.skeleton.pose(0.0), &mut rest);
    let offset = Vec3::from(rest[0]) - Vec3::from(lod0.positions[0]);
    for (a, b) in rest.iter().zip(&lod0.positions) {
        let d = Vec3::from(*a) - Vec3::from(*b);
        assert!(d.distance(offset) < 1e-4, "{a:?} vs {b:?}: not rigid");
    }
    // Mid-animation the top vertices (y = 2) swing sideways; the bottom ones (y = 0) stay.
    let mut bent = Vec::new();
    skin_positions(lod0, &skin.skeleton.pose(2.0), &mut bent);
    let mut top_moved = 0;
    for (p, q) in lod0.positions.iter().zip(&bent) {
        let d = (Vec3::from(*p) + offset).distance(Vec3::from(*q));
        if p[1] < 0.01 {
            assert!(d < 1e-4, "bottom vertex moved {d}");
        }
        if p[1] > 1.99 {
            assert!(d > 0.1, "top vertex moved only {d}");
            top_moved += 1;
        }
    }
    assert!(top_moved >= 2);
}

#[test]
fn characters_skin_in_parallel_like_serially() {
    let mesh = procedural::character(11);
    assert!(mesh.is_skinned());
    assert!(mesh.lods.len() >= 3);
    let jobs_for = |n: usize| -> Vec<SkinJob<'_>> {
        (0..n)
            .map(|i| SkinJob {
                geometry: &mesh.lods[i % mesh.lods.len()],
                time: i as f32 * 0.05,
                positions: Vec::new(),
            })
            .collect()
    };
    let mut serial = jobs_for(40);
    skin_parallel(&mut serial, 1);
    let mut parallel = jobs_for(40);
    skin_parallel(&mut parallel, 4);
    for (a, b) in serial.iter().zip(&parallel) {
        assert_eq!(a.positions, b.positions);
        assert_eq!(a.positions.len(), a.geometry.positions.len());
    }
    // The head moves over time; the feet do not.
    let g = &mesh.lods[0];
    let sk = &g.skin.as_ref().expect("skin").skeleton;
    let (mut a, mut b) = (Vec::new(), Vec::new());
    skin_positions(g, &sk.pose(0.1), &mut a);
    skin_positions(g, &sk.pose(sk.duration * 0.3), &mut b);
    // Vertex indices from the lowest to the highest.
    let mut by_height: Vec<usize> = (0..g.positions.len()).collect();
    by_height.sort_by(|&x, &y| g.positions[x][1].total_cmp(&g.positions[y][1]));
    let (bottom, top) = (by_height[0], *by_height.last().expect("vertex"));
    assert!(Vec3::from(a[top]).distance(Vec3::from(b[top])) > 0.01);
    assert!(Vec3::from(a[bottom]).distance(Vec3::from(b[bottom])) < 1e-4);
}
