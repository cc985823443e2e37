"""One training step of the paper's own DreamerV3 or cbDreamer (lilpharaoh1/context-f110 at
c0fd903, torch on CPU, one thread) on one batch from fixed weights and fixed noise, written for
ctxrace's test
`learner/tests/paper_one_batch.rs` (docs/parity/one_batch.md).

    deploy/paper_parity.sh export DIR          (with WIDTH=16 STOCH=4 LENGTH=16 MODEL_LR AC_LR)
    /work/venv-paper/bin/python deploy/paper_one_batch.py DIR OUT.safetensors \
        [--model dreamerv3|cmask] [--buffer BUFFER [--first-episode K]] [--mask-units U] \
        [--head-scale S]

builds the paper's agent (`Utils/dreamerv3/dreamerv3.py` `DreamerV3`, or with `--model cmask`
cbDreamer's, `Utils/cbdreamer/dreamerv3.py`, its mask SAC `CtxMask` at U units instead of its
hard-coded 256; its configs.yaml at the widths the export wrote) with torch seed SEED, gives it
episodes K to K + 39 of BUFFER (a paper run's `Buffer/` folder of `eps_K-N.npz`; without it,
synthetic episodes), and runs the agent's own `train()` on them: one batch of B sequences of T
steps from the code's `tools.sample_episodes`, the world model's step
(`WorldModel._train`; cbDreamer's draws the batch's masks and steps its mask SAC there), then
behaviour learning from its posterior states (`ImagBehavior._train`). It writes one
safetensors file with:

- the agent's weights under ctxrace's names, one group per ctxrace parameter store
  (`policy/`, `heads/`, `critic/`, `slow_critic/`, then the name in that store), reordered
  where the two lay a tensor out differently (see `ctxrace_weights`);
- the batch (`batch/obs`, `batch/action`, ... in `SequenceBatch`'s layout);
- the noise: what ctxrace's step 0 draws (its ChaCha8 streams, computed here), which the code's
  samples take in place of torch's random draws (`noise/model_uniform`: the posteriors'
  Gumbel uniforms; `noise/imag_normal`, `noise/imag_uniform`: the imagined actions' normals
  and priors' uniforms), so that both sides sample the same latents and actions;
- torch's loss terms, λ-return, return scale and gradient norms (`torch/...`), the gradient norm
  of each part (`torch/grad_norm/...`), and every gradient under ctxrace's names (`grad/...`);
- cbDreamer's: the batch's contexts and stored masks, the masks' and the mask SAC's noise
  (`noise/mask_normal`, `noise/sac_critic_normal`, `noise/sac_actor_normal`), the mask SAC's
  terms (`torch/mask_...`) and its weights after the step (`after/...`); see `MaskProbe`;
- the same terms of a second step on the same batch with the noise of ctxrace's step 1
  (`torch2/...`), after the first step's updates (Adam's moments, the slow critic, the return
  normaliser).

Three weights are moved from the code's initial values so that their paths carry gradients:
the reward head's and the critic's output layers (zero at the code's initialisation; uniform in
±`--head-scale`) and the learned initial state `W` (zero). cbDreamer's `log α` starts at
`ln 0.2`, the `α` its first step uses (the code's `log α` starts at 0 while `α` is held at 0.2
until its first update). The rest is the code's initialisation. cbDreamer's mask SAC trains only on the transitions whose next
row continues the episode, as ctxrace's (`drop_episode_ends`).
"""
import argparse
import contextlib
import glob
import json
import os
import struct
import sys

import numpy as np

SEED = 7  # torch's seed, and ctxrace's (its noise streams) in the test
BATCH, LENGTH = 4, 16
GOLDEN = 0x9E3779B97F4A7C15
MASK64 = (1 << 64) - 1


# ---------------------------------------------------------------- ctxrace's noise, in Python
def pcg32_seed(state):
    """rand_core 0.9's `SeedableRng::seed_from_u64`: 32 seed bytes from PCG32."""
    out = bytearray()
    for _ in range(8):
        state = (state * 6364136223846793005 + 11634580027462260723) & MASK64
        xorshifted = (((state >> 18) ^ state) >> 27) & 0xFFFFFFFF
        rot = state >> 59
        x = ((xorshifted >> rot) | (xorshifted << ((32 - rot) & 31))) & 0xFFFFFFFF
        out += struct.pack("<I", x)
    return bytes(out)


def chacha8_words(seed_bytes, stream, count, block=0):
    """`count` u32 words of rand_chacha 0.9's `ChaCha8Rng` from `seed_bytes` after
    `set_stream(stream)`, from block `block` on: the ChaCha keystream with 4 double rounds, a
    64-bit block counter (words 12, 13) and the stream (words 14, 15)."""
    key = list(struct.unpack("<8I", seed_bytes))
    const = [0x61707865, 0x3320646E, 0x79622D32, 0x6B206574]

    def rotl(v, n):
        return ((v << n) | (v >> (32 - n))) & 0xFFFFFFFF

    def quarter(x, a, b, c, d):
        x[a] = (x[a] + x[b]) & 0xFFFFFFFF; x[d] = rotl(x[d] ^ x[a], 16)
        x[c] = (x[c] + x[d]) & 0xFFFFFFFF; x[b] = rotl(x[b] ^ x[c], 12)
        x[a] = (x[a] + x[b]) & 0xFFFFFFFF; x[d] = rotl(x[d] ^ x[a], 8)
        x[c] = (x[c] + x[d]) & 0xFFFFFFFF; x[b] = rotl(x[b] ^ x[c], 7)

    words = []
    while len(words) < count:
        state = const + key + [block & 0xFFFFFFFF, block >> 32, stream & 0xFFFFFFFF, stream >> 32]
        x = list(state)
        for _ in range(4):
            quarter(x, 0, 4, 8, 12); quarter(x, 1, 5, 9, 13)
            quarter(x, 2, 6, 10, 14); quarter(x, 3, 7, 11, 15)
            quarter(x, 0, 5, 10, 15); quarter(x, 1, 6, 11, 12)
            quarter(x, 2, 7, 8, 13); quarter(x, 3, 4, 9, 14)
        words += [(a + b) & 0xFFFFFFFF for a, b in zip(x, state)]
        block += 1
    return words[:count]


class Stream:
    """One ChaCha8 stream as ctxrace's noise reads it: consecutive u32 words (rand's
    `fill` and `next_u64`, low word first, read the same keystream)."""

    def __init__(self, seed, stream):
        self.seed, self.stream, self.words, self.pos = pcg32_seed(seed), stream, [], 0

    def word(self):
        if self.pos == len(self.words):
            self.words += chacha8_words(self.seed, self.stream, 16, len(self.words) // 16)
        self.pos += 1
        return self.words[self.pos - 1]

    def u64(self):
        lo = self.word()
        return lo | (self.word() << 32)

    def uniforms(self, count):
        """`uniform_rows`: `(f32(w >> 9 | 0x3f800000) - 1) * (high - low) + low` per word."""
        low, high = np.float32(1e-6), np.float32(1.0 - 1e-6)
        words = np.array([self.word() for _ in range(count)], dtype=np.uint32)
        unit = ((words >> 9) | np.uint32(0x3F800000)).view(np.float32) - np.float32(1.0)
        return (unit * np.float32(high - low) + low).astype(np.float32)

    def normals(self, count):
        """rand_distr 0.5's `StandardNormal` as f32 (its ziggurat, tables read from its source)."""
        return np.array([np.float32(self.normal()) for _ in range(count)], dtype=np.float32)

    def normal(self):
        x_tab, f_tab, r = ZIGGURAT
        while True:
            bits = self.u64()
            i = bits & 0xFF
            u = f64_bits(((1023 + 1) << 52) | (bits >> 12)) - 3.0
            x = u * x_tab[i]
            if abs(x) < x_tab[i + 1]:
                return x
            if i == 0:
                x, y = 1.0, 0.0
                while -2.0 * y < x * x:
                    x = np.log(self.open01()) / r
                    y = np.log(self.open01())
                return x - r if u < 0.0 else r - x
            if f_tab[i + 1] + (f_tab[i] - f_tab[i + 1]) * ((self.u64() >> 11) * 2.0 ** -53) < np.exp(-x * x / 2.0):
                return x

    def open01(self):
        return f64_bits((1023 << 52) | (self.u64() >> 12)) - (1.0 - 2.0 ** -53)


def f64_bits(bits):
    return struct.unpack("<d", struct.pack("<Q", bits))[0]


def ziggurat_tables():
    """rand_distr 0.5.1's ZIG_NORM_X, ZIG_NORM_F and ZIG_NORM_R, read from its source in
    cargo's registry (where ctxrace's build fetched it)."""
    paths = glob.glob(os.path.expanduser("~/.cargo/registry/src/*/rand_distr-0.5.1/src/ziggurat_tables.rs"))
    if not paths:
        sys.exit("rand_distr 0.5.1's source is not in ~/.cargo/registry: build ctxrace first")
    text = open(paths[0]).read()

    def table(name):
        body = text.split(f"pub static {name}: [f64; 257] =")[1].split(";")[0]
        values = [float(v) for v in body.replace("[", " ").replace("]", " ").split(",") if v.strip()]
        assert len(values) == 257, name
        return values

    r = float(text.split("pub const ZIG_NORM_R: f64 =")[1].split(";")[0])
    return table("ZIG_NORM_X"), table("ZIG_NORM_F"), r


ZIGGURAT = None


def ctxrace_noise(seed, batch, length, z, act, horizon, step, sac_rows=0):
    """What ctxrace's DreamerV3 or cMask step `step` draws (`Dreamer::sequence_rngs`: sequence b's
    stream seeded with `seed ^ (b + 1) * golden`, stream number `step`), in its order: cMask's
    masks first, `T * 2` normals of each stream (`[B * T, 2]`, `sac_rows` > 0 only); the world
    model's posterior uniforms, per step t `Z` of each stream in turn (`[T, B, Z]`); per imagined
    step the actor's normals, `T * A` of each stream (its T starts), and the prior's uniforms,
    `T * Z` of each (`[H - 1, B * T, A]` and `[H - 1, B * T, Z]`); then cMask's mask SAC, the
    critics' pass and the actor's pass, `sac_rows * 2` normals of each stream each
    (`[B * sac_rows, 2]`). Returns a dict of these arrays."""
    global ZIGGURAT
    ZIGGURAT = ZIGGURAT or ziggurat_tables()
    streams = [Stream(seed ^ (((b + 1) * GOLDEN) & MASK64), step) for b in range(batch)]
    each = lambda count, width: np.concatenate([s.normals(count * width) for s in streams]).reshape(-1, width)
    out = {"mask": each(length, 2)} if sac_rows else {}
    out["model"] = np.stack([np.stack([s.uniforms(z) for s in streams]) for _ in range(length)])
    normals, uniforms = [], []
    for _ in range(horizon - 1):
        normals.append(each(length, act))
        uniforms.append(np.concatenate([s.uniforms(length * z) for s in streams]).reshape(-1, z))
    out["action"], out["prior"] = np.stack(normals), np.stack(uniforms)
    if sac_rows:
        out["sac_critic"], out["sac_actor"] = each(sac_rows, 2), each(sac_rows, 2)
    return out


# ---------------------------------------------------------------- the batch
def synthetic_episodes(rng, with_mask, count=40):
    """Episodes shaped as the code stores them: 108 LiDAR-like values in [0, 1], actions in
    [-1, 1], small rewards, the last row terminal; with `with_mask` (cbDreamer's) a context per
    episode and a mask in (0.27, 0.73) per row."""
    episodes = {}
    for k in range(count):
        n = int(rng.integers(8, 30))
        episodes[f"eps_{k}"] = {
            "is_first": np.eye(1, n, 0).reshape(n, 1),
            "image": rng.uniform(0, 1, (n, 108)),
            "action": rng.uniform(-1, 1, (n, 2)).astype(np.float32),
            "reward": rng.normal(0.2, 0.2, (n, 1)),
            "is_terminal": np.eye(1, n, n - 1).reshape(n, 1),
        }
        if with_mask:
            episodes[f"eps_{k}"]["context"] = np.tile(rng.uniform(-0.15, 0.15, (1, 2)), (n, 1))
            episodes[f"eps_{k}"]["mask"] = rng.uniform(0.27, 0.73, (n, 2)).astype(np.float32)
    return episodes


def buffer_episodes(folder, first=0, count=40):
    """Episodes `first` to `first + count - 1` of a paper run's Buffer/ (eps_K-N.npz by K)."""
    paths = sorted(glob.glob(f"{folder}/eps_*-*.npz"),
                   key=lambda p: int(os.path.basename(p)[4:].split("-")[0]))[first:first + count]
    if not paths:
        sys.exit(f"{folder}: no eps_K-N.npz episodes from number {first} (a paper run's Buffer/ folder?)")
    episodes = {}
    for p in paths:
        with np.load(p) as d:
            episodes[os.path.basename(p)] = {k: d[k] for k in d.files}
    return episodes


def one_batch(tools, episodes):
    """One batch from the code's sampler (a fresh RandomState(0), as its train() draws it),
    the scalars' trailing axis squeezed as train() does."""
    data = next(tools.from_generator(tools.sample_episodes(episodes, LENGTH), BATCH))
    for k, v in data.items():
        if v.shape[-1] == 1:
            data[k] = v.squeeze(-1)
    first = data["is_first"]
    for t in range(1, LENGTH):
        if first[:, t].sum() == BATCH:
            sys.exit(f"every sequence starts anew at step {t}: the code takes another branch "
                     "there (its obs_step resets without zeroing the stored action); pick other "
                     "episodes")
    return data


# ---------------------------------------------------------------- weights under ctxrace's names
def joined(parts, axis=0):
    """The parts concatenated, or None where one is (a gradient not computed)."""
    return None if any(p is None for p in parts) else np.concatenate(parts, axis=axis)


def ctxrace_weights(agent, of):
    """Every weight of the agent (`of(param)`: its value or its gradient, None for none) as
    ctxrace's stores name and lay them out: torch's Linear `[out, in]` is candle's; the heads'
    first layers read the model state as `[z, h, c]` in the code and `[h, z, c]` in ctxrace
    (the z and h columns swapped; `c` is cbDreamer's context); the decoder's per-key output
    layers (image, action) are one layer in ctxrace (its `reward` output, overwritten by the
    reward head's in the code's loss, has no counterpart); the actor's mean and std layers are
    one output layer `[2A, U]`. cbDreamer's mask SAC: `mask_weights`."""
    cfg = agent._config
    z, d = cfg.dyn_stoch * cfg.dyn_discrete, cfg.dyn_deter
    wm, beh = agent._wm, agent._task_behavior
    dyn = wm.dynamics
    out = {}

    def mlp(module, prefix, store, name, layers, out_layer=None):
        params = dict(module.named_parameters())
        for i in range(layers):
            w = of(params[f"layers.{prefix}_linear{i}.weight"])
            if i == 0 and name != "encoder" and w is not None:
                w = joined([w[:, z:z + d], w[:, :z], w[:, z + d:]], axis=1)
            out[f"{store}/{name}.l{i}.fc.weight"] = w
            out[f"{store}/{name}.l{i}.ln.weight"] = of(params[f"layers.{prefix}_norm{i}.weight"])
            out[f"{store}/{name}.l{i}.ln.bias"] = of(params[f"layers.{prefix}_norm{i}.bias"])
        if out_layer is not None:
            out[f"{store}/{name}.out.weight"] = of(out_layer.weight)
            out[f"{store}/{name}.out.bias"] = of(out_layer.bias)

    mlp(wm.encoder._mlp, "Encoder", "policy", "encoder", cfg.encoder["mlp_layers"])
    for module, name in [(dyn._img_in_layers, "img_in"), (dyn._img_out_layers, "prior"),
                         (dyn._obs_out_layers, "post")]:
        out[f"policy/rssm.{name}.fc.weight"] = of(module[0].weight)
        out[f"policy/rssm.{name}.ln.weight"] = of(module[1].weight)
        out[f"policy/rssm.{name}.ln.bias"] = of(module[1].bias)
    out["policy/rssm.gru.fc.weight"] = of(dyn._cell.layers.GRU_linear.weight)
    out["policy/rssm.gru.ln.weight"] = of(dyn._cell.layers.GRU_norm.weight)
    out["policy/rssm.gru.ln.bias"] = of(dyn._cell.layers.GRU_norm.bias)
    for layer, name in [(dyn._imgs_stat_layer, "prior_out"), (dyn._obs_stat_layer, "post_out")]:
        out[f"policy/rssm.{name}.weight"] = of(layer.weight)
        out[f"policy/rssm.{name}.bias"] = of(layer.bias)
    w = of(dyn.W)
    out["policy/rssm.initial_state.w"] = None if w is None else w.reshape(-1)
    actor = beh.actor
    mlp(actor, "Actor", "policy", "actor", cfg.actor["layers"])
    out["policy/actor.out.weight"] = joined([of(actor.mean_layer.weight), of(actor.std_layer.weight)])
    out["policy/actor.out.bias"] = joined([of(actor.mean_layer.bias), of(actor.std_layer.bias)])
    dec = wm.heads["decoder"]._mlp
    mlp(dec, "Decoder", "heads", "decoder", cfg.decoder["mlp_layers"])
    out["heads/decoder.out.weight"] = joined([of(dec.mean_layer[k].weight) for k in ("image", "action")])
    out["heads/decoder.out.bias"] = joined([of(dec.mean_layer[k].bias) for k in ("image", "action")])
    for key, prefix in [("reward", "Reward"), ("cont", "Cont")]:
        head = wm.heads[key]
        mlp(head, prefix, "heads", key, cfg.reward_head["layers"] if key == "reward" else cfg.cont_head["layers"],
            head.mean_layer)
    mlp(beh.value, "Value", "critic", "critic", cfg.critic["layers"], beh.value.mean_layer)
    mlp(beh._slow_value, "Value", "slow_critic", "critic", cfg.critic["layers"], beh._slow_value.mean_layer)
    if hasattr(wm, "_ctx_mask"):
        out.update(mask_weights(wm._ctx_mask, of))
    return {k: v for k, v in out.items() if v is not None}


def mask_weights(ctx, of):
    """cbDreamer's mask SAC (`CtxMask`) under ctxrace's names: the Gaussian policy's two ReLU
    layers and its mean and log-std layers (one output layer `[2·2, U]`) as the policy store's
    `mask.`; the twin critics (`linear1-3`, `linear4-6` of the code's QNetwork, on `[o, m]`) as
    `q1.`, `q2.` of the `mask_critic` and `mask_target` stores; `log α` as `mask_alpha`."""
    out, policy = {}, ctx.policy
    for i, layer in enumerate((policy.linear1, policy.linear2)):
        out[f"policy/mask.l{i}.fc.weight"], out[f"policy/mask.l{i}.fc.bias"] = of(layer.weight), of(layer.bias)
    out["policy/mask.out.weight"] = joined([of(policy.mean_linear.weight), of(policy.log_std_linear.weight)])
    out["policy/mask.out.bias"] = joined([of(policy.mean_linear.bias), of(policy.log_std_linear.bias)])
    for store, net in (("mask_critic", ctx.critic), ("mask_target", ctx.critic_target)):
        for q, first in (("q1", 1), ("q2", 4)):
            for i, name in enumerate(("l0.fc", "l1.fc", "out")):
                layer = getattr(net, f"linear{first + i}")
                out[f"{store}/{q}.{name}.weight"], out[f"{store}/{q}.{name}.bias"] = of(layer.weight), of(layer.bias)
    out["mask_alpha/log_alpha"] = of(ctx.log_alpha)
    return out


def value_of(p):
    return p.detach().numpy().astype(np.float32).copy()


def grad_of(p):
    return None if p.grad is None else p.grad.detach().numpy().astype(np.float32).copy()


def write_safetensors(path, tensors):
    """A safetensors file of float32 tensors (the format: an 8-byte header length, a JSON
    header of names, dtypes, shapes and offsets, the raw little-endian data)."""
    header, blobs, offset = {}, [], 0
    for name in sorted(tensors):
        a = np.ascontiguousarray(tensors[name], dtype="<f4")
        header[name] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [offset, offset + a.nbytes]}
        blobs.append(a.tobytes())
        offset += a.nbytes
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for b in blobs:
            f.write(b)


# ---------------------------------------------------------------- cbDreamer's mask SAC
class MaskProbe:
    """cbDreamer's mask SAC (`CtxMask`) run with ctxrace's noise and watched: its Gaussian
    samples take the queued normals in place of torch's (`Normal.rsample`), in the code's order
    of draws in one world-model step (the batch's masks, then in `_train` the critics' target
    sample, the actor's, the temperature's, and one or two it never uses); its losses are read
    where they are differentiated, its gradients where each optimiser steps, its masks where
    `forward` returns them."""

    def __init__(self, torch, ctx):
        self.torch, self.ctx, self.queue, self.calls = torch, ctx, [], []
        self.losses, self.grads, self.norms = [], {}, {}
        code_rsample, code_sample = torch.distributions.Normal.rsample, ctx.policy.sample
        code_forward, code_train, code_backward = ctx.forward, ctx._train, torch.Tensor.backward

        def rsample(dist, sample_shape=torch.Size()):
            if not self.queue:
                return code_rsample(dist, sample_shape)
            eps = self.queue.pop(0)
            return dist.loc + dist.scale * torch.from_numpy(np.ascontiguousarray(eps)).reshape(dist.loc.shape)

        def sample(state):
            result = code_sample(state)
            self.calls.append([r.detach().numpy().copy() for r in result])
            return result

        def forward(state, *a, **k):
            masks = code_forward(state, *a, **k)
            self.masks = masks.detach().numpy().copy()
            return masks

        def backward(loss, *a, **k):
            self.losses.append(float(loss))
            return code_backward(loss, *a, **k)

        def train(data):
            self.alpha = float(ctx.alpha)
            torch.Tensor.backward = backward
            try:
                return code_train(data)
            finally:
                torch.Tensor.backward = code_backward

        torch.distributions.Normal.rsample = rsample
        ctx.policy.sample, ctx.forward, ctx._train = sample, forward, train
        for opt, prefix, name in ((ctx.critic_optimizer, "mask_critic/", "mask_critic"),
                                  (ctx.policy_optim, "policy/mask.", "mask_actor"),
                                  (ctx.alpha_optim, "mask_alpha/", "mask_alpha")):
            opt.step = self.keeping(opt.step, prefix, name)

    def keeping(self, step, prefix, name):
        """The optimiser's `step`, keeping its gradients' norm first, and the gradients
        themselves (under ctxrace's names) on the first step."""
        def keep(*a, **k):
            grads = {n: g for n, g in mask_weights(self.ctx, grad_of).items() if n.startswith(prefix)}
            for n, g in grads.items():
                self.grads.setdefault(n, g)
            self.norms[name] = float(np.sqrt(sum(float((g.astype(np.float64) ** 2).sum()) for g in grads.values())))
            return step(*a, **k)
        return keep

    def arm(self, draws, step, keep):
        """Queues a step's normals: the masks', the critics' target sample's, the actor's (also
        the temperature's: ctxrace's temperature reads the actor's `log π`), zeros for the
        samples the code draws and never uses (one more on the steps its targets move); the
        mask SAC's only for the transitions `keep` (`[B * (T - 1)]`, see `drop_episode_ends`),
        ctxrace drawing one a transition, kept or not."""
        critic, actor = draws["sac_critic"][keep], draws["sac_actor"][keep]
        unused = np.zeros_like(actor)
        self.queue = [draws["mask"], critic, actor, actor, unused]
        self.queue += [unused] if step % 2 == 0 else []
        self.calls, self.losses = [], []

    def terms(self):
        """The step's mask SAC terms (names as ctxrace's metrics `mask/...`)."""
        assert not self.queue and len(self.losses) == 3, "the code's mask SAC drew or differentiated otherwise"
        target_entropy = float(self.ctx.target_entropy)
        return {
            "mask_mean": float(self.masks.mean()),
            "mask_alpha": self.alpha,
            "mask_q_loss": self.losses[0],
            "mask_actor_loss": self.losses[1],
            "mask_entropy": -float(self.calls[2][1].mean()),
            # the code's temperature loss reads a sample drawn after the actor's step
            "mask_entropy_after_actor_step": -float(self.calls[3][1].mean()),
            "mask_alpha_loss": self.losses[2],
            "mask_critic_grad_norm": self.norms["mask_critic"],
            "mask_actor_grad_norm": self.norms["mask_actor"],
            "mask_alpha_after": float(self.ctx.log_alpha.exp()),
            "target_entropy": target_entropy,
        }


def drop_episode_ends(ctx_mask):
    """Edits the code's `CtxMask._train` (in this process only) to train on the transitions
    `(t, t + 1)` whose row `t + 1` continues the episode, as ctxrace's mask SAC does
    (docs/parity/one_batch.md, row 21): the code's own takes every pair of a sequence, also
    across an episode end. Its source gets two lines after its slices of the batch: the
    transitions whose next row is not an episode's first kept, in the states, next states,
    rewards and masks; every mean after them is then over the kept ones, as ctxrace's (a batch
    without restarts inside its sequences keeps them all, the code's step unchanged)."""
    import inspect
    import textwrap

    lines = textwrap.dedent(inspect.getsource(ctx_mask._train)).splitlines()
    at = next(i for i, line in enumerate(lines) if line.lstrip().startswith("next_contexts ="))
    indent = lines[at][:len(lines[at]) - len(lines[at].lstrip())]
    lines[at + 1:at + 1] = [
        indent + "keep = data['is_first'].reshape(b, t)[:, 1:].reshape(-1) == 0",
        indent + "states, next_states, rewards, masks = states[keep], next_states[keep], rewards[keep], masks[keep]",
    ]
    namespace = {}
    exec("\n".join(lines), vars(sys.modules[ctx_mask.__module__]), namespace)
    ctx_mask._train = namespace["_train"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export", help="the paper's code as `deploy/paper_parity.sh export` wrote it")
    ap.add_argument("out", help="the safetensors file to write")
    ap.add_argument("--model", choices=("dreamerv3", "cmask"), default="dreamerv3",
                    help="the code's DreamerV3 (Utils/dreamerv3) or cbDreamer (Utils/cbdreamer, ctxrace's cMask)")
    ap.add_argument("--buffer", help="a paper run's Buffer/ folder (default: synthetic episodes)")
    ap.add_argument("--first-episode", type=int, default=0,
                    help="the first of the 40 Buffer/ episodes the batch is drawn from")
    ap.add_argument("--mask-units", type=int, default=16,
                    help="the mask SAC's hidden units (cbDreamer; the code's CtxMask hard-codes 256)")
    ap.add_argument("--model-lr", type=float, default=3e-4)
    ap.add_argument("--head-scale", type=float, default=0.2,
                    help="the reward head's and critic's output weights are drawn uniform in "
                         "±this (zero at the code's initialisation); larger spreads the imagined "
                         "rewards and values, and with them the λ-returns the return normaliser scales")
    args = ap.parse_args()
    out_path = os.path.abspath(args.out)
    buffer = os.path.abspath(args.buffer) if args.buffer else None
    cmask = args.model == "cmask"
    os.chdir(args.export)  # the agent reads its configs.yaml by a path relative to the export
    sys.path.insert(0, args.export)
    import importlib
    import torch

    torch.set_num_threads(1)
    # the code's own order: its DreamerV3 package first (its folder on sys.path gives every
    # package the bare `tools` and `networks` they import), then cbDreamer's
    importlib.import_module("TrajectoryAidedLearning.Utils.dreamerv3.dreamerv3")
    package = importlib.import_module(f"TrajectoryAidedLearning.Utils.{'cbdreamer' if cmask else 'dreamerv3'}.dreamerv3")
    tools = sys.modules["tools"]
    if cmask:
        # CtxMask builds its networks at 256 units whatever the widths; the harness's at
        # --mask-units (their constructors are given that width in place of the 256)
        for net in (package.cmodels.QNetwork, package.cmodels.GaussianPolicy):
            def init(self, *a, code_init=net.__init__, **k):
                code_init(self, *a[:-1], args.mask_units, **k)
            net.__init__ = init
        drop_episode_ends(package.cmodels.CtxMask)

    torch.manual_seed(SEED)
    np.random.seed(SEED)
    with contextlib.redirect_stdout(sys.stderr):  # the code prints its configuration
        agent = package.DreamerV3(108, 2, "one_batch", lr=args.model_lr)
    cfg = agent._config
    width, stoch, classes, horizon = cfg.units, cfg.dyn_stoch, cfg.dyn_discrete, cfg.imag_horizon
    z = stoch * classes
    assert (cfg.dyn_deter, cfg.dyn_hidden, cfg.encoder["mlp_units"], cfg.decoder["mlp_units"]) == (width,) * 4, \
        "the export's widths differ: run `deploy/paper_parity.sh export` with WIDTH and STOCH"
    assert cfg.batch_length == LENGTH, "the export's sequence length differs: LENGTH=16"
    cfg.batch_size = BATCH  # the batch train() draws
    # weights whose initial value (zero) would leave a path without gradient
    gen = torch.Generator().manual_seed(SEED + 1)
    beh = agent._task_behavior
    with torch.no_grad():
        for layer in (agent._wm.heads["reward"].mean_layer, beh.value.mean_layer):
            layer.weight.copy_(torch.empty(layer.weight.shape).uniform_(-args.head_scale, args.head_scale,
                                                                         generator=gen))
        beh._slow_value.load_state_dict(beh.value.state_dict())
        agent._wm.dynamics.W.copy_(torch.randn(agent._wm.dynamics.W.shape, generator=gen) * 0.5)
    probe = None
    if cmask:
        ctx = agent._wm._ctx_mask
        # the code's first step uses alpha = 0.2 while log alpha starts at 0 (alpha = 1 after
        # its first update): log alpha starts at ln 0.2 here, so that both sides' alpha is one
        with torch.no_grad():
            ctx.log_alpha.fill_(float(np.log(ctx.alpha)))
        probe = MaskProbe(torch, ctx)
    weights = ctxrace_weights(agent, value_of)
    if cmask:
        # the code's target critics start as a copy of the critics (`load_state_dict`): the
        # test copies them too, keeping the file small
        for name in [n for n in weights if n.startswith("mask_target/")]:
            assert np.array_equal(weights.pop(name), weights[name.replace("mask_target/", "mask_critic/")])

    rng = np.random.default_rng(SEED)
    episodes = buffer_episodes(buffer, args.first_episode) if buffer else synthetic_episodes(rng, cmask)
    data = one_batch(tools, episodes)  # the batch the code's train() draws from them
    keep = data["is_first"][:, 1:].reshape(-1) == 0  # the mask SAC's transitions (drop_episode_ends)
    agent.buffer_eps.update(episodes)
    draws = {}

    # ctxrace's noise in the code's samples: the posteriors' and the imagined priors' one-hot
    # by Gumbel-max, argmax_k p_k / (-ln u_k), with the unimix probabilities' straight-through
    # gradient (as OneHotDist.sample); the imagined actions `tanh(mu) + std * eps` scaled by
    # 1 / max(1, |a|) (as ContDist.sample with absmax 1)
    noise = {"phase": None, "t": 0, "call": 0}
    code_onehot, code_cont = tools.OneHotDist.sample, tools.ContDist.sample

    def gumbel_max(probs, u):
        u = torch.from_numpy(np.ascontiguousarray(u)).reshape(probs.shape)
        one_hot = torch.nn.functional.one_hot((probs / -torch.log(u)).argmax(-1), classes).float()
        return one_hot + probs - probs.detach()

    def onehot_sample(self, sample_shape=(), seed=None):
        probs = self.probs
        mode = torch.nn.functional.one_hot(probs.argmax(-1), classes).float()
        if noise["phase"] == "observe":
            noise["call"] += 1
            if noise["call"] == 1:  # obs_step's prior (img_step): not in the loss
                return mode
            return gumbel_max(probs, draws["model"][noise["t"]])
        if noise["phase"] == "imagine":
            t = noise["t"]
            noise["t"] += 1
            # the code imagines one step past the last state it keeps
            return gumbel_max(probs, draws["prior"][t]) if t < horizon - 1 else mode
        return code_onehot(self, sample_shape, seed)

    def cont_sample(self, sample_shape=()):
        if noise["phase"] != "imagine":
            return code_cont(self, sample_shape)
        base = self._dist.base_dist
        t = noise["t"]
        eps = torch.from_numpy(draws["action"][t]) if t < horizon - 1 else torch.zeros_like(base.loc)
        out = base.loc + base.scale * eps
        return out * (self.absmax / torch.clip(torch.abs(out), min=self.absmax)).detach()

    rssm = type(agent._wm.dynamics)
    code_obs_step = rssm.obs_step

    def obs_step(self, *a, **k):
        noise["call"] = 0
        result = code_obs_step(self, *a, **k)
        noise["t"] += 1
        return result

    tools.OneHotDist.sample, tools.ContDist.sample = onehot_sample, cont_sample
    rssm.obs_step = obs_step
    # behaviour learning imagines: the phase of the draws changes there
    code_behaviour = beh._train

    def behaviour(*a, **k):
        assert noise["call"] == 2, "the code's obs_step drew other than one prior and one posterior"
        noise.update(phase="imagine", t=0)
        return code_behaviour(*a, **k)

    beh._train = behaviour
    # each optimiser's gradients, read where it clips them: the world model's, the actor's,
    # the critic's, in this order
    parts = [
        ("model", {"encoder": agent._wm.encoder, "rssm": agent._wm.dynamics,
                   "decoder": agent._wm.heads["decoder"], "reward": agent._wm.heads["reward"],
                   "cont": agent._wm.heads["cont"]}, ("policy/encoder", "policy/rssm", "heads/")),
        ("actor", {"actor": beh.actor}, ("policy/actor",)),
        ("critic", {"critic": beh.value}, ("critic/",)),
    ]
    grads, norms, calls = {}, {}, []
    clip = torch.nn.utils.clip_grad_norm_

    def clip_and_keep(params, max_norm, *a, **k):
        optimiser, modules, prefixes = parts[len(calls) % len(parts)]
        if len(calls) < len(parts):  # the first step's gradients
            grads.update({name: g for name, g in ctxrace_weights(agent, grad_of).items()
                          if name.startswith(prefixes)})
        calls.append(optimiser)
        for name, module in modules.items():
            sq = sum(float((p.grad.double() ** 2).sum()) for p in module.parameters() if p.grad is not None)
            norms[name] = np.sqrt(sq)
        return clip(params, max_norm, *a, **k)

    torch.nn.utils.clip_grad_norm_ = clip_and_keep

    def code_step(step):
        """The code's training step (its agent's `train()`, which draws this batch again) with
        ctxrace's noise of step `step`: its loss terms, returns and gradient norms."""
        draws.update(ctxrace_noise(SEED, BATCH, LENGTH, z, 2, horizon, step, (LENGTH - 1) if cmask else 0))
        if probe:
            probe.arm(draws, step, keep)
        noise.update(phase="observe", t=0)
        agent.train()
        assert noise["phase"] == "imagine" and noise["t"] == horizon, \
            "the code's imagination drew other than one action and prior a step"
        noise["phase"] = None
        metrics = {k: v[-1] for k, v in agent._metrics.items()}
        ema = beh.ema_vals.detach().numpy()
        terms = {
            "model_loss": metrics["model_loss"],
            "recon": metrics["image_loss"].mean() + metrics["action_loss"].mean(),
            "reward": metrics["reward_loss"].mean(),
            "cont": metrics["cont_loss"].mean(),
            "kl": metrics["kl"],
            "model_grad_norm": metrics["model_grad_norm"],
            "actor_loss": metrics["actor_loss"],
            "critic_loss": metrics["value_loss"],
            "return": metrics["target_mean"],
            "return_scale": max(1.0, float(ema[1] - ema[0])),
            "actor_grad_norm": metrics["actor_grad_norm"],
            "critic_grad_norm": metrics["value_grad_norm"],
        }
        if probe:
            # the code clips (and reports) the world model's gradient together with every
            # parameter of the module, its mask SAC's stale gradients included: the world
            # model's own norm is that of its parts
            terms["model_grad_norm_code"] = terms["model_grad_norm"]
            terms["model_grad_norm"] = np.sqrt(sum(norms[k] ** 2 for k in parts[0][1]))
            terms.update(probe.terms())
        return terms

    terms = code_step(0)
    first_noise, first_norms = dict(draws), dict(norms)
    after = {f"after/{k}": v for k, v in ctxrace_weights(agent, value_of).items()
             if k.startswith(("policy/mask.", "mask_"))}
    # a second step on the same batch (the code draws the same one from an unchanged replay):
    # Adam's moments, the slow critic and the return normaliser after one update
    second = code_step(1)

    result = dict(weights)
    result.update({f"grad/{name}": g for name, g in grads.items()})
    if probe:
        result.update({f"grad/{name}": g for name, g in probe.grads.items()})
        result.update(after)
    result.update({f"torch/grad_norm/{name}": np.array([v], dtype=np.float32) for name, v in first_norms.items()})
    batch = {"obs": data["image"].reshape(BATCH, LENGTH, 108), "action": data["action"].reshape(BATCH, LENGTH, 2),
             "reward": data["reward"], "is_first": data["is_first"], "is_terminal": data["is_terminal"]}
    if cmask:
        batch.update(context=data["context"], mask=data["mask"])
    result.update({f"batch/{k}": np.asarray(v, dtype=np.float32) for k, v in batch.items()})
    result.update({"noise/model_uniform": first_noise["model"], "noise/imag_normal": first_noise["action"],
                   "noise/imag_uniform": first_noise["prior"]})
    if cmask:
        result.update({"noise/mask_normal": first_noise["mask"], "noise/sac_critic_normal": first_noise["sac_critic"],
                       "noise/sac_actor_normal": first_noise["sac_actor"]})
    result.update({f"torch/{k}": np.array([float(v)], dtype=np.float32) for k, v in terms.items()})
    result.update({f"torch2/{k}": np.array([float(v)], dtype=np.float32) for k, v in second.items()})
    config = [width, stoch, classes, BATCH, LENGTH, SEED, args.model_lr, cfg.actor["lr"], horizon]
    if cmask:
        config += [args.mask_units, cfg.ctx_mask["lr"]]
    result["config"] = np.array(config, dtype=np.float32)
    write_safetensors(out_path, result)
    print(f"{out_path}: {len(result)} tensors, {os.path.getsize(out_path)} bytes; "
          f"{int(data['is_first'].sum())} sequence starts, {int(data['is_terminal'].sum())} terminal rows"
          + (f", {int(keep.sum())} of {keep.size} mask-SAC transitions continue their episode" if cmask else ""))
    for k, v in terms.items():
        print(f"  torch {k} = {float(v):.7f} (second step {float(second[k]):.7f})")
    for name, v in first_norms.items():
        print(f"  torch gradient norm of {name} = {v:.6f}")


if __name__ == "__main__":
    main()
