"""Pre/post-processing pipelines of the OCN policy (and of OMPN and compILE, which use them too).

LeRobot's default pipelines (rename -> batch -> device -> normalise; unnormalise -> cpu) are all OCN
needs: no tokenizer step, so the raw task strings reach `forward` and `select_action` in
`batch["task"]`, where the policy maps them to its per-task initial controller states. A policy that
trains on a packed view (`--policy.window_start=packed`, `ocn_data.packed_view`) gets one more
preprocessing step, `PackedEpisodeNormalizerStep`, since the default normaliser sees only
`observation.state` and `action`, not the packed episode columns that hold them during training.
"""

from dataclasses import dataclass
from typing import Any

import torch

from lerobot.processor import (
    NormalizerProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
    TransitionKey,
)
from lerobot.processor.converters import EnvTransition
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines
from lerobot.utils.constants import ACTION, OBS_STATE

from ocn_data.packed_view import PACKED_ACTION, PACKED_STATE
from policies.sequence import SequenceConfig


@ProcessorStepRegistry.register(name="ocn_packed_episode_normalizer")
@dataclass
class PackedEpisodeNormalizerStep(NormalizerProcessorStep):
    """Normalises a packed view's episode columns frame by frame, exactly as the default normaliser
    normalises `observation.state` and `action` (the same statistics, modes and eps): row [B, W * D]
    -> frames [B, W, D] -> normalised -> [B, W * D]. Frames past an episode's end are padding, which
    it transforms too and the loss never reads. A batch without packed columns (inference, or
    training on windows) passes unchanged."""

    def __call__(self, transition: EnvTransition) -> EnvTransition:
        observation = transition.get(TransitionKey.OBSERVATION)
        if not observation or PACKED_STATE not in observation:
            return transition
        columns = dict(observation)
        for packed, key in ((PACKED_STATE, OBS_STATE), (PACKED_ACTION, ACTION)):
            feature = self.features[key]
            rows = torch.as_tensor(columns[packed])
            frames = rows.reshape(*rows.shape[:-1], -1, feature.shape[-1])
            columns[packed] = self._apply_transform(frames, key, feature.type).reshape(rows.shape)
        return {**transition, TransitionKey.OBSERVATION: columns}


def make_ocn_pre_post_processors(
    config: SequenceConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default policy pipelines, normalising by `config.normalization_mapping`, plus the
    packed columns' normaliser for a policy trained on a packed view."""
    steps = make_default_policy_processor_steps(config, dataset_stats)
    inputs = [steps.rename_observations, steps.add_batch_dim, steps.to_device, steps.normalize]
    if config.packed:
        inputs.append(PackedEpisodeNormalizerStep(
            features={**config.input_features, **config.output_features},
            norm_map=config.normalization_mapping,
            stats=dataset_stats,
        ))
    return make_policy_processor_pipelines(input_steps=inputs, output_steps=[steps.unnormalize, steps.to_cpu])
