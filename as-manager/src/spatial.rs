//! `GridIndex`: a uniform hash grid over the ground plane (x, z) of instance bounding spheres.
//!
//! Residency and culling only look at cells within a radius of the cameras, so their cost
//! follows what is near the cameras, not the world's size. Spheres larger than a cell go to a
//! short list visited every frame. (The benchmark compares it with an rstar R*-tree query.)

use rustc_hash::FxHashMap;

use glam::Vec3;

/// One indexed sphere; `slot` is the caller's instance slot; `data` is the caller's payload,
/// stored in the cell so that a query streams through memory instead of chasing slots.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridEntry<T = ()> {
    /// World-space centre.
    pub center: [f32; 3],
    /// World-space radius.
    pub radius: f32,
    /// Caller's slot.
    pub slot: u32,
    /// Caller's payload.
    pub data: T,
}

/// Where an entry sits now (valid until the next insert/remove).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridLoc {
    cell: u32,
    index: u32,
}

/// `GridLoc::cell` of an entry in the large list (not in a cell).
const LARGE: u32 = u32::MAX;

/// The grid. See the module docs.
#[derive(Debug)]
pub struct GridIndex<T = ()> {
    cell_size: f32,
    inv_cell: f32,
    cells: FxHashMap<u64, u32>,
    cell_coords: Vec<(i32, i32)>,
    cell_entries: Vec<Vec<GridEntry<T>>>,
    large: Vec<GridEntry<T>>,
    /// Per caller's slot (a dense index: the grid's callers number their entries densely,
    /// see `ids::IdAllocator`): where its entry is, `None` when absent.
    locs: Vec<Option<GridLoc>>,
    scratch: Vec<u32>,
    len: usize,
    /// Largest radius among the in-cell entries (<= cell size): the query's slack.
    max_small_radius: f32,
}

fn key(x: i32, z: i32) -> u64 {
    ((x as u32 as u64) << 32) | z as u32 as u64
}

impl<T: Copy> GridIndex<T> {
    /// An empty grid with square cells of `cell_size` world units.
    pub fn new(cell_size: f32) -> Self {
        assert!(cell_size > 0.0 && cell_size.is_finite());
        Self {
            cell_size,
            inv_cell: 1.0 / cell_size,
            cells: FxHashMap::default(),
            cell_coords: Vec::new(),
            cell_entries: Vec::new(),
            large: Vec::new(),
            locs: Vec::new(),
            scratch: Vec::new(),
            len: 0,
            max_small_radius: 0.0,
        }
    }

    /// Entries indexed.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether nothing is indexed.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Whether the cell rectangle `x0..=x1` by `z0..=z1` has more cells than the grid holds.
    fn rect_exceeds_cells(&self, x0: i32, x1: i32, z0: i32, z1: i32) -> bool {
        let w = (i64::from(x1) - i64::from(x0) + 1).max(0) as u64;
        let h = (i64::from(z1) - i64::from(z0) + 1).max(0) as u64;
        w.saturating_mul(h) > self.cell_coords.len() as u64
    }

    /// The grid's cells within the rectangle that `keep` accepts, in cell order.
    fn cells_in<'a>(
        &'a self,
        x0: i32,
        x1: i32,
        z0: i32,
        z1: i32,
        keep: impl Fn(i32, i32) -> bool + 'a,
    ) -> impl Iterator<Item = u32> + 'a {
        self.cell_coords
            .iter()
            .enumerate()
            .filter(move |&(_, &(x, z))| {
                (x0..=x1).contains(&x) && (z0..=z1).contains(&z) && keep(x, z)
            })
            .map(|(c, _)| c as u32)
    }

    fn coord(&self, v: f32) -> i32 {
        (v * self.inv_cell)
            .floor()
            .clamp(i32::MIN as f32 + 1.0, i32::MAX as f32 - 1.0) as i32
    }

    /// Inserts or moves `slot` with its payload.
    pub fn insert(&mut self, slot: u32, center: Vec3, radius: f32, data: T) {
        self.remove(slot);
        let e = GridEntry {
            center: center.to_array(),
            radius,
            slot,
            data,
        };
        if self.locs.len() <= slot as usize {
            self.locs.resize(slot as usize + 1, None);
        }
        if radius > self.cell_size {
            self.locs[slot as usize] = Some(GridLoc {
                cell: LARGE,
                index: self.large.len() as u32,
            });
            self.large.push(e);
        } else {
            self.max_small_radius = self.max_small_radius.max(radius);
            let (x, z) = (self.coord(center.x), self.coord(center.z));
            let n = self.cell_entries.len() as u32;
            let c = *self.cells.entry(key(x, z)).or_insert(n);
            if c == n {
                self.cell_entries.push(Vec::new());
                self.cell_coords.push((x, z));
            }
            let v = &mut self.cell_entries[c as usize];
            self.locs[slot as usize] = Some(GridLoc {
                cell: c,
                index: v.len() as u32,
            });
            v.push(e);
        }
        self.len += 1;
    }

    /// Where `slot` is now.
    pub fn loc(&self, slot: u32) -> Option<GridLoc> {
        self.locs.get(slot as usize).copied().flatten()
    }

    /// The entry at `loc`.
    pub fn at(&self, loc: GridLoc) -> &GridEntry<T> {
        if loc.cell == LARGE {
            &self.large[loc.index as usize]
        } else {
            &self.cell_entries[loc.cell as usize][loc.index as usize]
        }
    }

    /// The entry at `loc`, mutably.
    pub fn at_mut(&mut self, loc: GridLoc) -> &mut GridEntry<T> {
        if loc.cell == LARGE {
            &mut self.large[loc.index as usize]
        } else {
            &mut self.cell_entries[loc.cell as usize][loc.index as usize]
        }
    }

    /// The entry of `slot`.
    pub fn get(&self, slot: u32) -> Option<&GridEntry<T>> {
        self.loc(slot).map(|l| self.at(l))
    }

    /// The entry of `slot`, mutably.
    pub fn get_mut(&mut self, slot: u32) -> Option<&mut GridEntry<T>> {
        self.loc(slot).map(|l| self.at_mut(l))
    }

    /// Removes `slot` if present.
    pub fn remove(&mut self, slot: u32) {
        let Some(GridLoc { cell: c, index: i }) = self.loc(slot) else {
            return;
        };
        let v = if c == LARGE {
            &mut self.large
        } else {
            &mut self.cell_entries[c as usize]
        };
        v.swap_remove(i as usize);
        if let Some(moved) = v.get(i as usize) {
            self.locs[moved.slot as usize] = Some(GridLoc { cell: c, index: i });
        }
        self.locs[slot as usize] = None;
        self.len -= 1;
    }

    /// Calls `visit` for every entry whose centre lies in a cell that a sphere of `range` (plus
    /// the largest in-cell radius as slack) around any of `cameras` touches, and every large
    /// entry. Cells are deduplicated across cameras; each entry is visited once. The
    /// caller does the exact distance test.
    pub fn query(
        &mut self,
        cameras: &[Vec3],
        range: f32,
        visit: impl FnMut(GridLoc, &mut GridEntry<T>),
    ) {
        self.query_with_boxes(cameras, range, &[], visit);
    }

    /// Like [`GridIndex::query`], and also every entry of the cells overlapping one of
    /// `boxes` (XZ rectangles `[min_x, min_z, max_x, max_z]`, widened by the largest small
    /// radius); each entry is visited once.
    pub fn query_with_boxes(
        &mut self,
        cameras: &[Vec3],
        range: f32,
        boxes: &[[f32; 4]],
        mut visit: impl FnMut(GridLoc, &mut GridEntry<T>),
    ) {
        let reach = range + self.max_small_radius;
        let mut cells = std::mem::take(&mut self.scratch);
        cells.clear();
        let pad = self.max_small_radius;
        // A rectangle with more cells than the grid holds (an absurd range, box or camera
        // jump) walks the grid's cells instead of the rectangle's, in cell order.
        for b in boxes {
            let (x0, x1) = (self.coord(b[0] - pad), self.coord(b[2] + pad));
            let (z0, z1) = (self.coord(b[1] - pad), self.coord(b[3] + pad));
            if self.rect_exceeds_cells(x0, x1, z0, z1) {
                cells.extend(self.cells_in(x0, x1, z0, z1, |_, _| true));
                continue;
            }
            for x in x0..=x1 {
                for z in z0..=z1 {
                    if let Some(&c) = self.cells.get(&key(x, z)) {
                        cells.push(c);
                    }
                }
            }
        }
        for cam in cameras {
            let (x0, x1) = (self.coord(cam.x - reach), self.coord(cam.x + reach));
            let (z0, z1) = (self.coord(cam.z - reach), self.coord(cam.z + reach));
            let r2 = reach * reach;
            let size = self.cell_size;
            // The squared distance from the camera to cell (x, z) in XZ.
            let gap = |x: i32, z: i32| {
                let (lx, lz) = (x as f32 * size, z as f32 * size);
                let dx = (lx - cam.x).max(cam.x - (lx + size)).max(0.0);
                let dz = (lz - cam.z).max(cam.z - (lz + size)).max(0.0);
                dx * dx + dz * dz
            };
            if self.rect_exceeds_cells(x0, x1, z0, z1) {
                cells.extend(self.cells_in(x0, x1, z0, z1, |x, z| gap(x, z) <= r2));
                continue;
            }
            for x in x0..=x1 {
                let lo = x as f32 * self.cell_size;
                let dx = (lo - cam.x).max(cam.x - (lo + self.cell_size)).max(0.0);
                if dx * dx > r2 {
                    continue;
                }
                for z in z0..=z1 {
                    if gap(x, z) > r2 {
                        continue;
                    }
                    if let Some(&c) = self.cells.get(&key(x, z)) {
                        cells.push(c);
                    }
                }
            }
        }
        if cameras.len() > 1 || !boxes.is_empty() {
            cells.sort_unstable();
            cells.dedup();
        }
        for &c in &cells {
            for (i, e) in self.cell_entries[c as usize].iter_mut().enumerate() {
                visit(
                    GridLoc {
                        cell: c,
                        index: i as u32,
                    },
                    e,
                );
            }
        }
        for (i, e) in self.large.iter_mut().enumerate() {
            visit(
                GridLoc {
                    cell: LARGE,
                    index: i as u32,
                },
                e,
            );
        }
        self.scratch = cells;
    }

    /// Cell coordinates of `(x, z)` (for tests).
    pub fn cell_of(&self, p: Vec3) -> (i32, i32) {
        (self.coord(p.x), self.coord(p.z))
    }

    /// Number of non-empty-ever cells.
    pub fn cell_count(&self) -> usize {
        self.cell_coords.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_finds_everything_within_range() {
        let mut g = GridIndex::<()>::new(10.0);
        let mut pts = Vec::new();
        for i in 0..2000u32 {
            let x = ((i * 7919) % 1000) as f32 - 500.0;
            let z = ((i * 104_729) % 997) as f32 - 498.0;
            let r = if i % 100 == 1 { 25.0 } else { 1.0 };
            pts.push((Vec3::new(x, 0.0, z), r));
            g.insert(i, Vec3::new(x, 0.0, z), r, ());
        }
        // move and remove some
        for i in (0..2000u32).step_by(3) {
            pts[i as usize].0.x += 13.0;
            g.insert(i, pts[i as usize].0, pts[i as usize].1, ());
        }
        for i in (0..2000u32).step_by(5) {
            g.remove(i);
        }
        let cams = [Vec3::new(30.0, 0.0, -40.0), Vec3::new(60.0, 5.0, -40.0)];
        let mut seen = Vec::new();
        g.query(&cams, 50.0, |_, e| seen.push(e.slot));
        let n = seen.len();
        seen.sort_unstable();
        seen.dedup();
        assert_eq!(n, seen.len(), "visited once");
        for (i, (p, r)) in pts.iter().enumerate() {
            let near = cams.iter().any(|c| (c.distance(*p) - r).max(0.0) <= 50.0);
            if near && i % 5 != 0 {
                assert!(seen.binary_search(&(i as u32)).is_ok(), "missed {i}");
            }
            if i % 5 == 0 {
                assert!(seen.binary_search(&(i as u32)).is_err());
            }
        }
    }
}
