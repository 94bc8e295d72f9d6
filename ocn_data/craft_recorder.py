"""Run the Craft expert over a batch of envs and collect its successful episodes in chunks.

Per step, the whole batch is written into per-slot step buffers with one vectorised assignment
per column; Python only runs once per finished episode (copying its rows out and resetting the
slot with the next queued task). Tasks are queued interleaved (AC, CD, DA, AC, ...) so any prefix
of the recording, and so the validation split at its end, holds every task equally. An episode
the expert fails is not kept; its task goes back in the queue with a fresh map.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from envs.craft import CraftBatch, CraftExpert
from envs.craft.observation import OBS_DIM, OBS_NAMES
from envs.craft.render import render_batch
from envs.craft.world import SUBTASK_NAMES, default_max_steps, task_description
from ocn_data.episodes import EpisodeChunk

FPS = 10
IMAGE_KEY = "observation.image"


def craft_features(image_shape: tuple[int, int, int] | None = None) -> dict[str, dict]:
    """LeRobot features of a Craft demonstration dataset.

    `subtask.*` columns are ground truth for evaluation only: their names do not start with
    `observation.`, so LeRobot's processors never hand them to a policy.
    """
    features = {
        "observation.state": {"dtype": "int64", "shape": (OBS_DIM,), "names": list(OBS_NAMES)},
        "action": {"dtype": "int64", "shape": (1,), "names": ["action"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "subtask.index": {"dtype": "int64", "shape": (1,), "names": None},
        "subtask.id": {"dtype": "int64", "shape": (1,), "names": None},
        "subtask.end": {"dtype": "bool", "shape": (1,), "names": None},
    }
    if image_shape is not None:
        features[IMAGE_KEY] = {"dtype": "video", "shape": image_shape, "names": ["height", "width", "channels"]}
    return features


def attempt_seed(seed: int, attempt: int) -> int:
    """Map seed of the `attempt`-th episode attempt: independent streams for every (seed, attempt)."""
    return int(np.random.SeedSequence([seed, attempt]).generate_state(1)[0])


@dataclass
class _Episode:
    task: str
    rows: dict[str, np.ndarray]
    frames: np.ndarray | None


class CraftRecorder:
    """Collects `episodes_per_task` successful expert episodes of each task, chunk by chunk."""

    def __init__(
        self,
        tasks: list[tuple[int, ...]],
        episodes_per_task: int,
        *,
        mode: str = "paper",
        reward: str = "dense",
        seed: int = 0,
        first_attempt: int = 0,
        batch_size: int = 256,
        video: bool = False,
        max_failures: int = 1000,
    ) -> None:
        self.queue: deque[tuple[int, ...]] = deque(
            task for _ in range(episodes_per_task) for task in tasks
        )
        self.total = len(self.queue)
        self.seed = seed
        self.attempts = first_attempt
        self.failures = 0
        self.max_failures = max_failures
        self.video = video
        self.finished: list[_Episode] = []
        n = max(1, min(batch_size, self.total))
        self.batch = CraftBatch(n, mode=mode, reward=reward)
        self.expert = CraftExpert(self.batch)
        horizon = max(default_max_steps(len(t)) for t in tasks) + 1
        self.buffers = {
            "observation.state": np.zeros((n, horizon, OBS_DIM), dtype=np.int64),
            "action": np.zeros((n, horizon), dtype=np.int64),
            "next.reward": np.zeros((n, horizon), dtype=np.float32),
            "next.done": np.zeros((n, horizon), dtype=bool),
            "subtask.index": np.zeros((n, horizon), dtype=np.int64),
            "subtask.id": np.zeros((n, horizon), dtype=np.int64),
            "subtask.end": np.zeros((n, horizon), dtype=bool),
        }
        self.frames = None
        self.active = np.zeros(n, dtype=bool)
        self.t = np.zeros(n, dtype=np.int64)
        self._start(np.arange(n))

    def _start(self, slots: np.ndarray) -> None:
        """Reset the given slots with the next queued tasks; slots left without a task go idle."""
        slots = slots[: len(self.queue)]
        if len(slots) == 0:
            return
        tasks = [self.queue.popleft() for _ in slots]
        seeds = [attempt_seed(self.seed, self.attempts + k) for k in range(len(slots))]
        self.attempts += len(slots)
        self.batch.reset(seeds=seeds, tasks=tasks, env_ids=slots)
        self.active[slots] = True
        self.t[slots] = 0

    def _step(self) -> None:
        b = self.batch
        slots = np.flatnonzero(self.active)
        t = self.t[slots]
        obs = b.observe()
        if self.video:
            image = render_batch(b.grid, b.pos, b.facing)
            if self.frames is None:
                self.frames = np.zeros((b.num_envs, self.buffers["action"].shape[1], *image.shape[1:]), np.uint8)
            self.frames[slots, t] = image[slots]
        action = self.expert.act()
        _, reward, terminated, truncated, info = b.step(action)
        sub = info["subtask_index"]
        buf = self.buffers
        buf["observation.state"][slots, t] = obs[slots]
        buf["action"][slots, t] = action[slots]
        buf["next.reward"][slots, t] = reward[slots]
        buf["next.done"][slots, t] = terminated[slots]
        buf["subtask.index"][slots, t] = sub[slots]
        buf["subtask.id"][slots, t] = b.tasks[slots, sub[slots]]
        buf["subtask.end"][slots, t] = info["subtask_done"][slots]
        self.t[slots] += 1
        ended = slots[(terminated | truncated)[slots]]
        for slot in ended.tolist():
            if terminated[slot]:
                self.finished.append(self._take(slot))
            else:
                self._fail(slot)
        self.active[ended] = False
        self._start(ended)

    def _take(self, slot: int) -> _Episode:
        length = int(self.t[slot])
        task = task_description(self.batch.task_of(slot))
        rows = {key: buf[slot, :length].copy() for key, buf in self.buffers.items()}
        frames = None if self.frames is None else self.frames[slot, :length].copy()
        return _Episode(task, rows, frames)

    def _fail(self, slot: int) -> None:
        self.failures += 1
        task = self.batch.task_of(slot)
        if self.failures > self.max_failures:
            raise RuntimeError(
                f"the Craft expert failed {self.failures} episodes (last task {task_description(task)!r}); "
                "is the task feasible in this mode?"
            )
        self.queue.append(task)

    @property
    def done(self) -> bool:
        return not self.active.any()

    def chunks(self, chunk_episodes: int = 2000) -> Iterator[EpisodeChunk]:
        """Step until every queued episode is recorded, yielding a chunk every `chunk_episodes`."""
        while not self.done:
            self._step()
            if len(self.finished) >= chunk_episodes:
                yield self.take_finished()
        if self.finished:
            yield self.take_finished()

    def take_finished(self) -> EpisodeChunk:
        """The finished episodes not yet handed out, as one chunk (empty if none)."""
        episodes, self.finished = self.finished, []
        lengths = np.array([len(e.rows["action"]) for e in episodes], dtype=np.int64)
        columns = {}
        for key in self.buffers:
            stacked = np.concatenate([e.rows[key] for e in episodes]) if episodes else self.buffers[key][0, :0]
            columns[key] = stacked if stacked.ndim > 1 else stacked[:, None]
        videos = {}
        if self.video:
            videos[IMAGE_KEY] = np.concatenate([e.frames for e in episodes]) if episodes else np.zeros((0, 1, 1, 3))
        segments = [_segments(e.rows["subtask.index"], e.rows["subtask.id"]) for e in episodes]
        return EpisodeChunk(lengths, [e.task for e in episodes], columns, segments, videos)


def _segments(index: np.ndarray, ids: np.ndarray) -> list[tuple[int, str]]:
    """(start frame, subtask name) of each ground-truth segment of one episode."""
    starts = np.flatnonzero(np.diff(index, prepend=-1))
    return [(int(s), SUBTASK_NAMES[int(ids[s])]) for s in starts]
