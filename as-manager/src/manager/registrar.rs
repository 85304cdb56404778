//! `Registrar`: the thread-safe, queued half of the API. Loader threads call it; `update`
//! drains the queue in call order (ids are allocated and commands queued under one lock, so
//! queue order, id order and application order agree).

use std::sync::Arc;

use glam::Affine3A;
use parking_lot::Mutex;

use crate::ids::IdAllocator;
use crate::mesh::{LodGeometry, MeshDesc, MeshKind};
use crate::{AsError, GroupId, InstanceId, MeshId, Result};

/// Parameters of a placed instance.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceDesc {
    /// Its mesh.
    pub mesh: MeshId,
    /// Object to world.
    pub transform: Affine3A,
    /// `instanceCustomIndex` (24 bits), e.g. the engine's per-instance material/record index.
    pub custom_index: u32,
    /// Visibility mask (8 bits).
    pub mask: u8,
    /// `instanceShaderBindingTableRecordOffset` (24 bits).
    pub sbt_offset: u32,
    /// Extra instance flags (`record::INSTANCE_*`); FORCE_OPAQUE is added for opaque meshes.
    pub flags: u8,
    /// The leaf group the instance belongs to (its far-field proxy stands for it beyond r2).
    pub group: Option<GroupId>,
}

/// A group of instances: a node of the far-field tree. Leaves are what instances name
/// ([`InstanceDesc::group`]); a parent's proxy stands for all its leaves at once, farther away.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupDesc {
    /// The parent node (None for a root).
    pub parent: Option<GroupId>,
    /// World bounds of everything the group holds (its instances and its proxy).
    pub bounds_min: [f32; 3],
    /// Upper corner of the bounds.
    pub bounds_max: [f32; 3],
    /// `instanceCustomIndex` of the proxy's TLAS record (24 bits).
    pub custom_index: u32,
    /// Visibility mask of the proxy's TLAS record.
    pub mask: u8,
}

impl InstanceDesc {
    /// An instance with mask 0xff, custom index 0, SBT offset 0, no extra flags.
    pub fn new(mesh: MeshId, transform: Affine3A) -> Self {
        Self {
            mesh,
            transform,
            custom_index: 0,
            mask: 0xff,
            sbt_offset: 0,
            flags: 0,
            group: None,
        }
    }
}

#[derive(Debug)]
pub(crate) enum Command {
    RegisterMesh(MeshId, Arc<MeshDesc>),
    UnregisterMesh(MeshId),
    AddInstance(InstanceId, InstanceDesc),
    SetTransform(InstanceId, Affine3A),
    RemoveInstance(InstanceId),
    SetPose(InstanceId, Option<Arc<Vec<[f32; 3]>>>),
    SetDevicePose(InstanceId, crate::mesh::DeviceVertices),
    /// (mesh, LOD, geometry, new geometric error if any)
    SetLodGeometry(MeshId, usize, LodGeometry, Option<f32>),
    RegisterGroup(GroupId, GroupDesc),
    SetGroupProxy(GroupId, Option<(MeshId, f32)>),
    UnregisterGroup(GroupId),
}

#[derive(Debug, Default)]
pub(crate) struct Pending {
    pub commands: Vec<Command>,
    pub meshes: IdAllocator,
    pub instances: IdAllocator,
    pub groups: IdAllocator,
    pub mesh_kind: Vec<MeshKind>,
    pub mesh_lods: Vec<u8>,
    pub instance_skinned: Vec<bool>,
}

/// A cloneable, `Send + Sync` handle for registering meshes and instances from any thread.
/// Changes take effect at the next `AsManager::update`.
#[derive(Debug, Clone, Default)]
pub struct Registrar {
    pub(crate) pending: Arc<Mutex<Pending>>,
}

fn finite(transform: &Affine3A) -> bool {
    transform.matrix3.is_finite() && transform.translation.is_finite()
}

/// An id the registrar hands out and checks: meshes, instances and groups each have their own
/// allocator in [`Pending`] and their own error for an id that is not live.
trait QueuedId: Copy {
    /// The allocator of this kind of id.
    fn slots(p: &Pending) -> &IdAllocator;
    /// The same, to kill an id.
    fn slots_mut(p: &mut Pending) -> &mut IdAllocator;
    /// `(index, generation)`.
    fn slot(self) -> (u32, u32);
    /// The error for this id when it is not live.
    fn unknown(self) -> AsError;
}

/// Implements [`QueuedId`] for an id type, its allocator field of [`Pending`] and its error.
macro_rules! queued_id {
    ($id:ty, $slots:ident, $unknown:path) => {
        impl QueuedId for $id {
            fn slots(p: &Pending) -> &IdAllocator {
                &p.$slots
            }
            fn slots_mut(p: &mut Pending) -> &mut IdAllocator {
                &mut p.$slots
            }
            fn slot(self) -> (u32, u32) {
                (self.index, self.generation)
            }
            fn unknown(self) -> AsError {
                $unknown(self)
            }
        }
    };
}

queued_id!(MeshId, meshes, AsError::UnknownMesh);
queued_id!(InstanceId, instances, AsError::UnknownInstance);
queued_id!(GroupId, groups, AsError::UnknownGroup);

/// `Ok` if `id` is live, its kind's `Unknown*` error if not.
fn live<I: QueuedId>(p: &Pending, id: I) -> Result<()> {
    let (index, generation) = id.slot();
    if I::slots(p).is_live(index, generation) {
        Ok(())
    } else {
        Err(id.unknown())
    }
}

impl Registrar {
    /// Validates and queues a mesh (with its LOD chain).
    pub fn register_mesh(&self, desc: MeshDesc) -> Result<MeshId> {
        desc.validate()?;
        let mut p = self.pending.lock();
        let (index, generation) = p.meshes.alloc();
        let id = MeshId { index, generation };
        if p.mesh_kind.len() <= index as usize {
            p.mesh_kind.resize(index as usize + 1, MeshKind::Static);
        }
        p.mesh_kind[index as usize] = desc.kind;
        if p.mesh_lods.len() <= index as usize {
            p.mesh_lods.resize(index as usize + 1, 0);
        }
        p.mesh_lods[index as usize] = desc.lods.len() as u8;
        p.commands.push(Command::RegisterMesh(id, Arc::new(desc)));
        Ok(id)
    }

    /// Queues a swap of one LOD's geometry, for meshes whose LODs stream in and out: register
    /// the chain with [`LodGeometry::Counts`] for LODs not resident, then set
    /// [`LodGeometry::Data`] when one arrives and `Counts` again when it is evicted. A backend
    /// that [needs geometry](crate::backend::AsBackend::needs_geometry) only gets builds of LODs
    /// with data (others fall back to the nearest LOD with data); a BLAS already built from an
    /// evicted LOD stays until released normally (it holds no reference to the CPU data).
    /// The geometric error stays as registered ([`Registrar::set_lod`] replaces it too). The
    /// triangle count the policy estimates sizes and costs from follows the new geometry: a
    /// chain registered with guessed counts becomes exact as its LODs arrive.
    ///
    /// ```
    /// use rtstream_as_manager::{synth::{counts_chain, grid_geometry}, *};
    /// let r = Registrar::default();
    /// let mesh = r.register_mesh(MeshDesc::new("m", MeshKind::Static, 1.0, counts_chain(512, 3, 0.01))).unwrap();
    /// r.set_lod_geometry(mesh, 2, LodGeometry::Data(grid_geometry(8, 1.0))).unwrap();
    /// assert!(r.set_lod_geometry(mesh, 3, LodGeometry::Data(grid_geometry(8, 1.0))).is_err());
    /// ```
    pub fn set_lod_geometry(&self, mesh: MeshId, lod: usize, geometry: LodGeometry) -> Result<()> {
        self.set_lod_inner(mesh, lod, geometry, None)
    }

    /// Like [`Registrar::set_lod_geometry`], and replaces the LOD's geometric error (a guess
    /// made before the LOD was seen): the chain's errors are kept non-decreasing around it.
    ///
    /// ```
    /// use rtstream_as_manager::{synth::{counts_chain, grid_geometry}, *};
    /// let r = Registrar::default();
    /// let mesh = r.register_mesh(MeshDesc::new("m", MeshKind::Static, 1.0, counts_chain(512, 3, 0.01))).unwrap();
    /// let lod = LodDesc { geometry: LodGeometry::Data(grid_geometry(8, 1.0)), geometric_error: 0.5 };
    /// r.set_lod(mesh, 1, lod).unwrap();
    /// let bad = LodDesc { geometry: LodGeometry::Counts { vertices: 3, triangles: 1 }, geometric_error: f32::NAN };
    /// assert!(r.set_lod(mesh, 1, bad).is_err());
    /// ```
    pub fn set_lod(&self, mesh: MeshId, lod: usize, desc: crate::LodDesc) -> Result<()> {
        let e = desc.geometric_error;
        if !(e.is_finite() && e >= 0.0) {
            return Err(AsError::InvalidMesh {
                name: format!("{mesh:?}"),
                reason: format!("LOD {lod}: geometric error {e} is not finite and >= 0"),
            });
        }
        self.set_lod_inner(mesh, lod, desc.geometry, Some(e))
    }

    fn set_lod_inner(
        &self,
        mesh: MeshId,
        lod: usize,
        geometry: LodGeometry,
        error: Option<f32>,
    ) -> Result<()> {
        let probe = MeshDesc::new(
            "lod",
            MeshKind::Static,
            1.0,
            vec![crate::LodDesc {
                geometry,
                geometric_error: 0.0,
            }],
        );
        probe.validate()?;
        let geometry = probe
            .lods
            .into_iter()
            .next()
            .map(|l| l.geometry)
            .expect("one LOD");
        let mut p = self.pending.lock();
        live(&p, mesh)?;
        let lods = p.mesh_lods[mesh.index as usize] as usize;
        if lod >= lods {
            return Err(AsError::InvalidMesh {
                name: format!("{mesh:?}"),
                reason: format!("LOD {lod} out of range (mesh has {lods})"),
            });
        }
        p.commands
            .push(Command::SetLodGeometry(mesh, lod, geometry, error));
        Ok(())
    }

    /// Queues the removal of a mesh, its BLASes and all its instances.
    pub fn unregister_mesh(&self, id: MeshId) -> Result<()> {
        self.queue_removal(id, Command::UnregisterMesh(id))
    }

    /// Queues `command`, the removal of `id`: its kind's `Unknown*` error unless it is live;
    /// later calls see it as unknown at once (its slot is recycled once the manager applied
    /// the removal).
    fn queue_removal<I: QueuedId>(&self, id: I, command: Command) -> Result<()> {
        let mut p = self.pending.lock();
        live(&p, id)?;
        I::slots_mut(&mut p).kill(id.slot().0);
        p.commands.push(command);
        Ok(())
    }

    /// Queues a new instance.
    pub fn add_instance(&self, desc: InstanceDesc) -> Result<InstanceId> {
        if !finite(&desc.transform) {
            return Err(AsError::InvalidTransform);
        }
        if desc.custom_index >= 1 << 24 || desc.sbt_offset >= 1 << 24 {
            return Err(AsError::InvalidInstance(
                "customIndex and SBT offset must fit in 24 bits".into(),
            ));
        }
        let mut p = self.pending.lock();
        live(&p, desc.mesh)?;
        if let Some(g) = desc.group {
            live(&p, g)?;
        }
        let skinned = p.mesh_kind[desc.mesh.index as usize] == MeshKind::Skinned;
        let (index, generation) = p.instances.alloc();
        if p.instance_skinned.len() <= index as usize {
            p.instance_skinned.resize(index as usize + 1, false);
        }
        p.instance_skinned[index as usize] = skinned;
        let id = InstanceId { index, generation };
        p.commands.push(Command::AddInstance(id, desc));
        Ok(id)
    }

    /// Queues a far-field group (a node of the proxy tree; register parents first).
    pub fn register_group(&self, desc: GroupDesc) -> Result<GroupId> {
        let (lo, hi) = (desc.bounds_min, desc.bounds_max);
        if !lo.iter().chain(&hi).all(|v| v.is_finite()) || (0..3).any(|i| lo[i] > hi[i]) {
            return Err(AsError::InvalidGroup(format!("bounds {lo:?}..{hi:?}")));
        }
        if desc.custom_index >= 1 << 24 {
            return Err(AsError::InvalidGroup(
                "customIndex must fit in 24 bits".into(),
            ));
        }
        let mut p = self.pending.lock();
        if let Some(parent) = desc.parent {
            live(&p, parent)?;
        }
        let (index, generation) = p.groups.alloc();
        let id = GroupId { index, generation };
        p.commands.push(Command::RegisterGroup(id, desc));
        Ok(id)
    }

    /// Queues the proxy of a group: a registered static mesh whose geometry is in world space
    /// (shown with the identity transform), and its geometric error in metres. `None` clears
    /// it. The manager shows the proxy in the TLAS instead of the group's instances where they
    /// are beyond r2 (see [`crate::FarFieldConfig`]).
    pub fn set_group_proxy(&self, group: GroupId, proxy: Option<(MeshId, f32)>) -> Result<()> {
        let mut p = self.pending.lock();
        live(&p, group)?;
        if let Some((mesh, error)) = proxy {
            live(&p, mesh)?;
            if p.mesh_kind[mesh.index as usize] != MeshKind::Static || !error.is_finite() {
                return Err(AsError::InvalidGroup(
                    "a proxy is a static mesh with a finite error".into(),
                ));
            }
        }
        p.commands.push(Command::SetGroupProxy(group, proxy));
        Ok(())
    }

    /// Queues the removal of a group (its instances keep their place but lose their proxy;
    /// its children become roots).
    pub fn unregister_group(&self, id: GroupId) -> Result<()> {
        self.queue_removal(id, Command::UnregisterGroup(id))
    }

    /// Queues `command` about instance `id`: `UnknownInstance` unless it is live, and
    /// `NotSkinned` unless it is skinned where `skinned_only` says so.
    fn queue_for_instance(
        &self,
        id: InstanceId,
        skinned_only: bool,
        command: Command,
    ) -> Result<()> {
        let mut p = self.pending.lock();
        live(&p, id)?;
        if skinned_only && !p.instance_skinned[id.index as usize] {
            return Err(AsError::NotSkinned(id));
        }
        p.commands.push(command);
        Ok(())
    }

    /// Queues a transform change.
    pub fn set_transform(&self, id: InstanceId, transform: Affine3A) -> Result<()> {
        if !finite(&transform) {
            return Err(AsError::InvalidTransform);
        }
        self.queue_for_instance(id, false, Command::SetTransform(id, transform))
    }

    /// Queues the removal of an instance.
    pub fn remove_instance(&self, id: InstanceId) -> Result<()> {
        self.queue_removal(id, Command::RemoveInstance(id))
    }

    /// Queues a new pose of a skinned instance: mesh-space positions of the LOD it is built at
    /// (see `AsManager::instance_lod`); a pose whose length does not match is refitted without
    /// a quality measurement.
    pub fn set_skinned_pose(&self, id: InstanceId, positions: Arc<Vec<[f32; 3]>>) -> Result<()> {
        self.pose(id, Some(positions))
    }

    /// Queues a pose of a skinned instance that lives in the engine's GPU buffer (e.g. written
    /// by its skinning compute pass this frame): the refit reads the positions from there, with
    /// no CPU copy; the topology is the instance's LOD's (see `AsManager::instance_lod`), and
    /// `positions.count` must equal that LOD's vertex count (a pose that does not match is not
    /// refitted). The pose stays current, and every later frame refits from the same address,
    /// until another pose is set: call it again each frame the engine deforms the mesh.
    /// Refit quality is then measured on the GPU (see `VulkanBackend`'s refit-quality pass).
    /// See [`DeviceVertices`](crate::DeviceVertices) for the buffer's contract.
    pub fn set_skinned_pose_device(
        &self,
        id: InstanceId,
        positions: crate::mesh::DeviceVertices,
    ) -> Result<()> {
        positions.validate().map_err(AsError::InvalidDevicePose)?;
        self.queue_for_instance(id, true, Command::SetDevicePose(id, positions))
    }

    /// Marks a skinned instance deformed without data (counts-only meshes, model backend).
    pub fn mark_deformed(&self, id: InstanceId) -> Result<()> {
        self.pose(id, None)
    }

    fn pose(&self, id: InstanceId, positions: Option<Arc<Vec<[f32; 3]>>>) -> Result<()> {
        if let Some(p) = &positions {
            if !p.iter().flatten().all(|v| v.is_finite()) {
                return Err(AsError::InvalidTransform);
            }
        }
        self.queue_for_instance(id, true, Command::SetPose(id, positions))
    }
}
