"""A dataset's episodes held in memory by the sequence policies that train on them.

LeRobot's loader assembles a training window frame by frame: about 5 ms per window on a 2-core
machine (results/bench_train.md), most of a recurrent policy's training step. A sequence policy
built from a dataset instead reads the columns it trains on once, here, straight from the
dataset's parquet files, and asks LeRobot for single frames (no `delta_timestamps`), of which it
reads only `episode_index`: each sampled frame stands for its whole episode, as a window around it
would. LeRobot's sampler, `--dataset.episodes`, the processes' shards and `--resume` keep deciding
which episodes train; only the loading of their frames moves here.

The frames are stored once, unpadded, in episode order; `batch` pads the sampled episodes to the
longest among them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import torch
from torch import Tensor

EPISODE_INDEX = "episode_index"
TASK_INDEX = "task_index"


@dataclass
class EpisodeMemory:
    """Every episode of a dataset: `frames` {key: [F, ...]} in episode order, and per episode index
    (over the dataset's whole range) its first frame `start`, its `length` (0 where the dataset has no
    such episode), its `task_index` and whether it is `trainable` (in the split the policy trains on)."""

    frames: dict[str, Tensor]
    start: Tensor
    length: Tensor
    task_index: Tensor
    trainable: Tensor
    split: str

    @classmethod
    def read(cls, root: str | Path, keys: list[str]) -> EpisodeMemory:
        """The columns `keys` of every episode of the LeRobot dataset at `root`. Where the dataset names a
        "train" split in `meta/info.json` (LeRobot's `splits`), only its episodes are trainable: the others
        are held out for evaluation, as `record_demos` writes them."""
        root = Path(root)
        files = sorted((root / "data").glob("*/*.parquet"))
        if not files:
            raise FileNotFoundError(f"{root} has no data files under data/: is it a LeRobot dataset?")
        columns = [*keys, EPISODE_INDEX, TASK_INDEX]
        table = pa.concat_tables(pq.read_table(file, columns=columns) for file in files)
        table = table.take(pc.sort_indices(table, sort_keys=[(EPISODE_INDEX, "ascending")]))
        episode = table[EPISODE_INDEX].to_numpy()
        ids, first, counts = np.unique(episode, return_index=True, return_counts=True)
        size = int(ids.max()) + 1
        start, length, task_index = (np.zeros(size, dtype=np.int64) for _ in range(3))
        start[ids], length[ids] = first, counts
        task_index[ids] = table[TASK_INDEX].to_numpy()[first]
        info = json.loads((root / "meta" / "info.json").read_text())
        split = "train" if "train" in (info.get("splits") or {}) else "all"
        trainable = length > 0
        if split == "train":
            lo, hi = (int(bound) for bound in info["splits"]["train"].split(":"))
            in_split = np.zeros(size, dtype=bool)
            in_split[lo:min(hi, size)] = True
            trainable &= in_split
        frames = {key: torch.from_numpy(_column_numpy(table[key]).copy()) for key in keys}
        return cls(frames, torch.from_numpy(start), torch.from_numpy(length), torch.from_numpy(task_index),
                   torch.from_numpy(trainable), split)

    @property
    def longest(self) -> int:
        return int(self.length.max())

    @property
    def n_trainable(self) -> int:
        return int(self.trainable.sum())

    def to(self, device: torch.device) -> EpisodeMemory:
        """The same episodes on `device` (where the policy trains), so batches are gathered there."""
        moved = {key: value.to(device) for key, value in self.frames.items()}
        return EpisodeMemory(moved, *(field.to(device) for field in (self.start, self.length, self.task_index,
                                                                     self.trainable)), self.split)

    def batch(self, episode_index: Tensor) -> tuple[Tensor, dict[str, Tensor], Tensor]:
        """The episodes `episode_index` [B] as windows from their first frame, padded to the longest of
        them: mask [B, T] of real frames, {key: [B, T, ...]}, and their task indices [B]."""
        episode_index = episode_index.reshape(-1).long().to(self.start.device)
        if bool((episode_index >= self.length.shape[0]).any()) or bool((self.length[episode_index] == 0).any()):
            raise ValueError("The batch holds an episode that the policy's episode memory does not: was the policy "
                             "built from another dataset than the one it trains on?")
        length = self.length[episode_index]
        steps = torch.arange(int(length.max()), device=length.device)
        mask = steps < length[:, None]
        rows = self.start[episode_index, None] + torch.minimum(steps, length[:, None] - 1)
        return mask, {key: value[rows] for key, value in self.frames.items()}, self.task_index[episode_index]


def _column_numpy(column: pa.ChunkedArray) -> np.ndarray:
    """A column as numpy; list columns (vector features) become [rows, size]."""
    column = column.combine_chunks()
    if pa.types.is_fixed_size_list(column.type) or pa.types.is_list(column.type):
        # LeRobot's own writer stores vectors as variable-size lists of one size; this project's, fixed-size.
        return column.flatten().to_numpy(zero_copy_only=False).reshape(len(column), -1)
    return column.to_numpy(zero_copy_only=False)
