"""`--env.type=dial` for LeRobot's CLIs (`lerobot-eval`, and `lerobot-train` when it evaluates).

As for Craft, LeRobot's default `create_envs` makes `gym.make(gym_id, **gym_kwargs)` vector envs
from our gymnasium registration (`envs`). `lerobot-eval` always renders its first episodes into
videos, which needs an OpenGL backend for MuJoCo: run it with `MUJOCO_GL=egl` (or `osmesa`).
"""

from dataclasses import dataclass, field

from lerobot.configs import PolicyFeature
from lerobot.envs.configs import EnvConfig

from lerobot_policy_ocn.envs import DIAL_LEROBOT_ENV_ID
from lerobot_policy_ocn.envs.dial.batch import OBS_DIM
from lerobot_policy_ocn.envs.dial.env import FPS
from lerobot_policy_ocn.envs.dial.scene import N_JOINTS
from lerobot_policy_ocn.envs.lerobot_env import StateEnvConfig, state_action_features


@EnvConfig.register_subclass("dial")
@dataclass
class DialEnvConfig(StateEnvConfig):
    """One Dial PIN (`task`, e.g. "12"; `None` draws a random `pin_length`-digit PIN from `digits`
    at every reset) dialled from a random start pose.

    `max_steps=None` keeps the env's own limit (150 steps per digit).
    """

    task: str | None = "12"
    reward: str = "dense"
    max_steps: int | None = None
    digits: str = "1,2,4,8"
    pin_length: int = 2
    fps: int = FPS
    render_mode: str = "rgb_array"
    features: dict[str, PolicyFeature] = field(default_factory=lambda: state_action_features(OBS_DIM, N_JOINTS))

    @property
    def gym_id(self) -> str:
        return DIAL_LEROBOT_ENV_ID

    @property
    def gym_kwargs(self) -> dict:
        return {
            "task": self.task,
            "reward": self.reward,
            "max_steps": self.max_steps,
            "digits": self.digits,
            "pin_length": self.pin_length,
            "render_mode": self.render_mode,
        }
