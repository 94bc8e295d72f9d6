"""Per-episode and whole-chunk feature statistics in LeRobot's stats format, vectorised.

LeRobot's own `save_episode()` computes each episode's statistics one episode at a time through a
histogram-based running estimator, which costs a large part of a second per short episode. Here
all episodes of a chunk are reduced at once: min/max/mean/std with segment reductions, and exact
quantiles by stacking the episodes that share a length into one array and calling `np.quantile`
once per length. The result has the same keys, shapes and dtypes as LeRobot's
(`min, max, mean, std, count, q01, q10, q50, q90, q99`, vectors of the feature's width).
"""

from __future__ import annotations

import numpy as np

QUANTILES: tuple[float, ...] = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_KEYS: tuple[str, ...] = tuple(f"q{int(q * 100):02d}" for q in QUANTILES)
STAT_KEYS: tuple[str, ...] = ("min", "max", "mean", "std", "count", *QUANTILE_KEYS)


def _as_2d(values: np.ndarray) -> np.ndarray:
    """Frames x dims view of a column (a scalar-per-frame column becomes one dim)."""
    return values.reshape(len(values), -1).astype(np.float64, copy=False)


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
        rows = starts[episodes, None] + np.arange(length)[None, :]
        quantiles[:, episodes, :] = np.quantile(x[rows], QUANTILES, axis=1)
    for key, q in zip(QUANTILE_KEYS, quantiles, strict=True):
        out[key] = q
    return out


def pooled_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """Statistics of one feature over all frames of a chunk (exact quantiles)."""
    x = _as_2d(values)
    out = {
        "min": x.min(axis=0),
        "max": x.max(axis=0),
        "mean": x.mean(axis=0),
        "std": x.std(axis=0),
        "count": np.array([len(x)]),
    }
    for key, q in zip(QUANTILE_KEYS, np.quantile(x, QUANTILES, axis=0), strict=True):
        out[key] = q
    return out
