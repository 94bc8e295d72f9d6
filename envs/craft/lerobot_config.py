"""`--env.type=craft` for LeRobot's CLIs (`lerobot-eval`, and `lerobot-train` when it evaluates).

LeRobot's default `create_envs` makes `gym.make(gym_id, **gym_kwargs)` vector envs, importing
`package_name` first if `gym_id` is not registered; pointing both at our gymnasium registration
(`envs`) reuses it as is, sync or async.
"""

from dataclasses import dataclass, field

from lerobot.configs import PolicyFeature
from lerobot.envs.configs import EnvConfig

from lerobot_policy_ocn.envs import CRAFT_LEROBOT_ENV_ID
from lerobot_policy_ocn.envs.craft.observation import OBS_DIM
from lerobot_policy_ocn.envs.lerobot_env import StateEnvConfig, state_action_features


@EnvConfig.register_subclass("craft")
@dataclass
class CraftEnvConfig(StateEnvConfig):
    """One Craft task (subtask letters, a named task or a description) evaluated from its start state.

    `max_steps=None` keeps the env's own limit (64 steps up to two subtasks, else 100). Videos are
    on by default because `lerobot-eval` always renders its first episodes.
    """

    task: str = "AC"
    mode: str = "paper"
    reward: str = "dense"
    max_steps: int | None = None
    fps: int = 10
    render_mode: str = "rgb_array"
    features: dict[str, PolicyFeature] = field(default_factory=lambda: state_action_features(OBS_DIM, 1))

    @property
    def gym_id(self) -> str:
        return CRAFT_LEROBOT_ENV_ID

    @property
    def gym_kwargs(self) -> dict:
        return {
            "task": self.task,
            "mode": self.mode,
            "reward": self.reward,
            "max_steps": self.max_steps,
            "render_mode": self.render_mode,
        }
