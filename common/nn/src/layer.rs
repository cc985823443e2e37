//! A linear layer and a stack of them on plain buffers: forward into kept traces, backward by
//! hand.
//!
//! A layer is `p = x Wᵀ (+ b)` then `y = act(LayerNorm(p))` (DreamerV3's blocks), `y = max(p, 0)`,
//! or `y = p`. Backward, from the output's gradient `∂y`: the product's gradient `∂p` (the
//! normalisation's backward pass, [`crate::kernels`]' `norm_act`), then
//! `∂W += ∂pᵀ x`, `∂b += Σ_rows ∂p`, and `∂x = ∂p W` for the input columns asked for. Input
//! columns that are mostly zero (the one-hot `z` of a state, [`crate::kernels::SparseColumns`])
//! are multiplied over their non-zeros, forward and in the weight's gradient.

use super::parameters::{update_each, NamedTensor, Parameters};
use super::weights::{Weights, WeightsError};
use crate::kernels::{
    column_sums, count_flops, dense_parts, gemm_into, norm_act_rows_bwd_into, norm_act_rows_into,
    Norm, NormAct, Operand, SparseColumns, SparseRows,
};
use std::ops::Range;

/// Hidden-layer activation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    /// `x σ(x)`, with LayerNorm before it (DreamerV3).
    SiluNorm,
    /// `max(x, 0)` without normalisation (the paper's SAC networks).
    Relu,
}

/// The LayerNorms' `ε` in an [`Mlp`]'s hidden blocks.
pub const LAYER_NORM_EPS: f64 = 1e-3;

/// The sizes of an [`Mlp`]: what [`Mlp::from_weights`] is given besides its parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MlpShape {
    /// Input width.
    pub input: usize,
    /// Width of each hidden block.
    pub units: usize,
    /// Number of hidden blocks.
    pub layers: usize,
    /// Width of the output layer, if the network has one.
    pub out: Option<usize>,
    /// The hidden blocks' activation.
    pub act: Activation,
}

/// What follows a layer's product.
#[derive(Clone, Debug)]
pub enum After {
    /// `y = p`.
    Nothing,
    /// `y = act(γ (p − μ)/√(σ² + ε) + β)`.
    Norm(NormParams),
    /// `y = max(p, 0)`.
    Relu,
}

/// A normalisation's parameters, owned ([`Norm`] is their view).
#[derive(Clone, Debug)]
pub struct NormParams {
    /// `γ`.
    pub gain: Vec<f32>,
    /// `β`, of `γ`'s length.
    pub bias: Vec<f32>,
    /// `ε`.
    pub eps: f32,
    /// The activation after it.
    pub act: NormAct,
}

impl NormParams {
    fn view(&self) -> Norm<'_> {
        Norm {
            gain: &self.gain,
            bias: &self.bias,
            eps: self.eps,
            act: self.act,
        }
    }
}

/// A linear layer and what follows it: a normalisation and its activation, a ReLU, or nothing.
#[derive(Clone, Debug)]
pub struct Layer {
    inputs: usize,
    outputs: usize,
    /// `W` `[out, in]`, for the input's gradient `∂p W`.
    w: Vec<f32>,
    /// `Wᵀ` `[in, out]`, for the forward product `x Wᵀ`.
    wt: Vec<f32>,
    bias: Option<Vec<f32>>,
    after: After,
    /// Input columns that are mostly zero.
    sparse: Option<Range<usize>>,
    /// The names of its tensors in the order of [`Parameters::tensors`] (`W`, `b`, the
    /// normalisation's `γ` and `β`, those it has); empty for a layer copied from the tests' candle oracle.
    names: Vec<String>,
}

/// How a layer multiplies an input ([`Layer::split_inputs`]).
struct InputSplit<'a> {
    /// Column ranges multiplied by gemm.
    dense: Vec<Range<usize>>,
    /// The sparse columns and their non-zeros.
    sparse: Option<(Range<usize>, Found<'a>)>,
}

/// The non-zeros of an input's sparse columns: given with it, or gathered by the layer.
enum Found<'a> {
    Given(SparseRows<'a>),
    Gathered(SparseColumns),
}

impl Found<'_> {
    fn rows(&self) -> SparseRows<'_> {
        match self {
            Found::Given(r) => *r,
            Found::Gathered(g) => g.all(),
        }
    }
}

/// Rows of a layer's input: their values and, if found once already for every layer that
/// reads them ([`NonZeros`]), the non-zeros of some of their columns.
#[derive(Clone, Copy)]
pub struct Rows<'a> {
    values: &'a [f32],
    non_zeros: Option<(&'a Range<usize>, SparseRows<'a>)>,
}

impl<'a> From<&'a [f32]> for Rows<'a> {
    fn from(values: &'a [f32]) -> Self {
        Self {
            values,
            non_zeros: None,
        }
    }
}

impl<'a> From<&'a Vec<f32>> for Rows<'a> {
    fn from(values: &'a Vec<f32>) -> Self {
        values.as_slice().into()
    }
}

/// The non-zeros of some columns of a matrix whose rows many layers read (the states of an
/// imagination and their one-hot `z`), found once, block of rows by block as they are written,
/// instead of by each layer that reads them.
#[derive(Debug, Default)]
pub struct NonZeros {
    columns: Range<usize>,
    /// `None` when a block was too dense (the layers then find their own).
    found: Option<SparseColumns>,
}

impl NonZeros {
    /// Starts over, for the columns `columns`.
    pub fn reset(&mut self, columns: Range<usize>) {
        self.columns = columns;
        self.found = Some(SparseColumns::empty());
    }

    /// Finds the non-zeros of the next rows, `x` (`[rows, width]`).
    pub fn push(&mut self, x: &[f32], width: usize) {
        if let Some(found) = &mut self.found {
            match SparseColumns::gather(x, width, &self.columns) {
                Some(block) => found.append(&block),
                None => self.found = None,
            }
        }
    }

    /// The rows `r` (counted as pushed) with their values `values`.
    pub fn rows<'a>(&'a self, values: &'a [f32], r: Range<usize>) -> Rows<'a> {
        let non_zeros = self
            .found
            .as_ref()
            .filter(|f| r.end <= f.row_count())
            .map(|f| (&self.columns, f.rows(r)));
        Rows { values, non_zeros }
    }
}

/// The transpose `[cols, rows]` of the row-major `[rows, cols]` matrix `m`, in tiles that stay in
/// the cache (a plain loop writes a whole column of the result per row it reads).
fn transpose(m: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut t = vec![0f32; m.len()];
    transpose_into(m, rows, cols, &mut t);
    t
}

/// [`transpose`] into `t` (as long as `m`).
fn transpose_into(m: &[f32], rows: usize, cols: usize, t: &mut [f32]) {
    const TILE: usize = 16;
    for r0 in (0..rows).step_by(TILE) {
        let r1 = (r0 + TILE).min(rows);
        for c0 in (0..cols).step_by(TILE) {
            for c in c0..(c0 + TILE).min(cols) {
                let (dst, src) = (&mut t[c * rows + r0..c * rows + r1], &m[r0 * cols + c..]);
                for (i, d) in dst.iter_mut().enumerate() {
                    *d = src[i * cols];
                }
            }
        }
    }
}

impl Layer {
    /// The layer of `W` `[outputs, inputs]` (row-major) and `bias`, followed by `after`; its
    /// tensors unnamed (as the tests' oracle copies a layer from its candle module).
    pub fn from_values(
        w: Vec<f32>,
        (outputs, inputs): (usize, usize),
        bias: Option<Vec<f32>>,
        after: After,
    ) -> Self {
        let wt = transpose(&w, outputs, inputs);
        Self {
            inputs,
            outputs,
            w,
            wt,
            bias,
            after,
            sparse: None,
            names: Vec::new(),
        }
    }

    /// The layer `{name}.weight` `[outputs, inputs]` (and `{name}.bias` if `bias`) of
    /// `weights`, followed by `after`.
    fn from_weights(
        weights: &mut Weights,
        name: &str,
        (inputs, outputs): (usize, usize),
        bias: bool,
        after: After,
    ) -> std::result::Result<Self, WeightsError> {
        let mut names = vec![format!("{name}.weight")];
        let w = weights.take(&names[0], &[outputs, inputs])?;
        let bias = match bias {
            true => {
                names.push(format!("{name}.bias"));
                Some(weights.take(&names[1], &[outputs])?)
            }
            false => None,
        };
        Ok(Self {
            names,
            ..Self::from_values(w, (outputs, inputs), bias, after)
        })
    }

    /// The normalised block `{name}.fc` (no bias), `{name}.ln` of `weights`, then `act`:
    /// DreamerV3's hidden blocks under the names the candle modules give them.
    pub(super) fn normalised_from_weights(
        weights: &mut Weights,
        name: &str,
        (inputs, outputs): (usize, usize),
        act: NormAct,
    ) -> std::result::Result<Self, WeightsError> {
        let norm_names = [format!("{name}.ln.weight"), format!("{name}.ln.bias")];
        let norm = NormParams {
            gain: weights.take_or(&norm_names[0], &[outputs], 1.0)?,
            bias: weights.take(&norm_names[1], &[outputs])?,
            eps: LAYER_NORM_EPS as f32,
            act,
        };
        let fc = format!("{name}.fc");
        let mut layer =
            Self::from_weights(weights, &fc, (inputs, outputs), false, After::Norm(norm))?;
        layer.names.extend(norm_names);
        Ok(layer)
    }

    /// The plain product `x Wᵀ + b` of `{name}.weight`, `{name}.bias` in `weights`.
    pub(super) fn linear_from_weights(
        weights: &mut Weights,
        name: &str,
        size: (usize, usize),
    ) -> std::result::Result<Self, WeightsError> {
        Self::from_weights(weights, name, size, true, After::Nothing)
    }

    /// The same layer told that its input columns `columns` are mostly zero (a one-hot
    /// latent): the same results, fewer products.
    pub fn sparse_inputs(self, columns: Range<usize>) -> Self {
        Self {
            sparse: Some(columns),
            ..self
        }
    }

    /// Input width.
    pub fn inputs(&self) -> usize {
        self.inputs
    }

    /// Output width.
    pub fn outputs(&self) -> usize {
        self.outputs
    }

    /// `W` `[outputs, inputs]`, row-major.
    pub fn weight(&self) -> &[f32] {
        &self.w
    }

    /// `b` `[outputs]`, if the layer has one.
    pub fn bias(&self) -> Option<&[f32]> {
        self.bias.as_deref()
    }

    /// What follows the product `p = x Wᵀ (+ b)`.
    pub fn after(&self) -> &After {
        &self.after
    }

    /// Whether the output is a separate buffer from the product (a normalisation or a ReLU
    /// follows it).
    fn has_output(&self) -> bool {
        !matches!(self.after, After::Nothing)
    }

    /// How the layer multiplies `x`: the columns through gemm, and the sparse ones with their
    /// non-zeros (if the layer has such columns and they are sparse enough in `x`).
    fn split_inputs<'a>(&self, x: Rows<'a>) -> InputSplit<'a> {
        let k = self.inputs;
        let sparse = self.sparse.as_ref().and_then(|c| match x.non_zeros {
            Some((columns, given)) if columns == c => Some((c.clone(), Found::Given(given))),
            _ => Some((
                c.clone(),
                Found::Gathered(SparseColumns::gather(x.values, k, c)?),
            )),
        });
        let dense = match &sparse {
            Some((columns, _)) => dense_parts(k, columns).collect(),
            None => std::iter::once(0..k).collect(),
        };
        InputSplit { dense, sparse }
    }

    /// `product ← x Wᵀ + b` and (if something follows) `output ← after(product)` for the rows
    /// of `x`.
    pub fn forward<'a>(&self, x: impl Into<Rows<'a>>, product: &mut [f32], output: &mut [f32]) {
        let x = x.into();
        let InputSplit { dense, sparse } = self.split_inputs(x);
        let x = x.values;
        let (k, m) = (self.inputs, self.outputs);
        let rows = x.len() / k.max(1);
        let product = &mut product[..rows * m];
        let mut started = false;
        if let Some(b) = &self.bias {
            product
                .chunks_exact_mut(m)
                .for_each(|r| r.copy_from_slice(b));
            started = true;
        }
        for part in dense {
            let xs = Operand {
                data: &x[part.start..],
                row_stride: k,
                col_stride: 1,
            };
            let wt = Operand::rows(&self.wt[part.start * m..], m);
            gemm_into(product, m, started, (rows, m, part.len()), xs, wt);
            started = true;
        }
        if let Some((columns, sparse)) = sparse {
            if !started {
                product.fill(0.0);
            }
            let (wt, sparse) = (&self.wt[columns.start * m..columns.end * m], sparse.rows());
            sparse.add_products(wt, m, product);
            count_flops(2 * m * sparse.nonzeros());
        }
        match &self.after {
            After::Nothing => {}
            After::Norm(n) => norm_act_rows_into(product, n.view(), &mut output[..rows * m]),
            After::Relu => {
                for (o, &p) in output[..rows * m].iter_mut().zip(product.iter()) {
                    *o = p.max(0.0);
                }
            }
        }
    }

    /// The product's gradient `dp` from the output's `dy` over the rows of `product` (and of
    /// `output`, which a ReLU reads); the normalisation's `[∂γ, ∂β]` are added to `dnorm`
    /// (`2 out` values, [`LayerGrads::norm_mut`]; empty for a frozen layer, whose
    /// normalisation's gradients are then not computed). Without
    /// anything after the product, `dp = dy` and nothing is written.
    pub fn product_grad(
        &self,
        (product, output): (&[f32], &[f32]),
        dy: &[f32],
        dnorm: &mut [f32],
        dp: &mut [f32],
    ) {
        match &self.after {
            After::Nothing => {}
            After::Norm(n) => norm_act_rows_bwd_into((product, output), n.view(), dy, dnorm, dp),
            After::Relu => {
                for ((d, &g), &y) in dp.iter_mut().zip(dy).zip(output) {
                    *d = if y > 0.0 { g } else { 0.0 };
                }
            }
        }
    }

    /// `∂W += dpᵀ x` (and `∂b += Σ dp`) into `grads`, for the rows of `x` and `dp`.
    pub fn add_weight_grads<'a>(&self, x: impl Into<Rows<'a>>, dp: &[f32], grads: &mut LayerGrads) {
        let (k, m) = (self.inputs, self.outputs);
        let rows = dp.len() / m;
        let x = x.into();
        let InputSplit { dense, sparse } = self.split_inputs(x);
        let x = x.values;
        let dpt = Operand::transposed(dp, m);
        for part in dense {
            let xs = Operand {
                data: &x[part.start..],
                row_stride: k,
                col_stride: 1,
            };
            let dst = &mut grads.w[part.start..];
            gemm_into(dst, k, true, (m, part.len(), rows), dpt, xs);
        }
        if let Some((columns, sparse)) = sparse {
            let block = grads
                .sparse_wt
                .get_or_insert_with(|| vec![0f32; columns.len() * m]);
            let sparse = sparse.rows();
            sparse.add_weight_grads(dp, m, block);
            count_flops(2 * m * sparse.nonzeros());
        }
        if !grads.bias.is_empty() {
            column_sums(dp, &mut grads.bias);
        }
    }

    /// `dx (+)= dp W[:, columns]`: the input's gradient in `columns`, into `dx` whose rows are
    /// `row_stride` apart and whose first column is input column `columns.start`; added to
    /// what `dx` holds with `accumulate`.
    pub fn input_grad(
        &self,
        dp: &[f32],
        columns: Range<usize>,
        dx: &mut [f32],
        row_stride: usize,
        accumulate: bool,
    ) {
        let m = self.outputs;
        let rows = dp.len() / m;
        let w = Operand {
            data: &self.w[columns.start..],
            row_stride: self.inputs,
            col_stride: 1,
        };
        let dims = (rows, columns.len(), m);
        gemm_into(dx, row_stride, accumulate, dims, Operand::rows(dp, m), w);
    }

    /// `∂W` `[out, in]` whole from its dense part `w` and the sparse columns' `∂Wᵀ` rows
    /// `sparse_wt`, added into its columns in tiles of 16 x 16 (a column of `∂W` is a cache line
    /// a value; a tile's sixteen lines stay in the cache while it is written).
    fn whole_weight(&self, mut w: Vec<f32>, sparse_wt: Option<Vec<f32>>) -> Vec<f32> {
        const TILE: usize = 16;
        if let (Some(block), Some(columns)) = (sparse_wt, &self.sparse) {
            let (m, k) = (self.outputs, self.inputs);
            for c0 in (0..columns.len()).step_by(TILE) {
                for j0 in (0..m).step_by(TILE) {
                    for c in c0..(c0 + TILE).min(columns.len()) {
                        for j in j0..(j0 + TILE).min(m) {
                            w[j * k + columns.start + c] += block[c * m + j];
                        }
                    }
                }
            }
        }
        w
    }

    /// Zeroed gradients of this layer's parameters.
    pub fn zero_grads(&self) -> LayerGrads {
        LayerGrads {
            w: vec![0f32; self.outputs * self.inputs],
            sparse_wt: None,
            bias: vec![0f32; if self.bias.is_some() { self.outputs } else { 0 }],
            norm: vec![
                0f32;
                if matches!(self.after, After::Norm(..)) {
                    2 * self.outputs
                } else {
                    0
                }
            ],
        }
    }
}

impl Parameters for Layer {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        let (m, k) = (self.outputs, self.inputs);
        let mut values: Vec<(&[f32], Vec<usize>)> = vec![(&self.w, vec![m, k])];
        if let Some(b) = &self.bias {
            values.push((b, vec![m]));
        }
        if let After::Norm(n) = &self.after {
            values.extend([(&n.gain[..], vec![m]), (&n.bias[..], vec![m])]);
        }
        let names = self.names.iter().map(String::as_str);
        names
            .zip(values)
            .map(|(name, (values, shape))| NamedTensor {
                name,
                shape,
                values,
            })
            .collect()
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        f(0, &mut self.w);
        let mut i = 1;
        if let Some(b) = &mut self.bias {
            f(i, b);
            i += 1;
        }
        if let After::Norm(n) = &mut self.after {
            f(i, &mut n.gain);
            f(i + 1, &mut n.bias);
        }
        transpose_into(&self.w, self.outputs, self.inputs, &mut self.wt);
    }
}

/// The gradients of one layer's parameters.
#[derive(Clone, Debug)]
pub struct LayerGrads {
    /// `∂W` `[out, in]`, but for the sparse columns.
    w: Vec<f32>,
    /// `∂Wᵀ` of the sparse columns, `[columns, out]` (the layout their row-by-row sums write).
    sparse_wt: Option<Vec<f32>>,
    /// `∂b` (empty without a bias).
    bias: Vec<f32>,
    /// `[∂γ, ∂β]` of the normalisation (empty without one).
    norm: Vec<f32>,
}

impl LayerGrads {
    /// The gradients of `layer`'s tensors in the order of [`Parameters::tensors`] (a frozen
    /// normalisation's empty), added to `out`.
    pub fn push_tensors(self, layer: &Layer, out: &mut Vec<Vec<f32>>) {
        let Self {
            w,
            sparse_wt,
            bias,
            mut norm,
        } = self;
        out.push(layer.whole_weight(w, sparse_wt));
        if layer.bias.is_some() {
            out.push(bias);
        }
        if let After::Norm(..) = layer.after {
            let norm_bias = norm.split_off(norm.len().min(layer.outputs));
            out.extend([norm, norm_bias]);
        }
    }

    /// `[∂γ, ∂β]` of the normalisation (empty without one), for [`Layer::product_grad`].
    pub fn norm_mut(&mut self) -> &mut [f32] {
        &mut self.norm
    }

    /// `self += other` (the same layer's).
    pub fn add(&mut self, other: &Self) {
        let add = |a: &mut Vec<f32>, b: &Vec<f32>| a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
        add(&mut self.w, &other.w);
        add(&mut self.bias, &other.bias);
        add(&mut self.norm, &other.norm);
        match (&mut self.sparse_wt, &other.sparse_wt) {
            (Some(a), Some(b)) => add(a, b),
            (None, Some(b)) => self.sparse_wt = Some(b.clone()),
            _ => {}
        }
    }
}

/// A multi-layer perceptron: its hidden blocks (`Linear → [LayerNorm] → activation`), then its
/// output layer if it has one.
#[derive(Clone, Debug)]
pub struct Mlp {
    pub(super) layers: Vec<Layer>,
}

/// What a [`Mlp`]'s forward pass keeps for its backward pass, for a fixed number of rows:
/// each layer's product and output, and the backward pass's scratch.
#[derive(Debug, Default)]
pub struct MlpTrace {
    rows: usize,
    products: Vec<Vec<f32>>,
    outputs: Vec<Vec<f32>>,
    /// The backward pass's gradients at a layer's output, at its input and at its product.
    grad_out: Vec<f32>,
    grad_in: Vec<f32>,
    grad_product: Vec<f32>,
}

/// The gradients of a [`Mlp`]'s parameters.
#[derive(Clone, Debug)]
pub struct MlpGrads {
    pub(super) layers: Vec<LayerGrads>,
}

impl Mlp {
    /// The network of `layers`, in order (the last its output layer, if it has one).
    pub fn from_layers(layers: Vec<Layer>) -> Self {
        Self { layers }
    }

    /// The network of `shape` read from `weights` under the names the checkpoints give its
    /// parameters, after `prefix` (`"encoder."`; empty for none): `l{i}.fc` and `l{i}.ln` for
    /// the hidden blocks, `out` for the output layer.
    pub fn from_weights(
        weights: &mut Weights,
        prefix: &str,
        shape: &MlpShape,
    ) -> std::result::Result<Self, WeightsError> {
        let mut layers = Vec::with_capacity(shape.layers + 1);
        let mut width = shape.input;
        for i in 0..shape.layers {
            let block = format!("{prefix}l{i}");
            let size = (width, shape.units);
            layers.push(match shape.act {
                Activation::SiluNorm => {
                    Layer::normalised_from_weights(weights, &block, size, NormAct::Silu)?
                }
                Activation::Relu => {
                    Layer::from_weights(weights, &format!("{block}.fc"), size, true, After::Relu)?
                }
            });
            width = shape.units;
        }
        if let Some(out) = shape.out {
            let name = format!("{prefix}out");
            layers.push(Layer::linear_from_weights(weights, &name, (width, out))?);
        }
        Ok(Self { layers })
    }

    /// The same network told that its input columns `columns` are mostly zero (the one-hot
    /// `z` of `[h, z, c]`), as [`Mlp::sparse_inputs`].
    pub fn sparse_inputs(mut self, columns: Range<usize>) -> Self {
        if let Some(first) = self.layers.first_mut() {
            first.sparse = Some(columns);
        }
        self
    }

    /// Output width.
    pub fn outputs(&self) -> usize {
        self.layers.last().map_or(0, |l| l.outputs)
    }

    /// Its layers, first to last (the output layer last, if it has one).
    pub fn layers(&self) -> &[Layer] {
        &self.layers
    }

    /// Buffers for the forward and backward passes over `rows` rows.
    pub fn trace(&self, rows: usize) -> MlpTrace {
        let mut trace = MlpTrace::default();
        self.fit(&mut trace, rows);
        trace
    }

    /// Sizes `trace` for `rows` rows (reusing its buffers).
    pub fn fit(&self, trace: &mut MlpTrace, rows: usize) {
        let n = self.layers.len();
        trace.rows = rows;
        trace.products.resize_with(n, Vec::new);
        trace.outputs.resize_with(n, Vec::new);
        let widest = self.layers.iter().map(|l| l.outputs).max().unwrap_or(0);
        for (i, l) in self.layers.iter().enumerate() {
            trace.products[i].resize(rows * l.outputs, 0.0);
            let out = if l.has_output() { rows * l.outputs } else { 0 };
            trace.outputs[i].resize(out, 0.0);
        }
        let widest = widest.max(self.layers.iter().map(|l| l.inputs).max().unwrap_or(0));
        for buf in [
            &mut trace.grad_out,
            &mut trace.grad_in,
            &mut trace.grad_product,
        ] {
            buf.resize(rows * widest, 0.0);
        }
    }

    /// The network on the rows of `x`, kept as the rows `rows` of `trace`.
    pub fn forward<'a>(&self, x: impl Into<Rows<'a>>, trace: &mut MlpTrace, rows: Range<usize>) {
        let x = x.into();
        for (i, layer) in self.layers.iter().enumerate() {
            // this layer's buffers, and the layers' below it to read its input from
            let (products_below, products) = trace.products.split_at_mut(i);
            let (outputs_below, outputs) = trace.outputs.split_at_mut(i);
            let input: Rows = match i.checked_sub(1) {
                None => x,
                Some(j) => {
                    let below = &self.layers[j];
                    let kept = if below.has_output() {
                        &outputs_below[j]
                    } else {
                        &products_below[j]
                    };
                    kept[rows.start * below.outputs..rows.end * below.outputs].into()
                }
            };
            let span = rows.start * layer.outputs..rows.end * layer.outputs;
            let output: &mut [f32] = if layer.has_output() {
                &mut outputs[0][span.clone()]
            } else {
                &mut []
            };
            layer.forward(input, &mut products[0][span], output);
        }
    }

    /// The output of the rows `rows` of `trace`.
    pub fn output<'a>(&self, trace: &'a MlpTrace, rows: Range<usize>) -> &'a [f32] {
        match self.layers.len().checked_sub(1) {
            Some(last) => self.layer_output(trace, last, rows),
            None => &[],
        }
    }

    /// The backward pass over the rows `rows` of `trace` (whose input rows are `x`) from the
    /// output's gradient `dy`: the parameters' gradients added to `grads`, if given, and the
    /// input's gradient in `dx.columns`, if asked.
    pub fn backward<'a>(
        &self,
        x: impl Into<Rows<'a>>,
        trace: &mut MlpTrace,
        rows: Range<usize>,
        dy: &[f32],
        mut grads: Option<&mut MlpGrads>,
        mut dx: Option<InputGrad>,
    ) {
        let Some(last) = self.layers.len().checked_sub(1) else {
            return;
        };
        let x = x.into();
        let n = rows.len();
        let mut cur = std::mem::take(&mut trace.grad_out);
        let mut next = std::mem::take(&mut trace.grad_in);
        let mut dp_buf = std::mem::take(&mut trace.grad_product);
        for (i, layer) in self.layers.iter().enumerate().rev() {
            let m = layer.outputs;
            let span = rows.start * m..rows.end * m;
            // the gradient at this layer's output: the caller's, or what the layer above left
            let g = if i == last {
                &dy[..n * m]
            } else {
                &cur[..n * m]
            };
            let dnorm = match grads.as_deref_mut() {
                Some(gr) => &mut gr.layers[i].norm[..],
                None => &mut [],
            };
            let dp = if layer.has_output() {
                let kept = (&trace.products[i][span.clone()], &trace.outputs[i][span]);
                layer.product_grad(kept, g, dnorm, &mut dp_buf[..n * m]);
                &dp_buf[..n * m]
            } else {
                g
            };
            if let Some(gr) = grads.as_deref_mut() {
                let input = match i.checked_sub(1) {
                    None => x,
                    Some(j) => self.layer_output(trace, j, rows.clone()).into(),
                };
                layer.add_weight_grads(input, dp, &mut gr.layers[i]);
            }
            if i > 0 {
                let k = layer.inputs;
                layer.input_grad(dp, 0..k, &mut next[..n * k], k, false);
            } else if let Some(d) = dx.take() {
                layer.input_grad(dp, d.columns, d.data, d.row_stride, d.accumulate);
            }
            std::mem::swap(&mut cur, &mut next);
        }
        trace.grad_out = cur;
        trace.grad_in = next;
        trace.grad_product = dp_buf;
    }

    /// The output of layer `j` over the rows `rows` of `trace`.
    fn layer_output<'a>(&self, trace: &'a MlpTrace, j: usize, rows: Range<usize>) -> &'a [f32] {
        let layer = &self.layers[j];
        let kept = if layer.has_output() {
            &trace.outputs[j]
        } else {
            &trace.products[j]
        };
        &kept[rows.start * layer.outputs..rows.end * layer.outputs]
    }

    /// Zeroed gradients of the parameters.
    pub fn zero_grads(&self) -> MlpGrads {
        MlpGrads {
            layers: self.layers.iter().map(Layer::zero_grads).collect(),
        }
    }
}

impl Parameters for Mlp {
    fn tensors(&self) -> Vec<NamedTensor<'_>> {
        self.layers.iter().flat_map(|l| l.tensors()).collect()
    }

    fn update(&mut self, f: &mut dyn FnMut(usize, &mut [f32])) {
        update_each(self.layers.iter_mut().map(|l| l as &mut dyn Parameters), f);
    }
}

impl MlpGrads {
    /// The gradients of `mlp`'s tensors in the order of [`Parameters::tensors`].
    pub fn into_tensors(self, mlp: &Mlp) -> Vec<Vec<f32>> {
        let mut out = Vec::new();
        self.push_tensors(mlp, &mut out);
        out
    }

    /// [`MlpGrads::into_tensors`], added to `out`.
    pub fn push_tensors(self, mlp: &Mlp, out: &mut Vec<Vec<f32>>) {
        for (g, layer) in self.layers.into_iter().zip(&mlp.layers) {
            g.push_tensors(layer, out);
        }
    }

    /// `self += other` (the same network's).
    pub fn add(&mut self, other: &Self) {
        for (a, b) in self.layers.iter_mut().zip(&other.layers) {
            a.add(b);
        }
    }
}

/// Where a backward pass writes an input's gradient: the input columns `columns`, into `data`
/// whose rows are `row_stride` apart and whose first column is input column `columns.start`,
/// added to what it holds with `accumulate`.
pub struct InputGrad<'a> {
    /// The destination.
    pub data: &'a mut [f32],
    /// The distance of its rows.
    pub row_stride: usize,
    /// The input columns to compute.
    pub columns: Range<usize>,
    /// Add to the destination instead of overwriting it.
    pub accumulate: bool,
}

impl<'a> InputGrad<'a> {
    /// The input columns `columns` into `data` (rows `row_stride` apart), added to it with
    /// `accumulate`.
    pub fn new(
        data: &'a mut [f32],
        row_stride: usize,
        columns: Range<usize>,
        accumulate: bool,
    ) -> Self {
        Self {
            data,
            row_stride,
            columns,
            accumulate,
        }
    }
}
