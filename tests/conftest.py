"""Session-wide fixtures: a small recorded Craft dataset and an `ocn` checkpoint built on it.

The checkpoint is written the way `lerobot-train` writes one (policy config and weights plus the
pre/post-processor pipelines, all in one `pretrained_model` folder) but without training: tools
that read a checkpoint need a valid one, not a good one. Tests that need `lerobot-train` itself
live in test_lerobot_integration.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import lerobot_policy_ocn  # noqa: F401  (registers `ocn` and `craft` as LeRobot's CLIs do)
from ocn_data.record_demos import main as record_demos

CRAFT_REPO_ID = "local/craft_small"


@pytest.fixture(scope="session")
def craft_dataset(tmp_path_factory) -> Path:
    """Root of a recorded Craft dataset: 10 episodes each of AC and CD, train/val split, with MCAP."""
    root = tmp_path_factory.mktemp("craft") / "ds"
    args = ["--tasks", "AC,CD", "--episodes-per-task", "10", "--root", str(root), "--repo-id", CRAFT_REPO_ID,
            "--seed", "3", "--subtask-annotations"]
    assert record_demos(args) == 0
    return root


@pytest.fixture(scope="session")
def ocn_checkpoint(craft_dataset, tmp_path_factory) -> Path:
    """A `pretrained_model` folder of a small, untrained OCN (seeded weights) for `craft_dataset`."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from policies.ocn import OCNConfig

    torch.manual_seed(0)
    meta = LeRobotDatasetMetadata(CRAFT_REPO_ID, root=craft_dataset)
    config = OCNConfig(device="cpu", hidden_size=16, mlp_hidden_size=16, n_options=3, window_size=24, temperature=1.0)
    policy = make_policy(config, ds_meta=meta)
    with torch.no_grad():  # sharpen the random controller so that its chosen option switches within episodes
        policy.core.controller_init.normal_()
        for weight in policy.core.controller.parameters():
            weight.mul_(10.0)
    path = tmp_path_factory.mktemp("ocn") / "pretrained_model"
    policy.save_pretrained(path)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    preprocessor.save_pretrained(path)
    postprocessor.save_pretrained(path)
    return path
