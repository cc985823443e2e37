//! A time-major tensor read one step at a time by a loop, without candle's quadratic backward.
//!
//! A loop over `T` steps that reads `x_t = x.get(t)` of a tracked `[T, …]` tensor `x` costs, in
//! candle's backward pass, a zero-padded copy of the whole of `x` and a whole-size addition per
//! step: `O(T²)` over the loop (a tenth of the world model's step at `T = 64`). [`TimeRows`]
//! gives the loop each `x_t` as a graph leaf of its own instead, and [`TimeRows::backprop`] sends
//! their gradients `g_t` on into the graph behind `x` in one more backward pass, of the surrogate
//! `⟨x, sg [g_0 … g_{T−1}]⟩`, whose gradient in everything behind `x` is the one `x` would have
//! passed on.

use candle_core::backprop::GradStore;
use candle_core::{Result, Tensor, Var};

/// The steps of a time-major `[T, …]` tensor as separate leaves (see the module doc).
pub(crate) struct TimeRows {
    /// `x`, with the graph that computed it.
    whole: Tensor,
    /// `x_t` as leaves when `x` takes a gradient, else as views of `x`.
    rows: Vec<Tensor>,
}

impl TimeRows {
    /// Cuts `whole` (`[T, …]`) into its `T` steps; copies them only if `whole` is tracked.
    pub(crate) fn new(whole: &Tensor) -> Result<Self> {
        let steps = whole.dim(0)?;
        let tracked = whole.track_op();
        let rows = (0..steps)
            .map(|t| {
                let row = whole.get(t)?;
                if tracked {
                    Ok(Var::from_tensor(&row)?.as_tensor().clone())
                } else {
                    Ok(row)
                }
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            whole: whole.clone(),
            rows,
        })
    }

    /// `x_t`.
    pub(crate) fn get(&self, t: usize) -> &Tensor {
        &self.rows[t]
    }

    /// Adds to `grads` (a backward pass through the loop) the gradients that the steps' own
    /// gradients there pass on into the graph behind `x`; nothing if `x` is not tracked. Steps
    /// without a gradient contribute zero.
    pub(crate) fn backprop(&self, grads: &mut GradStore) -> Result<()> {
        if !self.whole.track_op() {
            return Ok(());
        }
        let step_grads = self
            .rows
            .iter()
            .map(|row| match grads.remove(row) {
                Some(g) => Ok(g),
                None => row.zeros_like(),
            })
            .collect::<Result<Vec<_>>>()?;
        let surrogate = self.whole.mul(&Tensor::stack(&step_grads, 0)?)?.sum_all()?;
        let behind = surrogate.backward()?;
        for id in behind.get_ids().copied().collect::<Vec<_>>() {
            let Some(g) = behind.get_id(id) else {
                continue;
            };
            let sum = match grads.get_id(id) {
                Some(existing) => existing.add(g)?,
                None => g.clone(),
            };
            grads.insert_id(id, sum);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, D};

    /// A loop over the steps of `tanh(x W)` through [`TimeRows`] gives `W` the gradient of the
    /// same loop over `get(t)`.
    #[test]
    fn split_steps_pass_the_gradients_of_direct_reads() {
        let dev = &Device::Cpu;
        let w = Var::from_tensor(
            &Tensor::arange(0f32, 12.0, dev)
                .unwrap()
                .affine(0.1, -0.5)
                .unwrap()
                .reshape((4, 3))
                .unwrap(),
        )
        .unwrap();
        let x = Tensor::arange(0f32, 40.0, dev)
            .unwrap()
            .affine(0.05, -1.0)
            .unwrap()
            .reshape((5, 2, 4))
            .unwrap();
        let whole = x.broadcast_matmul(w.as_tensor()).unwrap().tanh().unwrap();
        // a recurrence, so that step t's gradient depends on the later steps
        let run = |read: &dyn Fn(usize) -> Tensor| {
            let mut h = Tensor::zeros((2, 3), candle_core::DType::F32, dev).unwrap();
            for t in 0..5 {
                h = (h.sin().unwrap() + read(t)).unwrap();
            }
            h.sqr().unwrap().sum(D::Minus1).unwrap().sum_all().unwrap()
        };
        let direct = run(&|t| whole.get(t).unwrap()).backward().unwrap();
        let rows = TimeRows::new(&whole).unwrap();
        let loss = run(&|t| rows.get(t).clone());
        let mut split = loss.backward().unwrap();
        assert!(split.get(w.as_tensor()).is_none());
        rows.backprop(&mut split).unwrap();
        let flat = |g: &GradStore| -> Vec<f32> {
            g.get(w.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        let (want, got) = (flat(&direct), flat(&split));
        assert!(want.iter().any(|v| v.abs() > 1e-3), "{want:?}");
        for (a, b) in got.iter().zip(&want) {
            assert!(
                (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                "{got:?} vs {want:?}"
            );
        }
    }

    /// An untracked tensor is read as views and adds no gradient.
    #[test]
    fn untracked_tensors_are_views() {
        let x = Tensor::ones((3, 2), candle_core::DType::F32, &Device::Cpu).unwrap();
        let rows = TimeRows::new(&x).unwrap();
        assert!(!rows.get(1).is_variable());
        let loss = (rows.get(0) * 2.0).unwrap().sum_all().unwrap();
        let mut grads = loss.backward().unwrap();
        let before = grads.get_ids().count();
        rows.backprop(&mut grads).unwrap();
        assert_eq!(grads.get_ids().count(), before);
    }
}
