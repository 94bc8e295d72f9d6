"""Small helpers shared by the batch simulators (`CraftBatch`, `DialBatch`) for partial resets."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def reset_ids(num_envs: int, env_ids: Sequence[int] | np.ndarray | None, **per_env: Sequence | None) -> np.ndarray:
    """The env indices a reset selects (default: all); each given per-env list must match them in length."""
    ids = np.arange(num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
    for name, values in per_env.items():
        if values is not None and len(values) != len(ids):
            raise ValueError(f"got {len(values)} {name} for {len(ids)} envs")
    return ids


def env_rng(current: np.random.Generator | None, seed: int | None) -> np.random.Generator:
    """An env's Generator after a reset: reseeded when a seed is given, else continued (or fresh)."""
    if seed is not None or current is None:
        return np.random.default_rng(None if seed is None else int(seed))
    return current
