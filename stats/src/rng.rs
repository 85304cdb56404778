//! The deterministic random source of the world generator (`rtstream-streaming`) and the
//! synthetic benchmark world (`rtstream-as-manager`'s `synth`): one type for both, here because
//! this is the lowest crate the two share.

use rand_xoshiro::rand_core::{RngCore, SeedableRng};
use rand_xoshiro::SplitMix64;

/// [`rand_xoshiro::SplitMix64`] (its raw `next_u64` is value-stable across versions) with the
/// few helpers placement needs, written on top of `next_u64` so that a seed gives the same
/// world, bit for bit. No `rand` distributions: their values may change between versions.
///
/// ```
/// use rtstream_stats::Rng;
/// let (mut a, mut b) = (Rng::new(7), Rng::new(7));
/// assert_eq!(a.next_u64(), b.next_u64());
/// let x = a.range(2.0, 3.0);
/// assert!((2.0..3.0).contains(&x));
/// assert!(a.below(5) < 5);
/// assert_eq!(a.below(0), 0);
/// ```
#[derive(Debug, Clone)]
pub struct Rng(SplitMix64);

impl Rng {
    /// A generator whose state starts at `seed`.
    pub fn new(seed: u64) -> Rng {
        Rng(SplitMix64::seed_from_u64(seed))
    }
    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }
    /// Uniform in [0, 1).
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }
    /// Uniform integer in [0, n); 0 when n is 0.
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next_u64() % n as u64) as usize
        }
    }
}
