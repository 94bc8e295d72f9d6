"""record_demos end to end: real subprocesses, datasets read back by LeRobot, MCAP by its reader."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from huggingface_hub import DatasetCard
from lerobot.datasets.compute_stats import aggregate_stats, compute_episode_stats
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.collate import lerobot_collate_fn

from lerobot_policy_ocn.envs.craft.world import parse_task, task_description
from lerobot_policy_ocn.ocn_data.mcap_log import read_mcap_messages
from unwritable import read_only_folder

RECORD = [sys.executable, "-m", "lerobot_policy_ocn.ocn_data.record_demos"]


def run_record(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([*RECORD, *args], capture_output=True, text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"record_demos failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("rec")
    root, mcap = base / "ds", base / "demo.mcap"
    run_record("--tasks", "AC,CD,DA", "--episodes-per-task", "20", "--root", str(root),
               "--repo-id", "local/test_s1", "--seed", "3", "--mcap", str(mcap), "--chunk-episodes", "25")
    return root, mcap


def test_dataset_reads_back_in_lerobot(recorded):
    root, _ = recorded
    ds = LeRobotDataset("local/test_s1", root=root)
    assert ds.num_episodes == 60
    assert ds.meta.info.splits == {"train": "0:48", "val": "48:60"}
    assert set(ds.meta.tasks.index) == {task_description(parse_task(t)) for t in ("AC", "CD", "DA")}
    assert len(list((root / "data").glob("*/*.parquet"))) == 3  # chunks of 25, 25 and 10 episodes
    for key in ("observation.state", "action", "next.reward", "next.done", "subtask.index", "subtask.id",
                "subtask.end"):
        assert key in ds.meta.features
    assert not any(k.startswith("observation.") for k in ds.meta.features if k.startswith("subtask"))

    table = ds.hf_dataset.with_format("numpy")
    episode = np.asarray(table["episode_index"])
    reward = np.asarray(table["next.reward"])
    done = np.asarray(table["next.done"])
    sub_end = np.asarray(table["subtask.end"])
    sub_index = np.asarray(table["subtask.index"])
    for e in range(ds.num_episodes):
        rows = episode == e
        task = ds.meta.episodes[e]["tasks"][0]
        n_subtasks = len(parse_task(task))
        assert reward[rows].sum() == n_subtasks  # dense reward: one per subtask
        assert sub_end[rows].sum() == n_subtasks
        assert done[rows][-1] and not done[rows][:-1].any()
        np.testing.assert_array_equal(np.flatnonzero(np.diff(sub_index[rows])), np.flatnonzero(sub_end[rows])[:-1])


def test_stats_are_lerobots_own(recorded):
    """Episode and dataset statistics equal what LeRobot's save_episode computes (its histogram
    quantiles per episode) and what aggregate_stats makes of them (count-weighted quantiles)."""
    root, _ = recorded
    ds = LeRobotDataset("local/test_s1", root=root)
    table = ds.hf_dataset.with_format("numpy")
    episode_index = np.asarray(table["episode_index"])
    keys = ("observation.state", "action", "subtask.index")
    features = {k: ds.meta.features[k] for k in keys}
    theirs = [compute_episode_stats({k: np.asarray(table[k])[episode_index == e] for k in keys}, features)
              for e in range(ds.num_episodes)]
    episodes = pd.concat([pd.read_parquet(p) for p in sorted((root / "meta/episodes").glob("*/*.parquet"))])
    for e in (0, 1, ds.num_episodes - 1):
        for key in keys:
            for stat, value in theirs[e][key].items():
                ours = np.asarray(episodes.iloc[e][f"stats/{key}/{stat}"])
                np.testing.assert_allclose(ours, value, rtol=1e-5, atol=1e-6, err_msg=f"episode {e} {key} {stat}")
    pooled = aggregate_stats(theirs)
    for key in keys:
        for stat, value in pooled[key].items():
            np.testing.assert_allclose(ds.meta.stats[key][stat], value, rtol=1e-5, atol=1e-6, err_msg=f"{key} {stat}")


def test_windowed_access_pads_past_episode_end(recorded):
    root, _ = recorded
    window = [i / 10 for i in range(40)]
    ds = LeRobotDataset("local/test_s1", root=root, delta_timestamps={"observation.state": window, "action": window})
    item = ds[0]
    length = ds.meta.episodes[0]["length"]
    assert item["observation.state"].shape == (40, 81)
    assert item["action_is_pad"].sum().item() == 40 - length


def test_mcap_reads_back(recorded):
    root, mcap = recorded
    ds = LeRobotDataset("local/test_s1", root=root)
    topics = read_mcap_messages(mcap)
    assert set(topics) == {"/observation", "/action", "/reward", "/subtask"}
    for messages in topics.values():
        assert len(messages) == ds.num_frames
    first = ds[0]
    assert topics["/observation"][0]["state"] == first["observation.state"].tolist()
    assert topics["/action"][0]["action"] == [int(first["action"])]
    assert topics["/subtask"][0]["subtask"] == ds.meta.episodes[0]["tasks"][0].split(", ")[0]
    from mcap.reader import make_reader

    with open(mcap, "rb") as f:
        summary = make_reader(f).get_summary()
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}


def test_dataset_card(recorded):
    root, _ = recorded
    card = DatasetCard.load(root / "README.md")
    assert {"LeRobot", "robotics"} <= set(card.data.tags)
    assert card.data.license == "apache-2.0"
    assert "robotics" in card.data.task_categories
    text = card.text
    assert "record_demos --tasks AC,CD,DA --episodes-per-task 20" in text
    assert "| get wood, get iron | `AC` | 20 |" in text


def test_resume_appends_and_fresh_root_is_required(recorded, tmp_path):
    root, _ = recorded
    again = run_record("--tasks", "AC", "--episodes-per-task", "2", "--root", str(root), "--repo-id", "local/test_s1",
                       check=False)
    assert again.returncode == 2 and "already exists" in again.stderr and "--resume" in again.stderr

    copy = tmp_path / "copy"
    subprocess.run(["cp", "-r", str(root), str(copy)], check=True)
    noisy = run_record("--tasks", "AC", "--episodes-per-task", "5", "--root", str(copy), "--repo-id", "local/test_s1",
                       "--dart-noise", "0.3", "--resume", check=False)
    assert noisy.returncode == 2 and "recorded with dart_noise 0.1, not 0.3" in noisy.stderr
    assert LeRobotDataset("local/test_s1", root=copy).num_episodes == 60
    run_record("--tasks", "AC", "--episodes-per-task", "5", "--root", str(copy), "--repo-id", "local/test_s1",
               "--seed", "3", "--resume")
    ds = LeRobotDataset("local/test_s1", root=copy)
    assert ds.num_episodes == 65
    assert ds.meta.info.splits == {"train": "0:52", "val": "52:65"}
    # resumed attempts continue the seed stream: no map of the first session is recorded twice
    states = ds.hf_dataset.with_format("numpy")
    first_frames = np.asarray(states["observation.state"])[np.asarray(states["frame_index"]) == 0]
    assert len(np.unique(first_frames, axis=0)) == 65
    assert "| get wood, get iron | `AC` | 25 |" in (copy / "README.md").read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tasks", "AX"], "valid"),
        (["--tasks", "make bed"], "valid"),
        (["--tasks", "AC,AC"], "twice"),
        (["--tasks", "AC", "--resume"], "no LeRobot dataset"),
        (["--tasks", "AC", "--repo-id", "no slash here"], "must be ORG/NAME with exactly one slash"),
        (["--tasks", "AC", "--repo-id", "a/b/c"], "must be ORG/NAME with exactly one slash"),
        (["--tasks", "AC", "--chunk-episodes", "0"], "--chunk-episodes must be >= 1"),
    ],
)
def test_bad_input_is_a_clear_error(tmp_path, args, message):
    proc = run_record("--episodes-per-task", "2", "--root", str(tmp_path / "new"), "--repo-id", "local/x", *args,
                      check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert message in proc.stderr
    assert not (tmp_path / "new").exists() or "--resume" in args


def test_unwritable_outputs_are_refused_before_anything_is_written(tmp_path, capsys):
    from lerobot_policy_ocn.ocn_data.record_demos import main

    root, blocked, a_file = tmp_path / "new", tmp_path / "blocked", tmp_path / "a_file"
    a_file.write_text("not a folder")
    cases = {
        "--mcap": (["--root", str(root), "--mcap", str(blocked / "demo.mcap")], f"cannot write in {blocked}"),
        "--root": (["--root", str(blocked / "ds")], f"cannot write in {blocked}"),
        "--root ": (["--root", str(a_file / "ds")], f"{a_file} is a file, not a folder"),
    }
    with read_only_folder(blocked):
        for flag, (args, message) in cases.items():
            with pytest.raises(SystemExit) as exit_info:
                main(["--tasks", "AC", "--episodes-per-task", "2", "--repo-id", "local/x", *args])
            err = capsys.readouterr().err.strip()
            assert exit_info.value.code == 2 and len(err.splitlines()) == 1, err
            assert flag.strip() in err and message in err
            assert not root.exists() and list(blocked.iterdir()) == []


def test_unknown_letter_lists_valid_subtasks(tmp_path):
    proc = run_record("--tasks", "AZ", "--episodes-per-task", "1", "--root", str(tmp_path / "r"), "--repo-id", "l/x",
                      check=False)
    for letter, name in (("A", "get wood"), ("D", "get grass")):
        assert letter in proc.stderr and name in proc.stderr


def test_interrupted_recording_keeps_finished_episodes(tmp_path):
    root = tmp_path / "ds"
    proc = subprocess.Popen(
        [*RECORD, "--tasks", "AC,CD,DA", "--episodes-per-task", "200000", "--root", str(root),
         "--repo-id", "local/interrupted", "--chunk-episodes", "500", "--batch-size", "64"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    first_file = root / "data" / "chunk-000" / "file-001.parquet"
    deadline = time.time() + 120
    while not first_file.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert first_file.exists(), "recording produced no data file in time"
    os.kill(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "interrupted" in out
    ds = LeRobotDataset("local/interrupted", root=root)
    assert 1000 <= ds.num_episodes < 600000
    assert ds.num_frames == len(ds.hf_dataset)
    assert ds.meta.info.total_episodes == ds.num_episodes == len(ds.meta.episodes)


def test_dart_noise_executes_random_actions_but_records_the_experts():
    from lerobot_policy_ocn.envs.craft import CraftExpert
    from lerobot_policy_ocn.ocn_data.craft_recorder import CraftRecorder

    def recorder(noise: float) -> CraftRecorder:
        return CraftRecorder([(0, 2), (2, 3)], 200, seed=5, batch_size=400, dart_noise=noise)

    noisy, again, quiet = recorder(0.3), recorder(0.3), recorder(0.0)
    for _ in range(3):
        expert = CraftExpert(noisy.batch).act()  # what the expert does in the state about to be recorded
        recorded, executed = noisy._act()
        assert (recorded == expert).all()
        flipped = (executed != recorded).mean()
        assert 0.15 < flipped < 0.35  # 0.3 x 4/5: a drawn action may be the expert's own
        _, executed_again = again._act()
        assert (executed_again == executed).all()  # the noise comes from the episodes' seeds
        for rec in (noisy, again):
            rec.batch.step(executed)
    recorded, executed = quiet._act()
    assert (recorded == executed).all()
    with pytest.raises(ValueError, match=r"dart_noise must be in \[0, 1\), got 1.0"):
        recorder(1.0)


def test_dart_noise_is_kept_in_the_provenance_and_the_card(tmp_path):
    root = tmp_path / "ds"
    run_record("--tasks", "AC", "--episodes-per-task", "5", "--root", str(root), "--repo-id", "local/x",
               "--dart-noise", "0.2")
    dataset = LeRobotDataset("local/x", root=root)
    assert dataset.meta.total_episodes == 5
    card = (root / "README.md").read_text()
    assert "DART noise 0.2" in card and "--dart-noise 0.2" in card
    plain = tmp_path / "plain"  # record_demos' default noise, what OCN's Craft recipe was measured on
    run_record("--tasks", "AC", "--episodes-per-task", "5", "--root", str(plain), "--repo-id", "local/x")
    assert "DART noise 0.1" in (plain / "README.md").read_text()
    expert = tmp_path / "expert"
    run_record("--tasks", "AC", "--episodes-per-task", "5", "--root", str(expert), "--repo-id", "local/x",
               "--dart-noise", "0")
    assert "DART" not in (expert / "README.md").read_text()


def test_subtask_annotations_as_native_language_rows(tmp_path):
    root = tmp_path / "ds"
    run_record("--tasks", "ADC", "--episodes-per-task", "4", "--root", str(root), "--repo-id", "local/lang",
               "--subtask-annotations")
    ds = LeRobotDataset("local/lang", root=root)
    assert ds.meta.has_language_columns
    table = ds.hf_dataset.with_format("numpy")
    frame_index = np.asarray(table["frame_index"])
    sub_index = np.asarray(table["subtask.index"])
    item = ds[0]
    rows = item["language_persistent"]
    assert [r["content"] for r in rows] == ["get wood", "get grass", "get iron"]
    assert all(r["style"] == "subtask" and r["role"] == "assistant" and r["camera"] is None for r in rows)
    episode0 = sub_index[: ds.meta.episodes[0]["length"]]
    starts = [int(frame_index[i]) for i in np.flatnonzero(np.diff(episode0, prepend=-1))]
    assert [round(r["timestamp"] * 10) for r in rows] == starts
    assert item["language_events"] == []
    batch = lerobot_collate_fn([ds[i] for i in range(4)])  # what lerobot-train batches with
    assert isinstance(batch["observation.state"], torch.Tensor) and batch["observation.state"].shape == (4, 81)


def test_video_feature_decodes(tmp_path):
    root = tmp_path / "ds"
    run_record("--tasks", "AC", "--episodes-per-task", "2", "--root", str(root), "--repo-id", "local/vid", "--video")
    ds = LeRobotDataset("local/vid", root=root)
    assert ds.meta.video_keys == ["observation.image"]
    frame = ds[ds.meta.episodes[1]["dataset_from_index"]]["observation.image"]
    assert frame.shape == (3, 160, 160)
    assert 0.0 <= frame.min() and frame.max() <= 1.0 and frame.std() > 0.05


@pytest.fixture(scope="module")
def dial_recorded(tmp_path_factory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("dial")
    root, mcap = base / "ds", base / "dial.mcap"
    run_record("--env", "dial", "--pin-length", "2", "--digits", "1,2,4,8", "--episodes", "12", "--root", str(root),
               "--repo-id", "local/dial", "--seed", "4", "--mcap", str(mcap), "--chunk-episodes", "5")
    return root, mcap


def test_dial_dataset_reads_back_in_lerobot(dial_recorded):
    root, _ = dial_recorded
    ds = LeRobotDataset("local/dial", root=root)
    assert ds.num_episodes == 12 and ds.meta.info.splits == {"train": "0:10", "val": "10:12"}
    assert ds.meta.robot_type == "dial" and ds.fps == 25
    features = ds.meta.features
    assert (features["observation.state"]["dtype"], tuple(features["observation.state"]["shape"])) == ("float32", (39,))
    assert (features["action"]["dtype"], tuple(features["action"]["shape"])) == ("float32", (9,))
    assert {"next.reward", "next.done", "subtask.index", "subtask.id", "subtask.end"} <= set(features)
    item = ds[0]
    assert item["observation.state"].shape == (39,) and item["action"].shape == (9,)

    table = ds.hf_dataset.with_format("numpy")
    episode = np.asarray(table["episode_index"])
    action = np.asarray(table["action"])
    assert np.abs(action).max() <= 1.0
    for e in range(ds.num_episodes):
        rows = episode == e
        pin = [int(part.split()[1]) for part in ds.meta.episodes[e]["tasks"][0].split(", ")]
        assert len(pin) == 2 and set(pin) <= {1, 2, 4, 8} and pin[0] != pin[1]
        assert np.asarray(table["next.reward"])[rows].sum() == 2
        ids = np.asarray(table["subtask.id"])[rows]
        assert ids[0] == pin[0] and ids[-1] == pin[1]
        ends = np.flatnonzero(np.asarray(table["subtask.end"])[rows])
        assert len(ends) == 2 and ends[-1] == rows.sum() - 1
        # the last frame's fingertip is about to press the last digit's key
        state = np.asarray(table["observation.state"])[rows]
        assert np.abs(state[-1, 9 + 3 * pin[1] : 12 + 3 * pin[1]]).sum() < 0.1


def test_dial_mcap_and_card(dial_recorded):
    root, mcap = dial_recorded
    ds = LeRobotDataset("local/dial", root=root)
    topics = read_mcap_messages(mcap)
    assert {k: len(v) for k, v in topics.items()} == dict.fromkeys(
        ("/observation", "/action", "/reward", "/subtask"), ds.num_frames)
    np.testing.assert_allclose(topics["/observation"][0]["state"], ds[0]["observation.state"].numpy(), rtol=1e-6)
    np.testing.assert_allclose(topics["/action"][0]["action"], ds[0]["action"].numpy(), rtol=1e-6)
    assert topics["/subtask"][0]["subtask"] == ds.meta.episodes[0]["tasks"][0].split(", ")[0]
    card = DatasetCard.load(root / "README.md")
    assert "dial" in card.data.tags
    assert "record_demos --env dial --pin-length 2 --digits 1,2,4,8 --episodes 12" in card.text
    assert "random, 2 digits from 1, 2, 4, 8" in card.text and "| press " in card.text


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--episodes", "0"], "--episodes must be given and >= 1"),
        (["--episodes", "3", "--digits", "1"], "at least two distinct"),
        (["--episodes", "3", "--video"], "Craft options"),
        (["--episodes", "3", "--dart-noise", "0.1"], "Craft options"),
        (["--tasks", "12,1x", "--episodes-per-task", "2"], "PIN of digits"),
        (["--tasks", "12", "--episodes", "2"], "either --tasks"),
    ],
)
def test_dial_bad_input_is_a_one_line_error(tmp_path, capsys, args, message):
    from lerobot_policy_ocn.ocn_data.record_demos import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--env", "dial", "--root", str(tmp_path / "new"), "--repo-id", "local/x", *args])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "new").exists()
