"""Reading an `ocn-view` .rrd back with rerun's own reader, for the tests of every world's recording."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np


def read_rrd(path: Path) -> tuple[dict[str, dict[str, list]], dict[str, dict[str, list]]]:
    """(temporal, static): per entity path, each column's values over all chunks; temporal rows
    are sorted by frame."""
    from rerun.experimental import RrdReader

    temporal: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    static: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    for chunk in RrdReader(path).store().stream():
        columns = (static if chunk.is_static else temporal)[chunk.entity_path]
        for name, rows in chunk.to_record_batch().to_pydict().items():
            columns[name] += rows
    for columns in temporal.values():
        order = np.argsort(columns["frame"], kind="stable")
        for name in columns:
            columns[name] = [columns[name][i] for i in order]
    return temporal, static


def values(column: list) -> list:
    """A component column holds one batch per row; every batch here has one value."""
    assert all(len(batch) == 1 for batch in column)
    return [batch[0] for batch in column]


def forward_fill(frames: list[int], states: list[str], total: int) -> list[str]:
    """The state in force at each frame 0..total-1 of a state-change lane."""
    at = np.searchsorted(np.asarray(frames), np.arange(total), side="right") - 1
    return [states[i] for i in at]
