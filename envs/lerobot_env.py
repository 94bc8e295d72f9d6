"""Our envs as `lerobot-eval` drives them.

LeRobot's rollout reads observations from the `agent_pos` key (-> `observation.state`), sends every
action as a float row of shape (action_dim,), asks each sub-env for `_max_episode_steps` and its
`task_description`, and reads `info["is_success"]`. `LeRobotStateEnv` supplies the first three;
the wrapped env has the others, so its own API stays as it is.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
from gymnasium import spaces
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import FreezeAfterEpisodeEnd
from lerobot.utils.constants import ACTION, OBS_STATE

STATE_KEY = "agent_pos"


def state_action_features(state_dim: int, action_dim: int) -> dict[str, PolicyFeature]:
    """The env features of a state-only env: `agent_pos` (state) and `action` vectors."""
    return {
        ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,)),
        STATE_KEY: PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
    }


@dataclass
class StateEnvConfig(EnvConfig):
    """Base of our `--env.type` configs: state-only envs registered with gymnasium by `lerobot_policy_ocn.envs`
    (the package LeRobot imports when it finds an env's gym id unregistered)."""

    features_map: dict[str, str] = field(default_factory=lambda: {ACTION: ACTION, STATE_KEY: OBS_STATE})

    @property
    def package_name(self) -> str:
        return "lerobot_policy_ocn.envs"


class LeRobotStateEnv(gym.Wrapper):
    """Dict observations {"agent_pos": state}, policy action rows turned into env actions by
    `to_env_action`, and the step limit LeRobot asks for."""

    def __init__(
        self,
        env: gym.Env,
        action_space: spaces.Space,
        max_episode_steps: int,
        to_env_action: Callable[[Any], Any],
    ) -> None:
        super().__init__(env)
        self.observation_space = spaces.Dict({STATE_KEY: env.observation_space})
        self.action_space = action_space
        self._max_episode_steps = max_episode_steps
        self._to_env_action = to_env_action

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        obs, info = self.env.reset(seed=seed, options=options)
        return {STATE_KEY: obs}, info

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(self._to_env_action(action))
        return {STATE_KEY: obs}, reward, terminated, truncated, info


def lerobot_env(
    env: gym.Env,
    action_space: spaces.Space,
    max_episode_steps: int,
    to_env_action: Callable[[Any], Any],
) -> gym.Env:
    """`env` shaped for `lerobot-eval`.

    LeRobot's default vector env autoresets in the same step, so a finished sub-env would start a
    new episode whose first reward `lerobot-eval` still adds to the finished one (its mask keeps
    one step past the first done). LeRobot's `FreezeAfterEpisodeEnd` replays the terminal step
    with reward 0 instead, until the next rollout's reset.
    """
    return FreezeAfterEpisodeEnd(LeRobotStateEnv(env, action_space, max_episode_steps, to_env_action))
