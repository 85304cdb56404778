//! Scene set-up shared by the as-manager tests (through the harness) and the facade's tests
//! (`tests/common` includes this file): meshes with one exact LOD, and instances placed by a
//! translation with a custom index, and frames seen from one camera. The including module names
//! the as-manager crate `rtm`.

use std::sync::Arc;

use super::rtm::backend::AsBackend;
use super::rtm::{
    AsManager, FrameInput, FrameOutput, GeometryData, InstanceDesc, InstanceId, LodDesc,
    LodGeometry, MeshDesc, MeshId, MeshKind, Viewpoint,
};
use glam::{Affine3A, Vec3};

/// A mesh's one level of detail: `geometry` itself, exact (geometric error 0).
pub fn one_lod(geometry: Arc<GeometryData>) -> Vec<LodDesc> {
    vec![LodDesc {
        geometry: LodGeometry::Data(geometry),
        geometric_error: 0.0,
    }]
}

/// Registers `geometry` as mesh `name` of `kind`, bounding radius `radius`, with one exact LOD.
pub fn one_lod_mesh<B: AsBackend>(
    m: &AsManager<B>,
    name: impl Into<String>,
    kind: MeshKind,
    radius: f32,
    geometry: Arc<GeometryData>,
) -> MeshId {
    m.register_mesh(MeshDesc::new(name, kind, radius, one_lod(geometry)))
        .unwrap()
}

/// Places `mesh` translated to `at`, with custom index `custom_index`.
pub fn place<B: AsBackend>(
    m: &AsManager<B>,
    mesh: MeshId,
    at: Vec3,
    custom_index: u32,
) -> InstanceId {
    let mut d = InstanceDesc::new(mesh, Affine3A::from_translation(at));
    d.custom_index = custom_index;
    m.add_instance(d).unwrap()
}

/// Frame `frame` of `m` seen from the one viewpoint `camera`.
pub fn update_from<B: AsBackend>(
    m: &mut AsManager<B>,
    frame: u64,
    camera: Viewpoint,
) -> super::rtm::Result<FrameOutput<'_>> {
    m.update(FrameInput {
        frame,
        cameras: &[camera],
    })
}
