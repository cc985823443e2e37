"""PPO for continuous actions on ctxrace's vector env, top to bottom in one file (after CleanRL's
``ppo_continuous_action.py``: the same algorithm and defaults, its rollout, GAE and clipped
update written out).

    pip install ./deploy/python torch      # a CPU-only torch: --index-url https://download.pytorch.org/whl/cpu
    python deploy/python/examples/cleanrl_ppo.py --track f1_esp --steps 1000000 --out ppo-run

The agent sees the LiDAR scan and the episode's context (``obs_mode="scan+context"``) and races
one pure-pursuit rival whose context is drawn from ±0.15 each episode. Every update appends a row
to ``<out>/curve.csv``: env steps, wall seconds, and the mean return, progress (PG) and lap
fraction of the episodes that ended since the last row. At the end ``<out>/policy.pt`` holds the
trained agent, ``<out>/policy.safetensors`` its mean action as an MLP file the command line races
(``ctxrace race f1_esp --policy <out>/policy.safetensors``), and ``<out>/race.gif`` a race of it
against ``--rival`` (default: the pure-pursuit rival; ``--rival RUN_DIR`` races a trained
ctxrace agent instead, e.g. ``docs/table2/1r/cmask/seed10000``).
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from torch import nn
from torch.distributions.normal import Normal

import ctxrace


def layer(n_in: int, n_out: int, std: float = np.sqrt(2)) -> nn.Linear:
    """A linear layer with CleanRL's orthogonal initialisation."""
    lin = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(lin.weight, std)
    nn.init.constant_(lin.bias, 0.0)
    return lin


class Agent(nn.Module):
    """Separate actor and critic MLPs (2 x 64, tanh); a Gaussian policy with a learned,
    state-independent log standard deviation."""

    def __init__(self, obs_dim: int, act_dim: int):
        super().__init__()
        self.critic = nn.Sequential(
            layer(obs_dim, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, 1, 1.0)
        )
        self.actor_mean = nn.Sequential(
            layer(obs_dim, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, act_dim, 0.01)
        )
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_dim))

    def value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def act(self, x: torch.Tensor, action: torch.Tensor | None = None):
        """(action, its log-probability, the entropy, the value) at observations `x`."""
        mean = self.actor_mean(x)
        dist = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action).sum(1), dist.entropy().sum(1), self.critic(x)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--track", default="f1_esp")
    p.add_argument("--tracks-dir", default=None)
    p.add_argument("--steps", type=int, default=1_000_000, help="env steps in all")
    p.add_argument("--envs", type=int, default=32)
    p.add_argument("--rollout", type=int, default=128, help="steps per env per update")
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--gae-lambda", type=float, default=0.95)
    p.add_argument("--minibatches", type=int, default=8)
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--clip", type=float, default=0.2)
    p.add_argument("--ent-coef", type=float, default=0.0)
    p.add_argument("--vf-coef", type=float, default=0.5)
    p.add_argument("--max-grad-norm", type=float, default=0.5)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--threads", type=int, default=1, help="torch's threads")
    p.add_argument("--rival", default=None, help="race the trained agent against this run")
    p.add_argument("--out", type=Path, default=Path("ppo-run"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)

    envs = ctxrace.make_vec(
        args.track, args.envs, rivals=1, tracks_dir=args.tracks_dir, obs_mode="scan+context",
        autoreset_mode=AutoresetMode.SAME_STEP, threads=1,
    )
    obs_dim = envs.single_observation_space.shape[0]
    agent = Agent(obs_dim, 2)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)
    n, t = args.envs, args.rollout
    obs_buf = torch.zeros((t, n, obs_dim))
    act_buf = torch.zeros((t, n, 2))
    logp_buf, rew_buf, done_buf, val_buf = (torch.zeros((t, n)) for _ in range(4))
    batch = n * t
    minibatch = batch // args.minibatches
    updates = max(1, args.steps // batch)

    next_obs, _ = envs.reset(seed=args.seed)
    next_obs = torch.as_tensor(next_obs)
    next_done = torch.zeros(n)
    start, steps = time.time(), 0
    ended = {"return": [], "progress": [], "lap": []}
    running_return = np.zeros(n)
    curve = open(args.out / "curve.csv", "w", newline="")
    writer = csv.writer(curve)
    writer.writerow(["env_steps", "seconds", "episodes", "return", "progress", "laps"])
    for update in range(updates):
        frac = 1.0 - update / updates
        optimizer.param_groups[0]["lr"] = frac * args.lr
        for k in range(t):
            steps += n
            obs_buf[k], done_buf[k] = next_obs, next_done
            with torch.no_grad():
                action, logp, _, value = agent.act(next_obs)
            val_buf[k], act_buf[k], logp_buf[k] = value.flatten(), action, logp
            obs, reward, term, trunc, info = envs.step(action.clamp(-1, 1).numpy())
            done = np.logical_or(term, trunc)
            rew_buf[k] = torch.as_tensor(reward, dtype=torch.float32)
            next_obs = torch.as_tensor(obs)
            next_done = torch.as_tensor(done, dtype=torch.float32)
            running_return += reward
            for i in np.flatnonzero(done):
                ended["return"].append(running_return[i])
                ended["progress"].append(info["final_info"]["progress"][i])
                ended["lap"].append(info["final_info"]["progress"][i] >= 1.0)
                running_return[i] = 0.0

        # generalised advantage estimation
        with torch.no_grad():
            next_value = agent.value(next_obs).reshape(1, -1)
            adv = torch.zeros_like(rew_buf)
            last = 0
            for k in reversed(range(t)):
                nonterminal = 1.0 - (next_done if k == t - 1 else done_buf[k + 1])
                nv = next_value if k == t - 1 else val_buf[k + 1]
                delta = rew_buf[k] + args.gamma * nv * nonterminal - val_buf[k]
                adv[k] = last = delta + args.gamma * args.gae_lambda * nonterminal * last
            ret = adv + val_buf

        b_obs, b_act = obs_buf.reshape(-1, obs_dim), act_buf.reshape(-1, 2)
        b_logp, b_adv = logp_buf.reshape(-1), adv.reshape(-1)
        b_ret, b_val = ret.reshape(-1), val_buf.reshape(-1)
        for _ in range(args.epochs):
            order = torch.randperm(batch)
            for s in range(0, batch, minibatch):
                mb = order[s : s + minibatch]
                _, logp, entropy, value = agent.act(b_obs[mb], b_act[mb])
                ratio = (logp - b_logp[mb]).exp()
                a = b_adv[mb]
                a = (a - a.mean()) / (a.std() + 1e-8)
                pg_loss = torch.max(-a * ratio, -a * ratio.clamp(1 - args.clip, 1 + args.clip))
                v_clipped = b_val[mb] + (value.flatten() - b_val[mb]).clamp(-args.clip, args.clip)
                v_loss = 0.5 * torch.max(
                    (value.flatten() - b_ret[mb]) ** 2, (v_clipped - b_ret[mb]) ** 2
                ).mean()
                loss = pg_loss.mean() - args.ent_coef * entropy.mean() + args.vf_coef * v_loss
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()

        if ended["return"]:
            row = [
                steps, round(time.time() - start, 1), len(ended["return"]),
                float(np.mean(ended["return"])), float(np.mean(ended["progress"])),
                float(np.mean(ended["lap"])),
            ]
            writer.writerow(row)
            curve.flush()
            print(f"{row[0]:>9} steps {row[1]:>7.1f} s  return {row[3]:7.2f}  PG {row[4]:.3f}  "
                  f"laps {row[5]:.2f}", flush=True)
            ended = {k: [] for k in ended}
    curve.close()
    torch.save(agent.state_dict(), args.out / "policy.pt")
    # the mean action as an MLP file the command line races: ctxrace race f1_esp --policy FILE
    linears = [m for m in agent.actor_mean if isinstance(m, nn.Linear)]
    ctxrace.save_mlp_policy(
        args.out / "policy.safetensors",
        [(m.weight.detach().numpy(), m.bias.detach().numpy()) for m in linears],
        activation="tanh", inputs="scan+context", output="clip",
    )

    def mean_action(obs: np.ndarray, context: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(np.concatenate([obs, context], axis=1), dtype=torch.float32)
        with torch.no_grad():
            return agent.actor_mean(x).clamp(-1, 1).double().numpy()

    rival = {} if args.rival is None else {"rival": {"driver": "policy", "policy": args.rival}}
    result = ctxrace.race(
        mean_action, args.track, rivals=1, seed=args.seed, tracks_dir=args.tracks_dir,
        render=args.out / "race.gif", name="PPO (Python)", **rival,
    )
    (args.out / "race.json").write_text(json.dumps(result, indent=1))
    print(f"race against {args.rival or 'the pure-pursuit rival'}: {result['ended_by']}, "
          f"PG {result['progress']:.3f}, OT {result['overtakes']}; drawn in {args.out / 'race.gif'}")


if __name__ == "__main__":
    main()
