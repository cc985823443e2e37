//! DreamerV3's squashing and its discrete regression targets.
//!
//! `symlog(x) = sign(x) ln(1 + |x|)` and its inverse `symexp(x) = sign(x)(e^{|x|} − 1)` compress
//! large magnitudes while staying the identity near zero. A scalar `y` is regressed as a
//! distribution over `K` bins `b_k` evenly spaced in symlog space (`K = 255` over `[−20, 20]`): its
//! *two-hot* encoding puts weight on the two bins around `symlog(y)`, in proportion to closeness,
//! `w_k = 1 − |symlog(y) − b_k| / (b_{k+1} − b_k)`; a prediction decodes as
//! `symexp(Σ_k softmax(logits)_k b_k)`.

/// `sign(x) ln(1 + |x|)` of one value (the oracle's `symlog` on candle tensors).
pub fn symlog_value(x: f32) -> f32 {
    x.signum() * x.abs().ln_1p()
}

/// Evenly spaced bins in symlog space.
#[derive(Clone, Debug)]
pub struct TwoHot {
    low: f32,
    high: f32,
    bins: Vec<f32>,
}

impl TwoHot {
    /// DreamerV3's 255 bins over `[−20, 20]`.
    pub fn dreamer() -> Self {
        Self::new(255, -20.0, 20.0)
    }

    /// `count ≥ 2` bins over `[low, high]` (symlog space).
    pub fn new(count: usize, low: f32, high: f32) -> Self {
        let step = (high - low) / (count - 1) as f32;
        let values: Vec<f32> = (0..count).map(|k| low + step * k as f32).collect();
        Self {
            low,
            high,
            bins: values,
        }
    }

    /// Number of bins.
    pub fn count(&self) -> usize {
        self.bins.len()
    }

    /// The bins' values `b_k` (symlog space).
    pub fn bins(&self) -> &[f32] {
        &self.bins
    }

    /// `out_i += scale · twohot(y_i)`: the two-hot encodings of the values `y` (in the original
    /// space), scaled, added to the rows of `out` (`K` values each).
    pub fn add_encoded(&self, y: &[f32], scale: f32, out: &mut [f32]) {
        let k = self.bins.len();
        let step = (self.high - self.low) / (k - 1) as f32;
        for (&v, row) in y.iter().zip(out.chunks_exact_mut(k)) {
            let v = v.signum() * v.abs().ln_1p();
            let pos = ((v.clamp(self.low, self.high) - self.low) / step).min((k - 1) as f32);
            let below = (pos.floor() as usize).min(k - 2);
            let frac = pos - below as f32;
            row[below] += scale * (1.0 - frac);
            row[below + 1] += scale * frac;
        }
    }
}
