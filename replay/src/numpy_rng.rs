//! numpy's legacy `RandomState` (MT19937), as far as the paper's replay sampler uses it: seeding
//! from an integer, `random_sample`, `choice(p=...)` and `randint` with the default int64 dtype.
//! Each reproduces numpy's draws bit for bit, so a sampler written with them draws what the
//! paper's code drew.

use rand_mt::Mt;

/// A numpy `RandomState` seeded from an integer.
pub struct RandomState {
    mt: Mt,
}

impl RandomState {
    /// `np.random.RandomState(seed)`: MT19937's `init_genrand(seed)`.
    pub fn new(seed: u32) -> Self {
        Self { mt: Mt::new(seed) }
    }

    /// `random_sample()`: a double in `[0, 1)` from 53 bits of two 32-bit draws.
    pub fn random_sample(&mut self) -> f64 {
        let a = f64::from(self.mt.next_u32() >> 5);
        let b = f64::from(self.mt.next_u32() >> 6);
        (a * 67_108_864.0 + b) / 9_007_199_254_740_992.0
    }

    /// `randint(low, high)` (`high` excluded, int64 dtype), for ranges below `2^32`: numpy's
    /// masked rejection on 32-bit draws; an empty-width range (`high = low + 1`) draws nothing.
    pub fn randint(&mut self, low: i64, high: i64) -> i64 {
        assert!(high > low && high - low - 1 <= i64::from(u32::MAX));
        let range = (high - low - 1) as u32;
        if range == 0 {
            return low;
        }
        if range == u32::MAX {
            return low + i64::from(self.mt.next_u32());
        }
        let mask = u32::MAX >> range.leading_zeros();
        loop {
            let v = self.mt.next_u32() & mask;
            if v <= range {
                return low + i64::from(v);
            }
        }
    }

    /// `choice(n, p=weights / sum(weights))` for non-negative integer weights with a positive
    /// sum: the index whose cumulative probability first exceeds a uniform draw.
    pub fn choice(&mut self, cdf: &ChoiceCdf) -> usize {
        let u = self.random_sample();
        // searchsorted(side = "right"): the first index whose cdf exceeds u
        cdf.0.partition_point(|&c| c <= u).min(cdf.0.len() - 1)
    }
}

/// The normalised cumulative probabilities numpy's `choice` searches, for `p = w / sum(w)`.
pub struct ChoiceCdf(Vec<f64>);

impl ChoiceCdf {
    /// numpy's arithmetic: `p = w / w.sum()` (an exact integer sum), `cdf = p.cumsum()` summed
    /// in order, `cdf /= cdf[-1]`; `None` without weight.
    pub fn new(weights: &[u64]) -> Option<Self> {
        let total: u64 = weights.iter().sum();
        if total == 0 {
            return None;
        }
        let mut sum = 0.0;
        let mut cdf: Vec<f64> = weights
            .iter()
            .map(|&w| {
                sum += w as f64 / total as f64;
                sum
            })
            .collect();
        let last = sum;
        for c in &mut cdf {
            *c /= last;
        }
        Some(Self(cdf))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values printed by numpy 2.4 (`np.random.RandomState(0)`).
    #[test]
    fn draws_match_numpy() {
        let mut mt = Mt::new(0);
        assert_eq!(
            [mt.next_u32(), mt.next_u32(), mt.next_u32()],
            [2_357_136_044, 2_546_248_239, 3_071_714_933]
        );
        let mut rs = RandomState::new(0);
        assert_eq!(rs.random_sample(), 0.548_813_503_927_324_8);
        assert_eq!(rs.random_sample(), 0.715_189_366_372_419_5);
        let mut rs = RandomState::new(0);
        let got: Vec<i64> = [1, 2, 3, 7, 100, 1000, 65537]
            .iter()
            .map(|&n| rs.randint(0, n))
            .collect();
        assert_eq!(got, [0, 0, 1, 0, 67, 763, 41993]);
    }
}
