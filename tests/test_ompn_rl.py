"""OMPN's RL form: the copy for new tasks, PPO over the whole network on primitive actions, and
`ocn-finetune --checkpoint OMPN_CKPT` down to a checkpoint `lerobot-eval` runs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import reload_checkpoint, untrained_checkpoint
from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.observation import OBS_DIM
from lerobot_policy_ocn.envs.craft.world import parse_task, task_description
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ompn import OMPNConfig, OMPNPolicy
from test_ocn_finetune import ADC, CAD, assert_refused, decisions_match_frames, lerobot_eval_rollout, save_variant
from test_ompn import make_policy
from test_ppo import CRAFT, TASK, WoodAhead, wood_success_before_and_after
from lerobot_policy_ocn.tools.cli.ocn_finetune import main
from lerobot_policy_ocn.tools.rl.ompn_rl import TASK_EMBEDDING, MemoryActor, ompn_for_tasks
from lerobot_policy_ocn.tools.rl.ppo import PPOConfig, PPOTrainer, ValueHead, collect
from conftest import CRAFT_STATE

torch.set_num_threads(1)

IRON = task_description(parse_task("C"))


def craft_ompn(tasks: list[str], hidden_size: int = 8) -> OMPNPolicy:
    """A small OMPN over Craft's states and actions, seeded weights."""
    torch.manual_seed(0)
    config = OMPNConfig(
        device="cpu", hidden_size=hidden_size, cell_hidden_size=2 * hidden_size, tasks=tasks, **CRAFT_STATE,
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (OBS_DIM,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))},
    )
    return OMPNPolicy(config).eval()


class RecordingHead:
    """Stands in for an OMPN's action head: keeps every distribution `select_action` sampled from and
    the actions it drew."""

    def __init__(self, head) -> None:
        self.head = head
        self.probs: list[torch.Tensor] = []
        self.actions: list[torch.Tensor] = []

    def choose(self, weights: torch.Tensor, params: torch.Tensor, greedy: bool) -> torch.Tensor:
        self.probs.append(torch.softmax(params[0], -1))
        action = self.head.choose(weights, params, greedy)
        self.actions.append(action[:, 0].long())
        return action


def test_rl_form_keeps_every_weight_and_starts_each_new_task_at_the_mean_embedding():
    source = make_policy(inference_mode="greedy")
    trained = {name: value.clone() for name, value in source.state_dict().items()}
    copy = ompn_for_tasks(source, ["a", "b", "c"])
    assert copy.config.tasks == ["a", "b", "c"] and copy.config.inference_mode == "sample"
    state = copy.state_dict()
    assert set(state) == set(trained)
    for name, value in trained.items():
        if name != TASK_EMBEDDING:
            assert torch.equal(state[name], value), name
    torch.testing.assert_close(state[TASK_EMBEDDING], trained[TASK_EMBEDDING].mean(0).expand(3, -1))
    assert all(torch.equal(value, trained[name]) for name, value in source.state_dict().items())


def test_every_step_is_a_decision_and_the_replay_gives_what_select_action_sampled_from():
    policy = craft_ompn([TASK, IRON])
    recorder = RecordingHead(policy.head)
    policy.head = recorder
    batch = collect(policy, CraftBatch(6, reward="dense", max_steps=10), CRAFT, [TASK, IRON] * 3, range(6), gamma=0.9)
    assert np.array_equal(batch.count, batch.frames) and (batch.duration == batch.mask).all()
    np.testing.assert_allclose(batch.reward.sum(1), batch.return_)
    mask = torch.from_numpy(batch.mask)
    steps = mask.shape[1]
    actions = torch.stack(recorder.actions, 1)[:, :steps]
    assert torch.equal(torch.from_numpy(batch.option)[mask], actions[mask])
    actor = MemoryActor(policy)
    logits, value = actor.replay(ValueHead(actor.critic_size, 8), torch.from_numpy(batch.state),
                                 torch.from_numpy(batch.task_index), torch.from_numpy(batch.count))
    assert logits.shape == (6, steps, 5) and value.shape == (6, steps)
    sampled = torch.stack(recorder.probs, 1)[:, :steps]
    torch.testing.assert_close(torch.softmax(logits, -1)[mask], sampled[mask], rtol=1e-5, atol=1e-6)


def test_ppo_trains_every_weight_with_the_critic_from_a_ratio_of_one():
    policy = craft_ompn([TASK])
    batch = collect(policy, WoodAhead(16, reward="sparse", max_steps=6), CRAFT, [TASK] * 16, range(16), 0.97)
    trainer = PPOTrainer(policy, PPOConfig(epochs=1, batch_size=10**6))  # one gradient step
    optimised = {id(p) for group in trainer.optimizer.param_groups for p in group["params"]}
    assert optimised == {id(p) for p in [*policy.parameters(), *trainer.critic.parameters()]}
    before = {name: param.detach().clone() for name, param in policy.named_parameters()}
    stats = trainer.update(batch)
    assert stats["approx_kl"] < 1e-7 and stats["clip_fraction"] == 0.0
    assert [name for name, param in policy.named_parameters() if torch.equal(param, before[name])] == []


def test_ppo_refuses_a_greedy_ompn():
    policy = make_policy(inference_mode="greedy")
    with pytest.raises(ValueError, match="discrete actions and inference_mode='sample', got 'discrete' and 'greedy'"):
        PPOTrainer(policy, PPOConfig())


def test_ompn_learns_to_use_the_wood_it_faces_well_above_the_random_rate():
    """As flat PPO must (test_ppo.py), on 2k frames at lr 1e-3 to stay short: the untrained OMPN
    succeeds about 2 times in 5."""
    policy = craft_ompn([TASK], hidden_size=16)
    random_rate, learned = wood_success_before_and_after(policy, 2_000, PPOConfig(lr=1e-3, batch_size=256))
    assert random_rate < 0.5 and learned > 0.9 and learned > random_rate + 0.4, (random_rate, learned)


# ---- ocn-finetune --checkpoint OMPN_CKPT ---------------------------------------------------------------


@pytest.fixture(scope="module")
def untrained_ompn(craft_dataset, tmp_path_factory) -> Path:
    config = OMPNConfig(device="cpu", hidden_size=8, cell_hidden_size=16)
    return untrained_checkpoint(config, craft_dataset, tmp_path_factory.mktemp("ompn") / "pretrained_model")


@pytest.fixture(scope="module")
def finetuned_ompn(untrained_ompn, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ompn_finetune") / "run"
    argv = ["--checkpoint", str(untrained_ompn), "--tasks", "ADC,CAD", "--reward", "dense", "--frames", "150",
            "--envs", "4", "--max-steps", "20", "--seed", "1", "--batch-size", "80", "--out", str(out)]
    assert main(argv) == 0
    return out


def test_finetuning_an_ompn_writes_the_same_curve_and_an_ompn_checkpoint(finetuned_ompn, untrained_ompn):
    header = next(csv.reader(open(finetuned_ompn / "curve.csv")))
    assert {"frames", "mean_return", "success", "success[ADC]", "success[CAD]", "policy_loss"} <= set(header)
    assert decisions_match_frames(finetuned_ompn) and (finetuned_ompn / "curve.png").stat().st_size > 0
    summary = json.loads((finetuned_ompn / "finetune.json").read_text())
    assert summary["policy_type"] == "ompn" and summary["n_options"] is None and summary["n_slots"] == 3
    assert summary["tasks"] == [ADC, CAD] and summary["frames"] >= 150
    policy, _ = reload_checkpoint(finetuned_ompn / "pretrained_model", OMPNPolicy)
    source, _ = reload_checkpoint(untrained_ompn, OMPNPolicy)
    assert policy.config.tasks == [ADC, CAD] and policy.memory.task_embedding.num_embeddings == 2
    trained = source.state_dict()
    unchanged = [name for name, value in policy.state_dict().items() if torch.equal(value, trained[name])]
    assert unchanged == []


def test_finetuned_ompn_runs_under_lerobot_eval_rollout(finetuned_ompn):
    _, policy = lerobot_eval_rollout(finetuned_ompn / "pretrained_model", "craft", "ADC", max_steps=15)
    assert isinstance(policy, OMPNPolicy) and policy.last_expansion.shape == (2, 3)


def test_ompn_checkpoints_are_finetuned_alone_and_in_craft_only(untrained_ompn, ocn_checkpoint, tmp_path, capsys):
    continuous = save_variant(untrained_ompn, tmp_path / "continuous" / "pretrained_model", seed=1,
                              action_type="continuous")
    base = ["--tasks", "ADC", "--frames", "10", "--envs", "2"]
    ompn = ["--checkpoint", str(untrained_ompn)]
    pooled = "has no options to pool, so its whole network is finetuned alone"
    cases = {
        f"Cannot pool {untrained_ompn}, {untrained_ompn}: an `ompn` checkpoint {pooled}":
            [*base, *ompn, *ompn, "--out", str(tmp_path / "a")],
        f"Cannot pool {ocn_checkpoint}, {untrained_ompn}: an `ompn` checkpoint {pooled}":
            [*base, "--checkpoint", str(ocn_checkpoint), *ompn, "--out", str(tmp_path / "b")],
        "continuous actions: OMPN's RL form is finetuned in Craft only":
            [*base, "--checkpoint", str(continuous), "--out", str(tmp_path / "c")],
        "an `ompn` checkpoint has no controller to temper":
            [*base, *ompn, "--temperature", "2", "--out", str(tmp_path / "d")],
        "encoder and continuous actions: OMPN's RL form is finetuned in Craft only":
            ["--tasks", "124", "--frames", "10", "--envs", "2", "--checkpoint", str(continuous),
             "--out", str(tmp_path / "e")],
    }
    assert_refused(cases, capsys)
    assert not any((tmp_path / name).exists() for name in "abcde")
