"""`tools.gradient_spikes`: the loss it scores is the packed view's frame-weighted NLL, and it finds the
episode that a spike comes from."""

import dataclasses
import json

import numpy as np
import pytest

from conftest import untrained_checkpoint
from ocn_data.episodes_table import load_episodes, split_episodes
from policies.ocn import OCNConfig
from tools import gradient_spikes
from tools.episode_parsing import action_nll, load_policy, segment_episodes


def short_episodes(root, width):
    """The training episodes of the dataset at `root` that fit a window of `width` frames."""
    train = load_episodes(root, split_episodes(root, "train"))
    rows = np.flatnonzero(train.lengths <= width)
    assert len(rows) >= 4, "the fixture needs four training episodes that fit the policy's window"
    return train, rows[:4]


def test_the_episodes_shares_add_up_to_the_frame_weighted_nll(ocn_checkpoint, craft_dataset):
    """Summed over a batch, each episode's share is the mean NLL per frame over all the batch's frames,
    as the parse of those episodes measures it on its own path through the policy."""
    policy, preprocessor, _ = load_policy(ocn_checkpoint)
    policy.config.window_start = "any"
    train, rows = short_episodes(craft_dataset, policy.config.window_size)
    shares = gradient_spikes.episode_losses(policy, preprocessor, train, rows)
    chosen = load_episodes(craft_dataset, [int(train.episode_index[row]) for row in rows])
    expected = action_nll(segment_episodes(policy, preprocessor, chosen))
    assert shares.sum().item() == pytest.approx(expected, rel=1e-5)
    assert len(set(np.round(shares.detach().numpy(), 6))) > 1


def test_the_worst_batch_names_the_episode_that_pulls_hardest(dial_dataset, tmp_path):
    """One Dial episode whose actions are scaled a hundredfold carries the batch's gradient: the tool
    names it and its gradient norm exceeds every other episode's."""
    width = int(load_episodes(dial_dataset, split_episodes(dial_dataset, "all")).lengths.max())
    config = OCNConfig(device="cpu", obs_encoder="identity", action_type="continuous", hidden_size=16,
                       mlp_hidden_size=16, n_options=4, window_size=width)
    policy, preprocessor, _ = load_policy(untrained_checkpoint(config, dial_dataset, tmp_path / "pretrained_model"))
    policy.config.window_start = "any"
    policy.train()
    train, rows = short_episodes(dial_dataset, width)
    spiked = rows[2]
    action = train.action.copy()
    action[spiked] *= 100.0
    result = gradient_spikes.batch_gradients(policy, preprocessor, dataclasses.replace(train, action=action), rows)
    assert result["worst_episode"] == int(train.episode_index[spiked])
    norms = result["episode_grad_norm"]
    assert norms[2] == max(norms) and result["grad_norm"] <= sum(norms) + 1e-6
    assert next(iter(result["worst_episode_parameters"].values())) == max(result["worst_episode_parameters"].values())


def test_the_command_scores_batches_and_writes_them(ocn_checkpoint, craft_dataset, tmp_path, capsys):
    out = tmp_path / "spikes.json"
    assert gradient_spikes.main(["--policy", str(ocn_checkpoint), "--root", str(craft_dataset), "--batches", "3",
                                 "--batch-size", "4", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert len(result["batch_grad_norm"]) == len(result["batch_loss"]) == 3
    assert result["grad_norm"] == pytest.approx(max(result["batch_grad_norm"]), rel=1e-4)
    assert result["worst_batch"] == int(np.argmax(result["batch_grad_norm"]))
    assert len(result["episode_index"]) == 4 and "median gradient norm" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        gradient_spikes.main(["--policy", str(ocn_checkpoint), "--root", str(craft_dataset), "--batches", "0"])
