"""The Dial recipe: the switching affine split found without subtask labels, cached, and taught to the
options before the paper's loss takes over in the final phase."""

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import ACTION, OBS_STATE

from conftest import DIAL_REPO_ID
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.ocn import OCNConfig
from lerobot_policy_ocn.ocn.modeling_ocn import OPTION
from lerobot_policy_ocn.ocn.taught import (
    best_paths,
    cached_split,
    descend,
    episode_frames,
    fit_segmentation,
    split_and_merge,
    split_cache_dir,
)
from lerobot_policy_ocn.tools.eval.metrics import normalized_mutual_info


def test_best_paths_pay_the_switch_penalty_and_leave_padding_unlabelled():
    errors = np.array([[[0.0, 5.0], [0.0, 5.0], [5.0, 0.0], [5.0, 0.0]],
                       [[0.0, 1.0], [1.0, 0.0], [0.0, 1.0], [9.0, 9.0]]])
    mask = np.array([[True] * 4, [True, True, True, False]])
    labels, cost = best_paths(errors, mask, switch_penalty=3.0)
    # Episode 0 switches once (3 < 10); episode 1 stays on map 0 (1 < 2 x 3) and its padding is -1.
    assert labels.tolist() == [[0, 0, 1, 1], [0, 0, 0, -1]]
    assert cost == pytest.approx(3.0 + 1.0)
    labels, cost = best_paths(errors, mask, switch_penalty=100.0)
    assert labels[0].tolist() in ([0] * 4, [1] * 4) and cost == pytest.approx(10.0 + 1.0)


def switching_affine_episodes(n_episodes: int = 60, seed: int = 0):
    """Episodes of three segments, each driven by one of three affine maps (a random order per
    episode), with the true map of each frame."""
    rng = np.random.default_rng(seed)
    maps = rng.normal(size=(3, 6, 2)) * 2
    length = 75
    state = rng.normal(size=(n_episodes, length, 5))
    truth = np.full((n_episodes, length), -1)
    mask = np.zeros((n_episodes, length), bool)
    for row in range(n_episodes):
        cuts = np.cumsum(rng.integers(15, 26, size=3))
        mask[row, :cuts[-1]] = True
        for segment, option in enumerate(rng.permutation(3)):
            truth[row, (cuts[segment - 1] if segment else 0):cuts[segment]] = option
    inputs = np.concatenate([state, np.ones((n_episodes, length, 1))], -1)
    action = np.einsum("ets,etsa->eta", inputs, maps[truth.clip(0)]) + 0.05 * rng.normal(size=(n_episodes, length, 2))
    real = action[mask]
    return episode_frames(state, action, mask, (real.mean(0), real.std(0))), truth


def test_the_fit_recovers_the_maps_that_drove_the_episodes():
    frames, truth = switching_affine_episodes()
    fit = fit_segmentation(frames, n_maps=3, switch_penalty=5.0, starts=2, seed=0)
    assert normalized_mutual_info(truth[frames.mask], fit.labels[frames.mask]) > 0.99
    assert fit.cost <= min(fit.start_costs) and len(fit.start_costs) == 2


def test_split_and_merge_leaves_the_optimum_that_the_descent_keeps():
    """A start with two true maps merged into one label and the third split across two: the descent
    stays there, and one merge of the split pair with a split of the merged label finds the truth."""
    frames, truth = switching_affine_episodes(seed=1)
    halves = np.arange(truth.shape[0])[:, None] % 2 == 0
    start = np.where(truth == 1, 0, truth)
    start = np.where((truth == 2) & halves, 1, start)
    rng = np.random.default_rng(0)
    stuck, stuck_cost = descend(frames, start, 3, 5.0, rng)
    assert normalized_mutual_info(truth[frames.mask], stuck[frames.mask]) < 0.9
    found, cost, kept = split_and_merge(frames, stuck, stuck_cost, 3, 5.0, rng, chunk=20)
    assert kept >= 1 and cost < stuck_cost
    assert normalized_mutual_info(truth[frames.mask], found[frames.mask]) > 0.99


def test_the_split_of_a_dataset_is_fitted_once_and_read_back_from_the_cache(dial_dataset):
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "train"))
    arrays = (episodes.state.astype(np.float64), episodes.action.astype(np.float64), episodes.mask)
    labels, report = cached_split(*arrays, n_options=2)
    assert labels.shape == episodes.mask.shape and (labels[~episodes.mask] == -1).all()
    assert set(np.unique(labels[episodes.mask])) <= {0, 1} and sum(report.label_share) == int(episodes.mask.sum())
    assert report.cost <= min(report.start_costs)
    assert len(list(split_cache_dir().glob("*.npz"))) >= 1
    again, stored = cached_split(*arrays, n_options=2)
    assert np.array_equal(again, labels) and stored == report  # the same fit, seconds and all: read, not refitted
    other, _ = cached_split(*arrays, n_options=3)
    assert set(np.unique(other[episodes.mask])) <= {0, 1, 2}


def test_a_dial_policy_holds_each_training_frame_s_label_and_is_taught_them_before_its_final_phase(dial_dataset):
    meta = LeRobotDatasetMetadata(DIAL_REPO_ID, root=dial_dataset)
    torch.manual_seed(0)
    policy = make_policy(OCNConfig(device="cpu", hidden_size=16, mlp_hidden_size=16), ds_meta=meta)
    assert policy.config.recipe == "dial" and policy.config.n_options == 4
    memory = policy._episodes
    train = load_episodes(dial_dataset, split_episodes(dial_dataset, "train"))
    labels, _ = cached_split(train.state.astype(np.float64), train.action.astype(np.float64), train.mask, 4)
    option = memory.frames[OPTION]
    for row, episode in enumerate(train.episode_index):
        start, length = int(memory.start[episode]), int(memory.length[episode])
        assert option[start:start + length].tolist() == labels[row, :length].tolist()
    held_out = [int(e) for e in split_episodes(dial_dataset, "val")]
    assert all((option[int(memory.start[e]):int(memory.start[e] + memory.length[e])] == -1).all() for e in held_out)

    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    clock = policy.config.get_scheduler_preset().build(optimizer, num_training_steps=10)
    frames = LeRobotDataset(DIAL_REPO_ID, root=dial_dataset)
    starts = meta.episodes["dataset_from_index"]
    batch = torch.utils.data.default_collate([frames[int(starts[int(e)])] for e in train.episode_index])
    loss, stats = policy(batch)
    mask, state, action, tasks, columns = policy.training_windows(batch)
    episodes = {OBS_STATE: state, ACTION: action, "task": tasks}
    expected, _ = policy.labelled_forward(episodes, columns[OPTION].masked_fill(~mask, -1), 5.0)
    torch.testing.assert_close(loss, expected)
    assert "choice_ce" in stats and "final_phase" not in stats
    for _ in range(8):  # the final fifth of 10 steps: the paper's loss, at 0.03 times the lr
        optimizer.step()
        clock.step()
    loss, stats = policy(batch)
    assert stats["final_phase"] == 1.0 and "choice_ce" not in stats
    policy.config.recipe = "paper"
    torch.testing.assert_close(loss, policy(batch)[0])
    assert optimizer.param_groups[0]["lr"] == pytest.approx(3e-5)
