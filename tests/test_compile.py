"""Tests of the compILE baseline: its loss against a case worked by hand, the boundary masks, the
online `select_action`, and the whole path through LeRobot (`lerobot-train --policy.type=compile`,
`from_pretrained`, the Craft rollout `lerobot-eval` runs) and through `ocn-eval`'s shared parsing.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from conftest import CRAFT_REPO_ID, craft_rollout, episode_windows, reload_checkpoint, run_cli
from lerobot.configs import PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.compile import CompILEConfig, CompILEPolicy
from lerobot_policy_ocn.compile.modeling_compile import NEG, CompILEOutput, compile_loss, latent_kl, length_prior
from lerobot_policy_ocn.tools.eval.parsing import load_policy, score_segmentations, segment_episodes

torch.set_num_threads(1)

TASKS = ["make plank", "get gold"]
STATE_DIM = 5


def make_policy(action_type: str = "discrete", action_dim: int = 1, **overrides) -> CompILEPolicy:
    settings = dict(
        device="cpu", obs_encoder="identity", action_type=action_type, n_actions=4, n_segments=3, latent_dim=3,
        hidden_size=8, tasks=list(TASKS),
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (STATE_DIM,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )
    settings.update(overrides)
    torch.manual_seed(0)
    return CompILEPolicy(CompILEConfig(**settings))


def make_batch(lengths: list[int]) -> dict:
    return episode_windows(lengths, STATE_DIM, TASKS)


# ---- the loss, by hand ----------------------------------------------------------------------------------


def test_loss_by_hand():
    """Two segments over one episode of 3 steps (positions 0..3; a boundary at p starts the next
    segment at step p): b_0 = half at 1, half at 2; the last boundary sits at the end, p = 3."""
    log = math.log
    out = CompILEOutput(
        boundary_logits=torch.tensor([[[NEG, 0.0, 0.0, 0.0]]]),  # q(b_0) = 1/3 at each of p = 1, 2, 3
        boundaries=torch.tensor([[[0.0, 0.5, 0.5, 0.0]], [[0.0, 0.0, 0.0, 1.0]]]),
        latent_params=torch.tensor([[[0.0, 0.0]], [[log(3.0), 0.0]]]),  # q(z_0) uniform, q(z_1) = (3/4, 1/4)
        latents=torch.zeros(2, 1, 2),
        action_log_prob=torch.log(torch.tensor([[[0.5, 0.25, 0.1]], [[0.2, 0.4, 0.8]]])),
    )
    config = CompILEConfig(device="cpu")
    loss, terms = compile_loss(out, torch.ones(1, 3, dtype=torch.bool), config)
    # Segment 0 holds step 0 surely and step 1 half; segment 1 the other half of step 1 and step 2.
    nll = -(log(0.5) + 0.5 * log(0.25) + 0.5 * log(0.4) + log(0.8))
    kl_z = 0.0 + (0.75 * log(0.75) + 0.25 * log(0.25) + log(2.0))
    # Poisson(3) over the first segment's length p = 1, 2, 3: e^-3 (3, 4.5, 4.5), renormalised.
    prior = [3.0 / 12, 4.5 / 12, 4.5 / 12]
    kl_b = sum(1.0 / 3 * log((1.0 / 3) / p) for p in prior)
    torch.testing.assert_close(terms["nll"], torch.tensor([nll]))
    torch.testing.assert_close(terms["kl_z"], torch.tensor([kl_z]))
    torch.testing.assert_close(terms["kl_b"], torch.tensor([kl_b]))
    torch.testing.assert_close(loss, torch.tensor([nll + 0.1 * kl_z + 0.1 * kl_b]))
    # A padded fourth step changes nothing: neither the NLL (masked) nor the boundary prior (p <= L).
    padded = CompILEOutput(
        boundary_logits=torch.tensor([[[NEG, 0.0, 0.0, 0.0, NEG]]]),
        boundaries=torch.tensor([[[0.0, 0.5, 0.5, 0.0, 0.0]], [[0.0, 0.0, 0.0, 1.0, 0.0]]]),
        latent_params=out.latent_params,
        latents=out.latents,
        action_log_prob=torch.cat([out.action_log_prob, torch.full((2, 1, 1), -7.0)], dim=2),
    )
    torch.testing.assert_close(compile_loss(padded, torch.tensor([[True, True, True, False]]), config)[0], loss)


def test_length_prior_and_gaussian_kl_by_hand():
    start = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])  # the segment starts at step 2
    allowed = torch.tensor([[False, True, True, True, True, True]])
    prior = length_prior(start, allowed, 3.0).exp()
    pmf = torch.tensor([3.0, 4.5, 4.5])  # Poisson(3) of lengths 1, 2, 3, up to e^-3
    torch.testing.assert_close(prior[0, 3:], pmf / pmf.sum())
    assert prior[0, :3].sum() < 1e-30  # no mass where the segment would be empty or end before it starts
    params = torch.tensor([[1.0, 0.0, 0.0, math.log(2.0)]])  # mean (1, 0), log-variance (0, log 2)
    torch.testing.assert_close(latent_kl(params, "gaussian"), torch.tensor([0.5 + 0.5 * (1.0 - math.log(2.0))]))


# ---- the model ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("training", [True, False])
def test_boundaries_respect_padding_and_never_fall_on_position_zero(training):
    policy = make_policy()
    policy.train(training)
    batch = make_batch([6, 3, 1, 4])
    mask = ~batch[f"{ACTION}_is_pad"]
    out = policy._run(batch[OBS_STATE], batch[ACTION], mask, hard=not training)
    lengths = mask.sum(1)
    beyond = torch.arange(7)[None] > lengths[:, None]
    q = torch.softmax(out.boundary_logits, dim=-1)
    for distribution in (q, out.boundaries):
        assert (distribution[..., 0] == 0).all() and (distribution * beyond).sum() == 0
    torch.testing.assert_close(out.boundaries.sum(-1), torch.ones(3, 4))
    assert (out.boundaries[-1].argmax(-1) == lengths).all()  # the last segment ends at the episode's end
    # Padding's content cannot matter, and an episode's parse does not depend on its batch-mates.
    loss, stats = policy(batch)
    assert torch.isfinite(loss) and stats["frames_used"] == 14
    noisy = {**batch, OBS_STATE: torch.where(mask[..., None], batch[OBS_STATE], torch.randn_like(batch[OBS_STATE]))}
    if not training:
        torch.testing.assert_close(policy(noisy)[0], loss)
        alone = {key: value[1:2] for key, value in batch.items() if key != "task"} | {"task": batch["task"][1:2]}
        torch.testing.assert_close(policy.parse(alone)["segment"][0, :3], policy.parse(batch)["segment"][1, :3])


def test_gradients_reach_every_parameter():
    policy = make_policy()
    policy(make_batch([6, 5, 6, 4]))[0].backward()
    for name, param in policy.named_parameters():
        assert param.grad is not None and param.grad.abs().sum() > 0, name


def test_parse_segments_and_labels():
    policy = make_policy()
    batch = make_batch([6, 3, 1, 4])
    parsed = policy.parse(batch)
    real = parsed["mask"]
    assert (parsed["segment"][~real] == -1).all() and (parsed["label"][~real] == -1).all()
    for row, length in zip(parsed["segment"], real.sum(1), strict=True):
        assert row[0] == 0 and (row[:length].diff() >= 0).all()
    assert parsed["label"][real].max() < policy.config.latent_dim and parsed["boundary"].shape == (4, 3)
    assert (make_policy(latent_type="gaussian").parse(batch)["label"] == -1).all()
    with pytest.raises(ValueError, match="its encoder reads the actions"):
        policy.parse({key: value for key, value in batch.items() if key != ACTION})


def test_select_action_acts_from_the_parse_of_its_history():
    policy = make_policy(inference_mode="greedy")
    policy.eval()
    states = torch.randn(2, 5, STATE_DIM)
    actions = [policy.select_action({OBS_STATE: states[:, t], "task": "get gold"}) for t in range(5)]
    assert actions[0].shape == (2, 1)
    torch.testing.assert_close(policy.last_latent.sum(-1), torch.ones(2))
    history = {OBS_STATE: states[:, :4], ACTION: torch.stack(actions[:4], dim=1), "task": ["get gold"] * 2}
    # The fifth step acted with the latent of the segment that the history's last step lies in.
    assert policy.last_latent.argmax(-1).tolist() == policy.parse(history)["label"][:, -1].tolist()
    policy.reset()
    assert policy.last_latent is None
    first = policy.select_action({OBS_STATE: states[:, 0], "task": "get gold"})
    torch.testing.assert_close(policy.last_latent, torch.full((2, 3), 1.0 / 3))  # t = 1: the uniform prior
    assert torch.equal(first, actions[0])
    with pytest.raises(ValueError, match="Batch size changed from 2 to 3 without reset"):
        policy.select_action({OBS_STATE: torch.randn(3, STATE_DIM), "task": "get gold"})


def test_continuous_gaussian_latents_and_bad_config():
    policy = make_policy("continuous", action_dim=2, latent_type="gaussian")
    batch = make_batch([3, 2]) | {ACTION: torch.randn(2, 6, 2)}
    assert torch.isfinite(policy(batch)[0])
    assert policy.select_action({OBS_STATE: torch.randn(5, STATE_DIM), "task": "get gold"}).shape == (5, 2)
    assert policy.select_action({OBS_STATE: torch.randn(5, STATE_DIM), "task": "get gold"}).shape == (5, 2)
    assert PreTrainedConfig.get_choice_class("compile") is CompILEConfig
    defaults = CompILEConfig(device="cpu")
    assert (defaults.n_segments, defaults.latent_type) == (4, "concrete")
    assert (defaults.kl_z_weight, defaults.kl_b_weight) == (0.1, 0.1)
    assert (defaults.poisson_rate, defaults.get_optimizer_preset().lr) == (3.0, 1e-4)
    with pytest.raises(ValueError, match="`latent_type` must be one of"):
        CompILEConfig(device="cpu", latent_type="vq")
    with pytest.raises(ValueError, match="n_segments, latent_dim and hidden_size must be >= 1"):
        CompILEConfig(device="cpu", n_segments=0)


# ---- through LeRobot and ocn-eval (the checkpoint: conftest's `compile_checkpoint`) -------------------


def test_trained_checkpoint_reloads_and_segments(compile_checkpoint, craft_dataset):
    policy, preprocessor = reload_checkpoint(compile_checkpoint, CompILEPolicy)
    assert policy.config.latent_dim == 4 and len(policy.config.tasks) == 2
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    parses = segment_episodes(policy, preprocessor, episodes)
    assert len(parses) == len(episodes.tasks)
    for parse, length in zip(parses, episodes.lengths, strict=True):
        assert (np.diff(parse.boundaries) > 0).all() and 0 <= parse.boundaries[0]
        assert parse.boundaries[-1] == length - 1 and parse.boundaries.size <= policy.config.n_segments
        assert parse.labels.shape == (length,) and 0 <= parse.labels.min() and parse.labels.max() < 4
    assert score_segmentations(episodes, parses)["nmi"] is not None


def test_gaussian_latents_parse_without_labels(craft_dataset, compile_checkpoint):
    _, preprocessor, _ = load_policy(compile_checkpoint)
    config = PreTrainedConfig.from_pretrained(compile_checkpoint)
    config.latent_type = "gaussian"
    torch.manual_seed(0)
    policy = CompILEPolicy(config).eval()
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    parses = segment_episodes(policy, preprocessor, episodes)
    assert all(parse.labels is None for parse in parses) and score_segmentations(episodes, parses)["nmi"] is None


def test_compile_acts_in_lerobot_evals_craft_rollout(compile_checkpoint):
    policy = CompILEPolicy.from_pretrained(compile_checkpoint)
    craft_rollout(policy)
    assert policy.last_latent.shape == (2, policy.config.latent_dim)


def test_ocn_eval_scores_a_compile_checkpoint(compile_checkpoint, craft_dataset, tmp_path):
    """The console script in a process of its own, which has imported no policy module before it
    loads the checkpoint."""
    out = tmp_path / "eval.json"
    run_cli("ocn-eval", "--policy", str(compile_checkpoint), "--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID,
            "--rollouts", "2", "--max-episodes", "10", "--out", str(out), cwd=tmp_path)
    result = json.loads(out.read_text())
    assert result["policy_type"] == "compile" and 0.0 <= result["f1_tol0"] <= result["f1_tol1"] <= 1.0
    assert 0.0 <= result["align_acc"] <= 1.0 and 0.0 <= result["nmi"] <= 1.0
    assert 0.0 <= result["mean_success_rate"] <= 1.0 and result["option_subtask_success"] is None
    assert set(result["not_applicable"]) == {"option_subtask_success", "action_nll"} and result["episodes_parsed"] <= 10
    assert result["action_nll"] is None
    assert list(result["success_rate"]) == ["get wood, get iron", "get iron, get grass"]
