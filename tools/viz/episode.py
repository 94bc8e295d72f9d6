"""One episode as the viewer draws it: its recorded steps, its ground truth if any, a policy's parse."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from lerobot_policy_ocn.tools.eval.parsing import EpisodeParse


@dataclass
class Episode:
    """One episode to log, cut to its real steps: state [T, S] (None where the dataset has no
    `observation.state`), action [T, A], subtask_index and subtask_id [T] (None without ground truth),
    and the policy's parse (None without a policy)."""

    index: int
    task: str
    state: np.ndarray | None
    action: np.ndarray
    subtask_index: np.ndarray | None
    subtask_id: np.ndarray | None
    parse: EpisodeParse | None

    @property
    def length(self) -> int:
        """Steps of the episode (the action may hold several values per step)."""
        return len(self.action)

    @property
    def title(self) -> str:
        """How lanes, logs and the PNG name the episode."""
        return f"episode {self.index}: {self.task}"
