"""Whole episodes of a recorded dataset as padded arrays, read straight from its parquet files.

Evaluation needs every frame of a split's episodes at once, with the ground-truth subtask columns
that LeRobot's training pipeline drops (where the dataset has them: any LeRobot dataset reads, with
its ground truth None); reading the columns directly is far faster than LeRobotDataset's per-frame
access.
"""

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

STATE = "observation.state"
LABELS = ("subtask.index", "subtask.id")


@dataclass
class EpisodeArrays:
    """Episodes padded to the longest: state [E, T, S] (`observation.state`, None where the dataset has
    none), action [E, T, A], subtask_index / subtask_id [E, T] (padding -1; None where the dataset has
    no ground truth), mask [E, T], lengths [E], tasks (one string per episode), episode_index [E], and
    `inputs`: every input feature read for a policy ({key: [E, T, ...]}: states as stored, images as
    uint8 [E, T, C, size, size]), `observation.state` among them when it was read."""

    state: np.ndarray | None
    action: np.ndarray
    subtask_index: np.ndarray | None
    subtask_id: np.ndarray | None
    mask: np.ndarray
    lengths: np.ndarray
    tasks: list[str]
    episode_index: np.ndarray
    inputs: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def labelled(self) -> bool:
        """Whether the episodes carry ground-truth subtasks (the parsing scores need them)."""
        return self.subtask_index is not None


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


# Share of a dataset's episodes, its last ones, that stands in for a validation split it does not name.
LAST_FRACTION = 0.2


def split_episodes(root: Path, split: str) -> range:
    """Episode indices of a split named in `meta/info.json` ("train", "val", or "all"). A dataset that
    names no "val" split (LeRobot's writer names "train" alone, all of the episodes) has its last fifth
    of episodes as "val": `held_out` says whether those were left out of training."""
    info = read_info(root)
    if split == "all":
        return range(info["total_episodes"])
    splits = info.get("splits") or {}
    if split == "val" and split not in splits:
        total = info["total_episodes"]
        return range(total - max(1, round(total * LAST_FRACTION)), total)
    if split not in splits:
        raise ValueError(f"{root} has no split {split!r}; its splits are {sorted(splits)} (or use 'all').")
    start, stop = (int(part) for part in splits[split].split(":"))
    return range(start, stop)


def held_out(root: Path, episodes: range) -> bool:
    """Whether none of `episodes` lies in the dataset's "train" split (a policy built from the dataset
    trains on that split, or on every episode when it names none)."""
    train = (read_info(root).get("splits") or {}).get("train")
    if train is None:
        return False
    start, stop = (int(part) for part in train.split(":"))
    return not set(episodes) & set(range(start, stop))


def _task_strings(root: Path) -> dict[int, str]:
    table = pq.read_table(Path(root) / "meta" / "tasks.parquet").to_pandas()
    return {int(index): str(task) for task, index in zip(table.index, table["task_index"], strict=True)}


def _column_numpy(column: pa.ChunkedArray) -> np.ndarray:
    """A column as numpy; list columns (vector features; LeRobot's own writer stores variable-size
    lists of one size, this project's writer fixed-size ones) become [rows, size]."""
    flat = column.combine_chunks()
    if pa.types.is_fixed_size_list(flat.type) or pa.types.is_list(flat.type):
        return flat.flatten().to_numpy(zero_copy_only=False).reshape(len(flat), -1)
    return flat.to_numpy(zero_copy_only=False)


def load_episodes(
    root: Path, episodes: range, max_episodes: int | None = None, inputs: Sequence[str] | None = None,
    image_size: int = 0,
) -> EpisodeArrays:
    """The selected episodes (at most `max_episodes`, the first ones) with their ground truth where the
    dataset has it. `inputs`: the features to read besides the action (default: `observation.state`
    where the dataset has it); image features among them are decoded once and shrunk to `image_size`
    square pixels (`lerobot_policy_ocn.episode_memory.read_images`). A feature the dataset lacks is an error."""
    root = Path(root)
    files = sorted((root / "data").glob("*/*.parquet"))
    if not files:
        raise FileNotFoundError(f"No data files under {root / 'data'}: is {root} a LeRobot dataset?")
    wanted = list(episodes)[:max_episodes]
    if not wanted:
        raise ValueError(f"No episodes selected from {root}.")
    features = read_info(root)["features"]
    if inputs is None:
        inputs = [STATE] if STATE in features else []
    missing = [key for key in inputs if key not in features]
    if missing:
        raise ValueError(f"{root} has no {missing} (its features are {sorted(features)}); the policy reads them: "
                         "pass the dataset it was trained on, or one with the same features.")
    images = [key for key in inputs if features[key]["dtype"] in ("image", "video")]
    labelled = all(key in features for key in LABELS)
    stored = [key for key in inputs if features[key]["dtype"] != "video"]
    columns = list(dict.fromkeys([*stored, "action", "episode_index", "task_index", "timestamp",
                                  *(LABELS if labelled else ())]))
    lo, hi = wanted[0], wanted[-1]
    parts = []
    for file in files:
        part = pq.read_table(file, columns=columns)
        keep = pc.and_(pc.greater_equal(part["episode_index"], lo), pc.less_equal(part["episode_index"], hi))
        parts.append(part.filter(keep))
    table = pa.concat_tables(parts)
    table = table.take(pc.sort_indices(table, sort_keys=[("episode_index", "ascending")]))
    episode = table["episode_index"].to_numpy()
    ids, starts, lengths = np.unique(episode, return_index=True, return_counts=True)
    n, longest = ids.size, int(lengths.max())
    rows = starts[:, None] + np.minimum(np.arange(longest), lengths[:, None] - 1)
    mask = np.arange(longest) < lengths[:, None]

    def gather(values: np.ndarray, pad: int | None = None) -> np.ndarray:
        out = values[rows]
        return out if pad is None else np.where(mask, out, pad)

    loaded = {key: gather(_column_numpy(table[key])).reshape(n, longest, -1) for key in inputs if key not in images}
    if images:
        from lerobot_policy_ocn.episode_memory import read_images

        loaded |= {key: gather(read_images(root, table, key, image_size).numpy()) for key in images}
    task_of = _task_strings(root)
    tasks = [task_of[int(t)] for t in table["task_index"].to_numpy()[starts]]
    label = {key: gather(_column_numpy(table[key]).reshape(-1), -1) if labelled else None for key in LABELS}
    return EpisodeArrays(
        state=loaded.get(STATE),
        action=gather(_column_numpy(table["action"])).reshape(n, longest, -1),
        subtask_index=label["subtask.index"],
        subtask_id=label["subtask.id"],
        mask=mask,
        lengths=lengths,
        tasks=tasks,
        episode_index=ids,
        inputs=loaded,
    )
