"""Pre/post-processing pipelines of the OCN policy.

LeRobot's default pipelines (rename -> batch -> device -> normalise; unnormalise -> cpu) are all OCN
needs: no tokenizer step, so the raw task strings reach `forward` and `select_action` in
`batch["task"]`, where the policy maps them to its per-task initial controller states.
"""

from typing import Any

import torch

from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from policies.sequence import SequenceConfig


def make_ocn_pre_post_processors(
    config: SequenceConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default policy pipelines, normalising by `config.normalization_mapping`."""
    return make_default_pre_post_processors(config, dataset_stats)
