"""What the recurrent policies trained on whole episodes share (`ocn`, `ompn`, `compile`): the
configuration fields that follow from the dataset, the episodes held in memory, the masked loss, and
a policy mixin with LeRobot's constructor and the task table.

Training batches: LeRobot loads single frames (the policies ask for no `delta_timestamps`), and the
policy trains on the whole episode of each sampled frame, read from its `EpisodeMemory`
(`lerobot_policy_ocn.episode_memory`), from t = 1 with its task's initial state, as the paper trains. A batch
that already holds episodes ([B, T, S] states from their first frame, with `action_is_pad`) trains
as it is, which is how probes and tests feed chosen episodes.

Inputs: the policy reads the standard LeRobot features of its dataset by itself. Every `observation.*`
state feature (`observation.state`, `observation.environment_state`, ...) and every image feature
(`observation.image`, `observation.images.*`) is an input unless `drop_features` names it; a feature
it cannot read is an error that names it and that flag. The model sees one input vector per frame
(`SequencePolicy.observation`): the state features side by side, then each image's pixels at
`image_size` (uint8 values as floats), so that the recurrent models keep one input tensor; the
encoder (`lerobot_policy_ocn.ocn.encoders`) splits it again.
"""

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor

from lerobot_policy_ocn.envs.craft.observation import OBS_DIM as CRAFT_STATE_DIM
from lerobot_policy_ocn.envs.dial import OBS_DIM as DIAL_STATE_DIM
from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.optim import AdamConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ocn.distributed import global_mean_weight
from lerobot_policy_ocn.episode_memory import EpisodeMemory, fit_frames

# Encoders of the state features (see policies/ocn/encoders.py): Craft's compact state; "identity" takes
# float states as they are (standardised); "dial_keys" reads Dial's raw state and adds each key's log
# distance; "categorical" one-hots small integer codes (BabyAI's symbolic view); "none": no state feature
# (images alone). "auto" picks from the dataset when the policy is built (`resolve_from_dataset`).
CRAFT_ENCODERS = ("craft", "craft_full_view")
RAW_STATE_ENCODERS = (*CRAFT_ENCODERS, "dial_keys", "categorical")
OBS_ENCODERS = ("auto", *RAW_STATE_ENCODERS, "identity", "none")
ACTION_TYPES = ("auto", "discrete", "continuous")
INFERENCE_MODES = ("sample", "greedy")
AUTO = "auto"
STATE_TYPES = (FeatureType.STATE, FeatureType.ENV)
# Integer states whose every element takes at most this many values (0 .. n-1) are read as categories.
# BabyAI's view holds object (0-10), colour (0-5) and door-state (0-2) codes; a joint read in encoder
# ticks (thousands of values) stays a number.
MAX_CATEGORIES = 64
NUMERIC_DTYPES = ("float", "int", "uint", "bool")


def check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    """A config string must name one of its choices."""
    if value not in choices:
        raise ValueError(f"`{name}` must be one of {choices}, got {value!r}.")


@dataclass
class SequenceConfig(PreTrainedConfig):
    """Fields and LeRobot plumbing of a recurrent policy trained on whole episodes (not registered:
    each policy type subclasses it).

    The fields left at "auto" (or 0) follow from the dataset when the policy is built from one
    (`resolve_from_dataset`), and the saved config holds what they became: the input features (every
    state and image feature of the dataset but those `drop_features` names), the state encoder
    (Craft's compact state, Dial's, integer categories with their `state_vocab`, or float states as
    they are), discrete or continuous actions and the number of discrete actions, the task list, and
    `window_size`, the longest episode, which is what a training sequence may hold.

    Images are shrunk to `image_size` square pixels and held in memory as uint8 with the episodes;
    `episode_memory_mb` bounds that memory: a dataset whose inputs would need more is refused when
    the policy is built, before anything is decoded.
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

    # Dataset features the policy must not read, e.g. --policy.drop_features='[observation.image]'.
    drop_features: list[str] = field(default_factory=list)
    # Side of the square images the encoder reads: 40 keeps 4 px of each 16-px tile of Craft's render.
    image_size: int = 40
    # Memory the episodes' inputs may take (MiB), checked before they are read.
    episode_memory_mb: int = 4096
    # Values each state element takes under the categorical encoder (0 .. n-1), from the dataset's stats.
    state_vocab: list[int] = field(default_factory=list)

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
        if self.image_size < 8 or self.episode_memory_mb < 1:
            raise ValueError(f"image_size must be >= 8 and episode_memory_mb >= 1, got {self.image_size} and "
                             f"{self.episode_memory_mb}.")
        if self.resolved and not self.normalization_mapping:
            self.normalization_mapping = self._default_normalization()

    @property
    def resolved(self) -> bool:
        """Whether every field that follows from the dataset holds its value (a saved config's do)."""
        return AUTO not in (self.obs_encoder, self.action_type) and (self.action_type != "discrete" or self.n_actions)

    def _default_normalization(self) -> dict[str, NormalizationMode]:
        """Craft states are symbolic ids, categorical states are codes and discrete actions are indices:
        none may be rescaled; the dial_keys encoder measures distances in metres, so it takes the state
        unscaled too. Images are never normalised by the processors (LeRobot would put ImageNet's
        statistics there): the encoder reads their pixels / 255 itself."""
        state = NormalizationMode.IDENTITY if self.obs_encoder in RAW_STATE_ENCODERS else NormalizationMode.MEAN_STD
        action = NormalizationMode.IDENTITY if self.action_type == "discrete" else NormalizationMode.MEAN_STD
        return {"STATE": state, "ENV": state, "VISUAL": NormalizationMode.IDENTITY, "ACTION": action}

    @property
    def state_keys(self) -> list[str]:
        """The state features the policy reads, in the order the input vector holds them."""
        return [key for key, ft in (self.input_features or {}).items() if ft.type in STATE_TYPES]

    @property
    def image_keys(self) -> list[str]:
        """The image features the policy reads, after the states in the input vector."""
        return [key for key, ft in (self.input_features or {}).items() if ft.type is FeatureType.VISUAL]

    def image_channels(self, key: str) -> int:
        """Channels of an image input (LeRobot's policy features are channel-first)."""
        return int(self.input_features[key].shape[0])

    @property
    def input_dim(self) -> int:
        """Width of the input vector: the state features, then each image's pixels at `image_size`."""
        return self.state_dim + sum(self.image_channels(key) * self.image_size**2 for key in self.image_keys)

    def auto_encoder(self, dataset_meta: Any) -> str:
        """The state encoder for a dataset's state features: Craft's compact state gets OMPN's features
        (the paper's observation); integer states of few values per element are categories (BabyAI's
        symbolic view: `categorical`, measured against `identity` in results/babyai.md); any other
        state is read as floats; no state at all (images alone), "none"."""
        keys = self.state_keys
        if not keys:
            return "none"
        if keys == [OBS_STATE] and dataset_meta.robot_type == "craft" and \
                tuple(dataset_meta.features[OBS_STATE]["shape"]) == (CRAFT_STATE_DIM,):
            return "craft"
        if self.categories(dataset_meta) is not None:
            return "categorical"
        return "identity"

    def categories(self, dataset_meta: Any) -> list[int] | None:
        """Values per element (max + 1, from the dataset's stats) of the state features when every one is
        integer-typed, never negative and takes at most MAX_CATEGORIES values; None otherwise."""
        vocab = []
        for key in self.state_keys:
            stats = dataset_meta.stats.get(key) if dataset_meta.stats else None
            if not str(dataset_meta.features[key]["dtype"]).startswith(("int", "uint")) or stats is None:
                return None
            low, high = (torch.as_tensor(stats[name]).reshape(-1) for name in ("min", "max"))
            if bool((low < 0).any()) or bool((high + 1 > MAX_CATEGORIES).any()):
                return None
            vocab += [int(round(float(value))) + 1 for value in high]
        return vocab

    def select_inputs(self, dataset_meta: Any) -> None:
        """The input features: the dataset's state and image features but those `drop_features` names, each
        checked readable; a feature it cannot read is an error naming it and the flag that drops it."""
        from lerobot.utils.feature_utils import dataset_to_policy_features

        features = dataset_meta.features
        unknown = sorted(set(self.drop_features) - set(features))
        if unknown:
            raise ValueError(f"--policy.drop_features names {unknown}, which the dataset at {dataset_meta.root} does "
                             f"not have; its features are {sorted(features)}.")
        if ACTION not in features:
            raise ValueError(f"{self.model_name} clones the dataset's `{ACTION}`, which the dataset at "
                             f"{dataset_meta.root} does not have; its features are {sorted(features)}.")
        if ACTION in self.drop_features:
            raise ValueError(f"--policy.drop_features cannot drop `{ACTION}`: it is what {self.model_name} learns.")
        inputs = self.input_features or {
            key: ft for key, ft in dataset_to_policy_features(features).items() if ft.type is not FeatureType.ACTION
        }
        self.input_features = {key: ft for key, ft in inputs.items() if key not in self.drop_features}
        for key, ft in self.input_features.items():
            check_input(key, ft, features.get(key, {}), self.model_name)
        if not self.input_features:
            raise ValueError(f"{self.model_name} has no input left: the dataset at {dataset_meta.root} has no state "
                             f"or image feature besides {sorted(self.drop_features)}, which --policy.drop_features "
                             "drops.")

    def resolve_from_dataset(self, dataset_meta: Any) -> None:
        """Fill the "auto" fields from the dataset the policy is built on (see the class docstring)."""
        features = dataset_meta.features
        self.select_inputs(dataset_meta)
        if self.obs_encoder == AUTO:
            self.obs_encoder = self.auto_encoder(dataset_meta)
        if self.obs_encoder == "categorical" and not self.state_vocab:
            vocab = self.categories(dataset_meta)
            if vocab is None:
                raise ValueError(f"The categorical encoder reads integer states of at most {MAX_CATEGORIES} values "
                                 f"per element, which {self.state_keys} are not: take --policy.obs_encoder=identity.")
            self.state_vocab = vocab
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
        """Width of the state features side by side (0 with images alone)."""
        return sum(math.prod(self.input_features[key].shape) for key in self.state_keys)

    def get_optimizer_preset(self) -> AdamConfig:
        return AdamConfig(lr=self.optimizer_lr, grad_clip_norm=self.optimizer_grad_clip_norm)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if not self.state_keys and not self.image_keys:
            raise ValueError(f"{self.model_name} needs a state or image input feature.")
        action = (self.output_features or {}).get(ACTION)
        if action is None:
            raise ValueError(f"{self.model_name} needs an `{ACTION}` output feature.")
        state = (self.input_features or {}).get(OBS_STATE)
        raw = self.obs_encoder in (*CRAFT_ENCODERS, "dial_keys")
        if raw and self.state_keys != [OBS_STATE]:
            others = [key for key in self.state_keys if key != OBS_STATE] or [OBS_STATE]
            raise ValueError(f"The {self.obs_encoder} encoder reads `{OBS_STATE}` alone, not {others}: drop the "
                             f"others with --policy.drop_features, or take --policy.obs_encoder=identity.")
        if self.obs_encoder in CRAFT_ENCODERS and tuple(state.shape) != (CRAFT_STATE_DIM,):
            raise ValueError(
                f"The {self.obs_encoder} encoder expects a compact state of shape ({CRAFT_STATE_DIM},), "
                f"got {state.shape}; float states (Dial) take --policy.obs_encoder=identity."
            )
        if self.obs_encoder == "dial_keys" and tuple(state.shape) != (DIAL_STATE_DIM,):
            raise ValueError(
                f"The dial_keys encoder expects Dial's state of shape ({DIAL_STATE_DIM},), got {state.shape}."
            )
        if (self.obs_encoder == "none") != (not self.state_keys):
            raise ValueError(f"obs_encoder 'none' goes with no state feature and only then; the state features are "
                             f"{self.state_keys}.")
        if self.obs_encoder == "categorical" and len(self.state_vocab) != self.state_dim:
            raise ValueError(f"The categorical encoder needs one category count per state element ({self.state_dim}), "
                             f"got {len(self.state_vocab)}: build the policy from its dataset.")
        if self.action_type == "discrete" and tuple(action.shape) != (1,):
            raise ValueError(
                f"Discrete actions must be stored as one index, shape (1,); got {action.shape}: "
                "vector actions (Dial's motor controls) take --policy.action_type=continuous."
            )
        if self.action_type == "discrete" and self.n_actions < 2:
            raise ValueError(f"n_actions must be >= 2 for discrete actions, got {self.n_actions}.")


def check_input(key: str, feature: PolicyFeature, stored: dict, model_name: str) -> None:
    """One input feature the policy can read: a state vector of numbers, or an image of 1, 3 or 4
    channels; anything else is an error naming it and the flag that drops it."""
    drop = f"drop it with --policy.drop_features='[{key}]'"
    dtype = str(stored.get("dtype", "float32"))
    if feature.type in STATE_TYPES:
        if len(feature.shape) != 1 or not dtype.startswith(NUMERIC_DTYPES):
            raise ValueError(f"{model_name} reads state features as vectors of numbers; `{key}` is {dtype} of shape "
                             f"{tuple(feature.shape)}: {drop}.")
    elif feature.type is FeatureType.VISUAL:
        if len(feature.shape) != 3 or feature.shape[0] not in (1, 3, 4):
            raise ValueError(f"{model_name} reads images of 1, 3 or 4 channels; `{key}` has shape "
                             f"{tuple(feature.shape)} (channels first): {drop}.")
    else:
        raise ValueError(f"{model_name} cannot read `{key}` (a {feature.type.name} feature): {drop}.")


def memory_bytes(config: SequenceConfig, frames: int, itemsize: dict[str, int]) -> dict[str, int]:
    """Bytes each input feature takes in the episode memory for `frames` frames: state values at their
    stored width (`itemsize`), images as uint8 at `image_size`."""
    sizes = {key: frames * math.prod(config.input_features[key].shape) * itemsize.get(key, 4)
             for key in config.state_keys}
    return sizes | {key: frames * config.image_channels(key) * config.image_size**2 for key in config.image_keys}


def check_memory(config: SequenceConfig, frames: int, itemsize: dict[str, int]) -> None:
    """Refuse, before anything is read, inputs whose episodes would not fit in `episode_memory_mb`; the
    error names the largest feature, its size and the flags that shrink or drop it."""
    sizes = memory_bytes(config, frames, itemsize)
    budget = config.episode_memory_mb * 2**20
    if sum(sizes.values()) <= budget:
        return
    key = max(sizes, key=sizes.get)
    shrink = f", or shrink it with --policy.image_size (now {config.image_size})" if key in config.image_keys else ""
    raise ValueError(f"The {frames:,} frames' inputs need {sum(sizes.values()) / 2**20:,.0f} MiB in memory, over the "
                     f"{config.episode_memory_mb:,} MiB of --policy.episode_memory_mb; `{key}` alone takes "
                     f"{sizes[key] / 2**20:,.0f} MiB: drop it with --policy.drop_features='[{key}]'{shrink}, or "
                     "raise --policy.episode_memory_mb.")


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


def frame_mask(batch: dict[str, Any], observation: Tensor) -> Tensor:
    """Frames [B, T] of a batch of episodes (its input vectors `observation` [B, T, W]) that are real
    data: no feature of theirs is padding (`*_is_pad`)."""
    valid = torch.ones(observation.shape[:2], dtype=torch.bool, device=observation.device)
    for key, value in batch.items():
        if key.endswith("_is_pad") and value.shape == valid.shape:
            valid &= ~value.bool()
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
    """A training batch of whole episodes from t = 1: real frames `mask` [B, T], the input vectors `state`
    [B, T, W] (`SequencePolicy.observation`), `action` [B, T, ...], their `tasks`, and any further
    per-frame columns the policy keeps in memory ([B, T])."""

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
        """Read the dataset's inputs and actions into memory, the states and actions normalised as the
        preprocessor normalises a frame, the images shrunk once (`EpisodeMemory.read`), after checking
        that they fit (`check_memory`); size `window_size` to the longest episode."""
        from lerobot.processor import NormalizerProcessorStep

        config = self.config
        itemsize = {key: 8 if str(dataset_meta.features[key]["dtype"]).endswith("64") else 4
                    for key in config.state_keys}
        check_memory(config, int(dataset_meta.total_frames), itemsize)
        numeric = [*config.state_keys, ACTION]
        images = {key: config.image_size for key in config.image_keys}
        started = time.perf_counter()
        memory = EpisodeMemory.read(dataset_meta.root, numeric, images)
        features = {**config.input_features, **config.output_features}
        normalizer = NormalizerProcessorStep(features=features, norm_map=config.normalization_mapping,
                                             stats=dataset_meta.stats)
        for key in numeric:
            values = memory.frames[key]
            memory.frames[key] = normalizer._apply_transform(values.float(), key, features[key].type).to(values.dtype) \
                if values.is_floating_point() else values
        if images:
            logging.info(f"{config.model_name} decoded {sorted(images)} once, at {config.image_size} x "
                         f"{config.image_size} px, in {time.perf_counter() - started:.1f} s")
        self._episodes = memory
        self.config.window_size = memory.longest
        logging.info(f"{self.config.model_name} holds the {int((memory.length > 0).sum())} episodes of "
                     f"{dataset_meta.root} in memory and trains on the {memory.n_trainable} of split "
                     f"'{memory.split}'; frames LeRobot samples from other episodes are left out of the loss.")

    def observation(self, batch: dict[str, Any]) -> Tensor:
        """The input vectors [..., W] of a batch (of frames [B], or episodes [B, T]): the state features
        side by side (as floats), then each image's pixels at `image_size` (`fit_frames`; uint8 values
        as floats). A lone state feature is passed as it is, so that Craft's and Dial's policies read
        exactly what they always read. A missing input is an error naming it."""
        config = self.config
        missing = [key for key in (*config.state_keys, *config.image_keys) if key not in batch]
        if missing:
            raise ValueError(f"The batch has no {missing}, which {config.model_name} reads (it has {sorted(batch)}).")
        if config.state_keys == [OBS_STATE] and not config.image_keys:
            return batch[OBS_STATE]
        parts = [batch[key].float() for key in config.state_keys]
        parts += [fit_frames(batch[key], config.image_size).flatten(-3).float() for key in config.image_keys]
        return torch.cat(parts, dim=-1)

    def _holds_episodes(self, batch: dict[str, Any]) -> bool:
        """Whether a batch holds whole episodes [B, T, ...] rather than LeRobot's single frames [B, ...]."""
        config = self.config
        if config.state_keys:
            return batch[config.state_keys[0]].dim() == 3
        return batch[config.image_keys[0]].dim() == 5

    def training_windows(self, batch: dict[str, Any]) -> Episodes:
        """The whole episodes of a batch, from t = 1: those of LeRobot's sampled frames, from memory, or the
        batch itself where it already holds episodes."""
        if self._holds_episodes(batch):
            state = self.observation(batch)
            tasks = batch["task"]
            tasks = [tasks] * len(state) if isinstance(tasks, str) else list(tasks)
            return Episodes(frame_mask(batch, state), state, batch[ACTION], tasks, {})
        if self._episodes is None or "episode_index" not in batch:
            raise ValueError(f"{self.config.model_name} trains on whole episodes: build it from the dataset it trains "
                             "on (lerobot-train does) so that it holds them, or give it a batch of episodes.")
        device = batch["episode_index"].device
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
        state = self.observation(frames)
        inputs = {*self.config.state_keys, *self.config.image_keys}
        return Episodes(mask, state, action, tasks, {key: value for key, value in frames.items() if key not in inputs})

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
