"""Record the Craft expert (see ocn_data.recorder for the machinery).

Tasks are queued interleaved (AC, CD, DA, AC, ...) so any prefix of the recording, and so the
validation split at its end, holds every task equally.
"""

from __future__ import annotations

import numpy as np

from envs.craft import CraftBatch, CraftExpert
from envs.craft.observation import OBS_DIM, OBS_NAMES
from envs.craft.render import render_batch
from envs.craft.world import SUBTASK_NAMES, default_max_steps, task_description
from ocn_data.recorder import IMAGE_KEY, LABEL_FEATURES, ExpertRecorder

FPS = 10


def craft_features(image_shape: tuple[int, int, int] | None = None) -> dict[str, dict]:
    """LeRobot features of a Craft demonstration dataset.

    `subtask.*` columns are ground truth for evaluation only: their names do not start with
    `observation.`, so LeRobot's processors never hand them to a policy.
    """
    features = {
        "observation.state": {"dtype": "int64", "shape": (OBS_DIM,), "names": list(OBS_NAMES)},
        "action": {"dtype": "int64", "shape": (1,), "names": ["action"]},
        **LABEL_FEATURES,
    }
    if image_shape is not None:
        features[IMAGE_KEY] = {"dtype": "video", "shape": image_shape, "names": ["height", "width", "channels"]}
    return features


class CraftRecorder(ExpertRecorder):
    """Collects `episodes_per_task` successful expert episodes of each task, chunk by chunk."""

    world = "Craft"
    subtask_names = SUBTASK_NAMES

    def __init__(
        self,
        tasks: list[tuple[int, ...]],
        episodes_per_task: int,
        *,
        mode: str = "paper",
        reward: str = "dense",
        seed: int = 0,
        first_attempt: int = 0,
        batch_size: int = 256,
        video: bool = False,
        max_failures: int = 1000,
    ) -> None:
        queue = [task for _ in range(episodes_per_task) for task in tasks]
        batch = CraftBatch(max(1, min(batch_size, len(queue))), mode=mode, reward=reward)
        self.expert = CraftExpert(batch)
        horizon = max(default_max_steps(len(t)) for t in tasks)
        super().__init__(
            queue, batch, craft_features(), horizon,
            seed=seed, first_attempt=first_attempt, video=video, max_failures=max_failures,
        )

    def _reset(self, slots: np.ndarray, seeds: list[int], tasks: list[tuple[int, ...]]) -> None:
        self.batch.reset(seeds=seeds, tasks=tasks, env_ids=slots)

    def _act(self) -> tuple[np.ndarray, np.ndarray]:
        action = self.expert.act()
        return action, action

    def _describe(self, task: tuple[int, ...]) -> str:
        return task_description(task)

    def _render(self) -> np.ndarray:
        b = self.batch
        return render_batch(b.grid, b.pos, b.facing)
