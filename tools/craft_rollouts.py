"""Craft as a world of the batched rollouts (`tools.rollouts`: free-run success per task, and each
option alone): fresh maps (one `CraftBatch`, a map seed per episode: seed, seed+1, ... for each
task), and the policy's float actions turned into action indices.
"""

from collections.abc import Sequence

import numpy as np

from envs.craft.batch import CraftBatch
from envs.craft.lerobot_env import action_indices
from tools import rollouts


def craft_world(mode: str = "paper") -> rollouts.RolloutWorld:
    """Craft for `tools.rollouts`: one fresh map per env, from its seed."""

    def start(tasks: Sequence[str], seeds: Sequence[int]) -> tuple[CraftBatch, np.ndarray]:
        craft = CraftBatch(len(tasks), mode=mode, reward="sparse")
        return craft, craft.reset(seeds=seeds, tasks=tasks)

    return rollouts.RolloutWorld(start=start, env_action=action_indices)

