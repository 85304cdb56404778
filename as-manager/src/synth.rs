//! A deterministic synthetic world for benchmarks, examples and tests.
//!
//! Default: 104,366 instances over 4 km x 4 km (the seeds' map) from 300 meshes with 4-LOD
//! chains (triangles halving, geometric error doubling), ~5% non-opaque, 256 skinned
//! instances. The million preset keeps the density (~6,500 instances per km²), so its side is
//! 4 km x sqrt(1e6 / 104,366) ≈ 12.4 km.

use std::sync::Arc;

use glam::{Affine3A, Quat, Vec3};

use crate::mesh::{GeometryData, LodDesc, LodGeometry, MeshDesc, MeshKind};
use crate::{AsManager, InstanceDesc, InstanceId, MeshId, Result, Viewpoint};

/// The placement's random source, shared with the world generator (`rtstream-streaming`); a
/// generator's state starts at the seed.
pub use rtstream_stats::Rng;

/// World parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthParams {
    /// Instances (including skinned).
    pub instances: usize,
    /// Side of the square world (m).
    pub extent: f32,
    /// Distinct static meshes.
    pub meshes: usize,
    /// Distinct skinned meshes.
    pub skinned_meshes: usize,
    /// Skinned instances.
    pub skinned_instances: usize,
    /// Fraction of static meshes that are not opaque.
    pub non_opaque_fraction: f32,
    /// RNG seed.
    pub seed: u64,
}

impl SynthParams {
    /// The seeds' map: 104,366 instances, 4 km x 4 km.
    pub fn default_world() -> Self {
        Self {
            instances: 104_366,
            extent: 4000.0,
            meshes: 300,
            skinned_meshes: 4,
            skinned_instances: 256,
            non_opaque_fraction: 0.05,
            seed: 0x5eed,
        }
    }

    /// 1,000,000 instances at the default world's density.
    pub fn million() -> Self {
        let d = Self::default_world();
        Self {
            instances: 1_000_000,
            extent: d.extent * (1_000_000.0f32 / d.instances as f32).sqrt(),
            skinned_instances: 2_400,
            ..d
        }
    }

    /// A small world for tests.
    pub fn small(instances: usize, extent: f32, seed: u64) -> Self {
        Self {
            instances,
            extent,
            meshes: 24,
            skinned_meshes: 2,
            skinned_instances: instances / 50,
            non_opaque_fraction: 0.05,
            seed,
        }
    }
}

/// A generated world: mesh descriptions and instance placements.
#[derive(Debug, Clone)]
pub struct SynthWorld {
    /// Parameters used.
    pub params: SynthParams,
    /// Meshes (static first, then skinned).
    pub meshes: Vec<MeshDesc>,
    /// (mesh index, transform).
    pub instances: Vec<(usize, Affine3A)>,
}

/// A LOD chain of counts only: `tris0` halving per LOD, error doubling from `err1`.
pub fn counts_chain(tris0: u32, lods: usize, err1: f32) -> Vec<LodDesc> {
    (0..lods)
        .map(|i| {
            let t = (tris0 >> i).max(8);
            LodDesc {
                geometry: LodGeometry::Counts {
                    vertices: t / 2 + 3,
                    triangles: t,
                },
                geometric_error: if i == 0 {
                    0.0
                } else {
                    err1 * (1 << (i - 1)) as f32
                },
            }
        })
        .collect()
}

/// A `n` x `n` quad grid (2n² triangles) of side `size` centred at the origin, as data.
pub fn grid_geometry(n: u32, size: f32) -> Arc<GeometryData> {
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    for z in 0..=n {
        for x in 0..=n {
            positions.push([
                (x as f32 / n as f32 - 0.5) * size,
                0.0,
                (z as f32 / n as f32 - 0.5) * size,
            ]);
        }
    }
    let w = n + 1;
    for z in 0..n {
        for x in 0..n {
            let a = z * w + x;
            indices.extend([a, a + 1, a + w, a + 1, a + w + 1, a + w]);
        }
    }
    Arc::new(GeometryData { positions, indices })
}

impl SynthWorld {
    /// Generates the world deterministically from `params`.
    pub fn generate(params: SynthParams) -> Self {
        let mut rng = Rng::new(params.seed);
        let mut meshes = Vec::new();
        for m in 0..params.meshes {
            // log-uniform size and triangle count: many small props, some buildings
            let radius = 0.5 * 40f32.powf(rng.f32());
            let tris0 = (400.0 * 50f32.powf(rng.f32())) as u32;
            let mut d = MeshDesc::new(
                format!("static{m}"),
                MeshKind::Static,
                radius,
                counts_chain(tris0, 4, radius * 0.002),
            );
            d.opaque = rng.f32() >= params.non_opaque_fraction;
            meshes.push(d);
        }
        for m in 0..params.skinned_meshes {
            meshes.push(MeshDesc::new(
                format!("skinned{m}"),
                MeshKind::Skinned,
                1.0,
                counts_chain(8_000 + 2_000 * m as u32, 3, 0.004),
            ));
        }
        let mut instances = Vec::with_capacity(params.instances);
        let half = params.extent * 0.5;
        for i in 0..params.instances {
            let skinned = i < params.skinned_instances;
            let mesh = if skinned {
                params.meshes + i % params.skinned_meshes.max(1)
            } else {
                ((rng.f32() * rng.f32()) * params.meshes as f32) as usize % params.meshes.max(1)
            };
            let p = Vec3::new(
                rng.range(-half, half),
                rng.range(0.0, 5.0),
                rng.range(-half, half),
            );
            let rot = Quat::from_rotation_y(rng.range(0.0, std::f32::consts::TAU));
            let s = rng.range(0.8, 1.2);
            instances.push((
                mesh,
                Affine3A::from_scale_rotation_translation(Vec3::splat(s), rot, p),
            ));
        }
        Self {
            params,
            meshes,
            instances,
        }
    }

    /// Registers every mesh and instance; returns their ids.
    pub fn populate<B: crate::backend::AsBackend>(
        &self,
        m: &AsManager<B>,
    ) -> Result<(Vec<MeshId>, Vec<InstanceId>)> {
        let mesh_ids = self
            .meshes
            .iter()
            .map(|d| m.register_mesh(d.clone()))
            .collect::<Result<Vec<_>>>()?;
        let mut ids = Vec::with_capacity(self.instances.len());
        for (i, (mesh, t)) in self.instances.iter().enumerate() {
            let mut d = InstanceDesc::new(mesh_ids[*mesh], *t);
            d.custom_index = (i as u32) & 0xff_ffff;
            ids.push(m.add_instance(d)?);
        }
        Ok((mesh_ids, ids))
    }

    /// Like [`SynthWorld::populate`], with a far-field group tree over the map: leaves of
    /// `leaf_m` x `leaf_m` metres (static instances join the leaf they stand in), parents of
    /// 2x2 children up to `depths` levels, each node with a counts-only proxy of 768
    /// triangles whose error doubles per level (from 4 m). Returns the instance ids.
    pub fn populate_with_groups<B: crate::backend::AsBackend>(
        &self,
        m: &AsManager<B>,
        leaf_m: f32,
        depths: u32,
    ) -> Result<Vec<InstanceId>> {
        use crate::{GroupDesc, GroupId};
        let mesh_ids = self
            .meshes
            .iter()
            .map(|d| m.register_mesh(d.clone()))
            .collect::<Result<Vec<_>>>()?;
        let half = self.params.extent * 0.5;
        let cells = (self.params.extent / leaf_m).ceil().max(1.0) as i32;
        let mut groups: std::collections::HashMap<(u32, i32, i32), GroupId> = Default::default();
        let mut ci = 0x80_0000u32;
        for level in (0..depths).rev() {
            let size = 1i32 << level;
            let n = (cells + size - 1) / size;
            for x in 0..n {
                for z in 0..n {
                    let lo = [
                        -half + (x * size) as f32 * leaf_m,
                        -10.0,
                        -half + (z * size) as f32 * leaf_m,
                    ];
                    let side = size as f32 * leaf_m;
                    let parent = (level + 1 < depths)
                        .then(|| groups.get(&(level + 1, x / 2, z / 2)).copied())
                        .flatten();
                    let g = m.register_group(GroupDesc {
                        parent,
                        bounds_min: lo,
                        bounds_max: [lo[0] + side, 60.0, lo[2] + side],
                        custom_index: ci,
                        mask: 0xff,
                    })?;
                    ci += 1;
                    let proxy = m.register_mesh(MeshDesc::new(
                        format!("proxy{level}_{x}_{z}"),
                        MeshKind::Static,
                        side,
                        counts_chain(768, 1, 0.0),
                    ))?;
                    m.set_group_proxy(g, Some((proxy, 4.0 * (1u32 << level) as f32)))?;
                    groups.insert((level, x, z), g);
                }
            }
        }
        let mut ids = Vec::with_capacity(self.instances.len());
        for (i, (mesh, t)) in self.instances.iter().enumerate() {
            let mut d = InstanceDesc::new(mesh_ids[*mesh], *t);
            d.custom_index = (i as u32) & 0x7f_ffff;
            if self.meshes[*mesh].kind == MeshKind::Static {
                let p = t.translation;
                let (x, z) = (
                    ((p.x + half) / leaf_m).floor() as i32,
                    ((p.z + half) / leaf_m).floor() as i32,
                );
                d.group = groups.get(&(0, x, z)).copied();
            }
            ids.push(m.add_instance(d)?);
        }
        Ok(ids)
    }

    /// A camera on a closed path through the world at `speed` m per frame, looking ahead.
    pub fn camera_on_path(&self, frame: u64, speed: f32) -> Viewpoint {
        path_camera(self.params.extent, frame, speed)
    }
}

/// A camera on a rounded loop of radius 0.3 x `extent` (Lissajous-like), height 2 m.
pub fn path_camera(extent: f32, frame: u64, speed: f32) -> Viewpoint {
    let r = 0.3 * extent;
    let len = std::f32::consts::TAU * r;
    let t = ((frame as f64 * speed as f64) % len as f64) as f32 / r;
    let pos = Vec3::new(r * t.cos(), 2.0, r * (2.0 * t).sin() * 0.5);
    let ahead = Vec3::new(-r * t.sin(), 0.0, r * (2.0 * t).cos());
    Viewpoint::new(pos, ahead.normalize_or_zero())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_sized() {
        let a = SynthWorld::generate(SynthParams::small(1000, 500.0, 1));
        let b = SynthWorld::generate(SynthParams::small(1000, 500.0, 1));
        assert_eq!(a.instances, b.instances);
        assert_eq!(a.instances.len(), 1000);
        assert!(a.meshes.iter().all(|m| m.validate().is_ok()));
        let d = SynthParams::default_world();
        assert!(d.instances >= 104_366 && d.skinned_instances >= 200);
    }
}

/// A buffer of `mb` MB whose every cache line [`CacheEvictor::evict`] writes: `update` then
/// starts with cold caches, as in an engine whose other work and renderer run between two
/// frames (`docs/PROFILE.md`, "Cold caches"). The `frame_cost` example's `--evict-mb` and the
/// criterion bench's `_cold` cases use it, outside their timings.
///
/// ```
/// let mut caches = rtstream_as_manager::synth::CacheEvictor::new(1);
/// caches.evict();
/// ```
#[derive(Debug)]
pub struct CacheEvictor(Vec<u8>);

impl CacheEvictor {
    /// An evictor writing `mb` MB (0: nothing).
    pub fn new(mb: usize) -> Self {
        Self(vec![0; mb << 20])
    }

    /// Writes one byte of every 64-byte line.
    pub fn evict(&mut self) {
        for (i, line) in self.0.chunks_mut(64).enumerate() {
            line[0] = line[0].wrapping_add(i as u8 | 1);
        }
        std::hint::black_box(&mut self.0);
    }
}
