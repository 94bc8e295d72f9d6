"""Policy runs as MCAP logs: what an OCN saw, chose and did at every step of its env rollouts.

Channels (JSON schemas, readable by the `mcap` reader and Foxglove): `/observation` (the state),
`/action`, `/option` (the option distribution p^c, the chosen option argmax p^c and the
termination probability e_t) and `/reward` (reward, done and, on an episode's last step, whether
the task succeeded). Every message carries its episode and frame index and the episode's task;
episodes lie end to end on the log clock. Rollouts run batched, so steps are buffered per batch
(`RolloutTrace`) and written episode by episode when the batch ends.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_policy_ocn.ocn_data.mcap_log import JsonMcapLog, number_array, step_schema

TASK = {"task": {"type": "string"}}


@dataclass
class RolloutTrace:
    """Per-step records of a batch of envs: which rows were still running (`active` [B]) and what
    they saw (`state` [B, S]), did (`action` [B, A]), chose (`p_c` [B, N], `option` [B], `end` [B])
    and got (`reward` [B], `done` [B] after the step)."""

    active: list[np.ndarray] = field(default_factory=list)
    state: list[np.ndarray] = field(default_factory=list)
    action: list[np.ndarray] = field(default_factory=list)
    p_c: list[np.ndarray] = field(default_factory=list)
    option: list[np.ndarray] = field(default_factory=list)
    end: list[np.ndarray] = field(default_factory=list)
    reward: list[np.ndarray] = field(default_factory=list)
    done: list[np.ndarray] = field(default_factory=list)

    def add(self, **step: np.ndarray) -> None:
        for name, value in step.items():
            getattr(self, name).append(np.asarray(value))

    def rows(self, index: np.ndarray | slice) -> RolloutTrace:
        """The records of the selected envs only (a batch that ran several tasks, split by task)."""
        return RolloutTrace(**{name: [step[index] for step in steps] for name, steps in vars(self).items()})


class RolloutMcapWriter(JsonMcapLog):
    """An MCAP file of policy rollouts; `write(task, trace, success)` after each batch, then `close()`."""

    def __init__(self, path: str | Path, fps: int, state_names: list[str], policy: str) -> None:
        channels = {
            "/observation": step_schema("Observation", {**TASK, "state": number_array()}),
            "/action": step_schema("Action", {**TASK, "action": number_array()}),
            "/option": step_schema(
                "Option",
                {**TASK, "p_c": number_array(), "option": {"type": "integer"}, "termination": {"type": "number"}},
            ),
            "/reward": step_schema(
                "Reward",
                {
                    **TASK,
                    "reward": {"type": "number"},
                    "done": {"type": "boolean"},
                    "success": {"type": ["boolean", "null"]},
                },
            ),
        }
        super().__init__(path, fps, channels, library="ocn rollouts")
        self.add_metadata("observation.state", {"names": json.dumps(list(state_names))})
        self.add_metadata("policy", {"path": policy})
        self.episodes = 0

    def write(self, task: str, trace: RolloutTrace, success: np.ndarray) -> None:
        """Every env of the batch as one episode, in row order, with only the steps it was running."""
        active = np.stack(trace.active, axis=1)
        columns = {
            name: np.stack(getattr(trace, name), axis=1)
            for name in ("state", "action", "p_c", "option", "end", "reward", "done")
        }
        for row in range(active.shape[0]):
            steps = np.flatnonzero(active[row])
            for frame, t in enumerate(steps):
                meta = {"episode_index": self.episodes, "frame_index": frame, "task": task}
                last = frame == len(steps) - 1
                self.put_frame(
                    {
                        "/observation": {**meta, "state": columns["state"][row, t].reshape(-1).tolist()},
                        "/action": {**meta, "action": columns["action"][row, t].reshape(-1).tolist()},
                        "/option": {
                            **meta,
                            "p_c": columns["p_c"][row, t].tolist(),
                            "option": int(columns["option"][row, t]),
                            "termination": float(columns["end"][row, t]),
                        },
                        "/reward": {
                            **meta,
                            "reward": float(columns["reward"][row, t]),
                            "done": bool(columns["done"][row, t]),
                            "success": bool(success[row]) if last else None,
                        },
                    }
                )
            self.episodes += 1
