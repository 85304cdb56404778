//! The deterministic, seedable world generator and its presets.
//!
//! A world is a square grid of streaming levels (cells of ~71 m, as in the shipped game's
//! 4 km / 3,000+ level map). Each level holds one terrain tile and a seeded mix of rocks,
//! buildings, real props (the glTF2 models of Debian's assimp-testmodels, flattened and scaled to
//! a few metres), trees (alpha-masked), grass (world-position-offset), glass (transparent) and
//! skinned characters (generated ones and glTF2/simple_skin). A few hundred meshes are built once
//! (LOD chains on all cores); the instances only reference them. With districts
//! (`WorldPreset::districts`) each square of levels has its own copies of the opaque static
//! meshes, so that the BLAS manager sees thousands of distinct meshes, as in an open world
//! with regional assets.
//!
//! Why one file over 600 lines: the presets, `generate` and the mesh-library build are one pipeline
//! whose every step depends on the preset's fields and the same seeded random stream (the output
//! is pinned bit for bit by a stored hash in `tests/world_hash.rs`); the procedural shapes are in
//! `procedural.rs` and the LOD chains in `lod.rs`.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use glam::{Mat4, Quat, Vec3};
use parking_lot::Mutex;

use crate::error::{Result, StreamingError};
use crate::gltf_import::load_gltf;
use crate::lod::build_lod_chain;
use crate::model::{
    Aabb, Instance, Level, LevelId, MaterialClass, Mesh, MeshLod, Motion, WorldInstanceId,
    WorldMeshId,
};
use crate::procedural::{self, Rng};

/// Where Debian's assimp-testmodels puts its glTF2 models.
pub const ASSIMP_GLTF2_DIR: &str = "/usr/share/assimp/models/glTF2";

/// Real, valid glTF2 models used as props (relative to [`ASSIMP_GLTF2_DIR`]). The first one must
/// exist; the others are used when present.
pub const REAL_PROPS: &[&str] = &[
    "2CylinderEngine-glTF-Binary/2CylinderEngine.glb",
    "BoxTextured-glTF-Binary/BoxTextured.glb",
    "BoxTextured-glTF/BoxTextured.gltf",
    "BoxBadNormals-glTF-Binary/BoxBadNormals.glb",
    "glTF-Sample-Models/AnimatedMorphCube-glTF/AnimatedMorphCube.gltf",
    "cameras/Cameras.gltf",
    "ClearCoat-glTF/ClearCoatTest.gltf",
];

/// The real skinned model (relative to [`ASSIMP_GLTF2_DIR`]).
pub const REAL_SKINNED: &str = "simple_skin/simple_skin.gltf";

/// What to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldPreset {
    /// Name (for logs).
    pub name: String,
    /// Seed: the same preset and seed give the same world, bit for bit.
    pub seed: u64,
    /// Side of the square world in metres.
    pub size_m: f32,
    /// Levels per side (the world has `grid * grid` levels).
    pub grid: u32,
    /// Total instances (terrain tiles included).
    pub instances: u32,
    /// Every `character_every`-th level holds a generated skinned character.
    pub character_every: u32,
    /// Generated skinned characters in every level besides those (0 in the maps; a crowd).
    pub characters_per_level: u32,
    /// What the free instances are (the open map, or a dense city).
    pub style: WorldStyle,
    /// Districts of distinct assets, as a side in levels (0: none, the default). Without
    /// them every level draws from one library of a few hundred meshes, so a BLAS per loaded
    /// mesh is cheap whatever the map's size. With them the map is cut into squares of
    /// `districts` x `districts` levels and each square has its own copy of every opaque
    /// static mesh (rocks, buildings, props), as an open world's regions have their own
    /// assets: distinct meshes to the BLAS manager, with their own BLASes. A copy shares its
    /// LOD chain with the library's mesh in the generator and in the bake (its geometry is the
    /// same: the mesh library is written once), and is streamed as a mesh of its own (its LODs
    /// are read and held apart). Which mesh an instance draws is
    /// unchanged: the same preset and seed give the same instances, mapped to their
    /// district's copies.
    pub districts: u32,
    /// Directory holding assimp-testmodels' glTF2 models.
    pub asset_dir: PathBuf,
}

/// The mix of a world's free instances (after terrain and characters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WorldStyle {
    /// The open map: rocks 42%, props 32%, buildings 12%, trees 9%, grass 3.5%, glass 1.5%.
    #[default]
    Open,
    /// A city: props 58%, buildings 25% (2x to 8x taller), trees 8%, rocks 5%, grass 2%,
    /// glass 2%.
    City,
}

impl WorldPreset {
    /// The shipped game's map: 4 km x 4 km, 56 x 56 = 3,136 levels, 110,000 instances.
    ///
    /// ```no_run
    /// let world = rtstream_streaming::generate(&rtstream_streaming::WorldPreset::default_world())?;
    /// assert!(world.levels.len() >= 3000 && world.instance_count() >= 104_366);
    /// # Ok::<(), rtstream_streaming::StreamingError>(())
    /// ```
    pub fn default_world() -> WorldPreset {
        WorldPreset {
            name: "default".into(),
            seed: 0x5EED,
            size_m: 4000.0,
            grid: 56,
            instances: 110_000,
            character_every: 8,
            characters_per_level: 0,
            style: WorldStyle::Open,
            districts: 0,
            asset_dir: PathBuf::from(ASSIMP_GLTF2_DIR),
        }
    }

    /// The scale-test map: 16 km x 16 km, 224 x 224 levels, the default's density (1.76 M
    /// instances).
    pub fn large_world() -> WorldPreset {
        WorldPreset {
            name: "large".into(),
            grid: 224,
            size_m: 16_000.0,
            instances: 110_000 * 16,
            ..WorldPreset::default_world()
        }
    }

    /// A `grid` x `grid` corner of the default map at its density (for tests and examples).
    pub fn small(grid: u32, seed: u64) -> WorldPreset {
        let d = WorldPreset::default_world();
        let cells = f64::from(grid).powi(2) / f64::from(d.grid).powi(2);
        WorldPreset {
            name: format!("small{grid}"),
            seed,
            size_m: d.size_m * grid as f32 / d.grid as f32,
            grid,
            instances: (f64::from(d.instances) * cells).round() as u32,
            ..d
        }
    }

    /// A dense city: 16 x 16 levels of the default map's cell size (1.14 km), ten times the
    /// default's instance density (89,796 instances), tall buildings and many small props.
    pub fn city() -> WorldPreset {
        let small = WorldPreset::small(16, WorldPreset::default_world().seed);
        WorldPreset {
            name: "city".into(),
            instances: small.instances * 10,
            style: WorldStyle::City,
            ..small
        }
    }

    /// A crowd: 3 x 3 levels of the default map (214 m) with `characters` generated skinned
    /// characters spread over them (besides the map's own content), rounded up to a multiple
    /// of 9 and capped at what a u32 instance count holds.
    pub fn crowd(characters: u32) -> WorldPreset {
        let small = WorldPreset::small(3, WorldPreset::default_world().seed);
        // At most what the instance count (u32) can hold besides the map's own content.
        let per_level = characters.div_ceil(9).min((u32::MAX - small.instances) / 9);
        WorldPreset {
            name: format!("crowd{characters}"),
            characters_per_level: per_level,
            instances: small.instances + per_level * 9,
            ..small
        }
    }

    /// Side of one level cell in metres.
    pub fn cell_size(&self) -> f32 {
        self.size_m / self.grid.max(1) as f32
    }

    /// The district of level cell `(cx, cz)` (0 without districts).
    pub fn district_of(&self, cx: u32, cz: u32) -> u32 {
        if self.districts == 0 {
            return 0;
        }
        let per_side = self.grid.div_ceil(self.districts);
        (cz / self.districts) * per_side + cx / self.districts
    }

    /// Districts on the map (1 without districts).
    pub fn district_count(&self) -> u32 {
        if self.districts == 0 {
            return 1;
        }
        self.grid.div_ceil(self.districts).pow(2)
    }
}

/// A generated world: the mesh library and the levels.
#[derive(Debug, Clone)]
pub struct GeneratedWorld {
    /// What it was generated from.
    pub preset: WorldPreset,
    /// Ground rectangle of the map (Y from the level bounds).
    pub extent: Aabb,
    /// Every mesh, indexed by [`WorldMeshId`].
    pub meshes: Vec<Mesh>,
    /// Every level, indexed by [`LevelId`].
    pub levels: Vec<Level>,
}

/// Counts that the presets promise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldStats {
    /// Levels.
    pub levels: usize,
    /// Instances.
    pub instances: usize,
    /// Instances whose material is not opaque.
    pub non_opaque: usize,
    /// Skinned instances.
    pub skinned: usize,
    /// Distinct meshes.
    pub meshes: usize,
    /// Triangles over every LOD of every mesh.
    pub mesh_triangles: usize,
}

impl GeneratedWorld {
    /// Number of instances over all levels.
    pub fn instance_count(&self) -> usize {
        self.levels.iter().map(|l| l.instances.len()).sum()
    }

    /// Counts for checking the preset's figures.
    pub fn stats(&self) -> WorldStats {
        let all = self.levels.iter().flat_map(|l| &l.instances);
        let (mut non_opaque, mut skinned) = (0, 0);
        for i in all {
            non_opaque += usize::from(i.material != MaterialClass::Opaque);
            skinned += usize::from(i.motion == Motion::Skinned);
        }
        WorldStats {
            levels: self.levels.len(),
            instances: self.instance_count(),
            non_opaque,
            skinned,
            meshes: self.meshes.len(),
            mesh_triangles: self.lods().map(|l| l.triangle_count()).sum(),
        }
    }

    /// Bytes of the in-memory world description: levels, instances and mesh headers (names, LOD
    /// pointer lists), but not the mesh geometry, which is counted apart.
    pub fn description_bytes(&self) -> usize {
        let levels: usize = self
            .levels
            .iter()
            .map(|l| {
                std::mem::size_of::<Level>()
                    + l.instances.capacity() * std::mem::size_of::<Instance>()
            })
            .sum();
        let meshes: usize = self
            .meshes
            .iter()
            .map(|m| std::mem::size_of::<Mesh>() + m.name.capacity() + m.lods.capacity() * 8)
            .sum();
        std::mem::size_of::<Self>() + levels + meshes
    }

    /// [`GeneratedWorld::description_bytes`] per instance.
    pub fn bytes_per_instance(&self) -> f64 {
        self.description_bytes() as f64 / self.instance_count().max(1) as f64
    }

    /// CPU bytes of all mesh geometry (every LOD).
    pub fn mesh_bytes(&self) -> usize {
        self.lods().map(|l| l.byte_size()).sum()
    }

    /// Every LOD of every mesh.
    fn lods(&self) -> impl Iterator<Item = &Arc<MeshLod>> {
        self.meshes.iter().flat_map(|m| &m.lods)
    }
}

/// What each generated mesh is, and how its instances look.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Terrain,
    Rock,
    Building,
    Prop,
    Tree,
    Grass,
    Glass,
    Character,
    RealSkinned,
}

impl Kind {
    fn material(self) -> MaterialClass {
        match self {
            Kind::Tree => MaterialClass::AlphaMasked,
            Kind::Grass => MaterialClass::WorldPositionOffset,
            Kind::Glass => MaterialClass::Transparent,
            _ => MaterialClass::Opaque,
        }
    }
}

enum Spec {
    Procedural(Kind, u64),
    Gltf(PathBuf, f32),
}

/// Builds a world from a preset. Deterministic: same preset, same world.
///
/// Fails with [`StreamingError::MissingAssets`] when the real models are not installed, and with
/// the loader's error if one of them is unusable.
pub fn generate(preset: &WorldPreset) -> Result<GeneratedWorld> {
    let _span = tracing::info_span!("generate", preset = %preset.name).entered();
    let bar = progress(u64::from(preset.grid * preset.grid) + 1);
    bar.set_message("meshes");
    let (mut meshes, kinds) = build_meshes(preset)?;
    // Each district's copies of the opaque static meshes (`WorldPreset::districts`), laid out
    // district by district after the library: district k > 0's copy of mesh `m` is
    // `copies[m] + (k - 1) * with_copies` (NONE: a mesh without copies).
    const NONE: u32 = u32::MAX;
    let base_meshes = meshes.len();
    let mut copies = vec![NONE; base_meshes];
    for k in 1..preset.district_count() {
        for m in 0..base_meshes {
            if !matches!(kinds[m], Kind::Rock | Kind::Building | Kind::Prop) {
                continue;
            }
            if k == 1 {
                copies[m] = meshes.len() as u32;
            }
            let id = WorldMeshId(meshes.len() as u32);
            let base = &meshes[m];
            let copy = Mesh {
                id,
                name: format!("{} (district {k})", base.name),
                bounds: base.bounds,
                lods: base.lods.clone(),
            };
            meshes.push(copy);
        }
    }
    let with_copies = copies.iter().filter(|&&c| c != NONE).count() as u32;
    let copy_of = |mesh: WorldMeshId, district: u32| -> WorldMeshId {
        match copies[mesh.0 as usize] {
            c if c == NONE || district == 0 => mesh,
            c => WorldMeshId(c + (district - 1) * with_copies),
        }
    };
    bar.inc(1);
    bar.set_message("levels");
    let by_kind = |k: Kind| -> Vec<WorldMeshId> {
        kinds
            .iter()
            .enumerate()
            .filter(|(_, &x)| x == k)
            .map(|(i, _)| WorldMeshId(i as u32))
            .collect()
    };
    let pools: Vec<(Kind, Vec<WorldMeshId>)> = [
        Kind::Terrain,
        Kind::Rock,
        Kind::Building,
        Kind::Prop,
        Kind::Tree,
        Kind::Grass,
        Kind::Glass,
        Kind::Character,
        Kind::RealSkinned,
    ]
    .into_iter()
    .map(|k| (k, by_kind(k)))
    .collect();
    let pool = |k: Kind| -> &[WorldMeshId] {
        pools
            .iter()
            .find(|(x, _)| *x == k)
            .map(|(_, v)| v.as_slice())
            .unwrap_or(&[])
    };
    // Weighted mix of the free instances (after terrain and characters): each kind's weight
    // in the open world and in the city.
    const MIX: [(Kind, f32, f32); 6] = [
        (Kind::Rock, 0.42, 0.05),
        (Kind::Building, 0.12, 0.25),
        (Kind::Prop, 0.32, 0.58),
        (Kind::Tree, 0.09, 0.08),
        (Kind::Grass, 0.035, 0.02),
        (Kind::Glass, 0.015, 0.02),
    ];
    let mix: [(Kind, f32); 6] = MIX.map(|(kind, open, city)| match preset.style {
        WorldStyle::Open => (kind, open),
        WorldStyle::City => (kind, city),
    });
    let city = preset.style == WorldStyle::City;

    let n_levels = preset.grid * preset.grid;
    let cell = preset.cell_size();
    let half = preset.size_m * 0.5;
    let mut levels = Vec::with_capacity(n_levels as usize);
    let mut next_instance = 0u32;
    let mut extent = Aabb::EMPTY;
    for lid in 0..n_levels {
        let (cx, cz) = ((lid % preset.grid) as i32, (lid / preset.grid) as i32);
        let mut rng = procedural::seeded(
            preset.seed ^ (u64::from(lid) << 20).wrapping_mul(0x2545_F491_4F6C_DD1D),
        );
        let base = preset.instances / n_levels;
        let count = base + u32::from(lid < preset.instances % n_levels);
        let origin = Vec3::new(
            -half + (cx as f32 + 0.5) * cell,
            0.0,
            -half + (cz as f32 + 0.5) * cell,
        );
        let mut instances = Vec::with_capacity(count as usize);
        let district = preset.district_of(cx as u32, cz as u32);
        let place = |kind: Kind, rng: &mut Rng, next: &mut u32| -> Option<Instance> {
            let ids = pool(kind);
            if ids.is_empty() {
                return None;
            }
            let mesh = copy_of(ids[rng.below(ids.len())], district);
            let transform = if kind == Kind::Terrain {
                Mat4::from_translation(origin)
            } else {
                let p = origin
                    + Vec3::new(
                        rng.range(-0.5, 0.5) * cell,
                        0.0,
                        rng.range(-0.5, 0.5) * cell,
                    );
                let s = match kind {
                    Kind::Rock => rng.range(0.5, 2.5),
                    _ => rng.range(0.85, 1.2),
                };
                // City towers: 2x to 8x taller (drawn only in the city, so the open map's
                // random sequence is unchanged).
                let tall = if city && kind == Kind::Building {
                    rng.range(2.0, 8.0)
                } else {
                    1.0
                };
                Mat4::from_scale_rotation_translation(
                    Vec3::new(s, s * tall, s),
                    Quat::from_rotation_y(rng.range(0.0, std::f32::consts::TAU)),
                    p,
                )
            };
            let motion = if matches!(kind, Kind::Character | Kind::RealSkinned) {
                Motion::Skinned
            } else {
                Motion::Static
            };
            let id = WorldInstanceId(*next);
            *next += 1;
            let m = &meshes[mesh.0 as usize];
            Some(Instance::new(
                id,
                mesh,
                transform,
                &m.bounds,
                kind.material(),
                motion,
            ))
        };
        let mut left = count;
        let mut fixed = vec![Kind::Terrain];
        if lid % preset.character_every.max(1) == 3 {
            fixed.push(Kind::Character);
        }
        if lid % 64 == 17 {
            fixed.push(Kind::RealSkinned);
        }
        fixed.extend(std::iter::repeat_n(
            Kind::Character,
            preset.characters_per_level as usize,
        ));
        for k in fixed {
            if left == 0 {
                break;
            }
            if let Some(i) = place(k, &mut rng, &mut next_instance) {
                instances.push(i);
                left -= 1;
            }
        }
        for _ in 0..left {
            let mut x = rng.f32();
            let mut kind = Kind::Rock;
            for (k, w) in mix {
                if x < w {
                    kind = k;
                    break;
                }
                x -= w;
            }
            if let Some(i) = place(kind, &mut rng, &mut next_instance) {
                instances.push(i);
            }
        }
        let ground = Aabb {
            min: origin - Vec3::new(cell * 0.5, 0.0, cell * 0.5),
            max: origin + Vec3::new(cell * 0.5, 0.0, cell * 0.5),
        };
        let bounds = instances.iter().fold(ground, |b, i| b.union(i.aabb));
        extent = extent.union(bounds);
        levels.push(Level {
            id: LevelId(lid),
            cell: [cx, cz],
            bounds,
            instances,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    tracing::info!(
        levels = levels.len(),
        instances = next_instance,
        meshes = meshes.len(),
        "world generated"
    );
    Ok(GeneratedWorld {
        preset: preset.clone(),
        extent,
        meshes,
        levels,
    })
}

fn progress(len: u64) -> indicatif::ProgressBar {
    if std::io::stderr().is_terminal() {
        let bar = indicatif::ProgressBar::new(len);
        if let Ok(style) =
            indicatif::ProgressStyle::with_template("{msg:>8} [{bar:40}] {pos}/{len} {elapsed}")
        {
            bar.set_style(style);
        }
        bar
    } else {
        indicatif::ProgressBar::hidden()
    }
}

/// Builds the mesh library (LOD chains in parallel); returns meshes and their kinds.
fn build_meshes(preset: &WorldPreset) -> Result<(Vec<Mesh>, Vec<Kind>)> {
    let dir = &preset.asset_dir;
    let first = dir.join(REAL_PROPS[0]);
    if !first.is_file() {
        return Err(StreamingError::MissingAssets {
            path: first,
            reason: "required model not found".into(),
        });
    }
    let mut specs: Vec<(Kind, Spec)> = Vec::new();
    let s = preset.seed;
    for (kind, n) in [
        (Kind::Terrain, 24u64),
        (Kind::Rock, 96),
        (Kind::Building, 48),
        (Kind::Tree, 32),
        (Kind::Grass, 16),
        (Kind::Glass, 8),
        (Kind::Character, 8),
    ] {
        for v in 0..n {
            specs.push((
                kind,
                Spec::Procedural(
                    kind,
                    s.wrapping_mul(31).wrapping_add(v * 7919 + kind as u64),
                ),
            ));
        }
    }
    for (k, rel) in REAL_PROPS.iter().enumerate() {
        let p = dir.join(rel);
        if p.is_file() {
            // Scaled to a few metres, in a few sizes.
            for size in [1.5f32, 3.0, 6.0] {
                specs.push((
                    Kind::Prop,
                    Spec::Gltf(p.clone(), size * (1.0 + k as f32 * 0.1)),
                ));
            }
        }
    }
    let skin_path = dir.join(REAL_SKINNED);
    if skin_path.is_file() {
        specs.push((Kind::RealSkinned, Spec::Gltf(skin_path, 1.8)));
    }
    let cell = preset.cell_size();
    let results: Vec<Mutex<Option<Result<Mesh>>>> =
        specs.iter().map(|_| Mutex::new(None)).collect();
    let next = AtomicUsize::new(0);
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    std::thread::scope(|sc| {
        for _ in 0..threads {
            sc.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some((_, spec)) = specs.get(i) else { break };
                let r = build_one(spec, cell);
                *results[i].lock() = Some(r);
            });
        }
    });
    let mut meshes = Vec::with_capacity(specs.len());
    for (i, slot) in results.into_iter().enumerate() {
        let mut m = slot
            .into_inner()
            .ok_or_else(|| StreamingError::MissingAssets {
                path: PathBuf::new(),
                reason: format!("mesh {i} was not built"),
            })??;
        m.id = WorldMeshId(i as u32);
        meshes.push(m);
    }
    Ok((meshes, specs.into_iter().map(|(k, _)| k).collect()))
}

fn build_one(spec: &Spec, cell: f32) -> Result<Mesh> {
    let (name, pos, idx) = match *spec {
        Spec::Procedural(Kind::Character, seed) => return Ok(procedural::character(seed)),
        Spec::Procedural(kind, seed) => {
            let (p, i) = match kind {
                Kind::Terrain => procedural::grid_terrain(32, cell, 3.0, seed),
                Kind::Rock => procedural::rock(seed, 2.0),
                Kind::Building => procedural::building(seed),
                Kind::Tree => procedural::tree(seed),
                Kind::Grass => procedural::grass(seed),
                _ => procedural::glass_pane(seed),
            };
            (format!("{kind:?}{seed}").to_lowercase(), p, i)
        }
        Spec::Gltf(ref path, size) => return gltf_mesh(path, size),
    };
    Ok(Mesh {
        id: WorldMeshId(0),
        name,
        bounds: Aabb::from_points(&pos),
        lods: build_lod_chain(pos, idx, None)
            .into_iter()
            .map(Arc::new)
            .collect(),
    })
}

/// Loads a glTF file as one mesh: a skinned file keeps its first skinned mesh; otherwise every
/// instance is flattened into one mesh. The result is scaled so its largest side is `size` metres
/// and stands on Y = 0, centred in X/Z, so LOD errors are in world metres.
pub(crate) fn gltf_mesh(path: &Path, size: f32) -> Result<Mesh> {
    let scene = load_gltf(path)?;
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let (mut pos, idx, mut skin) = if let Some(m) = scene.meshes.iter().find(|m| m.skin.is_some()) {
        (m.positions.clone(), m.indices.clone(), m.skin.clone())
    } else {
        let (mut pos, mut idx) = (Vec::new(), Vec::new());
        for inst in &scene.instances {
            let m = &scene.meshes[inst.mesh];
            let base = pos.len() as u32;
            pos.extend(
                m.positions
                    .iter()
                    .map(|p| inst.transform.transform_point3(Vec3::from(*p)).to_array()),
            );
            idx.extend(m.indices.iter().map(|i| i + base));
        }
        (pos, idx, None)
    };
    let b = Aabb::from_points(&pos);
    let extent = (b.max - b.min).max_element();
    if pos.is_empty() || !extent.is_finite() || extent <= 0.0 {
        return Err(StreamingError::InvalidMesh {
            path: path.to_owned(),
            mesh: name,
            reason: "no usable triangles".into(),
        });
    }
    let s = size / extent;
    let shift = Vec3::new(-b.center().x, -b.min.y, -b.center().z);
    let to_world = Mat4::from_scale(Vec3::splat(s)) * Mat4::from_translation(shift);
    for p in &mut pos {
        *p = to_world.transform_point3(Vec3::from(*p)).to_array();
    }
    if let Some(sk) = &mut skin {
        // Skinned vertices come out in skeleton space: re-apply the same normalisation above it.
        let mut skel = (*sk.skeleton).clone();
        skel.root = to_world * skel.root;
        for j in &mut skel.joints {
            j.inverse_bind *= to_world.inverse();
        }
        sk.skeleton = Arc::new(skel);
    }
    Ok(Mesh {
        id: WorldMeshId(0),
        name: format!("{name}@{size}m"),
        bounds: Aabb::from_points(&pos),
        lods: build_lod_chain(pos, idx, skin)
            .into_iter()
            .map(Arc::new)
            .collect(),
    })
}
