"""Per-episode and whole-chunk feature statistics, by LeRobot's own definitions, vectorised.

LeRobot's `save_episode()` reduces each episode through `RunningQuantileStats`: min/max/mean/std, and
quantiles read off a 5,000-bin histogram spanning the episode's range, interpolated within the bin. A
dataset's statistics are `aggregate_stats` of its episodes' (`pooled_stats` calls it): min/max/mean/std
pooled exactly, each quantile the frame-count-weighted mean of the episodes' quantiles. Recording one
episode at a time that way costs a large part of a second per short episode, so here all episodes of a
chunk are reduced at once. The histogram never has to be built: an episode of L frames fills at most L
bins, so sorting the frames' bin numbers gives the cumulative counts the quantile search needs. The
result has LeRobot's keys, shapes and values (`min, max, mean, std, count, q01, q10, q50, q90, q99`).
"""

from __future__ import annotations

import numpy as np
from lerobot.datasets.compute_stats import aggregate_feature_stats

QUANTILES: tuple[float, ...] = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_KEYS: tuple[str, ...] = tuple(f"q{int(q * 100):02d}" for q in QUANTILES)
STAT_KEYS: tuple[str, ...] = ("min", "max", "mean", "std", "count", *QUANTILE_KEYS)
HISTOGRAM_BINS = 5000  # RunningQuantileStats' default
RANGE_PADDING = 1e-10  # the histogram spans [min - padding, max + padding], as LeRobot's does


def _as_2d(values: np.ndarray) -> np.ndarray:
    """Frames x dims view of a column (a scalar-per-frame column becomes one dim)."""
    return values.reshape(len(values), -1).astype(np.float64, copy=False)


def _histogram_quantiles(x: np.ndarray) -> np.ndarray:
    """LeRobot's histogram quantiles of each episode of equal length: x [episodes, L, dims] ->
    [quantiles, episodes, dims]."""
    low = x.min(axis=1, keepdims=True) - RANGE_PADDING
    width = (x.max(axis=1, keepdims=True) + RANGE_PADDING - low) / HISTOGRAM_BINS
    bins = np.clip(np.floor((x - low) / width), 0, HISTOGRAM_BINS - 1)
    # Half-open bins [edge_b, edge_b+1), as np.histogram places a value that the division rounds over.
    bins -= (bins > 0) & (x < low + bins * width)
    bins += (bins < HISTOGRAM_BINS - 1) & (x >= low + (bins + 1) * width)
    bins = np.sort(bins, axis=1)
    length = x.shape[1]
    out = np.empty((len(QUANTILES), x.shape[0], x.shape[2]))
    for i, q in enumerate(QUANTILES):
        target = q * length
        # The first bin whose cumulative count reaches the target, the count below it and in it.
        b = bins[:, int(np.ceil(target)) - 1, :]
        below = (bins < b[:, None, :]).sum(axis=1)
        inside = (bins == b[:, None, :]).sum(axis=1)
        edge = low[:, 0, :] + b * width[:, 0, :]
        out[i] = np.where(b == 0, low[:, 0, :], edge + (target - below) / inside * width[:, 0, :])
    return out


def episode_stats(values: np.ndarray, lengths: np.ndarray) -> dict[str, np.ndarray]:
    """Statistics of each episode of one feature.

    `values` holds the frames of consecutive episodes ([frames, ...]); `lengths` their lengths.
    Returns arrays with a leading episode axis: stats[key][e] is episode e's vector.
    """
    x = _as_2d(values)
    lengths = np.asarray(lengths, dtype=np.int64)
    n_eps, dims = len(lengths), x.shape[1]
    starts = np.concatenate(([0], np.cumsum(lengths)[:-1]))

    sums = np.add.reduceat(x, starts, axis=0)
    mean = sums / lengths[:, None]
    sq_dev = (x - np.repeat(mean, lengths, axis=0)) ** 2
    std = np.sqrt(np.add.reduceat(sq_dev, starts, axis=0) / lengths[:, None])
    out = {
        "min": np.minimum.reduceat(x, starts, axis=0),
        "max": np.maximum.reduceat(x, starts, axis=0),
        "mean": mean,
        "std": std,
        "count": lengths[:, None].copy(),
    }
    quantiles = np.empty((len(QUANTILES), n_eps, dims))
    for length in np.unique(lengths):
        episodes = np.flatnonzero(lengths == length)
        if length < 2:  # LeRobot gives an episode of one frame its mean as every quantile
            quantiles[:, episodes, :] = mean[episodes]
            continue
        rows = starts[episodes, None] + np.arange(length)[None, :]
        quantiles[:, episodes, :] = _histogram_quantiles(x[rows])
    for key, q in zip(QUANTILE_KEYS, quantiles, strict=True):
        out[key] = q
    return out


def pooled_stats(per_episode: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The statistics of a set of episodes, from `episode_stats`' output, pooled by LeRobot's own
    `aggregate_feature_stats` (exact min/max/mean/std, count-weighted mean quantiles)."""
    episodes = [{key: value[e] for key, value in per_episode.items()} for e in range(len(per_episode["count"]))]
    return aggregate_feature_stats(episodes)
