"""`ocn-finetune` on Dial: PPO over frozen continuous options on 3-digit PINs, through the
checkpoint's normalising processors, a finetuned checkpoint that `lerobot-eval --env.type=dial` runs
(its path taken in process; test_dial_ocn runs the CLI itself on a Dial checkpoint), MoE as the
baseline, bad input; and `ocn-reproduce dial`'s command line and checks."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import ACTION, OBS_STATE

import lerobot_policy_ocn  # noqa: F401  (registers `ocn` and `dial` as LeRobot's CLIs do)
from envs.dial import DialBatch, task_description
from policies.ocn import OCNConfig, make_ocn_pre_post_processors
from test_ocn_finetune import assert_refused, decisions_match_frames, lerobot_eval_rollout, save_variant
from tools.dial_rollouts import DIAL_WORLD
from tools.episode_parsing import load_ocn, load_policy, validation_nll
from tools.ocn_finetune import main, merge_option_pools, save_checkpoint
from tools.ppo import Acting, collect
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
    config = OCNConfig(device="cpu", obs_encoder="identity", action_type="continuous", hidden_size=16,
                       mlp_hidden_size=16, n_options=3, window_size=64, skip_long_episodes=True)
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


# ---- ocn-reproduce dial ----------------------------------------------------------------------------


def test_ocn_reproduce_dial_help_lists_its_options(capsys):
    from tools.reproduce import main as reproduce

    with pytest.raises(SystemExit) as exit_info:
        reproduce(["dial", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--seeds", "--frames", "--envs", "--rewards", "--methods", "--tasks", "--rollouts", "--steps",
                   "--batch-size", "--episodes-per-task", "--workdir", "--results", "--first-seed", "--usage-balance",
                   "--gamma", "--lr-decay-step", "--restarts", "--select-step"):
        assert option in text, option
    # Dial's own discount, not the paper's 0.97.
    assert re.search(r"--gamma GAMMA\s+PPO's discount[^()]*\(ocn-finetune --gamma\)[^()]*\(default:\s+0\.995\)",
                     text)


def test_dial_clones_train_on_the_induction_recipe_and_finetune_on_the_pins(dial_dataset, tmp_path):
    import argparse

    from tools.reproduce import build_parser, dial
    from tools.reproduce.finetune import Setting, finetune_command, finetune_run

    assert dial.TWO_DIGIT_PINS.split(",") == ["12", "14", "18", "21", "24", "28", "41", "42", "48", "81", "82", "84"]
    assert [method.key for method in dial.METHODS] == ["ocn", "moe"]
    args = build_parser().parse_args([
        "dial", "--steps", "2", "--batch-size", "4", "--num-workers", "0", "--lr-decay-step", "1", "--frames", "100",
        "--envs", "4", "--restarts", "2", "--select-step", "1", "--workdir", str(tmp_path),
        "--results", str(tmp_path / "results")])
    args.argv = None
    # Both methods' clones really train on the recipe (lerobot-train accepts every flag), and only
    # OCN's pays for hand-overs.
    chosen = {method.key: dial.clone(args, dial_dataset, method, 1) for method in dial.METHODS}
    clones = {key: trained for key, (trained, _) in chosen.items()}
    for key, clone in clones.items():
        for flag in ("--policy.obs_encoder=dial_keys", "--policy.action_type=continuous",
                     "--policy.skip_long_episodes=true", "--policy.n_options=4", "--policy.temperature=10.0",
                     "--policy.option_memory=false", "--policy.log_std_max=0.0", "--policy.lr_schedule=step",
                     "--policy.lr_decay_step=1", "--policy.usage_balance=1.0"):
            assert flag in clone.command.split(), (key, flag)
        config = OCNConfig.from_pretrained(clone.checkpoint)
        assert (config.obs_encoder, config.option_memory, config.usage_balance) == ("dial_keys", False, 1.0)
        assert config.termination_cost == (1.0 if key == "ocn" else 0.0)
        assert config.hierarchy == key
    # Each clone is the restart, of seeds 2 and 3, whose step-1 checkpoint fits the validation
    # demonstrations best; it alone trains on to step 2.
    ocn_choice = chosen["ocn"][1]
    assert [r["seed"] for r in ocn_choice["restarts"]] == [2, 3] and ocn_choice["select_step"] == 1
    nlls = [r["val_nll"] for r in ocn_choice["restarts"]]
    assert ocn_choice["chosen"] == int(np.argmin(nlls)) and nlls[0] != nlls[1]
    assert f"--seed={ocn_choice['chosen_seed']}" in clones["ocn"].command.split()
    folder = dial.clone_dir(args, dial.METHODS[0], 1)
    other = 1 - ocn_choice["chosen"]
    steps = [json.loads((folder / f"restart{j}" / "train" / "checkpoints" / "last" / "training_state" /
                         "training_step.json").read_text())["step"] for j in (ocn_choice["chosen"], other)]
    assert steps == [2, 1]
    loser = folder / f"restart{other}" / "train" / "checkpoints" / "last" / "pretrained_model"
    assert validation_nll(loser, dial_dataset) == pytest.approx(nlls[other], rel=1e-6)
    recorded = json.loads((folder / "restarts.json").read_text())
    assert recorded == {key: value for key, value in ocn_choice.items() if key != "train_wall_s"}
    # The clone's cost counts the restart that lost too.
    walls = [json.loads((folder / f"restart{j}" / "train_wall_s.json").read_text())["total"] for j in (0, 1)]
    assert ocn_choice["train_wall_s"] == pytest.approx(sum(walls), abs=0.1)
    assert ocn_choice["train_wall_s"] > clones["ocn"].train_wall_s > 0
    # Asked again, the clone is the same choice, trained no further.
    logs = [(folder / f"restart{j}" / "train.log").read_text() for j in (0, 1)]
    run, choice = chosen["ocn"]
    assert run.trained_now and dial.clone(args, dial_dataset, dial.METHODS[0], 1) == (
        dataclasses.replace(run, trained_now=False), choice)
    assert [(folder / f"restart{j}" / "train.log").read_text() for j in (0, 1)] == logs
    for restarts, step, message in (("2", "0", r"chosen at step 0 \(--select-step\), which must lie in 1..2"),
                                    ("2", "3", r"chosen at step 3 \(--select-step\), which must lie in 1..2"),
                                    ("0", "1", "--restarts 0: a run needs at least one")):
        bad = build_parser().parse_args(["dial", "--steps", "2", "--restarts", restarts, "--select-step", step,
                                         "--workdir", str(tmp_path / "bad")])
        with pytest.raises(SystemExit, match=message):
            dial.clone(bad, dial_dataset, dial.METHODS[0], 1)
        bad.argv = None
        with pytest.raises(SystemExit, match=message):  # before recording anything
            bad.func(bad)
    assert not (tmp_path / "bad").exists()
    moe = dial.METHODS[1]
    setting = Setting("dial", ((dial.DATA, dial.TWO_DIGIT_PINS),), dial.N_OPTIONS, dial.FINETUNE_PINS)
    command = finetune_command(args, setting, moe, "sparse", 1, [clones["moe"]], tmp_path / "out")
    assert command[command.index("--tasks") + 1] == "124,481,842" and "--flat" not in command
    assert command[command.index("--checkpoint") + 1] == str(clones["moe"].checkpoint)
    assert command[command.index("--gamma") + 1] == "0.995"  # Dial's discount, not the paper's 0.97
    # The reproduction's own finetuning step, on the command line's settings, then its results files.
    run = finetune_run(args, setting, dial.METHODS[0], "sparse", 1, [clones["ocn"]])
    assert run["method"] == "OCN" and run["command"].startswith("ocn-finetune") and run["curve"]
    result = dial.write_results(args, dial_dataset, [], [run], 1, 1.0)
    assert result["runs_finished"] == 1 and (tmp_path / "results" / "dial.md").exists()
    # Clones under the usage balance (Dial's default) live beside the paper-loss ones.
    paper = argparse.Namespace(workdir=tmp_path, usage_balance=0.0)
    assert dial.clone_dir(paper, moe, 2) == tmp_path / "clone" / "dial2" / "moe" / "seed2"
    assert dial.clone_dir(args, moe, 2) == tmp_path / "clone" / "dial2" / "moe_usage_balance1.0" / "seed2"


def test_dial_clones_asked_for_the_packed_view_train_on_it_in_folders_of_their_own(dial_dataset, tmp_path):
    from ocn_data.packed_view import packed_view_path
    from tools.reproduce import build_parser, dial
    from tools.reproduce.runs import run_command

    args = build_parser().parse_args(["dial", "--window-start", "packed", "--workdir", str(tmp_path)])
    for method in dial.METHODS:
        overrides = dial.clone_overrides(args, method)
        command, _ = run_command(dial.train_settings(args), dial_dataset, DIAL_REPO_ID, tmp_path / method.key, 1,
                                 overrides)
        assert "--policy.window_start=packed" in command, method.key
        # The view keeps each longer episode's first window, as the recipe's skip_long_episodes trains on.
        assert f"--dataset.root={packed_view_path(dial_dataset, 120, cut_long=True)}" in command, method.key
        assert dial.clone_dir(args, method, 1).parent.name == f"{method.key}_usage_balance1.0_packed"


def test_dial_checks_hold_only_where_ocn_meets_the_bars_and_beats_moe():
    from tools.reproduce.dial import must_show

    imitated = {"f1_tol1": {"mean": 0.95}, "nmi": {"mean": 0.7}, "mean_success_rate": {"mean": 0.85}}
    summary = {"OCN | sparse": {"at_budget": {"success": {"mean": 0.75}}},
               "MoE | sparse": {"at_budget": {"success": {"mean": 0.8}}}}
    checks = {check["check"].split(" (")[0]: check["holds"] for check in must_show(imitated, summary)}
    assert checks == {
        "OCN imitation: F1@1 >= 0.9": True, "OCN imitation: NMI >= 0.8": False,
        "OCN imitation: 2-digit success >= 0.8": True, "OCN, sparse: 3-digit success >= 0.7": True,
        "sparse: MoE's 3-digit success below OCN's": False,
    }
    assert must_show({}, {}) == []
