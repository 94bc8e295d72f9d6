"""Batched Craft simulator: every game rule lives here, applied to all envs at once.

``CraftBatch`` keeps the state of ``n`` independent envs in numpy arrays and advances them
together with a fixed number of vectorized array operations per step, whatever ``n`` is. The
gymnasium wrappers (a single env is a batch of one), the scripted expert and the data
recorders all drive this one class, so the rules cannot drift apart.

Rules, per env and step:

* A move action (0 down, 1 up, 2 left, 3 right) turns the agent that way and moves it one cell
  if that cell is empty; otherwise it only turns.
* ``use`` (4) acts on the faced cell: a resource (iron, grass, wood, gold, gem) is picked up;
  water with a bridge held becomes empty and uses the bridge up; stone with an axe held becomes
  empty (the axe is kept); a workshop crafts its first recipe whose ingredients are all held.
* The current subtask completes when its event happens while it is current: gathering its
  resource ("get X") or crafting anything at its workshop ("use W"). The same event while a
  different subtask is current counts for nothing, so tasks must be done in order.
* Reward is +1 per completed subtask ("dense") or +1 when the whole task completes ("sparse").
  An env terminates on success and truncates when its step limit is reached.

Envs that are done are frozen: a step ignores their action, leaves their state as it is and
reports reward 0 with terminated and truncated False, until ``reset`` is called for them.

The public arrays (``grid``, ``pos``, ``facing``, ``inventory``, ...) are the live state; tests
and scripted scenarios may edit them in place between steps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lerobot_policy_ocn.envs.batching import EpisodeBatch, env_rng, reset_ids
from lerobot_policy_ocn.envs.craft.layout import sample_map
from lerobot_policy_ocn.envs.craft.observation import (
    AGENT_COL, AGENT_ROW, CELLS, FACING, INVENTORY, INVENTORY_FIRST_KIND, OBS_DIM,
)
from lerobot_policy_ocn.envs.craft.world import (
    AXE,
    BRIDGE,
    EMPTY,
    GATHERABLE_KINDS,
    GRID_SIZE,
    INTERIOR_SIZE,
    MOVE_DELTAS,
    N_ACTIONS,
    N_KINDS,
    RECIPE_INGREDIENTS,
    RECIPE_PRODUCT,
    RECIPE_WORKSHOP,
    REWARDS,
    STONE,
    SUBTASK_TARGET,
    USE,
    WATER,
    WORKSHOP_KINDS,
    check_mode,
    check_task,
    default_max_steps,
    parse_task,
)

_IS_GATHERABLE = np.zeros(N_KINDS, dtype=bool)
_IS_GATHERABLE[list(GATHERABLE_KINDS)] = True
_IS_WORKSHOP = np.zeros(N_KINDS, dtype=bool)
_IS_WORKSHOP[list(WORKSHOP_KINDS)] = True
# Internal action that does nothing, used for frozen (done) envs.
_NOOP = N_ACTIONS
# Target kind per subtask id, with index -1 (task padding / task finished) mapped to -1.
_TARGET_OR_NONE = np.append(SUBTASK_TARGET, -1)


class CraftBatch(EpisodeBatch):
    """State and rules of ``num_envs`` Craft envs, each with its own task and Generator."""

    def __init__(self, num_envs: int, mode: str = "paper", reward: str = "dense", max_steps: int | None = None):
        super().__init__(num_envs, reward, REWARDS, max_steps)
        n = num_envs
        self.mode = check_mode(mode)
        self.grid = np.zeros((n, GRID_SIZE, GRID_SIZE), dtype=np.int8)
        self.pos = np.ones((n, 2), dtype=np.int64)
        self.facing = np.zeros(n, dtype=np.int64)
        self.inventory = np.zeros((n, N_KINDS), dtype=np.int64)
        self._target_kinds = np.full((n, 2), -1, dtype=np.int64)
        self._ready = False

    def reset(
        self,
        seeds: Sequence[int | None] | np.ndarray | None = None,
        tasks: Sequence[Sequence[int] | str] | None = None,
        env_ids: Sequence[int] | np.ndarray | None = None,
    ) -> np.ndarray:
        """Give the selected envs (default: all) new random maps and return all observations.

        ``seeds[i]`` reseeds env ``env_ids[i]``'s Generator; ``None`` (or no seeds) continues it.
        ``tasks[i]`` is a subtask-id tuple or a task string; no tasks keeps each env's task.
        """
        ids = reset_ids(self.num_envs, env_ids, seeds=seeds, tasks=tasks)
        if tasks is not None:
            self._set_tasks(ids, tasks)
        elif (self.task_len[ids] == 0).any():
            raise ValueError("the first reset of an env must give its task")
        for k, i in enumerate(ids.tolist()):
            self.rngs[i] = env_rng(self.rngs[i], None if seeds is None else seeds[k])
            grid, agent, facing = sample_map(self.rngs[i], self.mode)
            self.grid[i] = grid
            self.pos[i] = divmod(agent, GRID_SIZE)
            self.facing[i] = facing
        self.inventory[ids] = 0
        self._restart(ids)
        self._ready = bool((self.task_len > 0).all())
        return self.observe()

    def _set_tasks(self, ids: np.ndarray, tasks: Sequence[Sequence[int] | str]) -> None:
        """Store tasks (strings or subtask-id tuples) in the task table."""
        parsed = [parse_task(t, self.mode) if isinstance(t, str) else check_task(t, self.mode) for t in tasks]
        self._store_tasks(ids, parsed, default_max_steps)
        # One extra -1 column so progress == task_len indexes "no current target".
        self._target_kinds = _TARGET_OR_NONE[np.pad(self.tasks, ((0, 0), (0, 1)), constant_values=-1)]

    def current_target(self) -> np.ndarray:
        """Grid kind the current subtask acts on, per env; -1 once the task is complete."""
        return self._target_kinds[self._arange, self.progress]

    def observe(self) -> np.ndarray:
        """Compact observation (n, OBS_DIM) int64; layout in lerobot_policy_ocn.envs.craft.observation."""
        n = self.num_envs
        obs = np.empty((n, OBS_DIM), dtype=np.int64)
        obs[:, CELLS].reshape(n, INTERIOR_SIZE, INTERIOR_SIZE)[...] = self.grid[:, 1:-1, 1:-1]
        obs[:, AGENT_ROW : AGENT_COL + 1] = self.pos - 1
        obs[:, FACING] = self.facing
        obs[:, INVENTORY] = self.inventory[:, INVENTORY_FIRST_KIND:]
        return obs

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Advance every env by one action; returns (obs, reward, terminated, truncated, info)."""
        n = self.num_envs
        ar = self._arange
        if not self._ready:
            raise RuntimeError("reset every env (giving it a task) before stepping")
        a = np.asarray(actions).reshape(n)
        if a.min() < 0 or a.max() >= N_ACTIONS:
            raise ValueError(f"actions must be in [0, {N_ACTIONS}), got {a}")
        was_done = self.done
        a = np.where(was_done, _NOOP, a)

        move = a < USE
        facing = np.where(move, a, self.facing)
        self.facing = facing
        ahead_pos = self.pos + MOVE_DELTAS[facing]
        ahead_flat = ahead_pos[:, 0] * GRID_SIZE + ahead_pos[:, 1]
        flat_grid = self.grid.reshape(n, GRID_SIZE * GRID_SIZE)
        ahead = flat_grid[ar, ahead_flat].astype(np.int64)

        walks = move & (ahead == EMPTY)
        self.pos = np.where(walks[:, None], ahead_pos, self.pos)

        use = a == USE
        inv = self.inventory
        gather = use & _IS_GATHERABLE[ahead]
        inv[ar, ahead] += gather
        bridged = use & (ahead == WATER) & (inv[:, BRIDGE] > 0)
        inv[:, BRIDGE] -= bridged
        cleared = gather | bridged | (use & (ahead == STONE) & (inv[:, AXE] > 0))
        flat_grid[ar, ahead_flat] = np.where(cleared, EMPTY, ahead)

        event = gather
        at_workshop = use & _IS_WORKSHOP[ahead]
        if at_workshop.any():
            event = gather | self._craft(at_workshop, ahead)

        sub_done = event & (ahead == self._target_kinds[ar, self.progress])
        reward, terminated, truncated, info = self._advance(sub_done, ~was_done)
        return self.observe(), reward, terminated, truncated, info

    def _craft(self, at_workshop: np.ndarray, workshop: np.ndarray) -> np.ndarray:
        """Craft the first feasible recipe of the faced workshop; returns which envs crafted."""
        inv = self.inventory
        feasible = (
            (inv[:, None, :] >= RECIPE_INGREDIENTS[None]).all(axis=2)
            & (RECIPE_WORKSHOP[None] == workshop[:, None])
            & at_workshop[:, None]
        )
        crafted = feasible.any(axis=1)
        recipe = feasible.argmax(axis=1)
        inv -= RECIPE_INGREDIENTS[recipe] * crafted[:, None]
        inv[self._arange, RECIPE_PRODUCT[recipe]] += crafted
        return crafted
