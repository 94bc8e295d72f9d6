"""Continuous-action OCN on Dial: the Gaussian-mixture NLL on recorded Dial windows, unnormalised
torques out of the postprocessor, `lerobot-train --policy.type=ocn` and `lerobot-eval
--env.type=dial` as real subprocesses, and the Dial rollouts of `tools.dial_rollouts`.

One tiny recorded dataset (PINs 12 and 21) and one tiny training run are shared by the module.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch.distributions import Categorical, Independent, MixtureSameFamily, Normal

import lerobot_policy_ocn  # noqa: F401  (registers `ocn` and `dial` as LeRobot's CLIs do)
from envs.dial import DialBatch
from ocn_data.record_demos import main as record_demos
from policies.ocn import OCNConfig, OCNPolicy
from policies.ocn.processor_ocn import make_ocn_pre_post_processors
from policies.sequence import training_windows
from tools.dial_rollouts import free_run_success, option_subtask_success
from tools.episode_parsing import load_ocn

BIN = Path(sys.executable).parent
REPO_ID = "local/dial_ocn_test"
STEPS = 3
# Recorded episodes are about 40-140 frames long: windows of 64 make some of them "long episodes".
WINDOW = 64
DIAL = {"obs_encoder": "identity", "action_type": "continuous", "hidden_size": 16, "mlp_hidden_size": 16}


def run_cli(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(BIN / name), *args], capture_output=True, text=True, timeout=300, cwd=cwd)
    assert proc.returncode == 0, f"{name} failed ({proc.returncode}):\n{proc.stderr[-4000:]}"
    return proc


@pytest.fixture(scope="module")
def dial_dataset(tmp_path_factory) -> Path:
    """Root of 3 expert episodes each of PINs 12 and 21."""
    root = tmp_path_factory.mktemp("dial") / "ds"
    args = ["--env", "dial", "--tasks", "12,21", "--episodes-per-task", "3", "--root", str(root), "--repo-id", REPO_ID]
    assert record_demos(args) == 0
    return root


@pytest.fixture(scope="module")
def trained(dial_dataset) -> Path:
    """The `pretrained_model` folder of a few `lerobot-train` steps of 2-option OCN on `dial_dataset`."""
    base = dial_dataset.parent
    run_cli(
        "lerobot-train", "--policy.type=ocn", f"--dataset.repo_id={REPO_ID}", f"--dataset.root={dial_dataset}",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false", "--env_eval_freq=0",
        f"--steps={STEPS}", "--batch_size=4", "--num_workers=0", "--policy.n_options=2",
        *[f"--policy.{key}={value}" for key, value in DIAL.items()],
        f"--policy.window_size={WINDOW}", "--policy.skip_long_episodes=true", "--policy.inference_mode=greedy",
        f"--output_dir={base / 'train'}",
        cwd=base,
    )
    return base / "train" / "checkpoints" / f"{STEPS:06d}" / "pretrained_model"


def _windows(root: Path, config: OCNConfig) -> dict:
    """Every training window of the dataset as one batch, as LeRobot's loader builds them."""
    offsets = [i / 25 for i in config.observation_delta_indices]
    dataset = LeRobotDataset(REPO_ID, root=root, delta_timestamps={OBS_STATE: offsets, ACTION: offsets})
    return next(iter(torch.utils.data.DataLoader(dataset, batch_size=len(dataset))))


def _lengths(root: Path) -> np.ndarray:
    return np.asarray(LeRobotDatasetMetadata(REPO_ID, root=root).episodes["length"])


def _policy(root: Path, **overrides) -> tuple[OCNPolicy, LeRobotDatasetMetadata]:
    """A 3-option Dial OCN built from the dataset's metadata, as `lerobot-train` builds it."""
    torch.manual_seed(0)
    meta = LeRobotDatasetMetadata(REPO_ID, root=root)
    settings = {**DIAL, "window_size": int(_lengths(root).max()), **overrides}
    config = OCNConfig(device="cpu", n_options=3, **settings)
    return make_policy(config, ds_meta=meta), meta


def test_gaussian_mixture_nll_on_dial_windows(dial_dataset):
    policy, meta = _policy(dial_dataset)
    preprocessor, _ = make_ocn_pre_post_processors(policy.config, meta.stats)
    raw = _windows(dial_dataset, policy.config)
    batch = preprocessor(raw)
    stats = meta.stats[ACTION]
    expected_action = (raw[ACTION] - torch.as_tensor(stats["mean"])) / torch.as_tensor(stats["std"])
    torch.testing.assert_close(batch[ACTION], expected_action.float(), rtol=1e-5, atol=1e-5)

    loss, info = policy.forward(batch)
    lengths = _lengths(dial_dataset)
    assert info["frames_used"] == int((lengths**2).sum())  # every window holds its whole episode

    # The same NLL from torch.distributions, over the core's per-step mixture of 2N Gaussians.
    mask, state, action = training_windows(policy.config, batch)
    out = policy._unroll(state, batch["task"])
    mean, log_std = out.params.chunk(2, dim=-1)
    log_std = log_std.clamp(policy.config.log_std_min, policy.config.log_std_max)
    components = Independent(Normal(mean.permute(2, 0, 1, 3), log_std.exp().permute(2, 0, 1, 3)), 1)
    mixture = MixtureSameFamily(Categorical(probs=out.weights.transpose(0, 1)), components)
    nll = -mixture.log_prob(action) * mask
    reference = (nll.sum(1) / mask.sum(1)).mean()
    torch.testing.assert_close(loss, reference, rtol=1e-4, atol=1e-4)
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in policy.parameters())


def test_craft_defaults_on_dial_data_name_the_dial_flags(dial_dataset):
    meta = LeRobotDatasetMetadata(REPO_ID, root=dial_dataset)
    with pytest.raises(ValueError, match="obs_encoder=identity"):
        make_policy(OCNConfig(device="cpu", window_size=400), ds_meta=meta)
    with pytest.raises(ValueError, match="action_type=continuous"):
        make_policy(OCNConfig(device="cpu", window_size=400, obs_encoder="identity"), ds_meta=meta)


def test_long_episodes_train_on_their_first_window(dial_dataset):
    lengths = _lengths(dial_dataset)
    window = int(np.median(lengths))
    assert lengths.min() < window <= lengths.max()
    with pytest.raises(ValueError, match="skip_long_episodes"):
        _policy(dial_dataset, window_size=window)
    policy, meta = _policy(dial_dataset, window_size=window, skip_long_episodes=True)
    preprocessor, _ = make_ocn_pre_post_processors(policy.config, meta.stats)
    batch = preprocessor(_windows(dial_dataset, policy.config))
    loss, info = policy.forward(batch)
    per_window, _ = policy.forward(batch, reduction="none")
    short, long = lengths[lengths < window], lengths[lengths >= window]
    # A long episode keeps its windows sampled at frames 0 .. window-2: each starts the episode and
    # trains on its first `window` frames. Its later windows might start mid-episode and are left out.
    assert info["frames_used"] == int((short**2).sum()) + len(long) * (window - 1) * window
    kept = per_window != 0
    assert kept.sum() == short.sum() + len(long) * (window - 1) and len(per_window) == lengths.sum()
    torch.testing.assert_close(loss, per_window[kept].mean())


def test_select_action_returns_unnormalised_torques(dial_dataset):
    policy, meta = _policy(dial_dataset, inference_mode="greedy")
    preprocessor, postprocessor = make_ocn_pre_post_processors(policy.config, meta.stats)
    obs = DialBatch(2).reset(seeds=[0, 1], tasks=["12", "21"])
    batch = preprocessor({OBS_STATE: torch.from_numpy(obs), "task": ["press 1, press 2", "press 2, press 1"]})
    action = postprocessor(policy.select_action(batch))
    report = policy.last_step
    assert action.shape == (2, 9) and report.p_c.shape == (2, 3)
    # Greedy: the mean of the heaviest component (at t = 1 the restarted options, the last N).
    _, params = policy.core.step(policy.core.initial_state(policy.task_index(batch["task"], 2)),
                                 policy.core.project(batch[OBS_STATE]), torch.ones(2, dtype=torch.bool))[1][:2]
    chosen = params[3 + report.option, torch.arange(2), :9]
    stats = meta.stats[ACTION]
    torch.testing.assert_close(action, chosen * torch.as_tensor(stats["std"]).float() + torch.as_tensor(stats["mean"]).float())


def test_lerobot_train_checkpoint_reloads_and_runs_in_lerobot_eval(trained):
    policy = OCNPolicy.from_pretrained(trained)
    assert sorted(policy.config.tasks) == ["press 1, press 2", "press 2, press 1"]
    assert (policy.config.obs_encoder, policy.config.action_type, policy.config.n_options) == ("identity", "continuous", 2)
    assert policy.config.normalization_mapping == {"STATE": "MEAN_STD", "ACTION": "MEAN_STD"}
    out = trained.parents[3] / "eval"
    # --eval.recording writes the rollout as a dataset instead of rendering videos, so no OpenGL is needed.
    run_cli(
        "lerobot-eval", f"--policy.path={trained}", "--env.type=dial", "--env.task=12", "--eval.n_episodes=1",
        "--eval.batch_size=1", "--env.max_steps=50", "--eval.recording=true", "--policy.device=cpu", f"--output_dir={out}",
        cwd=trained.parents[3],
    )
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1 and info["overall"]["pc_success"] in (0.0, 100.0)
    assert 0.0 <= info["overall"]["avg_sum_reward"] <= 2.0


def test_dial_rollouts_of_the_trained_policy(trained):
    policy, preprocessor, postprocessor = load_ocn(trained)
    rates = free_run_success(policy, preprocessor, postprocessor, ["12", "press 2, press 1"], episodes=1, seed=5)
    assert list(rates) == ["12", "press 2, press 1"] and all(0.0 <= r <= 1.0 for r in rates.values())
    table = option_subtask_success(policy, preprocessor, postprocessor, ["1", "press 2"], episodes=1, seed=5)
    assert table.shape == (2, 2) and np.isin(table, [0.0, 1.0]).all()
    with torch.no_grad():  # options that terminate at once get one step: too short to reach a key
        policy.core.options.b_out[..., -1] = 50.0
        policy.core.options.w_out[..., -1] = 0.0
    table = option_subtask_success(policy, preprocessor, postprocessor, ["1", "2"], episodes=2, seed=5)
    assert np.array_equal(table, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="Unknown task"):
        free_run_success(policy, preprocessor, postprocessor, ["48"], episodes=1)
