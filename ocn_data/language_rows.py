"""Ground-truth subtask segments as LeRobot 0.6's native language annotation columns.

`lerobot-annotate` stores an episode's subtask segmentation in `language_persistent`: one row
per segment (role "assistant", style "subtask", the subtask text, the segment's start time),
the same list repeated on every frame of the episode, plus an empty `language_events` list per
frame. We build both columns as Arrow arrays directly, without a Python object per frame.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from lerobot.datasets.language import language_event_row_arrow_type, language_persistent_row_arrow_type


def persistent_column(segments: list[list[tuple[int, str]]], lengths: np.ndarray, fps: int) -> pa.ListArray:
    """`language_persistent` for consecutive episodes: every frame lists its episode's segments."""
    lengths = np.asarray(lengths, dtype=np.int64)
    per_episode = np.array([len(s) for s in segments], dtype=np.int64)
    contents = [name for episode in segments for _, name in episode]
    starts = np.array([start for episode in segments for start, _ in episode], dtype=np.float64)
    n_rows = len(contents)
    row_type = language_persistent_row_arrow_type()
    rows = pa.StructArray.from_arrays(
        [
            pa.array(["assistant"] * n_rows, pa.string()),
            pa.array(contents, pa.string()),
            pa.array(["subtask"] * n_rows, pa.string()),
            pa.array((starts / fps).astype(np.float32), pa.float32()),
            pa.nulls(n_rows, pa.string()),
            pa.nulls(n_rows, row_type.field("tool_calls").type),
        ],
        fields=list(row_type),
    )
    first_row = np.concatenate(([0], np.cumsum(per_episode)[:-1]))
    rows_per_frame = np.repeat(per_episode, lengths)
    offsets = np.concatenate(([0], np.cumsum(rows_per_frame)))
    frame_first_row = np.repeat(np.repeat(first_row, lengths), rows_per_frame)
    within = np.arange(offsets[-1]) - np.repeat(offsets[:-1], rows_per_frame)
    taken = rows.take(pa.array(frame_first_row + within))
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), taken)


def empty_events_column(n_frames: int) -> pa.ListArray:
    """`language_events` with an empty list on every frame (demonstrations carry no events)."""
    row_type = language_event_row_arrow_type()
    empty = pa.StructArray.from_arrays([pa.nulls(0, f.type) for f in row_type], fields=list(row_type))
    return pa.ListArray.from_arrays(pa.array(np.zeros(n_frames + 1, dtype=np.int32)), empty)
