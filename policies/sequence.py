"""What the recurrent policies trained on whole episodes share (`ocn`, `ompn`): the configuration
fields and window plumbing of LeRobot's training loop, the masked loss, and a policy mixin with
LeRobot's constructor and the task table.

Batches arrive as LeRobot builds them: `observation.state` [B, W, S] and `action` [B, W, A] windows
with `*_is_pad` masks [B, W] and the task strings in `batch["task"]`, or from a packed view
(`ocn_data.packed_view`) one row per episode. How a sample becomes a training sequence is
`SequenceConfig.window_start`'s business (see its docstring).
"""

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor

from envs.craft.observation import OBS_DIM as CRAFT_STATE_DIM
from envs.dial import OBS_DIM as DIAL_STATE_DIM
from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.datasets.io_utils import load_episodes
from lerobot.optim import AdamConfig, AdamWConfig
from lerobot.optim.schedulers import CosineAnnealingWithWarmupSchedulerConfig, LRSchedulerConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from ocn_data.packed_view import PACKED_ACTION, PACKED_KEYS, PACKED_LENGTH, PACKED_STATE
from policies.schedules import StepDecaySchedulerConfig

# Encoders of Craft's compact state (see policies/ocn/encoders.py); "identity" takes float states as they
# are (standardised); "dial_keys" reads Dial's raw state and adds each key's log distance.
CRAFT_ENCODERS = ("craft", "craft_full_view")
RAW_STATE_ENCODERS = (*CRAFT_ENCODERS, "dial_keys")
OBS_ENCODERS = (*RAW_STATE_ENCODERS, "identity")
ACTION_TYPES = ("discrete", "continuous")
WINDOW_STARTS = ("episode", "any", "packed")
INFERENCE_MODES = ("sample", "greedy")
LR_SCHEDULES = ("constant", "cosine", "step")
PAD_KEYS = (f"{ACTION}_is_pad", f"{OBS_STATE}_is_pad")


def check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    """A config string must name one of its choices."""
    if value not in choices:
        raise ValueError(f"`{name}` must be one of {choices}, got {value!r}.")


@dataclass
class SequenceConfig(PreTrainedConfig):
    """Fields and LeRobot plumbing of a recurrent policy trained on whole episodes (not registered:
    each policy type subclasses it).

    Training windows: LeRobot's sampler starts a window at every frame of every episode and clamps
    offsets that leave the episode, flagging them in `*_is_pad`. `window_start` says how the policy
    turns such a window into a training sequence:
    - "episode" (default): the window reaches `window_size - 1` frames either side of the sampled
      frame, so it always holds its whole episode when episodes are at most `window_size` frames
      long (checked against the dataset when the policy is built). The policy shifts each window to
      its first real frame, so every sampled frame trains on its whole episode from t = 1 with the
      task's initial state: the paper's setting, and no window starts mid-episode.
    - "any": the window is the `window_size` frames from the sampled frame on, and its first frame
      is treated as t = 1 of a fresh episode. Half the frames to load, but the model is told that a
      task restarts where it does not.
    - "packed": no windows; the dataset is a packed view (`python -m ocn_data.packed_view --width
      window_size`), one row per episode holding all its frames, so LeRobot loads one row per sample
      instead of a window of frames (several times faster, `results/bench_train.md`). The
      preprocessor normalises the packed columns as it does states and actions
      (`policies.ocn.processor_ocn.PackedEpisodeNormalizerStep`), so Dial's standardised states and
      actions train on it too.
    "episode" and "any" average the NLL over each window's real frames first, then over the windows
    that have any: sampling windows at every frame weights an episode by its length, so this is the
    per-frame mean NLL of the dataset in expectation. A packed view's rows are drawn uniformly, one
    per episode, so "packed" averages over the batch's real frames (`batch_mean`): the same mean in
    expectation.

    `skip_long_episodes` (with "episode" windows) trains on datasets whose rare longest episodes
    exceed `window_size` instead of refusing them: a window whose first position is a real frame
    may start mid-episode and is left out of the loss, so an episode longer than `window_size`
    trains on its first `window_size` frames only (from the windows sampled there). The padding
    flags cannot tell a window sampled exactly at frame `window_size - 1` from a later one, so that
    one is left out too. Dial's DART-noised demonstrations are mostly under 100 frames with a tail
    to about 300; a window loads 2 * window_size - 1 frames, so sizing it for the tail would
    nearly triple LeRobot's loading cost for a few episodes.
    """

    # The model's name in error messages.
    model_name: ClassVar[str] = "The policy"

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

    optimizer_lr: float = 1e-3
    optimizer_grad_clip_norm: float = 10.0
    # Decoupled weight decay (AdamW); 0 is the paper's plain Adam.
    optimizer_weight_decay: float = 0.0
    # "constant" is the paper's Adam at a fixed lr; "cosine" anneals every parameter group's lr to 0
    # over `lerobot-train --steps` (no warm-up). On S1, cosine from step 0 keeps OCN's options from
    # splitting (results/imitation_s1_lr_schedule): use it to continue a trained model, if at all.
    # "step" keeps the lr until step `lr_decay_step`, then multiplies it by `lr_decay_factor`: on Dial,
    # memoryless options split at 1e-3 and one seed collapsed there after 3,500 steps, while 1e-4
    # from step 3,000 kept its split (results/dial_memoryless).
    lr_schedule: str = "constant"
    lr_decay_step: int = 0
    lr_decay_factor: float = 0.1

    # Empty means "derive from obs_encoder and action_type" (see `__post_init__`).
    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("obs_encoder", self.obs_encoder, OBS_ENCODERS)
        check_choice("action_type", self.action_type, ACTION_TYPES)
        check_choice("window_start", self.window_start, WINDOW_STARTS)
        check_choice("inference_mode", self.inference_mode, INFERENCE_MODES)
        check_choice("lr_schedule", self.lr_schedule, LR_SCHEDULES)
        if self.lr_schedule == "step" and (self.lr_decay_step < 1 or not 0 < self.lr_decay_factor < 1):
            raise ValueError(
                "lr_schedule='step' needs lr_decay_step >= 1 and 0 < lr_decay_factor < 1, got "
                f"{self.lr_decay_step} and {self.lr_decay_factor}."
            )
        if self.window_size < 1:
            raise ValueError(f"window_size must be >= 1, got {self.window_size}.")
        if self.optimizer_weight_decay < 0:
            raise ValueError(f"optimizer_weight_decay must be >= 0, got {self.optimizer_weight_decay}.")
        if not self.normalization_mapping:
            self.normalization_mapping = self._default_normalization()

    def _default_normalization(self) -> dict[str, NormalizationMode]:
        """Craft states are symbolic ids and discrete actions are indices: neither may be rescaled; the
        dial_keys encoder measures distances in metres, so it takes the state unscaled too."""
        state = NormalizationMode.IDENTITY if self.obs_encoder in RAW_STATE_ENCODERS else NormalizationMode.MEAN_STD
        action = NormalizationMode.IDENTITY if self.action_type == "discrete" else NormalizationMode.MEAN_STD
        return {"STATE": state, "ACTION": action}

    @property
    def observation_delta_indices(self) -> list[int] | None:
        if self.packed:
            return None
        if self.window_start == "episode":
            return list(range(1 - self.window_size, self.window_size))
        return list(range(self.window_size))

    @property
    def action_delta_indices(self) -> list[int] | None:
        return self.observation_delta_indices

    @property
    def reward_delta_indices(self) -> None:
        return None

    @property
    def packed(self) -> bool:
        """Whether the policy trains on a packed view (one row per episode) instead of windows."""
        return self.window_start == "packed"

    @property
    def action_dim(self) -> int:
        """Width of one action in the batch: 1 index for discrete actions, the vector size otherwise."""
        return self.output_features[ACTION].shape[0]

    @property
    def state_dim(self) -> int:
        return self.input_features[OBS_STATE].shape[0]

    def get_optimizer_preset(self) -> AdamConfig | AdamWConfig:
        if self.optimizer_weight_decay:
            return AdamWConfig(
                lr=self.optimizer_lr,
                weight_decay=self.optimizer_weight_decay,
                grad_clip_norm=self.optimizer_grad_clip_norm,
            )
        return AdamConfig(lr=self.optimizer_lr, grad_clip_norm=self.optimizer_grad_clip_norm)

    def get_scheduler_preset(self) -> LRSchedulerConfig | None:
        if self.lr_schedule == "cosine":
            return CosineAnnealingWithWarmupSchedulerConfig(num_warmup_steps=0)
        if self.lr_schedule == "step":
            return StepDecaySchedulerConfig(decay_step=self.lr_decay_step, factor=self.lr_decay_factor)
        return None

    def validate_features(self) -> None:
        state = (self.input_features or {}).get(OBS_STATE)
        if state is None or state.type is not FeatureType.STATE:
            raise ValueError(f"{self.model_name} needs a `{OBS_STATE}` STATE input feature.")
        action = (self.output_features or {}).get(ACTION)
        if action is None:
            raise ValueError(f"{self.model_name} needs an `{ACTION}` output feature.")
        if self.obs_encoder in CRAFT_ENCODERS and tuple(state.shape) != (CRAFT_STATE_DIM,):
            raise ValueError(
                f"The {self.obs_encoder} encoder expects a compact state of shape ({CRAFT_STATE_DIM},), "
                f"got {state.shape}; float states (Dial) take --policy.obs_encoder=identity."
            )
        if self.obs_encoder == "dial_keys" and tuple(state.shape) != (DIAL_STATE_DIM,):
            raise ValueError(
                f"The dial_keys encoder expects Dial's state of shape ({DIAL_STATE_DIM},), got {state.shape}."
            )
        if self.action_type == "discrete" and tuple(action.shape) != (1,):
            raise ValueError(
                f"Discrete actions must be stored as one index, shape (1,); got {action.shape}: "
                "vector actions (Dial's motor controls) take --policy.action_type=continuous."
            )
        if self.action_type == "discrete" and self.n_actions < 2:
            raise ValueError(f"n_actions must be >= 2 for discrete actions, got {self.n_actions}.")


def tasks_from_meta(dataset_meta: Any) -> list[str]:
    """Task strings of a LeRobot dataset, in task-index order."""
    if dataset_meta.tasks is None:
        return []
    return [str(task) for task in dataset_meta.tasks.sort_values("task_index").index]


def episode_lengths(dataset_meta: Any) -> list[int]:
    """Frames per episode of a LeRobot dataset (its episode table is read from disk if not loaded yet)."""
    if dataset_meta.total_episodes == 0:
        return []
    episodes = dataset_meta.episodes if dataset_meta.episodes is not None else load_episodes(dataset_meta.root)
    return [int(length) for length in episodes["length"]]


def prepare_config(config: SequenceConfig, dataset_meta: Any | None) -> dict[str, int]:
    """Check the config when a policy is built and return its task table (task string -> index).

    `dataset_meta` fills `config.tasks` when it is empty, so the saved config keeps them, and with
    window_start="episode" its longest episode must fit in a window. A packed view's columns
    (`ocn_data.packed_view`), which LeRobot takes for state inputs, leave the policy's features.
    """
    packed_columns = set(PACKED_KEYS) & set(config.input_features or {})
    if packed_columns and not config.packed:
        raise ValueError(
            f"{config.model_name} is built on a packed view (it has {sorted(packed_columns)}), whose episodes are "
            "single rows: train it with --policy.window_start=packed, or on the recorded dataset."
        )
    config.input_features = {key: ft for key, ft in (config.input_features or {}).items() if key not in PACKED_KEYS}
    config.validate_features()
    name = config.model_name
    if not config.tasks and dataset_meta is not None:
        config.tasks = tasks_from_meta(dataset_meta)
    if not config.tasks:
        raise ValueError(f"{name} needs its task list: set `tasks` or build the policy from a dataset.")
    if dataset_meta is not None and config.packed:
        check_packed_width(config, dataset_meta.features)
    if dataset_meta is not None and config.window_start == "episode" and not config.skip_long_episodes:
        longest = max(episode_lengths(dataset_meta), default=0)
        if longest > config.window_size:
            raise ValueError(
                f"The dataset has episodes of up to {longest} frames but window_size is "
                f"{config.window_size}: with window_start='episode' a window must hold a whole "
                f"episode. Set --policy.window_size={longest} or more, --policy.skip_long_episodes=true "
                "or --policy.window_start=any."
            )
    return {task: i for i, task in enumerate(config.tasks)}


def check_packed_width(config: SequenceConfig, features: dict[str, dict]) -> None:
    """A packed view's rows must hold `window_size` frames of the policy's state."""
    name = config.model_name
    if PACKED_STATE not in features:
        raise ValueError(
            f"{name} with window_start='packed' trains on a packed view, made by `python -m ocn_data.packed_view "
            f"--root DATASET --width {config.window_size}`; this dataset has no `{PACKED_STATE}` column."
        )
    width, state = features[PACKED_STATE]["shape"][0], config.state_dim
    if width != config.window_size * state:
        raise ValueError(
            f"The packed view holds {width // state} frames per episode but window_size is {config.window_size}: "
            f"set --policy.window_size={width // state} or pack the dataset with --width {config.window_size}."
        )


def frame_mask(batch: dict[str, Any]) -> Tensor:
    """Frames [B, T] that are real data: neither the action nor the state is padding."""
    valid = torch.ones(batch[OBS_STATE].shape[:2], dtype=torch.bool, device=batch[OBS_STATE].device)
    for key in PAD_KEYS:
        if key in batch:
            valid &= ~batch[key].bool()
    return valid


def align_to_first_frame(valid: Tensor, length: int, *windows: Tensor) -> tuple[Tensor, ...]:
    """Shift each row of windows [B, W', ...] so that it starts at its first real frame.

    Returns the mask [B, length] of the shifted rows, then each window cut to [B, length, ...].
    Positions past the window's end read its last frame and are masked out.
    """
    width = valid.shape[1]
    first = valid.int().argmax(dim=1)
    position = first.unsqueeze(1) + torch.arange(length, device=valid.device)
    inside = position < width
    index = position.clamp_max(width - 1)
    mask = valid.gather(1, index) & inside
    shifted = []
    for window in windows:
        gather_index = index.view(*index.shape, *([1] * (window.dim() - 2))).expand(-1, -1, *window.shape[2:])
        shifted.append(window.gather(1, gather_index))
    return (mask, *shifted)


def training_windows(config: SequenceConfig, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
    """(mask [B, W], state [B, W, S], action [B, W, ...]) of sequences that each start at t = 1."""
    if config.packed:
        return trim_trailing_padding(*unpack_episodes(config, batch))
    valid = frame_mask(batch)
    if config.window_start == "any":
        windows = (valid, batch[OBS_STATE], batch[ACTION])
    else:
        if config.skip_long_episodes:
            # A real first position may mean the episode began before the window: leave it out.
            valid = valid & ~valid[:, :1]
        windows = align_to_first_frame(valid, config.window_size, batch[OBS_STATE], batch[ACTION])
    return trim_trailing_padding(*windows)


def unpack_episodes(config: SequenceConfig, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
    """(mask [B, W], state [B, W, S], action [B, W, ...]) of a packed view's rows (`ocn_data.packed_view`),
    shaped as LeRobot shapes windows: an action of one value per frame is [B, W]."""
    length = batch[PACKED_LENGTH].reshape(-1, 1)
    rows, width = length.shape[0], config.window_size
    action = batch[PACKED_ACTION].reshape(rows, width, config.action_dim)
    return (
        torch.arange(width, device=length.device) < length,
        batch[PACKED_STATE].reshape(rows, width, config.state_dim),
        action.squeeze(-1) if config.action_dim == 1 else action,
    )


def trim_trailing_padding(mask: Tensor, *windows: Tensor) -> tuple[Tensor, ...]:
    """Cut mask [B, W] and windows [B, W, ...] after the last step that any row uses.

    A recurrence costs the same per step whether a step is padding or not, and windows hold whole
    episodes padded to the longest one the dataset may have: most batches end long before.
    """
    used = int(mask.any(0).nonzero().max().item()) + 1 if mask.any() else 1
    return tuple(window[:, :used] for window in (mask, *windows))


def batch_mean(per_window: Tensor, frames: Tensor, packed: bool) -> Tensor:
    """The batch's loss from each window's loss [B], the window having `frames` [B] real frames:
    windows sampled at every frame (window_start "episode" or "any") weigh the same, and windows
    with no real frame (skipped long episodes) not at all; a packed view's episodes, drawn uniformly,
    weigh by their frames. Either way an episode weighs by its length in expectation, as it did
    when windows were sampled at its every frame."""
    weight = frames.float() if packed else (frames > 0).float()
    return (per_window * weight).sum() / weight.sum().clamp_min(1.0)


def window_nll(
    log_prob: Tensor, mask: Tensor, reduction: str, after_first: dict[str, Tensor],
    penalties: dict[str, tuple[float, Tensor]] | None = None, packed: bool = False,
) -> tuple[Tensor, dict[str, float]]:
    """The training loss from log p(a_t) [B, T] of windows with real frames mask [B, T]: the NLL's
    mean over each window's real frames, then `batch_mean` over the windows (`packed`: of a packed
    view; reduction "none": per window [B]).

    Stats: nll, frames_used, and the mean over real frames t > 1 of each `after_first` quantity
    (time-major [T, B], detached here): a model's per-step readout, meaningless at t = 1.
    `penalties` name (weight, quantity [T, B]) pairs whose mean over each window's real frames t > 1,
    times the weight, joins that window's loss (stats: the quantity's mean, as for `after_first`).
    """
    mask = mask.float()
    frames = mask.sum(1)
    per_window = (-log_prob * mask).sum(1) / frames.clamp_min(1.0)
    later = mask[:, 1:]
    stats = {"nll": batch_mean(per_window, frames, packed).item(), "frames_used": int(frames.sum().item())}
    for name, (weight, value) in {**{name: (0.0, v) for name, v in after_first.items()}, **(penalties or {})}.items():
        sums = (value[1:].transpose(0, 1) * later).sum(1)
        stats[name] = float(sums.detach().sum() / later.sum().clamp_min(1.0))
        if weight:
            per_window = per_window + weight * sums / later.sum(1).clamp_min(1.0)
    if reduction == "none":
        return per_window, stats
    return batch_mean(per_window, frames, packed), stats


class SequencePolicy:
    """Mixin of the LeRobot policies over whole episodes, placed before `PreTrainedPolicy` in the
    bases: LeRobot's constructor, the task table, and `select_action` from `predict_action_chunk`."""

    config: SequenceConfig

    def __init__(self, config: SequenceConfig, dataset_meta: Any | None = None, **kwargs: Any) -> None:
        """LeRobot's factory also passes `dataset_stats`, unused: normalisation lives in the processors.
        `dataset_meta` fills `config.tasks` when it is empty, so the saved config keeps them."""
        super().__init__(config)
        self._task_ids = prepare_config(config, dataset_meta)

    def task_index(self, tasks: Sequence[str] | str | None, batch_size: int) -> Tensor:
        """Map a batch's task strings (one string: the whole batch) to rows of the per-task parameters."""
        name, known = self.config.model_name, self.config.tasks
        if tasks is None:
            raise ValueError(f"The batch has no 'task'; {name} needs one of {known}.")
        if isinstance(tasks, str):
            tasks = [tasks] * batch_size
        for task in tasks:
            if task not in self._task_ids:
                raise ValueError(f"Unknown task {task!r}; this {name} knows the tasks {known}.")
        device = next(self.parameters()).device
        return torch.tensor([self._task_ids[task] for task in tasks], dtype=torch.long, device=device)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """One action [B, A] per env; the recurrent state persists until `reset()`."""
        return self.predict_action_chunk(batch)[:, 0]
