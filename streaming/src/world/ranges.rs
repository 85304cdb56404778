//! What the loaded levels hold that a per-frame pass reads, all levels in one array.

use std::collections::HashMap;

/// Items of the loaded levels in one array, a range per level. One array per level (606 of
/// them loaded in the default world, 38 instances each) made a per-frame pass a chain of
/// short reads at scattered addresses, each starting cold; one array streams. An unloaded
/// level's range is emptied in place (its items become `None`, skipped by `live`), and the
/// array is compacted once half of it is empty: moving the ranges after it down at each
/// unload cost 0.07 ms a frame on the H200 host.
#[derive(Debug)]
pub(super) struct LevelRanges<T> {
    items: Vec<Option<T>>,
    /// Level -> (start, length) in `items`.
    ranges: HashMap<u32, (usize, usize)>,
    /// Emptied items in `items`.
    empty: usize,
}

impl<T> Default for LevelRanges<T> {
    fn default() -> Self {
        Self {
            items: Vec::new(),
            ranges: HashMap::new(),
            empty: 0,
        }
    }
}

impl<T> LevelRanges<T> {
    /// Adds (or replaces) a level's items. A level without items has no range (an empty
    /// range's start could lie past the array's end once the array is cut short).
    pub(super) fn insert(&mut self, level: u32, items: impl Iterator<Item = T>) {
        self.remove(level);
        let start = self.items.len();
        self.items.extend(items.map(Some));
        if self.items.len() > start {
            self.ranges.insert(level, (start, self.items.len() - start));
        }
    }

    /// Drops a level's items (nothing if it has none).
    pub(super) fn remove(&mut self, level: u32) {
        let Some((start, len)) = self.ranges.remove(&level) else {
            return;
        };
        if start + len == self.items.len() {
            self.items.truncate(start);
        } else {
            self.items[start..start + len].fill_with(|| None);
            self.empty += len;
        }
        if self.empty * 2 > self.items.len() {
            self.compact();
        }
    }

    /// Moves the live ranges together, in their order.
    fn compact(&mut self) {
        let mut order: Vec<(usize, u32)> = self.ranges.iter().map(|(&l, r)| (r.0, l)).collect();
        order.sort_unstable();
        let mut at = 0;
        for (start, level) in order {
            let len = self.ranges[&level].1;
            for k in 0..len {
                self.items.swap(at + k, start + k);
            }
            self.ranges.insert(level, (at, len));
            at += len;
        }
        self.items.truncate(at);
        self.empty = 0;
    }

    /// Every loaded level's items.
    pub(super) fn live(&self) -> impl Iterator<Item = &T> {
        self.items.iter().flatten()
    }

    /// One level's items, in the order inserted (empty for a level without any; a loaded
    /// level's items are all `Some`).
    pub(super) fn level(&self, level: u32) -> &[Option<T>] {
        let (start, len) = self.ranges.get(&level).copied().unwrap_or((0, 0));
        &self.items[start..start + len]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Levels coming and going in any order leave exactly the items of the levels still
    /// loaded, each level's in one piece.
    #[test]
    fn levels_in_and_out_keep_exactly_the_loaded_items() {
        let mut ranges = LevelRanges::default();
        let mut loaded: HashMap<u32, u32> = HashMap::new();
        let mut rng = 0x9e37_79b9u64;
        for step in 0..2000u32 {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            let level = (rng % 40) as u32;
            if loaded.remove(&level).is_some() {
                ranges.remove(level);
            } else {
                // Often none (a level without skinned instances).
                let n = if (rng >> 40) % 3 == 0 {
                    0
                } else {
                    (rng >> 8) as u32 % 50
                };
                ranges.insert(level, (0..n).map(|k| level * 1000 + k));
                loaded.insert(level, n);
            }
            let mut want: Vec<u32> = loaded
                .iter()
                .flat_map(|(&l, &n)| (0..n).map(move |k| l * 1000 + k))
                .collect();
            let mut have: Vec<u32> = ranges.live().copied().collect();
            assert!(
                ranges.empty * 2 <= ranges.items.len().max(1),
                "step {step}: not compacted"
            );
            want.sort_unstable();
            have.sort_unstable();
            assert_eq!(have, want, "step {step}");
            for (&l, &(start, len)) in &ranges.ranges {
                assert!(len > 0 && start + len <= ranges.items.len(), "step {step}");
                assert!(ranges.items[start..start + len]
                    .iter()
                    .all(|i| i.is_some_and(|i| i / 1000 == l)));
            }
        }
    }
}
