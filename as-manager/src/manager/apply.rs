//! Applying queued registry commands, in queue order.

use std::sync::Arc;

use glam::Affine3A;

use super::registrar::{Command, InstanceDesc};
use super::state::{EntryState, Hot, InstanceState, MeshState, NONE};
use super::AsManager;
use crate::backend::AsBackend;
use crate::mesh::{LodGeometry, MeshDesc, MeshKind, MAX_LODS};
use crate::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};
use crate::{InstanceId, MeshId};

fn world_sphere(desc: &MeshDesc, t: &Affine3A) -> (glam::Vec3, f32, f32) {
    let c = t.transform_point3(glam::Vec3::from(desc.bounds_center));
    let m = t.matrix3;
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
                Command::SetTransform(id, t) => self.apply_transform(id, t),
                Command::RemoveInstance(id) => {
                    if self.apply_remove(id.index) {
                        dead_instances.push(id.index);
                    }
                }
                Command::SetLodGeometry(id, lod, geometry, error) => {
                    self.set_lod_now(id.index, lod, geometry, error);
                }
                Command::RegisterGroup(id, desc) => self.far.register(id, desc),
                Command::SetGroupProxy(id, proxy) => {
                    // The proxy's BLAS belongs to its mesh: unregistering the mesh frees it;
                    // a proxy no longer named is released like any unkept BLAS.
                    self.far.set_proxy(id, proxy.map(|(m, e)| (m.index, e)));
                    if let Some((m, _)) = proxy {
                        if let Some(Some(mesh)) = self.t.meshes.get_mut(m.index as usize) {
                            mesh.proxy = true;
                        }
                    }
                }
                Command::UnregisterGroup(id) => self.far.unregister(id),
                Command::SetPose(id, pose) => {
                    if let Some(Some(i)) = self.t.instances.get_mut(id.index as usize) {
                        i.pose = pose;
                        i.device_pose = None;
                        i.pose_version += 1;
                    }
                }
                Command::SetDevicePose(id, pose) => {
                    if let Some(Some(i)) = self.t.instances.get_mut(id.index as usize) {
                        i.pose = None;
                        i.device_pose = Some(pose);
                        i.pose_version += 1;
                    }
                }
            }
        }
        if !dead_meshes.is_empty() || !dead_instances.is_empty() {
            let mut p = self.registrar.pending.lock();
            for m in dead_meshes {
                p.meshes.recycle(m);
            }
            for i in dead_instances {
                p.instances.kill(i);
                p.instances.recycle(i);
            }
        }
    }

    fn apply_register(&mut self, id: MeshId, desc: Arc<MeshDesc>) {
        let slot = id.index as usize;
        if self.t.meshes.len() <= slot {
            self.t.meshes.resize_with(slot + 1, || None);
        }
        let mut errors = [0.0; MAX_LODS];
        let mut lod_tris = [0; MAX_LODS];
        for (i, l) in desc.lods.iter().enumerate() {
            errors[i] = l.geometric_error;
            lod_tris[i] = l.geometry.triangles();
        }
        if self.t.meshes[slot].is_none() {
            self.live_meshes += 1;
        }
        self.t.meshes[slot] = Some(MeshState {
            kind: desc.kind,
            nlods: desc.lods.len() as u8,
            errors,
            lod_tris,
            desc,
            lod_entry: [NONE; MAX_LODS],
            lod_floor: 0,
            floor_since: 0,
            instances: Vec::new(),
            proxy: false,
        });
    }

    /// A LOD's new geometry (and error): the estimates follow it. An unbuilt entry of the LOD
    /// takes the new triangle count; a built one keeps what it was built from.
    fn set_lod_now(&mut self, mesh: u32, lod: usize, geometry: LodGeometry, error: Option<f32>) {
        let Some(Some(m)) = self.t.meshes.get_mut(mesh as usize) else {
            return;
        };
        if lod >= m.nlods as usize {
            return;
        }
        let tris = geometry.triangles();
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
        let slot = m.lod_entry[lod];
        if slot != NONE {
            let e = &mut self.t.entries[slot as usize];
            if e.state != EntryState::Built {
                e.triangles = tris;
            }
        }
    }

    /// Removes the mesh's instances and BLASes; returns the instance slots removed.
    fn apply_unregister(&mut self, id: MeshId) -> Vec<u32> {
        let Some(Some(mesh)) = self.t.meshes.get(id.index as usize) else {
            return Vec::new();
        };
        let insts = mesh.instances.clone();
        let entries: Vec<u32> = mesh
            .lod_entry
            .iter()
            .copied()
            .filter(|&e| e != NONE)
            .collect();
        for &i in &insts {
            self.apply_remove(i);
        }
        for e in entries {
            if self.t.entries[e as usize].live {
                self.release_entry(e);
            }
        }
        self.floors.retain(|&m| m != id.index);
        self.t.meshes[id.index as usize] = None;
        self.live_meshes -= 1;
        insts
    }

    fn apply_add(&mut self, id: InstanceId, desc: InstanceDesc) {
        let Some(Some(mesh)) = self.t.meshes.get_mut(desc.mesh.index as usize) else {
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
        mesh.instances.push(id.index);
        let slot = id.index as usize;
        if self.t.instances.len() <= slot {
            self.t.instances.resize_with(slot + 1, || None);
        }
        let group = desc
            .group
            .filter(|g| self.far.is_live(*g))
            .map_or(NONE, |g| g.index);
        self.t.instances[slot] = Some(InstanceState {
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
        let hot = Hot {
            template: TlasInstance::new(
                &desc.transform,
                desc.custom_index,
                desc.mask,
                desc.sbt_offset,
                flags,
                0,
            ),
            mesh: desc.mesh.index,
            scale,
            shown: (NONE, 0),
            own: (NONE, 0),
            last_visit: u64::MAX,
            group,
            lod_target: (MAX_LODS - 1) as u8,
            culled: true,
        };
        self.grid.insert(id.index, center, radius, hot);
        self.live_instances += 1;
    }

    fn apply_transform(&mut self, id: InstanceId, t: Affine3A) {
        let Some(Some(inst)) = self.t.instances.get_mut(id.index as usize) else {
            return;
        };
        let Some(Some(mesh)) = self.t.meshes.get(inst.mesh as usize) else {
            return;
        };
        let Some(e) = self.grid.get(id.index) else {
            return;
        };
        let (center, radius, scale) = world_sphere(&mesh.desc, &t);
        inst.center = center;
        inst.radius = radius;
        let mut hot = e.data;
        hot.template.transform = crate::record::transform_rows(&t);
        hot.scale = scale;
        self.grid.insert(id.index, center, radius, hot);
    }

    /// Removes an instance's state; returns whether it existed.
    fn apply_remove(&mut self, slot: u32) -> bool {
        let Some(Some(inst)) = self.t.instances.get(slot as usize) else {
            return false;
        };
        let (mesh, mesh_pos, seed_has) = (inst.mesh, inst.mesh_pos, inst.seed_has);
        let (own, shown) = self
            .grid
            .get(slot)
            .map_or(((NONE, 0), (NONE, 0)), |e| (e.data.own, e.data.shown));
        if let Some(Some(m)) = self.t.meshes.get_mut(mesh as usize) {
            m.instances.swap_remove(mesh_pos as usize);
            if let Some(&moved) = m.instances.get(mesh_pos as usize) {
                if let Some(Some(mi)) = self.t.instances.get_mut(moved as usize) {
                    mi.mesh_pos = mesh_pos;
                }
            }
        }
        let kind = self.t.meshes[mesh as usize].as_ref().map(|m| m.kind());
        if seed_has {
            self.seed_drop_ref(slot);
        }
        if kind == Some(MeshKind::Skinned) {
            // Skinned BLASes belong to the instance: release every entry it owns.
            for key in [own, shown] {
                if self.t.entry_valid(key) && self.t.entries[key.0 as usize].owner == slot {
                    self.release_entry(key.0);
                }
            }
            let owned: Vec<u32> = self
                .t
                .active
                .iter()
                .copied()
                .filter(|&e| self.t.entries[e as usize].owner == slot)
                .collect();
            for e in owned {
                self.release_entry(e);
            }
        }
        self.grid.remove(slot);
        self.t.instances[slot as usize] = None;
        self.live_instances -= 1;
        true
    }
}
