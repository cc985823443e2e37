//! cMask's mask SAC (the paper's contribution): a soft actor-critic whose action is the context
//! mask `m_t ∈ [0, 1]²` and whose observation is the LiDAR frame `o_t`, trained on the extrinsic
//! reward, one SAC step per world-model step on the same sequence batch.
//!
//! **Transitions.** Row `t + 1` of a sequence stores the action and the mask chosen at `o_t`, and
//! the reward earned by them: the SAC transitions are `(o_t, m_t, r_{t+1}, o_{t+1},
//! terminal_{t+1})` for `t < T − 1`, with `m_t` the mask that acted (as the paper's code stores
//! it). A mask drawn afresh from `π(· | o_t)` carries no information about `r_{t+1}`: a critic
//! fitted on it is flat in `m`, and the mask actor would learn from its entropy alone.
//! Transitions into a new episode, and those whose action no mask chose (random prefill), are
//! dropped (`valid = 0`).
//!
//! **Losses** (means over the valid transitions), with the twin critics and Polyak targets of
//! [`crate::sac`]: critics `Σ_i (Q_i(o, m) − y)²`, `y = r + γ (1 − d) (min_i Q̄_i(o', m') − α log
//! π(m' | o'))`, `m' ~ π(· | o')`; actor `α log π(m̃ | o) − min_i Q_i(o, m̃)` with a fresh
//! `m̃ ~ π(· | o)`; temperature `−log α · (log π + H̄)`. Each worker's shard of sequences sums its
//! part of a mean (divided by the batch's count of valid transitions) and differentiates it in
//! parallel ([`crate::shards`]), by hand on plain buffers with SAC's passes
//! ([`crate::sac::Workspace`]), each transition weighted by `valid / count`.
//!
//! **The paper's code** (c0fd903, `Utils/cbdreamer/cbmodels.py`, `CtxMask._train`) differs in
//! five ways, each a key of [`MaskConfig`] (`with_paper_code_mask` sets them all):
//! `mask_space = "paper-code"` ([`MaskSpace::PaperCode`]: the critics fitted on the stored
//! `sigmoid(tanh u)` masks, the actor's loss evaluating them at `tanh ũ`, the target at
//! `clamp(tanh u', 0, 1)`, `log π` of `tanh u`); `bootstrap_terminals` (`d = 0` always);
//! `target_every = 2` (Polyak on every second step, the first included); `log_std_clamp =
//! [−20, 2]`; `reward_delay = 1` (`(o_t, m_t, r_{t+2}, o_{t+1})`: the code's rows hold
//! `(o_t, a_t, r_{t+1}, m_t)` and it pairs row `t` with the reward of row `t + 1`; the
//! transition is dropped where `t + 2` starts a new episode). Not reproduced: the code's
//! transitions across an episode end (ctxrace's rows store an episode's last observation, and a
//! first row carries no mask), its first step's `α = 0.2` before `log α = 0` takes over, and its
//! temperature loss on a fresh sample after the actor's step.

use crate::algorithm::Metrics;
use crate::error::SacError;
use crate::error::{LearnerError, Result};
use crate::sac::{ActionRange, ActorNet, PassSum, SoftTarget, WeightedTransitions, Workspace};
use crate::sac_core::{ActorPass, CoreConfig, CriticPass, LearningRates, Passes, SacCore};
use crate::shards::{on_shards_with, Shard};
use ctxrace_config::agents::{DreamerConfig, MaskConfig, MaskSpace, StepAlignment, CONTEXT_DIM};
use ctxrace_config::SequenceBatch;
use ctxrace_nn::dreamer::normal_rows;
use ctxrace_nn::initial_weights;
use ctxrace_nn::{Mlp, NamedTensor};
use rand_chacha::ChaCha8Rng;
use std::ops::Range;

/// The mask SAC's transitions `(o_t, m_t, r_{t+1+δ}, o_{t+1}, terminal_{t+1})` for every `t`
/// whose rows lie in the sequence (`δ` = `reward_delay`; [`transitions_per_sequence`]),
/// row-major `[B·n, …]`, `m_t` the stored mask that acted at `o_t`, with `valid = 0` where
/// `o_{t+1}` (or, delayed, `o_{t+2}`) starts a new episode or no mask chose the action at `o_t`; every terminal flag 0 with
/// `bootstrap_terminals`. Where the mask, reward and terminal flag of `o_t`'s choice are stored
/// follows the rows' [`StepAlignment`] ([`choice_row`]); a transition whose next row starts an
/// episode is left out in both (the paper's code, whose sequences cross episode ends, bootstraps
/// across them).
pub(crate) struct Transitions {
    /// `n` transitions a sequence ([`transitions_per_sequence`]), sequence after sequence.
    per_sequence: usize,
    obs: Vec<f32>,
    mask: Vec<f32>,
    reward: Vec<f32>,
    next_obs: Vec<f32>,
    terminal: Vec<f32>,
    valid: Vec<f32>,
}

/// The number of transitions of a sequence of `length` rows: `o_t` pairs with `o_{t+1}` and
/// with the reward `delay` rows after its choice's row `row` ([`choice_row`]), so every `t`
/// with `t + max(1, row + delay) < length` (`T − 1 − δ` with ctxrace's rows, `T − 1` with
/// the paper code's, whose last transition takes the reward of the sequence's last row, as the
/// code's `data['reward'][:, 1:]` does); `None` for none.
pub(crate) fn transitions_per_sequence(length: usize, delay: usize, row: usize) -> Option<usize> {
    length.checked_sub((row + delay).max(1)).filter(|&n| n > 0)
}

/// The row, counted from `o_t`'s, that stores the mask, reward and terminal flag of the choice
/// made at `o_t`: the next (ctxrace's rows `(o_t, a_{t−1}, r_t)`) or its own (the paper code's
/// `(o_t, a_t, r_{t+1})`).
pub(crate) fn choice_row(alignment: StepAlignment) -> usize {
    match alignment {
        StepAlignment::Ctxrace => 1,
        StepAlignment::PaperCode => 0,
    }
}

impl Transitions {
    /// From a batch whose rows are laid out by `alignment` under `cfg`'s `reward_delay` and
    /// `bootstrap_terminals`; `None` for sequences too short for one transition.
    fn new(seq: &SequenceBatch, cfg: &MaskConfig, alignment: StepAlignment) -> Option<Self> {
        let (t, delay) = (seq.length, cfg.reward_delay);
        let row = choice_row(alignment);
        let n = transitions_per_sequence(t, delay, row)?;
        // rows `start … start + n − 1` of every sequence of `x` (`width` values a row)
        let span = |x: &[f32], width: usize, start: usize| -> Vec<f32> {
            (0..seq.batch)
                .flat_map(|b| {
                    let first = (b * t + start) * width;
                    x[first..first + n * width].iter().copied()
                })
                .collect()
        };
        let terminal = if cfg.bootstrap_terminals {
            vec![0.0; seq.batch * n]
        } else {
            span(&seq.is_terminal, 1, row)
        };
        Some(Self {
            per_sequence: n,
            obs: span(&seq.obs, seq.obs_dim, 0),
            mask: span(&seq.mask, CONTEXT_DIM, row),
            reward: span(&seq.reward, 1, row + delay),
            next_obs: span(&seq.obs, seq.obs_dim, 1),
            terminal,
            valid: Self::valid(seq, delay, row),
        })
    }

    /// `[B·n]` ([`transitions_per_sequence`]): 1 where rows `t + 1 … t + max(1, row + delay)`
    /// of the sequences continue the episode and the action of row `t + row` was chosen
    /// through a mask (`row` from [`choice_row`]).
    fn valid(seq: &SequenceBatch, delay: usize, row: usize) -> Vec<f32> {
        let t = seq.length;
        let n = transitions_per_sequence(t, delay, row).unwrap_or(0);
        let mut valid = Vec::with_capacity(seq.batch * n);
        for b in 0..seq.batch {
            for i in b * t..b * t + n {
                let continues = (1..=(row + delay).max(1)).all(|s| seq.is_first[i + s] == 0.0);
                valid.push(if continues {
                    seq.has_mask[i + row]
                } else {
                    0.0
                });
            }
        }
        valid
    }

    /// The number of valid transitions.
    fn valid_count(&self) -> f32 {
        self.valid.iter().sum()
    }

    /// The transitions of the sequences `seqs`, with `weight` per transition.
    fn weighted<'a>(&'a self, seqs: &Range<usize>, weight: &'a [f32]) -> WeightedTransitions<'a> {
        let r = self.span(seqs);
        let o = self.obs.len() / self.valid.len().max(1);
        let rows = |x: &'a [f32], width: usize| &x[r.start * width..r.end * width];
        WeightedTransitions {
            obs: rows(&self.obs, o),
            action: rows(&self.mask, CONTEXT_DIM),
            reward: rows(&self.reward, 1),
            next_obs: rows(&self.next_obs, o),
            terminal: rows(&self.terminal, 1),
            weight,
        }
    }

    /// The share of a mean over `count` valid transitions that each transition of the sequences
    /// `seqs` carries.
    fn weights(&self, seqs: &Range<usize>, count: f32) -> Vec<f32> {
        self.valid[self.span(seqs)]
            .iter()
            .map(|v| v / count)
            .collect()
    }

    /// The transitions of the sequences `seqs`.
    fn span(&self, seqs: &Range<usize>) -> Range<usize> {
        seqs.start * self.per_sequence..seqs.end * self.per_sequence
    }
}

/// cMask's mask SAC: SAC's core ([`SacCore`]: twin critics, targets, temperature, optimisers)
/// stepping the policy's mask actor on the batch's masked transitions.
pub(crate) struct MaskSac {
    /// The critics ("mask_critic"), targets ("mask_target"), `log α` ("mask_alpha") and the
    /// optimisers.
    pub(crate) core: SacCore,
    cfg: MaskConfig,
    /// How the batches' rows are laid out (where a choice's mask and reward are stored).
    alignment: StepAlignment,
    /// The buffers of each shard's passes.
    work: Vec<Workspace>,
}

/// A step's passes over the valid transitions of a batch, shard by shard in parallel, the
/// masks' noise drawn from each shard's sequences' streams.
struct MaskPasses<'a> {
    transitions: &'a Transitions,
    /// The count of valid transitions (the means' divisor).
    count: f32,
    workers: usize,
    rngs: &'a mut [ChaCha8Rng],
    work: &'a mut Vec<Workspace>,
}

impl MaskPasses<'_> {
    /// Runs `pass` on each shard's weighted transitions, one shard per worker in parallel, and
    /// sums the results.
    fn on_transitions<T: PassSum + Send>(
        &mut self,
        pass: impl Fn(&mut Workspace, &WeightedTransitions, &[f32]) -> T + Sync,
    ) -> std::result::Result<T, SacError> {
        let (tr, count) = (self.transitions, self.count);
        let batch = tr.valid.len() / tr.per_sequence;
        let work = &mut *self.work;
        work.resize_with(self.workers.clamp(1, batch.max(1)), Workspace::default);
        let shards = on_shards_with(
            self.workers,
            batch,
            self.rngs,
            work,
            |shard: Shard, rngs, w| {
                let weight = tr.weights(&shard.rows, count);
                let noise = normal_rows(rngs, tr.per_sequence, CONTEXT_DIM);
                Ok(pass(w, &tr.weighted(&shard.rows, &weight), &noise))
            },
        );
        let mut parts = shards
            .map_err(|e| SacError::Shards(Box::new(e)))?
            .into_iter();
        let Some(mut sum) = parts.next() else {
            return Err(SacError::NoShards);
        };
        for part in parts {
            sum.add(&part);
        }
        Ok(sum)
    }
}

impl Passes for MaskPasses<'_> {
    type Error = SacError;

    fn critic(
        &mut self,
        nets: (&[Mlp; 2], &[Mlp; 2], ActorNet),
        soft: SoftTarget,
    ) -> std::result::Result<CriticPass, SacError> {
        self.on_transitions(|w, tr, noise| w.critic_pass(nets, tr, noise, soft))
    }

    fn actor(
        &mut self,
        nets: (&[Mlp; 2], ActorNet),
        with: (f32, ActionRange),
    ) -> std::result::Result<ActorPass, SacError> {
        self.on_transitions(|w, tr, noise| w.actor_pass(nets, (tr.obs, tr.weight), noise, with))
    }
}

impl MaskSac {
    /// The mask SAC of `cfg` for observations of `obs_dim` and the mask actor `actor`: critics
    /// drawn from `cfg.seed + 3` (as `cfg.init` says), the targets their copy, `log α` from
    /// `init_alpha`.
    pub(crate) fn new(cfg: &DreamerConfig, obs_dim: usize, actor: &Mlp) -> Result<Self> {
        let m = &cfg.mask;
        if m.init_alpha.is_nan() || m.init_alpha <= 0.0 {
            return Err(LearnerError::MaskTemperature(m.init_alpha));
        }
        let seed = cfg.seed.wrapping_add(3);
        let core = CoreConfig {
            input: obs_dim + CONTEXT_DIM,
            hidden: m.units,
            layers: m.layers,
            seed,
            initial_alpha: m.init_alpha,
            lr: LearningRates {
                actor: m.lr,
                critic: m.lr,
                alpha: m.lr,
            },
            gamma: m.gamma,
            tau: m.tau,
            target_every: m.target_every,
            target_entropy: m.target_entropy,
            range: match m.mask_space {
                MaskSpace::Unit => ActionRange::UNIT,
                MaskSpace::PaperCode => ActionRange::SYMMETRIC,
            },
            bounds: [0.0, 1.0],
        };
        let draw = |t: &NamedTensor| initial_weights::draw(cfg.init, t, (obs_dim, 0));
        Ok(Self {
            core: SacCore::new(core, actor, &draw)?,
            cfg: m.clone(),
            alignment: cfg.step_alignment,
            work: Vec::new(),
        })
    }

    /// One SAC step (critics, actor, temperature, targets) on the transitions of the batch `seq`
    /// and the masks stored with them, the learner's step `step` (the targets move when it is a
    /// multiple of `target_every`; `mask/q_spread` only when `diagnose`, on a logged step). The
    /// critic and actor losses are means over the valid
    /// transitions; each of the `workers` shards of sequences sums its part (divided by the
    /// batch's count) and differentiates it in parallel, and the gradients are summed. A batch
    /// without valid transitions (all random prefill) takes no step.
    pub(crate) fn step(
        &mut self,
        actor: &mut Mlp,
        seq: &SequenceBatch,
        (step, workers, diagnose): (u64, usize, bool),
        rngs: &mut [ChaCha8Rng],
        metrics: &mut Metrics,
    ) -> Result<()> {
        let Some(transitions) = Transitions::new(seq, &self.cfg, self.alignment) else {
            return Ok(());
        };
        let valid_count = f64::from(transitions.valid_count());
        metrics.insert("mask/acted_transitions".into(), valid_count);
        metrics.insert("mask/alpha".into(), self.core.alpha());
        if valid_count == 0.0 {
            // the losses over no transitions are zero; nothing is stepped
            let keys = ["mask/q_loss", "mask/actor_loss", "mask/entropy"];
            let spread = diagnose.then_some("mask/q_spread");
            for key in keys.into_iter().chain(spread) {
                metrics.insert(key.into(), 0.0);
            }
            return Ok(());
        }
        let mut passes = MaskPasses {
            transitions: &transitions,
            count: valid_count as f32,
            workers,
            rngs,
            work: &mut self.work,
        };
        let clamp = self.cfg.log_std_clamp.map(|b| b as f32);
        let losses = self.core.step((actor, clamp), &mut passes, step)?;
        metrics.insert("mask/q_loss".into(), losses.critic_loss);
        metrics.insert("mask/actor_loss".into(), losses.actor_loss);
        metrics.insert("mask/entropy".into(), -losses.log_prob);
        if diagnose {
            metrics.insert("mask/q_spread".into(), self.q_spread(&transitions));
        }
        Ok(())
    }

    /// How much the mask matters to the critics after the step: over the first
    /// [`SPREAD_OBSERVATIONS`] valid transitions' observations `o`, the mean of
    /// `max_m Q(o, m) − min_m Q(o, m)`, `Q = min(Q_1, Q_2)`, on the 3 × 3 grid of masks at
    /// `tanh u ∈ {−1, 0, 1}` per dimension (the mask's range's corners, edge midpoints and
    /// centre). The actor maximises `Q(o, m) + α H(π(· | o))`: a spread small against the
    /// entropy term (`mask/alpha` × `mask/entropy`) leaves the mask where the entropy puts it,
    /// at the range's centre.
    fn q_spread(&self, tr: &Transitions) -> f64 {
        let n = tr.valid.len();
        let obs_dim = tr.obs.len() / n.max(1);
        let observations: Vec<&[f32]> = (0..n)
            .filter(|&i| tr.valid[i] > 0.0)
            .take(SPREAD_OBSERVATIONS)
            .map(|i| &tr.obs[i * obs_dim..(i + 1) * obs_dim])
            .collect();
        if observations.is_empty() {
            return 0.0;
        }
        let range = self.core.cfg.range;
        let grid: Vec<[f32; 2]> = [-1.0, 0.0, 1.0]
            .iter()
            .flat_map(|&v| [-1.0, 0.0, 1.0].map(|t| [range.at(v), range.at(t)]))
            .collect();
        let width = obs_dim + CONTEXT_DIM;
        let mut input = Vec::with_capacity(observations.len() * grid.len() * width);
        for o in &observations {
            for m in &grid {
                input.extend_from_slice(o);
                input.extend_from_slice(m);
            }
        }
        let rows = observations.len() * grid.len();
        let q: Vec<Vec<f32>> = self
            .core
            .critics
            .q
            .iter()
            .map(|critic| {
                let mut trace = critic.trace(rows);
                critic.forward(input.as_slice(), &mut trace, 0..rows);
                critic.output(&trace, 0..rows).to_vec()
            })
            .collect();
        let spread: f64 = (0..observations.len())
            .map(|k| {
                let cells = k * grid.len()..(k + 1) * grid.len();
                let q_min = cells.map(|r| q[0][r].min(q[1][r]));
                let (lo, hi) = q_min.fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(v), hi.max(v))
                });
                f64::from(hi - lo)
            })
            .sum();
        spread / observations.len() as f64
    }
}

/// The observations [`MaskSac::q_spread`] averages over (of a batch's valid transitions).
const SPREAD_OBSERVATIONS: usize = 64;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algorithm::scalar;
    use crate::candle_sac::TwinQ;
    use crate::sequences::SeqData;
    use crate::world_model::oracle;
    use candle_core::{Device, Result, Tensor};
    use ctxrace_nn::{Activation, MlpShape, Parameters, Weights};
    use ctxrace_oracle::TanhGaussianActor;
    use rand::{Rng, SeedableRng};

    /// One sequence of one-value observations and actions (actions and contexts zero): its
    /// observations, rewards, `(is_first, is_terminal)` flags and `(mask, has_mask)` per row.
    fn one_sequence(
        obs: Vec<f32>,
        reward: Vec<f32>,
        (is_first, is_terminal): (Vec<f32>, Vec<f32>),
        (mask, has_mask): (Vec<f32>, Vec<f32>),
    ) -> SequenceBatch {
        let length = obs.len();
        SequenceBatch {
            batch: 1,
            length,
            obs_dim: 1,
            act_dim: 1,
            obs,
            action: vec![0.0; length],
            reward,
            is_first,
            is_terminal,
            context: vec![0.0; 2 * length],
            mask,
            has_mask,
        }
    }

    #[test]
    fn sac_transitions_take_the_reward_and_mask_of_their_own_step() {
        let seq = one_sequence(
            vec![0.0, 1.0, 2.0, 3.0],
            vec![0.0, 10.0, 20.0, 30.0],
            (vec![1.0, 0.0, 1.0, 0.0], vec![0.0, 1.0, 0.0, 0.0]),
            // row t + 1 holds the mask that acted at o_t; the action into o_3 had none
            (
                vec![0.0, 0.0, 0.3, 0.4, 0.0, 0.0, 0.7, 0.8],
                vec![0.0, 1.0, 0.0, 0.0],
            ),
        );
        let tr = Transitions::new(&seq, &MaskConfig::default(), StepAlignment::Ctxrace).unwrap();
        assert_eq!(tr.obs, [0.0, 1.0, 2.0]);
        assert_eq!(tr.mask, [0.3, 0.4, 0.0, 0.0, 0.7, 0.8]);
        assert_eq!(tr.reward, [10.0, 20.0, 30.0]);
        assert_eq!(tr.next_obs, [1.0, 2.0, 3.0]);
        assert_eq!(tr.terminal, [1.0, 0.0, 0.0]);
        // o_2 starts a new episode; no mask chose the action into o_3
        assert_eq!(tr.valid, [1.0, 0.0, 0.0]);
    }

    /// The paper's code's rows: `(o_t, m_t)` with the reward of step `t + 2`, no terminal
    /// flags, and no transition whose delayed reward lies in the next episode.
    #[test]
    fn paper_code_transitions_take_the_next_reward_and_bootstrap_terminals() {
        let seq = one_sequence(
            vec![0.0, 1.0, 2.0, 3.0, 4.0],
            vec![0.0, 10.0, 20.0, 30.0, 40.0],
            (vec![1.0, 0.0, 0.0, 0.0, 1.0], vec![0.0, 0.0, 0.0, 1.0, 0.0]),
            (
                vec![0.0, 0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.0, 0.0],
                vec![0.0, 1.0, 1.0, 1.0, 0.0],
            ),
        );
        let ours = Transitions::new(&seq, &MaskConfig::default(), StepAlignment::Ctxrace).unwrap();
        assert_eq!(ours.reward, [10.0, 20.0, 30.0, 40.0]);
        assert_eq!(ours.terminal, [0.0, 0.0, 1.0, 0.0]);
        assert_eq!(ours.valid, [1.0, 1.0, 1.0, 0.0]);
        let code = MaskConfig::default().with_paper_code_mask();
        let tr = Transitions::new(&seq, &code, StepAlignment::Ctxrace).unwrap();
        assert_eq!(tr.obs, [0.0, 1.0, 2.0]);
        assert_eq!(tr.mask, [0.3, 0.4, 0.5, 0.6, 0.7, 0.8]);
        assert_eq!(tr.reward, [20.0, 30.0, 40.0]);
        assert_eq!(tr.next_obs, [1.0, 2.0, 3.0]);
        assert_eq!(tr.terminal, [0.0, 0.0, 0.0]);
        // o_4 starts a new episode: the last mask's delayed reward is not its own episode's
        assert_eq!(tr.valid, [1.0, 1.0, 0.0]);
        let short = SequenceBatch {
            length: 2,
            obs: vec![0.0; 2],
            action: vec![0.0; 2],
            reward: vec![0.0; 2],
            is_first: vec![1.0, 0.0],
            is_terminal: vec![0.0; 2],
            context: vec![0.0; 4],
            mask: vec![0.0; 4],
            has_mask: vec![0.0, 1.0],
            ..seq
        };
        assert!(Transitions::new(&short, &code, StepAlignment::Ctxrace).is_none());
    }

    /// Under the paper code's rows `(o_t, a_t, r_{t+1})` (`step_alignment = "paper-code"`) the
    /// choice at `o_t` is paired with the mask, reward and terminal flag of its own row, and its
    /// reward `reward_delay` rows later; a transition into a row that starts an episode is out.
    #[test]
    fn paper_code_rows_pair_each_observation_with_its_own_rows_choice() {
        let seq = one_sequence(
            vec![0.0, 1.0, 2.0, 3.0, 4.0],
            vec![10.0, 20.0, 30.0, 40.0, 50.0],
            (vec![1.0, 0.0, 0.0, 0.0, 1.0], vec![0.0, 0.0, 0.0, 1.0, 0.0]),
            (
                vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0],
                vec![1.0, 1.0, 0.0, 1.0, 1.0],
            ),
        );
        let own = Transitions::new(&seq, &MaskConfig::default(), StepAlignment::PaperCode).unwrap();
        assert_eq!(own.obs, [0.0, 1.0, 2.0, 3.0]);
        assert_eq!(own.mask, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8]);
        assert_eq!(own.reward, [10.0, 20.0, 30.0, 40.0]);
        assert_eq!(own.next_obs, [1.0, 2.0, 3.0, 4.0]);
        assert_eq!(own.terminal, [0.0, 0.0, 0.0, 1.0]);
        // no mask chose at o_2; o_4 starts the next episode
        assert_eq!(own.valid, [1.0, 1.0, 0.0, 0.0]);
        let late = MaskConfig {
            reward_delay: 1,
            ..MaskConfig::default()
        };
        // the late reward of the last transition is the sequence's last row's
        let tr = Transitions::new(&seq, &late, StepAlignment::PaperCode).unwrap();
        assert_eq!(tr.mask, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8]);
        assert_eq!(tr.reward, [20.0, 30.0, 40.0, 50.0]);
        assert_eq!(tr.next_obs, [1.0, 2.0, 3.0, 4.0]);
        assert_eq!(tr.valid, [1.0, 1.0, 0.0, 0.0]);
    }

    /// The critics' input for the actor's sample `a = tanh u` with `log π(a)` under `cfg`, and
    /// `log π` of that input: the unit mask `(1 + a)/2` (its density), or the paper's code's
    /// `a` itself (the target's clamped to `[0, 1]` by `bound`).
    fn critic_input(
        cfg: &MaskConfig,
        (a, log_prob): (Tensor, Tensor),
        bound: bool,
    ) -> Result<(Tensor, Tensor)> {
        match cfg.mask_space {
            MaskSpace::Unit => Ok((
                a.affine(0.5, 0.5)?,
                (log_prob + CONTEXT_DIM as f64 * std::f64::consts::LN_2)?,
            )),
            MaskSpace::PaperCode if bound => Ok((a.clamp(0f32, 1f32)?, log_prob)),
            MaskSpace::PaperCode => Ok((a, log_prob)),
        }
    }

    /// `(critic loss, actor loss)` of the module doc (in the form `sac.cfg` selects) composed of
    /// candle operations over the whole batch, autograd's statement of what the sharded passes
    /// differentiate by hand.
    fn candle_losses(
        sac: &MaskSac,
        (actor, q, q_target): (&TanhGaussianActor, &TwinQ, &TwinQ),
        (seq, d): (&SequenceBatch, &SeqData),
        (next_noise, noise): (&[f32], &[f32]),
        alpha: f64,
    ) -> Result<(Tensor, Tensor)> {
        let cfg = &sac.cfg;
        let row = choice_row(sac.alignment);
        let b = d.batch;
        let per = transitions_per_sequence(d.length, cfg.reward_delay, row).unwrap();
        let n = b * per;
        let span = |x: &Tensor, start: usize| x.narrow(1, start, per)?.reshape((n, ()));
        let (obs, next_obs, mask) = (span(&d.obs, 0)?, span(&d.obs, 1)?, span(&d.mask, row)?);
        let reward = span(&d.reward, row + cfg.reward_delay)?.flatten_all()?;
        let terminal = span(&d.terminal, row)?.flatten_all()?;
        let terminal = (terminal * f64::from(u8::from(!cfg.bootstrap_terminals)))?;
        let valid = Transitions::valid(seq, cfg.reward_delay, row);
        let valid = Tensor::from_vec(valid, n, &Device::Cpu)?;
        let count = valid.sum_all()?;
        let mean = |x: &Tensor| x.mul(&valid)?.sum_all()?.div(&count);
        let noise_of = |v: &[f32]| Tensor::from_slice(v, (n, CONTEXT_DIM), &Device::Cpu);
        let next = actor.sample(&next_obs, &noise_of(next_noise)?)?;
        let (next_m, next_logp) = critic_input(cfg, next, true)?;
        let soft = (q_target.min(&next_obs, &next_m)? - (next_logp * alpha)?)?;
        let keep = ((1.0 - terminal)? * cfg.gamma)?;
        let y = (reward + keep.mul(&soft)?)?.detach();
        let (q1, q2) = q.forward(&obs, &mask)?;
        let critic = mean(&((q1 - &y)?.sqr()? + (q2 - &y)?.sqr()?)?)?;
        let sample = actor.sample(&obs, &noise_of(noise)?)?;
        let (m, logp) = critic_input(cfg, sample, false)?;
        let actor_loss = mean(&((logp * alpha)? - q.min(&obs, &m)?)?)?;
        Ok((critic, actor_loss))
    }

    /// The sharded, hand-differentiated critic and actor gradients are those of the candle
    /// composition over the whole batch, whatever the number of shards, in ctxrace's form and
    /// in the paper's code's.
    #[test]
    fn the_step_differentiates_the_candle_composition() {
        let small = MaskConfig {
            units: 16,
            ..MaskConfig::default()
        };
        the_step_differentiates_the_candle_composition_of(small.clone());
        the_step_differentiates_the_candle_composition_of(small.with_paper_code_mask());
    }

    /// A batch of `b` sequences of `t` rows of `o` random observation values: a second
    /// episode starts inside sequence 1, sequence 2 ends in a terminal, and the random prefill
    /// of sequence 3 chose no masks.
    fn random_batch(b: usize, t: usize, o: usize, seed: u64) -> SequenceBatch {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut u = |lo: f32, hi: f32| rng.random_range(lo..hi);
        SequenceBatch {
            batch: b,
            length: t,
            obs_dim: o,
            act_dim: 1,
            obs: (0..b * t * o).map(|_| u(-1.0, 1.0)).collect(),
            action: vec![0.0; b * t],
            reward: (0..b * t).map(|_| u(-1.0, 1.0)).collect(),
            is_first: (0..b * t)
                .map(|k| f32::from(k % t == 0 || k == t + 3))
                .collect(),
            is_terminal: (0..b * t).map(|k| f32::from(k == 2 * t + 4)).collect(),
            context: vec![0.3; b * t * 2],
            mask: (0..b * t * 2).map(|_| u(0.0, 1.0)).collect(),
            has_mask: (0..b * t)
                .map(|k| f32::from(k % t != 0 && k / t != 3))
                .collect(),
        }
    }

    /// A mask SAC of `mask` with 16-unit networks for observations of `o` values, its
    /// configuration and its mask actor.
    fn small_sac(mask: MaskConfig, o: usize) -> (DreamerConfig, Mlp, MaskSac) {
        let cfg = DreamerConfig {
            mask,
            ..DreamerConfig::default()
        };
        let shape = MlpShape {
            input: o,
            units: 16,
            layers: 2,
            out: Some(2 * CONTEXT_DIM),
            act: Activation::Relu,
        };
        let mut actor = Mlp::from_weights(&mut Weights::initial(), "mask.", &shape).unwrap();
        ctxrace_nn::parameters::init(&mut actor, 5);
        let sac = MaskSac::new(&cfg, o, &actor).unwrap();
        (cfg, actor, sac)
    }

    /// `mask/q_spread` is the range of the candle twin's minimum over the 3 × 3 grid of masks,
    /// averaged over the valid transitions' observations, in both mask spaces.
    #[test]
    fn the_q_spread_is_the_critics_range_over_the_mask_grid() {
        let small = MaskConfig {
            units: 16,
            ..MaskConfig::default()
        };
        for (mask, values) in [
            (small.clone(), [0.0, 0.5, 1.0]),
            (small.with_paper_code_mask(), [-1.0, 0.0, 1.0]),
        ] {
            let o = 3;
            let seq = random_batch(4, 6, o, 3);
            let (cfg, _, sac) = small_sac(mask, o);
            let tr = Transitions::new(&seq, &cfg.mask, cfg.step_alignment).unwrap();
            let twin = |vb: candle_nn::VarBuilder| TwinQ::new(o + CONTEXT_DIM, 16, 2, vb).unwrap();
            let (_store, q) = oracle::store_of(&sac.core.critics, twin);
            let grid: Vec<f32> = values
                .iter()
                .flat_map(|&v| values.map(|t| [v, t]))
                .flatten()
                .collect();
            let masks = Tensor::from_slice(&grid, (9, CONTEXT_DIM), &Device::Cpu).unwrap();
            let mut spreads = Vec::new();
            for i in (0..tr.valid.len()).filter(|&i| tr.valid[i] > 0.0) {
                let o_i = &tr.obs[i * o..(i + 1) * o];
                let rows: Vec<f32> = (0..9).flat_map(|_| o_i.iter().copied()).collect();
                let obs = Tensor::from_slice(&rows, (9, o), &Device::Cpu).unwrap();
                let q_min: Vec<f32> = q.min(&obs, &masks).unwrap().to_vec1().unwrap();
                let hi = q_min.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let lo = q_min.iter().copied().fold(f32::INFINITY, f32::min);
                spreads.push(f64::from(hi - lo));
            }
            let want = spreads.iter().sum::<f64>() / spreads.len() as f64;
            let got = sac.q_spread(&tr);
            assert!(want > 0.0);
            assert!((got - want).abs() <= 1e-6 * want, "{got} != {want}");
        }
    }

    fn the_step_differentiates_the_candle_composition_of(mask: MaskConfig) {
        let (b, t, o) = (4, 6, 3);
        let seq = random_batch(b, t, o, 8);
        let (cfg, mut actor, mut sac) = small_sac(mask, o);
        let streams = |seed: u64| -> Vec<ChaCha8Rng> {
            (0..b as u64)
                .map(|i| {
                    let mut r = ChaCha8Rng::seed_from_u64(seed);
                    r.set_stream(i);
                    r
                })
                .collect()
        };
        // critics and targets apart, so that the target path weighs
        for k in 0..3 {
            sac.step(
                &mut actor,
                &seq,
                (k, 2, true),
                &mut streams(k),
                &mut Metrics::new(),
            )
            .unwrap();
        }
        // the candle oracle of the networks as they are now
        let clamp = cfg.mask.log_std_clamp;
        let (actor_store, candle_actor) = oracle::store_of(&actor, |vb| {
            TanhGaussianActor::new(o, CONTEXT_DIM, 16, 2, vb.pp("mask"))
                .unwrap()
                .with_log_std_clamp(clamp)
        });
        let twin = |vb: candle_nn::VarBuilder| TwinQ::new(o + CONTEXT_DIM, 16, 2, vb).unwrap();
        let (critic_store, q) = oracle::store_of(&sac.core.critics, twin);
        let (_, q_target) = oracle::store_of(&sac.core.targets, twin);
        let alpha = 0.25;
        let mut draws = streams(99);
        let row = choice_row(cfg.step_alignment);
        let per = transitions_per_sequence(t, cfg.mask.reward_delay, row).unwrap();
        let next_noise = normal_rows(&mut draws, per, CONTEXT_DIM);
        let noise = normal_rows(&mut draws, per, CONTEXT_DIM);
        let d = SeqData::new(&seq, o, 1).unwrap();
        let candle_nets = (&candle_actor, &q, &q_target);
        let (critic, actor_loss) =
            candle_losses(&sac, candle_nets, (&seq, &d), (&next_noise, &noise), alpha).unwrap();
        let (want_c, want_a) = (critic.backward().unwrap(), actor_loss.backward().unwrap());
        let transitions = Transitions::new(&seq, &cfg.mask, cfg.step_alignment).unwrap();
        let view = ActorNet {
            net: &actor,
            log_std_clamp: clamp.map(|b| b as f32),
        };
        let range = sac.core.cfg.range;
        let soft = SoftTarget {
            alpha: alpha as f32,
            gamma: cfg.mask.gamma as f32,
            range,
            bounds: [0.0, 1.0],
            smoothing: &[],
        };
        for workers in [1, 2, 4] {
            let mut rngs = streams(99);
            let mut work = Vec::new();
            let mut passes = MaskPasses {
                transitions: &transitions,
                count: transitions.valid_count(),
                workers,
                rngs: &mut rngs,
                work: &mut work,
            };
            let (critics, targets) = (&sac.core.critics, &sac.core.targets);
            let critic_pass = passes.critic((&critics.q, &targets.q, view), soft).unwrap();
            let actor_pass = passes
                .actor((&critics.q, view), (alpha as f32, range))
                .unwrap();
            let (loss_c, loss_a) = (critic_pass.loss, actor_pass.loss);
            let got_c = critics.grad_tensors(critic_pass.grads);
            let got_a = actor_pass.grads.into_tensors(&actor);
            let close = |a: f64, t: &Tensor| {
                let b = scalar(t).unwrap();
                assert!((a - b).abs() < 1e-5 * (1.0 + b.abs()), "{a} vs {b}");
            };
            close(loss_c, &critic);
            close(loss_a, &actor_loss);
            let actor_tensors = actor.tensors();
            let critic_tensors = sac.core.critics.tensors();
            for (tensors, store, got, want) in [
                (&actor_tensors, &actor_store, &got_a, &want_a),
                (&critic_tensors, &critic_store, &got_c, &want_c),
            ] {
                assert_eq!(tensors.len(), got.len());
                for (t, g) in tensors.iter().zip(got) {
                    let name = t.name;
                    let w: Vec<f32> = oracle::grad(want, store, name).unwrap();
                    assert_eq!(g.len(), w.len(), "{name}");
                    let scale = w.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-6);
                    assert!(w.iter().any(|&x| x != 0.0), "{name}: zero gradient");
                    for (i, (a, b)) in g.iter().zip(&w).enumerate() {
                        assert!(
                            (a - b).abs() <= 1e-4 * scale,
                            "{workers} workers, {name}[{i}]: {a} vs {b}"
                        );
                    }
                }
            }
        }
    }
}
