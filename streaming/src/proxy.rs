//! Level proxies (HLOD) for the far field, baked with the world.
//!
//! A quadtree over the level grid: one node per 2x2 block of levels (depth 1, the leaves), 4x4
//! (depth 2), 8x8 (depth 3) and 16x16 (depth 4); partial blocks at the map's edge are fine. A
//! node is made of the static opaque instances of its levels (world space; skinned and
//! non-opaque instances are left out), to a triangle budget, in one of two ways
//! ([`ProxyMethod`]):
//! - **Select** (the default): every instance keeps its own shape at the coarsest LOD of its
//!   chain within an error `E`, and is left out when its bounding radius is within `E` (at
//!   that size it is missing, not misshapen); `E` is the smallest error at which the node fits
//!   its budget. In the default world a leaf's few tall buildings keep their exact boxes while
//!   its small, dense props (a 774-triangle LOD on a 3 m statue) go, where simplifying the
//!   whole merge had cut every building down to a blob. Nodes deeper than
//!   [`ProxyConfig::select_depth`] cover too many terrain tiles to keep each one whole: they
//!   select to `SIMPLIFY_HEADROOM` times the budget and simplify the merge the rest of the way.
//! - **Simplify**: merge each instance's coarsest LOD within
//!   [`ProxyConfig::source_error`] and simplify the merge to the budget with meshoptimizer's
//!   sloppy simplifier; a parent merges its children's proxies and simplifies again.
//!
//! Each node records its geometric error in metres, never less than its children's, so errors
//! only grow up the tree. Side by side on the fly-through (`docs/RESULTS.md`, "Proxies that
//! keep their buildings"), Select halves the error beyond r2 at the same memory, which lets the
//! manager's far keep angle be 0.75° instead of 0.5° (36 % fewer TLAS records).
//!
//! A leaf also lists its **landmarks**: the static opaque instances whose bounding sphere is at
//! least [`ProxyConfig::landmark_radius`]. Streaming loads levels only within its load radius;
//! beyond it, the proxy's landmark list lets an engine place those instances anyway (the manager
//! shows them as far landmarks beside the proxy, at the LOD their distance needs), so a tower
//! 2 km away keeps its own silhouette although its level never loaded.
//!
//! Proxies live in their own file (`proxies.bin`): a checksummed index (with the landmark
//! lists), then one checksummed chunk per node, so one corrupt node loses only itself.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use crate::error::{FormatError, Result, StreamingError};
use crate::format::{self, frame, unframe, Reader, Writer};
use crate::generate::GeneratedWorld;
use crate::lod::compact;
use crate::model::{Aabb, LevelId, MaterialClass, MeshLod, Motion, WorldMeshId};
use glam::Mat4;

/// The proxy file of a baked world.
pub const PROXY_FILE: &str = "proxies.bin";
/// Magic of the proxy index.
pub const PROXY_INDEX_MAGIC: [u8; 4] = *b"RTSP";
/// Version of the proxy index's layout (inside the framed payload; 2 added the landmark lists).
pub const PROXY_INDEX_VERSION: u32 = 2;

/// An instance a leaf lists as a landmark: what is needed to place it without loading its
/// level (it is static and opaque by construction; bounds follow from its mesh's bounds).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProxyLandmark {
    /// The instance (the same id its level gives it, so an engine can tell them apart).
    pub instance: crate::model::WorldInstanceId,
    /// Its level.
    pub level: LevelId,
    /// Its mesh.
    pub mesh: WorldMeshId,
    /// Local-to-world transform.
    pub transform: Mat4,
}

/// A proxy node's id: its index in [`ProxyTree::nodes`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ProxyId(pub u32);

/// One node of the proxy quadtree (its geometry is kept apart).
#[derive(Debug, Clone, PartialEq)]
pub struct ProxyNode {
    /// Its id.
    pub id: ProxyId,
    /// 1 for 2x2 levels, 2 for 4x4, 3 for 8x8, 4 for 16x16.
    pub depth: u8,
    /// The block's first level cell (x, z) and its side in cells (`1 << depth`).
    pub cell: [i32; 2],
    /// World bounds of what it merges.
    pub bounds: Aabb,
    /// Geometric error against the instances' finest LODs is at least the LOD chain's; this is
    /// the error of the proxy against the coarsest LODs it merges, in metres.
    pub error: f32,
    /// Its parent (None for a root).
    pub parent: Option<ProxyId>,
    /// Its children (empty for a leaf).
    pub children: Vec<ProxyId>,
    /// Levels it covers.
    pub levels: Vec<LevelId>,
    /// Triangles of its geometry.
    pub triangles: u32,
    /// Leaves: the static opaque instances of its levels with a bounding sphere of at least
    /// [`ProxyConfig::landmark_radius`], in level then instance order (empty for parents).
    pub landmarks: Vec<ProxyLandmark>,
}

/// The quadtree's structure.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ProxyTree {
    /// Every node, leaves first.
    pub nodes: Vec<ProxyNode>,
    /// The leaf covering each level (indexed by level id).
    pub leaf_of_level: Vec<Option<ProxyId>>,
}

impl ProxyTree {
    /// The leaf (2x2 block) holding `level`.
    pub fn leaf_of(&self, level: LevelId) -> Option<ProxyId> {
        self.leaf_of_level.get(level.0 as usize).copied().flatten()
    }

    /// Nodes without a parent.
    pub fn roots(&self) -> impl Iterator<Item = &ProxyNode> {
        self.nodes.iter().filter(|n| n.parent.is_none())
    }

    /// A node.
    pub fn node(&self, id: ProxyId) -> Option<&ProxyNode> {
        self.nodes.get(id.0 as usize)
    }
}

/// How a node's geometry is made of its instances (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProxyMethod {
    /// Each instance at its own LOD, the smallest ones left out, to the budget.
    Select,
    /// The instances' LODs merged and simplified to the budget (sloppy simplification).
    Simplify,
}

impl ProxyMethod {
    /// A short name (bake stamps, reports).
    pub fn name(self) -> &'static str {
        match self {
            ProxyMethod::Select => "select",
            ProxyMethod::Simplify => "simplify",
        }
    }
}

/// How far past the budget a node deeper than [`ProxyConfig::select_depth`] selects before
/// simplifying the merge to the budget. (On the default fly-through, 2, 4 and 12 scored alike:
/// 0.44, 0.43 and 0.46 % hit mismatch at a 1° keep angle.)
const SIMPLIFY_HEADROOM: u64 = 4;

/// How proxies are built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProxyConfig {
    /// Depths to build (1 = 2x2 blocks only ... 4 = up to 16x16).
    pub max_depth: u8,
    /// Triangle budget of every node.
    pub triangles: u32,
    /// How a node's geometry is made.
    pub method: ProxyMethod,
    /// With [`ProxyMethod::Select`]: the deepest nodes that select to the budget alone (deeper
    /// ones simplify after selecting). 2: the 4x4 blocks; the default world's 8x8 blocks have
    /// 64 terrain tiles, too many to keep whole in the budget.
    pub select_depth: u8,
    /// With [`ProxyMethod::Simplify`]: leaves merge each instance's coarsest LOD whose error
    /// is at most this (metres).
    pub source_error: f32,
    /// Leaves list the static opaque instances with a bounding sphere at least this large
    /// (metres) as landmarks. 4 m subtends 0.75° (the manager's default far keep angle) out to
    /// 305 m and 0.25° to 920 m: anything smaller is too small to keep beyond the load radius.
    pub landmark_radius: f32,
    /// Worker threads.
    pub threads: usize,
}

impl Default for ProxyConfig {
    fn default() -> Self {
        Self {
            max_depth: 4,
            triangles: 768,
            method: ProxyMethod::Select,
            select_depth: 2,
            source_error: 1.0,
            landmark_radius: 4.0,
            threads: std::thread::available_parallelism().map_or(2, |n| n.get()),
        }
    }
}

/// Figures of a proxy build.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ProxyReport {
    /// Nodes.
    pub nodes: u32,
    /// Triangles over all nodes.
    pub triangles: u64,
    /// Landmarks listed over all leaves.
    pub landmarks: u64,
    /// Bytes of the proxy file.
    pub file_bytes: u64,
    /// Largest node geometry in bytes (positions and indices).
    pub max_node_bytes: u64,
    /// Build time, microseconds.
    pub build_us: u64,
}

/// The proxies of a world: the tree and each node's world-space geometry.
#[derive(Debug, Clone, Default)]
pub struct Proxies {
    /// Structure.
    pub tree: ProxyTree,
    /// Geometry per node (world-space positions; no skin).
    pub geometry: Vec<Arc<MeshLod>>,
}

fn merge(parts: &[(&MeshLod, glam::Mat4)]) -> MeshLod {
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    for (g, t) in parts {
        let base = positions.len() as u32;
        positions.extend(
            g.positions
                .iter()
                .map(|p| t.transform_point3(glam::Vec3::from(*p)).to_array()),
        );
        indices.extend(g.indices.iter().map(|i| i + base));
    }
    MeshLod {
        positions,
        indices,
        error: 0.0,
        skin: None,
    }
}

/// Simplifies `g` to at most `triangles`; returns it with its error (metres) added.
fn simplify(g: MeshLod, triangles: u32, base_error: f32) -> MeshLod {
    if g.triangle_count() <= triangles as usize || g.positions.is_empty() {
        return MeshLod {
            error: base_error,
            ..g
        };
    }
    let mut err = 0.0f32;
    let idx = meshopt::simplify_sloppy_decoder(
        &g.indices,
        &g.positions,
        triangles as usize * 3,
        f32::MAX,
        Some(&mut err),
    );
    let err = err * meshopt::simplify_scale_decoder(&g.positions);
    compact(&g.positions, &idx, None, base_error + err.max(0.0))
}

/// Builds the proxy tree of `world` (deterministic: the same world gives the same bytes).
pub fn build_proxies(world: &GeneratedWorld, cfg: &ProxyConfig) -> (Proxies, ProxyReport) {
    let started = Instant::now();
    let mut nodes: Vec<ProxyNode> = Vec::new();
    let mut geometry: Vec<Arc<MeshLod>> = Vec::new();
    let mut leaf_of_level = vec![None; world.levels.len()];
    // Depth 1 from the levels, then each depth from the one below.
    let mut below: Vec<u32> = Vec::new();
    for depth in 1..=cfg.max_depth.max(1) {
        let mut blocks: std::collections::BTreeMap<(i32, i32), Vec<u32>> = Default::default();
        if depth == 1 {
            for l in &world.levels {
                blocks
                    .entry((l.cell[0] >> 1, l.cell[1] >> 1))
                    .or_default()
                    .push(l.id.0);
            }
        } else {
            for &c in &below {
                let n = &nodes[c as usize];
                let s = 1 << depth;
                blocks
                    .entry((n.cell[0].div_euclid(s), n.cell[1].div_euclid(s)))
                    .or_default()
                    .push(c);
            }
        }
        if depth > 1 && blocks.len() == below.len() {
            break; // one node per block already: nothing coarser to add
        }
        let jobs: Vec<((i32, i32), Vec<u32>)> = blocks.into_iter().collect();
        let built: Vec<(Aabb, MeshLod, Vec<ProxyLandmark>)> =
            parallel_map(&jobs, cfg.threads, |(_, members)| {
                if depth == 1 {
                    let mut parts = Vec::new();
                    let mut landmarks = Vec::new();
                    let mut bounds = Aabb::EMPTY;
                    let mut err = 0.0f32;
                    for &l in members {
                        for inst in &world.levels[l as usize].instances {
                            if inst.material != MaterialClass::Opaque
                                || inst.motion != Motion::Static
                            {
                                continue;
                            }
                            if inst.sphere.radius >= cfg.landmark_radius {
                                landmarks.push(ProxyLandmark {
                                    instance: inst.id,
                                    level: LevelId(l),
                                    mesh: inst.mesh,
                                    transform: inst.transform,
                                });
                            }
                            let mesh = &world.meshes[inst.mesh.0 as usize];
                            if mesh.lods.is_empty() {
                                continue;
                            }
                            bounds = bounds.union(inst.aabb);
                            if cfg.method != ProxyMethod::Simplify {
                                continue; // `select_node` picks each instance's LOD
                            }
                            // The coarsest LOD still within the leaf's source error: the very
                            // coarsest LODs of tall buildings are pyramids, not what a skyline is.
                            let scale = inst.max_scale();
                            let g = mesh
                                .lods
                                .iter()
                                .rev()
                                .find(|g| g.error * scale <= cfg.source_error)
                                .unwrap_or(&mesh.lods[0]);
                            parts.push((&**g, inst.transform));
                            err = err.max(g.error * scale);
                        }
                    }
                    let g = match cfg.method {
                        ProxyMethod::Simplify => simplify(merge(&parts), cfg.triangles, err),
                        ProxyMethod::Select => select_node(world, members, cfg, depth),
                    };
                    (bounds, g, landmarks)
                } else {
                    let bounds = members
                        .iter()
                        .fold(Aabb::EMPTY, |b, &c| b.union(nodes[c as usize].bounds));
                    // Never finer than a child: errors only grow up the tree (the cut refines
                    // a node into its children).
                    let err = members
                        .iter()
                        .map(|&c| nodes[c as usize].error)
                        .fold(0.0f32, f32::max);
                    let g = match cfg.method {
                        ProxyMethod::Simplify => {
                            let parts: Vec<(&MeshLod, glam::Mat4)> = members
                                .iter()
                                .map(|&c| (&*geometry[c as usize], glam::Mat4::IDENTITY))
                                .collect();
                            simplify(merge(&parts), cfg.triangles, err)
                        }
                        ProxyMethod::Select => {
                            let levels: Vec<u32> = members
                                .iter()
                                .flat_map(|&c| nodes[c as usize].levels.iter().map(|l| l.0))
                                .collect();
                            let g = select_node(world, &levels, cfg, depth);
                            MeshLod {
                                error: g.error.max(err),
                                ..g
                            }
                        }
                    };
                    (bounds, g, Vec::new())
                }
            });
        let mut level_ids = Vec::new();
        for (((bx, bz), members), (bounds, g, landmarks)) in jobs.into_iter().zip(built) {
            let id = ProxyId(nodes.len() as u32);
            let s = 1 << depth;
            let levels: Vec<LevelId> = if depth == 1 {
                members.iter().map(|&l| LevelId(l)).collect()
            } else {
                members
                    .iter()
                    .flat_map(|&c| nodes[c as usize].levels.clone())
                    .collect()
            };
            let children: Vec<ProxyId> = if depth == 1 {
                for l in &levels {
                    leaf_of_level[l.0 as usize] = Some(id);
                }
                Vec::new()
            } else {
                members.iter().map(|&c| ProxyId(c)).collect()
            };
            for c in &children {
                nodes[c.0 as usize].parent = Some(id);
            }
            nodes.push(ProxyNode {
                id,
                depth,
                cell: [bx * s, bz * s],
                bounds,
                error: g.error,
                parent: None,
                children,
                levels,
                triangles: g.triangle_count() as u32,
                landmarks,
            });
            geometry.push(Arc::new(g));
            level_ids.push(id.0);
        }
        below = level_ids;
    }
    let report = ProxyReport {
        nodes: nodes.len() as u32,
        triangles: geometry.iter().map(|g| g.triangle_count() as u64).sum(),
        landmarks: nodes.iter().map(|n| n.landmarks.len() as u64).sum(),
        file_bytes: 0,
        max_node_bytes: geometry
            .iter()
            .map(|g| g.byte_size() as u64)
            .max()
            .unwrap_or(0),
        build_us: started.elapsed().as_micros() as u64,
    };
    (
        Proxies {
            tree: ProxyTree {
                nodes,
                leaf_of_level,
            },
            geometry,
        },
        report,
    )
}

/// One instance as a node's proxy may show it: at one of its LODs, or left out.
struct Source<'a> {
    lods: &'a [Arc<MeshLod>],
    scale: f32,
    radius: f32,
    transform: Mat4,
}

impl<'a> Source<'a> {
    /// Its coarsest LOD within `e` metres (`None`: none is).
    fn within(&self, e: f32) -> Option<&'a MeshLod> {
        self.lods
            .iter()
            .rev()
            .find(|g| g.error * self.scale <= e)
            .map(|g| &**g)
    }

    /// Whether it is left out at error `e`: no larger than `e`.
    fn left_out(&self, e: f32) -> bool {
        self.radius <= e
    }
}

/// The static opaque instances of `levels`.
fn sources<'a>(world: &'a GeneratedWorld, levels: &[u32]) -> Vec<Source<'a>> {
    levels
        .iter()
        .flat_map(|&l| &world.levels[l as usize].instances)
        .filter(|i| i.material == MaterialClass::Opaque && i.motion == Motion::Static)
        .map(|i| Source {
            lods: &world.meshes[i.mesh.0 as usize].lods,
            scale: i.max_scale(),
            radius: i.sphere.radius,
            transform: i.transform,
        })
        .collect()
}

/// Triangles of `sources` at error `e` (`None`: one can neither be left out nor has a LOD
/// within `e`).
fn triangles_at(sources: &[Source<'_>], e: f32) -> Option<u64> {
    sources
        .iter()
        .filter(|s| !s.left_out(e))
        .map(|s| s.within(e).map(|g| g.triangle_count() as u64))
        .sum()
}

/// The smallest error at which `sources` fit in `budget` triangles (each at its coarsest LOD
/// within it, left out when no larger), and their parts at it. The error is one of the LODs'
/// errors or the radii, found by bisection (the triangles only fall as the error grows).
fn select_within<'a>(sources: &[Source<'a>], budget: u64) -> (Vec<(&'a MeshLod, Mat4)>, f32) {
    let mut errors: Vec<f32> = sources
        .iter()
        .flat_map(|s| s.lods.iter().map(|g| g.error * s.scale).chain([s.radius]))
        .chain([0.0])
        .collect();
    errors.sort_by(f32::total_cmp);
    errors.dedup();
    let fits = |e: f32| triangles_at(sources, e).is_some_and(|t| t <= budget);
    // The largest error leaves everything out, so it always fits.
    let (mut lo, mut hi) = (0, errors.len() - 1);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if fits(errors[mid]) {
            hi = mid;
        } else {
            lo = mid + 1;
        }
    }
    let e = errors[lo];
    let parts = sources
        .iter()
        .filter(|s| !s.left_out(e))
        .filter_map(|s| s.within(e).map(|g| (g, s.transform)))
        .collect();
    (parts, e)
}

/// A node's geometry by [`ProxyMethod::Select`] (see the module docs).
fn select_node(world: &GeneratedWorld, levels: &[u32], cfg: &ProxyConfig, depth: u8) -> MeshLod {
    let sources = sources(world, levels);
    let budget = u64::from(cfg.triangles);
    let headroom = if depth <= cfg.select_depth {
        1
    } else {
        SIMPLIFY_HEADROOM
    };
    let (parts, e) = select_within(&sources, budget * headroom);
    simplify(weld(merge(&parts)), cfg.triangles, e)
}

/// `g` with coincident vertices shared (a merge keeps each part's own).
fn weld(g: MeshLod) -> MeshLod {
    let (count, remap) = meshopt::generate_vertex_remap(&g.positions, Some(&g.indices));
    MeshLod {
        positions: meshopt::remap_vertex_buffer(&g.positions, count, &remap),
        indices: meshopt::remap_index_buffer(Some(&g.indices), count, &remap),
        ..g
    }
}

fn parallel_map<T: Sync, R: Send>(
    items: &[T],
    threads: usize,
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let chunk = items.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|s| {
        let handles: Vec<_> = items
            .chunks(chunk)
            .map(|c| s.spawn(|| c.iter().map(&f).collect::<Vec<R>>()))
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().expect("proxy worker panicked"))
            .collect()
    })
}

/// Encodes the proxy file: the index, then one chunk per node.
pub fn encode_proxies(p: &Proxies) -> Vec<u8> {
    let chunks: Vec<Vec<u8>> = p
        .geometry
        .iter()
        .enumerate()
        .map(|(i, g)| format::encode_lod(WorldMeshId(i as u32), 0, g))
        .collect();
    let mut w = Writer::default();
    w.u32(PROXY_INDEX_VERSION);
    w.u32(p.tree.nodes.len() as u32);
    let mut offset = 0u64;
    for (n, c) in p.tree.nodes.iter().zip(&chunks) {
        w.u32(n.id.0);
        w.u8(n.depth);
        w.i32(n.cell[0]);
        w.i32(n.cell[1]);
        w.aabb(&n.bounds);
        w.f32(n.error);
        w.u32(n.parent.map_or(u32::MAX, |p| p.0));
        w.u32(n.triangles);
        w.u32(n.levels.len() as u32);
        for l in &n.levels {
            w.u32(l.0);
        }
        w.u32(n.landmarks.len() as u32);
        for l in &n.landmarks {
            w.u32(l.instance.0);
            w.u32(l.level.0);
            w.u32(l.mesh.0);
            w.f32s(&l.transform.to_cols_array());
        }
        w.u64(offset);
        w.u64(c.len() as u64);
        offset += c.len() as u64;
    }
    let mut out = frame(PROXY_INDEX_MAGIC, &w.0);
    let index_len = out.len() as u64;
    let mut file = index_len.to_le_bytes().to_vec();
    file.append(&mut out);
    for c in chunks {
        file.extend_from_slice(&c);
    }
    file
}

/// A proxy file read back: the tree, and per node its geometry or why it could not be read.
#[derive(Debug, Default)]
pub struct ProxyFile {
    /// Structure (from the checksummed index).
    pub tree: ProxyTree,
    /// Per node: its geometry, or the typed error of its chunk.
    pub geometry: Vec<std::result::Result<Arc<MeshLod>, Arc<StreamingError>>>,
}

/// Decodes a proxy file of a world with `levels` levels and `meshes` meshes (`path` names
/// errors). A corrupt index fails the whole file; a corrupt node chunk fails only that node.
pub fn decode_proxies(
    bytes: &[u8],
    path: &Path,
    levels: usize,
    meshes: usize,
) -> Result<ProxyFile> {
    let fail = |reason: FormatError| StreamingError::Format {
        path: path.to_owned(),
        reason,
    };
    let mut head = Reader::new(bytes);
    let index_len = head.u64().map_err(fail)? as usize;
    let index_bytes = head.bytes(index_len).map_err(fail)?;
    let chunks = &bytes[8 + index_len..];
    let mut r = Reader::new(unframe(PROXY_INDEX_MAGIC, index_bytes).map_err(fail)?);
    let version = r.u32().map_err(fail)?;
    if version != PROXY_INDEX_VERSION {
        return Err(fail(FormatError::Version {
            found: version,
            supported: PROXY_INDEX_VERSION,
        }));
    }
    let n = r.count(4).map_err(fail)?;
    let mut nodes = Vec::with_capacity(n);
    let mut spans = Vec::with_capacity(n);
    let mut leaf_of_level = vec![None; levels];
    let inconsistent = |s: String| fail(FormatError::Inconsistent(s));
    for i in 0..n {
        let id = r.u32().map_err(fail)?;
        if id as usize != i {
            return Err(inconsistent(format!("node {i} says it is node {id}")));
        }
        let depth = r.u8().map_err(fail)?;
        let cell = [r.i32().map_err(fail)?, r.i32().map_err(fail)?];
        let bounds = r.aabb().map_err(fail)?;
        let error = r.f32().map_err(fail)?;
        let parent = r.u32().map_err(fail)?;
        let triangles = r.u32().map_err(fail)?;
        let nl = r.count(4).map_err(fail)?;
        let mut lv = Vec::with_capacity(nl);
        for _ in 0..nl {
            let l = r.u32().map_err(fail)?;
            if l as usize >= levels {
                return Err(inconsistent(format!("node {i} covers unknown level {l}")));
            }
            lv.push(LevelId(l));
        }
        let nm = r.count(76).map_err(fail)?;
        let mut landmarks = Vec::with_capacity(nm);
        for _ in 0..nm {
            let (instance, level, mesh) = (
                r.u32().map_err(fail)?,
                r.u32().map_err(fail)?,
                r.u32().map_err(fail)?,
            );
            let mut cols = [0f32; 16];
            for c in &mut cols {
                *c = r.f32().map_err(fail)?;
            }
            if !lv.contains(&LevelId(level)) || mesh as usize >= meshes {
                return Err(inconsistent(format!(
                    "node {i}: landmark {instance} names level {level} or mesh {mesh}"
                )));
            }
            landmarks.push(ProxyLandmark {
                instance: crate::model::WorldInstanceId(instance),
                level: LevelId(level),
                mesh: WorldMeshId(mesh),
                transform: Mat4::from_cols_array(&cols),
            });
        }
        if depth != 1 && !landmarks.is_empty() {
            return Err(inconsistent(format!("node {i}: a parent lists landmarks")));
        }
        let (off, len) = (r.u64().map_err(fail)?, r.u64().map_err(fail)?);
        if parent != u32::MAX && (parent as usize >= n || parent as usize <= i) {
            return Err(inconsistent(format!("node {i} has parent {parent}")));
        }
        if depth == 1 {
            for l in &lv {
                leaf_of_level[l.0 as usize] = Some(ProxyId(id));
            }
        }
        spans.push((off, len));
        nodes.push(ProxyNode {
            id: ProxyId(id),
            depth,
            cell,
            bounds,
            error,
            parent: (parent != u32::MAX).then_some(ProxyId(parent)),
            children: Vec::new(),
            levels: lv,
            triangles,
            landmarks,
        });
    }
    for i in 0..nodes.len() {
        if let Some(p) = nodes[i].parent {
            nodes[p.0 as usize].children.push(ProxyId(i as u32));
        }
    }
    let geometry = spans
        .iter()
        .enumerate()
        .map(|(i, &(off, len))| {
            let bytes = usize::try_from(off)
                .ok()
                .zip(usize::try_from(len).ok())
                .and_then(|(o, l)| chunks.get(o..o.checked_add(l)?))
                .ok_or(FormatError::Truncated {
                    offset: off as usize,
                    needed: len as usize,
                    available: chunks.len().saturating_sub(off as usize),
                })
                .and_then(|b| format::decode_lod(b, WorldMeshId(i as u32), 0));
            bytes.map(Arc::new).map_err(|reason| Arc::new(fail(reason)))
        })
        .collect();
    Ok(ProxyFile {
        tree: ProxyTree {
            nodes,
            leaf_of_level,
        },
        geometry,
    })
}

/// Reads `dir`'s proxy file (of a world with `levels` levels and `meshes` meshes); `Ok(None)`
/// when the world has none (an older bake).
pub fn read_proxies(dir: &Path, levels: usize, meshes: usize) -> Result<Option<ProxyFile>> {
    let path = dir.join(PROXY_FILE);
    match std::fs::read(&path) {
        Ok(bytes) => decode_proxies(&bytes, &path, levels, meshes).map(Some),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(StreamingError::Io { path, source }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand_xoshiro::rand_core::{RngCore, SeedableRng};

    /// A LOD of `tris` triangles (over one shared vertex triple) with `error` metres.
    fn lod(tris: usize, error: f32) -> Arc<MeshLod> {
        Arc::new(MeshLod {
            positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            indices: (0..tris).flat_map(|_| [0, 1, 2]).collect(),
            error,
            skin: None,
        })
    }

    fn source(lods: &[Arc<MeshLod>], radius: f32) -> Source<'_> {
        Source {
            lods,
            scale: 1.0,
            radius,
            transform: Mat4::IDENTITY,
        }
    }

    #[test]
    fn select_keeps_the_large_and_leaves_out_the_small() {
        // A tall building whose coarse LOD is exact, and ten 3 m props of 774 triangles: what
        // a default-world leaf holds (streaming/src/proxy.rs module docs).
        let building = [lod(1296, 0.0), lod(44, 0.03)];
        let prop = [lod(774, 0.5)];
        let mut sources = vec![source(&building, 20.0)];
        sources.extend((0..10).map(|_| source(&prop, 3.0)));
        let (parts, e) = select_within(&sources, 768);
        assert_eq!(e, 3.0, "the props are left out, at their radius");
        assert_eq!(parts.len(), 1);
        assert_eq!(
            parts[0].0.triangle_count(),
            44,
            "the building keeps its exact box"
        );
        // With room for the props, they stay, at the smallest error that fits.
        let (parts, e) = select_within(&sources, 44 + 10 * 774);
        assert_eq!((parts.len(), e), (11, 0.5));
    }

    #[test]
    fn select_finds_the_smallest_error_that_fits() {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(7);
        let mut chains = Vec::new();
        for _ in 0..60 {
            let mut tris = 8 + (rng.next_u32() % 2000) as usize;
            let mut error = 0.0;
            let mut chain = Vec::new();
            for _ in 0..1 + rng.next_u32() % 6 {
                chain.push(lod(tris, error));
                tris = (tris / 2).max(2);
                error += (rng.next_u32() % 400) as f32 / 100.0;
            }
            chains.push((chain, (rng.next_u32() % 3000) as f32 / 100.0));
        }
        let sources: Vec<Source<'_>> = chains.iter().map(|(c, r)| source(c, *r)).collect();
        for budget in [0, 10, 100, 768, 3000, 20_000, 1_000_000] {
            let (parts, e) = select_within(&sources, budget);
            let tris: u64 = parts.iter().map(|(g, _)| g.triangle_count() as u64).sum();
            assert!(tris <= budget, "budget {budget}: {tris} triangles");
            assert_eq!(Some(tris), triangles_at(&sources, e));
            // No smaller error of any LOD or radius fits.
            let smaller = sources
                .iter()
                .flat_map(|s| s.lods.iter().map(|g| g.error).chain([s.radius]))
                .filter(|&x| x < e);
            for x in smaller {
                assert!(
                    triangles_at(&sources, x).is_none_or(|t| t > budget),
                    "budget {budget}: {x} < {e} fits too"
                );
            }
        }
    }

    #[test]
    fn weld_shares_coincident_vertices() {
        let a = lod(1, 0.0);
        let g = weld(merge(&[(&*a, Mat4::IDENTITY), (&*a, Mat4::IDENTITY)]));
        assert_eq!(g.positions.len(), 3);
        assert_eq!(g.indices, vec![0, 1, 2, 0, 1, 2]);
    }
}
