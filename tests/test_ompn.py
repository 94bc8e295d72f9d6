"""Tests of the OMPN baseline: the ordered memory's equations, masks and gradients, stateful inference,
and the whole path through LeRobot (`lerobot-train --policy.type=ompn`, `from_pretrained`, the
Craft rollout `lerobot-eval` runs) and through `ocn-eval`'s model-agnostic parsing.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from conftest import CRAFT_REPO_ID, craft_rollout, episode_windows, reload_checkpoint, train_on_craft
from lerobot.configs import PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.ompn import OMPNConfig, OMPNPolicy
from lerobot_policy_ocn.ompn.memory import stick_breaking
from lerobot_policy_ocn.ompn.modeling_ompn import expansion_boundaries, threshold_boundaries
from lerobot_policy_ocn.tools.cli import ocn_eval
from lerobot_policy_ocn.tools.eval.parsing import (
    Segmentation, load_ocn, load_policy, score_segmentations, segment_episodes,
)
from lerobot_policy_ocn.tools.eval.metrics import boundaries_from_labels, parsing_scores

torch.set_num_threads(1)

TASKS = ["make plank", "get gold"]
STATE_DIM = 6
N_SLOTS = 3
STEPS = 3


def make_policy(action_type: str = "discrete", action_dim: int = 1, **overrides) -> OMPNPolicy:
    settings = dict(
        device="cpu",
        obs_encoder="identity",
        action_type=action_type,
        n_actions=4,
        n_slots=N_SLOTS,
        hidden_size=8,
        cell_hidden_size=12,
        tasks=list(TASKS),
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )
    settings.update(overrides)
    torch.manual_seed(0)
    return OMPNPolicy(OMPNConfig(**settings))


def make_batch(lengths: list[int], steps: int = 6) -> dict:
    return episode_windows(lengths, STATE_DIM, TASKS, steps)


# ---- the ordered memory ------------------------------------------------------------------------------


def test_stick_breaking_by_hand_and_sums_to_one():
    beta = torch.tensor([[0.5, 0.2], [0.25, 1.0]])  # [n - 1 = 2 slots below the top, B = 2]
    expected = torch.tensor([[0.5, 0.2], [0.5 * 0.25, 0.8 * 1.0], [0.5 * 0.75, 0.0]])
    torch.testing.assert_close(stick_breaking(beta), expected)
    random = stick_breaking(torch.rand(4, 7))
    torch.testing.assert_close(random.sum(0), torch.ones(7))


def test_gated_cell_is_the_ompn_equation():
    """Composition cell i by hand: gates = sigmoid(LN_affine(.)), out = LN(g_v v + g_h h + g_c new)."""
    cells = make_policy().memory.compose
    with torch.no_grad():
        for param in (cells.gate_weight, cells.gate_bias):
            param.normal_()
    v, h, c = torch.randn(5, 8), torch.randn(5, 8), torch.randn(5, 16)
    i = 1
    out = cells.cell(cells.unbound()[i], v, cells.prepare(cells.project(c), h.expand(N_SLOTS, -1, -1))[i], h)
    weight = torch.cat([cells.w_chain[i], cells.w_side[i], cells.w_context[i]])
    first = torch.cat([v, h, c], -1) @ weight + cells.b_in[i]
    gates, new = (torch.relu(first) @ cells.w_out[i] + cells.b_out[i]).split([24, 8], -1)
    g_v, g_h, g_c = torch.sigmoid(F.layer_norm(gates, (24,)) * cells.gate_weight[i] + cells.gate_bias[i]).chunk(3, -1)
    torch.testing.assert_close(out, F.layer_norm(g_v * v + g_h * h + g_c * new, (8,)))


def force_expansion(policy: OMPNPolicy, stop_logit: float) -> None:
    """Every slot's stopping probability beta = sigmoid(stop_logit): +big stops at the bottom, -big at the top."""
    with torch.no_grad():
        policy.memory.expansion_out.weight.zero_()
        policy.memory.expansion_out.bias.fill_(stop_logit)


@pytest.mark.parametrize(("stop_logit", "changed"), [(50.0, [True, False, False]), (-50.0, [True, True, True])])
def test_expansion_height_decides_which_slots_change(stop_logit, changed):
    policy = make_policy()
    force_expansion(policy, stop_logit)
    memory_net, batch = policy.memory, make_batch([2, 2])
    task = memory_net.task_embedding(policy.task_index(batch["task"], 2))
    x = [memory_net.obs_projection(batch[OBS_STATE][:, t]) for t in range(2)]
    first, p_first, _ = memory_net.step(None, x[0], task, memory_net.context(x[0], task))
    torch.testing.assert_close(p_first, torch.tensor([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]]))  # t = 1: full expansion
    torch.testing.assert_close(first[-1], F.layer_norm(task, (8,)))  # the top slot holds the task
    second, p, _ = memory_net.step(first, x[1], task, memory_net.context(x[1], task))
    assert p.argmax(0).tolist() == ([0, 0] if stop_logit > 0 else [N_SLOTS - 1] * 2)
    differs = [(second[i] - first[i]).abs().max().item() > 1e-4 for i in range(N_SLOTS)]
    assert differs == changed


def test_shapes_masks_and_expansion_distribution():
    policy = make_policy()
    batch = make_batch([6, 3, 1, 4])
    loss, stats = policy(batch)
    assert torch.isfinite(loss) and stats["frames_used"] == 14 and 0.0 <= stats["mean_depth"] <= N_SLOTS - 1
    parsed = policy.parse(batch)
    assert parsed["expansion"].shape == (4, 6, N_SLOTS) and parsed["depth"].shape == parsed["mask"].shape == (4, 6)
    real = parsed["mask"]
    torch.testing.assert_close(parsed["expansion"].sum(-1)[real], torch.ones(14))
    assert (parsed["expansion"][~real] == 0).all()  # padding is never run
    assert (parsed["depth"][:, 0] == N_SLOTS - 1).all()  # every episode starts with a full expansion
    # Padding's content cannot matter, and a row's parse does not depend on its batch-mates.
    noisy = {**batch, OBS_STATE: torch.where(real[..., None], batch[OBS_STATE], torch.randn_like(batch[OBS_STATE]))}
    torch.testing.assert_close(policy(noisy)[0], loss)
    alone = {key: value[1:2] for key, value in batch.items() if key != "task"} | {"task": batch["task"][1:2]}
    torch.testing.assert_close(policy.parse(alone)["expansion"][0], parsed["expansion"][1])


def test_gradients_reach_every_slot_and_the_task_embedding():
    policy = make_policy()
    loss, _ = policy(make_batch([6, 5, 6, 4]))
    loss.backward()
    memory = policy.memory
    for cells in (memory.compose, memory.decompose):
        for name, param in cells.named_parameters():
            per_slot = param.grad.flatten(1).abs().sum(1)
            assert (per_slot > 0).all(), name
    assert memory.decompose.w_chain.shape[0] == N_SLOTS - 1  # the bottom slot has no child to build
    assert (memory.task_embedding.weight.grad.abs().sum(1) > 0).all()
    for name, param in policy.named_parameters():
        assert param.grad is not None and param.grad.abs().sum() > 0, name


def test_select_action_keeps_the_memory_and_reset_clears_it():
    policy = make_policy(inference_mode="greedy")
    episode = make_batch([4, 4], steps=4)
    actions = [policy.select_action({OBS_STATE: episode[OBS_STATE][:, t], "task": episode["task"]}) for t in range(4)]
    torch.testing.assert_close(policy.last_expansion, policy.parse(episode)["expansion"][:, -1])
    policy.reset()
    assert torch.equal(policy.select_action({OBS_STATE: episode[OBS_STATE][:, 0], "task": episode["task"]}), actions[0])
    assert actions[0].shape == (2, 1)
    with pytest.raises(ValueError, match="Batch size changed from 2 to 3 without reset"):
        policy.select_action({OBS_STATE: torch.randn(3, STATE_DIM), "task": "get gold"})


def test_continuous_actions_and_bad_config():
    policy = make_policy("continuous", action_dim=2)
    batch = make_batch([3, 2]) | {ACTION: torch.randn(2, 6, 2)}
    assert torch.isfinite(policy(batch)[0])
    assert policy.select_action({OBS_STATE: torch.randn(5, STATE_DIM), "task": "get gold"}).shape == (5, 2)
    assert PreTrainedConfig.get_choice_class("ompn") is OMPNConfig
    defaults = OMPNConfig(device="cpu")
    assert (defaults.n_slots, defaults.hidden_size, defaults.get_optimizer_preset().grad_clip_norm) == (3, 128, 0.2)
    with pytest.raises(ValueError, match="n_slots must be >= 2"):
        OMPNConfig(device="cpu", n_slots=1)


def test_boundary_read_out():
    depth = np.array([2.0, 0.1, 1.5, 0.2, 1.5, 0.9])
    # A new subtask starts at each high expansion, so the boundary is the step before it; the last
    # step always ends the last segment.
    assert expansion_boundaries(depth, 2).tolist() == [1, 5]  # a tie goes to the earlier step
    assert expansion_boundaries(depth, 3).tolist() == [1, 3, 5]
    assert expansion_boundaries(depth, 6).tolist() == [0, 1, 2, 3, 4, 5]  # step 0 never starts one
    assert expansion_boundaries(depth, 1).tolist() == [5]
    with pytest.raises(ValueError, match="Cannot pick 7 boundaries in an episode of 6 steps"):
        expansion_boundaries(depth, 7)


def test_count_free_read_out():
    # Scaled heights 1, 0, 0.74, 0.05, 0.74, 0.42: at 0.5 the runs at steps 2 and 4 start subtasks.
    depth = np.array([2.0, 0.1, 1.5, 0.2, 1.5, 0.9])
    assert threshold_boundaries(depth, 0.5).tolist() == [1, 3, 5]
    assert threshold_boundaries(depth, 0.3).tolist() == [1, 3, 5]  # steps 4-5 are one run, peaked at 4
    assert threshold_boundaries(depth, 0.8).tolist() == [5]  # no step but the first is that high
    # The run that holds step 0 is the episode's start; a later run's boundary is before its peak.
    assert threshold_boundaries(np.array([2.0, 1.9, 0.1, 1.2, 1.8, 0.1]), 0.5).tolist() == [3, 5]
    assert threshold_boundaries(np.array([1.0, 1.0, 1.0]), 0.5).tolist() == [2]  # flat: one segment
    with pytest.raises(ValueError, match="must lie in \\(0, 1\\), got 1.0"):
        threshold_boundaries(depth, 1.0)
    with pytest.raises(ValueError, match="boundary_threshold must lie in \\(0, 1\\) or be None, got 0.0"):
        OMPNConfig(device="cpu", boundary_threshold=0.0)


# ---- through LeRobot and ocn-eval ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def ompn_checkpoint(craft_dataset, tmp_path_factory) -> Path:
    """A few steps of `lerobot-train --policy.type=ompn` on the session's Craft dataset."""
    out = tmp_path_factory.mktemp("ompn_train") / "train"
    flags = ("--policy.hidden_size=16", "--policy.cell_hidden_size=16", "--policy.window_size=24")
    return train_on_craft("ompn", craft_dataset, out, STEPS, *flags)


def test_trained_checkpoint_reloads_and_yields_boundaries(ompn_checkpoint, craft_dataset):
    policy, preprocessor = reload_checkpoint(ompn_checkpoint, OMPNPolicy)
    assert policy.config.hidden_size == 16 and len(policy.config.tasks) == 2
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    parses = segment_episodes(policy, preprocessor, episodes)
    assert len(parses) == len(episodes.tasks)
    for i, parse in enumerate(parses):
        true = boundaries_from_labels(episodes.subtask_index[i, : episodes.lengths[i]])
        assert parse.labels is None and parse.boundaries.shape == true.shape
        assert (np.diff(parse.boundaries) > 0).all() and 0 < parse.boundaries[0]
        assert parse.boundaries[-1] < episodes.lengths[i]
    with pytest.raises(ValueError, match="holds an `ompn` checkpoint; this tool needs an `ocn` one"):
        load_ocn(ompn_checkpoint)


def test_ompn_acts_in_lerobot_evals_craft_rollout(ompn_checkpoint):
    policy = OMPNPolicy.from_pretrained(ompn_checkpoint)
    craft_rollout(policy)
    assert policy.last_expansion.shape == (2, policy.config.n_slots)


def test_ocn_eval_scores_an_ompn_checkpoint(ompn_checkpoint, craft_dataset, tmp_path):
    out = tmp_path / "eval.json"
    base = ["--policy", str(ompn_checkpoint), "--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID,
            "--rollouts", "2"]
    assert ocn_eval.main([*base, "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["policy_type"] == "ompn" and 0.0 <= result["f1_tol0"] <= result["f1_tol1"] <= 1.0
    assert 0.0 <= result["align_acc"] <= 1.0 and 0.0 <= result["mean_success_rate"] <= 1.0
    assert result["nmi"] is None and result["option_subtask_success"] is None
    assert set(result["not_applicable"]) == {"nmi", "option_subtask_success"} and result["action_nll"] > 0.0
    assert list(result["success_rate"]) == ["get wood, get iron", "get iron, get grass"]
    assert not out.with_suffix(".png").exists() and result["boundary_threshold"] is None
    assert result["parse_statistics"]["segments_per_episode"] == result["parse_statistics"]["true_segments_per_episode"]
    assert ocn_eval.main([*base, "--out", str(tmp_path / "x.json"), "--mcap", str(tmp_path / "x.mcap")]) == 2


def test_ocn_eval_count_free_read_out(ompn_checkpoint, ocn_checkpoint, craft_dataset, tmp_path, capsys):
    """--boundary-threshold parses OMPN without the true counts; it is refused out of range and for
    a model that has no such read-out."""
    out = tmp_path / "eval.json"
    base = ["--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--rollouts", "1"]
    assert ocn_eval.main(["--policy", str(ompn_checkpoint), *base, "--out", str(out),
                          "--boundary-threshold", "0.5"]) == 0
    result = json.loads(out.read_text())
    assert result["boundary_threshold"] == 0.5 and 0.0 <= result["f1_tol0"] <= result["f1_tol1"] <= 1.0
    policy, preprocessor = reload_checkpoint(ompn_checkpoint, OMPNPolicy)
    policy.config.boundary_threshold = 0.5
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    parses = segment_episodes(policy, preprocessor, episodes)
    depths = policy.parse(preprocessor({
        OBS_STATE: torch.from_numpy(episodes.state).float(), ACTION: torch.from_numpy(episodes.action).float(),
        f"{ACTION}_is_pad": torch.from_numpy(~episodes.mask), "task": episodes.tasks,
    }))
    for i, parse in enumerate(parses):
        n = episodes.lengths[i]
        assert parse.boundaries.tolist() == threshold_boundaries(depths["depth"][i, :n].numpy(), 0.5).tolist()
    segments = np.mean([len(parse.boundaries) for parse in parses])
    assert result["parse_statistics"]["segments_per_episode"] == pytest.approx(segments)
    refused = str(tmp_path / "refused.json")  # a new --out: ocn-eval keeps the result above
    assert ocn_eval.main(["--policy", str(ompn_checkpoint), *base, "--out", refused, "--boundary-threshold", "1"]) == 2
    assert "boundary_threshold must lie in (0, 1)" in capsys.readouterr().err
    assert ocn_eval.main(["--policy", str(ocn_checkpoint), *base, "--out", refused,
                          "--boundary-threshold", "0.5"]) == 2
    assert "`ocn` has none" in capsys.readouterr().err


def test_shared_metrics_read_only_the_predictions(ompn_checkpoint, ocn_checkpoint, craft_dataset):
    """Both models' parses are scored by one function that sees boundaries and labels only: the same
    predictions score the same whichever model they came from, and NMI needs labels."""
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    ompn = segment_episodes(*load_policy(ompn_checkpoint)[:2], episodes)
    ocn = segment_episodes(*load_ocn(ocn_checkpoint)[:2], episodes)
    segments = [episodes.subtask_index[i, :n] for i, n in enumerate(episodes.lengths)]
    for parses in (ompn, ocn):
        boundaries = [parse.boundaries for parse in parses]
        unlabelled = score_segmentations(episodes, [Segmentation(b, None) for b in boundaries])
        assert unlabelled == {**parsing_scores(segments, segments, boundaries), "nmi": None}
        labelled = score_segmentations(episodes, parses)
        assert {key: labelled[key] for key in ("f1_tol0", "f1_tol1", "align_acc")} == {
            key: unlabelled[key] for key in ("f1_tol0", "f1_tol1", "align_acc")
        }
    assert score_segmentations(episodes, ompn)["nmi"] is None and score_segmentations(episodes, ocn)["nmi"] is not None
