//! How the DreamerV3 family's initial weights are drawn (`[agent.dreamer] init`,
//! [`WeightInit`]): ctxrace's draw, or the paper code's PyTorch initialisers, tensor by tensor
//! by the names the networks give their parameters.
//!
//! The paper's code (c0fd903, `Utils/dreamerv3/tools.py` `weight_init`, `uniform_weight_init`;
//! `Utils/cbdreamer/cbmodels.py` `weights_init_`), with `fan_avg = (fan_in + fan_out) / 2`:
//!
//! | tensors | draw |
//! |---|---|
//! | hidden layers (`*.fc.weight` of the normalised blocks: encoder, RSSM, decoder, heads, actor, critic) | truncated normal, variance `1/fan_avg` |
//! | latent logits (`rssm.prior_out`, `rssm.post_out`), continue head, decoder (per part: observation, action) and actor (per part: means, standard deviations) outputs | uniform, variance `1/fan_avg` |
//! | reward head and critic outputs | zero |
//! | the mask SAC's actor (`mask.*`, its output per part) and critics (`q1.*`, `q2.*`) | Xavier uniform, variance `1/fan_avg` |
//! | biases | zero |
//! | LayerNorm gains, the learned initial state, `log α` | as built (one, zero, `ln α₀`) |

use crate::parameters::{ctxrace_draw, fan_avg_draw, init_with, Draw, NamedTensor, Parameters};
use ctxrace_config::agents::{DreamerConfig, WeightInit};

/// Draws the networks `net` of a DreamerV3-family agent of `cfg` for observations of `obs_dim`
/// and actions of `act_dim` from `seed`, as `cfg.init` says.
pub fn init_dreamer<P: Parameters + ?Sized>(
    net: &mut P,
    seed: u64,
    cfg: &DreamerConfig,
    (obs_dim, act_dim): (usize, usize),
) {
    let decoded_actions = cfg.encoder_inputs(obs_dim, act_dim) - obs_dim;
    let init = cfg.init;
    init_with(net, seed, &|t| draw(init, t, (obs_dim, decoded_actions)));
}

/// The draw of tensor `t` under `init`, for a DreamerV3-family agent whose decoder reconstructs
/// `observation` values and `action` values (the latter zero unless the step alignment is the
/// paper code's).
pub fn draw(init: WeightInit, t: &NamedTensor, (observation, action): (usize, usize)) -> Draw {
    match init {
        WeightInit::Ctxrace => ctxrace_draw(t),
        WeightInit::PaperCode => paper_code_draw(t, (observation, action)),
    }
}

/// The paper code's draw of tensor `t` (see the module doc).
fn paper_code_draw(t: &NamedTensor, (observation, action): (usize, usize)) -> Draw {
    let (outputs, inputs) = match t.shape.as_slice() {
        &[outputs, inputs] => (outputs, inputs),
        [_] if t.name.ends_with("bias") => return Draw::Zero,
        _ => return Draw::Keep,
    };
    let uniform = |rows: usize| fan_avg_draw(inputs, rows, Some(1.0));
    let halves = || Draw::Rows(vec![(outputs / 2, uniform(outputs / 2)); 2]);
    let net = t.name.split('.').next().unwrap_or_default();
    match (net, t.name) {
        ("mask", "mask.out.weight") => halves(),
        ("mask" | "q1" | "q2", _) => uniform(outputs),
        (_, name) if name.ends_with(".fc.weight") => fan_avg_draw(inputs, outputs, None),
        ("reward" | "critic", _) => Draw::Zero,
        ("actor", _) => halves(),
        ("decoder", _) if action > 0 && outputs == observation + action => Draw::Rows(vec![
            (observation, uniform(observation)),
            (action, uniform(action)),
        ]),
        _ => uniform(outputs),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tensor(name: &str, shape: &[usize]) -> Draw {
        let values = vec![0.0; shape.iter().product()];
        let t = NamedTensor {
            name,
            shape: shape.to_vec(),
            values: &values,
        };
        draw(WeightInit::PaperCode, &t, (108, 2))
    }

    /// Each tensor of a cMask agent at the parity widths draws as the paper code's initialiser
    /// of the module it maps to (docs/parity/one_batch.md: the standard deviations measured in
    /// the code).
    #[test]
    fn paper_code_draws_follow_the_code_module_by_module() {
        let normal =
            |i: usize, o: usize| Draw::TruncatedNormal((2.0 / (i + o) as f32).sqrt() / 0.879_625_7);
        let uniform = |i: usize, o: usize| Draw::Uniform((6.0 / (i + o) as f32).sqrt());
        assert_eq!(tensor("encoder.l0.fc.weight", &[64, 110]), normal(110, 64));
        assert_eq!(tensor("rssm.gru.fc.weight", &[192, 128]), normal(128, 192));
        assert_eq!(tensor("rssm.prior_out.weight", &[64, 64]), uniform(64, 64));
        assert_eq!(tensor("rssm.post_out.bias", &[64]), Draw::Zero);
        assert_eq!(tensor("rssm.post.ln.weight", &[64]), Draw::Keep);
        assert_eq!(tensor("rssm.initial_state.w", &[64]), Draw::Keep);
        assert_eq!(
            tensor("decoder.out.weight", &[110, 64]),
            Draw::Rows(vec![(108, uniform(64, 108)), (2, uniform(64, 2))])
        );
        assert_eq!(tensor("cont.out.weight", &[1, 64]), uniform(64, 1));
        assert_eq!(tensor("reward.out.weight", &[255, 64]), Draw::Zero);
        assert_eq!(tensor("critic.out.weight", &[255, 64]), Draw::Zero);
        assert_eq!(tensor("critic.l1.fc.weight", &[64, 64]), normal(64, 64));
        assert_eq!(
            tensor("actor.out.weight", &[4, 64]),
            Draw::Rows(vec![(2, uniform(64, 2)); 2])
        );
        assert_eq!(tensor("mask.l0.fc.weight", &[256, 108]), uniform(108, 256));
        assert_eq!(
            tensor("mask.out.weight", &[4, 256]),
            Draw::Rows(vec![(2, uniform(256, 2)); 2])
        );
        assert_eq!(tensor("q2.l1.fc.weight", &[256, 256]), uniform(256, 256));
        assert_eq!(tensor("log_alpha", &[1]), Draw::Keep);
        // the measured standard deviations of the code (one_batch.md): 0.125 for 64 → 64
        // hidden layers, 0.174 for the actor's outputs
        let Draw::Uniform(limit) = uniform(64, 2) else {
            unreachable!()
        };
        assert!((limit / 3f32.sqrt() - 0.174).abs() < 1e-3);
    }

    /// A cMask agent of the paper-code preset starts from the paper code's draws (the standard
    /// deviations measured in its code, one_batch.md), and the preset and the key say so; the
    /// default agent keeps ctxrace's.
    #[test]
    fn the_paper_code_preset_draws_the_agent_as_the_code() {
        use crate::dreamer::PolicyNets;
        use ctxrace_config::agents::{AgentConfig, ContextMode};
        let preset = AgentConfig::paper_code();
        assert_eq!(preset.dreamer.init, WeightInit::PaperCode);
        assert_eq!(AgentConfig::default().dreamer.init, WeightInit::Ctxrace);
        let table: toml::Table = "preset = \"paper-code\"\n[dreamer]\ninit = \"ctxrace\""
            .parse()
            .unwrap();
        let read = AgentConfig::from_table(table).unwrap();
        assert_eq!(read.dreamer.init, WeightInit::Ctxrace);
        let std_of = |nets: &PolicyNets, name: &str| {
            let tensors = nets.tensors();
            let x = tensors.iter().find(|t| t.name == name).unwrap().values;
            (x.iter().map(|v| v * v).sum::<f32>() / x.len() as f32).sqrt()
        };
        let cfg = |init| DreamerConfig {
            context: ContextMode::Cmask,
            units: 64,
            deter: 64,
            hidden: 64,
            head_units: 64,
            stoch: 8,
            classes: 8,
            init,
            ..preset.dreamer.clone()
        };
        let paper = PolicyNets::initial(&cfg(WeightInit::PaperCode), 108, 2).unwrap();
        let ours = PolicyNets::initial(&cfg(WeightInit::Ctxrace), 108, 2).unwrap();
        for (name, want, ctxrace) in [
            ("encoder.l1.fc.weight", 0.125, 0.072),
            ("rssm.prior_out.weight", 0.125, 0.072),
            ("actor.out.weight", 0.174, 0.072),
            ("rssm.gru.fc.weight", 0.079, 0.051),
        ] {
            let (p, o) = (std_of(&paper, name), std_of(&ours, name));
            assert!(
                (p / want - 1.0).abs() < 0.08,
                "{name}: {p} against the code's {want}"
            );
            assert!(
                (o / ctxrace - 1.0).abs() < 0.08,
                "{name}: {o} against {ctxrace}"
            );
        }
    }
}
