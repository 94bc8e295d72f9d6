"""Scripted shortest-path expert for Craft, acting for a whole ``CraftBatch`` at once.

For each env it keeps a BFS distance field (n, 10, 10) to the goal set of the current subtask:
passable cells next to a target cell (the resource for "get X", the workshop for "use W").
Fields are grown layer by layer for all stale envs together with shifted boolean arrays, and
are reused until the subtask target, the grid or the held bridge/axe changes.

Per step the agent, in order of priority:

* next to a target: turns to face it (a move into a blocked cell only turns), then uses it;
* otherwise steps to a neighbour one closer to the goal set (ties broken in action order); water
  (with a bridge held) and stone (with an axe held) count as passable, and when the next cell is
  one of them the agent faces it and uses it to clear the way first;
* with no path (e.g. the prerequisites of "get gold" were skipped), it plays ``use``.
"""

from __future__ import annotations

import numpy as np

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.world import AXE, BRIDGE, EMPTY, GRID_SIZE, STONE, USE, WATER

UNREACHABLE = np.iinfo(np.int16).max
# Flat-index offsets of the 4 neighbours, in move-action order (down, up, left, right).
_NEIGHBOUR_OFFSETS = np.array([GRID_SIZE, -GRID_SIZE, -1, 1], dtype=np.int64)


def _neighbours_any(mask: np.ndarray) -> np.ndarray:
    """Interior cells with a 4-neighbour in ``mask`` (n, 10, 10); border cells are False."""
    out = np.zeros_like(mask)
    out[:, 1:-1, 1:-1] = mask[:, 2:, 1:-1] | mask[:, :-2, 1:-1] | mask[:, 1:-1, :-2] | mask[:, 1:-1, 2:]
    return out


class CraftExpert:
    """Expert policy for every env of ``batch``; call ``act()`` before each ``batch.step``."""

    def __init__(self, batch: CraftBatch):
        self.batch = batch
        n = batch.num_envs
        cells = GRID_SIZE * GRID_SIZE
        self._dist = np.full((n, cells), UNREACHABLE, dtype=np.int16)
        # What each cached field was computed for; -1 never matches a real grid or target.
        self._key_grid = np.full((n, cells), -1, dtype=np.int8)
        self._key_target = np.full(n, -2, dtype=np.int64)
        self._key_bridge = np.zeros(n, dtype=bool)
        self._key_axe = np.zeros(n, dtype=bool)

    def act(self) -> np.ndarray:
        """Expert action (n,) int64 for the batch's current state."""
        b = self.batch
        n = b.num_envs
        ar = np.arange(n)
        grid = b.grid.reshape(n, GRID_SIZE * GRID_SIZE)
        target = b.current_target()
        bridge = b.inventory[:, BRIDGE] > 0
        axe = b.inventory[:, AXE] > 0
        stale = (
            (target != self._key_target)
            | (bridge != self._key_bridge)
            | (axe != self._key_axe)
            | (grid != self._key_grid).any(axis=1)
        )
        if stale.any():
            self._refresh(np.flatnonzero(stale), grid, target, bridge, axe)

        here = b.pos[:, 0] * GRID_SIZE + b.pos[:, 1]
        around = here[:, None] + _NEIGHBOUR_OFFSETS
        around_kind = grid[ar[:, None], around]
        around_dist = self._dist[ar[:, None], around]
        facing = b.facing

        is_target = around_kind == target[:, None]
        at_target = np.where(is_target[ar, facing], USE, is_target.argmax(axis=1))

        dist_here = self._dist[ar, here].astype(np.int64)
        step = (around_dist == dist_here[:, None] - 1).argmax(axis=1)
        blocked = around_kind[ar, step] != EMPTY
        walk = np.where(blocked & (facing == step), USE, step)

        reachable = dist_here < UNREACHABLE
        return np.where(is_target.any(axis=1), at_target, np.where(reachable, walk, USE)).astype(np.int64)

    def _refresh(
        self, ids: np.ndarray, grid: np.ndarray, target: np.ndarray, bridge: np.ndarray, axe: np.ndarray
    ) -> None:
        """Recompute the distance fields of envs ``ids`` by breadth-first layers."""
        k = len(ids)
        g = grid[ids].reshape(k, GRID_SIZE, GRID_SIZE)
        passable = (
            (g == EMPTY) | ((g == WATER) & bridge[ids, None, None]) | ((g == STONE) & axe[ids, None, None])
        )
        frontier = passable & _neighbours_any(g == target[ids, None, None])
        reached = frontier.copy()
        dist = np.full((k, GRID_SIZE, GRID_SIZE), UNREACHABLE, dtype=np.int16)
        dist[frontier] = 0
        layer = 0
        while frontier.any():
            layer += 1
            frontier = _neighbours_any(frontier) & passable & ~reached
            reached |= frontier
            dist[frontier] = layer
        self._dist[ids] = dist.reshape(k, -1)
        self._key_grid[ids] = grid[ids]
        self._key_target[ids] = target[ids]
        self._key_bridge[ids] = bridge[ids]
        self._key_axe[ids] = axe[ids]
