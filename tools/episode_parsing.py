"""A trained OCN read back over recorded episodes: one place for loading a checkpoint and parsing.

`ocn-eval` scores the parse, `ocn-view` draws it and `ocn-annotate` writes it into a dataset; all
three load the checkpoint and its processors with `load_ocn` and get the per-step hierarchy of
whole episodes from `parse_episodes`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lerobot.utils.constants import ACTION, OBS_STATE
from ocn_data.episodes_table import EpisodeArrays
from policies.ocn import OCNPolicy
from tools.parsing_metrics import segment_starts

Processor = Callable[[Any], Any]


@dataclass
class EpisodeParse:
    """One episode's hierarchy, per real step: p_c [T, N], option = argmax p^c [T], end = e_t [T]
    (1 at t = 1, where the controller always chooses)."""

    p_c: np.ndarray
    option: np.ndarray
    end: np.ndarray

    @property
    def switches(self) -> np.ndarray:
        """Steps t >= 1 (0-based) where the chosen option differs from the step before."""
        return segment_starts(self.option)[1:]


def load_ocn(path: Path, device: str = "cpu") -> tuple[OCNPolicy, Processor, Processor]:
    """An `ocn` checkpoint (a `pretrained_model` folder) in eval mode, with its pre/post-processors."""
    from lerobot.policies.factory import make_pre_post_processors

    path = Path(path)
    if not (path / "config.json").exists():
        raise FileNotFoundError(f"{path} holds no config.json: pass a checkpoint's pretrained_model folder.")
    policy = OCNPolicy.from_pretrained(path)
    policy.config.device = device
    policy.to(device).eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy.config, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}}
    )
    return policy, preprocessor, postprocessor


def check_tasks(policy: OCNPolicy, episodes: EpisodeArrays) -> None:
    """Every task of the episodes must have an initial controller state in the policy."""
    unknown = sorted(set(episodes.tasks) - set(policy.config.tasks))
    if unknown:
        raise ValueError(f"The dataset has tasks {unknown} that the policy was not trained on ({policy.config.tasks}).")


@torch.no_grad()
def parse_episodes(
    policy: OCNPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int = 1024
) -> list[EpisodeParse]:
    """The policy's hierarchy over each whole episode, cut to the episode's real steps."""
    check_tasks(policy, episodes)
    parses = []
    for start in range(0, len(episodes.tasks), batch_size):
        rows = slice(start, start + batch_size)
        batch = {
            OBS_STATE: torch.from_numpy(episodes.state[rows]).float(),
            ACTION: torch.from_numpy(episodes.action[rows]).float(),
            f"{ACTION}_is_pad": torch.from_numpy(~episodes.mask[rows]),
            "task": episodes.tasks[rows],
        }
        parsed = {key: value.cpu().numpy() for key, value in policy.parse(preprocessor(batch)).items()}
        for i, length in enumerate(episodes.lengths[rows]):
            parses.append(EpisodeParse(parsed["p_c"][i, :length], parsed["option"][i, :length], parsed["end"][i, :length]))
    return parses
