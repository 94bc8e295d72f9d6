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

Image features are decoded here once, with LeRobot's own decoders (`decode_video_frames` for video
features, the `datasets` Image feature that LeRobot's parquet files use for image features), shrunk
to the policy's input size (`fit_frames`) and kept as uint8: a 40 x 40 RGB frame is 4.8 kB, against
77 kB for Craft's 160 x 160 render, so a dataset's frames fit in memory where its decoded video
would not. LeRobot itself still decodes the image of every frame it samples for the batch (it loads
every feature of the dataset), which the policy does not read.
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
from torch.nn import functional as F

EPISODE_INDEX = "episode_index"
TASK_INDEX = "task_index"
TIMESTAMP = "timestamp"


def fit_frames(frames: Tensor, size: int) -> Tensor:
    """Images [..., C, H, W] (uint8 0-255, or floats in [0, 1] as LeRobot's env pipeline gives them) as
    uint8 [..., C, size, size]. Area averaging: Craft's 160-px render of 16-px tiles becomes 4 px a
    tile at 40, each pixel the mean of a 4 x 4 block. The memory and the policy's inputs at inference
    both pass through here, so a frame reads the same in training and when acting."""
    if frames.dtype == torch.uint8 and tuple(frames.shape[-2:]) == (size, size):
        return frames
    pixels = frames.float() if frames.dtype == torch.uint8 else frames.float() * 255.0
    lead = pixels.shape[:-3]
    pixels = pixels.reshape(-1, *pixels.shape[-3:])
    if tuple(pixels.shape[-2:]) != (size, size):
        pixels = F.interpolate(pixels, size=(size, size), mode="area")
    return pixels.round().clamp(0, 255).to(torch.uint8).reshape(*lead, *pixels.shape[-3:])


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
    def read(cls, root: str | Path, keys: list[str], images: dict[str, int] | None = None) -> EpisodeMemory:
        """The columns `keys` of every episode of the LeRobot dataset at `root`, and each image feature of
        `images` ({key: size}) as uint8 frames [F, C, size, size] (`read_images`). Where the dataset names a
        "train" split in `meta/info.json` (LeRobot's `splits`), only its episodes are trainable: the others
        are held out for evaluation, as `record_demos` writes them."""
        root = Path(root)
        table = read_table(root, [*keys, *(images or {})])
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
        frames |= {key: read_images(root, table, key, size) for key, size in (images or {}).items()}
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


def read_table(root: Path, keys: list[str]) -> pa.Table:
    """The parquet columns of `keys` (a video feature has none: its timestamps are read instead) with each
    frame's episode, task and timestamp, in episode order (a stable sort: frames keep their order)."""
    files = sorted((Path(root) / "data").glob("*/*.parquet"))
    if not files:
        raise FileNotFoundError(f"{root} has no data files under data/: is it a LeRobot dataset?")
    stored = set(pq.read_schema(files[0]).names)
    columns = list(dict.fromkeys([*(key for key in keys if key in stored), EPISODE_INDEX, TASK_INDEX, TIMESTAMP]))
    table = pa.concat_tables(pq.read_table(file, columns=columns) for file in files)
    return table.take(pc.sort_indices(table, sort_keys=[(EPISODE_INDEX, "ascending")]))


def read_images(root: Path, table: pa.Table, key: str, size: int) -> Tensor:
    """The frames of image feature `key` for the rows of `table` (`read_table`'s), as uint8 [F, C, size,
    size] (`fit_frames`), decoded by LeRobot's own readers: a video feature through
    `lerobot.datasets.video_utils.decode_video_frames`, one call per episode at its frames' timestamps
    (shifted by the episode's start in its video file, as LeRobot's loader does); an image feature
    (PNG bytes in the parquet file) through the `datasets` Image feature LeRobot stores it with."""
    info = json.loads((Path(root) / "meta" / "info.json").read_text())
    if info["features"][key]["dtype"] == "video":
        return _read_video(Path(root), table, key, size, info["fps"])
    from datasets import Image

    decoder, mode = Image(), IMAGE_MODES[image_channels(info["features"][key])]
    out = []
    for cell in table[key].to_pylist():
        picture = np.asarray(decoder.decode_example(cell).convert(mode))
        picture = picture[:, :, None] if picture.ndim == 2 else picture
        out.append(fit_frames(torch.from_numpy(picture.copy()).permute(2, 0, 1), size))
    return torch.stack(out)


# PIL modes of images of 1, 3 and 4 channels.
IMAGE_MODES = {1: "L", 3: "RGB", 4: "RGBA"}


def image_channels(feature: dict) -> int:
    """Channels of an image or video feature of `meta/info.json` (LeRobot stores (height, width, channels))."""
    shape, names = list(feature["shape"]), list(feature.get("names") or [])
    return int(shape[0] if names[:1] in (["channels"], ["channel"]) else shape[-1])


def _read_video(root: Path, table: pa.Table, key: str, size: int, fps: float) -> Tensor:
    """`read_images` of a video feature: one LeRobot decode per episode, shrunk at once."""
    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
    from lerobot.datasets.video_utils import decode_video_frames

    meta = LeRobotDatasetMetadata("local/episode_memory", root=root)
    episode = table[EPISODE_INDEX].to_numpy()
    timestamps = table[TIMESTAMP].to_numpy()
    ids, first, counts = np.unique(episode, return_index=True, return_counts=True)
    out = []
    for e, start, count in zip(ids.tolist(), first.tolist(), counts.tolist(), strict=True):
        offset = float(meta.episodes[e][f"videos/{key}/from_timestamp"])
        query = [offset + float(t) for t in timestamps[start : start + count]]
        frames = decode_video_frames(root / meta.get_video_file_path(e, key), query, tolerance_s=0.5 / fps,
                                     return_uint8=True)
        out.append(fit_frames(frames, size))
    return torch.cat(out)


def _column_numpy(column: pa.ChunkedArray) -> np.ndarray:
    """A column as numpy; list columns (vector features) become [rows, size]."""
    column = column.combine_chunks()
    if pa.types.is_fixed_size_list(column.type) or pa.types.is_list(column.type):
        # LeRobot's own writer stores vectors as variable-size lists of one size; this project's, fixed-size.
        return column.flatten().to_numpy(zero_copy_only=False).reshape(len(column), -1)
    return column.to_numpy(zero_copy_only=False)
