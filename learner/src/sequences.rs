//! A sequence batch of the replay as candle tensors, for the tests' candle compositions of the
//! world model and cMask's mask SAC (the training steps read the batch's rows as they are).

use candle_core::{Device, Result, Tensor};
use ctxrace_config::agents::CONTEXT_DIM;
use ctxrace_config::SequenceBatch;

/// A sequence batch as tensors, `B` sequences of `T` steps.
pub(crate) struct SeqData {
    /// `B`.
    pub(crate) batch: usize,
    /// `T`.
    pub(crate) length: usize,
    /// `[B, T, O]`.
    pub(crate) obs: Tensor,
    /// `[B, T]`.
    pub(crate) reward: Tensor,
    /// `[B, T]`.
    pub(crate) first: Tensor,
    /// `[B, T]`.
    pub(crate) terminal: Tensor,
    /// `[B, T, 2]`.
    pub(crate) context: Tensor,
    /// `[B, T, 2]` the mask that chose the action before step `t`.
    pub(crate) mask: Tensor,
}

impl SeqData {
    pub(crate) fn new(b: &SequenceBatch, obs_dim: usize, act_dim: usize) -> Result<Self> {
        b.validate(obs_dim, act_dim)
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        let dev = &Device::Cpu;
        let (bs, t) = (b.batch, b.length);
        Ok(Self {
            batch: bs,
            length: t,
            obs: Tensor::from_slice(&b.obs, (bs, t, obs_dim), dev)?,
            reward: Tensor::from_slice(&b.reward, (bs, t), dev)?,
            first: Tensor::from_slice(&b.is_first, (bs, t), dev)?,
            terminal: Tensor::from_slice(&b.is_terminal, (bs, t), dev)?,
            context: Tensor::from_slice(&b.context, (bs, t, CONTEXT_DIM), dev)?,
            mask: Tensor::from_slice(&b.mask, (bs, t, CONTEXT_DIM), dev)?,
        })
    }

    /// `x` `[B, T, …]` as `[B·T, k]`.
    pub(crate) fn flat(&self, x: &Tensor) -> Result<Tensor> {
        x.reshape((self.batch * self.length, ()))
    }
}
