"""`ctxrace.export_onnx` and `ctxrace export onnx`: a trained agent's ONNX model, stepped with
onnxruntime, acts as ``load_policy(...).act(..., deterministic=True)`` does, decision by
decision, through episode starts and in batches, for every agent and the settings that change
its decision; what has no such model is refused."""

import subprocess

import numpy as np
import onnxruntime as ort
import pytest

import ctxrace
from conftest import ROOT

#: Each agent and the settings that change its decision: keys set in the sections of
#: testdata/tiny-cmask.toml (a 300-decision run of tiny networks on generated:0).
VARIANTS = {
    "sac": ("sac", {"agent.sac": {"hidden": 16}}),
    "sac-3-frames": ("sac", {"agent.sac": {"hidden": 16, "frames": 3}}),
    "dreamerv3": ("dreamerv3", {}),
    "crssm": ("crssm", {}),
    "cmask": ("cmask", {}),
    # the paper's code: the encoder reads the previous action, a learned initial state, the
    # mask sigmoid(tanh u), the context divided by the training range; and a deeper encoder
    # and a larger uniform mixture
    "cmask-paper-code": ("cmask", {
        "agent": {"context_scale": '"normalised"'},
        "agent.dreamer": {"step_alignment": '"paper-code"', "initial_state": '"learned"',
                          "layers": 2, "unimix": 0.3},
        "agent.dreamer.mask": {"mask_space": '"paper-code"'},
    }),
    # no encoder: the posterior reads symlog o itself; and scans of 64 beams
    "crssm-no-encoder": ("crssm", {"agent.dreamer": {"layers": 0}}),
    "crssm-64-beams": ("crssm", {"race.lidar": {"beams": 64}}),
}


def with_keys(text, sections):
    """The TOML `text` with `sections` (``{section: {key: value as TOML}}``) set: a key's line
    replaced where the section has it, else added under the section's header (a section the
    text lacks is added at its end)."""
    lines = text.splitlines()
    for section, keys in sections.items():
        if f"[{section}]" not in lines:
            lines.append(f"[{section}]")
        start = lines.index(f"[{section}]") + 1
        end = next((i for i in range(start, len(lines)) if lines[i].startswith("[")),
                   len(lines))
        for key, value in keys.items():
            line = f"{key} = {value}"
            found = [i for i in range(start, end) if lines[i].split("=")[0].strip() == key]
            if found:
                lines[found[0]] = line
            else:
                lines.insert(start, line)
                end += 1
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def runs(tmp_path_factory, ctxrace_bin):
    """The tiny runs of `VARIANTS`, trained once, by name."""
    folder = tmp_path_factory.mktemp("onnx-runs")
    text = (ROOT / "testdata" / "tiny-cmask.toml").read_text()
    made = {}
    for name, (algo, sections) in VARIANTS.items():
        cfg = folder / f"{name}.toml"
        cfg.write_text(with_keys(text, sections))
        made[name] = folder / name
        subprocess.run([ctxrace_bin, "train", cfg, "--inline", "--algo", algo, "--run-dir",
                        made[name]], check=True, capture_output=True)
    return made


def step_side_by_side(policy, session, state_dim, batch, steps, seed):
    """Drives `batch` races with the policy's deterministic actions for `steps` decisions,
    asking the ONNX session for each decision too (its state carried from call to call, a
    new episode started with ``is_first = 1`` and a state of NaN, which it must ignore), and
    returns the largest action and mask differences and the episodes started."""
    lidar = {"beams": policy.obs_dim}
    envs = [ctxrace.RaceEnv(policy.track, lidar=lidar) for _ in range(batch)]
    rng = np.random.default_rng(seed)
    ctx = rng.uniform(-0.1, 0.1, size=(batch, 2))
    obs = np.stack([e.reset(seed=seed + i, options={"context": ctx[i]})[0]
                    for i, e in enumerate(envs)])
    policy.reset(rows=range(batch))
    first = np.ones(batch, np.float32)
    state = np.zeros((batch, state_dim), np.float32)
    worst = {"action": 0.0, "mask": 0.0}
    starts = batch
    for _ in range(steps):
        state[first == 1] = np.nan
        action, mask = policy.act(obs, ctx, deterministic=True, return_mask=True)
        names = [o.name for o in session.get_outputs()]
        out = dict(zip(names, session.run(None, {
            "obs": obs.astype(np.float32), "context": ctx.astype(np.float32),
            "is_first": first, "state": state,
        })))
        state = out["state_out"]
        assert np.isfinite(state).all()
        worst["action"] = max(worst["action"], float(np.abs(out["action"] - action).max()))
        assert ("mask" in out) == (mask is not None)
        if mask is not None:
            worst["mask"] = max(worst["mask"], float(np.abs(out["mask"] - mask).max()))
        first[:] = 0
        for i, env in enumerate(envs):
            obs[i], _, terminated, truncated, _ = env.step(action[i])
            if terminated or truncated:
                ctx[i] = rng.uniform(-0.1, 0.1, size=2)
                obs[i], _ = env.reset(seed=seed + starts, options={"context": ctx[i]})
                policy.reset(rows=[i])
                first[i] = 1
                starts += 1
    return worst, starts


@pytest.mark.parametrize("name", VARIANTS)
def test_the_onnx_model_acts_as_the_policy_acts(tmp_path, runs, name):
    path = tmp_path / f"{name}.onnx"
    info = ctxrace.export_onnx(runs[name], path)
    policy = ctxrace.load_policy(runs[name])
    assert info["bytes"] == path.stat().st_size
    beams = VARIANTS[name][1].get("race.lidar", {}).get("beams", 108)
    assert (info["algo"], info["obs_dim"], info["opset"]) == (policy.algo, beams, 17)
    assert policy.obs_dim == beams
    assert info["state"][-1][2] == info["state_dim"]
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    shapes = {v.name: v.shape for v in session.get_inputs() + session.get_outputs()}
    s = info["state_dim"]
    want = {"obs": ["B", policy.obs_dim], "context": ["B", 2], "is_first": ["B"], "state": ["B", s],
            "action": ["B", 2], "state_out": ["B", s]}
    if policy.algo == "cmask":
        want["mask"] = ["B", 2]
    assert shapes == want
    assert info["outputs"] == [o for o in want if o in ("action", "state_out", "mask")]
    # one race, then three at once, each with episodes starting along the way
    for batch, steps in [(1, 300), (3, 150)]:
        worst, starts = step_side_by_side(policy, session, s, batch, steps, seed=batch)
        assert starts > batch, "an episode started along the way"
        print(f"{name} B={batch}: max |action diff| {worst['action']:.2e}, "
              f"max |mask diff| {worst['mask']:.2e}, {starts} episodes")
        assert worst["action"] < 1e-4 and worst["mask"] < 1e-5, worst


def test_the_command_line_writes_the_same_model_and_bad_input_is_refused(tmp_path, runs,
                                                                         ctxrace_bin):
    mine = tmp_path / "python.onnx"
    cli = tmp_path / "cli.onnx"
    ctxrace.export_onnx(runs["cmask"], mine, checkpoint="latest")
    out = subprocess.run([ctxrace_bin, "export", "onnx", runs["cmask"], cli, "--checkpoint",
                          "latest"], check=True, capture_output=True, text=True)
    assert out.stdout.startswith(f"wrote {cli} ") and "mask (B, 2)" in out.stdout
    assert cli.read_bytes() == mine.read_bytes()
    with pytest.raises(ValueError, match="neither a checkpoint"):
        ctxrace.export_onnx(ROOT / "configs", tmp_path / "x.onnx")
    with pytest.raises(ValueError, match="not best, latest, step-N"):
        ctxrace.export_onnx(runs["cmask"], tmp_path / "x.onnx", checkpoint="newest")
    mlp = tmp_path / "policy.safetensors"
    ctxrace.save_mlp_policy(mlp, [(np.zeros((2, 108)), np.zeros(2))])
    with pytest.raises(ValueError, match="MLP policy file"):
        ctxrace.export_onnx(mlp, tmp_path / "x.onnx")
    with pytest.raises(ValueError, match="writing"):
        ctxrace.export_onnx(runs["cmask"], tmp_path / "no" / "such" / "x.onnx")


def test_a_sac_agent_whose_deterministic_action_is_random_is_refused(tmp_path, ctxrace_bin):
    cfg = tmp_path / "noisy.toml"
    text = (ROOT / "testdata" / "tiny-cmask.toml").read_text()
    cfg.write_text(with_keys(text, {"agent.sac": {"explore_noise": 0.1}}))
    run = tmp_path / "noisy"
    subprocess.run([ctxrace_bin, "train", cfg, "--inline", "--algo", "sac", "--steps", "250",
                    "--run-dir", run], check=True, capture_output=True)
    with pytest.raises(ValueError, match="explore_noise = 0"):
        ctxrace.export_onnx(run, tmp_path / "x.onnx")
