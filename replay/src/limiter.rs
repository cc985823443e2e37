//! The samples-per-insert rate limiter (DeepMind Reverb's `SampleToInsertRatio`), so that the
//! learner's replay ratio holds whatever the actors' speed.
//!
//! With `d = inserts · spi − samples`, sampling `n` needs `inserts ≥ min_fill` and
//! `d − n ≥ spi · min_fill − error_buffer`; inserting `n` (once past `min_fill`) needs
//! `d + n · spi ≤ spi · min_fill + error_buffer`. A too fast learner waits for inserts, too fast
//! actors wait for samples. With `spi = 0` only `min_fill` holds. Once closed (the run's
//! env-step budget is stored: no insert will come again) sampling waits for nothing.

/// Counts inserts and samples and says whether more of either may happen now.
#[derive(Clone, Debug, PartialEq)]
pub struct RateLimiter {
    spi: f64,
    min_fill: u64,
    min_diff: f64,
    max_diff: f64,
    inserts: u64,
    samples: u64,
    closed: bool,
}

impl RateLimiter {
    /// `samples_per_insert` sampled steps per inserted step, after `min_fill` inserts, with
    /// `error_buffer_steps` inserts of slack either way (`error_buffer_steps · spi` samples).
    pub fn new(samples_per_insert: f64, min_fill: u64, error_buffer_steps: f64) -> Self {
        let spi = if samples_per_insert.is_finite() {
            samples_per_insert.max(0.0)
        } else {
            0.0
        };
        let offset = spi * min_fill as f64;
        let buffer = spi * error_buffer_steps.max(0.0);
        Self {
            spi,
            min_fill,
            min_diff: offset - buffer,
            max_diff: offset + buffer,
            inserts: 0,
            samples: 0,
            closed: false,
        }
    }

    /// Sets the counters (a restored snapshot's).
    pub fn restore(&mut self, inserts: u64, samples: u64) {
        self.inserts = inserts;
        self.samples = samples;
    }

    fn diff(&self) -> f64 {
        self.inserts as f64 * self.spi - self.samples as f64
    }

    /// Whether `n` steps may be sampled now.
    pub fn can_sample(&self, n: u64) -> bool {
        self.closed
            || (self.inserts >= self.min_fill
                && (self.spi == 0.0 || self.diff() - n as f64 >= self.min_diff))
    }

    /// Notes that no insert will come again (the run's env-step budget is stored): from now on
    /// sampling waits neither for `min_fill` nor for the ratio.
    pub fn close(&mut self) {
        self.closed = true;
    }

    /// Whether [`close`](Self::close) was called.
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Whether `n` steps could ever be sampled at once: a larger request than the ratio's window
    /// (`2 · error_buffer_steps · samples_per_insert`) would wait forever.
    pub fn can_ever_sample(&self, n: u64) -> bool {
        self.spi == 0.0 || n as f64 <= self.max_diff - self.min_diff
    }

    /// Whether `n` steps may be inserted now.
    pub fn can_insert(&self, n: u64) -> bool {
        self.spi == 0.0
            || self.inserts + n < self.min_fill
            || self.diff() + n as f64 * self.spi <= self.max_diff
    }

    /// Records inserted steps.
    pub fn inserted(&mut self, n: u64) {
        self.inserts += n;
    }

    /// Records sampled steps.
    pub fn sampled(&mut self, n: u64) {
        self.samples += n;
    }

    /// Steps inserted.
    pub fn inserts(&self) -> u64 {
        self.inserts
    }

    /// Steps sampled.
    pub fn samples(&self) -> u64 {
        self.samples
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn min_fill_gates_sampling() {
        let mut r = RateLimiter::new(0.0, 100, 10.0);
        assert!(!r.can_sample(1));
        r.inserted(99);
        assert!(!r.can_sample(1));
        r.inserted(1);
        assert!(r.can_sample(1_000_000));
        assert!(r.can_insert(1_000_000));
    }

    #[test]
    fn a_closed_limiter_lets_sampling_finish() {
        let mut r = RateLimiter::new(4.0, 10, 5.0);
        r.inserted(10);
        r.sampled(20);
        assert!(!r.can_sample(4));
        r.close();
        assert!(r.is_closed() && r.can_sample(4) && r.can_sample(1_000));
        // even below min_fill: the data is final
        let mut early = RateLimiter::new(4.0, 10, 5.0);
        early.inserted(3);
        early.close();
        assert!(early.can_sample(8));
    }

    #[test]
    fn ratio_holds_within_the_error_buffer() {
        // 4 samples per insert, min fill 10, slack of 5 inserts = 20 samples.
        let mut r = RateLimiter::new(4.0, 10, 5.0);
        r.inserted(10);
        // d = 40 = offset: sampling needs d - n >= 20, so 20 samples now, not 21.
        assert!(r.can_sample(20));
        assert!(!r.can_sample(21));
        // Inserting needs d + 4n <= 60: 5 more inserts, not 6.
        assert!(r.can_insert(5));
        assert!(!r.can_insert(6));
        r.sampled(20);
        assert!(!r.can_sample(1));
        r.inserted(1);
        assert!(r.can_sample(4));
        assert!(!r.can_sample(5));
        // the window is 2 x 20 samples: a request of 41 could never be served
        assert!(r.can_ever_sample(40) && !r.can_ever_sample(41));
        // Over a long run the ratio converges to spi whatever the order.
        let mut r = RateLimiter::new(2.0, 10, 3.0);
        let (mut ins, mut smp) = (0u64, 0u64);
        for step in 0..10_000u64 {
            if step % 3 == 0 && r.can_insert(1) {
                r.inserted(1);
                ins += 1;
            } else if r.can_sample(1) {
                r.sampled(1);
                smp += 1;
            }
        }
        let ratio = smp as f64 / ins as f64;
        assert!((ratio - 2.0).abs() < 0.05, "ratio {ratio}");
    }

    #[test]
    fn nonsense_ratio_disables_it() {
        let mut r = RateLimiter::new(f64::NAN, 0, 1.0);
        assert!(r.can_sample(5) && r.can_insert(5));
        r.restore(7, 3);
        assert_eq!((r.inserts(), r.samples()), (7, 3));
    }
}
