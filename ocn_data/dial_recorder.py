"""Record the Dial expert (see lerobot_policy_ocn.ocn_data.recorder for the machinery).

The queue holds either random PINs (`pin_length` digits from `digits`, drawn from the recording
seed and the session's first attempt, so a resumed session draws new ones) or given PINs
interleaved like Craft's tasks. Each episode's seed sets its start pose and its DART noise; the
dataset stores the expert's clean control as `action` and the executed (noisy) control is not
kept, as DART prescribes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lerobot_policy_ocn.envs.dial import DialBatch, DialExpert
from lerobot_policy_ocn.envs.dial.batch import OBS_DIM
from lerobot_policy_ocn.envs.dial.env import FPS
from lerobot_policy_ocn.envs.dial.expert import NOISE_LEVELS
from lerobot_policy_ocn.envs.dial.scene import JOINTS, N_JOINTS
from lerobot_policy_ocn.envs.dial.task import SUBTASK_NAMES, default_max_steps, sample_pin, task_description
from lerobot_policy_ocn.ocn_data.recorder import LABEL_FEATURES, ExpertRecorder

__all__ = ["FPS", "DialRecorder", "dial_features", "dial_state_names", "random_pins"]


def dial_state_names() -> list[str]:
    """Names of the 39 state entries: joint angles, then `key<d>_<axis>` fingertip offsets."""
    offsets = [f"key{d}_{axis}" for d in range(10) for axis in "xyz"]
    return [f"q_{name}" for name in JOINTS] + offsets


def dial_features() -> dict[str, dict]:
    """LeRobot features of a Dial demonstration dataset (`subtask.*`: ground truth, evaluation only)."""
    return {
        "observation.state": {"dtype": "float32", "shape": (OBS_DIM,), "names": dial_state_names()},
        "action": {"dtype": "float32", "shape": (N_JOINTS,), "names": [f"u_{name}" for name in JOINTS]},
        **LABEL_FEATURES,
    }


def random_pins(count: int, length: int, digits: Sequence[int], seed: int, first_attempt: int) -> list[tuple[int, ...]]:
    """`count` random PINs for one recording session."""
    rng = np.random.default_rng([seed, first_attempt, 2])
    return [sample_pin(rng, length, digits) for _ in range(count)]


class DialRecorder(ExpertRecorder):
    """Collects one successful expert episode per queued PIN, chunk by chunk."""

    world = "Dial"
    subtask_names = SUBTASK_NAMES

    def __init__(
        self,
        pins: list[tuple[int, ...]],
        *,
        reward: str = "dense",
        noise_levels: Sequence[float] = NOISE_LEVELS,
        seed: int = 0,
        first_attempt: int = 0,
        batch_size: int = 64,
        max_failures: int = 1000,
    ) -> None:
        batch = DialBatch(max(1, min(batch_size, len(pins))), reward=reward)
        self.expert = DialExpert(batch, noise_levels)
        horizon = max(default_max_steps(len(p)) for p in pins)
        super().__init__(
            pins, batch, dial_features(), horizon, seed=seed, first_attempt=first_attempt, max_failures=max_failures
        )

    def _reset(self, slots: np.ndarray, seeds: list[int], tasks: list[tuple[int, ...]]) -> None:
        self.batch.reset(seeds=seeds, tasks=tasks, env_ids=slots)
        self.expert.reset(slots, seeds)

    def _act(self) -> tuple[np.ndarray, np.ndarray]:
        clean = self.expert.act()
        return clean, self.expert.perturb(clean)

    def _describe(self, task: tuple[int, ...]) -> str:
        return task_description(task)
