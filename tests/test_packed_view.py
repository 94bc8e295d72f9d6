"""The packed view (`ocn_data.packed_view`): one row per episode that a policy with
`window_start="packed"` unpacks into the sequences LeRobot's windows give, and a loss that weighs
episodes as sampling windows at every frame does."""

import json

import numpy as np
import pytest
import torch

from conftest import CRAFT_REPO_ID, DIAL_REPO_ID
from lerobot.utils.constants import OBS_STATE
from ocn_data.episodes_table import load_episodes, read_info, split_episodes
from ocn_data.packed_view import (
    PACKED_KEYS,
    PACKED_LENGTH,
    PACKED_OPTION,
    PACKED_STATE,
    compact_dtype,
    packed_view,
    packed_view_path,
)
from ocn_data.training_view import MARKER
from policies.ocn import OCNConfig, OCNPolicy, make_ocn_pre_post_processors
from policies.sequence import training_windows

WIDTH = 24
# Each world's dataset fixture, repo id and policy settings (Dial's states and actions are standardised).
WORLDS = {
    "craft": ("craft_dataset", CRAFT_REPO_ID, {}),
    "dial": ("dial_dataset", DIAL_REPO_ID, {"obs_encoder": "identity", "action_type": "continuous"}),
}


def loaded(root, episodes, config=None, repo_id=CRAFT_REPO_ID):
    """The dataset at `root` as lerobot-train loads it for `config` (None: plain rows)."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    delta = None if config is None else resolve_delta_timestamps(config, LeRobotDatasetMetadata(repo_id, root=root))
    return LeRobotDataset(repo_id, root=root, episodes=episodes, delta_timestamps=delta)


def built(config: OCNConfig, root, episodes=None, repo_id=CRAFT_REPO_ID) -> OCNPolicy:
    """The policy as lerobot-train builds it on the dataset at `root` (features and tasks from its metadata)."""
    from lerobot.policies.factory import make_policy

    torch.manual_seed(0)
    return make_policy(config, ds_meta=loaded(root, episodes, repo_id=repo_id).meta)


def processed_batch(dataset, policy) -> dict:
    """Every sample of `dataset` in one batch as lerobot-train collates it, through the policy's preprocessor
    (with the dataset's statistics, as lerobot-train builds it)."""
    from lerobot.utils.collate import lerobot_collate_fn

    loader = torch.utils.data.DataLoader(dataset, batch_size=len(dataset), shuffle=False, collate_fn=lerobot_collate_fn)
    batch = next(iter(loader))
    preprocessor, _ = make_ocn_pre_post_processors(policy.config, dataset.meta.stats)
    return preprocessor(batch)


def test_the_packed_view_keeps_episodes_tasks_and_splits_in_one_row_each(craft_dataset):
    view = packed_view(craft_dataset, CRAFT_REPO_ID, WIDTH)
    assert view == packed_view_path(craft_dataset, WIDTH)
    source, packed = read_info(craft_dataset), read_info(view)
    assert packed["splits"] == source["splits"]
    assert packed["total_episodes"] == packed["total_frames"] == source["total_episodes"]
    assert packed["features"][OBS_STATE] == source["features"][OBS_STATE]
    assert packed["features"][PACKED_STATE]["shape"] == [WIDTH * source["features"][OBS_STATE]["shape"][0]]
    assert packed["features"][PACKED_STATE]["dtype"] == "uint8"  # Craft's ids and counts are small
    assert json.loads((view / MARKER).read_text())["packed_width"] == WIDTH
    # Asked again, it is reused; another width is another view.
    written = (view / MARKER).stat().st_mtime_ns
    assert packed_view(craft_dataset, CRAFT_REPO_ID, WIDTH) == view and (view / MARKER).stat().st_mtime_ns == written
    assert packed_view_path(craft_dataset, WIDTH + 1) != view


@pytest.mark.parametrize("world", WORLDS)
def test_packed_rows_unpack_to_the_episode_windows_and_give_the_same_loss(world, request):
    """Through LeRobot's loader and preprocessor: the train split's packed rows give the sequences that
    every frame's episode window gives, and the packed loss over all episodes equals the windowed loss
    over all frames' windows (the per-frame mean NLL, each frame counted once). On Dial the preprocessor
    standardises the packed columns exactly as it standardises the windows' states and actions."""
    fixture, repo_id, world_settings = WORLDS[world]
    root = request.getfixturevalue(fixture)
    train = list(split_episodes(root, "train"))
    width = int(load_episodes(root, split_episodes(root, "all")).lengths.max())
    view = packed_view(root, repo_id, width)
    settings = dict(device="cpu", window_size=width, hidden_size=16, mlp_hidden_size=16, temperature=1.0,
                    **world_settings)
    windowed = built(OCNConfig(**settings), root, train, repo_id)
    packed = built(OCNConfig(**settings, window_start="packed"), view, train, repo_id)
    packed.load_state_dict(windowed.state_dict())
    assert set(packed.config.input_features) == {OBS_STATE}  # the packed columns are layout, not inputs

    windows = processed_batch(loaded(root, train, windowed.config, repo_id), windowed)
    rows = processed_batch(loaded(view, train, packed.config, repo_id), packed)
    assert set(PACKED_KEYS) - set(rows) == {PACKED_OPTION}  # no labels: an unlabelled view
    mask_w, state_w, action_w = training_windows(windowed.config, windows)
    mask_p, state_p, action_p = training_windows(packed.config, rows)
    episode = windows["episode_index"]
    first_frames = torch.cat([torch.ones(1, dtype=torch.bool), episode[1:] != episode[:-1]])
    assert int(first_frames.sum()) == len(train) == mask_p.shape[0]
    for got, expected in ((mask_p, mask_w), (state_p, state_w), (action_p, action_w)):
        expected = expected[first_frames][:, : got.shape[1]]
        assert got.shape == expected.shape and got.dtype == expected.dtype
        assert torch.equal(got * mask_p.view(*mask_p.shape, *[1] * (got.dim() - 2)),
                           expected * mask_p.view(*mask_p.shape, *[1] * (got.dim() - 2)))
    windowed.eval(), packed.eval()
    loss_windows, _ = windowed(windows)
    loss_rows, stats = packed(rows)
    torch.testing.assert_close(loss_rows, loss_windows)
    assert stats["frames_used"] == len(episode)


def test_compact_dtype_is_the_smallest_exact_one():
    assert compact_dtype(np.array([0, 255])) == np.uint8
    assert compact_dtype(np.array([-1, 3])) == np.int16
    assert compact_dtype(np.array([0, 70000])) == np.int32
    assert compact_dtype(np.array([0.5], dtype=np.float64)) == np.float32


def test_packed_training_names_its_misuses(craft_dataset):
    view = packed_view(craft_dataset, CRAFT_REPO_ID, WIDTH)
    with pytest.raises(ValueError, match="holds 24 frames per episode but window_size is 30"):
        built(OCNConfig(device="cpu", window_size=30, window_start="packed"), view)
    with pytest.raises(ValueError, match="no `observation.packed.state` column"):
        built(OCNConfig(device="cpu", window_size=WIDTH, window_start="packed"), craft_dataset)
    with pytest.raises(ValueError, match="built on a packed view"):
        built(OCNConfig(device="cpu", window_size=WIDTH), view)
    with pytest.raises(ValueError, match="Pass --width"):
        packed_view(craft_dataset, CRAFT_REPO_ID, 3)
    assert not packed_view_path(craft_dataset, 3).joinpath(MARKER).exists()


def test_long_episodes_keep_their_first_frames_in_a_cut_view(dial_dataset):
    """`cut_long`: episodes longer than the width keep the first `width` frames (what skip_long_episodes
    trains on windows), the others whole, in a folder of its own; without it they are an error."""
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    width = int(np.median(episodes.lengths))
    assert (episodes.lengths > width).any() and (episodes.lengths <= width).any()
    with pytest.raises(ValueError, match="--cut-long-episodes"):
        packed_view(dial_dataset, DIAL_REPO_ID, width)
    view = packed_view(dial_dataset, DIAL_REPO_ID, width, cut_long=True)
    assert view == packed_view_path(dial_dataset, width, cut_long=True) != packed_view_path(dial_dataset, width)
    assert json.loads((view / MARKER).read_text())["cut_long_episodes"] is True
    rows = loaded(view, None, repo_id=DIAL_REPO_ID)
    state_dim = episodes.state.shape[-1]
    for e, length in enumerate(episodes.lengths.tolist()):
        row = rows[e]
        kept = min(length, width)
        assert int(row[PACKED_LENGTH]) == kept
        packed_state = row[PACKED_STATE].numpy().reshape(width, state_dim)
        np.testing.assert_array_equal(packed_state[:kept], episodes.state[e, :kept])
        assert not packed_state[kept:].any()
