"""Pre/post-processing pipelines of the OCN policy (and of OMPN and compILE, which use them too).

LeRobot's default pipelines (rename -> batch -> device -> normalise; unnormalise -> cpu) are all OCN
needs: no tokenizer step, so the raw task strings reach `forward` and `select_action` in
`batch["task"]`, where the policy maps them to its per-task initial controller states. The episodes
a policy holds in memory for training are normalised once, with the same statistics and modes, when
it reads them (`lerobot_policy_ocn.sequence.SequencePolicy`).
"""

from typing import Any

import torch

from lerobot.processor import (
    PolicyAction,
    PolicyProcessorPipeline,
)
from lerobot.processor.factory import make_default_policy_processor_steps, make_policy_processor_pipelines

from lerobot_policy_ocn.sequence import SequenceConfig


def make_ocn_pre_post_processors(
    config: SequenceConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default policy pipelines, normalising by `config.normalization_mapping`."""
    steps = make_default_policy_processor_steps(config, dataset_stats)
    inputs = [steps.rename_observations, steps.add_batch_dim, steps.to_device, steps.normalize]
    return make_policy_processor_pipelines(input_steps=inputs, output_steps=[steps.unnormalize, steps.to_cpu])
