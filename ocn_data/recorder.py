"""Run a scripted expert over a batch of envs and collect its successful episodes in chunks.

World-agnostic: a world's recorder (`CraftRecorder`, `DialRecorder`) supplies the batch simulator,
its expert and a few hooks; this class does the rest. Per step, the whole batch is written into
per-slot step buffers with one vectorised assignment per column; Python only runs once per
finished episode (copying its rows out and resetting the slot with the next queued task). Tasks
are consumed in queue order, so any prefix of the recording, and so the validation split at its
end, holds the tasks as the queue mixes them. An episode the expert fails is not kept; its task
goes back in the queue with a fresh seed.

Every batch has `num_envs`, `tasks` ([n, L] subtask ids padded with -1), `task_of(slot)`,
`observe()` and `step(actions)` returning (obs, reward, terminated, truncated, info) with
`info["subtask_index"]` and `info["subtask_done"]`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lerobot_policy_ocn.ocn_data.episodes import EpisodeChunk

IMAGE_KEY = "observation.image"
# Columns every recorder writes besides the state and the action: ground truth for evaluation only.
LABEL_FEATURES = {
    "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
    "next.done": {"dtype": "bool", "shape": (1,), "names": None},
    "subtask.index": {"dtype": "int64", "shape": (1,), "names": None},
    "subtask.id": {"dtype": "int64", "shape": (1,), "names": None},
    "subtask.end": {"dtype": "bool", "shape": (1,), "names": None},
}


def attempt_seed(seed: int, attempt: int) -> int:
    """Seed of the `attempt`-th episode attempt: independent streams for every (seed, attempt)."""
    return int(np.random.SeedSequence([seed, attempt]).generate_state(1)[0])


@dataclass
class _Episode:
    task: str
    rows: dict[str, np.ndarray]
    frames: np.ndarray | None


class ExpertRecorder:
    """Collects one successful expert episode per queued task, chunk by chunk.

    Subclasses define `_reset(slots, seeds, tasks)`, `_act()` (the recorded and the executed
    action), `_describe(task)` (the LeRobot task string) and, for video, `_render()`.
    """

    world = "world"
    subtask_names: Sequence[str] = ()

    def __init__(
        self,
        queue: Iterable[Any],
        batch: Any,
        features: dict[str, dict],
        horizon: int,
        *,
        seed: int = 0,
        first_attempt: int = 0,
        video: bool = False,
        max_failures: int = 1000,
    ) -> None:
        self.queue: deque[Any] = deque(queue)
        self.total = len(self.queue)
        self.seed = seed
        self.attempts = first_attempt
        self.failures = 0
        self.max_failures = max_failures
        self.video = video
        self.finished: list[_Episode] = []
        self.batch = batch
        n = batch.num_envs
        self.buffers = {
            key: np.zeros((n, horizon + 1, *[d for d in ft["shape"] if ft["shape"] != (1,)]), dtype=ft["dtype"])
            for key, ft in features.items()
            if ft["dtype"] != "video"
        }
        self.frames = None
        self.active = np.zeros(n, dtype=bool)
        self.t = np.zeros(n, dtype=np.int64)
        self._start(np.arange(n))

    def _reset(self, slots: np.ndarray, seeds: list[int], tasks: list[Any]) -> None:
        raise NotImplementedError

    def _act(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _describe(self, task: tuple[int, ...]) -> str:
        raise NotImplementedError

    def _render(self) -> np.ndarray:
        raise NotImplementedError(f"{self.world} recordings have no video")

    def _start(self, slots: np.ndarray) -> None:
        """Reset the given slots with the next queued tasks; slots left without a task go idle."""
        slots = slots[: len(self.queue)]
        if len(slots) == 0:
            return
        tasks = [self.queue.popleft() for _ in slots]
        seeds = [attempt_seed(self.seed, self.attempts + k) for k in range(len(slots))]
        self.attempts += len(slots)
        self._reset(slots, seeds, tasks)
        self.active[slots] = True
        self.t[slots] = 0

    def _step(self) -> None:
        b = self.batch
        slots = np.flatnonzero(self.active)
        t = self.t[slots]
        obs = b.observe()
        if self.video:
            image = self._render()
            if self.frames is None:
                self.frames = np.zeros((b.num_envs, self.buffers["action"].shape[1], *image.shape[1:]), np.uint8)
            self.frames[slots, t] = image[slots]
        recorded, executed = self._act()
        _, reward, terminated, truncated, info = b.step(executed)
        sub = info["subtask_index"]
        buf = self.buffers
        buf["observation.state"][slots, t] = obs[slots]
        buf["action"][slots, t] = recorded[slots]
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
        task = self._describe(self.batch.task_of(slot))
        rows = {key: buf[slot, :length].copy() for key, buf in self.buffers.items()}
        frames = None if self.frames is None else self.frames[slot, :length].copy()
        return _Episode(task, rows, frames)

    def _fail(self, slot: int) -> None:
        self.failures += 1
        task = self.batch.task_of(slot)
        if self.failures > self.max_failures:
            raise RuntimeError(
                f"the {self.world} expert failed {self.failures} episodes (last task {self._describe(task)!r}); "
                "is the task feasible?"
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
        segments = [self._segments(e.rows["subtask.index"], e.rows["subtask.id"]) for e in episodes]
        return EpisodeChunk(lengths, [e.task for e in episodes], columns, segments, videos)

    def _segments(self, index: np.ndarray, ids: np.ndarray) -> list[tuple[int, str]]:
        """(start frame, subtask name) of each ground-truth segment of one episode."""
        starts = np.flatnonzero(np.diff(index, prepend=-1))
        return [(int(s), self.subtask_names[int(ids[s])]) for s in starts]
