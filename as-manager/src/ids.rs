//! Stable ids: index + generation, recycled through a free list.

/// A registered mesh (its LOD chain). Cheap to copy; stale ids are detected by generation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MeshId {
    pub(crate) index: u32,
    pub(crate) generation: u32,
}

/// A placed instance of a mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct InstanceId {
    pub(crate) index: u32,
    pub(crate) generation: u32,
}

/// A group of instances (e.g. a block of streaming levels) that a far-field proxy can stand
/// for; groups form a tree (see `AsManager::register_group`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct GroupId {
    pub(crate) index: u32,
    pub(crate) generation: u32,
}

impl GroupId {
    /// The slot index (stable while the group lives).
    pub fn index(self) -> u32 {
        self.index
    }
}

impl MeshId {
    /// The slot index (stable while the mesh lives).
    pub fn index(self) -> u32 {
        self.index
    }
}

impl InstanceId {
    /// The slot index (stable while the instance lives).
    pub fn index(self) -> u32 {
        self.index
    }
}

/// Allocates `(index, generation)` pairs; a freed index comes back with generation + 1.
///
/// Hand-written, not a `slotmap::SlotMap` like the manager's BLAS entries
/// (`manager::state::EntryKey`), because the manager needs each id's dense index and slotmap
/// does not give it out (`KeyData::as_ffi`'s layout is documented as unspecified):
/// - the spatial grid (`spatial::GridIndex`) maps an instance's `u32` slot to its cell through
///   a `Vec`, and each cell entry names its instance by that slot (4 bytes, in the records the
///   residency and cull passes stream through);
/// - `InstanceHot` (with its grid entry, one cache line) names its mesh and far-field group by
///   `u32` slot, and the manager's mesh and instance tables are `Vec`s indexed by it;
/// - [`MeshId::index`], [`InstanceId::index`] and [`GroupId::index`] are public, and callers
///   key their own tables with them.
///
/// It also keeps a state slotmap has no word for: killed (unknown to later calls, which
/// fail) but not yet recycled (the manager still applies the queued removal).
#[derive(Debug, Default)]
pub(crate) struct IdAllocator {
    generations: Vec<u32>,
    live: Vec<bool>,
    free: Vec<u32>,
}

impl IdAllocator {
    pub fn alloc(&mut self) -> (u32, u32) {
        if let Some(i) = self.free.pop() {
            self.live[i as usize] = true;
            (i, self.generations[i as usize])
        } else {
            let i = self.generations.len() as u32;
            self.generations.push(0);
            self.live.push(true);
            (i, 0)
        }
    }

    pub fn is_live(&self, index: u32, generation: u32) -> bool {
        let i = index as usize;
        i < self.live.len() && self.live[i] && self.generations[i] == generation
    }

    /// Marks the id dead now (later calls see it as unknown); the index is recycled by
    /// [`IdAllocator::recycle`] once the manager has applied the removal.
    pub fn kill(&mut self, index: u32) {
        self.live[index as usize] = false;
    }

    pub fn recycle(&mut self, index: u32) {
        let i = index as usize;
        self.generations[i] = self.generations[i].wrapping_add(1);
        self.free.push(index);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recycled_ids_get_new_generation() {
        let mut a = IdAllocator::default();
        let (i, g) = a.alloc();
        assert!(a.is_live(i, g));
        a.kill(i);
        assert!(!a.is_live(i, g));
        a.recycle(i);
        let (j, h) = a.alloc();
        assert_eq!(i, j);
        assert_ne!(g, h);
        assert!(!a.is_live(i, g));
    }
}
