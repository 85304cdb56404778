//! The set's bookkeeping: the (mesh, LOD) pairs the landmarks target, select and show, and
//! the landmark records at the front of the manager's records.

use super::*;
use crate::manager::state::Logged;
use crate::mesh::MAX_LODS;

impl Landmarks {
    #[track_caller]
    pub(super) fn pair(&mut self, i: u32) -> &mut PairUse {
        self.pairs[i as usize].as_mut().expect("a live pair")
    }

    /// The pairs a step looks at for a mesh log (`MeshLog`): every live pair, or those of the
    /// logged meshes; in index order (the order a scan of every pair visits them), into `out`.
    pub(super) fn logged_pairs(&self, logged: Logged, meshes: &[u32], out: &mut Vec<u32>) {
        out.clear();
        match logged {
            Logged::All => out
                .extend((0..self.pairs.len() as u32).filter(|&i| self.pairs[i as usize].is_some())),
            Logged::Meshes => {
                for &m in meshes {
                    out.extend(
                        (0..MAX_LODS as u8)
                            .filter_map(|l| self.pair_index.get(&pair_key(m, l)).copied()),
                    );
                }
                out.sort_unstable();
            }
        }
    }

    /// The pair of (mesh, LOD), created when missing.
    pub(super) fn pair_of(&mut self, mesh: u32, lod: u8) -> u32 {
        if let Some(&i) = self.pair_index.get(&pair_key(mesh, lod)) {
            return i;
        }
        let p = Some(PairUse::new(mesh, lod));
        let i = slab_insert(&mut self.pairs, &mut self.free_pairs, p);
        self.pair_index.insert(pair_key(mesh, lod), i);
        i
    }

    /// Frees pair `i` if nothing uses it any more.
    pub(super) fn release_pair(&mut self, i: u32) {
        let p = self.pairs[i as usize].as_ref().expect("a live pair");
        if p.is_unused() {
            self.pair_index.remove(&pair_key(p.mesh, p.lod));
            self.pairs[i as usize] = None;
            self.free_pairs.push(i);
        }
    }

    /// Swap-removes `slot` from a pair's member list at `pos`; returns the slot moved there.
    pub(super) fn list_remove(list: &mut Vec<u32>, pos: u32) -> Option<u32> {
        list.swap_remove(pos as usize);
        list.get(pos as usize).copied()
    }

    pub(super) fn member_of(&self, slot: u32) -> usize {
        self.cand(slot).map(|c| c.member).expect("a member") as usize
    }

    /// Removes a member's record (swap-remove in the manager's records).
    pub(super) fn drop_record(&mut self, m: usize, records: &mut Vec<TlasInstance>) {
        let r = self.members[m].record;
        if r == NONE {
            return;
        }
        if self.members[m].detail {
            self.detail_records -= 1;
        }
        let last = self.record_slots.len() - 1;
        records.swap(r as usize, last);
        records.truncate(last);
        self.record_slots.swap_remove(r as usize);
        if let Some(&moved) = self.record_slots.get(r as usize) {
            let mi = self.member_of(moved);
            self.members[mi].record = r;
            self.changed.push(r);
        }
        self.members[m].record = NONE;
    }

    pub(super) fn unselect(&mut self, m: usize) {
        let mb = self.members[m];
        self.unselect_at(mb.selected, mb.selected_pos);
    }

    /// Takes the member at `pos` of `pair`'s selecting list out of it.
    pub(super) fn unselect_at(&mut self, pair: u32, pos: u32) {
        if let Some(moved) = Self::list_remove(&mut self.pair(pair).selecting, pos) {
            let mi = self.member_of(moved);
            self.members[mi].selected_pos = pos;
        }
        self.release_pair(pair);
    }

    pub(super) fn select_pair(&mut self, m: usize, pair: u32) {
        let slot = self.members[m].slot;
        let list = &mut self.pair(pair).selecting;
        list.push(slot);
        let pos = (list.len() - 1) as u32;
        self.members[m].selected = pair;
        self.members[m].selected_pos = pos;
    }

    /// Gives a member `record` (`None`: none), at the end of the landmark records when it
    /// had none; lists what changed for the TLAS delta.
    pub(super) fn put_record(
        &mut self,
        m: usize,
        record: Option<TlasInstance>,
        records: &mut Vec<TlasInstance>,
    ) {
        let Some(record) = record else {
            self.drop_record(m, records);
            return;
        };
        let r = self.members[m].record;
        if r == NONE {
            let at = self.record_slots.len();
            debug_assert_eq!(records.len(), at, "landmark records come first");
            records.push(record);
            self.record_slots.push(self.members[m].slot);
            self.members[m].record = at as u32;
            self.changed.push(at as u32);
            if self.members[m].detail {
                self.detail_records += 1;
            }
        } else if records[r as usize] != record {
            records[r as usize] = record;
            self.changed.push(r);
        }
    }

    /// Makes a member count in its shown pair's `visible` (or not).
    pub(super) fn set_counted(&mut self, m: usize, counted: bool) {
        let mb = self.members[m];
        if mb.shown == NONE || mb.counted == counted {
            return;
        }
        let p = self.pair(mb.shown);
        if counted {
            p.visible += 1;
        } else {
            p.visible -= 1;
        }
        self.members[m].counted = counted;
    }

    /// Takes a member out of its shown pair's list.
    pub(super) fn unshow(&mut self, m: usize) {
        self.set_counted(m, false);
        let mb = self.members[m];
        if mb.shown == NONE {
            return;
        }
        if let Some(moved) = Self::list_remove(&mut self.pair(mb.shown).showing, mb.shown_pos) {
            let mi = self.member_of(moved);
            self.members[mi].shown_pos = mb.shown_pos;
        }
        self.release_pair(mb.shown);
        self.members[m].shown = NONE;
    }

    pub(super) fn untarget(&mut self, pair: u32) {
        self.pair(pair).targets -= 1;
        self.release_pair(pair);
    }

    /// Takes the detail of the near leaves in `covered` (sorted; covered by their own proxy
    /// this frame, handing over) out of the records, and puts back that of leaves no longer
    /// covered.
    /// `template` is an instance's record without its BLAS address.
    pub fn hide_covered(
        &mut self,
        covered: &[u32],
        records: &mut Vec<TlasInstance>,
        template: impl Fn(u32) -> Option<TlasInstance>,
    ) {
        if covered == self.hidden.as_slice() {
            return;
        }
        let old = std::mem::replace(&mut self.hidden, covered.to_vec());
        let flipped: Vec<u32> = old
            .iter()
            .filter(|g| !covered.contains(g))
            .chain(covered.iter().filter(|g| !old.contains(g)))
            .copied()
            .collect();
        for g in flipped {
            let Some(slots) = self.groups.get(&g) else {
                continue;
            };
            let members: Vec<usize> = slots
                .iter()
                .filter_map(|&s| self.cand(s))
                .filter(|c| c.member != NONE)
                .map(|c| c.member as usize)
                .filter(|&m| self.members[m].detail)
                .collect();
            let hide = covered.contains(&g);
            for m in members {
                if hide {
                    self.drop_record(m, records);
                } else {
                    let mb = self.members[m];
                    let c = self.cand(mb.slot).expect("a member is a candidate");
                    if mb.shown != NONE && !c.culled {
                        let address = self.pairs[mb.shown as usize]
                            .as_ref()
                            .expect("a live pair")
                            .address;
                        let r = template(mb.slot).map(|t| TlasInstance {
                            blas_address: address,
                            ..t
                        });
                        self.put_record(m, r, records);
                    }
                }
            }
        }
    }

    /// A member leaves the set (its record goes, its pairs forget it).
    pub(super) fn leave(&mut self, slot: u32, records: &mut Vec<TlasInstance>) {
        let ci = self.index[slot as usize] as usize;
        let m = self.cands[ci].member;
        if m == NONE {
            return;
        }
        let m = m as usize;
        self.drop_record(m, records);
        self.unshow(m);
        self.unselect(m);
        self.untarget(self.members[m].target);
        self.members.swap_remove(m);
        if let Some(moved) = self.members.get(m) {
            let mc = self.index[moved.slot as usize];
            self.cands[mc as usize].member = m as u32;
        }
        self.cands[ci].member = NONE;
    }
}
