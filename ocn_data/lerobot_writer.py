"""Write chunks of finished episodes straight into a LeRobot v3.0 dataset, each as one atomic commit.

Why not `LeRobotDataset.add_frame()/save_episode()`: it validates, converts and computes
statistics one frame and one episode at a time (about 0.04-0.25 s per episode here), which caps
recording at a few hundred frames per second. This writer produces the same on-disk layout that
LeRobot's own writer produces (`meta/info.json`, `meta/stats.json`, `meta/tasks.parquet`,
`meta/episodes/chunk-*/file-*.parquet` with per-episode statistics, `data/chunk-*/file-*.parquet`,
`videos/<key>/chunk-*/file-*.mp4`) one chunk of many episodes at a time, through LeRobot's own
metadata, IO, stats-aggregation and video-encoding helpers. Each chunk becomes one data file.

Crash safety: each chunk is one `lerobot_policy_ocn.ocn_data.durable.FolderTransaction`. Its data file, videos and
episode table, the rewritten tasks, statistics and `meta/info.json` (totals and splits), and
whatever the caller adds (`record_demos`: the provenance and the card) are staged beside the
dataset, fsynced, and swapped in at once. A SIGKILL at any instant leaves the dataset as it was
after the previous chunk or after this one, and never a file that the metadata does not describe.
SIGINT and SIGTERM are held while a chunk is published, then delivered as the process would have.
The dataset folder appears with the first published chunk: a recording stopped before it leaves none.

Test hook: with `OCN_FAULT_AFTER=STAGE[:N]` in the environment, the writer SIGKILLs its own process
the N-th time (default 1st) it reaches STAGE: `data` (the chunk's data file is staged, its metadata
not yet), `staged` (everything is staged, nothing swapped in), `swapped` (the new version is in
place, the replaced one not yet removed). tests/test_recording_faults.py kills it there.

With `language=True` the chunks' subtask segments are also written as LeRobot's native
`language_persistent` / `language_events` columns. They are optional because LeRobot 0.6.1's
`lerobot-dataset-viz` batches frames with PyTorch's `default_collate`, which cannot batch the
`camera=None` field that LeRobot's own row schema requires (`lerobot-train` uses
`lerobot_collate_fn` and is fine), so an annotated dataset does not open in that viewer.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import signal
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.compute_stats import aggregate_stats
from lerobot.datasets.dataset_metadata import CODEBASE_VERSION, LeRobotDatasetMetadata
from lerobot.datasets.feature_utils import create_empty_dataset_info, get_hf_features_from_features
from lerobot.datasets.io_utils import load_info, load_stats, load_tasks, write_info, write_stats, write_tasks
from lerobot.datasets.language import LANGUAGE_EVENTS, LANGUAGE_PERSISTENT, language_feature_info
from lerobot.datasets.utils import DatasetInfo, update_chunk_file_indices
from lerobot.datasets.video_utils import encode_video_frames, get_video_info
from lerobot.utils.constants import DEFAULT_FEATURES
from lerobot.utils.feature_utils import _validate_feature_names
from PIL import Image

from lerobot_policy_ocn.ocn_data.dataset_files import (
    DATA_PATH, EPISODES_PATH, INFO_PATH, STATS_PATH, TASKS_PATH, VIDEO_PATH, split_ranges,
)
from lerobot_policy_ocn.ocn_data.durable import FolderTransaction
from lerobot_policy_ocn.ocn_data.episodes import EpisodeChunk
from lerobot_policy_ocn.ocn_data.language_rows import empty_events_column, persistent_column
from lerobot_policy_ocn.ocn_data.stats import STAT_KEYS, episode_stats, pooled_stats

BOOKKEEPING = tuple(DEFAULT_FEATURES)
FAULT_ENV = "OCN_FAULT_AFTER"
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_stages_reached: Counter[str] = Counter()


def fault_point(stage: str) -> None:
    """The test hook: SIGKILL this process at `stage` when `OCN_FAULT_AFTER` names it (see above)."""
    wanted = os.environ.get(FAULT_ENV)
    if not wanted:
        return
    name, _, count = wanted.partition(":")
    if name != stage:
        return
    _stages_reached[stage] += 1
    if _stages_reached[stage] == int(count or 1):
        os.kill(os.getpid(), signal.SIGKILL)


class DatasetExistsError(FileExistsError):
    """The dataset root already exists and the caller did not ask to resume."""

    def __init__(self, root: Path) -> None:
        super().__init__(f"{root} already exists; pass --resume to append to it or choose a new --root")


class NoDatasetError(FileNotFoundError):
    """The caller asked to resume a dataset that is not there."""

    def __init__(self, root: Path) -> None:
        super().__init__(f"--resume: no LeRobot dataset at {root} (meta/info.json missing)")


@contextmanager
def held_stop_signals() -> Iterator[None]:
    """Hold SIGINT and SIGTERM while a chunk is published, then deliver them to the handlers the
    process had (Ctrl-C's KeyboardInterrupt, a SIGTERM handler, or SIGTERM's default exit), so a
    stop request never cuts a commit short and is never lost."""
    pending: list[int] = []
    try:
        previous = {signum: signal.signal(signum, lambda signum, frame: pending.append(signum))
                    for signum in STOP_SIGNALS}
    except ValueError:  # not the main thread: signals cannot be handled here anyway
        yield
        return
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for signum in dict.fromkeys(pending):
            signal.raise_signal(signum)


def read_episode_index(root: Path, columns: list[str]) -> pa.Table:
    """`columns` of every row of the dataset's episode tables, in file order."""
    files = sorted((Path(root) / "meta" / "episodes").glob("*/*.parquet"))
    return pa.concat_tables([pq.read_table(file, columns=columns) for file in files])


# A session's callback adds its own files (provenance, card) to each staged version.
Finish = Callable[[FolderTransaction], None]


@dataclasses.dataclass
class _Published:
    """What the writer knows of the published dataset; replaced as a whole after each commit."""

    info: DatasetInfo
    tasks: pd.DataFrame | None
    stats: dict | None
    next_file: tuple[int, int]


class ColumnarDatasetWriter:
    """Append chunks of episodes to a new or existing LeRobot v3.0 dataset at `root`, one atomic
    commit per chunk. Nothing is written before the first `write`."""

    def __init__(
        self,
        root: str | Path,
        repo_id: str,
        fps: int,
        features: dict[str, dict],
        *,
        resume: bool = False,
        robot_type: str | None = None,
        language: bool = False,
        val_fraction: float = 0.2,
    ) -> None:
        self.root = Path(root)
        self.repo_id = repo_id
        self.val_fraction = val_fraction
        if language:
            features = {**features, **language_feature_info()}
        if resume:
            if not (self.root / INFO_PATH).is_file():
                raise NoDatasetError(self.root)
            info = load_info(self.root)
            self._check_same_features(info.features, features)
            next_file = (0, 0)
            if info.total_episodes:
                last = read_episode_index(self.root, ["data/chunk_index", "data/file_index"]).to_pylist()[-1]
                next_file = update_chunk_file_indices(last["data/chunk_index"], last["data/file_index"],
                                                      info.chunks_size)
            tasks = load_tasks(self.root) if info.total_tasks else None
            self._published = _Published(info, tasks, load_stats(self.root), next_file)
        else:
            if self.root.exists():
                raise DatasetExistsError(self.root)
            features = {**copy.deepcopy(features), **DEFAULT_FEATURES}
            _validate_feature_names(features)
            use_videos = any(ft["dtype"] == "video" for ft in features.values())
            info = create_empty_dataset_info(CODEBASE_VERSION, fps, features, use_videos, robot_type)
            self._published = _Published(info, None, None, (0, 0))
        self.features = self._published.info.features
        self.hf_features = get_hf_features_from_features(
            {k: ft for k, ft in self.features.items() if ft["dtype"] != "video"}
        )

    @property
    def total_episodes(self) -> int:
        return self._published.info.total_episodes

    @property
    def total_frames(self) -> int:
        return self._published.info.total_frames

    @property
    def meta(self) -> LeRobotDatasetMetadata:
        """The published dataset's metadata, as LeRobot reads it."""
        return LeRobotDatasetMetadata(self.repo_id, root=self.root)

    def _check_same_features(self, existing_features: dict, features: dict[str, dict]) -> None:
        existing = {k: (ft["dtype"], tuple(ft["shape"])) for k, ft in existing_features.items()}
        wanted = {k: (ft["dtype"], tuple(ft["shape"])) for k, ft in features.items()}
        wanted.update({k: existing[k] for k in BOOKKEEPING if k in existing})
        if existing != wanted:
            raise ValueError(
                f"--resume: the dataset at {self.root} has features {sorted(existing)} "
                f"but this recording would write {sorted(wanted)}"
            )

    def write(self, chunk: EpisodeChunk, finish: Finish | None = None) -> None:
        """Publish `chunk` as the dataset's next version, with `finish`'s files, in one atomic
        step. An empty chunk publishes `finish`'s files alone (nothing at all before the dataset
        exists: LeRobot cannot load a dataset without episodes)."""
        if chunk.num_episodes == 0 and not self.root.exists():
            return
        with held_stop_signals():
            transaction = FolderTransaction(self.root)
            try:
                published = self._stage(transaction, chunk)
                if finish is not None:
                    finish(transaction)
                fault_point("staged")
                transaction.publish()
                fault_point("swapped")
            finally:
                transaction.discard()
            self._published = published

    def _stage(self, transaction: FolderTransaction, chunk: EpisodeChunk) -> _Published:
        """Stage the chunk's files and the metadata that describes the dataset with it."""
        old = self._published
        info = dataclasses.replace(old.info, features=copy.deepcopy(old.info.features))
        tasks, stats, next_file = old.tasks, old.stats, old.next_file
        if chunk.num_episodes:
            tasks, pooled = self._stage_chunk(transaction, chunk, info, tasks)
            stats = pooled if stats is None else aggregate_stats([stats, pooled])
            next_file = update_chunk_file_indices(*next_file, info.chunks_size)
            transaction.fresh(TASKS_PATH)
            write_tasks(tasks, transaction.staging)
            transaction.fresh(STATS_PATH)
            write_stats(stats, transaction.staging)
        info.splits = split_ranges(info.total_episodes, self.val_fraction)
        transaction.fresh(INFO_PATH)
        write_info(info, transaction.staging)
        return _Published(info, tasks, stats, next_file)

    def _stage_chunk(
        self, transaction: FolderTransaction, chunk: EpisodeChunk, info: DatasetInfo, tasks: pd.DataFrame | None
    ) -> tuple[pd.DataFrame, dict]:
        """Stage the chunk's data file, videos and episode table; count it in `info`. Returns the
        task table with the chunk's tasks and the chunk's pooled statistics."""
        fps = info.fps
        n_eps, n_frames = chunk.num_episodes, chunk.num_frames
        first_episode, first_frame = info.total_episodes, info.total_frames
        episode_index = first_episode + np.arange(n_eps, dtype=np.int64)
        frame_index = np.arange(n_frames, dtype=np.int64) - np.repeat(chunk.starts, chunk.lengths)
        task_index, tasks = _task_indices(tasks, chunk.tasks)
        columns = {
            **chunk.columns,
            "timestamp": (frame_index / fps).astype(np.float32),
            "frame_index": frame_index,
            "episode_index": np.repeat(episode_index, chunk.lengths),
            "index": first_frame + np.arange(n_frames, dtype=np.int64),
            "task_index": np.repeat(task_index, chunk.lengths),
        }
        chunk_idx, file_idx = self._published.next_file
        self._write_data(transaction.fresh(DATA_PATH.format(chunk=chunk_idx, file=file_idx)), columns, chunk, fps)
        fault_point("data")
        video_columns, video_episode_stats, video_pooled = self._write_videos(
            transaction, chunk, chunk_idx, file_idx, info
        )

        numeric = [k for k, ft in self.features.items() if ft["dtype"] not in ("video", "language", "string")]
        per_episode = {k: episode_stats(columns[k], chunk.lengths) for k in numeric} | video_episode_stats
        pooled = {k: pooled_stats(per_episode[k]) for k in numeric} | video_pooled

        ends = np.cumsum(chunk.lengths) + first_frame
        episodes = {
            "episode_index": episode_index,
            "tasks": [[t] for t in chunk.tasks],
            "length": chunk.lengths,
            "data/chunk_index": np.full(n_eps, chunk_idx),
            "data/file_index": np.full(n_eps, file_idx),
            "dataset_from_index": ends - chunk.lengths,
            "dataset_to_index": ends,
            **video_columns,
        }
        for key, stats in per_episode.items():
            for stat in STAT_KEYS:
                values = stats[stat].reshape(n_eps, -1)
                episodes[f"stats/{key}/{stat}"] = list(values.astype(np.int64 if stat == "count" else np.float64))
        episodes["meta/episodes/chunk_index"] = np.full(n_eps, chunk_idx)
        episodes["meta/episodes/file_index"] = np.full(n_eps, file_idx)
        episodes_path = transaction.fresh(EPISODES_PATH.format(chunk=chunk_idx, file=file_idx))
        pq.write_table(pa.table(episodes), episodes_path, compression="snappy")
        info.total_episodes += n_eps
        info.total_frames += n_frames
        info.total_tasks = len(tasks)
        return tasks, pooled

    def _write_data(self, path: Path, columns: dict[str, np.ndarray], chunk: EpisodeChunk, fps: int) -> None:
        schema = self.hf_features.arrow_schema
        arrays = []
        for field in schema:
            if field.name == LANGUAGE_PERSISTENT:
                arrays.append(persistent_column(chunk.segments, chunk.lengths, fps))
            elif field.name == LANGUAGE_EVENTS:
                arrays.append(empty_events_column(chunk.num_frames))
            elif field.name not in columns:
                raise KeyError(f"chunk has no column for dataset feature {field.name!r}")
            else:
                arrays.append(_arrow_column(columns[field.name], field.type))
        pq.write_table(pa.Table.from_arrays(arrays, schema=schema), path, compression="snappy", use_dictionary=True)

    def _write_videos(
        self, transaction: FolderTransaction, chunk: EpisodeChunk, chunk_idx: int, file_idx: int, info: DatasetInfo
    ) -> tuple[dict, dict, dict]:
        """Encode each video feature's frames of the chunk into one MP4 with LeRobot's encoder; the
        first file also sets the feature's video info in `info` (codec, size), as LeRobot's does.

        Returns the episodes-table columns locating each episode in the file, and per-episode and
        pooled per-channel statistics in [0, 1] (shape (3, 1, 1), as LeRobot stores image stats),
        computed on every 4th pixel of each frame.
        """
        columns: dict[str, np.ndarray] = {}
        per_episode: dict[str, dict] = {}
        pooled: dict[str, dict] = {}
        fps, n_eps, starts = info.fps, chunk.num_episodes, chunk.starts
        for key in (k for k, ft in self.features.items() if ft["dtype"] == "video"):
            if key not in chunk.videos:
                raise KeyError(f"dataset has video feature {key!r} but the chunk carries no frames for it")
            frames = chunk.videos[key]
            path = transaction.fresh(VIDEO_PATH.format(key=key, chunk=chunk_idx, file=file_idx))
            with tempfile.TemporaryDirectory() as tmp:
                for i, frame in enumerate(frames):
                    Image.fromarray(frame).save(Path(tmp) / f"frame-{i:06d}.png", compress_level=1)
                encode_video_frames(tmp, path, fps, overwrite=True)
            if (chunk_idx, file_idx) == (0, 0):
                info.features[key]["info"] = get_video_info(path)
            columns[f"videos/{key}/chunk_index"] = np.full(n_eps, chunk_idx)
            columns[f"videos/{key}/file_index"] = np.full(n_eps, file_idx)
            columns[f"videos/{key}/from_timestamp"] = starts / fps
            columns[f"videos/{key}/to_timestamp"] = (starts + chunk.lengths) / fps
            pixels = frames[:, ::4, ::4, :]
            per_frame = pixels.shape[1] * pixels.shape[2]
            pixels = pixels.reshape(-1, 3) / 255.0
            ep = episode_stats(pixels, chunk.lengths * per_frame)
            ep["count"] = chunk.lengths[:, None]
            per_episode[key] = {k: v if k == "count" else v.reshape(n_eps, 3, 1, 1) for k, v in ep.items()}
            pooled[key] = pooled_stats(per_episode[key])
        return columns, per_episode, pooled


def _task_indices(tasks: pd.DataFrame | None, chunk_tasks: list[str]) -> tuple[np.ndarray, pd.DataFrame]:
    """Each episode's task index, and the task table with any new task added at the end."""
    known = {} if tasks is None else dict(zip(tasks.index, tasks["task_index"], strict=True))
    for task in dict.fromkeys(chunk_tasks):
        known.setdefault(task, len(known))
    table = pd.DataFrame({"task_index": list(known.values())}, index=pd.Index(list(known), name="task"))
    return np.array([known[t] for t in chunk_tasks], dtype=np.int64), table


def _arrow_column(values: np.ndarray, arrow_type: pa.DataType) -> pa.Array:
    """A numpy column as the Arrow type LeRobot's HF features declare (scalar or fixed list)."""
    if pa.types.is_fixed_size_list(arrow_type):
        flat = np.ascontiguousarray(values).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat, arrow_type.value_type), arrow_type.list_size)
    return pa.array(np.ascontiguousarray(values).reshape(-1), arrow_type)

