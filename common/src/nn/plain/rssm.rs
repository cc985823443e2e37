//! The RSSM's imagination step on plain buffers, frozen: its backward pass gives the gradients
//! of the state and the action, none of its weights.
//!
//! A state row is `[h, z, c]` (`D + Z + c` values: GRU state, one-hot sample, context). One step
//! from `s_t` and the action `a_t`:
//!
//! ```text
//! u = SiLU(LN([z, a, c] W_inᵀ))                    the sequence model's input
//! g = LN([u, h] W_gᵀ),  h' = GRU(g, h)             kernels::gru_gates
//! l = SiLU(LN(h' W_pᵀ)) W_oᵀ + b_o                 the prior's logits
//! z' = onehot(argmax(ln p(l) + Gumbel)),           straight through: ∂l = ∂p/∂l ∂z'
//! ```
//!
//! and backward, from the gradients of `s_{t+1}`: `∂l`, then `∂h'` (its own plus the prior's),
//! the GRU's `∂g` and `∂h`, `∂u` and `∂h` through `W_g`, and `∂z`, `∂a` through `W_in`.

use super::layer::PlainLayer;
use crate::nn::kernels::{gru_rows, gru_rows_bwd, probs_rows_bwd, sample_rows, Unimix};
use crate::nn::{Rssm, RssmConfig};
use candle_core::Result;

/// An RSSM's imagination step, its weights copied out of candle.
#[derive(Clone, Debug)]
pub struct PlainRssm {
    cfg: RssmConfig,
    img_in: PlainLayer,
    gates: PlainLayer,
    prior: PlainLayer,
    prior_out: PlainLayer,
}

/// What one imagination step over `N` rows keeps for its backward pass.
#[derive(Debug, Default)]
pub struct StepTrace {
    /// `[z, a, c]` `[N, Z + A + c]`.
    input: Vec<f32>,
    in_product: Vec<f32>,
    /// `u` `[N, hidden]`.
    in_output: Vec<f32>,
    /// `[u, h]` `[N, hidden + D]`.
    gru_input: Vec<f32>,
    gate_product: Vec<f32>,
    /// `g` `[N, 3 D]`.
    gates: Vec<f32>,
    /// `h` `[N, D]`, and `h'`.
    h: Vec<f32>,
    h_next: Vec<f32>,
    prior_product: Vec<f32>,
    prior_output: Vec<f32>,
    /// `l` `[N, Z]`.
    logits: Vec<f32>,
    /// `z'` `[N, Z]`.
    z_next: Vec<f32>,
}

/// The backward pass's buffers of a [`PlainRssm`] step, reused from step to step.
#[derive(Debug, Default)]
pub struct StepScratch {
    dz: Vec<f32>,
    dl: Vec<f32>,
    d_prior: Vec<f32>,
    dh: Vec<f32>,
    d_gates: Vec<f32>,
    dh_direct: Vec<f32>,
    du: Vec<f32>,
    d_in: Vec<f32>,
    d_norm: Vec<f32>,
}

/// `v` resized to `n` values (zeros where it grows) as a slice.
fn sized(v: &mut Vec<f32>, n: usize) -> &mut [f32] {
    v.resize(n, 0.0);
    &mut v[..n]
}

impl PlainRssm {
    /// The weights of `rssm` as they are now.
    pub fn new(rssm: &Rssm) -> Result<Self> {
        let [img_in, gates, prior, prior_out] = rssm.prior_blocks();
        let layer = |(dense, norm)| PlainLayer::from_parts(dense, norm, false);
        Ok(Self {
            cfg: *rssm.config(),
            img_in: layer(img_in)?,
            gates: layer(gates)?,
            prior: layer(prior)?,
            prior_out: layer(prior_out)?,
        })
    }

    /// The sizes.
    pub fn config(&self) -> &RssmConfig {
        &self.cfg
    }

    /// `(D, Z, c)`: the widths of a state row's parts.
    fn widths(&self) -> (usize, usize, usize) {
        let c = &self.cfg;
        (c.deter, c.stoch * c.classes, c.context_dim)
    }

    /// The distribution of the latents.
    fn unimix(&self) -> Unimix {
        Unimix {
            classes: self.cfg.classes,
            unimix: self.cfg.unimix as f32,
        }
    }

    /// One step from the state rows `state` (`[N, D + Z + c]`) and `action` (`[N, A]`) with
    /// Gumbel uniforms `uniform` (`[N, Z]`): the next state rows into `next` (the context
    /// copied), what the backward pass needs into `trace`.
    pub fn step(
        &self,
        state: &[f32],
        action: &[f32],
        uniform: &[f32],
        trace: &mut StepTrace,
        next: &mut [f32],
    ) {
        let (d, z, c) = self.widths();
        let (a, hidden, f) = (self.cfg.act_dim, self.cfg.hidden, d + z + c);
        let n = state.len() / f;
        let input = sized(&mut trace.input, n * (z + a + c));
        let h = sized(&mut trace.h, n * d);
        let rows = state.chunks_exact(f).zip(action.chunks_exact(a));
        for (((s, act), inp), hr) in rows
            .zip(input.chunks_exact_mut(z + a + c))
            .zip(h.chunks_exact_mut(d))
        {
            inp[..z].copy_from_slice(&s[d..d + z]);
            inp[z..z + a].copy_from_slice(act);
            inp[z + a..].copy_from_slice(&s[d + z..]);
            hr.copy_from_slice(&s[..d]);
        }
        self.img_in.forward(
            &trace.input,
            sized(&mut trace.in_product, n * hidden),
            sized(&mut trace.in_output, n * hidden),
        );
        let gru_input = sized(&mut trace.gru_input, n * (hidden + d));
        let parts = trace
            .in_output
            .chunks_exact(hidden)
            .zip(trace.h.chunks_exact(d));
        for ((u, hr), row) in parts.zip(gru_input.chunks_exact_mut(hidden + d)) {
            row[..hidden].copy_from_slice(u);
            row[hidden..].copy_from_slice(hr);
        }
        self.gates.forward(
            &trace.gru_input,
            sized(&mut trace.gate_product, n * 3 * d),
            sized(&mut trace.gates, n * 3 * d),
        );
        gru_rows(&trace.gates, &trace.h, sized(&mut trace.h_next, n * d), d);
        self.prior.forward(
            &trace.h_next,
            sized(&mut trace.prior_product, n * hidden),
            sized(&mut trace.prior_output, n * hidden),
        );
        self.prior_out.forward(
            &trace.prior_output,
            sized(&mut trace.logits, n * z),
            &mut [],
        );
        let z_next = sized(&mut trace.z_next, n * z);
        z_next.fill(0.0);
        sample_rows(self.unimix(), &trace.logits, uniform, z_next);
        let rows = next.chunks_exact_mut(f).zip(state.chunks_exact(f));
        let parts = trace
            .h_next
            .chunks_exact(d)
            .zip(trace.z_next.chunks_exact(z));
        for ((row, s), (hr, zr)) in rows.zip(parts) {
            row[..d].copy_from_slice(hr);
            row[d..d + z].copy_from_slice(zr);
            row[d + z..].copy_from_slice(&s[d + z..]);
        }
    }

    /// The backward pass of [`PlainRssm::step`] from the gradients `d_next` of the next state
    /// rows (`[N, D + Z + c]`, the context's ignored): the action's gradient into `d_action`
    /// (`[N, A]`) and, if given, the state's (`h` and `z`) added to `d_state`.
    pub fn step_backward(
        &self,
        trace: &StepTrace,
        d_next: &[f32],
        d_action: &mut [f32],
        d_state: Option<&mut [f32]>,
        scratch: &mut StepScratch,
    ) {
        let (d, z, c) = self.widths();
        let (a, hidden, f) = (self.cfg.act_dim, self.cfg.hidden, d + z + c);
        let n = d_next.len() / f;
        let s = scratch;
        // ∂z' and ∂h' of the next state, contiguous
        let dz = sized(&mut s.dz, n * z);
        let dh = sized(&mut s.dh, n * d);
        for ((row, dzr), dhr) in d_next
            .chunks_exact(f)
            .zip(dz.chunks_exact_mut(z))
            .zip(dh.chunks_exact_mut(d))
        {
            dhr.copy_from_slice(&row[..d]);
            dzr.copy_from_slice(&row[d..d + z]);
        }
        probs_rows_bwd(self.unimix(), &trace.logits, &s.dz, sized(&mut s.dl, n * z));
        // the prior: ∂(its hidden output), its product, then ∂h' += … W_p
        self.prior_out.input_grad(
            &s.dl,
            0..hidden,
            sized(&mut s.d_prior, n * hidden),
            hidden,
            false,
        );
        let mut d_product = std::mem::take(&mut s.d_in);
        self.prior.product_grad(
            (&trace.prior_product, &trace.prior_output),
            &s.d_prior,
            sized(&mut s.d_norm, 2 * hidden),
            sized(&mut d_product, n * hidden),
        );
        self.prior.input_grad(&d_product, 0..d, &mut s.dh, d, true);
        // the GRU: ∂g, the direct ∂h, then the gates' product
        gru_rows_bwd(
            &trace.gates,
            &trace.h,
            &s.dh,
            sized(&mut s.d_gates, n * 3 * d),
            sized(&mut s.dh_direct, n * d),
            d,
        );
        let mut d_gate_product = std::mem::take(&mut s.dl);
        self.gates.product_grad(
            (&trace.gate_product, &trace.gates),
            &s.d_gates,
            sized(&mut s.d_norm, 6 * d),
            sized(&mut d_gate_product, n * 3 * d),
        );
        self.gates.input_grad(
            &d_gate_product,
            0..hidden,
            sized(&mut s.du, n * hidden),
            hidden,
            false,
        );
        // the input layer: ∂[z, a, c] = … W_in
        self.img_in.product_grad(
            (&trace.in_product, &trace.in_output),
            &s.du,
            sized(&mut s.d_norm, 2 * hidden),
            sized(&mut d_product, n * hidden),
        );
        self.img_in
            .input_grad(&d_product, z..z + a, d_action, a, false);
        if let Some(d_state) = d_state {
            for (row, dhr) in d_state.chunks_exact_mut(f).zip(s.dh_direct.chunks_exact(d)) {
                row[..d].iter_mut().zip(dhr).for_each(|(o, v)| *o += v);
            }
            self.gates
                .input_grad(&d_gate_product, hidden..hidden + d, d_state, f, true);
            self.img_in
                .input_grad(&d_product, 0..z, &mut d_state[d..], f, true);
        }
        s.d_in = d_product;
        s.dl = d_gate_product;
    }
}
