//! The far field: beyond r2, group proxies stand for their instances.
//!
//! Why one file over 600 lines: the group tree (`FarField`) and the manager's far-field steps
//! (prepare, select, the display cut) read and write the same private node fields; apart, those
//! fields would be crate-wide.
//!
//! Groups form a tree (leaves are what instances name; a parent's proxy covers all its leaves).
//! Each frame (`Managed` only):
//! 1. `far_prepare` (before the BLAS upkeep): distances of every node to the nearest camera;
//!    leaves turn "far" beyond r2 + `handover_margin` and "near" within r2 (hysteresis in
//!    between); the proxies the display cut will want — and, ahead of time, those of leaves
//!    approaching r2 and of children about to replace their parent — are requested, so they
//!    build through the ordinary scheduler within the frame budgets.
//! 2. `select_and_cull` (and the landmark set, for the detail it keeps) counts, per leaf, the
//!    unculled instances that have no BLAS to show yet, and those of no LOD with data or a
//!    BLAS whatever their angle (`unready`).
//! 3. `far_select`: a leaf wants its proxy when it is far, or when it was showing its proxy
//!    and its detail is not complete yet (the hand-over: the proxy leaves only once every
//!    unculled instance within r2 has its BLAS). The display cut walks the tree from the roots:
//!    a parent is shown when all its leaves are far, its proxy is built and its error projects
//!    under `max_pixel_error`; otherwise its children, falling back to the parent when a child
//!    has nothing built. Every leaf under a shown proxy is "covered": its instances are taken
//!    out of the TLAS, so no frame shows a group's proxy and its detail together. A near leaf
//!    whose proxy is not built shows its detail, so none shows neither.
//!
//! Proxies cost a walk of the cut per frame (the nodes near the cameras and the shown cut,
//! distances computed as visited; covered leaves are found through their ancestors' `shown`
//! epoch), not a pass over the tree or over the instances.

use glam::{Affine3A, Vec3};

use super::state::{EntryKey, EntryState};
use super::AsManager;
use crate::backend::AsBackend;
use crate::record::{TlasInstance, INSTANCE_FORCE_OPAQUE};
use crate::{GroupDesc, GroupId};

#[derive(Debug, Clone)]
pub(crate) struct GroupNode {
    desc: GroupDesc,
    /// The parent's slot (`None` for a root).
    parent: Option<u32>,
    children: Vec<u32>,
    /// (proxy mesh slot, error in metres).
    proxy: Option<(u32, f32)>,
    /// The proxy's BLAS entry as of its last request (`request_proxy`): the display cut reads
    /// the entry through it, not through the proxy mesh's state (one cold read less a node
    /// the cut visits). Checked before use: slotmap keys are versioned, and the entry must
    /// still be of this node's proxy mesh.
    proxy_entry: Option<EntryKey>,
    /// Distance from the nearest camera to the bounds, as of epoch `dist_epoch`.
    dist: f32,
    dist_epoch: u64,
    /// Leaf: detail (true) or proxy (false) side of the hand-over hysteresis. A near leaf is
    /// always in `FarField::near_leaves`.
    near: bool,
    /// Leaf: the epoch it was last put in `near_leaves`.
    listed: u64,
    /// The epoch (far-field frame) this node was last part of the display cut; every leaf
    /// under it was covered then.
    shown: u64,
    /// Leaves under this node (itself for a leaf).
    leaves: u32,
    /// Leaf: its near instances not ready this frame (unculled without a BLAS to show, or of
    /// no LOD with data or a BLAS).
    pub unready: u32,
    /// Proxy culled last frame (culling hysteresis).
    culled: bool,
    /// The bounds' centre and half diagonal (the proxy's culling sphere), and its TLAS record
    /// but for the BLAS address: fixed at registration, not derived again each frame it shows.
    centre: Vec3,
    radius: f32,
    template: TlasInstance,
}

/// The group tree and last frame's picks.
#[derive(Debug, Default)]
pub(crate) struct FarField {
    nodes: Vec<Option<GroupNode>>,
    generations: Vec<u32>,
    /// Proxy records of this frame.
    pub records: Vec<TlasInstance>,
    /// Root slots (rebuilt after the tree changes).
    roots: Vec<u32>,
    roots_dirty: bool,
    /// Leaves on the near side of the hand-over.
    near_leaves: Vec<u32>,
    /// Scratch of `far_prepare` kept between frames: last frame's `near_leaves` while this
    /// frame's are listed, the walk's stack, the nodes whose proxies are wanted.
    near_spare: Vec<u32>,
    stack: Vec<u32>,
    want: Vec<u32>,
    /// Scratch of `far_select`: the display cut's (group, entry, address).
    cut: Vec<(u32, EntryKey, u64)>,
    /// Leaves whose `unready` count is non-zero this frame.
    unready_leaves: Vec<u32>,
    /// Nodes of this frame's display cut.
    picks: Vec<u32>,
    /// Near leaves among them (sorted).
    covered_near: Vec<u32>,
    /// Leaves that changed hand-over side (or were registered or unregistered) since the
    /// landmarks last looked (`landmarks.rs` drains it).
    pub flipped: Vec<u32>,
    /// Per node slot: a live leaf on the near side (`is_near_leaf`, asked per instance by the
    /// residency pass and the landmarks: a byte here, not a node's cache lines).
    near_bits: Vec<bool>,
    /// Per node slot, dense for the per-record coverage test (`is_covered`): its `shown`
    /// epoch and its parent (`NO_PARENT` for a root or a vacant slot).
    shown_at: Vec<u64>,
    parent_of: Vec<u32>,
    /// Far-field frames so far (one per `far_prepare`); 0: none yet.
    epoch: u64,
    /// Live nodes.
    live: usize,
}

impl FarField {
    pub fn is_live(&self, id: GroupId) -> bool {
        self.generations.get(id.index as usize) == Some(&id.generation)
            && matches!(self.nodes.get(id.index as usize), Some(Some(_)))
    }

    /// Whether group slot `index` holds a registered group.
    pub fn slot_is_live(&self, index: u32) -> bool {
        matches!(self.nodes.get(index as usize), Some(Some(_)))
    }

    pub fn is_empty(&self) -> bool {
        self.live == 0
    }

    pub fn register(&mut self, id: GroupId, desc: GroupDesc) {
        self.flipped.push(id.index);
        let i = id.index as usize;
        if self.nodes.len() <= i {
            self.nodes.resize(i + 1, None);
            self.generations.resize(i + 1, u32::MAX);
        }
        let parent = desc.parent.filter(|p| self.is_live(*p)).map(|p| p.index);
        if let Some(parent) = parent {
            if let Some(Some(p)) = self.nodes.get_mut(parent as usize) {
                p.children.push(id.index);
            }
        }
        self.generations[i] = id.generation;
        self.roots_dirty = true;
        self.live += usize::from(self.nodes[i].is_none());
        let (lo, hi) = (Vec3::from(desc.bounds_min), Vec3::from(desc.bounds_max));
        let template = TlasInstance::new(
            &Affine3A::IDENTITY,
            desc.custom_index,
            desc.mask,
            0,
            INSTANCE_FORCE_OPAQUE,
            0,
        );
        self.nodes[i] = Some(GroupNode {
            desc,
            parent,
            children: Vec::new(),
            proxy: None,
            proxy_entry: None,
            dist: f32::INFINITY,
            dist_epoch: 0,
            near: false,
            listed: 0,
            shown: u64::MAX,
            leaves: 1,
            unready: 0,
            culled: false,
            centre: 0.5 * (lo + hi),
            radius: 0.5 * (hi - lo).length(),
            template,
        });
        self.refresh_near_bit(id.index);
        if let Some(p) = parent {
            self.refresh_near_bit(p);
        }
    }

    /// Sets `near_bits[i]`, `shown_at[i]` and `parent_of[i]` from the node.
    fn refresh_near_bit(&mut self, i: u32) {
        let n = self.nodes.get(i as usize).and_then(|n| n.as_ref());
        let (shown, parent) = n.map_or((u64::MAX, NO_PARENT), |n| {
            (n.shown, n.parent.unwrap_or(NO_PARENT))
        });
        if self.shown_at.len() <= i as usize {
            self.shown_at.resize(i as usize + 1, u64::MAX);
            self.parent_of.resize(i as usize + 1, NO_PARENT);
        }
        self.shown_at[i as usize] = shown;
        self.parent_of[i as usize] = parent;
        let near =
            matches!(self.nodes.get(i as usize), Some(Some(n)) if n.children.is_empty() && n.near);
        if self.near_bits.len() <= i as usize {
            self.near_bits.resize(i as usize + 1, false);
        }
        self.near_bits[i as usize] = near;
    }

    pub fn set_proxy(&mut self, id: GroupId, proxy: Option<(u32, f32)>) {
        if self.is_live(id) {
            if let Some(Some(n)) = self.nodes.get_mut(id.index as usize) {
                n.proxy = proxy;
            }
        }
    }

    pub fn unregister(&mut self, id: GroupId) {
        self.flipped.push(id.index);
        if !self.is_live(id) {
            return;
        }
        let Some(n) = self.nodes[id.index as usize].take() else {
            return;
        };
        self.roots_dirty = true;
        self.live -= 1;
        if let Some(Some(p)) = n.parent.and_then(|p| self.nodes.get_mut(p as usize)) {
            p.children.retain(|&c| c != id.index);
        }
        for &c in &n.children {
            if let Some(Some(child)) = self.nodes.get_mut(c as usize) {
                child.parent = None;
            }
            self.refresh_near_bit(c);
        }
        self.refresh_near_bit(id.index);
        if let Some(p) = n.parent {
            // A parent left without children is a leaf again.
            self.refresh_near_bit(p);
            self.flipped.push(p);
        }
    }

    /// Counts an unculled instance within r2 of leaf `group` that has no BLAS to show yet.
    pub fn add_unready(&mut self, group: u32) {
        if let Some(Some(n)) = self.nodes.get_mut(group as usize) {
            if n.children.is_empty() {
                if n.unready == 0 {
                    self.unready_leaves.push(group);
                }
                n.unready += 1;
            }
        }
    }

    fn node(&self, i: u32) -> &GroupNode {
        self.nodes[i as usize].as_ref().expect("live group")
    }

    /// The root slots and every node's leaf count (recomputed after the tree changed; it
    /// changes rarely). Taken out of the tree (give them back with `put_roots`): the walks
    /// borrow the tree while they go through them, and a copy a frame cost an allocation.
    fn take_roots(&mut self) -> Vec<u32> {
        if self.roots_dirty {
            self.roots = (0..self.nodes.len() as u32)
                .filter(|&i| matches!(&self.nodes[i as usize], Some(n) if n.parent.is_none()))
                .collect();
            // Leaf counts, children before parents (post-order from the roots).
            let mut order = Vec::with_capacity(self.live);
            let mut stack = self.roots.clone();
            while let Some(i) = stack.pop() {
                order.push(i);
                stack.extend_from_slice(&self.node(i).children);
            }
            for &i in order.iter().rev() {
                let n = self.node(i);
                let leaves = if n.children.is_empty() {
                    1
                } else {
                    n.children.iter().map(|&c| self.node(c).leaves).sum()
                };
                self.nodes[i as usize].as_mut().expect("live").leaves = leaves;
            }
            self.roots_dirty = false;
        }
        std::mem::take(&mut self.roots)
    }

    /// Gives back what `take_roots` took (unless the tree changed meanwhile).
    fn put_roots(&mut self, roots: Vec<u32>) {
        if !self.roots_dirty {
            self.roots = roots;
        }
    }

    /// Whether `leaf` or one of its ancestors was part of the display cut of `epoch`.
    fn shown_in(&self, leaf: u32, epoch: u64) -> bool {
        let mut i = leaf;
        while let Some(&shown) = self.shown_at.get(i as usize) {
            if shown == epoch {
                return true;
            }
            i = self.parent_of[i as usize];
        }
        false
    }

    /// Whether a leaf was covered by a shown proxy in the previous far-field frame.
    fn covered_last(&self, leaf: u32) -> bool {
        self.epoch >= 1 && self.shown_in(leaf, self.epoch - 1)
    }

    /// Whether `group` is a leaf on the near (detail) side of the hand-over (false for
    /// `NO_GROUP`, which names no node).
    pub fn is_near_leaf(&self, group: u32) -> bool {
        self.near_bits.get(group as usize).copied().unwrap_or(false)
    }

    /// XZ rectangles of the near leaves that reach beyond `r2` of every camera (their
    /// instances there are near field too), into `out`.
    pub fn near_leaf_boxes(&self, cameras: &[Vec3], r2: f32, out: &mut Vec<[f32; 4]>) {
        out.clear();
        for n in self
            .near_leaves
            .iter()
            .filter_map(|&i| self.nodes[i as usize].as_ref())
        {
            if !n.children.is_empty() || !n.near {
                continue;
            }
            if reaches_beyond(n, cameras, r2) {
                let (lo, hi) = (n.desc.bounds_min, n.desc.bounds_max);
                out.push([lo[0], lo[2], hi[0], hi[2]]);
            }
        }
    }

    /// Near leaves covered by their own proxy this frame (handing over).
    #[cfg(test)]
    pub fn covered_near_count(&self) -> usize {
        self.covered_near.len()
    }

    /// The near leaves that reach beyond `r2` of every camera (`near_leaf_boxes`'s), into `out`.
    pub fn near_leaves_beyond(&self, cameras: &[Vec3], r2: f32, out: &mut Vec<u32>) {
        out.clear();
        for &i in &self.near_leaves {
            let Some(n) = self.nodes[i as usize].as_ref() else {
                continue;
            };
            if n.children.is_empty() && n.near && reaches_beyond(n, cameras, r2) {
                out.push(i);
            }
        }
    }

    /// Whether a leaf is covered by a proxy this frame (after `far_select`).
    pub fn is_covered(&self, group: u32) -> bool {
        self.epoch >= 1 && self.shown_in(group, self.epoch)
    }
}

/// Whether a leaf's bounds reach beyond `r2` of every camera: its farthest corner (XZ) from
/// each camera is beyond (inside r2 means nothing of it is beyond).
fn reaches_beyond(n: &GroupNode, cameras: &[Vec3], r2: f32) -> bool {
    let (lo, hi) = (n.desc.bounds_min, n.desc.bounds_max);
    cameras.iter().all(|c| {
        let dx = (c.x - lo[0]).abs().max((c.x - hi[0]).abs());
        let dz = (c.z - lo[2]).abs().max((c.z - hi[2]).abs());
        dx * dx + dz * dz > r2 * r2
    })
}

/// `FarField::parent_of` of a root.
const NO_PARENT: u32 = u32::MAX;

/// Pixels an error of `error` metres projects to at `dist` (the LOD config's screen).
fn projected_px(c: &crate::Config, error: f32, dist: f32) -> f32 {
    let l = &c.lod;
    let pixel_angle = l.vertical_fov / l.screen_height_px;
    error / (dist.max(1e-3) * pixel_angle)
}

/// Distance from the nearest camera to a node's bounds.
fn node_distance(n: &GroupNode, cams: &[Vec3]) -> f32 {
    cams.iter()
        .map(|&c| aabb_distance(n.desc.bounds_min, n.desc.bounds_max, c))
        .fold(f32::INFINITY, f32::min)
}

fn aabb_distance(lo: [f32; 3], hi: [f32; 3], p: Vec3) -> f32 {
    let d = (Vec3::from(lo) - p).max(p - Vec3::from(hi)).max(Vec3::ZERO);
    d.length()
}

impl<B: AsBackend> AsManager<B> {
    fn far_on(&self) -> bool {
        self.config.far_field.enabled && !self.far.is_empty()
    }

    /// Pixels a proxy error of `error` metres spans at `dist` metres.
    fn projected_px(&self, error: f32, dist: f32) -> f32 {
        projected_px(&self.config, error, dist)
    }

    /// Step 1 (see the module docs): distances, hand-over states, proxy requests.
    pub(crate) fn far_prepare(&mut self) {
        if !self.far_on() {
            return;
        }
        let r2 = self.config.residency.r2;
        let f = self.config.far_field.clone();
        let cams = std::mem::take(&mut self.cam_pos);
        let far = &mut self.far;
        far.epoch += 1;
        let e = far.epoch;
        for i in std::mem::take(&mut far.unready_leaves) {
            if let Some(Some(n)) = far.nodes.get_mut(i as usize) {
                n.unready = 0;
            }
        }
        // Distances are computed for the nodes a walk visits, not for the whole tree; a leaf's
        // hand-over side changes only near the cameras (visited) or for leaves that were near
        // (listed), so both are updated and the rest keep `near == false`.
        // Returns whether the leaf changed sides (the landmarks of its instances are looked at
        // again).
        let visit = |n: &mut GroupNode| {
            if n.dist_epoch != e {
                n.dist = node_distance(n, &cams);
                n.dist_epoch = e;
            }
            let was = n.near;
            if n.children.is_empty() {
                if n.dist <= r2 {
                    n.near = true;
                } else if n.dist > r2 + f.handover_margin {
                    n.near = false;
                }
            }
            n.near != was
        };
        // Last frame's list is walked while this frame's fills the spare one (no allocation
        // a frame).
        let mut listed = std::mem::take(&mut far.near_leaves);
        far.near_leaves = std::mem::take(&mut far.near_spare);
        far.near_leaves.clear();
        for &i in &listed {
            if let Some(Some(n)) = far.nodes.get_mut(i as usize) {
                if visit(n) {
                    far.flipped.push(i);
                    far.near_bits[i as usize] = n.children.is_empty() && n.near;
                }
                if n.near && n.listed != e {
                    n.listed = e;
                    far.near_leaves.push(i);
                }
            }
        }
        listed.clear();
        far.near_spare = listed;
        let mut want = std::mem::take(&mut far.want);
        want.clear();
        let roots = far.take_roots();
        let mut stack = std::mem::take(&mut far.stack);
        stack.clear();
        stack.extend_from_slice(&roots);
        far.put_roots(roots);
        while let Some(i) = stack.pop() {
            let n = far.nodes[i as usize].as_mut().expect("live group");
            if visit(n) {
                far.flipped.push(i);
                far.near_bits[i as usize] = n.children.is_empty() && n.near;
            }
            if n.children.is_empty() && n.near && n.listed != e {
                n.listed = e;
                far.near_leaves.push(i);
            }
            let n = far.node(i);
            if n.dist > f.far_radius {
                continue;
            }
            if n.children.is_empty() {
                // Far or soon far, or still handing over.
                let soon = n.dist > r2 - f.handover_margin;
                if soon || !n.near || far.covered_last(i) {
                    want.push(i);
                }
                continue;
            }
            let px = n.proxy.map_or(f32::INFINITY, |(_, err)| {
                projected_px(&self.config, err, n.dist)
            });
            if n.dist > r2 + f.lookahead && px <= f.max_pixel_error {
                want.push(i);
                // Its children will replace it when the camera comes closer: build them ahead.
                if px > f.max_pixel_error * f.refine_ahead {
                    want.extend(n.children.iter().copied());
                }
            } else {
                stack.extend(n.children.iter().copied());
            }
        }
        far.stack = stack;
        self.cam_pos = cams;
        let frame = self.frame;
        for &i in &want {
            let n = self.far.node(i);
            let (Some((mesh, _)), dist) = (n.proxy, self.far_dist(i)) else {
                continue;
            };
            // Coverage before refinement: a node that covers k leaves is built as if it stood
            // sqrt(k) times nearer, so a 16x16 block 2 km away (256 leaves: 125 m) goes before
            // a leaf at 300 m. When the budget admits a proxy or two a frame (a TLAS that takes
            // most of it), the far field is covered coarsely first instead of finely near the
            // cameras and not at all farther out.
            let leaves = n.leaves.max(1) as f32;
            let cached = self.proxy_key(i);
            let key = self.request_proxy(mesh, cached, dist / leaves.sqrt(), frame);
            if let Some(Some(n)) = self.far.nodes.get_mut(i as usize) {
                n.proxy_entry = key;
            }
        }
        self.far.want = want;
    }

    /// A node's distance to the nearest camera this frame (cached by the walk, else computed).
    fn far_dist(&self, i: u32) -> f32 {
        let n = self.far.node(i);
        if n.dist_epoch == self.far.epoch {
            n.dist
        } else {
            node_distance(n, &self.cam_pos)
        }
    }

    /// Requests a proxy's BLAS this frame; `dist` orders its build and eviction among the
    /// proxies (`far_prepare` passes a coverage-weighted distance).
    /// `known` is the node's entry when it has one (`proxy_key`): then the mesh's state is
    /// not read. Returns the proxy's entry (`None`: its mesh is gone).
    fn request_proxy(
        &mut self,
        mesh: u32,
        known: Option<EntryKey>,
        dist: f32,
        frame: u64,
    ) -> Option<EntryKey> {
        let key = match known {
            Some(key) => key,
            None => self.tables.new_lod_entry(mesh, 0, frame)?,
        };
        let e = &mut self.tables.entries[key];
        e.last_request = frame;
        e.last_keep = frame;
        if e.dist_frame != frame {
            e.dist_frame = frame;
            e.min_dist = dist;
        } else {
            e.min_dist = e.min_dist.min(dist);
        }
        if e.state == EntryState::Idle {
            e.state = EntryState::Queued;
            e.queued_since = frame;
            e.streak_start = frame;
        }
        Some(key)
    }

    /// The proxy's entry of a node: the one its last request found when still live and of
    /// its proxy mesh, else through the mesh's state.
    fn proxy_key(&self, group: u32) -> Option<EntryKey> {
        let n = self.far.node(group);
        let (mesh, _) = n.proxy?;
        let cached = n
            .proxy_entry
            .filter(|&k| self.tables.entries.get(k).is_some_and(|e| e.mesh == mesh));
        let through_mesh = || self.tables.lod_entry(mesh, 0);
        debug_assert!(
            cached.is_none() || cached == through_mesh(),
            "a node's cached proxy entry is its mesh's"
        );
        cached.or_else(through_mesh)
    }

    fn proxy_built(&self, group: u32) -> Option<(EntryKey, u64)> {
        let key = self.proxy_key(group)?;
        let e = &self.tables.entries[key];
        if e.state != EntryState::Built {
            return None;
        }
        e.handle?;
        Some((key, e.record_address(&self.backend)))
    }

    /// Picks of the display cut under `i`: (group, entry, address). `None` when some far
    /// leaf under `i` would show nothing.
    fn display_cut(&self, i: u32, picks: &mut Vec<(u32, EntryKey, u64)>) -> bool {
        let f = &self.config.far_field;
        let r2 = self.config.residency.r2;
        let n = self.far.node(i);
        let dist = self.far_dist(i);
        if dist > f.far_radius {
            return true;
        }
        if n.children.is_empty() {
            let wants = !n.near || (self.far.covered_last(i) && n.unready > 0);
            if !wants {
                return true;
            }
            return match self.proxy_built(i) {
                Some((key, addr)) => {
                    picks.push((i, key, addr));
                    true
                }
                // A near leaf shows its detail instead; a far one has nothing.
                None => n.near,
            };
        }
        let all_far = dist > r2 + f.handover_margin;
        let parent = if all_far { self.proxy_built(i) } else { None };
        let px = n
            .proxy
            .map_or(f32::INFINITY, |(_, e)| self.projected_px(e, dist));
        if let (Some((key, addr)), true) = (parent, px <= f.max_pixel_error) {
            picks.push((i, key, addr));
            return true;
        }
        let mark = picks.len();
        let mut complete = true;
        for &c in &n.children {
            complete &= self.display_cut(c, picks);
        }
        if !complete {
            if let Some((key, addr)) = parent {
                // A child has nothing built yet: the coarser parent covers them all.
                picks.truncate(mark);
                picks.push((i, key, addr));
                return true;
            }
        }
        complete
    }

    /// Step 3 (see the module docs): the display cut, the detail it covers taken out of the
    /// TLAS list, the proxy records.
    pub(crate) fn far_select(&mut self) {
        self.far.records.clear();
        self.far.picks.clear();
        if !self.far_on() {
            self.tlas_groups.clear();
            return;
        }
        let mut picks = std::mem::take(&mut self.far.cut);
        picks.clear();
        let roots = self.far.take_roots();
        for &r in &roots {
            self.display_cut(r, &mut picks);
        }
        self.far.put_roots(roots);
        let frame = self.frame;
        let mut proxy_bytes = 0;
        for &(g, key, addr) in &picks {
            let n = self.far.node(g);
            let (centre, radius, was_culled) = (n.centre, n.radius, n.culled);
            let centre_dist = self
                .cam_pos
                .iter()
                .map(|c| c.distance(centre))
                .fold(f32::INFINITY, f32::min);
            // Culling decides what is traced, not what is covered: a culled proxy's detail
            // stays out too (it is beyond r2 or handing over).
            self.far.picks.push(g);
            let culled = self.culler.cull_small(radius, centre_dist, was_culled);
            let n = self.far.nodes[g as usize].as_mut().expect("live");
            n.culled = culled;
            let template = n.template;
            let e = &mut self.tables.entries[key];
            e.last_keep = frame;
            if culled {
                continue;
            }
            e.last_in_tlas = Some(frame);
            proxy_bytes += e.bytes;
            self.far.records.push(TlasInstance {
                blas_address: addr,
                ..template
            });
        }
        self.far.cut = picks;
        // Every leaf under a pick is covered this frame.
        let e = self.far.epoch;
        let mut covered_leaves = 0;
        let mut covered_near = std::mem::take(&mut self.far.covered_near);
        covered_near.clear();
        for &g in &self.far.picks {
            let n = self.far.nodes[g as usize].as_mut().expect("live");
            n.shown = e;
            self.far.shown_at[g as usize] = e;
            covered_leaves += n.leaves;
            // A near leaf is covered only by its own proxy (a parent is picked only when all
            // its leaves are far): handing over.
            if self.far.near_bits.get(g as usize).copied().unwrap_or(false) {
                covered_near.push(g);
            }
        }
        covered_near.sort_unstable();
        // The detail the landmark set keeps leaves the TLAS with them.
        let (grid, templates) = (&self.grid, &self.templates);
        self.landmarks
            .hide_covered(&covered_near, &mut self.records, |slot| {
                grid.loc(slot).map(|_| templates[slot as usize])
            });
        self.far.covered_near = covered_near;
        // Take the covered leaves' detail out of the TLAS list. Only a near leaf handing
        // over (covered by its own proxy) or an entry of a far leaf (covered through an
        // ancestor) can be covered; most frames have neither, and the list stays as it is.
        let coverable = !self.far.covered_near.is_empty() || self.tlas_far_leaf_entries > 0;
        debug_assert!(
            coverable
                || self
                    .tlas_groups
                    .iter()
                    .flatten()
                    .all(|&g| !self.far.is_covered(g)),
            "an entry of a covered leaf was left in the TLAS list"
        );
        if !self.far.picks.is_empty() && coverable {
            // In place; neighbours in the list mostly share their leaf, so its answer is kept.
            // A near leaf is covered only by its own proxy (a parent is picked only when all
            // its leaves are far): one look at its own epoch, not a walk up the tree.
            let (groups, far) = (&self.tlas_groups, &self.far);
            let (mut i, mut last) = (0, (NO_PARENT, false));
            self.tlas_list.retain(|_| {
                let g = groups[i];
                i += 1;
                g.is_none_or(|g| {
                    if last.0 != g {
                        let near = far.near_bits.get(g as usize).copied().unwrap_or(false);
                        let covered = if near {
                            far.shown_at.get(g as usize) == Some(&e)
                        } else {
                            far.is_covered(g)
                        };
                        last = (g, covered);
                    }
                    !last.1
                })
            });
        }
        self.tlas_groups.clear();
        self.stats.proxy_instances = self.far.records.len() as u32;
        self.stats.proxy_blas_bytes = proxy_bytes;
        self.stats.far_groups_covered = covered_leaves;
    }
}
