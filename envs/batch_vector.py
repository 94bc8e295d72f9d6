"""Gymnasium vector env over a batch simulator (``CraftBatch``, ``DialBatch``), with next-step autoreset.

A batch simulator steps all its envs in one call and exposes ``progress`` and ``task_len`` per env;
this shell adds gymnasium's vector API on top: per-env seeds, partial resets, autoreset on the step
after an episode ends, and infos as dicts of arrays ("subtask_index", "progress", "is_success",
"task" descriptions, plus whatever the batch's own step info holds).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space


class BatchVectorEnv(VectorEnv):
    """Subclasses call ``_setup`` from their ``__init__`` and define ``_parse_task`` and ``_describe``."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP}

    def _setup(self, batch: Any, task: Any, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        """Attach the batch simulator, the per-env spaces and the tasks."""
        self.batch = batch
        self.num_envs = batch.num_envs
        self.single_observation_space = observation_space
        self.single_action_space = action_space
        self.observation_space = batch_space(observation_space, self.num_envs)
        self.action_space = batch_space(action_space, self.num_envs)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self.task_descriptions = np.full(self.num_envs, "", dtype=object)
        self._set_tasks(task)

    def _parse_task(self, task: Any) -> Any:
        """One env's task spec as the batch's ``reset`` takes it."""
        raise NotImplementedError

    def _describe(self, env_id: int) -> str:
        """Language description of env ``env_id``'s current task."""
        raise NotImplementedError

    def _set_tasks(self, task: Any) -> None:
        """One task for all envs or one per env (a list); takes effect at the next reset of each env."""
        tasks = list(task) if isinstance(task, (list, tuple)) else [task] * self.num_envs
        if len(tasks) != self.num_envs:
            raise ValueError(f"got {len(tasks)} tasks for {self.num_envs} envs")
        self.task_specs = [self._parse_task(t) for t in tasks]

    def _reset_envs(self, ids: np.ndarray, seeds: Sequence[int | None] | None) -> np.ndarray:
        obs = self.batch.reset(seeds=seeds, tasks=[self.task_specs[i] for i in ids.tolist()], env_ids=ids)
        for i in ids.tolist():
            self.task_descriptions[i] = self._describe(i)
        self._autoreset[ids] = False
        return obs

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Reset all envs, or those in ``options["reset_mask"]``; env i gets seed ``seed + i``.

        ``seed`` may also be a list with one seed (or None) per env; ``options["task"]`` sets
        new tasks (one for all, or a list with one per env).
        """
        options = options or {}
        if isinstance(seed, (int, np.integer)):
            super().reset(seed=int(seed))
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = [None] * self.num_envs if seed is None else list(seed)
        if "task" in options:
            self._set_tasks(options["task"])
        mask = np.asarray(options.get("reset_mask", np.ones(self.num_envs, dtype=bool)), dtype=bool)
        ids = np.flatnonzero(mask)
        obs = self._reset_envs(ids, [seeds[i] for i in ids.tolist()])
        b = self.batch
        info = {
            "subtask_index": b.progress.copy(),
            "progress": b.progress.copy(),
            "is_success": b.progress == b.task_len,
            "task": self.task_descriptions.copy(),
        }
        return obs, info

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Step all envs; envs that ended on the previous step are reset instead (their action is ignored)."""
        obs, reward, terminated, truncated, info = self.batch.step(actions)
        if self._autoreset.any():
            ids = np.flatnonzero(self._autoreset)
            obs = self._reset_envs(ids, None)
            info["subtask_index"][ids] = 0
            info["progress"][ids] = 0
            info["is_success"][ids] = False
        self._autoreset = terminated | truncated
        info["task"] = self.task_descriptions.copy()
        return obs, reward, terminated, truncated, info
