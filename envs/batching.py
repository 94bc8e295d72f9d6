"""What the batch simulators (`CraftBatch`, `DialBatch`) share: partial-reset helpers and the
per-env episode bookkeeping (`EpisodeBatch`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

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


class EpisodeBatch:
    """Per-env episode bookkeeping that every batch simulator keeps the same way: the task table
    (one row of subtask ids per env, padded with -1), progress through it, step counts and limits,
    done flags and per-env Generators. A world subclasses it and adds its own physics and rules."""

    def __init__(self, num_envs: int, reward: str, rewards: Sequence[str], max_steps: int | None) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if reward not in rewards:
            raise ValueError(f"unknown reward {reward!r}; valid rewards: {', '.join(rewards)}")
        if max_steps is not None and max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.num_envs = num_envs
        self.reward = reward
        self.max_steps_override = max_steps
        self.tasks = np.full((num_envs, 1), -1, dtype=np.int64)
        self.task_len = np.zeros(num_envs, dtype=np.int64)
        self.progress = np.zeros(num_envs, dtype=np.int64)
        self.t = np.zeros(num_envs, dtype=np.int64)
        self.max_steps = np.zeros(num_envs, dtype=np.int64)
        # Envs start done: they must be reset (which also gives them a task) before stepping.
        self.done = np.ones(num_envs, dtype=bool)
        self.rngs: list[np.random.Generator | None] = [None] * num_envs
        self._arange = np.arange(num_envs)

    def _store_tasks(
        self, ids: np.ndarray, tasks: Sequence[Sequence[int]], default_max_steps: Callable[[int], int], spare: int = 0
    ) -> None:
        """Write envs `ids`' tasks into the table, growing it when a longer task arrives; `spare`
        extra -1 columns stay after the longest task (a "finished" entry that `progress` may index).
        Each env's step limit is the override or `default_max_steps` of its task's length."""
        longest = max(len(task) for task in tasks) + spare
        if longest > self.tasks.shape[1]:
            grown = np.full((self.num_envs, longest), -1, dtype=np.int64)
            grown[:, : self.tasks.shape[1]] = self.tasks
            self.tasks = grown
        self.tasks[ids] = -1
        for i, task in zip(ids.tolist(), tasks, strict=True):
            self.tasks[i, : len(task)] = task
            self.task_len[i] = len(task)
            self.max_steps[i] = self.max_steps_override or default_max_steps(len(task))

    def _restart(self, ids: np.ndarray) -> None:
        """Envs `ids` begin a new episode of their stored task."""
        self.progress[ids] = 0
        self.t[ids] = 0
        self.done[ids] = False

    def _advance(
        self, sub_done: np.ndarray, active: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Count one step of the `active` envs, of which `sub_done` completed their current subtask:
        progress, termination at the task's end, truncation at the step limit. Returns the dense or
        sparse reward, terminated, truncated and the info every world reports."""
        sub_index = self.progress
        self.progress = sub_index + sub_done
        success = self.progress == self.task_len
        terminated = sub_done & success
        self.t = self.t + active
        truncated = (self.t >= self.max_steps) & ~terminated & active
        self.done = self.done | terminated | truncated
        reward = (sub_done if self.reward == "dense" else terminated).astype(np.float32)
        info = {
            "subtask_index": sub_index,
            "subtask_done": sub_done,
            "progress": self.progress.copy(),
            "is_success": success,
        }
        return reward, terminated, truncated, info

    def task_of(self, env_id: int) -> tuple[int, ...]:
        """One env's task as subtask ids."""
        return tuple(self.tasks[env_id, : self.task_len[env_id]].tolist())
