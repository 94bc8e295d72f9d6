"""Write chunks of finished episodes straight into a LeRobot v3.0 dataset.

Why not `LeRobotDataset.add_frame()/save_episode()`: it validates, converts and computes
statistics one frame and one episode at a time (about 0.04-0.25 s per episode here), which caps
recording at a few hundred frames per second. This writer produces the same on-disk layout that
LeRobot's own writer produces (`meta/info.json`, `meta/stats.json`, `meta/tasks.parquet`,
`meta/episodes/chunk-*/file-*.parquet` with per-episode statistics, `data/chunk-*/file-*.parquet`,
`videos/<key>/chunk-*/file-*.mp4`) one chunk of many episodes at a time, through LeRobot's own
metadata, IO, stats-aggregation and video-encoding helpers. Each chunk becomes one data file, so
an interrupted recording keeps every chunk written before it and `resume` simply adds files.

With `language=True` the chunks' subtask segments are also written as LeRobot's native
`language_persistent` / `language_events` columns. They are optional because LeRobot 0.6.1's
`lerobot-dataset-viz` batches frames with PyTorch's `default_collate`, which cannot batch the
`camera=None` field that LeRobot's own row schema requires (`lerobot-train` uses
`lerobot_collate_fn` and is fine), so an annotated dataset does not open in that viewer.
"""

from __future__ import annotations

import signal
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.compute_stats import aggregate_stats
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.feature_utils import get_hf_features_from_features
from lerobot.datasets.io_utils import load_stats, write_info, write_stats, write_tasks
from lerobot.datasets.language import LANGUAGE_EVENTS, LANGUAGE_PERSISTENT, language_feature_info
from lerobot.datasets.utils import update_chunk_file_indices
from lerobot.datasets.video_utils import encode_video_frames
from PIL import Image

from ocn_data.episodes import EpisodeChunk
from ocn_data.language_rows import empty_events_column, persistent_column
from ocn_data.stats import STAT_KEYS, episode_stats, pooled_stats

DATA_PATH = "data/chunk-{chunk:03d}/file-{file:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk:03d}/file-{file:03d}.parquet"
VIDEO_PATH = "videos/{key}/chunk-{chunk:03d}/file-{file:03d}.mp4"
BOOKKEEPING = ("timestamp", "frame_index", "episode_index", "index", "task_index")


class DatasetExistsError(FileExistsError):
    """The dataset root already exists and the caller did not ask to resume."""


@contextmanager
def deferred_sigint() -> Iterator[None]:
    """Hold back Ctrl-C while a chunk is written, then deliver it, so no file is half-written."""
    pending: list[tuple] = []
    previous = signal.getsignal(signal.SIGINT)
    try:
        signal.signal(signal.SIGINT, lambda *args: pending.append(args))
    except ValueError:  # not the main thread: signals cannot be handled here anyway
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if pending:
            raise KeyboardInterrupt


class ColumnarDatasetWriter:
    """Append chunks of episodes to a new or existing LeRobot v3.0 dataset at `root`."""

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
    ) -> None:
        self.root = Path(root)
        if language:
            features = {**features, **language_feature_info()}
        if resume:
            if not (self.root / "meta" / "info.json").is_file():
                raise FileNotFoundError(f"--resume: no LeRobot dataset at {self.root} (meta/info.json missing)")
            self.meta = LeRobotDatasetMetadata(repo_id, root=self.root)
            self._check_same_features(features)
            self.stats = load_stats(self.root)
            last = self.meta.episodes[-1] if self.meta.total_episodes else None
            self._next_file = (
                update_chunk_file_indices(last["data/chunk_index"], last["data/file_index"], self.meta.chunks_size)
                if last is not None
                else (0, 0)
            )
        else:
            if self.root.exists():
                raise DatasetExistsError(
                    f"{self.root} already exists; pass --resume to append to it or choose a new --root"
                )
            video_keys = [k for k, ft in features.items() if ft["dtype"] == "video"]
            self.meta = LeRobotDatasetMetadata.create(
                repo_id, fps, features, robot_type=robot_type, root=self.root, use_videos=bool(video_keys)
            )
            self.stats = None
            self._next_file = (0, 0)
        self.meta.finalize()
        self.features = self.meta.features
        self.hf_features = get_hf_features_from_features(
            {k: ft for k, ft in self.features.items() if ft["dtype"] != "video"}
        )
        self.tasks: pd.DataFrame | None = self.meta.tasks
        self.task_counts: dict[str, int] = {}
        if resume and self.meta.episodes is not None:
            for episode_tasks in self.meta.episodes["tasks"]:
                self.task_counts[episode_tasks[0]] = self.task_counts.get(episode_tasks[0], 0) + 1

    @property
    def total_episodes(self) -> int:
        return self.meta.info.total_episodes

    @property
    def total_frames(self) -> int:
        return self.meta.info.total_frames

    def _check_same_features(self, features: dict[str, dict]) -> None:
        existing = {k: (ft["dtype"], tuple(ft["shape"])) for k, ft in self.meta.features.items()}
        wanted = {k: (ft["dtype"], tuple(ft["shape"])) for k, ft in features.items()}
        wanted.update({k: existing[k] for k in BOOKKEEPING if k in existing})
        if existing != wanted:
            raise ValueError(
                f"--resume: the dataset at {self.root} has features {sorted(existing)} "
                f"but this recording would write {sorted(wanted)}"
            )

    def _task_indices(self, tasks: list[str]) -> np.ndarray:
        known = {} if self.tasks is None else dict(zip(self.tasks.index, self.tasks["task_index"], strict=True))
        for task in dict.fromkeys(tasks):
            known.setdefault(task, len(known))
        self.tasks = pd.DataFrame({"task_index": list(known.values())}, index=pd.Index(list(known), name="task"))
        return np.array([known[t] for t in tasks], dtype=np.int64)

    def write(self, chunk: EpisodeChunk) -> None:
        """Write one chunk as a new data file plus its episode metadata; Ctrl-C waits for it."""
        if chunk.num_episodes == 0:
            return
        with deferred_sigint():
            self._write(chunk)

    def _write(self, chunk: EpisodeChunk) -> None:
        fps = self.meta.fps
        n_eps, n_frames = chunk.num_episodes, chunk.num_frames
        first_episode, first_frame = self.total_episodes, self.total_frames
        episode_index = first_episode + np.arange(n_eps, dtype=np.int64)
        frame_index = np.arange(n_frames, dtype=np.int64) - np.repeat(chunk.starts, chunk.lengths)
        task_index = self._task_indices(chunk.tasks)
        for task in chunk.tasks:
            self.task_counts[task] = self.task_counts.get(task, 0) + 1
        columns = {
            **chunk.columns,
            "timestamp": (frame_index / fps).astype(np.float32),
            "frame_index": frame_index,
            "episode_index": np.repeat(episode_index, chunk.lengths),
            "index": first_frame + np.arange(n_frames, dtype=np.int64),
            "task_index": np.repeat(task_index, chunk.lengths),
        }
        chunk_idx, file_idx = self._next_file
        self._write_data(columns, chunk, chunk_idx, file_idx)
        video_columns, video_episode_stats, video_pooled = self._write_videos(chunk, chunk_idx, file_idx)

        numeric = [k for k, ft in self.features.items() if ft["dtype"] not in ("video", "language", "string")]
        per_episode = {k: episode_stats(columns[k], chunk.lengths) for k in numeric} | video_episode_stats
        pooled = {k: pooled_stats(columns[k]) for k in numeric} | video_pooled

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
        episodes_path = self.root / EPISODES_PATH.format(chunk=chunk_idx, file=file_idx)
        episodes_path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(episodes), episodes_path, compression="snappy")

        write_tasks(self.tasks, self.root)
        self.stats = pooled if self.stats is None else aggregate_stats([self.stats, pooled])
        write_stats(self.stats, self.root)
        info = self.meta.info
        info.total_episodes += n_eps
        info.total_frames += n_frames
        info.total_tasks = len(self.tasks)
        write_info(info, self.root)
        self._next_file = update_chunk_file_indices(chunk_idx, file_idx, self.meta.chunks_size)

    def _write_data(self, columns: dict[str, np.ndarray], chunk: EpisodeChunk, chunk_idx: int, file_idx: int) -> None:
        schema = self.hf_features.arrow_schema
        arrays = []
        for field in schema:
            if field.name == LANGUAGE_PERSISTENT:
                arrays.append(persistent_column(chunk.segments, chunk.lengths, self.meta.fps))
            elif field.name == LANGUAGE_EVENTS:
                arrays.append(empty_events_column(chunk.num_frames))
            elif field.name not in columns:
                raise KeyError(f"chunk has no column for dataset feature {field.name!r}")
            else:
                arrays.append(_arrow_column(columns[field.name], field.type))
        table = pa.Table.from_arrays(arrays, schema=schema)
        path = self.root / DATA_PATH.format(chunk=chunk_idx, file=file_idx)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".parquet.tmp")
        pq.write_table(table, tmp, compression="snappy", use_dictionary=True)
        tmp.replace(path)

    def _write_videos(self, chunk: EpisodeChunk, chunk_idx: int, file_idx: int) -> tuple[dict, dict, dict]:
        """Encode each video feature's frames of the chunk into one MP4 with LeRobot's encoder.

        Returns the episodes-table columns locating each episode in the file, and per-episode and
        pooled per-channel statistics in [0, 1] (shape (3, 1, 1), as LeRobot stores image stats),
        computed on every 4th pixel of each frame.
        """
        columns: dict[str, np.ndarray] = {}
        per_episode: dict[str, dict] = {}
        pooled: dict[str, dict] = {}
        fps, n_eps, starts = self.meta.fps, chunk.num_episodes, chunk.starts
        for key in (k for k, ft in self.features.items() if ft["dtype"] == "video"):
            if key not in chunk.videos:
                raise KeyError(f"dataset has video feature {key!r} but the chunk carries no frames for it")
            frames = chunk.videos[key]
            path = self.root / VIDEO_PATH.format(key=key, chunk=chunk_idx, file=file_idx)
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory() as tmp:
                for i, frame in enumerate(frames):
                    Image.fromarray(frame).save(Path(tmp) / f"frame-{i:06d}.png", compress_level=1)
                encode_video_frames(tmp, path, fps, overwrite=True)
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
            pool = pooled_stats(pixels)
            pool["count"] = np.array([chunk.num_frames])
            pooled[key] = {k: v if k == "count" else v.reshape(3, 1, 1) for k, v in pool.items()}
        return columns, per_episode, pooled

    def finalize(self, val_fraction: float = 0.2) -> None:
        """Record the train/validation split (the last `val_fraction` of episodes) and video info."""
        info = self.meta.info
        n = info.total_episodes
        n_train = n - int(round(n * val_fraction))
        info.splits = {"train": f"0:{n_train}"}
        if n_train < n:
            info.splits["val"] = f"{n_train}:{n}"
        write_info(info, self.root)
        if n and any(ft["dtype"] == "video" for ft in self.features.values()):
            LeRobotDatasetMetadata(self.meta.repo_id, root=self.root).update_video_info()


def _arrow_column(values: np.ndarray, arrow_type: pa.DataType) -> pa.Array:
    """A numpy column as the Arrow type LeRobot's HF features declare (scalar or fixed list)."""
    if pa.types.is_fixed_size_list(arrow_type):
        flat = np.ascontiguousarray(values).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat, arrow_type.value_type), arrow_type.list_size)
    return pa.array(np.ascontiguousarray(values).reshape(-1), arrow_type)

