//! What the loaded levels hold that a per-frame pass reads, all levels in one array.

use std::collections::HashMap;

/// Items of the loaded levels in one array, a range per level. One array per level (606 of
/// them loaded in the default world, 38 instances each) made a per-frame pass a chain of
/// short reads at scattered addresses, each starting cold; one array streams. An unloaded
/// level's range is dropped by moving the ranges after it down (a level unloads every few
/// frames; the copy is a few hundred kilobytes at most).
#[derive(Debug)]
pub(super) struct LevelRanges<T> {
    items: Vec<T>,
    /// Level -> (start, length) in `items`.
    ranges: HashMap<u32, (usize, usize)>,
}

impl<T> Default for LevelRanges<T> {
    fn default() -> Self {
        Self {
            items: Vec::new(),
            ranges: HashMap::new(),
        }
    }
}

impl<T> LevelRanges<T> {
    /// Adds (or replaces) a level's items.
    pub(super) fn insert(&mut self, level: u32, items: impl Iterator<Item = T>) {
        self.remove(level);
        let start = self.items.len();
        self.items.extend(items);
        self.ranges.insert(level, (start, self.items.len() - start));
    }

    /// Drops a level's items (nothing if it has none).
    pub(super) fn remove(&mut self, level: u32) {
        let Some((start, len)) = self.ranges.remove(&level) else {
            return;
        };
        self.items.drain(start..start + len);
        for r in self.ranges.values_mut() {
            if r.0 > start {
                r.0 -= len;
            }
        }
    }

    /// Every loaded level's items.
    pub(super) fn live(&self) -> &[T] {
        &self.items
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
                let n = (rng >> 8) as u32 % 50;
                ranges.insert(level, (0..n).map(|k| level * 1000 + k));
                loaded.insert(level, n);
            }
            let mut want: Vec<u32> = loaded
                .iter()
                .flat_map(|(&l, &n)| (0..n).map(move |k| l * 1000 + k))
                .collect();
            let mut have = ranges.live().to_vec();
            want.sort_unstable();
            have.sort_unstable();
            assert_eq!(have, want, "step {step}");
            for (&l, &(start, len)) in &ranges.ranges {
                assert!(ranges.items[start..start + len]
                    .iter()
                    .all(|i| i / 1000 == l));
            }
        }
    }
}
