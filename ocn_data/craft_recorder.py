"""Record the Craft expert (see lerobot_policy_ocn.ocn_data.recorder for the machinery).

Tasks are queued interleaved (AC, CD, DA, AC, ...) so any prefix of the recording, and so the
validation split at its end, holds every task equally.

DART noise (Laskey et al. 2017): with probability `dart_noise` per step the env executes a uniformly
drawn action instead of the expert's, while the dataset keeps the expert's action as the label. The
demonstrations then visit states just off the expert's path, each labelled with the way back, which
a cloned policy needs once its own small errors take it there. `record_demos` records with
`CRAFT_DART_NOISE` unless told otherwise: OCN's Craft recipe was measured on such demonstrations.
"""

from __future__ import annotations

import numpy as np

from lerobot_policy_ocn.envs.craft import N_ACTIONS, CraftBatch, CraftExpert
from lerobot_policy_ocn.envs.craft.observation import OBS_DIM, OBS_NAMES
from lerobot_policy_ocn.envs.craft.render import render_live
from lerobot_policy_ocn.envs.craft.world import SUBTASK_NAMES, default_max_steps, task_description
from lerobot_policy_ocn.ocn_data.recorder import IMAGE_KEY, LABEL_FEATURES, ExpertRecorder

# The noise `record_demos` records Craft with by default (results/imitation_s1.md).
CRAFT_DART_NOISE = 0.1

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
        dart_noise: float = 0.0,
    ) -> None:
        if not 0.0 <= dart_noise < 1.0:
            raise ValueError(f"dart_noise must be in [0, 1), got {dart_noise}")
        queue = [task for _ in range(episodes_per_task) for task in tasks]
        batch = CraftBatch(max(1, min(batch_size, len(queue))), mode=mode, reward=reward)
        self.expert = CraftExpert(batch)
        self.dart_noise = dart_noise
        # One generator per env slot, seeded by its episode's seed: an episode's noise does not
        # depend on which slot or batch it was recorded in.
        self._noise: list[np.random.Generator | None] = [None] * batch.num_envs
        horizon = max(default_max_steps(len(t)) for t in tasks)
        super().__init__(
            queue, batch, craft_features(), horizon,
            seed=seed, first_attempt=first_attempt, video=video, max_failures=max_failures,
        )

    def _reset(self, slots: np.ndarray, seeds: list[int], tasks: list[tuple[int, ...]]) -> None:
        self.batch.reset(seeds=seeds, tasks=tasks, env_ids=slots)
        for slot, seed in zip(slots.tolist(), seeds, strict=True):
            self._noise[slot] = np.random.default_rng(seed)

    def _act(self) -> tuple[np.ndarray, np.ndarray]:
        action = self.expert.act()
        if not self.dart_noise:
            return action, action
        executed = action.copy()
        for slot in np.flatnonzero(self.active).tolist():
            rng = self._noise[slot]
            if rng.random() < self.dart_noise:
                executed[slot] = rng.integers(N_ACTIONS)
        return action, executed

    def _describe(self, task: tuple[int, ...]) -> str:
        return task_description(task)

    def _render(self) -> np.ndarray:
        return render_live(self.batch)
