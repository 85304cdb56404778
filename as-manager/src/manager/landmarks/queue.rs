//! The due queue: when each landmark candidate is next looked at, as camera travel.
//!
//! A timing wheel in two levels. Entries due within the current block of 64 one-metre buckets
//! go to a fine ring (a vector per bucket); entries due in later blocks, up to 4 km ahead, go
//! to a coarse ring (a list of fixed-size chunks per block, from one shared pool) and move to
//! the fine ring when their block becomes current; farther ones wait in an overflow map by
//! block, each block brought into the coarse ring as it comes within 4 km. A push appends
//! to one of 64 + 128 vectors whose ends stay in cache; with a vector per metre over 4 km, the
//! pushes of a fast camera (8 m a frame: about 1,300 a frame) went to cold vectors, and pushing
//! took 14 % of `update`'s samples (`docs/PROFILE.md`, "The due queue in two levels"). Entries
//! come out in the order the one-level ring gave them (by bucket, then as pushed), so the looks
//! are the same.
//!
//! The coarse ring holds most entries (about 400,000 in the million world). With a vector per
//! block, each block kept the capacity of the fullest it had ever been: the ring's capacity
//! grew to the sum of 128 peaks (4.2 M entries, 167 MB, after 12 km of travel), and each new
//! peak cost a reallocation and fresh pages in the frame (13 % of the landmarks' samples were
//! the kernel clearing pages). Chunks of `CHUNK` entries go back to the pool when their block
//! moves to the fine ring, so the ring holds about the entries live at once.
//!
//! The overflow was one list, scanned in full every kilometre of travel to bring in what came
//! within 4 km: 100,000–320,000 entries in the million world, a 1.3–4.8 ms frame every 2,048
//! frames at 0.5 m a frame (the slowest frames of `frame_cost --million --far`). By kilometre,
//! the kilometre coming in still took 0.9–1.5 ms; by block, each 64 m of travel brings in its
//! own 64 m.
//!
//! A block's move from the coarse ring to the fine one was done at once, in the frame whose
//! travel entered the block: at 8 m a frame, every eighth frame moved a block's few thousand
//! entries (0.2 ms more `collect_due` in the H200's slowest frames, `docs/PROFILE.md`). The
//! fine ring now holds two blocks, the current one and the next, and the next block's
//! entries move over while the current one is consumed, in step with the travel through it;
//! the rest moves when the block becomes current. Entries pushed to the next block go to its
//! coarse list behind those not moved yet, so each bucket still comes out in push order.

use glam::Vec3;
use rustc_hash::FxHashMap;

/// Metres of camera travel per bucket of the due queue (a candidate may be looked at up to this
/// much early, never late).
const BUCKET_M: f64 = 1.0;
/// Buckets per block (the fine ring holds the current block and the next).
const BLOCK: u64 = 64;
/// Buckets of the fine ring: two blocks.
const FINE: u64 = 2 * BLOCK;
/// Buckets ahead of the current one that the rings hold (4 km of travel); farther entries wait
/// in the overflow list.
const RING: u64 = 1 << 12;
/// Blocks in the coarse ring: every block that a bucket less than `RING` ahead can be in.
const COARSE: u64 = 2 * RING / BLOCK;
/// The longest camera move a frame that the queue steps through (metres): a longer one (a
/// teleport across the map) makes every candidate due instead, as a pop would walk a bucket
/// a metre of it.
pub(super) const MAX_STEP_M: f64 = RING as f64 * BUCKET_M;
/// Entries per chunk of a coarse block.
const CHUNK: usize = 1024;

/// A queued look: the candidate (index and stamp: an entry whose stamp is no longer the
/// candidate's is stale), with what deciding that it only waits again needs (its centre and the
/// band of centre distances its last look holds for), so that most due entries are settled
/// from the queue alone, without touching the candidate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Due {
    pub(super) ci: u32,
    pub(super) stamp: u32,
    pub(super) center: Vec3,
    pub(super) band: (f32, f32),
}

/// A coarse block's chunk: (bucket, entry), at most `CHUNK` of them.
type Chunk = Vec<(u64, Due)>;

/// When each candidate is due, as camera travel (see the module docs).
#[derive(Debug)]
pub(super) struct DueQueue {
    /// The buckets of the current block, and of the next block's entries moved so far, by
    /// bucket index modulo `FINE`.
    fine: Vec<Vec<Due>>,
    /// (bucket, entry) of the later blocks, by block index modulo `COARSE`. The next block's
    /// list moves to `fine` from its front: `moved` is (chunk, entry) of the first not moved.
    coarse: Vec<Vec<Chunk>>,
    moved: (usize, usize),
    /// Emptied chunks, for the next block that needs one.
    spare: Vec<Chunk>,
    /// Bucket index of the next bucket to pop.
    base: u64,
    /// Due before `base` (within the bucket popped last): popped at the next pop, whatever
    /// the travel.
    soon: Vec<Due>,
    /// (bucket, entry) `RING` or more buckets ahead, by block (bucket / `BLOCK`).
    overflow: FxHashMap<u64, Vec<(u64, Due)>>,
}

impl Default for DueQueue {
    fn default() -> Self {
        Self {
            fine: (0..FINE).map(|_| Vec::new()).collect(),
            coarse: (0..COARSE).map(|_| Vec::new()).collect(),
            moved: (0, 0),
            spare: Vec::new(),
            base: 0,
            soon: Vec::new(),
            overflow: FxHashMap::default(),
        }
    }
}

impl DueQueue {
    pub(super) fn clear(&mut self) {
        self.fine.iter_mut().for_each(Vec::clear);
        for block in &mut self.coarse {
            for mut chunk in block.drain(..) {
                chunk.clear();
                self.spare.push(chunk);
            }
        }
        self.moved = (0, 0);
        self.soon.clear();
        self.overflow.clear();
    }

    /// Due once the odometer reaches `due` (a bucket early at most, never late).
    pub(super) fn push(&mut self, due: f64, entry: Due) {
        self.push_bucket((due / BUCKET_M) as u64, entry);
    }

    fn push_bucket(&mut self, b: u64, entry: Due) {
        if b < self.base {
            self.soon.push(entry);
        } else if b - self.base >= RING {
            self.overflow.entry(b / BLOCK).or_default().push((b, entry));
        } else if b / BLOCK == self.base / BLOCK {
            self.fine[(b % FINE) as usize].push(entry);
        } else {
            let block = &mut self.coarse[((b / BLOCK) % COARSE) as usize];
            match block.last_mut() {
                Some(chunk) if chunk.len() < CHUNK => chunk.push((b, entry)),
                _ => {
                    let mut chunk = self
                        .spare
                        .pop()
                        .unwrap_or_else(|| Vec::with_capacity(CHUNK));
                    chunk.push((b, entry));
                    block.push(chunk);
                }
            }
        }
    }

    /// Appends every entry due at odometer `odo`.
    pub(super) fn pop_due(&mut self, odo: f64, out: &mut Vec<Due>) {
        let current = (odo / BUCKET_M) as u64;
        out.append(&mut self.soon);
        if self.base > current {
            return;
        }
        let left_before = BLOCK - self.base % BLOCK;
        let mut crossed = false;
        while self.base <= current {
            let bucket = &mut self.fine[(self.base % FINE) as usize];
            out.append(bucket);
            self.base += 1;
            if self.base % BLOCK == 0 {
                // A new block: the rest of its entries move to the fine ring, in the order
                // pushed, and the block after it is the next to move.
                crossed = true;
                let block = ((self.base / BLOCK) % COARSE) as usize;
                self.move_from(block, usize::MAX);
                let mut done = std::mem::take(&mut self.coarse[block]);
                for mut chunk in done.drain(..) {
                    chunk.clear();
                    self.spare.push(chunk);
                }
                self.coarse[block] = done;
                self.moved = (0, 0);
                // The block that came within `RING`: its overflow joins the coarse ring
                // (after what was pushed there directly). `base` and `RING` are whole
                // blocks, and the overflow never holds a block within `RING` (pushes there go
                // to the rings): only the block that just came within is in it.
                let entering = (self.base + RING) / BLOCK - 1;
                if let Some(entries) = self.overflow.remove(&entering) {
                    for (b, e) in entries {
                        self.push_bucket(b.max(self.base), e);
                    }
                }
            }
        }
        // The next block moves over in step with the travel through this one: of what is
        // left to move, the share of this block's remaining buckets that this pop went
        // through (the whole of it by the block's last bucket).
        let left = BLOCK - self.base % BLOCK;
        let went = if crossed {
            BLOCK - left
        } else {
            left_before - left
        };
        let remaining = if crossed { BLOCK } else { left_before };
        if went > 0 {
            let block = ((self.base / BLOCK + 1) % COARSE) as usize;
            let (c, e) = self.moved;
            let waiting = self.coarse[block]
                .iter()
                .skip(c)
                .map(Vec::len)
                .sum::<usize>()
                - e;
            let n = (waiting as u64 * went).div_ceil(remaining);
            self.move_from(block, n as usize);
        }
    }

    /// Moves up to `n` entries of coarse block `block` (the one moving: from `moved` on) to
    /// the fine ring.
    fn move_from(&mut self, block: usize, mut n: usize) {
        let (mut c, mut e) = self.moved;
        let chunks = &self.coarse[block];
        while let Some(chunk) = chunks.get(c) {
            if e == chunk.len() {
                // On to the next chunk only when there is one: pushes still go to the last.
                if c + 1 == chunks.len() {
                    break;
                }
                (c, e) = (c + 1, 0);
                continue;
            }
            if n == 0 {
                break;
            }
            let take = n.min(chunk.len() - e);
            for &(b, entry) in &chunk[e..e + take] {
                self.fine[(b % FINE) as usize].push(entry);
            }
            (e, n) = (e + take, n - take);
        }
        self.moved = (c, e);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one-level ring of a vector per metre that this queue replaced, as the reference.
    #[derive(Default)]
    struct Reference {
        ring: std::collections::BTreeMap<u64, Vec<Due>>,
        base: u64,
        soon: Vec<Due>,
        overflow: Vec<(u64, Due)>,
    }

    impl Reference {
        fn push(&mut self, due: f64, e: Due) {
            let b = (due / BUCKET_M) as u64;
            if b < self.base {
                self.soon.push(e);
            } else if b - self.base >= RING {
                self.overflow.push((b, e));
            } else {
                self.ring.entry(b).or_default().push(e);
            }
        }

        fn pop_due(&mut self, odo: f64, out: &mut Vec<Due>) {
            let current = (odo / BUCKET_M) as u64;
            out.append(&mut self.soon);
            while self.base <= current {
                if let Some(mut v) = self.ring.remove(&self.base) {
                    out.append(&mut v);
                }
                self.base += 1;
                if self.base % BLOCK == 0 {
                    let base = self.base;
                    let mut keep = Vec::new();
                    for (b, e) in std::mem::take(&mut self.overflow) {
                        if b - base.min(b) < RING {
                            self.ring.entry(b.max(base)).or_default().push(e);
                        } else {
                            keep.push((b, e));
                        }
                    }
                    self.overflow = keep;
                }
            }
        }
    }

    /// Random pushes (within a block, blocks ahead, beyond the rings, already due) and pops
    /// (steps of a few metres, and teleport-sized jumps across many blocks) give the same
    /// entries in the same order as the one-level ring.
    /// A fresh entry for candidate `*ci` (then the next one).
    fn entry(ci: &mut u32, stamp: u32) -> Due {
        *ci += 1;
        Due {
            ci: *ci - 1,
            stamp,
            center: Vec3::ZERO,
            band: (0.0, 1.0),
        }
    }

    #[test]
    fn the_two_level_queue_pops_what_the_one_level_ring_popped() {
        let (mut q, mut r) = (DueQueue::default(), Reference::default());
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng
        };
        let (mut odo, mut ci) = (0.0f64, 0u32);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let mut popped = 0;
        for step in 0..4000 {
            for _ in 0..next() % 40 {
                let ahead = match next() % 10 {
                    0 => (next() % 20_000) as f64,
                    1 => -((next() % 5) as f64),
                    2..=4 => (next() % 4_200) as f64 + 0.5,
                    // Into the next block, which moves to the fine ring while it is pushed to.
                    5 => (BLOCK as f64 - odo % BLOCK as f64) + (next() % 64) as f64,
                    _ => (next() % 70) as f64 * 0.7,
                };
                let e = entry(&mut ci, step);
                q.push(odo + ahead, e);
                r.push(odo + ahead, e);
            }
            if step % 500 == 7 {
                // A burst into one coarse block: more than a chunk holds.
                for _ in 0..3 * CHUNK {
                    let e = entry(&mut ci, step);
                    q.push(odo + 700.0, e);
                    r.push(odo + 700.0, e);
                }
            }
            odo += if next() % 97 == 0 {
                (next() % 3_000) as f64
            } else {
                (next() % 900) as f64 / 100.0
            };
            q.pop_due(odo, &mut a);
            r.pop_due(odo, &mut b);
            assert_eq!(a, b, "step {step}");
            popped += a.len();
            a.clear();
            b.clear();
        }
        assert!(popped > 50_000, "{popped}");
    }

    /// The next block moves to the fine ring a share each pop, not all at once when it
    /// becomes current (a frame's worth of travel moves a frame's share), and every entry
    /// still comes out at its bucket.
    #[test]
    fn the_next_block_moves_over_in_step_with_the_travel() {
        let mut q = DueQueue::default();
        let mut out = Vec::new();
        let mut ci = 0;
        // 64,000 entries due in block 2 (buckets 128..192), pushed at odometer 0.
        for i in 0..64_000u32 {
            q.push(f64::from(128 + i % 64) + 0.5, entry(&mut ci, 1));
        }
        let in_fine = |q: &DueQueue| q.fine.iter().map(Vec::len).sum::<usize>();
        let mut most = 0;
        for step in 0..128u32 {
            let before = in_fine(&q);
            q.pop_due(f64::from(step) + 0.5, &mut out);
            assert!(out.is_empty(), "step {step}: {} popped early", out.len());
            most = most.max(in_fine(&q) - before);
        }
        // Block 2 moved while block 1 was current: about 1,000 entries a metre.
        assert_eq!(in_fine(&q), 64_000);
        assert!(most <= 1_100, "{most} entries moved in one pop");
        for step in 128..192u32 {
            q.pop_due(f64::from(step) + 0.5, &mut out);
            assert_eq!(out.len(), 1_000, "bucket {step}");
            out.clear();
        }
    }

    /// Entries the coarse ring can hold without allocating (its chunks and the spare ones).
    fn coarse_capacity(q: &DueQueue) -> usize {
        let held: usize = q.coarse.iter().flatten().map(Vec::capacity).sum();
        held + q.spare.iter().map(Vec::capacity).sum::<usize>()
    }

    #[test]
    fn the_coarse_ring_holds_about_its_live_entries_not_every_blocks_peak() {
        // Each block in turn is the fullest (10,000 entries), while the queue never holds
        // more than about 12,000: vectors kept per block would hold 128 peaks.
        let mut q = DueQueue::default();
        let mut out = Vec::new();
        let mut odo = 0.0f64;
        let mut peak_live = 0;
        for round in 0..(2 * COARSE as u32) {
            for i in 0..10_000u32 {
                let e = Due {
                    ci: round * 10_000 + i,
                    stamp: 1,
                    center: Vec3::ZERO,
                    band: (0.0, 1.0),
                };
                q.push(odo + 100.0 + f64::from(i % 50), e);
            }
            let live: usize = q.coarse.iter().flatten().map(Vec::len).sum::<usize>()
                + q.fine.iter().map(Vec::len).sum::<usize>();
            peak_live = peak_live.max(live);
            odo += BLOCK as f64;
            q.pop_due(odo, &mut out);
            out.clear();
        }
        let cap = coarse_capacity(&q);
        assert!(
            cap <= 2 * peak_live + CHUNK * COARSE as usize,
            "coarse capacity {cap} for at most {peak_live} live entries"
        );
    }
}
