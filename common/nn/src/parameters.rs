//! A network's trainable tensors where they live: visited by name for the optimiser, the
//! seeded initialisation, Polyak averaging and safetensors files, so that the networks the
//! learner trains are the ones it saves and the actors run, with no copy in between.
//!
//! Initialisation ([`init`]), in sorted name order over all the networks given, so that a seed
//! always gives the same weights: matrices `[out, in]` uniform in `±1/√in` (PyTorch's default
//! for linear layers), vectors named `*.bias` zero, other vectors (LayerNorm gains, a learned
//! initial state, `log α`) left at the value the network was built with
//! ([`crate::Weights::initial`]). [`init_with`] draws each tensor as a rule says instead
//! ([`fan_avg_draw`]: the draws of the paper's PyTorch code).

use crate::weights::WeightsError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safetensors::tensor::TensorView;
use safetensors::Dtype;

/// One trainable tensor: its name in a weights file, its shape and its values (row-major).
#[derive(Clone, Debug)]
pub struct NamedTensor<'a> {
    /// The name (`encoder.l0.fc.weight`).
    pub name: &'a str,
    /// The shape.
    pub shape: Vec<usize>,
    /// The values.
    pub values: &'a [f32],
}

/// A network's trainable tensors, in an order fixed by its architecture.
pub trait Parameters {
    /// Every tensor.
    fn tensors(&self) -> Vec<NamedTensor<'_>>;

    /// Calls `f(i, values)` for the `i`-th tensor of [`Parameters::tensors`], for each, letting
    /// it change the values; then refreshes whatever the network derives from them.
    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32]));
}

/// Several networks trained or saved together, as one (their tensors one after the other).
impl Parameters for [&mut dyn Parameters] {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        self.iter().flat_map(|n| n.tensors()).collect()
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        update_each(self.iter_mut().map(|n| &mut **n), f);
    }
}

/// [`Parameters::update`] of several networks as one: `f`'s index runs on from one network's
/// tensors to the next's (for a struct of networks implementing [`Parameters`]).
pub fn update_each<'a: 'b, 'b>(
    nets: impl IntoIterator<Item = &'b mut (dyn Parameters + 'a)>,
    f: &mut dyn FnMut(usize, &mut [f32]),
) {
    let mut first = 0;
    for net in nets {
        let count = net.tensors().len();
        net.update(&mut |i, values| f(first + i, values));
        first += count;
    }
}

/// The number of scalar parameters of `net`.
pub fn count<P: Parameters + ?Sized>(net: &P) -> usize {
    net.tensors().iter().map(|t| t.values.len()).sum()
}

/// How a tensor's initial values are drawn ([`init_with`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Draw {
    /// Left at the value the network was built with.
    Keep,
    /// Zero.
    Zero,
    /// Uniform in `[−limit, limit]`.
    Uniform(f32),
    /// Normal of standard deviation `std` (before truncation), redrawn outside `±2 std`
    /// (PyTorch's `trunc_normal_(std, a = −2 std, b = 2 std)`).
    TruncatedNormal(f32),
    /// A matrix's rows in blocks, each `(rows, draw)` (layers joined into one, as a head's
    /// mean and standard deviation).
    Rows(Vec<(usize, Draw)>),
}

impl Draw {
    /// Appends `count` values drawn from `rng` to `out`; `Keep` appends the `current` ones.
    fn fill(&self, current: &[f32], count: usize, rng: &mut ChaCha8Rng, out: &mut Vec<f32>) {
        match self {
            Draw::Keep => out.extend_from_slice(&current[..count.min(current.len())]),
            Draw::Zero => out.extend(std::iter::repeat_n(0.0, count)),
            &Draw::Uniform(limit) => {
                out.extend((0..count).map(|_| rng.random_range(-limit..=limit)));
            }
            Draw::TruncatedNormal(std) => {
                let Ok(normal) = rand_distr::Normal::new(0.0, *std) else {
                    return out.extend(std::iter::repeat_n(0.0, count));
                };
                out.extend((0..count).map(|_| loop {
                    let x: f32 = rng.sample(normal);
                    if x.abs() <= 2.0 * std {
                        break x;
                    }
                }));
            }
            Draw::Rows(blocks) => {
                let width = current.len() / blocks.iter().map(|b| b.0).sum::<usize>().max(1);
                let mut start = 0;
                for (rows, draw) in blocks {
                    let end = (start + rows * width).min(current.len());
                    draw.fill(&current[start..end], end - start, rng, out);
                    start = end;
                }
            }
        }
    }
}

/// ctxrace's draw (see the module doc): matrices `[out, in]` uniform in `±1/√in`, vectors named
/// `*.bias` zero, others kept.
pub fn ctxrace_draw(t: &NamedTensor) -> Draw {
    match t.shape.as_slice() {
        [_, inp] => Draw::Uniform(1.0 / (*inp as f32).sqrt()),
        [_] if t.name.ends_with("bias") => Draw::Zero,
        _ => Draw::Keep,
    }
}

/// The draws of DreamerV3's PyTorch code (`tools.weight_init`, `uniform_weight_init`) for a
/// matrix of `inputs` columns and `outputs` rows, `fan_avg = (in + out) / 2`: a hidden layer's
/// truncated normal of variance `1 / fan_avg`; an output layer's uniform of variance
/// `scale / fan_avg` (`scale` 1 for logits, decoder, continue and actor, 0 for reward and
/// critic); Xavier's uniform is the latter with scale 1.
pub fn fan_avg_draw(inputs: usize, outputs: usize, output_scale: Option<f32>) -> Draw {
    let fan_avg = (inputs + outputs) as f32 / 2.0;
    match output_scale {
        None => Draw::TruncatedNormal((1.0 / fan_avg).sqrt() / 0.879_625_7),
        Some(0.0) => Draw::Zero,
        Some(scale) => Draw::Uniform((3.0 * scale / fan_avg).sqrt()),
    }
}

/// Draws `net`'s initial weights from `seed` with ctxrace's draw (see the module doc).
pub fn init<P: Parameters + ?Sized>(net: &mut P, seed: u64) {
    init_with(net, seed, &ctxrace_draw);
}

/// Draws `net`'s initial weights from `seed`, each tensor as `draw` says, in sorted name order
/// from one generator (a seed always gives the same weights).
pub fn init_with<P: Parameters + ?Sized>(
    net: &mut P,
    seed: u64,
    draw: &dyn Fn(&NamedTensor) -> Draw,
) {
    let tensors = net.tensors();
    let mut order: Vec<usize> = (0..tensors.len()).collect();
    order.sort_by(|&a, &b| tensors[a].name.cmp(tensors[b].name));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut drawn: Vec<Option<Vec<f32>>> = vec![None; tensors.len()];
    for i in order {
        let t = &tensors[i];
        let how = draw(t);
        if how != Draw::Keep {
            let mut values = Vec::with_capacity(t.values.len());
            how.fill(t.values, t.values.len(), &mut rng, &mut values);
            drawn[i] = Some(values);
        }
    }
    net.update(&mut |i, values| match &drawn[i] {
        Some(new) if new.len() == values.len() => values.copy_from_slice(new),
        _ => {}
    });
}

/// `net`'s tensors as safetensors bytes (`f32`, under their names).
pub fn to_safetensors<P: Parameters + ?Sized>(net: &P) -> Result<Vec<u8>, WeightsError> {
    let tensors = net.tensors();
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|t| t.values.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let views = tensors
        .iter()
        .zip(&bytes)
        .map(|(t, b)| {
            TensorView::new(Dtype::F32, t.shape.clone(), b)
                .map(|view| (t.name, view))
                .map_err(|e| WeightsError::Format(format!("tensor '{}': {e}", t.name)))
        })
        .collect::<Result<Vec<_>, _>>()?;
    safetensors::serialize(views, None).map_err(|e| WeightsError::Format(e.to_string()))
}

/// Sets `net`'s tensors to those of the safetensors `bytes`: every name and shape must match,
/// and no tensor may be left over; on an error `net` is unchanged.
pub fn load_safetensors<P: Parameters + ?Sized>(
    net: &mut P,
    bytes: &[u8],
) -> Result<(), WeightsError> {
    let mut weights = crate::Weights::from_safetensors(bytes)?;
    let loaded = net
        .tensors()
        .iter()
        .map(|t| weights.take(t.name, &t.shape))
        .collect::<Result<Vec<_>, _>>()?;
    weights.finish()?;
    net.update(&mut |i, values| values.copy_from_slice(&loaded[i]));
    Ok(())
}

/// `target ← (1 − τ) target + τ source`, tensor by tensor (networks of one architecture).
pub fn polyak<P: Parameters + ?Sized>(target: &mut P, source: &P, tau: f64) {
    let source = source.tensors();
    let (keep, take) = ((1.0 - tau) as f32, tau as f32);
    target.update(&mut |i, values| {
        for (t, &s) in values.iter_mut().zip(source[i].values) {
            *t = *t * keep + s * take;
        }
    });
}

/// `target ← source`, tensor by tensor (networks of one architecture).
pub fn copy<P: Parameters + ?Sized>(target: &mut P, source: &P) {
    let source = source.tensors();
    target.update(&mut |i, values| values.copy_from_slice(source[i].values));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Activation, Mlp, MlpShape, Weights};

    /// A few matrices as a network.
    struct Matrices(Vec<(String, [usize; 2], Vec<f32>)>);

    impl Parameters for Matrices {
        fn tensors(&self) -> Vec<NamedTensor<'_>> {
            self.0
                .iter()
                .map(|(name, shape, values)| NamedTensor {
                    name: name.as_str(),
                    shape: shape.to_vec(),
                    values: values.as_slice(),
                })
                .collect()
        }

        fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
            for (i, (_, _, values)) in self.0.iter_mut().enumerate() {
                f(i, values);
            }
        }
    }

    fn std_of(x: &[f32]) -> f32 {
        let mean = x.iter().sum::<f32>() / x.len() as f32;
        (x.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / x.len() as f32).sqrt()
    }

    /// The paper code's draws have the variances its PyTorch initialisers give: `1 / fan_avg`
    /// for hidden layers (truncated at two standard deviations of the normal drawn), `scale /
    /// fan_avg` for output layers, zero at scale 0; joined layers draw each block by its own
    /// rule; a seed gives the same weights.
    #[test]
    fn fan_avg_draws_have_the_torch_initialisers_variances() {
        let (inp, out) = (200, 120);
        let net = || {
            Matrices(vec![
                ("hidden".into(), [out, inp], vec![0.0; out * inp]),
                ("head".into(), [out, inp], vec![0.0; out * inp]),
                ("joined".into(), [4, inp], vec![7.0; 4 * inp]),
            ])
        };
        let rule = move |t: &NamedTensor<'_>| -> Draw {
            match t.name {
                "hidden" => fan_avg_draw(inp, out, None),
                "head" => fan_avg_draw(inp, out, Some(1.0)),
                _ => Draw::Rows(vec![(2, fan_avg_draw(inp, 2, Some(0.0))), (2, Draw::Keep)]),
            }
        };
        let (mut a, mut b) = (net(), net());
        init_with(&mut a, 5, &rule);
        init_with(&mut b, 5, &rule);
        assert_eq!(a.0, b.0);
        let fan_avg = (inp + out) as f32 / 2.0;
        let hidden = &a.0[0].2;
        let limit = 2.0 * (1.0 / fan_avg).sqrt() / 0.879_625_7;
        assert!(hidden.iter().all(|x| x.abs() <= limit));
        let want = (1.0 / fan_avg).sqrt();
        assert!(
            (std_of(hidden) / want - 1.0).abs() < 0.03,
            "{}",
            std_of(hidden)
        );
        let head = &a.0[1].2;
        assert!((std_of(head) / want - 1.0).abs() < 0.03, "{}", std_of(head));
        let joined = &a.0[2].2;
        assert!(joined[..2 * inp].iter().all(|&x| x == 0.0));
        assert!(joined[2 * inp..].iter().all(|&x| x == 7.0));
    }

    /// Weights of another architecture are refused by name and leave the network unchanged;
    /// Polyak averaging and copies blend tensor by tensor.
    #[test]
    fn loading_checks_names_and_polyak_blends() {
        let shape = |units| MlpShape {
            input: 3,
            units,
            layers: 1,
            out: Some(2),
            act: Activation::Relu,
        };
        let build = |units, seed| {
            let mut net = Mlp::from_weights(&mut Weights::initial(), "q.", &shape(units)).unwrap();
            init(&mut net, seed);
            net
        };
        let (mut a, b, other) = (build(4, 1), build(4, 2), build(5, 1));
        let before = to_safetensors(&a).unwrap();
        let err = load_safetensors(&mut a, &to_safetensors(&other).unwrap()).unwrap_err();
        assert!(err.to_string().contains("q.l0.fc.weight"), "{err}");
        assert_eq!(to_safetensors(&a).unwrap(), before);
        let original = a.clone();
        polyak(&mut a, &b, 0.25);
        for ((x, y), z) in a.tensors().iter().zip(b.tensors()).zip(original.tensors()) {
            for ((x, y), z) in x.values.iter().zip(y.values).zip(z.values) {
                assert_eq!(*x, z * 0.75 + y * 0.25);
            }
        }
        copy(&mut a, &b);
        assert_eq!(to_safetensors(&a).unwrap(), to_safetensors(&b).unwrap());
    }
}
