//! Applying queued registry commands, in queue order.

use std::sync::Arc;

use glam::Affine3A;

use super::landmarks::CandSphere;
use super::registrar::{Command, InstanceDesc};
use super::state::{EntryKey, EntryState, InstanceHot, InstanceState, MeshState, NO_GROUP};
use super::AsManager;
use crate::backend::AsBackend;
use crate::mesh::{LodGeometry, MeshDesc, MeshKind, MAX_LODS};
use crate::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};
use crate::{InstanceId, MeshId};

fn world_sphere(desc: &MeshDesc, transform: &Affine3A) -> (glam::Vec3, f32, f32) {
    let c = transform.transform_point3(glam::Vec3::from(desc.bounds_center));
    let m = transform.matrix3;
    let scale = m
        .x_axis
        .length()
        .max(m.y_axis.length())
        .max(m.z_axis.length());
    (c, desc.bounds_radius * scale, scale)
}

impl<B: AsBackend> AsManager<B> {
    pub(crate) fn apply_commands(&mut self) {
        let commands = std::mem::take(&mut self.registrar.pending.lock().commands);
        // Last frame's near and proxy records go (a removed landmark's record is taken out
        // of the landmark records at the front).
        self.records.truncate(self.landmarks.len());
        self.stats.commands_applied = commands.len() as u32;
        let mut dead_meshes = Vec::new();
        let mut dead_instances = Vec::new();
        for c in commands {
            match c {
                Command::RegisterMesh(id, desc) => self.apply_register(id, desc),
                Command::UnregisterMesh(id) => {
                    dead_instances.extend(self.apply_unregister(id));
                    dead_meshes.push(id.index);
                }
                Command::AddInstance(id, desc) => self.apply_add(id, desc),
                Command::SetTransform(id, transform) => self.apply_transform(id, transform),
                Command::RemoveInstance(id) => {
                    if self.apply_remove(id.index) {
                        dead_instances.push(id.index);
                    }
                }
                Command::SetLodGeometry(id, lod, geometry, error) => {
                    // New data or none: the landmarks see it in what their selection
                    // resolves to; new errors change the selection itself.
                    if self.set_lod_now(id.index, lod, geometry, error) {
                        self.landmarks.mesh_changed(id.index);
                    }
                }
                Command::RegisterGroup(id, desc) => self.far.register(id, desc),
                Command::SetGroupProxy(id, proxy) => {
                    // The proxy's BLAS belongs to its mesh: unregistering the mesh frees it;
                    // a proxy no longer named is released like any unkept BLAS.
                    self.far.set_proxy(id, proxy.map(|(m, e)| (m.index, e)));
                    if let Some((m, _)) = proxy {
                        if let Some(Some(mesh)) = self.tables.meshes.get_mut(m.index as usize) {
                            mesh.proxy = true;
                            for k in mesh.lod_entry.iter().flatten() {
                                if let Some(e) = self.tables.entries.get_mut(*k) {
                                    e.proxy = true;
                                }
                            }
                        }
                    }
                }
                Command::UnregisterGroup(id) => {
                    if self.far.is_live(id) {
                        self.far.unregister(id);
                        if self.members_of(id.index) == 0 {
                            self.dead_groups.push(id.index);
                        }
                    }
                }
                Command::SetPose(id, pose) => {
                    if let Some(Some(i)) = self.tables.instances.get_mut(id.index as usize) {
                        i.pose = pose;
                        i.device_pose = None;
                        i.pose_version += 1;
                    }
                }
                Command::SetDevicePose(id, pose) => {
                    if let Some(Some(i)) = self.tables.instances.get_mut(id.index as usize) {
                        i.pose = None;
                        i.device_pose = Some(pose);
                        i.pose_version += 1;
                    }
                }
            }
        }
        if !dead_meshes.is_empty() || !dead_instances.is_empty() || !self.dead_groups.is_empty() {
            let mut p = self.registrar.pending.lock();
            for m in dead_meshes {
                p.meshes.recycle(m);
            }
            for i in dead_instances {
                p.instances.kill(i);
                p.instances.recycle(i);
            }
            for g in self.dead_groups.drain(..) {
                p.groups.recycle(g);
            }
        }
    }

    /// Applied instances naming group slot `g`.
    fn members_of(&self, g: u32) -> u32 {
        self.group_members.get(g as usize).copied().unwrap_or(0)
    }

    fn apply_register(&mut self, id: MeshId, desc: Arc<MeshDesc>) {
        let slot = id.index as usize;
        if self.tables.meshes.len() <= slot {
            self.tables.meshes.resize_with(slot + 1, || None);
        }
        let mut errors = [0.0; MAX_LODS];
        let mut lod_tris = [0; MAX_LODS];
        let mut buildable = 0u8;
        for (i, l) in desc.lods.iter().enumerate() {
            errors[i] = l.geometric_error;
            lod_tris[i] = l.geometry.triangles();
            buildable |= u8::from(l.geometry.is_buildable()) << i;
        }
        if self.tables.meshes[slot].is_none() {
            self.live_meshes += 1;
        }
        self.tables.mesh_log.note(id.index);
        self.tables.meshes[slot] = Some(MeshState {
            kind: desc.kind,
            nlods: desc.lods.len() as u8,
            errors,
            lod_tris,
            buildable,
            desc,
            lod_entry: [None; MAX_LODS],
            lod_floor: 0,
            floor_since: 0,
            instances: Vec::new(),
            proxy: false,
            blas_epoch: 0,
        });
    }

    /// A LOD's new geometry (and error): the estimates follow it. An unbuilt entry of the LOD
    /// takes the new triangle count; a built one keeps what it was built from. Returns whether
    /// the mesh's errors changed.
    fn set_lod_now(
        &mut self,
        mesh: u32,
        lod: usize,
        geometry: LodGeometry,
        error: Option<f32>,
    ) -> bool {
        let Some(Some(m)) = self.tables.meshes.get_mut(mesh as usize) else {
            return false;
        };
        if lod >= m.nlods as usize {
            return false;
        }
        let errors_before = m.errors;
        let tris = geometry.triangles();
        self.tables.mesh_log.note(mesh);
        m.buildable = (m.buildable & !(1 << lod)) | (u8::from(geometry.is_buildable()) << lod);
        let d = Arc::make_mut(&mut m.desc);
        d.lods[lod].geometry = geometry;
        m.lod_tris[lod] = tris;
        if let Some(e) = error {
            d.lods[lod].geometric_error = e;
            m.errors[lod] = e;
            // Keep the chain non-decreasing around the new value.
            let n = m.nlods as usize;
            for l in (0..lod).rev() {
                m.errors[l] = m.errors[l].min(m.errors[l + 1]);
                d.lods[l].geometric_error = m.errors[l];
            }
            for l in lod + 1..n {
                m.errors[l] = m.errors[l].max(m.errors[l - 1]);
                d.lods[l].geometric_error = m.errors[l];
            }
        }
        let errors_changed = m.errors != errors_before;
        if let Some(key) = m.lod_entry[lod] {
            let e = &mut self.tables.entries[key];
            if e.state != EntryState::Built {
                e.triangles = tris;
            }
        }
        errors_changed
    }

    /// Removes the mesh's instances and BLASes; returns the instance slots removed.
    fn apply_unregister(&mut self, id: MeshId) -> Vec<u32> {
        let Some(Some(mesh)) = self.tables.meshes.get(id.index as usize) else {
            return Vec::new();
        };
        let insts = mesh.instances.clone();
        let entries: Vec<EntryKey> = mesh.lod_entry.iter().copied().flatten().collect();
        for &i in &insts {
            self.apply_remove(i);
        }
        for key in entries {
            if self.tables.entries.contains_key(key) {
                self.release_entry(key);
            }
        }
        self.floors.retain(|&m| m != id.index);
        self.tables.meshes[id.index as usize] = None;
        self.live_meshes -= 1;
        self.tables.mesh_log.note(id.index);
        insts
    }

    fn apply_add(&mut self, id: InstanceId, desc: InstanceDesc) {
        let Some(Some(mesh)) = self.tables.meshes.get_mut(desc.mesh.index as usize) else {
            return;
        };
        let (center, radius, scale) = world_sphere(&mesh.desc, &desc.transform);
        let flags = desc.flags
            | if mesh.desc.opaque {
                INSTANCE_FORCE_OPAQUE
            } else {
                0
            };
        let mesh_pos = mesh.instances.len() as u32;
        let mesh_kind = mesh.kind;
        mesh.instances.push(id.index);
        let slot = id.index as usize;
        if self.tables.instances.len() <= slot {
            self.tables.instances.resize_with(slot + 1, || None);
        }
        let group = desc
            .group
            .filter(|g| self.far.is_live(*g))
            .map_or(NO_GROUP, |g| g.index);
        if group != NO_GROUP {
            let g = group as usize;
            if self.group_members.len() <= g {
                self.group_members.resize(g + 1, 0);
            }
            self.group_members[g] += 1;
        }
        self.tables.instances[slot] = Some(InstanceState {
            generation: id.generation,
            mesh: desc.mesh.index,
            mesh_pos,
            center,
            radius,
            pose: None,
            device_pose: None,
            pose_version: 0,
            seed_request: None,
            seed_keep: None,
            seed_has: false,
        });
        if self.templates.len() <= slot {
            self.templates
                .resize(slot + 1, bytemuck::Zeroable::zeroed());
        }
        self.templates[slot] = TlasInstance::new(
            &desc.transform,
            desc.custom_index,
            desc.mask,
            desc.sbt_offset,
            flags,
            0,
        );
        let hot = InstanceHot {
            mesh: desc.mesh.index,
            scale,
            shown: None,
            own: None,
            last_visit: u64::MAX,
            group,
            lod_target: (MAX_LODS - 1) as u8,
            culled: true,
        };
        self.grid.insert(id.index, center, radius, hot);
        let is_static = mesh_kind == MeshKind::Static;
        let sphere = CandSphere {
            center,
            radius,
            mesh: desc.mesh.index,
            scale,
        };
        self.landmarks.track(id.index, sphere, is_static, group);
        self.live_instances += 1;
    }

    fn apply_transform(&mut self, id: InstanceId, transform: Affine3A) {
        let Some(Some(inst)) = self.tables.instances.get_mut(id.index as usize) else {
            return;
        };
        let Some(Some(mesh)) = self.tables.meshes.get(inst.mesh as usize) else {
            return;
        };
        let Some(grid_entry) = self.grid.get(id.index) else {
            return;
        };
        let (center, radius, scale) = world_sphere(&mesh.desc, &transform);
        inst.center = center;
        inst.radius = radius;
        let mut hot = grid_entry.data;
        self.templates[id.index as usize].transform = crate::record::transform_rows(&transform);
        hot.scale = scale;
        let is_static = mesh.kind == MeshKind::Static;
        let group = hot.group;
        self.grid.insert(id.index, center, radius, hot);
        let sphere = CandSphere {
            center,
            radius,
            mesh: inst.mesh,
            scale,
        };
        self.landmarks.track(id.index, sphere, is_static, group);
    }

    /// Removes an instance's state; returns whether it existed.
    fn apply_remove(&mut self, slot: u32) -> bool {
        let Some(Some(inst)) = self.tables.instances.get(slot as usize) else {
            return false;
        };
        let (mesh, mesh_pos, seed_has) = (inst.mesh, inst.mesh_pos, inst.seed_has);
        let (own, shown, group) =
            self.grid
                .get(slot)
                .map_or((None, None, NO_GROUP), |grid_entry| {
                    let d = &grid_entry.data;
                    (d.own, d.shown, d.group)
                });
        if group != NO_GROUP {
            // The last member of an unregistered group frees its slot.
            let n = &mut self.group_members[group as usize];
            *n -= 1;
            if *n == 0 && !self.far.slot_is_live(group) {
                self.dead_groups.push(group);
            }
        }
        if let Some(Some(m)) = self.tables.meshes.get_mut(mesh as usize) {
            m.instances.swap_remove(mesh_pos as usize);
            if let Some(&moved) = m.instances.get(mesh_pos as usize) {
                if let Some(Some(mi)) = self.tables.instances.get_mut(moved as usize) {
                    mi.mesh_pos = mesh_pos;
                }
            }
        }
        let kind = self.tables.meshes[mesh as usize].as_ref().map(|m| m.kind());
        if seed_has {
            self.seed_drop_ref(slot);
        }
        if kind == Some(MeshKind::Skinned) {
            // Skinned BLASes belong to the instance: release every entry it owns.
            for key in [own, shown].into_iter().flatten() {
                if self
                    .tables
                    .entries
                    .get(key)
                    .is_some_and(|e| e.owner == Some(slot))
                {
                    self.release_entry(key);
                }
            }
            let owned: Vec<EntryKey> = self
                .tables
                .active
                .iter()
                .copied()
                .filter(|&key| self.tables.entries[key].owner == Some(slot))
                .collect();
            for key in owned {
                self.release_entry(key);
            }
        }
        self.landmarks.remove(slot, &mut self.records);
        self.grid.remove(slot);
        self.tables.instances[slot as usize] = None;
        self.live_instances -= 1;
        true
    }
}
