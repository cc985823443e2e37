//! The world model's and the critics' row losses, differentiated by hand: the two-hot heads'
//! decoded values, the cross-entropy against fixed targets and the KL divergence of the unimix
//! categoricals, each a forward function over rows and its backward pass, on the fused row
//! kernels ([`crate::kernels`]; each checked against candle's composed operations by its candle
//! op in the tests' oracle, `ctxrace-oracle`).

use super::kernels::{
    cross_entropy_rows, cross_entropy_rows_bwd, decode_rows, decode_rows_bwd, kl_rows, kl_rows_bwd,
    Unimix,
};

/// `out_i = symexp(Σ_k softmax(l_i)_k b_k)` for the rows `l_i` of `logits` (`bins.len()` values
/// each): the two-hot heads' decoded values (the oracle's `TwoHot::decode`).
pub fn twohot_decode(logits: &[f32], bins: &[f32], out: &mut [f32]) {
    decode_rows(logits, bins, out);
}

/// The backward pass of [`twohot_decode`]: `dl` from the values' gradients `g`.
pub fn twohot_decode_backward(logits: &[f32], bins: &[f32], g: &[f32], dl: &mut [f32]) {
    decode_rows_bwd(logits, bins, g, dl);
}

/// `out_i = −Σ_k t_ik log softmax(l_i)_k` for the rows of `logits` and of fixed `targets`
/// (the oracle's `kernels::soft_cross_entropy`).
pub fn soft_cross_entropy(logits: &[f32], targets: &[f32], out: &mut [f32]) {
    if !out.is_empty() {
        cross_entropy_rows(logits, targets, out);
    }
}

/// The backward pass of [`soft_cross_entropy`]: `dl` from the losses' gradients `g`.
pub fn soft_cross_entropy_backward(logits: &[f32], targets: &[f32], g: &[f32], dl: &mut [f32]) {
    if !g.is_empty() {
        cross_entropy_rows_bwd(logits, targets, g, dl);
    }
}

/// `out_i = KL(p_a ‖ p_b)` of the unimix categoricals (`classes` each, mixed with `unimix`
/// uniform) with logits the rows `a_i` and `b_i`, summed over each row's variables
/// (the oracle's `kernels::categorical_kl`).
pub fn categorical_kl(a: &[f32], b: &[f32], classes: usize, unimix: f32, out: &mut [f32]) {
    out.fill(0.0);
    if out.is_empty() || classes == 0 {
        return;
    }
    let per_row = a.len() / out.len();
    kl_rows(Unimix { classes, unimix }, a, b, per_row, out);
}

/// The backward pass of [`categorical_kl`] from the divergences' gradients `g`: the logits'
/// gradients into `da` and `db`, each left alone when empty.
pub fn categorical_kl_backward(
    a: &[f32],
    b: &[f32],
    g: &[f32],
    (classes, unimix): (usize, f32),
    (da, db): (&mut [f32], &mut [f32]),
) {
    if g.is_empty() || classes == 0 {
        return;
    }
    let per_row = a.len() / g.len();
    kl_rows_bwd(Unimix { classes, unimix }, a, b, g, per_row, da, db);
}
