"""Craft as a world of the batched rollouts (`lerobot_policy_ocn.tools.rl.rollouts`: free-run success per task, and each
option alone, and PPO's episodes in `lerobot_policy_ocn.tools.rl.ppo`): fresh maps (one `CraftBatch`, a map seed per
episode: seed, seed+1, ... for each task), and the policy's float actions turned into action indices.
"""

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.lerobot_env import action_indices
from lerobot_policy_ocn.tools.rl import rollouts


def craft_world(mode: str = "paper") -> rollouts.RolloutWorld:
    """Craft for `lerobot_policy_ocn.tools.rl.rollouts` in world mode `mode`: one fresh map per env, from its seed."""

    def new_batch(num_envs: int, reward: str, max_steps: int | None) -> CraftBatch:
        return CraftBatch(num_envs, mode=mode, reward=reward, max_steps=max_steps)

    return rollouts.RolloutWorld(new_batch=new_batch, env_action=action_indices)
