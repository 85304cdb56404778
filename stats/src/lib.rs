//! # rtstream-stats
//!
//! One way to summarise a sample, used by every crate that reports a median or a percentile
//! (the frame driver's report, the GPU measurements, the benches and examples), so a figure
//! means the same wherever it is printed.
//!
//! Design choices:
//! - **Nearest rank.** The `p`-th percentile of `n` sorted values is the value of rank
//!   `ceil(p * n)` (1-based): always a sample value, never an interpolation; for an even `n`
//!   the median is the lower middle value.
//! - **Exact, not a histogram.** The samples are small (a few thousand frames at most) and the
//!   driver's deterministic figures (BLAS bytes, TLAS instances) are compared exactly between
//!   runs (`tests/driver_run.rs`); `hdrhistogram` would round them to its significant digits.
//! - **Non-finite values are left out** (a PSNR of identical frames is infinite).
//! - Its own crate because `streaming` and `as-manager` do not know each other and both need it.
//!   For the same reason it holds the one seeded random source both generators use ([`Rng`]).

#![warn(missing_docs)]

use serde::Serialize;

mod rng;
pub use rng::Rng;

/// The 0-based index of the `p`-th percentile (nearest rank) in a sorted sample of `n` values;
/// `p` in `[0, 1]`, `n > 0`.
///
/// ```
/// use rtstream_stats::nearest_rank;
/// assert_eq!(nearest_rank(100, 0.95), 94); // the 95th value
/// assert_eq!(nearest_rank(5, 0.5), 2);
/// assert_eq!(nearest_rank(4, 0.5), 1);     // the lower middle
/// assert_eq!(nearest_rank(4, 0.0), 0);
/// ```
pub fn nearest_rank(n: usize, p: f64) -> usize {
    debug_assert!(n > 0, "a percentile of an empty sample");
    ((p * n as f64).ceil() as usize).clamp(1, n) - 1
}

/// A sample, sorted once, with its percentiles.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Samples {
    sorted: Vec<f64>,
}

impl Samples {
    /// The finite values of `values`, sorted.
    pub fn new(values: impl IntoIterator<Item = f64>) -> Self {
        let mut sorted: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        Self { sorted }
    }

    /// Number of (finite) values.
    pub fn len(&self) -> usize {
        self.sorted.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.sorted.is_empty()
    }

    /// The `p`-th percentile (nearest rank, `p` in `[0, 1]`); 0 for an empty sample.
    pub fn percentile(&self, p: f64) -> f64 {
        if self.sorted.is_empty() {
            return 0.0;
        }
        self.sorted[nearest_rank(self.sorted.len(), p)]
    }

    /// The median (the lower middle value for an even count); 0 for an empty sample.
    pub fn median(&self) -> f64 {
        self.percentile(0.5)
    }

    /// Arithmetic mean; 0 for an empty sample.
    pub fn mean(&self) -> f64 {
        if self.sorted.is_empty() {
            return 0.0;
        }
        self.sorted.iter().sum::<f64>() / self.sorted.len() as f64
    }

    /// Largest value; 0 for an empty sample.
    pub fn max(&self) -> f64 {
        self.sorted.last().copied().unwrap_or(0.0)
    }

    /// Mean, p50, p95, p99 and max.
    pub fn summary(&self) -> Summary {
        Summary {
            n: self.len(),
            mean: self.mean(),
            p50: self.percentile(0.50),
            p95: self.percentile(0.95),
            p99: self.percentile(0.99),
            max: self.max(),
        }
    }
}

/// Mean, percentiles and extremes of a sample.
///
/// ```
/// let s = rtstream_stats::Summary::of((1..=100).map(f64::from));
/// assert_eq!((s.n, s.p50, s.p95, s.p99, s.max), (100, 50.0, 95.0, 99.0, 100.0));
/// ```
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Summary {
    /// Sample size.
    pub n: usize,
    /// Arithmetic mean (0 for an empty sample).
    pub mean: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest value.
    pub max: f64,
}

impl Summary {
    /// Summarises `values`; non-finite values are left out.
    pub fn of(values: impl IntoIterator<Item = f64>) -> Self {
        Samples::new(values).summary()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles() {
        let s = Summary::of((1..=100).map(f64::from));
        assert_eq!(
            (s.n, s.p50, s.p95, s.p99, s.max),
            (100, 50.0, 95.0, 99.0, 100.0)
        );
        assert!((s.mean - 50.5).abs() < 1e-12);
        let one = Summary::of([f64::NAN, 3.0]);
        assert_eq!((one.n, one.p50, one.p99), (1, 3.0, 3.0));
        assert_eq!(Summary::of([]), Summary::default());
    }

    #[test]
    fn samples_sort_once_and_answer_any_percentile() {
        let s = Samples::new([5.0, 1.0, f64::INFINITY, 3.0, 2.0, 4.0]);
        assert_eq!(s.len(), 5);
        assert_eq!(
            (s.median(), s.percentile(0.1), s.percentile(1.0)),
            (3.0, 1.0, 5.0)
        );
        assert_eq!(Samples::new([2.0, 1.0]).median(), 1.0);
        assert_eq!(Samples::default().median(), 0.0);
    }
}
