//! The oracle's DreamerV3 recurrent state-space model (candle modules), with the cRSSM context
//! input: [`ctxrace_nn::Rssm`] is checked against it.
//!
//! The state is a deterministic part `h_t` (a GRU state) and a stochastic part `z_t`: `S` one-hot
//! categorical variables of `C` classes each.
//! - Sequence model: `h_t = GRU(h_{t−1}, f([z_{t−1}, a_{t−1}, c]))` with
//!   `f = SiLU ∘ LayerNorm ∘ Linear`; the context `c` is cRSSM's (absent for DreamerV3).
//! - Prior `p(z_t | h_t)` and posterior `q(z_t | h_t, e_t)` from the observation embedding `e_t`,
//!   each one hidden layer then logits `[S, C]`, mixed with 1 % uniform (`unimix`).
//! - GRU (DreamerV3's): `[r, ĉ, u] = LN(W [x, h])`, `h' = σ(u − 1) tanh(σ(r) ĉ) + (1 − σ(u − 1)) h`:
//!   the −1 bias makes the cell keep its state by default.
//!
//! Samples use the Gumbel-max trick on noise the caller draws from its own seeded generator, and
//! pass gradients straight through: `z = onehot + p − sg(p)` ([`kernels::straight_through_sample`]).

use super::dense::Dense;
use super::norm::LayerNorm;
use super::params::ParamStore;
use crate::kernels;
use candle_core::{DType, Device, Result, Tensor, D};
use candle_nn::VarBuilder;
use ctxrace_nn::kernels::NormAct;
use ctxrace_nn::RssmConfig;

/// A batch of RSSM states.
#[derive(Clone, Debug)]
pub struct RssmState {
    /// `[B, deter]`.
    pub deter: Tensor,
    /// `[B, stoch · classes]`, one-hot per variable (with straight-through gradients).
    pub stoch: Tensor,
}

impl RssmState {
    /// The same state cut from the graph that computed it: gradients stop here, and the
    /// operations (and tensors) behind it can be freed.
    pub fn detach(&self) -> Self {
        Self {
            deter: self.deter.detach(),
            stoch: self.stoch.detach(),
        }
    }

    /// The model features `[h, z]`, `[B, deter + stoch · classes]`.
    pub fn feat(&self) -> Result<Tensor> {
        Tensor::cat(&[&self.deter, &self.stoch], D::Minus1)
    }

    /// The heads' input `[h, z, c]` (`[h, z]` without a context), in one concatenation.
    pub fn head_input(&self, ctx: Option<&Tensor>) -> Result<Tensor> {
        match ctx {
            Some(c) => Tensor::cat(&[&self.deter, &self.stoch, c], D::Minus1),
            None => self.feat(),
        }
    }
}

/// A `Linear → LayerNorm → act` block (SiLU, or the identity before the GRU's gates).
#[derive(Clone, Debug)]
struct NormBlock {
    fc: Dense,
    ln: LayerNorm,
    act: NormAct,
}

impl NormBlock {
    fn new(input: usize, out: usize, act: NormAct, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            fc: Dense::new(input, out, false, vb.pp("fc"))?,
            ln: LayerNorm::new(out, 1e-3, vb.pp("ln"))?,
            act,
        })
    }

    /// The same block told that its input columns `columns` are mostly zero.
    fn sparse_inputs(self, columns: std::ops::Range<usize>) -> Self {
        Self {
            fc: self.fc.sparse_inputs(columns),
            ..self
        }
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.fc.forward_norm_act(x, &self.ln, self.act)
    }

    fn frozen(&self) -> Self {
        Self {
            fc: self.fc.frozen(),
            ln: self.ln.frozen(),
            act: self.act,
        }
    }
}

/// DreamerV3's GRU cell with a LayerNorm on the gates and update bias −1.
#[derive(Clone, Debug)]
pub struct Gru {
    /// `LN(W [x, h])`, the normalised gates `[r, ĉ, u]` (parameters `fc`, `ln`).
    gates: NormBlock,
}

impl Gru {
    /// A cell from `input` features to a state of `size`.
    pub fn new(input: usize, size: usize, vb: VarBuilder) -> Result<Self> {
        let gates = NormBlock::new(input + size, 3 * size, NormAct::Identity, vb)?;
        Ok(Self { gates })
    }

    /// The next state.
    pub fn forward(&self, x: &Tensor, h: &Tensor) -> Result<Tensor> {
        let parts = self.gates.forward(&Tensor::cat(&[x, h], D::Minus1)?)?;
        kernels::gru_gates(&parts, h)
    }

    /// The same cell on detached (shared) parameters.
    pub fn frozen(&self) -> Self {
        Self {
            gates: self.gates.frozen(),
        }
    }
}

/// The recurrent state-space model.
#[derive(Clone, Debug)]
pub struct Rssm {
    cfg: RssmConfig,
    img_in: NormBlock,
    gru: Gru,
    prior_hidden: NormBlock,
    prior_out: Dense,
    post_hidden: NormBlock,
    post_out: Dense,
    /// The learned initial state's `w` (`[D]`, `h_0 = tanh(w)`), the parameter
    /// `initial_state.w`; `None` where sequences start from zeros.
    initial_w: Option<Tensor>,
}

impl Rssm {
    /// Builds the model under `vb`.
    pub fn new(cfg: RssmConfig, vb: VarBuilder) -> Result<Self> {
        let (z, silu) = (cfg.stoch * cfg.classes, NormAct::Silu);
        Ok(Self {
            img_in: NormBlock::new(
                z + cfg.act_dim + cfg.context_dim,
                cfg.hidden,
                silu,
                vb.pp("img_in"),
            )?
            .sparse_inputs(0..z),
            gru: Gru::new(cfg.hidden, cfg.deter, vb.pp("gru"))?,
            prior_hidden: NormBlock::new(cfg.deter, cfg.hidden, silu, vb.pp("prior"))?,
            prior_out: Dense::new(cfg.hidden, z, true, vb.pp("prior_out"))?,
            post_hidden: NormBlock::new(
                cfg.deter + cfg.embed_dim,
                cfg.hidden,
                silu,
                vb.pp("post"),
            )?,
            post_out: Dense::new(cfg.hidden, z, true, vb.pp("post_out"))?,
            initial_w: match cfg.learned_initial {
                // a vector not named `bias`: [`ParamStore::init`] leaves it at zero
                true => Some(vb.pp("initial_state").get_with_hints(
                    cfg.deter,
                    "w",
                    candle_nn::Init::Const(0.0),
                )?),
                false => None,
            },
            cfg,
        })
    }

    /// The same model on detached (shared) parameters: imagination through it passes gradients
    /// to the states and actions but trains none of its weights.
    pub fn frozen(&self) -> Self {
        Self {
            cfg: self.cfg,
            img_in: self.img_in.frozen(),
            gru: self.gru.frozen(),
            prior_hidden: self.prior_hidden.frozen(),
            prior_out: self.prior_out.frozen(),
            post_hidden: self.post_hidden.frozen(),
            post_out: self.post_out.frozen(),
            initial_w: self.initial_w.as_ref().map(Tensor::detach),
        }
    }

    /// Its blocks, each a layer and its normalisation and activation (none for the output
    /// layers), in order: the input layer (`f` of the sequence model), the GRU's gates, the
    /// prior's hidden and output layers, the posterior's hidden and output layers.
    pub(crate) fn blocks(&self) -> [(&Dense, Option<(&LayerNorm, NormAct)>); 6] {
        fn block(b: &NormBlock) -> (&Dense, Option<(&LayerNorm, NormAct)>) {
            (&b.fc, Some((&b.ln, b.act)))
        }
        [
            block(&self.img_in),
            block(&self.gru.gates),
            block(&self.prior_hidden),
            (&self.prior_out, None),
            block(&self.post_hidden),
            (&self.post_out, None),
        ]
    }

    /// The sizes.
    pub fn config(&self) -> &RssmConfig {
        &self.cfg
    }

    /// The learned initial state's `w` (`[D]`), if sequences start from it.
    pub fn initial_weight(&self) -> Option<&Tensor> {
        self.initial_w.as_ref()
    }

    /// The columns of the one-hot sample `z` in [`RssmState::feat`] and
    /// [`RssmState::head_input`] (`[h, z, …]`): a layer reading either can be told they are
    /// mostly zero ([`super::Mlp::sparse_inputs`]).
    pub fn stoch_columns(&self) -> std::ops::Range<usize> {
        self.cfg.deter..self.cfg.deter + self.cfg.stoch * self.cfg.classes
    }

    /// Size of [`RssmState::feat`].
    pub fn feat_dim(&self) -> usize {
        self.cfg.deter + self.cfg.stoch * self.cfg.classes
    }

    /// The state a batch of sequences starts from: zeros, or the learned state (the paper's
    /// code, `networks.py` `RSSM.initial`): `h = tanh(w)` and `z` the mode of the prior
    /// `p(z | h)`, `onehot(argmax) + ln p − sg(ln p)` (`ln p` of the unimix probabilities, so
    /// that gradients reach `w` and the prior straight through the log-probabilities).
    pub fn initial(&self, batch: usize) -> Result<RssmState> {
        if let Some(w) = &self.initial_w {
            let (d, z) = (self.cfg.deter, self.cfg.stoch * self.cfg.classes);
            let deter = w.tanh()?.unsqueeze(0)?;
            let log_p = self.probs(&self.prior_logits(&deter)?)?.log()?;
            let classes = Tensor::arange(0u32, self.cfg.classes as u32, &Device::Cpu)?
                .reshape((1, 1, self.cfg.classes))?;
            let one_hot = log_p
                .argmax_keepdim(D::Minus1)?
                .broadcast_eq(&classes)?
                .to_dtype(DType::F32)?;
            let stoch = (one_hot + (&log_p - log_p.detach())?)?.reshape((1, z))?;
            return Ok(RssmState {
                deter: deter.broadcast_as((batch, d))?.contiguous()?,
                stoch: stoch.broadcast_as((batch, z))?.contiguous()?,
            });
        }
        Ok(RssmState {
            deter: Tensor::zeros((batch, self.cfg.deter), DType::F32, &Device::Cpu)?,
            stoch: Tensor::zeros(
                (batch, self.cfg.stoch * self.cfg.classes),
                DType::F32,
                &Device::Cpu,
            )?,
        })
    }

    /// The sequence model: `h_t` from the previous state, action and (cRSSM) context.
    pub fn deter_step(
        &self,
        prev: &RssmState,
        action: &Tensor,
        context: Option<&Tensor>,
    ) -> Result<Tensor> {
        let mut parts = vec![&prev.stoch, action];
        if let Some(c) = context {
            parts.push(c);
        }
        let x = self.img_in.forward(&Tensor::cat(&parts, D::Minus1)?)?;
        self.gru.forward(&x, &prev.deter)
    }

    /// Prior logits `[B, S, C]` from `h_t`.
    pub fn prior_logits(&self, deter: &Tensor) -> Result<Tensor> {
        self.unflat(&self.prior_out.forward(&self.prior_hidden.forward(deter)?)?)
    }

    /// Posterior logits `[B, S, C]` from `h_t` and the observation embedding.
    pub fn post_logits(&self, deter: &Tensor, embed: &Tensor) -> Result<Tensor> {
        let x = self
            .post_hidden
            .forward(&Tensor::cat(&[deter, embed], D::Minus1)?)?;
        self.unflat(&self.post_out.forward(&x)?)
    }

    fn unflat(&self, x: &Tensor) -> Result<Tensor> {
        x.reshape((x.dim(0)?, self.cfg.stoch, self.cfg.classes))
    }

    /// Class probabilities `[B, S, C]`: softmax mixed with `unimix` uniform.
    pub fn probs(&self, logits: &Tensor) -> Result<Tensor> {
        let p = candle_nn::ops::softmax(logits, D::Minus1)?;
        let u = self.cfg.unimix;
        (p * (1.0 - u))? + u / self.cfg.classes as f64
    }

    /// A straight-through one-hot sample `[B, S·C]` from logits, with Gumbel noise
    /// `g = −ln(−ln U)` given as uniforms `U ∈ (0, 1)` of shape `[B, S, C]`.
    pub fn sample(&self, logits: &Tensor, uniform: &Tensor) -> Result<Tensor> {
        kernels::straight_through_sample(logits, uniform, self.cfg.unimix)
    }

    /// One observation step: `(posterior state, posterior logits)`. The prior of `h_t` does not
    /// feed the next step, so a sequence's priors are one batched [`Rssm::prior_logits`] after it.
    pub fn obs_step(
        &self,
        prev: &RssmState,
        action: &Tensor,
        context: Option<&Tensor>,
        embed: &Tensor,
        uniform: &Tensor,
    ) -> Result<(RssmState, Tensor)> {
        let deter = self.deter_step(prev, action, context)?;
        let post = self.post_logits(&deter, embed)?;
        let stoch = self.sample(&post, uniform)?;
        Ok((RssmState { deter, stoch }, post))
    }

    /// `KL(p_a ‖ p_b)` per batch element, summed over the variables, from logits `[B, S, C]`.
    pub fn kl(&self, logits_a: &Tensor, logits_b: &Tensor) -> Result<Tensor> {
        kernels::categorical_kl(logits_a, logits_b, self.cfg.unimix)
    }
}

/// Builds an RSSM in a fresh store initialised from `seed` (for tests and tools).
pub fn standalone(cfg: RssmConfig, seed: u64) -> Result<(ParamStore, Rssm)> {
    let ps = ParamStore::new();
    let rssm = Rssm::new(cfg, ps.builder().pp("rssm"))?;
    ps.init(seed)?;
    Ok((ps, rssm))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(context_dim: usize) -> RssmConfig {
        RssmConfig {
            deter: 8,
            hidden: 8,
            stoch: 3,
            classes: 4,
            unimix: 0.01,
            act_dim: 2,
            embed_dim: 5,
            context_dim,
            learned_initial: false,
        }
    }

    /// Checkpoints name the parameters, and [`ParamStore::init`] draws them in name order: the
    /// names and shapes are the ones every saved run has.
    #[test]
    fn parameter_names_are_those_of_saved_checkpoints() {
        let (ps, _) = standalone(cfg(2), 0).unwrap();
        let names: Vec<(String, Vec<usize>)> = ps
            .named()
            .into_iter()
            .map(|(n, v)| (n, v.dims().to_vec()))
            .collect();
        let want = [
            ("rssm.gru.fc.weight", vec![24, 16]),
            ("rssm.gru.ln.bias", vec![24]),
            ("rssm.gru.ln.weight", vec![24]),
            ("rssm.img_in.fc.weight", vec![8, 16]),
            ("rssm.img_in.ln.bias", vec![8]),
            ("rssm.img_in.ln.weight", vec![8]),
            ("rssm.post.fc.weight", vec![8, 13]),
            ("rssm.post.ln.bias", vec![8]),
            ("rssm.post.ln.weight", vec![8]),
            ("rssm.post_out.bias", vec![12]),
            ("rssm.post_out.weight", vec![12, 8]),
            ("rssm.prior.fc.weight", vec![8, 8]),
            ("rssm.prior.ln.bias", vec![8]),
            ("rssm.prior.ln.weight", vec![8]),
            ("rssm.prior_out.bias", vec![12]),
            ("rssm.prior_out.weight", vec![12, 8]),
        ];
        let want: Vec<(String, Vec<usize>)> =
            want.into_iter().map(|(n, d)| (n.to_string(), d)).collect();
        assert_eq!(names, want);
    }

    fn uniform(b: usize, c: &RssmConfig, v: f32) -> Tensor {
        Tensor::full(v, (b, c.stoch, c.classes), &Device::Cpu).unwrap()
    }

    #[test]
    fn steps_have_the_right_shapes_and_one_hot_samples() {
        let c = cfg(2);
        let (_, rssm) = standalone(c, 0).unwrap();
        let s0 = rssm.initial(4).unwrap();
        let a = Tensor::ones((4, 2), DType::F32, &Device::Cpu).unwrap();
        let ctx = Tensor::ones((4, 2), DType::F32, &Device::Cpu).unwrap();
        let e = Tensor::ones((4, 5), DType::F32, &Device::Cpu).unwrap();
        let (s1, post) = rssm
            .obs_step(&s0, &a, Some(&ctx), &e, &uniform(4, &c, 0.5))
            .unwrap();
        let prior = rssm.prior_logits(&s1.deter).unwrap();
        assert_eq!(s1.deter.dims(), &[4, 8]);
        assert_eq!(prior.dims(), &[4, 3, 4]);
        assert_eq!(post.dims(), &[4, 3, 4]);
        assert_eq!(s1.feat().unwrap().dims(), &[4, 8 + 12]);
        // forward values of a straight-through sample are exactly one-hot
        let z: Vec<Vec<f32>> = s1.stoch.reshape((12, 4)).unwrap().to_vec2().unwrap();
        for row in z {
            let ones = row.iter().filter(|&&v| (v - 1.0).abs() < 1e-6).count();
            let zeros = row.iter().filter(|&&v| v.abs() < 1e-6).count();
            assert_eq!((ones, zeros), (1, 3), "{row:?}");
        }
        let deter = rssm.deter_step(&s1, &a, Some(&ctx)).unwrap();
        let prior = rssm.prior_logits(&deter).unwrap();
        let stoch = rssm.sample(&prior, &uniform(4, &c, 0.3)).unwrap();
        assert_eq!(stoch.dims(), &[4, 12]);
    }

    #[test]
    fn unimix_floors_the_probabilities_and_kl_is_zero_on_itself() {
        let c = cfg(0);
        let (_, rssm) = standalone(c, 1).unwrap();
        let logits = Tensor::new(&[[[50.0f32, 0.0, 0.0, 0.0]; 3]], &Device::Cpu).unwrap();
        let p: Vec<f32> = rssm
            .probs(&logits)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert!(p.iter().all(|&v| v >= 0.01 / 4.0 - 1e-7));
        assert!((p[0] - (0.99 + 0.0025)).abs() < 1e-5);
        let kl: Vec<f32> = rssm.kl(&logits, &logits).unwrap().to_vec1().unwrap();
        assert!(kl[0].abs() < 1e-6);
        let other = Tensor::zeros((1, 3, 4), DType::F32, &Device::Cpu).unwrap();
        let kl: Vec<f32> = rssm.kl(&logits, &other).unwrap().to_vec1().unwrap();
        // KL(p ‖ uniform) = Σ_vars (ln C − H(p))
        let h: f32 = p[..4].iter().map(|&q| -q * q.ln()).sum();
        assert!((kl[0] - 3.0 * (4f32.ln() - h)).abs() < 1e-4, "{kl:?}");
    }

    #[test]
    fn straight_through_samples_pass_gradients_to_the_logits() {
        let c = cfg(0);
        let (_, rssm) = standalone(c, 2).unwrap();
        let logits = candle_core::Var::from_tensor(
            &Tensor::new(&[[[0.1f32, 0.2, 0.3, 0.4]; 3]], &Device::Cpu).unwrap(),
        )
        .unwrap();
        let z = rssm
            .sample(logits.as_tensor(), &uniform(1, &c, 0.7))
            .unwrap();
        let weights = Tensor::new(
            &[[
                1.0f32, 2.0, 3.0, 4.0, 1.0, 2.0, 3.0, 4.0, 1.0, 2.0, 3.0, 4.0,
            ]],
            &Device::Cpu,
        )
        .unwrap();
        let loss = z.mul(&weights).unwrap().sum_all().unwrap();
        let grads = loss.backward().unwrap();
        let g: Vec<f32> = grads
            .get(logits.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert!(g.iter().any(|v| v.abs() > 1e-4), "{g:?}");
    }

    /// The learned initial state adds one parameter, `rssm.initial_state.w` `[D]`, at zero
    /// after initialisation and drawn from no random number, so that every other parameter
    /// starts as without it; it starts sequences at `h = tanh(w)` and the one-hot mode of the
    /// prior. Weights saved without it (the default, every older checkpoint) still load into the
    /// default model and are refused by a learned one.
    #[test]
    fn the_learned_initial_state_is_one_named_parameter_starting_at_zero() {
        let learned = RssmConfig {
            learned_initial: true,
            ..cfg(2)
        };
        let (ps, rssm) = standalone(learned, 5).unwrap();
        let (old, zeros) = standalone(cfg(2), 5).unwrap();
        let values = |t: &Tensor| -> Vec<f32> { t.flatten_all().unwrap().to_vec1().unwrap() };
        let new: std::collections::HashMap<String, Vec<f32>> = ps
            .named()
            .into_iter()
            .map(|(n, v)| (n, values(v.as_tensor())))
            .collect();
        assert_eq!(new.len(), old.named().len() + 1);
        assert_eq!(new["rssm.initial_state.w"], vec![0.0; 8]);
        for (name, v) in old.named() {
            assert_eq!(new[&name], values(v.as_tensor()), "{name}");
        }
        let (_, var) = ps
            .named()
            .into_iter()
            .find(|(n, _)| n == "rssm.initial_state.w")
            .unwrap();
        var.set(&Tensor::randn(0f32, 1.0, 8, &Device::Cpu).unwrap())
            .unwrap();
        let w = rssm.initial_weight().unwrap();
        let s0 = rssm.initial(3).unwrap();
        let h0: Vec<f32> = values(&w.tanh().unwrap());
        let mode = values(
            &rssm
                .prior_logits(&w.tanh().unwrap().unsqueeze(0).unwrap())
                .unwrap()
                .argmax(D::Minus1)
                .unwrap()
                .to_dtype(DType::F32)
                .unwrap(),
        );
        let z: Vec<Vec<f32>> = s0.stoch.to_vec2().unwrap();
        for (row, h) in z.iter().zip(s0.deter.to_vec2::<f32>().unwrap()) {
            assert_eq!(h, h0);
            for (var, &k) in row.chunks_exact(4).zip(&mode) {
                let one_hot: Vec<f32> = (0..4).map(|j| f32::from(j == k as usize)).collect();
                assert_eq!(var, &one_hot[..]);
            }
        }
        assert!(zeros.initial_weight().is_none());
        let z0 = zeros.initial(2).unwrap();
        assert!(values(&z0.deter)
            .iter()
            .chain(&values(&z0.stoch))
            .all(|&v| v == 0.0));
        let saved = old.to_bytes().unwrap();
        assert!(old.load_bytes(&saved).is_ok());
        assert!(ps.load_bytes(&saved).is_err());
    }
}
