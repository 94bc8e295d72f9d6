"""A chunk of finished episodes held column-wise, the unit that recorders hand to the writer."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class EpisodeChunk:
    """Consecutive finished episodes, frames of all episodes concatenated in order.

    `columns` maps a dataset feature name to a [frames, ...] array; `tasks` holds each episode's
    task string; `segments` holds, per episode, the (start frame, subtask name) pairs of its
    ground-truth subtask segments; `videos` maps a video feature to its [frames, H, W, 3] uint8
    frames.
    """

    lengths: np.ndarray
    tasks: list[str]
    columns: dict[str, np.ndarray]
    segments: list[list[tuple[int, str]]]
    videos: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.lengths = np.asarray(self.lengths, dtype=np.int64)
        n_frames = int(self.lengths.sum())
        if len(self.tasks) != len(self.lengths) or len(self.segments) != len(self.lengths):
            raise ValueError("EpisodeChunk: tasks, segments and lengths must have one entry per episode")
        for name, values in {**self.columns, **self.videos}.items():
            if len(values) != n_frames:
                raise ValueError(f"EpisodeChunk: column {name!r} has {len(values)} rows, expected {n_frames}")

    @property
    def num_episodes(self) -> int:
        return len(self.lengths)

    @property
    def num_frames(self) -> int:
        return int(self.lengths.sum())

    @property
    def starts(self) -> np.ndarray:
        """Index of each episode's first frame within the chunk."""
        return np.concatenate(([0], np.cumsum(self.lengths)[:-1])).astype(np.int64)
