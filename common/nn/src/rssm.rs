//! The RSSM on plain buffers: the imagination step, frozen (its backward pass gives the
//! gradients of the state and the action, none of its weights), and the observation loop over a
//! batch of sequences, trained (the world model's).
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
//!
//! An observation step is the same sequence model from the previous posterior state (the initial
//! state, and a zero action, where a sequence starts anew: zeros, or the learned `h_0 = tanh(w)`
//! and `z_0` the mode of the prior `p(z | h_0)` with its gradient straight through `ln p`), then
//! the posterior
//! `l = SiLU(LN([h', e] W_qᵀ)) W_rᵀ + b_r` of the observation's embedding `e` instead of the
//! prior. Backward, its steps from the last to the first pass `∂h` and `∂z` on to the step
//! before and `∂e` to the encoder; the layers' weight gradients are one product each over all
//! the steps' rows at the end, not one thin product per step.

use super::layer::{InputGrad, Layer, LayerGrads, Mlp, MlpGrads, MlpTrace};
use super::parameters::{update_each, NamedTensor, Parameters};
use super::weights::{Weights, WeightsError};
use crate::kernels::{gru_rows, gru_rows_bwd, probs_rows_bwd, sample_rows, NormAct, Unimix};
use crate::sized;
use std::ops::Range;

/// Sizes of the RSSM.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RssmConfig {
    /// GRU state size.
    pub deter: usize,
    /// Hidden layer size.
    pub hidden: usize,
    /// Number of categorical variables.
    pub stoch: usize,
    /// Classes per variable.
    pub classes: usize,
    /// Uniform mixture weight of the categorical probabilities.
    pub unimix: f64,
    /// Action size.
    pub act_dim: usize,
    /// Observation embedding size.
    pub embed_dim: usize,
    /// Context size fed to the sequence model (0 for DreamerV3, 2 for cRSSM and cMask).
    pub context_dim: usize,
    /// Sequences start from a learned state ([`Rssm::initial_state`]) rather than from zeros.
    pub learned_initial: bool,
}

/// DreamerV3's recurrent state-space model with the cRSSM context input (see the module doc).
#[derive(Clone, Debug)]
pub struct Rssm {
    pub(super) cfg: RssmConfig,
    pub(super) img_in: Layer,
    pub(super) gates: Layer,
    /// The prior's hidden and output layers.
    pub(super) prior: Mlp,
    pub(super) post: Layer,
    pub(super) post_out: Layer,
    /// The learned initial state's `w` (`[D]`), if sequences start from it.
    pub(super) initial_w: Option<Vec<f32>>,
    /// The name of `initial_w` (empty for a model copied from the tests' candle oracle).
    pub(super) initial_name: String,
}

/// The gradients of a [`Rssm`]'s parameters.
#[derive(Clone, Debug)]
pub struct RssmGrads {
    img_in: LayerGrads,
    gates: LayerGrads,
    /// The prior's (which the world model runs as a [`Mlp`], [`Rssm::prior`]).
    pub prior: MlpGrads,
    post: LayerGrads,
    post_out: LayerGrads,
    /// The learned initial state's `w` (`[D]`; empty without one).
    initial_w: Vec<f32>,
}

impl Parameters for Rssm {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        let mut tensors: Vec<_> = self
            .layers()
            .into_iter()
            .flat_map(|l| l.tensors())
            .collect();
        if let Some(w) = &self.initial_w {
            tensors.push(NamedTensor {
                name: &self.initial_name,
                shape: vec![w.len()],
                values: w,
            });
        }
        tensors
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        let (prior, prior_out) = match self.prior.layers.as_mut_slice() {
            [prior, prior_out] => (prior, prior_out),
            _ => return,
        };
        let layers = [
            &mut self.img_in,
            &mut self.gates,
            prior,
            prior_out,
            &mut self.post,
            &mut self.post_out,
        ];
        let first: usize = layers.iter().map(|l| l.tensors().len()).sum();
        update_each(layers.map(|l| l as &mut dyn Parameters), f);
        if let Some(w) = &mut self.initial_w {
            f(first, w);
        }
    }
}

impl RssmGrads {
    /// The gradients of `rssm`'s tensors in the order of [`Parameters::tensors`].
    pub fn into_tensors(self, rssm: &Rssm) -> Vec<Vec<f32>> {
        let mut out = Vec::new();
        let mut prior = self.prior.layers.into_iter();
        let grads = [
            Some(self.img_in),
            Some(self.gates),
            prior.next(),
            prior.next(),
        ]
        .into_iter()
        .chain([Some(self.post), Some(self.post_out)]);
        for (g, layer) in grads.zip(rssm.layers()) {
            match g {
                Some(g) => g.push_tensors(layer, &mut out),
                None => out.extend(layer.tensors().iter().map(|_| Vec::new())),
            }
        }
        if rssm.initial_w.is_some() {
            out.push(self.initial_w);
        }
        out
    }

    /// `self += other` (the same model's).
    pub fn add(&mut self, other: &Self) {
        self.img_in.add(&other.img_in);
        self.gates.add(&other.gates);
        self.prior.add(&other.prior);
        self.post.add(&other.post);
        self.post_out.add(&other.post_out);
        for (a, b) in self.initial_w.iter_mut().zip(&other.initial_w) {
            *a += b;
        }
    }
}

/// The sequence model's buffers over some rows: from `[z, a, c]` and `h` to `h'`, and back.
#[derive(Debug, Default)]
struct SequenceTrace {
    /// `[z, a, c]` `[rows, Z + A + c]` and `h` `[rows, D]`, the inputs.
    input: Vec<f32>,
    h_prev: Vec<f32>,
    in_product: Vec<f32>,
    /// `u` `[rows, hidden]`.
    in_output: Vec<f32>,
    /// `[u, h]` `[rows, hidden + D]`.
    gru_input: Vec<f32>,
    gate_product: Vec<f32>,
    /// `g` `[rows, 3 D]`.
    gates: Vec<f32>,
    /// `h'` `[rows, D]`.
    h: Vec<f32>,
    /// Backward: the two products' gradients.
    d_in_product: Vec<f32>,
    d_gate_product: Vec<f32>,
}

/// What one imagination step over `N` rows keeps for its backward pass.
#[derive(Debug, Default)]
pub struct StepTrace {
    sequence: SequenceTrace,
    prior_product: Vec<f32>,
    prior_output: Vec<f32>,
    /// The prior's logits `[N, Z]` and the sample `z'`.
    logits: Vec<f32>,
    z_next: Vec<f32>,
}

/// The observation loop's buffers over `T` steps of `B` sequences, time-major (step `t` is the
/// rows `t B … (t + 1) B − 1`), kept from one training step to the next.
#[derive(Debug, Default)]
pub struct ObserveTrace {
    /// The sequence model over all the steps (`h_prev` zeroed where a sequence starts).
    sequence: SequenceTrace,
    /// The posterior samples `z'` `[T B, Z]` and logits `[T B, Z]`.
    z: Vec<f32>,
    logits: Vec<f32>,
    /// `[h', e]`.
    post_input: Vec<f32>,
    post_product: Vec<f32>,
    post_output: Vec<f32>,
    /// Backward: the posterior's products' gradients of every step, for the weights' at the end.
    d_post_product: Vec<f32>,
    d_logits: Vec<f32>,
    scratch: StepScratch,
    /// The state the sequences start from.
    initial: InitialTrace,
}

/// The initial state of an observation loop and its backward pass.
#[derive(Debug, Default)]
struct InitialTrace {
    /// `h_0` `[D]` and `z_0` `[Z]` (zeros without a learned state).
    h: Vec<f32>,
    z: Vec<f32>,
    /// The prior on `h_0` (a learned state's).
    prior: MlpTrace,
    /// Backward: `∂h_0` and `∂z_0`, summed over the rows that start from them, and `∂l_0`.
    dh: Vec<f32>,
    dz: Vec<f32>,
    dl: Vec<f32>,
}

/// The backward passes' buffers of a [`Rssm`] step, reused from step to step.
#[derive(Debug, Default)]
pub struct StepScratch {
    dz: Vec<f32>,
    dl: Vec<f32>,
    d_hidden: Vec<f32>,
    d_product: Vec<f32>,
    dh: Vec<f32>,
    d_gates: Vec<f32>,
    dh_direct: Vec<f32>,
    du: Vec<f32>,
}

impl Rssm {
    /// The model of `cfg` from its layers `[img_in, gates, prior, prior_out, post, post_out]`
    /// (the GRU's gates, the prior's and the posterior's hidden and output layers) and, with a
    /// learned initial state, its `w`; its initial state unnamed (as the tests' oracle copies a
    /// model from its candle module).
    pub fn from_layers(
        cfg: RssmConfig,
        [img_in, gates, prior, prior_out, post, post_out]: [Layer; 6],
        initial_w: Option<Vec<f32>>,
    ) -> Self {
        Self {
            cfg,
            img_in,
            gates,
            prior: Mlp::from_layers(vec![prior, prior_out]),
            post,
            post_out,
            initial_w,
            initial_name: String::new(),
        }
    }

    /// The model of `cfg` read from `weights` under the names the checkpoints give its
    /// parameters, after `prefix` (`"rssm."`): `img_in`, `gru`, `prior`, `post` (each `fc`
    /// and `ln`), `prior_out`, `post_out` and, with a learned initial state, `initial_state.w`.
    pub fn from_weights(
        weights: &mut Weights,
        prefix: &str,
        cfg: RssmConfig,
    ) -> std::result::Result<Self, WeightsError> {
        let z = cfg.stoch * cfg.classes;
        let mut block = |name: &str, size, act| {
            Layer::normalised_from_weights(weights, &format!("{prefix}{name}"), size, act)
        };
        let silu = NormAct::Silu;
        let img_in = block(
            "img_in",
            (z + cfg.act_dim + cfg.context_dim, cfg.hidden),
            silu,
        )?
        .sparse_inputs(0..z);
        let gates = block(
            "gru",
            (cfg.hidden + cfg.deter, 3 * cfg.deter),
            NormAct::Identity,
        )?;
        let prior = block("prior", (cfg.deter, cfg.hidden), silu)?;
        let post = block("post", (cfg.deter + cfg.embed_dim, cfg.hidden), silu)?;
        let mut linear = |name: &str| {
            Layer::linear_from_weights(weights, &format!("{prefix}{name}"), (cfg.hidden, z))
        };
        let (prior_out, post_out) = (linear("prior_out")?, linear("post_out")?);
        let initial_name = format!("{prefix}initial_state.w");
        let initial_w = match cfg.learned_initial {
            true => Some(weights.take(&initial_name, &[cfg.deter])?),
            false => None,
        };
        Ok(Self {
            cfg,
            img_in,
            gates,
            prior: Mlp {
                layers: vec![prior, prior_out],
            },
            post,
            post_out,
            initial_w,
            initial_name,
        })
    }

    /// Its layers in the order of [`Parameters::tensors`]: `[img_in, gates, prior, prior_out,
    /// post, post_out]` (the sequence model's input and GRU gates, the prior's and the
    /// posterior's hidden and output layers; the module doc's `W_in`, `W_g`, `W_p`, `W_o`,
    /// `W_q`, `W_r`).
    pub fn layers(&self) -> [&Layer; 6] {
        let [prior, prior_out] = [&self.prior.layers[0], &self.prior.layers[1]];
        let (img_in, gates, post, post_out) =
            (&self.img_in, &self.gates, &self.post, &self.post_out);
        [img_in, gates, prior, prior_out, post, post_out]
    }

    /// The prior's logits from `h` as a network of two layers (hidden, output).
    pub fn prior(&self) -> &Mlp {
        &self.prior
    }

    /// Zeroed gradients of the parameters.
    pub fn zero_grads(&self) -> RssmGrads {
        RssmGrads {
            img_in: self.img_in.zero_grads(),
            gates: self.gates.zero_grads(),
            prior: self.prior.zero_grads(),
            post: self.post.zero_grads(),
            post_out: self.post_out.zero_grads(),
            initial_w: vec![0.0; self.initial_w.as_ref().map_or(0, Vec::len)],
        }
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

    /// Sizes `t` for `rows` rows.
    fn fit(&self, t: &mut SequenceTrace, rows: usize) {
        let (d, z, c) = self.widths();
        let (a, hidden) = (self.cfg.act_dim, self.cfg.hidden);
        for (v, width) in [
            (&mut t.input, z + a + c),
            (&mut t.h_prev, d),
            (&mut t.in_product, hidden),
            (&mut t.in_output, hidden),
            (&mut t.gru_input, hidden + d),
            (&mut t.gate_product, 3 * d),
            (&mut t.gates, 3 * d),
            (&mut t.h, d),
            (&mut t.d_in_product, hidden),
            (&mut t.d_gate_product, 3 * d),
        ] {
            sized(v, rows * width);
        }
    }

    /// The sequence model on the rows `r` of `t` (whose `input` and `h_prev` are set): `h'`.
    fn sequence_forward(&self, t: &mut SequenceTrace, r: Range<usize>) {
        let (d, hidden) = (self.cfg.deter, self.cfg.hidden);
        let span = |w: usize| r.start * w..r.end * w;
        let k = self.img_in.inputs();
        self.img_in.forward(
            &t.input[span(k)],
            &mut t.in_product[span(hidden)],
            &mut t.in_output[span(hidden)],
        );
        let parts = t.in_output[span(hidden)]
            .chunks_exact(hidden)
            .zip(t.h_prev[span(d)].chunks_exact(d));
        for ((u, h), row) in parts.zip(t.gru_input[span(hidden + d)].chunks_exact_mut(hidden + d)) {
            row[..hidden].copy_from_slice(u);
            row[hidden..].copy_from_slice(h);
        }
        self.gates.forward(
            &t.gru_input[span(hidden + d)],
            &mut t.gate_product[span(3 * d)],
            &mut t.gates[span(3 * d)],
        );
        gru_rows(
            &t.gates[span(3 * d)],
            &t.h_prev[span(d)],
            &mut t.h[span(d)],
            d,
        );
    }

    /// The backward pass of [`Rssm::sequence_forward`] on the rows `r` from `∂h'` (`dh`,
    /// those rows'): the products' gradients into `t`, the normalisations' added to `dnorm`
    /// (gates, input layer), and the GRU's direct `∂h` (not yet through its gates' product:
    /// [`Rssm::add_previous_grads`]) in `s.dh_direct`.
    fn sequence_backward(
        &self,
        t: &mut SequenceTrace,
        r: Range<usize>,
        dh: &[f32],
        (dnorm_gates, dnorm_in): (&mut [f32], &mut [f32]),
        s: &mut StepScratch,
    ) {
        let (d, hidden) = (self.cfg.deter, self.cfg.hidden);
        let (span, n) = (|w: usize| r.start * w..r.end * w, r.len());
        gru_rows_bwd(
            &t.gates[span(3 * d)],
            &t.h_prev[span(d)],
            dh,
            sized(&mut s.d_gates, n * 3 * d),
            sized(&mut s.dh_direct, n * d),
            d,
        );
        self.gates.product_grad(
            (&t.gate_product[span(3 * d)], &t.gates[span(3 * d)]),
            &s.d_gates,
            dnorm_gates,
            &mut t.d_gate_product[span(3 * d)],
        );
        let du = sized(&mut s.du, n * hidden);
        self.gates
            .input_grad(&t.d_gate_product[span(3 * d)], 0..hidden, du, hidden, false);
        self.img_in.product_grad(
            (&t.in_product[span(hidden)], &t.in_output[span(hidden)]),
            &s.du,
            dnorm_in,
            &mut t.d_in_product[span(hidden)],
        );
    }

    /// The previous state's gradients from the rows `r` of `t` after
    /// [`Rssm::sequence_backward`]: `∂h` into `s.dh_direct` (its direct part plus the
    /// gates' product's) and `∂z` into `s.dz`.
    fn add_previous_grads(&self, t: &SequenceTrace, r: Range<usize>, s: &mut StepScratch) {
        let (d, z, _) = self.widths();
        let (hidden, n) = (self.cfg.hidden, r.len());
        let span = |w: usize| r.start * w..r.end * w;
        let dgp = &t.d_gate_product[span(3 * d)];
        self.gates
            .input_grad(dgp, hidden..hidden + d, &mut s.dh_direct, d, true);
        let dz = sized(&mut s.dz, n * z);
        self.img_in
            .input_grad(&t.d_in_product[span(hidden)], 0..z, dz, z, false);
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
        let seq = &mut trace.sequence;
        self.fit(seq, n);
        let rows = state.chunks_exact(f).zip(action.chunks_exact(a));
        let inputs = seq
            .input
            .chunks_exact_mut(z + a + c)
            .zip(seq.h_prev.chunks_exact_mut(d));
        for ((s, act), (inp, h)) in rows.zip(inputs) {
            inp[..z].copy_from_slice(&s[d..d + z]);
            inp[z..z + a].copy_from_slice(act);
            inp[z + a..].copy_from_slice(&s[d + z..]);
            h.copy_from_slice(&s[..d]);
        }
        self.sequence_forward(seq, 0..n);
        let [prior, prior_out] = [&self.prior.layers[0], &self.prior.layers[1]];
        prior.forward(
            &seq.h,
            sized(&mut trace.prior_product, n * hidden),
            sized(&mut trace.prior_output, n * hidden),
        );
        prior_out.forward(
            &trace.prior_output,
            sized(&mut trace.logits, n * z),
            &mut [],
        );
        let z_next = sized(&mut trace.z_next, n * z);
        z_next.fill(0.0);
        sample_rows(self.unimix(), &trace.logits, uniform, z_next);
        let rows = next.chunks_exact_mut(f).zip(state.chunks_exact(f));
        let parts = trace
            .sequence
            .h
            .chunks_exact(d)
            .zip(trace.z_next.chunks_exact(z));
        for ((row, s), (h, zr)) in rows.zip(parts) {
            row[..d].copy_from_slice(h);
            row[d..d + z].copy_from_slice(zr);
            row[d + z..].copy_from_slice(&s[d + z..]);
        }
    }

    /// The backward pass of [`Rssm::step`] from the gradients `d_next` of the next state
    /// rows (`[N, D + Z + c]`, the context's ignored): the action's gradient into `d_action`
    /// (`[N, A]`) and, if given, the state's (`h` and `z`) added to `d_state`.
    pub fn step_backward(
        &self,
        trace: &mut StepTrace,
        d_next: &[f32],
        d_action: &mut [f32],
        d_state: Option<&mut [f32]>,
        s: &mut StepScratch,
    ) {
        let (d, z, c) = self.widths();
        let (a, hidden, f) = (self.cfg.act_dim, self.cfg.hidden, d + z + c);
        let n = d_next.len() / f;
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
        let [prior, prior_out] = [&self.prior.layers[0], &self.prior.layers[1]];
        let d_hidden = sized(&mut s.d_hidden, n * hidden);
        prior_out.input_grad(&s.dl, 0..hidden, d_hidden, hidden, false);
        prior.product_grad(
            (&trace.prior_product, &trace.prior_output),
            &s.d_hidden,
            &mut [],
            sized(&mut s.d_product, n * hidden),
        );
        prior.input_grad(&s.d_product, 0..d, &mut s.dh, d, true);
        // the sequence model, then ∂a (and ∂h, ∂z) through its input
        // the normalisations are frozen: no gradients of their parameters
        let dh = std::mem::take(&mut s.dh);
        self.sequence_backward(&mut trace.sequence, 0..n, &dh, (&mut [], &mut []), s);
        s.dh = dh;
        let seq = &trace.sequence;
        self.img_in
            .input_grad(&seq.d_in_product, z..z + a, d_action, a, false);
        if let Some(d_state) = d_state {
            self.add_previous_grads(seq, 0..n, s);
            for ((row, dh), dz) in d_state
                .chunks_exact_mut(f)
                .zip(s.dh_direct.chunks_exact(d))
                .zip(s.dz.chunks_exact(z))
            {
                row[..d].iter_mut().zip(dh).for_each(|(o, v)| *o += v);
                row[d..d + z].iter_mut().zip(dz).for_each(|(o, v)| *o += v);
            }
        }
    }

    /// The observation loop over `T = keep.len() / B` steps of `B` sequences, every input
    /// time-major: the embeddings `[T B, E]`, the previous actions `[T B, A]`, the contexts
    /// `[T B, c]`, `keep` `[T B]` (0 where a sequence starts: the previous state and action are
    /// zeroed) and the Gumbel uniforms `[T B, Z]`; from zeros. The posterior states and logits
    /// are [`ObserveTrace::states`].
    pub fn observe(
        &self,
        batch: usize,
        (embed, action, ctx, keep): (&[f32], &[f32], &[f32], &[f32]),
        uniform: &[f32],
        trace: &mut ObserveTrace,
    ) {
        let (d, z, c) = self.widths();
        let (a, e) = (self.cfg.act_dim, self.cfg.embed_dim);
        let rows = keep.len();
        let tr = trace;
        self.fit_observe(tr, rows);
        self.initial_forward(&mut tr.initial);
        let k = z + a + c;
        for t in 0..rows / batch.max(1) {
            let r = t * batch..(t + 1) * batch;
            // the previous state and action, the initial state and a zero action where a
            // sequence starts
            let seq = &mut tr.sequence;
            let init = &tr.initial;
            for row in r.clone() {
                let keep_row = if t == 0 { 0.0 } else { keep[row] };
                let prev = row.saturating_sub(batch);
                let blend = |dst: &mut [f32], src: &[f32], start: &[f32]| {
                    for ((o, &v), &v0) in dst.iter_mut().zip(src).zip(start) {
                        *o = keep_row * v + (1.0 - keep_row) * v0;
                    }
                };
                let (h_all, z_all) = (&seq.h, &tr.z);
                let h_prev = &mut seq.h_prev[row * d..(row + 1) * d];
                blend(h_prev, &h_all[prev * d..(prev + 1) * d], &init.h);
                let input = &mut seq.input[row * k..(row + 1) * k];
                blend(&mut input[..z], &z_all[prev * z..(prev + 1) * z], &init.z);
                let act = &action[row * a..(row + 1) * a];
                for (o, &v) in input[z..z + a].iter_mut().zip(act) {
                    *o = keep_row * v;
                }
                input[z + a..].copy_from_slice(&ctx[row * c..(row + 1) * c]);
            }
            self.posterior_forward(tr, &embed[r.start * e..r.end * e], uniform, r);
        }
    }

    /// Sizes `tr` for an observation loop over `rows` rows.
    fn fit_observe(&self, tr: &mut ObserveTrace, rows: usize) {
        let (d, z, _) = self.widths();
        let (hidden, e) = (self.cfg.hidden, self.cfg.embed_dim);
        self.fit(&mut tr.sequence, rows);
        for (v, width) in [
            (&mut tr.z, z),
            (&mut tr.logits, z),
            (&mut tr.post_input, d + e),
            (&mut tr.post_product, hidden),
            (&mut tr.post_output, hidden),
        ] {
            sized(v, rows * width);
        }
    }

    /// The posterior step on the rows `r` of `tr`, whose sequence model's inputs are set: `h'`,
    /// the posterior's logits of `[h', e]` (`embed`, those rows') and its samples with the
    /// Gumbel uniforms of those rows in `uniform` (all the rows').
    fn posterior_forward(
        &self,
        tr: &mut ObserveTrace,
        embed: &[f32],
        uniform: &[f32],
        r: Range<usize>,
    ) {
        let (d, z, _) = self.widths();
        let (hidden, e) = (self.cfg.hidden, self.cfg.embed_dim);
        let span = |w: usize| r.start * w..r.end * w;
        let seq = &mut tr.sequence;
        self.sequence_forward(seq, r.clone());
        let parts = seq.h[span(d)].chunks_exact(d).zip(embed.chunks_exact(e));
        for ((h, er), row) in parts.zip(tr.post_input[span(d + e)].chunks_exact_mut(d + e)) {
            row[..d].copy_from_slice(h);
            row[d..].copy_from_slice(er);
        }
        self.post.forward(
            &tr.post_input[span(d + e)],
            &mut tr.post_product[span(hidden)],
            &mut tr.post_output[span(hidden)],
        );
        self.post_out.forward(
            &tr.post_output[span(hidden)],
            &mut tr.logits[span(z)],
            &mut [],
        );
        let z_rows = &mut tr.z[span(z)];
        z_rows.fill(0.0);
        sample_rows(
            self.unimix(),
            &tr.logits[span(z)],
            &uniform[span(z)],
            z_rows,
        );
    }

    /// The state a sequence starts from, `(h_0, z_0)` (`[D]`, `[Z]`), into `trace`: zeros, or
    /// the learned `h_0 = tanh(w)` and `z_0` the one-hot mode of the prior `p(z | h_0)`.
    pub fn initial_state<'a>(&self, trace: &'a mut ObserveTrace) -> (&'a [f32], &'a [f32]) {
        self.initial_forward(&mut trace.initial);
        (&trace.initial.h, &trace.initial.z)
    }

    /// One observation step of one sequence (acting, batch 1): from the previous state `h`
    /// `[D]` and `z` `[Z]`, the previous action `[A]`, the context `[c]`, the observation's
    /// embedding `[E]` and the Gumbel uniforms `[Z]`, the posterior state `(h', z')` and its
    /// logits ([`ObserveTrace::states`], one row), as [`Rssm::observe`] computes a step.
    pub fn posterior_step(
        &self,
        (h, z): (&[f32], &[f32]),
        (action, ctx, embed): (&[f32], &[f32], &[f32]),
        uniform: &[f32],
        trace: &mut ObserveTrace,
    ) {
        let (d, zw, c) = self.widths();
        self.fit_observe(trace, 1);
        let seq = &mut trace.sequence;
        seq.h_prev.copy_from_slice(&h[..d]);
        let input = &mut seq.input;
        input[..zw].copy_from_slice(&z[..zw]);
        input[zw..zw + action.len()].copy_from_slice(action);
        input[zw + action.len()..].copy_from_slice(&ctx[..c]);
        self.posterior_forward(trace, embed, uniform, 0..1);
    }

    /// The backward pass of [`Rssm::observe`] from the gradients of the posterior states,
    /// `dh` `[T B, D]` and `dz` `[T B, Z]` (both used up: the loop adds the later steps' to the
    /// earlier ones'), and `d_logits` `[T B, Z]` of the posterior logits directly (the KL
    /// terms'): the embeddings' gradients into `d_embed` `[T B, E]`, the parameters' added to
    /// `grads` (the prior's only through a learned initial state).
    #[allow(clippy::too_many_arguments)]
    pub fn observe_backward(
        &self,
        batch: usize,
        keep: &[f32],
        trace: &mut ObserveTrace,
        (dh, dz): (&mut [f32], &mut [f32]),
        d_logits: &[f32],
        d_embed: &mut [f32],
        grads: &mut RssmGrads,
    ) {
        let (d, z, _) = self.widths();
        let (hidden, e) = (self.cfg.hidden, self.cfg.embed_dim);
        let rows = keep.len();
        let tr = trace;
        sized(&mut tr.d_post_product, rows * hidden);
        sized(&mut tr.d_logits, rows * z);
        let s = &mut tr.scratch;
        let learned = self.initial_w.is_some();
        let init = &mut tr.initial;
        sized(&mut init.dh, if learned { d } else { 0 }).fill(0.0);
        sized(&mut init.dz, if learned { z } else { 0 }).fill(0.0);
        for t in (0..rows / batch.max(1)).rev() {
            let r = t * batch..(t + 1) * batch;
            let span = |w: usize| r.start * w..r.end * w;
            // the posterior: ∂l (straight through, and the KL terms'), then its layers
            let dl = &mut tr.d_logits[span(z)];
            probs_rows_bwd(self.unimix(), &tr.logits[span(z)], &dz[span(z)], dl);
            dl.iter_mut()
                .zip(&d_logits[span(z)])
                .for_each(|(o, &v)| *o += v);
            let d_out = sized(&mut s.d_hidden, batch * hidden);
            self.post_out
                .input_grad(&tr.d_logits[span(z)], 0..hidden, d_out, hidden, false);
            self.post.product_grad(
                (
                    &tr.post_product[span(hidden)],
                    &tr.post_output[span(hidden)],
                ),
                &s.d_hidden,
                grads.post.norm_mut(),
                &mut tr.d_post_product[span(hidden)],
            );
            let dpp = &tr.d_post_product[span(hidden)];
            self.post.input_grad(dpp, 0..d, &mut dh[span(d)], d, true);
            self.post
                .input_grad(dpp, d..d + e, &mut d_embed[span(e)], e, false);
            // the sequence model, then the previous state's gradients where the step read it
            let norms = (grads.gates.norm_mut(), grads.img_in.norm_mut());
            self.sequence_backward(&mut tr.sequence, r.clone(), &dh[span(d)], norms, s);
            if t == 0 && !learned {
                continue;
            }
            // the previous state's gradients: the previous step's, and the initial state's
            // where the step started from it
            self.add_previous_grads(&tr.sequence, r.clone(), s);
            let add = |dst: &mut [f32], src: &[f32], k: f32| {
                dst.iter_mut().zip(src).for_each(|(o, &v)| *o += k * v);
            };
            for i in 0..batch {
                let (dh_i, dz_i) = (&s.dh_direct[i * d..(i + 1) * d], &s.dz[i * z..(i + 1) * z]);
                let k = if t == 0 { 0.0 } else { keep[r.start + i] };
                if t > 0 {
                    let row = r.start - batch + i;
                    add(&mut dh[row * d..(row + 1) * d], dh_i, k);
                    add(&mut dz[row * z..(row + 1) * z], dz_i, k);
                }
                if learned {
                    add(&mut init.dh, dh_i, 1.0 - k);
                    add(&mut init.dz, dz_i, 1.0 - k);
                }
            }
        }
        self.initial_backward(init, grads);
        // the weights' gradients, one product per layer over all the steps
        let seq = &tr.sequence;
        self.img_in
            .add_weight_grads(&seq.input, &seq.d_in_product, &mut grads.img_in);
        self.gates
            .add_weight_grads(&seq.gru_input, &seq.d_gate_product, &mut grads.gates);
        self.post
            .add_weight_grads(&tr.post_input, &tr.d_post_product, &mut grads.post);
        self.post_out
            .add_weight_grads(&tr.post_output, &tr.d_logits, &mut grads.post_out);
    }
}

impl Rssm {
    /// The initial state into `init`: zeros, or the learned `h_0 = tanh(w)` and `z_0` the
    /// one-hot mode of the prior `p(z | h_0)` (the first most likely class of each variable).
    fn initial_forward(&self, init: &mut InitialTrace) {
        let (d, z, _) = self.widths();
        let (h0, z0) = (sized(&mut init.h, d), sized(&mut init.z, z));
        z0.fill(0.0);
        let Some(w) = &self.initial_w else {
            h0.fill(0.0);
            return;
        };
        h0.iter_mut().zip(w).for_each(|(h, &w)| *h = w.tanh());
        self.prior.fit(&mut init.prior, 1);
        self.prior.forward(&init.h[..], &mut init.prior, 0..1);
        let logits = self.prior.output(&init.prior, 0..1);
        let classes = self.cfg.classes;
        for (l, onehot) in logits
            .chunks_exact(classes)
            .zip(init.z.chunks_exact_mut(classes))
        {
            let best = (1..classes).fold(0, |b, j| if l[j] > l[b] { j } else { b });
            onehot[best] = 1.0;
        }
    }

    /// The learned initial state's backward pass from `∂h_0` and `∂z_0` in `init`: `∂l_0` of
    /// `ln p` (the mode's straight-through path), the prior's parameters' gradients and its
    /// `∂h_0`, then `∂w = ∂h_0 (1 − h_0²)`; nothing without a learned state.
    fn initial_backward(&self, init: &mut InitialTrace, grads: &mut RssmGrads) {
        if self.initial_w.is_none() {
            return;
        }
        let (d, z, _) = self.widths();
        let logits = self.prior.output(&init.prior, 0..1);
        log_probs_rows_bwd(self.unimix(), logits, &init.dz, sized(&mut init.dl, z));
        let target = InputGrad::new(&mut init.dh, d, 0..d, true);
        self.prior.backward(
            &init.h[..],
            &mut init.prior,
            0..1,
            &init.dl,
            Some(&mut grads.prior),
            Some(target),
        );
        for ((g, &dh), &h) in grads.initial_w.iter_mut().zip(&init.dh).zip(&init.h) {
            *g += dh * (1.0 - h * h);
        }
    }
}

/// `∂l` from `∂ ln p` (`dlp`) for rows of logits `l` of `classes` values each, `p` the
/// unimix probabilities `(1 − u) softmax(l) + u / C`: with `s = softmax(l)` and
/// `g_j = ∂ln p_j s_j / p_j`, `∂l_k = (1 − u)(g_k − s_k Σ_j g_j)`.
fn log_probs_rows_bwd(dist: Unimix, logits: &[f32], dlp: &[f32], dl: &mut [f32]) {
    let (c, u) = (dist.classes, dist.unimix);
    let mut s = vec![0f32; c];
    let rows = logits
        .chunks_exact(c)
        .zip(dlp.chunks_exact(c))
        .zip(dl.chunks_exact_mut(c));
    for ((l, dlp), out) in rows {
        let max = l.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
        s.iter_mut().zip(l).for_each(|(e, &v)| *e = (v - max).exp());
        let total: f32 = s.iter().sum();
        s.iter_mut().for_each(|e| *e /= total);
        let mut sum_g = 0f32;
        for ((o, &sj), &gj) in out.iter_mut().zip(&s).zip(dlp) {
            *o = gj * sj / ((1.0 - u) * sj + u / c as f32);
            sum_g += *o;
        }
        for (o, &sj) in out.iter_mut().zip(&s) {
            *o = (1.0 - u) * (*o - sj * sum_g);
        }
    }
}

impl ObserveTrace {
    /// The posterior states `(h, z)` (`[T B, D]`, `[T B, Z]`) and logits `[T B, Z]` of the last
    /// [`Rssm::observe`].
    pub fn states(&self) -> (&[f32], &[f32], &[f32]) {
        (&self.sequence.h, &self.z, &self.logits)
    }
}
