"""Configuration of the Option-Controller Network (OCN) policy, registered with LeRobot as `ocn`."""

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.optim import AdamConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from envs.craft.observation import OBS_DIM as CRAFT_STATE_DIM

OBS_ENCODERS = ("craft", "identity")
ACTION_TYPES = ("discrete", "continuous")
WINDOW_STARTS = ("episode", "any")
INFERENCE_MODES = ("sample", "greedy")
EXECUTIONS = ("soft", "hard")


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"`{name}` must be one of {choices}, got {value!r}.")


@PreTrainedConfig.register_subclass("ocn")
@dataclass
class OCNConfig(PreTrainedConfig):
    """Hyperparameters of OCN (paper section 3, appendix A.2) plus the LeRobot plumbing.

    Training windows: LeRobot's sampler starts a window at every frame of every episode and clamps
    offsets that leave the episode, flagging them in `*_is_pad`. `window_start` says how OCN turns
    such a window into a training sequence:
    - "episode" (default): the window reaches `window_size - 1` frames either side of the sampled
      frame, so it always holds its whole episode when episodes are at most `window_size` frames
      long (checked against the dataset when the policy is built). The policy shifts each window to
      its first real frame, so every sampled frame trains on its whole episode from t = 1 with the
      task's initial controller state: the paper's setting, and no window starts mid-episode.
    - "any": the window is the `window_size` frames from the sampled frame on, and its first frame
      is treated as t = 1 of a fresh episode. Half the frames to load, but the controller is told
      that a task restarts where it does not.
    Both average the NLL over each window's real frames first, then over windows: sampling windows
    at every frame weights an episode by its length, so this is the per-frame mean NLL of the
    dataset in expectation.

    `skip_long_episodes` (with "episode" windows) trains on datasets whose rare longest episodes
    exceed `window_size` instead of refusing them: a window whose first position is a real frame
    may start mid-episode and is left out of the loss, so an episode longer than `window_size`
    trains on its first `window_size` frames only (from the windows sampled there). The padding
    flags cannot tell a window sampled exactly at frame `window_size - 1` from a later one, so that
    one is left out too. Dial's DART-noised demonstrations are mostly under 100 frames with a tail
    to about 300; a window loads 2 * window_size - 1 frames, so sizing it for the tail would
    nearly triple LeRobot's loading cost for a few episodes.
    """

    n_options: int = 3
    hidden_size: int = 128
    mlp_hidden_size: int = 128
    mlp_depth: int = 2
    temperature: float = 10.0

    window_size: int = 32
    window_start: str = "episode"
    skip_long_episodes: bool = False

    obs_encoder: str = "craft"
    action_type: str = "discrete"
    n_actions: int = 5
    log_std_min: float = -5.0
    log_std_max: float = 2.0

    # Task strings in task-index order; filled from the dataset's metadata when the policy is built.
    tasks: list[str] = field(default_factory=list)

    inference_mode: str = "sample"
    # How `select_action` runs the hierarchy. "soft": the differentiable eq. 17 mixture that training
    # uses. "hard": the option-level semantics of the RL phase (appendix A.1): the controller samples
    # one option, which acts alone until its sampled termination fires, then the controller (whose
    # state advances only at these decisions) samples the next one, which restarts from h^o_0.
    # `forward` and `parse` are the soft recurrence in both cases.
    execution: str = "soft"

    optimizer_lr: float = 1e-3
    # The controller's learning rate is optimizer_lr * controller_lr_scale. The paper slows the
    # controller by dividing its logits by T, which also shrinks its gradients; Adam normalises
    # gradient scale away, so this is the way to keep the controller slower under Adam.
    controller_lr_scale: float = 1.0
    optimizer_grad_clip_norm: float = 10.0

    # Empty means "derive from obs_encoder and action_type" (see `__post_init__`).
    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_choice("obs_encoder", self.obs_encoder, OBS_ENCODERS)
        _check_choice("action_type", self.action_type, ACTION_TYPES)
        _check_choice("window_start", self.window_start, WINDOW_STARTS)
        _check_choice("inference_mode", self.inference_mode, INFERENCE_MODES)
        _check_choice("execution", self.execution, EXECUTIONS)
        if self.n_options < 1 or self.mlp_depth < 1 or self.window_size < 1:
            raise ValueError("n_options, mlp_depth and window_size must all be >= 1.")
        if self.controller_lr_scale <= 0:
            raise ValueError(f"controller_lr_scale must be > 0, got {self.controller_lr_scale}.")
        if self.temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {self.temperature}.")
        if not self.normalization_mapping:
            self.normalization_mapping = self._default_normalization()

    def _default_normalization(self) -> dict[str, NormalizationMode]:
        """Craft states are symbolic ids and discrete actions are indices: neither may be rescaled."""
        state = NormalizationMode.IDENTITY if self.obs_encoder == "craft" else NormalizationMode.MEAN_STD
        action = NormalizationMode.IDENTITY if self.action_type == "discrete" else NormalizationMode.MEAN_STD
        return {"STATE": state, "ACTION": action}

    @property
    def observation_delta_indices(self) -> list[int]:
        if self.window_start == "episode":
            return list(range(1 - self.window_size, self.window_size))
        return list(range(self.window_size))

    @property
    def action_delta_indices(self) -> list[int]:
        return self.observation_delta_indices

    @property
    def reward_delta_indices(self) -> None:
        return None

    @property
    def action_dim(self) -> int:
        """Width of one action in the batch: 1 index for discrete actions, the vector size otherwise."""
        return self.output_features[ACTION].shape[0]

    @property
    def state_dim(self) -> int:
        return self.input_features[OBS_STATE].shape[0]

    def get_optimizer_preset(self) -> AdamConfig:
        return AdamConfig(lr=self.optimizer_lr, grad_clip_norm=self.optimizer_grad_clip_norm)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        state = (self.input_features or {}).get(OBS_STATE)
        if state is None or state.type is not FeatureType.STATE:
            raise ValueError(f"OCN needs a `{OBS_STATE}` STATE input feature.")
        action = (self.output_features or {}).get(ACTION)
        if action is None:
            raise ValueError(f"OCN needs an `{ACTION}` output feature.")
        if self.obs_encoder == "craft" and tuple(state.shape) != (CRAFT_STATE_DIM,):
            raise ValueError(
                f"The craft encoder expects a compact state of shape ({CRAFT_STATE_DIM},), got {state.shape}; "
                "float states (Dial) take --policy.obs_encoder=identity."
            )
        if self.action_type == "discrete" and tuple(action.shape) != (1,):
            raise ValueError(
                f"Discrete actions must be stored as one index, shape (1,); got {action.shape}: "
                "vector actions (Dial's motor controls) take --policy.action_type=continuous."
            )
        if self.action_type == "discrete" and self.n_actions < 2:
            raise ValueError(f"n_actions must be >= 2 for discrete actions, got {self.n_actions}.")
