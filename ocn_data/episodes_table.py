"""Whole episodes of a recorded dataset as padded arrays, read straight from its parquet files.

Evaluation needs every frame of a split's episodes at once, with the ground-truth subtask columns
that LeRobot's training pipeline drops; reading the columns directly is far faster than
LeRobotDataset's per-frame access.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

COLUMNS = ("observation.state", "action", "subtask.index", "subtask.id", "episode_index", "task_index")


@dataclass
class EpisodeArrays:
    """Episodes padded to the longest: state [E, T, S], action [E, T, A], subtask_index / subtask_id
    [E, T] (padding -1), mask [E, T], lengths [E], tasks (one string per episode), episode_index [E]."""

    state: np.ndarray
    action: np.ndarray
    subtask_index: np.ndarray
    subtask_id: np.ndarray
    mask: np.ndarray
    lengths: np.ndarray
    tasks: list[str]
    episode_index: np.ndarray


def read_info(root: Path) -> dict:
    """A LeRobot dataset's `meta/info.json`; a folder without one is named as not a dataset."""
    path = Path(root) / "meta" / "info.json"
    if not path.is_file():
        raise FileNotFoundError(f"{root} is not a LeRobot dataset (no meta/info.json).")
    return json.loads(path.read_text())


WORLDS = ("craft", "dial")


def dataset_world(root: Path) -> str:
    """The world a record_demos dataset holds, from its `meta/info.json` robot type (record_demos
    stores `--env` there; a dataset without one is Craft, recorded before the field was set), so
    that tools pick the world's rules from the data rather than from a flag."""
    world = read_info(root).get("robot_type") or "craft"
    if world not in WORLDS:
        raise ValueError(
            f"{root} holds robot_type {world!r} in meta/info.json; the worlds recorded by record_demos are "
            f"{', '.join(WORLDS)}."
        )
    return world


def split_episodes(root: Path, split: str) -> range:
    """Episode indices of a split named in `meta/info.json` ("train", "val", or "all")."""
    info = read_info(root)
    if split == "all":
        return range(info["total_episodes"])
    splits = info.get("splits") or {}
    if split not in splits:
        raise ValueError(f"{root} has no split {split!r}; its splits are {sorted(splits)} (or use 'all').")
    start, stop = (int(part) for part in splits[split].split(":"))
    return range(start, stop)


def _task_strings(root: Path) -> dict[int, str]:
    table = pq.read_table(Path(root) / "meta" / "tasks.parquet").to_pandas()
    return {int(index): str(task) for task, index in zip(table.index, table["task_index"], strict=True)}


def _column_numpy(column: pa.ChunkedArray) -> np.ndarray:
    """A column as numpy; fixed-size list columns (vector features) become [rows, size]."""
    if pa.types.is_fixed_size_list(column.type):
        flat = column.combine_chunks()
        return flat.flatten().to_numpy().reshape(len(flat), column.type.list_size)
    return column.to_numpy()


def load_episodes(root: Path, episodes: range, max_episodes: int | None = None) -> EpisodeArrays:
    """The selected episodes (at most `max_episodes`, the first ones) with their ground truth."""
    files = sorted((Path(root) / "data").glob("*/*.parquet"))
    if not files:
        raise FileNotFoundError(f"No data files under {Path(root) / 'data'}: is {root} a LeRobot dataset?")
    wanted = list(episodes)[:max_episodes]
    if not wanted:
        raise ValueError(f"No episodes selected from {root}.")
    lo, hi = wanted[0], wanted[-1]
    parts = []
    for file in files:
        table = pq.read_table(file, columns=list(COLUMNS))
        keep = pc.and_(pc.greater_equal(table["episode_index"], lo), pc.less_equal(table["episode_index"], hi))
        parts.append(table.filter(keep))
    columns = {name: np.concatenate([_column_numpy(part[name]) for part in parts]) for name in COLUMNS}
    order = np.argsort(columns["episode_index"], kind="stable")
    episode = columns["episode_index"][order]
    ids, starts, lengths = np.unique(episode, return_index=True, return_counts=True)
    n, longest = ids.size, int(lengths.max())
    rows = starts[:, None] + np.minimum(np.arange(longest), lengths[:, None] - 1)
    mask = np.arange(longest) < lengths[:, None]
    frames = order[rows]

    def gather(name: str, pad: int | None = None) -> np.ndarray:
        out = columns[name][frames]
        if pad is not None:
            out = np.where(mask, out, pad)
        return out

    state = gather("observation.state")
    action = gather("action")
    action = action.reshape(n, longest, -1)
    task_of = _task_strings(root)
    tasks = [task_of[int(t)] for t in gather("task_index")[:, 0]]
    return EpisodeArrays(
        state=state.reshape(n, longest, -1),
        action=action,
        subtask_index=gather("subtask.index", -1),
        subtask_id=gather("subtask.id", -1),
        mask=mask,
        lengths=lengths,
        tasks=tasks,
        episode_index=ids,
    )
