"""Per-frame option labels of a recording's episodes, stored beside it as an .npz.

`tools.affine_segmentation` writes them without reading the subtask labels; `tools.fast_imitation
--option-labels` and a labelled packed view (`ocn_data.packed_view --option-labels`, for `lerobot-train
--policy.taught_options=true`) teach them to OCN. The file holds each labelled episode's index and
length and the labels of all its frames, concatenated, so that a reader can tell a file written for
another recording.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np


def write_labels(path: Path, episodes: Any, labels: np.ndarray) -> None:
    """Write the labels [E, T] of `episodes` (an `ocn_data.episodes_table.EpisodeArrays`), padding dropped."""
    path.parent.mkdir(parents=True, exist_ok=True)
    flat = np.concatenate([labels[row, :length] for row, length in enumerate(episodes.lengths)])
    np.savez_compressed(path, episode_index=episodes.episode_index, lengths=episodes.lengths, labels=flat)


def read_labels(path: Path, episode_index: np.ndarray, lengths: np.ndarray, width: int,
                unlabelled_ok: bool = False) -> np.ndarray:
    """The labels of the given episodes, [E, width], -1 past each episode's end (an episode longer than
    `width` keeps its first `width` frames). An episode whose length differs from the file's is a
    ValueError naming it; so is one the file lacks, unless `unlabelled_ok` (its row is then all -1)."""
    stored = np.load(path)
    offsets = np.r_[0, np.cumsum(stored["lengths"])]
    where = {int(index): row for row, index in enumerate(stored["episode_index"])}
    out = np.full((len(episode_index), width), -1, dtype=np.int64)
    for row, (index, length) in enumerate(zip(episode_index.tolist(), lengths.tolist(), strict=True)):
        if index not in where:
            if unlabelled_ok:
                continue
            raise ValueError(f"{path} has no labels for episode {index}; label the same dataset's training split.")
        stored_row = where[index]
        if stored["lengths"][stored_row] != length:
            raise ValueError(f"{path} labels {stored['lengths'][stored_row]} frames of episode {index}, "
                             f"which has {length}; were they written for another recording?")
        kept = min(length, width)
        out[row, :kept] = stored["labels"][offsets[stored_row]:offsets[stored_row] + kept]
    return out


def labels_fingerprint(path: Path) -> str:
    """SHA-256 of the label file, so that a view made from other labels is remade."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
