"""Session-wide fixtures: a small recorded Craft dataset, an `ocn` checkpoint built on it, and a
`compile` checkpoint trained on it; a tiny recorded Dial dataset.

The `ocn` checkpoint is written the way `lerobot-train` writes one (policy config and weights plus
the pre/post-processor pipelines, all in one `pretrained_model` folder) but without training: tools
that read a checkpoint need a valid one, not a good one. Tests that need `lerobot-train` itself for
OCN live in test_lerobot_integration.py; the `compile` checkpoint comes from a 3-step
`lerobot-train` run, shared by the compILE tests and compILE's finetuning tests.
"""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
import torch

import lerobot_policy_ocn
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn_data.record_demos import main as record_demos

lerobot_policy_ocn.register()  # the project's policy and env types, as LeRobot's CLIs register them

CRAFT_REPO_ID = "local/craft_small"
# What a policy of Craft's compact state and actions takes from a dataset, for policies built in memory.
CRAFT_STATE = {"obs_encoder": "craft", "action_type": "discrete", "n_actions": 5}
# The Dial recipe caches its affine fits beside LeRobot's cache (`lerobot_policy_ocn.ocn.taught.split_cache_dir`): the
# tests, and the processes they start, keep theirs in a folder of their own.
os.environ["HF_LEROBOT_HOME"] = tempfile.mkdtemp(prefix="ocn_tests_lerobot_home_")
atexit.register(shutil.rmtree, os.environ["HF_LEROBOT_HOME"], ignore_errors=True)
DIAL_REPO_ID = "local/dial_ocn_test"


def run_cli(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """One of the environment's console scripts as a subprocess; a failure shows its stderr's tail."""
    proc = subprocess.run([str(Path(sys.executable).parent / name), *args], capture_output=True, text=True,
                          timeout=300, cwd=cwd)
    assert proc.returncode == 0, f"{name} failed ({proc.returncode}):\n{proc.stderr[-4000:]}"
    return proc


def train_on_craft(policy_type: str, root: Path, out: Path, steps: int, *flags: str) -> Path:
    """`lerobot-train --policy.type=POLICY_TYPE` for a few steps of batch 4 on the Craft dataset at
    `root` (plus the policy's own `flags`); returns the final checkpoint's pretrained_model folder."""
    command = [
        str(Path(sys.executable).parent / "lerobot-train"), f"--policy.type={policy_type}",
        f"--dataset.repo_id={CRAFT_REPO_ID}", f"--dataset.root={root}", "--policy.device=cpu",
        "--policy.push_to_hub=false", "--wandb.enable=false", "--env_eval_freq=0", f"--steps={steps}",
        "--batch_size=4", "--num_workers=0", f"--output_dir={out}", *flags,
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}  # one thread: far faster than two on a shared machine
    proc = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=out.parent, env=env)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return out / "checkpoints" / f"{steps:06d}" / "pretrained_model"


def reload_checkpoint(path: Path, policy_class: type) -> tuple[torch.nn.Module, Any]:
    """A trained checkpoint loaded as the tools load it (`load_policy`), after checking that it is a
    `policy_class` and that LeRobot's own `from_pretrained` reads the same weights; returns the
    policy and its preprocessor."""
    from lerobot_policy_ocn.tools.eval.parsing import load_policy

    policy, preprocessor, _ = load_policy(path)
    assert isinstance(policy, policy_class)
    again = policy_class.from_pretrained(path)
    for key, value in policy.state_dict().items():
        torch.testing.assert_close(value, again.state_dict()[key], rtol=0, atol=0, msg=key)
    return policy, preprocessor


def episode_windows(lengths: list[int], state_dim: int, tasks: Sequence[str], steps: int = 6, seed: int = 1) -> dict:
    """A batch of windows that each start an episode, real for their first lengths[b] frames: random
    states, actions among 4, and the tasks taken in turn."""
    gen = torch.Generator().manual_seed(seed)
    return {
        OBS_STATE: torch.randn(len(lengths), steps, state_dim, generator=gen),
        ACTION: torch.randint(0, 4, (len(lengths), steps, 1), generator=gen).float(),
        f"{ACTION}_is_pad": torch.arange(steps)[None] >= torch.tensor(lengths)[:, None],
        "task": [tasks[i % len(tasks)] for i in range(len(lengths))],
    }


def craft_rollout(policy: torch.nn.Module) -> dict:
    """What `lerobot-eval` runs: one batched rollout of the policy in 2 Craft envs on task AC, which
    must run both episodes to their end."""
    from lerobot.envs.factory import make_env, make_env_config
    from lerobot.scripts.lerobot_eval import rollout

    vec = make_env(make_env_config("craft", task="AC"), n_envs=2)["craft"][0]
    out = rollout(vec, policy, lambda x: x, lambda x: x, lambda x: x, lambda x: x, seeds=[0, 1])
    vec.close()
    assert out["action"].shape[0] == 2 and out["done"].any(1).all()
    return out


@pytest.fixture(scope="session", autouse=True)
def temporary_files_under_pytest(tmp_path_factory) -> Iterator[None]:
    """Temporary files, the tests' and those of every process they start, go to this session's pytest
    folder, which pytest prunes: LeRobot's `PreTrainedConfig.from_pretrained` leaves one JSON file in
    the system's temporary folder at each call (about 1,600 a run of the suite)."""
    folder = str(tmp_path_factory.mktemp("tempfiles"))
    before = os.environ.get("TMPDIR")
    os.environ["TMPDIR"], tempfile.tempdir = folder, folder
    yield
    tempfile.tempdir = None
    if before is None:
        os.environ.pop("TMPDIR")
    else:
        os.environ["TMPDIR"] = before


@pytest.fixture(scope="session")
def craft_dataset(tmp_path_factory) -> Path:
    """Root of a recorded Craft dataset: 10 episodes each of AC and CD, train/val split, with MCAP."""
    root = tmp_path_factory.mktemp("craft") / "ds"
    args = ["--tasks", "AC,CD", "--episodes-per-task", "10", "--root", str(root), "--repo-id", CRAFT_REPO_ID,
            "--seed", "3", "--subtask-annotations"]
    assert record_demos(args) == 0
    return root


@pytest.fixture(scope="session")
def dial_dataset(tmp_path_factory) -> Path:
    """Root of a recorded Dial dataset: 3 expert episodes each of PINs 12 and 21."""
    root = tmp_path_factory.mktemp("dial") / "ds"
    args = ["--env", "dial", "--tasks", "12,21", "--episodes-per-task", "3", "--root", str(root),
            "--repo-id", DIAL_REPO_ID]
    assert record_demos(args) == 0
    return root


def untrained_checkpoint(
    config: Any, root: Path, path: Path, adjust: Callable[[torch.nn.Module], None] | None = None
) -> Path:
    """A `pretrained_model` folder at `path` of a policy of `config` for the Craft dataset at `root`,
    with weights seeded by 0 (and changed by `adjust`), as `lerobot-train` writes one."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    torch.manual_seed(0)
    meta = LeRobotDatasetMetadata(CRAFT_REPO_ID, root=root)
    policy = make_policy(config, ds_meta=meta)
    if adjust is not None:
        with torch.no_grad():
            adjust(policy)
    policy.save_pretrained(path)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    preprocessor.save_pretrained(path)
    postprocessor.save_pretrained(path)
    return path


@pytest.fixture(scope="session")
def ocn_checkpoint(craft_dataset, tmp_path_factory) -> Path:
    """A `pretrained_model` folder of a small, untrained OCN (seeded weights) for `craft_dataset`."""
    from lerobot_policy_ocn.ocn import OCNConfig

    def sharpen(policy: torch.nn.Module) -> None:
        """Sharpen the random controller so that its chosen option switches within episodes."""
        policy.core.controller_init.normal_()
        for weight in policy.core.controller.parameters():
            weight.mul_(10.0)

    config = OCNConfig(device="cpu", hidden_size=16, mlp_hidden_size=16, n_options=3, temperature=1.0)
    return untrained_checkpoint(config, craft_dataset, tmp_path_factory.mktemp("ocn") / "pretrained_model", sharpen)


@pytest.fixture(scope="session")
def compile_checkpoint(craft_dataset, tmp_path_factory) -> Path:
    """3 steps of `lerobot-train --policy.type=compile` (4 concrete latents) on `craft_dataset`."""
    out = tmp_path_factory.mktemp("compile_train") / "train"
    flags = ("--policy.hidden_size=16", "--policy.latent_dim=4")
    return train_on_craft("compile", craft_dataset, out, 3, *flags)
