"""Fault injection into record_demos: real subprocesses killed with SIGKILL at each commit stage and
at random instants, stopped with SIGTERM, and cut off by a file size limit (a full disk); damaged
copies repaired by ocn-doctor. After each fault the dataset loads with LeRobot, its data and its
metadata agree, and `--resume` records no episode twice.

Each subprocess pays record_demos' imports (torch, LeRobot: several seconds on a busy machine), so
recordings are tiny: chunks of 2 episodes from batches of 4 envs, a commit every couple of episodes.
"""

from __future__ import annotations

import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_policy_ocn.ocn_data import durable
from lerobot_policy_ocn.ocn_data.doctor import diagnose
from lerobot_policy_ocn.ocn_data.doctor import main as doctor
from lerobot_policy_ocn.ocn_data.lerobot_writer import FAULT_ENV
from lerobot_policy_ocn.ocn_data.mcap_log import log_is_finished, read_mcap_messages
from lerobot_policy_ocn.ocn_data.provenance import load_provenance
from lerobot_policy_ocn.ocn_data.record_demos import main as record_demos

REPO_ID = "local/faults"
RECORD = [sys.executable, "-m", "lerobot_policy_ocn.ocn_data.record_demos"]


def recording(root: Path, per_task: int, *extra: str) -> list[str]:
    """record_demos arguments for a tiny Craft recording that publishes a chunk every 2 episodes."""
    return ["--tasks", "AC,CD,DA", "--episodes-per-task", str(per_task), "--root", str(root), "--repo-id", REPO_ID,
            "--seed", "7", "--chunk-episodes", "2", "--batch-size", "4", *extra]


def run(args: list[str], fault: str | None = None, **popen: object) -> subprocess.CompletedProcess:
    env = {**os.environ, FAULT_ENV: fault} if fault else {k: v for k, v in os.environ.items() if k != FAULT_ENV}
    return subprocess.run([*RECORD, *args], capture_output=True, text=True, timeout=300, env=env, **popen)


def published_episodes(root: Path) -> int:
    """The episodes of the published dataset (0 before the first chunk), read as a reader would."""
    try:
        return json.loads((root / "meta" / "info.json").read_text())["total_episodes"]
    except FileNotFoundError:
        return 0


def start_and_kill(args: list[str], rng: random.Random, signum: int = signal.SIGKILL) -> subprocess.Popen:
    """Start record_demos, wait for it to publish a chunk beyond what `--root` holds now, then wait a
    random moment (commits follow each other closely, so the signal often lands inside one) and
    send `signum`."""
    root = Path(args[args.index("--root") + 1])
    before = published_episodes(root)
    proc = subprocess.Popen([*RECORD, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while published_episodes(root) <= before and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, f"record_demos ended before the signal: {proc.communicate()[1][-2000:]}"
    time.sleep(rng.uniform(0.0, 0.6))
    proc.send_signal(signum)
    proc.communicate(timeout=120)
    return proc


def episode_sequences(dataset: LeRobotDataset) -> list[bytes]:
    """Each episode's states and actions, as bytes: equal bytes mean a recorded twice episode."""
    table = dataset.hf_dataset.with_format("numpy")
    episode = np.asarray(table["episode_index"])
    state, action = np.asarray(table["observation.state"]), np.asarray(table["action"])
    return [state[episode == e].tobytes() + action[episode == e].tobytes() for e in range(dataset.num_episodes)]


def check_consistent(root: Path, episodes: int | None = None) -> LeRobotDataset:
    """The dataset loads with LeRobot; its data, episode tables, totals, splits and provenance agree
    (whatever an interrupted commit left beside the folder aside); no episode is there twice."""
    dataset = LeRobotDataset(REPO_ID, root=root)
    meta = dataset.meta
    assert len(dataset.hf_dataset) == meta.total_frames == dataset.num_frames
    assert len(meta.episodes) == meta.total_episodes
    assert sorted(set(dataset.hf_dataset.with_format("numpy")["episode_index"])) == list(range(meta.total_episodes))
    assert sum(meta.episodes["length"]) == meta.total_frames
    stop = int(meta.info.splits.get("val", meta.info.splits["train"]).split(":")[1])
    assert stop == meta.total_episodes
    diagnosis = diagnose(root)
    assert len(diagnosis.findings) == len(diagnosis.leftovers), diagnosis.findings
    provenance = load_provenance(root)
    dropped = sum(repair["dropped_episodes"] for repair in provenance.get("repairs", []))
    assert sum(s["episodes"] for s in provenance["sessions"]) - dropped == meta.total_episodes
    sequences = episode_sequences(dataset)
    assert len(set(sequences)) == len(sequences), "an episode was recorded twice"
    if episodes is not None:
        assert meta.total_episodes == episodes
    return dataset


def data_files(root: Path) -> list[str]:
    return sorted(path.name for path in (root / "data").glob("*/*.parquet"))


def test_sigkill_at_each_commit_stage_loses_nothing_published_and_resume_repeats_nothing(tmp_path, capsys):
    root = tmp_path / "ds"
    staging = durable.staging_path(root)
    # The 3rd commit dies with its data file staged and its metadata not: the first two chunks stay.
    assert run(recording(root, 5), fault="data:3").returncode == -signal.SIGKILL
    first = check_consistent(root).num_episodes
    assert data_files(root) == ["file-000.parquet", "file-001.parquet"] and staging.exists()
    session = load_provenance(root)["sessions"][-1]
    assert session["status"] == "recording" and session["interrupted"] and session["episodes"] == first

    # The settings guard holds after a SIGKILL: noisy episodes are not mixed into clean ones.
    with pytest.raises(SystemExit) as refused:
        record_demos(recording(root, 5, "--resume", "--dart-noise", "0.3"))
    assert refused.value.code == 2
    assert "recorded with dart_noise 0.1, not 0.3" in capsys.readouterr().err
    check_consistent(root, episodes=first)

    # Killed with everything staged, before the swap: the dataset is as it was.
    assert run(recording(root, 5, "--resume"), fault="staged:1").returncode == -signal.SIGKILL
    check_consistent(root, episodes=first)
    # Killed after its second swap, before removing the replaced version: both chunks are in.
    resumed = run(recording(root, 5, "--resume"), fault="swapped:2")
    assert resumed.returncode == -signal.SIGKILL
    assert f"removed {staging}" in resumed.stderr  # what the 'staged' kill left, named
    second = check_consistent(root).num_episodes
    assert len(data_files(root)) == 4 and staging.exists()

    finished = run(recording(root, 5, "--resume"))
    assert finished.returncode == 0, finished.stderr[-2000:]
    assert "the last session was cut off" in finished.stderr
    dataset = check_consistent(root, episodes=second + 15)
    assert not staging.exists()
    sessions = load_provenance(root)["sessions"]
    assert [s["status"] for s in sessions] == ["recording", "recording", "finished"]
    assert [s["episodes"] for s in sessions] == [first, second - first, 15]
    val = round((second + 15) * 0.2)
    assert dataset.meta.info.splits == {"train": f"0:{second + 15 - val}", "val": f"{second + 15 - val}:{second + 15}"}
    assert sessions[-1]["command"] in (root / "README.md").read_text()


def test_sigkill_at_random_instants_keeps_every_published_chunk_and_the_mcap_log(tmp_path):
    rng = random.Random(75)
    root, log = tmp_path / "ds", tmp_path / "first.mcap"
    first = start_and_kill(recording(root, 40, "--mcap", str(log)), rng)
    assert first.returncode == -signal.SIGKILL
    dataset = check_consistent(root)
    killed_at = dataset.num_episodes

    # The log holds every published episode (it is flushed before each commit), as complete records.
    assert not log_is_finished(log)
    messages = read_mcap_messages(log)
    logged = {m["episode_index"] for m in messages["/observation"]}
    assert set(range(killed_at)) <= logged
    rows = [m for m in messages["/observation"] if m["episode_index"] < killed_at]
    np.testing.assert_array_equal([m["state"] for m in rows],
                                  np.asarray(dataset.hf_dataset.with_format("numpy")["observation.state"]))
    assert doctor([str(log)]) == 1
    assert doctor([str(log), "--repair"]) == 0 and log_is_finished(log)
    assert len(read_mcap_messages(log)["/observation"]) == len(messages["/observation"])

    # A resumed session killed at random after its first chunk: published, and nothing recorded twice.
    second = start_and_kill(recording(root, 40, "--resume"), rng)
    assert second.returncode == -signal.SIGKILL
    assert check_consistent(root).num_episodes > killed_at


def test_sigterm_is_a_clean_stop_with_card_provenance_splits_and_a_finished_log(tmp_path):
    root, log = tmp_path / "ds", tmp_path / "demo.mcap"
    proc = start_and_kill(recording(root, 40, "--mcap", str(log)), random.Random(143), signal.SIGTERM)
    assert proc.returncode == 143
    dataset = check_consistent(root)
    session = load_provenance(root)["sessions"][-1]
    assert session["status"] == "interrupted by SIGTERM" and session["interrupted"]
    assert session["episodes"] == dataset.num_episodes
    assert set(dataset.meta.info.splits) == {"train", "val"}
    assert "--episodes-per-task 40" in (root / "README.md").read_text()
    assert log_is_finished(log)
    logged = {m["episode_index"] for m in read_mcap_messages(log)["/observation"]}
    assert logged == set(range(dataset.num_episodes))


def test_a_full_disk_loses_nothing_published(tmp_path):
    root, log = tmp_path / "ds", tmp_path / "demo.mcap"

    def small_files() -> None:
        """Every file of the child stops at 80 KiB (an episode table of 8 episodes takes 62 KB, the
        log 1 KB per episode): the MCAP log, which grows with every chunk, runs into the limit
        first, as into a full disk."""
        resource.setrlimit(resource.RLIMIT_FSIZE, (80 * 1024, 80 * 1024))

    full = run(recording(root, 40, "--mcap", str(log), "--chunk-episodes", "8"), preexec_fn=small_files)
    assert full.returncode == 1
    error = full.stderr.strip().splitlines()[-1]
    assert error.startswith("record_demos: error: File too large writing") and "--resume" in error
    dataset = check_consistent(root)
    assert 0 < dataset.num_episodes < 120
    assert set(range(dataset.num_episodes)) <= {m["episode_index"] for m in read_mcap_messages(log)["/observation"]}

    again = run(recording(root, 1, "--resume"))
    assert again.returncode == 0, again.stderr[-2000:]
    check_consistent(root, episodes=dataset.num_episodes + 3)


def test_no_folder_is_left_when_the_first_chunk_cannot_be_written(tmp_path):
    root = tmp_path / "ds"

    def tiny_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))

    proc = run(recording(root, 2), preexec_fn=tiny_files)
    assert proc.returncode == 1 and "File too large" in proc.stderr
    assert not root.exists() and not durable.leftovers(root)


@pytest.fixture
def small_dataset(tmp_path) -> Path:
    """6 episodes in 6 data files, recorded in this process."""
    root = tmp_path / "small"
    assert record_demos(recording(root, 2, "--batch-size", "1", "--chunk-episodes", "1")) == 0
    return root


def test_a_damaged_copy_is_refused_by_resume_and_repaired_by_the_doctor(small_dataset, tmp_path, capsys):
    root = tmp_path / "copy"
    shutil.copytree(small_dataset, root)
    cut = root / "data" / "chunk-000" / "file-004.parquet"
    cut.write_bytes(cut.read_bytes()[:1000])  # a copy cut off mid-file
    orphan = root / "data" / "chunk-000" / "file-006.parquet"
    shutil.copy(small_dataset / "data" / "chunk-000" / "file-005.parquet", orphan)
    (root / "data" / "chunk-000" / "file-007.parquet.tmp").write_bytes(b"partial")
    capsys.readouterr()

    with pytest.raises(SystemExit) as refused:
        record_demos(recording(root, 1, "--resume"))
    error = capsys.readouterr().err.strip()
    assert refused.value.code == 2 and len(error.splitlines()) == 1
    assert str(cut) in error and f"ocn-doctor --repair {root}" in error

    assert doctor([str(root)]) == 1
    report = capsys.readouterr().err
    for named in (cut, orphan, "file-007.parquet.tmp", "keep episodes 0-3, drop 2"):
        assert str(named) in report
    assert doctor([str(root), "--repair"]) == 0
    assert "a sound LeRobot v3.0 dataset: 4 episodes" in capsys.readouterr().out
    check_consistent(root, episodes=4)
    assert data_files(root) == [f"file-00{i}.parquet" for i in range(4)]
    untouched = small_dataset / "data" / "chunk-000" / "file-000.parquet"
    assert (root / "data" / "chunk-000" / "file-000.parquet").read_bytes() == untouched.read_bytes()
    repairs = load_provenance(root)["repairs"]
    assert repairs[0]["kept_episodes"] == 4 and repairs[0]["dropped_episodes"] == 2

    assert record_demos(recording(root, 1, "--resume")) == 0
    check_consistent(root, episodes=7)


def test_metadata_behind_its_data_is_caught_up_by_the_repair(small_dataset, tmp_path):
    """What record_demos' writer before the atomic commit left when killed after the data and the
    episode table of a chunk but before meta/info.json: sound episodes the totals leave out."""
    root = tmp_path / "lagging"
    shutil.copytree(small_dataset, root)
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info_path.write_text(json.dumps({**info, "total_episodes": 4, "total_frames": info["total_frames"] - 1}))
    diagnosis = diagnose(root)
    assert diagnosis.findings == [f"{info_path}: says 4 episodes and {info['total_frames'] - 1} frames; the episode "
                                  f"tables list 6 episodes and {info['total_frames']} frames."]
    assert doctor([str(root), "--repair"]) == 0
    check_consistent(root, episodes=6)
    assert json.loads(info_path.read_text())["splits"] == info["splits"]


def test_a_session_without_its_record_makes_resume_ask_for_a_new_seed(small_dataset, capsys):
    """A dataset killed under record_demos before this fix holds episodes no session accounts for:
    their seeds would be drawn again, unless the resumed session takes a seed of its own."""
    provenance_path = small_dataset / "meta" / "ocn_recording.json"
    provenance = json.loads(provenance_path.read_text())
    provenance["sessions"][0]["episodes"] = 2
    provenance_path.write_text(json.dumps(provenance))
    with pytest.raises(SystemExit) as refused:
        record_demos(recording(small_dataset, 1, "--resume"))
    assert refused.value.code == 2 and "--seed no session used (used: 7)" in capsys.readouterr().err
    args = recording(small_dataset, 1, "--resume")
    args[args.index("--seed") + 1] = "8"
    assert record_demos(args) == 0
    dataset = LeRobotDataset(REPO_ID, root=small_dataset)
    sequences = episode_sequences(dataset)
    assert dataset.num_episodes == 9 and len(set(sequences)) == 9


def test_the_swap_without_renameat2_and_its_recovery(tmp_path, monkeypatch):
    """Where the system cannot exchange two folders the swap is two renames; a kill between them
    leaves the folder missing and its last version parked, which `recover` puts back."""
    root = tmp_path / "folder"
    root.mkdir()
    (root / "kept.txt").write_text("old")
    monkeypatch.setattr(durable, "_exchange", lambda first, second: False)
    transaction = durable.FolderTransaction(root)
    transaction.fresh("kept.txt").write_text("new")
    transaction.publish()
    transaction.discard()
    assert (root / "kept.txt").read_text() == "new" and not durable.leftovers(root)

    transaction = durable.FolderTransaction(root)
    transaction.fresh("kept.txt").write_text("newer")
    root.rename(durable.previous_path(root))  # the kill falls between the two renames
    assert durable.recover(root) == [
        f"restored {root} from {durable.previous_path(root)}, where a swap cut off by a kill had left it",
        f"removed {durable.staging_path(root)}, left by a write cut off by a kill",
    ]
    assert (root / "kept.txt").read_text() == "new" and not durable.leftovers(root)


def test_doctor_names_a_missing_folder_and_a_sound_one(small_dataset, tmp_path, capsys):
    assert doctor([str(tmp_path / "nowhere")]) == 2
    error = capsys.readouterr().err.strip()
    assert error == (f"ocn-doctor: {tmp_path / 'nowhere'} does not exist: pass the folder of a LeRobot dataset "
                     "(its --root).")
    assert doctor([str(small_dataset)]) == 0
    assert "a sound LeRobot v3.0 dataset: 6 episodes" in capsys.readouterr().out
