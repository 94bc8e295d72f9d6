"""The switching affine segmentation that labels options without reading subtask labels."""

import json

import numpy as np
import pytest

from conftest import DIAL_REPO_ID
from ocn_data.episodes_table import load_episodes, split_episodes
from ocn_data.option_labels import read_labels, write_labels
from tools.affine_segmentation import (
    best_paths,
    descend,
    episode_frames,
    fit_segmentation,
    main,
    split_and_merge,
)
from tools.fast_imitation import main as fast_imitation
from tools.parsing_metrics import normalized_mutual_info


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
    return episode_frames(state, action, mask), truth


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


def test_labels_round_trip_and_a_mismatched_file_is_named(dial_dataset, tmp_path):
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "train"))
    labels = np.where(episodes.mask, np.arange(episodes.mask.shape[1]) % 4, -1)
    path = tmp_path / "labels.npz"
    write_labels(path, episodes, labels)
    width = episodes.mask.shape[1] + 3
    back = read_labels(path, episodes.episode_index, episodes.lengths, width)
    assert back.shape == (len(episodes.tasks), width)
    assert np.array_equal(back[:, :labels.shape[1]], labels) and (back[:, labels.shape[1]:] == -1).all()
    with pytest.raises(ValueError, match="no labels for episode 999"):
        read_labels(path, np.r_[episodes.episode_index[:1], 999], episodes.lengths[:2], width)
    with pytest.raises(ValueError, match="another recording"):
        read_labels(path, episodes.episode_index[:1], episodes.lengths[:1] + 1, width)
    # Cut to a narrower width, and with an episode the file lacks left unlabelled where that is asked for.
    cut = read_labels(path, np.r_[episodes.episode_index[:1], 999], np.r_[episodes.lengths[:1], 5], 4,
                      unlabelled_ok=True)
    assert np.array_equal(cut, [labels[0, :4], [-1] * 4])


def test_cli_labels_a_dial_recording_that_supervised_training_then_reads(dial_dataset, craft_dataset, tmp_path):
    labels, report = tmp_path / "labels.npz", tmp_path / "report.json"
    assert main(["--root", str(dial_dataset), "--out", str(labels), "--report", str(report), "--starts", "1",
                 "--n-options", "3"]) == 0
    result = json.loads(report.read_text())
    train = load_episodes(dial_dataset, split_episodes(dial_dataset, "train"))
    assert sum(result["label_share"]) == int(train.mask.sum()) and len(result["label_share"]) == 3
    assert result["cost"] <= min(result["start_costs"]) and len(result["start_costs"]) == 1
    for split in ("train_scores", "val_scores"):
        assert all(0 <= result[split][key] <= 1 for key in ("f1_tol0", "f1_tol1", "align_acc", "nmi"))
    stored = read_labels(labels, train.episode_index, train.lengths, train.mask.shape[1])
    assert set(np.unique(stored[train.mask])) <= {0, 1, 2} and (stored[~train.mask] == -1).all()

    out = tmp_path / "curve.json"
    argv = ["train", "--root", str(dial_dataset), "--repo-id", DIAL_REPO_ID, "--out", str(out), "--steps", "2",
            "--batch-size", "2", "--eval-every", "2", "--window-size", "20", "--supervise-options",
            "--option-labels", str(labels), "--set", "hidden_size=16", "mlp_hidden_size=16"]
    assert fast_imitation(argv) == 0
    assert json.loads(out.read_text())["settings"]["option_labels"] == str(labels)
    with pytest.raises(SystemExit, match="n_options is 2"):
        fast_imitation([*argv, "n_options=2"])
    with pytest.raises(SystemExit, match="needs it"):
        fast_imitation([arg for arg in argv if arg != "--supervise-options"])
    other = tmp_path / "first_episode_only.npz"
    np.savez(other, episode_index=train.episode_index[:1], lengths=train.lengths[:1],
             labels=np.zeros(train.lengths[0], dtype=int))
    with pytest.raises(ValueError, match=f"no labels for episode {train.episode_index[1]}"):
        fast_imitation([*argv[:argv.index("--option-labels") + 1], str(other), *argv[argv.index("--set"):]])


def test_cli_refuses_discrete_actions(craft_dataset, tmp_path):
    with pytest.raises(SystemExit, match="continuous"):
        main(["--root", str(craft_dataset), "--out", str(tmp_path / "labels.npz")])
