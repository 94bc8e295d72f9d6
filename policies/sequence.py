"""What the recurrent policies trained on whole episodes share (`ocn`, `ompn`, `compile`): the
configuration fields that follow from the dataset, the episodes held in memory, the masked loss, and
a policy mixin with LeRobot's constructor and the task table.

Training batches: LeRobot loads single frames (the policies ask for no `delta_timestamps`), and the
policy trains on the whole episode of each sampled frame, read from its `EpisodeMemory`
(`lerobot_policy_ocn.episode_memory`), from t = 1 with its task's initial state, as the paper trains. A batch
that already holds episodes ([B, T, S] states from their first frame, with `action_is_pad`) trains
as it is, which is how probes and tests feed chosen episodes.
"""

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor

from lerobot_policy_ocn.envs.craft.observation import OBS_DIM as CRAFT_STATE_DIM
from lerobot_policy_ocn.envs.dial import OBS_DIM as DIAL_STATE_DIM
from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.optim import AdamConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ocn.distributed import global_mean_weight
from lerobot_policy_ocn.episode_memory import EpisodeMemory

# Encoders of Craft's compact state (see policies/ocn/encoders.py); "identity" takes float states as they
# are (standardised); "dial_keys" reads Dial's raw state and adds each key's log distance. "auto" picks
# from the dataset when the policy is built (`resolve_from_dataset`).
CRAFT_ENCODERS = ("craft", "craft_full_view")
RAW_STATE_ENCODERS = (*CRAFT_ENCODERS, "dial_keys")
OBS_ENCODERS = ("auto", *RAW_STATE_ENCODERS, "identity")
ACTION_TYPES = ("auto", "discrete", "continuous")
INFERENCE_MODES = ("sample", "greedy")
PAD_KEYS = (f"{ACTION}_is_pad", f"{OBS_STATE}_is_pad")
AUTO = "auto"


def check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    """A config string must name one of its choices."""
    if value not in choices:
        raise ValueError(f"`{name}` must be one of {choices}, got {value!r}.")


@dataclass
class SequenceConfig(PreTrainedConfig):
    """Fields and LeRobot plumbing of a recurrent policy trained on whole episodes (not registered:
    each policy type subclasses it).

    The fields left at "auto" (or 0) follow from the dataset when the policy is built from one
    (`resolve_from_dataset`), and the saved config holds what they became: the observation encoder
    (Craft's compact state, Dial's, or float states as they are), discrete or continuous actions and
    the number of discrete actions, the task list, and `window_size`, the longest episode, which is
    what a training sequence may hold.
    """

    # The model's name in error messages.
    model_name: ClassVar[str] = "The policy"

    window_size: int = 0

    obs_encoder: str = AUTO
    action_type: str = AUTO
    n_actions: int = 0
    log_std_min: float = -5.0
    log_std_max: float = 2.0

    # Task strings in task-index order; filled from the dataset's metadata when the policy is built.
    tasks: list[str] = field(default_factory=list)

    inference_mode: str = "sample"

    optimizer_lr: float = 1e-3
    optimizer_grad_clip_norm: float = 10.0

    # Empty means "derive from obs_encoder and action_type" (see `_default_normalization`).
    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("obs_encoder", self.obs_encoder, OBS_ENCODERS)
        check_choice("action_type", self.action_type, ACTION_TYPES)
        check_choice("inference_mode", self.inference_mode, INFERENCE_MODES)
        if self.window_size < 0 or self.n_actions < 0:
            raise ValueError(f"window_size and n_actions must be >= 0 (0: from the dataset), got "
                             f"{self.window_size} and {self.n_actions}.")
        if self.resolved and not self.normalization_mapping:
            self.normalization_mapping = self._default_normalization()

    @property
    def resolved(self) -> bool:
        """Whether every field that follows from the dataset holds its value (a saved config's do)."""
        return AUTO not in (self.obs_encoder, self.action_type) and (self.action_type != "discrete" or self.n_actions)

    def _default_normalization(self) -> dict[str, NormalizationMode]:
        """Craft states are symbolic ids and discrete actions are indices: neither may be rescaled; the
        dial_keys encoder measures distances in metres, so it takes the state unscaled too."""
        state = NormalizationMode.IDENTITY if self.obs_encoder in RAW_STATE_ENCODERS else NormalizationMode.MEAN_STD
        action = NormalizationMode.IDENTITY if self.action_type == "discrete" else NormalizationMode.MEAN_STD
        return {"STATE": state, "ACTION": action}

    def auto_encoder(self, dataset_meta: Any) -> str:
        """The observation encoder for a dataset's state: Craft's compact state gets OMPN's features (the
        paper's observation), any other state is read as floats."""
        shape = tuple(dataset_meta.features[OBS_STATE]["shape"])
        if dataset_meta.robot_type == "craft" and shape == (CRAFT_STATE_DIM,):
            return "craft"
        return "identity"

    def resolve_from_dataset(self, dataset_meta: Any) -> None:
        """Fill the "auto" fields from the dataset the policy is built on (see the class docstring)."""
        features = dataset_meta.features
        if OBS_STATE not in features or ACTION not in features:
            raise ValueError(f"{self.model_name} trains on `{OBS_STATE}` and `{ACTION}`; the dataset at "
                             f"{dataset_meta.root} has {sorted(features)}.")
        if self.obs_encoder == AUTO:
            self.obs_encoder = self.auto_encoder(dataset_meta)
        if self.action_type == AUTO:
            integer = str(features[ACTION]["dtype"]).startswith(("int", "uint"))
            self.action_type = "discrete" if integer and tuple(features[ACTION]["shape"]) == (1,) else "continuous"
        if self.action_type == "discrete" and not self.n_actions:
            self.n_actions = int(round(float(dataset_meta.stats[ACTION]["max"][0]))) + 1
        if not self.normalization_mapping:
            self.normalization_mapping = self._default_normalization()

    @property
    def observation_delta_indices(self) -> None:
        """No windows: LeRobot loads single frames, and the policy trains on their whole episodes."""
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

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


def prepare_config(config: SequenceConfig, dataset_meta: Any | None) -> dict[str, int]:
    """Check the config when a policy is built and return its task table (task string -> index).

    Built from a dataset (`dataset_meta`), the "auto" fields and an empty task list are filled from it,
    so that the saved config keeps them; built from a saved config, they must be there already.
    """
    name = config.model_name
    if dataset_meta is not None:
        config.resolve_from_dataset(dataset_meta)
        if not config.tasks:
            config.tasks = tasks_from_meta(dataset_meta)
    if not config.resolved:
        raise ValueError(f"{name}'s obs_encoder, action_type and n_actions follow from its training data: build it "
                         "from a dataset, or set them.")
    config.validate_features()
    if not config.tasks:
        raise ValueError(f"{name} needs its task list: set `tasks` or build the policy from a dataset.")
    return {task: i for i, task in enumerate(config.tasks)}


def frame_mask(batch: dict[str, Any]) -> Tensor:
    """Frames [B, T] that are real data: neither the action nor the state is padding."""
    valid = torch.ones(batch[OBS_STATE].shape[:2], dtype=torch.bool, device=batch[OBS_STATE].device)
    for key in PAD_KEYS:
        if key in batch:
            valid &= ~batch[key].bool()
    return valid


def batch_mean(per_episode: Tensor, frames: Tensor, global_batch: bool = True) -> Tensor:
    """The batch's loss from each episode's loss [B] (its mean over its `frames` [B] real frames): the
    mean over the episodes that have any. LeRobot samples frames uniformly and each sampled frame
    stands for its episode, so an episode is drawn in proportion to its length, and this is the
    dataset's per-frame mean loss in expectation. In a distributed run the mean is over every process's
    episodes once DDP averages the gradients (`global_mean_weight`); `global_batch=False` gives this
    process's own mean, for its logged statistics."""
    weight = (frames > 0).to(per_episode.dtype)
    count = global_mean_weight(weight) if global_batch else weight.sum()
    return (per_episode * weight).sum() / count.clamp_min(1e-6)


def window_nll(
    log_prob: Tensor, mask: Tensor, reduction: str, after_first: dict[str, Tensor],
    penalties: dict[str, tuple[float, Tensor]] | None = None,
) -> tuple[Tensor, dict[str, float]]:
    """The training loss from log p(a_t) [B, T] of episodes with real frames mask [B, T]: the NLL's
    mean over each episode's real frames, then `batch_mean` over the episodes (reduction "none": per
    episode [B]).

    Stats: nll, frames_used, and the mean over real frames t > 1 of each `after_first` quantity
    (time-major [T, B], detached here): a model's per-step readout, meaningless at t = 1.
    `penalties` name (weight, quantity [T, B]) pairs whose mean over each episode's real frames t > 1,
    times the weight, joins that episode's loss (stats: the quantity's mean, as for `after_first`).
    """
    mask = mask.float()
    frames = mask.sum(1)
    per_episode = (-log_prob * mask).sum(1) / frames.clamp_min(1.0)
    later = mask[:, 1:]
    stats = {"nll": batch_mean(per_episode, frames, global_batch=False).item(), "frames_used": int(frames.sum().item())}
    for name, (weight, value) in {**{name: (0.0, v) for name, v in after_first.items()}, **(penalties or {})}.items():
        sums = (value[1:].transpose(0, 1) * later).sum(1)
        stats[name] = float(sums.detach().sum() / later.sum().clamp_min(1.0))
        if weight:
            per_episode = per_episode + weight * sums / later.sum(1).clamp_min(1.0)
    if reduction == "none":
        return per_episode, stats
    return batch_mean(per_episode, frames), stats


class Episodes(NamedTuple):
    """A training batch of whole episodes from t = 1: real frames `mask` [B, T], `state` [B, T, S], `action`
    [B, T, ...], their `tasks`, and any further per-frame columns the policy keeps in memory ([B, T])."""

    mask: Tensor
    state: Tensor
    action: Tensor
    tasks: list[str]
    columns: dict[str, Tensor]


class SequencePolicy:
    """Mixin of the LeRobot policies over whole episodes, placed before `PreTrainedPolicy` in the
    bases: LeRobot's constructor, the episodes in memory, the task table, and `select_action` from
    `predict_action_chunk`."""

    config: SequenceConfig

    def __init__(self, config: SequenceConfig, dataset_meta: Any | None = None, **kwargs: Any) -> None:
        """LeRobot's factory also passes `dataset_stats`, unused: normalisation lives in the processors
        (and, for the episodes in memory, in `_remember_episodes`)."""
        super().__init__(config)
        self._task_ids = prepare_config(config, dataset_meta)
        self._episodes: EpisodeMemory | None = None
        if dataset_meta is not None:
            self._remember_episodes(dataset_meta)

    def _remember_episodes(self, dataset_meta: Any) -> None:
        """Read the dataset's states and actions into memory, normalised as the preprocessor normalises a
        frame, and size `window_size` to its longest episode."""
        from lerobot.processor import NormalizerProcessorStep

        memory = EpisodeMemory.read(dataset_meta.root, [OBS_STATE, ACTION])
        features = {**self.config.input_features, **self.config.output_features}
        normalizer = NormalizerProcessorStep(features=features, norm_map=self.config.normalization_mapping,
                                             stats=dataset_meta.stats)
        for key in (OBS_STATE, ACTION):
            values = memory.frames[key]
            memory.frames[key] = normalizer._apply_transform(values.float(), key, features[key].type).to(values.dtype) \
                if values.is_floating_point() else values
        self._episodes = memory
        self.config.window_size = memory.longest
        logging.info(f"{self.config.model_name} holds the {int((memory.length > 0).sum())} episodes of "
                     f"{dataset_meta.root} in memory and trains on the {memory.n_trainable} of split "
                     f"'{memory.split}'; frames LeRobot samples from other episodes are left out of the loss.")

    def training_windows(self, batch: dict[str, Any]) -> Episodes:
        """The whole episodes of a batch, from t = 1: those of LeRobot's sampled frames, from memory, or the
        batch itself where it already holds episodes."""
        if batch[OBS_STATE].dim() == 3:
            tasks = batch["task"]
            tasks = [tasks] * len(batch[OBS_STATE]) if isinstance(tasks, str) else list(tasks)
            return Episodes(frame_mask(batch), batch[OBS_STATE], batch[ACTION], tasks, {})
        if self._episodes is None or "episode_index" not in batch:
            raise ValueError(f"{self.config.model_name} trains on whole episodes: build it from the dataset it trains "
                             "on (lerobot-train does) so that it holds them, or give it a batch of episodes.")
        device = batch[OBS_STATE].device
        if self._episodes.start.device != device:
            self._episodes = self._episodes.to(device)
        episode_index = batch["episode_index"].reshape(-1).long().to(device)
        if self.training:
            # Episodes held out by the dataset's split leave the batch; a batch of nothing else keeps
            # them masked, so that its loss is still a (zero) function of the weights.
            trainable = self._episodes.trainable[episode_index]
            if trainable.any():
                episode_index = episode_index[trainable]
        mask, frames, task_index = self._episodes.batch(episode_index)
        if self.training:
            mask &= self._episodes.trainable[episode_index][:, None]
        action = frames.pop(ACTION)
        if action.shape[-1] == 1 and self.config.action_type == "discrete":
            action = action.squeeze(-1)
        tasks = [self.config.tasks[int(i)] for i in task_index]
        return Episodes(mask, frames.pop(OBS_STATE), action, tasks, frames)

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
