//! The due queue: when each landmark candidate is next looked at, as camera travel.

use glam::Vec3;

/// Metres of camera travel per bucket of the due queue (a candidate may be looked at up to this
/// much early, never late).
const BUCKET_M: f64 = 1.0;
/// Buckets in the ring (4 km of travel ahead: its headers stay in cache); farther ones wait in
/// the overflow list, brought in every kilometre.
const RING: u64 = 1 << 12;

/// A queued look: the candidate (index and stamp: an entry whose stamp is no longer the
/// candidate's is stale), with what deciding that it only waits again needs (its centre and the
/// band of centre distances its last look holds for), so that most due entries are settled
/// from the queue alone, without touching the candidate.
#[derive(Debug, Clone, Copy)]
pub(super) struct Due {
    pub(super) ci: u32,
    pub(super) stamp: u32,
    pub(super) center: Vec3,
    pub(super) band: (f32, f32),
}

/// When each candidate is due, as camera travel: a ring of one-metre buckets of entries.
#[derive(Debug)]
pub(super) struct DueQueue {
    ring: Vec<Vec<Due>>,
    /// Bucket index of the next bucket to pop.
    base: u64,
    /// Due before `base` (within the bucket popped last): popped at the next pop, whatever
    /// the travel.
    soon: Vec<Due>,
    /// (bucket, entry) beyond the ring.
    overflow: Vec<(u64, Due)>,
    /// Emptied buckets' vectors, handed to buckets that get their first entry: each bucket is
    /// used once per 4 km of travel, so its allocation goes round the ring instead.
    spares: Vec<Vec<Due>>,
}

impl Default for DueQueue {
    fn default() -> Self {
        Self {
            ring: (0..RING).map(|_| Vec::new()).collect(),
            base: 0,
            soon: Vec::new(),
            overflow: Vec::new(),
            spares: Vec::new(),
        }
    }
}

impl DueQueue {
    pub(super) fn clear(&mut self) {
        self.ring.iter_mut().for_each(Vec::clear);
        self.soon.clear();
        self.overflow.clear();
    }

    /// Due once the odometer reaches `due` (a bucket early at most, never late).
    pub(super) fn push(&mut self, due: f64, entry: Due) {
        let b = (due / BUCKET_M) as u64;
        if b < self.base {
            self.soon.push(entry);
        } else if b - self.base >= RING {
            self.overflow.push((b, entry));
        } else {
            let bucket = &mut self.ring[(b % RING) as usize];
            if bucket.capacity() == 0 {
                if let Some(v) = self.spares.pop() {
                    *bucket = v;
                }
            }
            bucket.push(entry);
        }
    }

    /// Appends every entry due at odometer `odo`.
    pub(super) fn pop_due(&mut self, odo: f64, out: &mut Vec<Due>) {
        let current = (odo / BUCKET_M) as u64;
        out.append(&mut self.soon);
        while self.base <= current {
            let mut bucket = std::mem::take(&mut self.ring[(self.base % RING) as usize]);
            if bucket.capacity() > 0 {
                out.append(&mut bucket);
                self.spares.push(bucket);
            }
            self.base += 1;
            if self.base % (RING / 4) == 0 && !self.overflow.is_empty() {
                // A quarter of the ring passed: bring the overflow that now fits into it.
                let (base, mut keep) = (self.base, Vec::new());
                for (b, entry) in std::mem::take(&mut self.overflow) {
                    if b - base.min(b) < RING {
                        self.ring[(b.max(base) % RING) as usize].push(entry);
                    } else {
                        keep.push((b, entry));
                    }
                }
                self.overflow = keep;
            }
        }
    }
}
