"""RGB pictures of Craft states for videos and debugging.

Each cell is a 16x16 tile filled with its kind's palette colour (darker tile edges make the grid
readable); the agent is a red disc with a dark bar pointing the way it faces. The border, always
boundary, shows the inventory: each carried kind (7 .. 20) has a border tile of its own, drawn in the
kind's colour while the agent holds at least one (top row, columns 1-8: kinds 7-14; bottom row,
columns 1-6: kinds 15-20). Without it a frame would not show what has been collected, which the
compact state holds and which tells one subtask from the next. A whole batch of images is one lookup
into prebuilt uint8 tiles plus one transpose, with no per-pixel Python.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lerobot_policy_ocn.envs.craft.observation import INVENTORY_FIRST_KIND
from lerobot_policy_ocn.envs.craft.world import EMPTY, GRID_SIZE, N_KINDS

if TYPE_CHECKING:
    from lerobot_policy_ocn.envs.craft.batch import CraftBatch

TILE = 16

PALETTE = np.array(
    [
        (235, 232, 220),  # empty
        (70, 70, 70),  # boundary
        (60, 120, 220),  # water
        (140, 140, 150),  # stone
        (160, 90, 40),  # toolshed
        (200, 150, 80),  # workbench
        (110, 60, 120),  # factory
        (170, 170, 190),  # iron
        (90, 190, 70),  # grass
        (120, 80, 30),  # wood
        (250, 200, 30),  # gold
        (40, 220, 220),  # gem
        (220, 180, 120),  # plank
        (150, 110, 60),  # stick
        (180, 50, 50),  # axe
        (210, 200, 150),  # rope
        (230, 120, 160),  # bed
        (100, 100, 120),  # shears
        (240, 240, 255),  # cloth
        (130, 90, 60),  # bridge
        (190, 140, 70),  # ladder
    ],
    dtype=np.uint8,
)

AGENT_COLOUR = np.array((220, 30, 30), dtype=np.uint8)
POINTER_COLOUR = np.array((20, 20, 20), dtype=np.uint8)

_yy, _xx = np.mgrid[0:TILE, 0:TILE]
_EDGE = (_yy == 0) | (_xx == 0) | (_yy == TILE - 1) | (_xx == TILE - 1)
# One 16x16 tile per kind, edges darkened so neighbouring equal tiles stay apart.
KIND_TILES = np.where(_EDGE[None, ..., None], PALETTE[:, None, None] * 0.8, PALETTE[:, None, None]).astype(np.uint8)


def _agent_sprites() -> np.ndarray:
    """Agent tiles for the 4 facings (down, up, left, right): a disc and a pointer bar."""
    centre = (TILE - 1) / 2
    dy, dx = _yy - centre, _xx - centre
    disc = dy**2 + dx**2 <= (TILE * 0.4) ** 2
    half = TILE // 2
    pointers = (
        (_yy >= half) & (np.abs(dx) <= 1.5),
        (_yy < half) & (np.abs(dx) <= 1.5),
        (_xx < half) & (np.abs(dy) <= 1.5),
        (_xx >= half) & (np.abs(dy) <= 1.5),
    )
    sprites = np.repeat(KIND_TILES[EMPTY][None], 4, axis=0)
    for facing, pointer in enumerate(pointers):
        sprites[facing][disc] = AGENT_COLOUR
        sprites[facing][disc & pointer] = POINTER_COLOUR
    return sprites


AGENT_SPRITES = _agent_sprites()


# The border tile (row, col) of each carried kind, INVENTORY_FIRST_KIND onwards.
_SLOTS = [(0, col) for col in range(1, GRID_SIZE - 1)] + [(GRID_SIZE - 1, col) for col in range(1, GRID_SIZE - 1)]
INVENTORY_SLOTS = np.array(_SLOTS[: N_KINDS - INVENTORY_FIRST_KIND])


def render_batch(grid: np.ndarray, pos: np.ndarray, facing: np.ndarray, inventory: np.ndarray) -> np.ndarray:
    """Images (n, 160, 160, 3) uint8 of n states given as grid (n, 10, 10), pos (n, 2), facing (n,) and the
    inventory counts (n, 14) of kinds 7 .. 20."""
    n = grid.shape[0]
    tiles = KIND_TILES[grid]
    tiles[np.arange(n), pos[:, 0], pos[:, 1]] = AGENT_SPRITES[facing]
    state, kind = np.nonzero(inventory > 0)
    tiles[state, INVENTORY_SLOTS[kind, 0], INVENTORY_SLOTS[kind, 1]] = KIND_TILES[INVENTORY_FIRST_KIND + kind]
    return tiles.transpose(0, 1, 3, 2, 4, 5).reshape(n, GRID_SIZE * TILE, GRID_SIZE * TILE, 3)


def render_state(grid: np.ndarray, pos: np.ndarray, facing: int, inventory: np.ndarray) -> np.ndarray:
    """Image (160, 160, 3) uint8 of one state."""
    return render_batch(grid[None], np.asarray(pos)[None], np.asarray([facing]), np.asarray(inventory)[None])[0]


def render_live(batch: CraftBatch) -> np.ndarray:
    """Images (n, 160, 160, 3) uint8 of every env of a live batch: its grids, agents and inventories."""
    return render_batch(batch.grid, batch.pos, batch.facing, batch.inventory[:, INVENTORY_FIRST_KIND:])
