"""The training view (`ocn_data.training_view`): LeRobot's loader gives the same training windows from
it as from the recorded dataset, without the evaluation-only columns, and a stale view is remade."""

import json

import torch

from conftest import CRAFT_REPO_ID
from ocn_data.episodes_table import read_info, split_episodes
from ocn_data.training_view import MARKER, training_view, training_view_path

COMPARED = ("observation.state", "action", "observation.state_is_pad", "action_is_pad", "episode_index",
            "frame_index", "index", "task")


def test_the_view_gives_lerobot_train_the_same_windows_without_the_label_columns(craft_dataset):
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    from policies.ocn import OCNConfig

    view = training_view(craft_dataset, CRAFT_REPO_ID)
    assert view == training_view_path(craft_dataset) and view != craft_dataset
    source_info, view_info = read_info(craft_dataset), read_info(view)
    assert {"subtask.index", "subtask.id", "next.reward"} <= set(source_info["features"])
    assert set(view_info["features"]) == {"observation.state", "action", "timestamp", "frame_index", "episode_index",
                                          "index", "task_index"}
    for key in ("splits", "total_episodes", "total_frames", "robot_type", "fps"):
        assert view_info[key] == source_info[key], key
    # The train split as lerobot-train loads it (episode-filtered), every frame's window compared.
    train = list(split_episodes(craft_dataset, "train"))
    delta = resolve_delta_timestamps(OCNConfig(device="cpu", window_size=30),
                                     LeRobotDatasetMetadata(CRAFT_REPO_ID, root=craft_dataset))
    source, lean = (LeRobotDataset(CRAFT_REPO_ID, root=root, episodes=train, delta_timestamps=delta)
                    for root in (craft_dataset, view))
    assert len(source) == len(lean) > 0
    for k in range(len(source)):
        a, b = source[k], lean[k]
        for key in COMPARED:
            assert (a[key] == b[key]) if key == "task" else torch.equal(a[key], b[key]), (k, key)


def test_a_current_view_is_reused_and_a_stale_one_remade(craft_dataset, tmp_path):
    import shutil

    source = tmp_path / "ds"
    shutil.copytree(craft_dataset, source)
    view = training_view(source, CRAFT_REPO_ID)
    marker = view / MARKER
    written = marker.stat().st_mtime_ns
    assert training_view(source, CRAFT_REPO_ID) == view and marker.stat().st_mtime_ns == written
    # A view has nothing left to drop: it is its own training view.
    assert training_view(view, CRAFT_REPO_ID) == view
    # Another recording in the same folder (here: its metadata changed) makes the view stale.
    info_path = source / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["fps"] = info["fps"] * 2
    info_path.write_text(json.dumps(info, indent=4))
    training_view(source, CRAFT_REPO_ID)
    assert read_info(view)["fps"] == info["fps"]
    # An interrupted write (no marker) is remade too.
    marker.unlink()
    training_view(source, CRAFT_REPO_ID)
    assert marker.is_file()


def test_views_asked_for_at_once_are_written_once(craft_dataset, tmp_path):
    import multiprocessing
    import shutil
    from concurrent.futures import ProcessPoolExecutor

    source = tmp_path / "ds"
    shutil.copytree(craft_dataset, source)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        views = list(pool.map(training_view, [source, source], [CRAFT_REPO_ID, CRAFT_REPO_ID]))
    assert views == [training_view_path(source)] * 2
    marker = json.loads((views[0] / MARKER).read_text())
    assert marker["source"] == str(source) and "subtask.id" in marker["dropped"]
    assert read_info(views[0])["total_frames"] == read_info(source)["total_frames"]
