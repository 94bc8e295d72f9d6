"""`ocn-finetune` on Dial: PPO over frozen continuous options on 3-digit PINs, through the
checkpoint's normalising processors, a finetuned checkpoint that `lerobot-eval --env.type=dial` runs
(its path taken in process; test_dial_ocn runs the CLI itself on a Dial checkpoint), MoE as the
baseline, bad input; and `ocn-reproduce dial`'s command line and checks."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ocn.envs.dial import DialBatch, task_description
from lerobot_policy_ocn.ocn import OCNConfig, make_ocn_pre_post_processors
from test_ocn_finetune import assert_refused, decisions_match_frames, lerobot_eval_rollout, save_variant
from lerobot_policy_ocn.tools.rl.dial_rollouts import DIAL_WORLD
from lerobot_policy_ocn.tools.eval.parsing import load_ocn, load_policy
from lerobot_policy_ocn.tools.cli.ocn_finetune import main
from lerobot_policy_ocn.tools.rl.finetuning import merge_option_pools, save_checkpoint
from lerobot_policy_ocn.tools.rl.ppo import Acting, collect
from conftest import DIAL_REPO_ID

torch.set_num_threads(1)

PINS = ["124", "481"]
TASKS = [task_description(tuple(int(d) for d in pin)) for pin in PINS]


@pytest.fixture(scope="module")
def dial_checkpoint(dial_dataset, tmp_path_factory) -> Path:
    """A `pretrained_model` folder of a small, untrained 3-option Dial OCN (seeded weights) with the
    dataset's normalising processors, as `lerobot-train` would write it."""
    torch.manual_seed(0)
    meta = LeRobotDatasetMetadata(DIAL_REPO_ID, root=dial_dataset)
    config = OCNConfig(device="cpu", recipe="paper", obs_encoder="identity", hidden_size=16, mlp_hidden_size=16,
                       n_options=3)
    policy = make_policy(config, ds_meta=meta)
    path = tmp_path_factory.mktemp("dial_ocn") / "pretrained_model"
    save_checkpoint(policy, *make_ocn_pre_post_processors(policy.config, meta.stats), path)
    return path


def _finetune(checkpoint: Path, out: Path, *flags: str) -> Path:
    """A few hundred frames of `ocn-finetune` on two PINs in 4 envs of at most 30 steps."""
    argv = ["--checkpoint", str(checkpoint), "--tasks", ",".join(PINS), "--frames", "200", "--envs", "4",
            "--max-steps", "30", "--seed", "1", "--batch-size", "32", "--out", str(out), *flags]
    assert main(argv) == 0
    return out


@pytest.fixture(scope="module")
def finetuned(dial_checkpoint, tmp_path_factory) -> Path:
    return _finetune(dial_checkpoint, tmp_path_factory.mktemp("dial_finetune") / "run", "--reward", "dense")


def test_dial_finetuning_writes_pin_curves_and_keeps_the_options_bit_identical(finetuned, dial_checkpoint):
    rows = list(csv.DictReader(open(finetuned / "curve.csv")))
    assert rows and {"frames", "mean_return", "success", "success[124]", "success[481]"} <= set(rows[0])
    assert int(rows[-1]["frames"]) >= 200 and all(0.0 <= float(row["mean_return"]) <= 3.0 for row in rows)
    summary = json.loads((finetuned / "finetune.json").read_text())
    assert summary["world"] == "dial" and summary["tasks"] == TASKS and summary["n_options"] == 3
    assert summary["mode"] is None  # a Craft world mode; Dial has none

    policy, preprocessor, _ = load_ocn(finetuned / "pretrained_model")
    source, source_preprocessor, _ = load_ocn(dial_checkpoint)
    assert policy.config.execution == "hard" and policy.config.tasks == TASKS
    assert (policy.config.obs_encoder, policy.config.action_type) == ("identity", "continuous")
    for name, param in policy.named_parameters():
        if not name.startswith("core.controller"):
            assert torch.equal(param, source.get_parameter(name)), name
    assert not torch.equal(policy.core.controller_init, torch.zeros_like(policy.core.controller_init))
    saved, own = preprocessor.state_dict(), source_preprocessor.state_dict()
    assert saved.keys() == own.keys() and all(
        torch.equal(saved[step][key], own[step][key]) for step in own for key in own[step])


def test_ppo_on_dial_records_the_standardised_states_the_policy_saw(dial_checkpoint, dial_dataset):
    source, preprocessor, postprocessor = load_ocn(dial_checkpoint)
    policy = merge_option_pools([source], TASKS)
    seeds = [3, 4, 5, 6]
    batch = collect(policy, DialBatch(4, max_steps=5), Acting(DIAL_WORLD, preprocessor, postprocessor),
                    TASKS * 2, seeds, gamma=0.97)
    assert (batch.frames == 5).all() and (batch.count >= 1).all() and not batch.success.any()
    first = DialBatch(4).reset(seeds=seeds, tasks=PINS * 2)
    stats = LeRobotDatasetMetadata(DIAL_REPO_ID, root=dial_dataset).stats[OBS_STATE]
    standardised = (first - stats["mean"]) / (stats["std"] + 1e-8)  # LeRobot's MEAN_STD, eps included
    np.testing.assert_allclose(batch.state[:, 0], standardised, rtol=1e-5, atol=1e-5)
    assert np.abs(batch.state[:, 0] - first).max() > 0.1  # raw states would not pass


def test_the_finetuned_dial_checkpoint_runs_under_lerobot_eval_rollout(finetuned):
    out, policy = lerobot_eval_rollout(finetuned / "pretrained_model", "dial", "124", max_steps=30)
    assert out["action"].shape[:2] == (2, 30) and out["action"].shape[2] == 9  # 9 torques for 30 steps
    assert torch.isfinite(out["action"]).all() and ((out["reward"] >= 0) & (out["reward"] <= 1)).all()
    assert policy.config.execution == "hard" and policy.config.tasks == TASKS


def test_an_moe_checkpoint_finetunes_on_dial_with_one_decision_per_step(dial_checkpoint, tmp_path):
    moe = save_variant(dial_checkpoint, tmp_path / "moe" / "pretrained_model", seed=5, hierarchy="moe")
    out = _finetune(moe, tmp_path / "run", "--reward", "sparse")
    assert decisions_match_frames(out)
    policy, _, _ = load_ocn(out / "pretrained_model")
    source, _, _ = load_ocn(moe)
    assert policy.config.hierarchy == "moe"
    for name, param in policy.core.options.named_parameters():
        assert torch.equal(param, source.core.options.get_parameter(name)), name


def test_flat_ppo_on_dial_and_other_bad_dial_input_are_refused(dial_checkpoint, dial_dataset, tmp_path, capsys):
    source, _, _ = load_policy(dial_checkpoint)
    stats = LeRobotDatasetMetadata(DIAL_REPO_ID, root=dial_dataset).stats
    shifted = {**stats, ACTION: {**stats[ACTION], "mean": stats[ACTION]["mean"] + 0.5}}
    other = tmp_path / "other" / "pretrained_model"
    clone = type(source)(dataclasses.replace(source.config, pretrained_path=None))
    save_checkpoint(clone, *make_ocn_pre_post_processors(clone.config, shifted), other)
    base = ["--checkpoint", str(dial_checkpoint), "--frames", "10", "--envs", "2"]
    cases = {
        "--flat with Dial PINs is refused": ["--flat", "--tasks", "124,481", "--out", str(tmp_path / "a")],
        "a Dial task is a PIN": [*base, "--tasks", "ADC", "--out", str(tmp_path / "b")],
        "normalisation statistics differ": [*base, "--checkpoint", str(other), "--tasks", "124",
                                            "--out", str(tmp_path / "c")],
    }
    assert_refused(cases, capsys)
    assert not any((tmp_path / name).exists() for name in "abc")


