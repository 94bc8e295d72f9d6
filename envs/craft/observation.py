"""Compact Craft state vector and the OMPN feature encoding built from it.

The compact state is what datasets store and what the env returns: 81 int64 values that fully
describe the world (the border is constant, so only the interior is kept)::

    [0:64]   interior cell kinds, row-major (grid rows/cols 1..8)
    [64]     agent row, interior coordinates 0..7
    [65]     agent col, interior coordinates 0..7
    [66]     facing, same codes as the move actions (0 down, 1 up, 2 left, 3 right)
    [67:81]  inventory counts of kinds 7..20 (iron ... ladder)

``ompn_features`` expands it into the 1075 float features of the OMPN Craft encoder::

    [0:525]     egocentric 5x5 window centred on the agent, one-hot over the 21 kinds,
                index (i * 5 + j) * 21 + kind, i/j = window row/col; cells outside the
                10x10 grid count as boundary
    [525:1050]  coarse map: the 10x10 grid (border included) cut into 5x5 blocks of 2x2
                cells, count of each kind per block, index (bi * 5 + bj) * 21 + kind
    [1050:1071] inventory counts over all 21 kinds (kinds 0..6 are always 0)
    [1071:1075] facing one-hot

The OMPN features place objects outside the 5x5 window only to their 2x2 block, while the scripted
expert plans on the exact map. ``full_view_features`` is the exact alternative, 4750 floats::

    [0:4725]    egocentric 15x15 window centred on the agent, one-hot over the 21 kinds (the
                whole interior is inside it from every agent cell; outside cells are boundary)
    [4725:4746] inventory counts over all 21 kinds
    [4746:4750] facing one-hot
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

from lerobot_policy_ocn.envs.craft.world import BOUNDARY, GRID_SIZE, INTERIOR_SIZE, KIND_NAMES, N_KINDS

if TYPE_CHECKING:
    import torch

N_CELLS = INTERIOR_SIZE * INTERIOR_SIZE
CELLS = slice(0, N_CELLS)
AGENT_ROW = N_CELLS
AGENT_COL = N_CELLS + 1
FACING = N_CELLS + 2
INVENTORY_FIRST_KIND = 7
INVENTORY = slice(N_CELLS + 3, N_CELLS + 3 + N_KINDS - INVENTORY_FIRST_KIND)
OBS_DIM = INVENTORY.stop

OBS_NAMES = (
    tuple(f"cell_r{r}_c{c}" for r in range(INTERIOR_SIZE) for c in range(INTERIOR_SIZE))
    + ("agent_row", "agent_col", "facing")
    + tuple(f"inv_{name}" for name in KIND_NAMES[INVENTORY_FIRST_KIND:])
)

# Inclusive upper bounds for the observation space. Inventory counts are bounded by the finite
# resources of a map; 255 leaves room for hand-edited test states.
INVENTORY_MAX = 255
OBS_HIGH = np.concatenate(
    (
        np.full(N_CELLS, N_KINDS - 1),
        [INTERIOR_SIZE - 1, INTERIOR_SIZE - 1, 3],
        np.full(INVENTORY.stop - INVENTORY.start, INVENTORY_MAX),
    )
).astype(np.int64)

WINDOW = 5
BLOCK = 2
N_BLOCKS = GRID_SIZE // BLOCK
EGO_DIM = WINDOW * WINDOW * N_KINDS
MAP_DIM = N_BLOCKS * N_BLOCKS * N_KINDS
OMPN_DIM = EGO_DIM + MAP_DIM + N_KINDS + 4


N_ACTIVE = WINDOW * WINDOW + GRID_SIZE * GRID_SIZE + (N_KINDS - INVENTORY_FIRST_KIND) + 1
N_CELL_ENTRIES = WINDOW * WINDOW + GRID_SIZE * GRID_SIZE
FACING_FEATURE = EGO_DIM + MAP_DIM + N_KINDS

FULL_WINDOW = 2 * INTERIOR_SIZE - 1
FULL_EGO_DIM = FULL_WINDOW * FULL_WINDOW * N_KINDS
FULL_VIEW_DIM = FULL_EGO_DIM + N_KINDS + 4


def _interior_cell(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Index of interior cells (rows, cols) in the compact state, or N_CELLS (where
    `ompn_active_entries` puts the boundary kind) for cells outside the interior."""
    inside = (rows >= 0) & (rows < INTERIOR_SIZE) & (cols >= 0) & (cols < INTERIOR_SIZE)
    return np.where(inside, rows * INTERIOR_SIZE + cols, N_CELLS)


def _window_cells(size: int) -> np.ndarray:
    """[N_CELLS, size * size]: per agent cell, the compact-state cell each cell of the size x size
    window centred on it reads (row-major), N_CELLS where it falls outside the interior."""
    agent_row, agent_col = np.divmod(np.arange(N_CELLS), INTERIOR_SIZE)
    window_row, window_col = np.divmod(np.arange(size * size), size)
    radius = size // 2
    return _interior_cell(agent_row[:, None] + window_row - radius, agent_col[:, None] + window_col - radius)


def _window_kinds(s: torch.Tensor, windows: torch.Tensor) -> torch.Tensor:
    """The kinds [B, W] of the cells that compact states s [B, 81] read through per-agent-cell
    tables windows [N_CELLS, W] (index N_CELLS, outside the interior, reads the boundary kind)."""
    import torch

    kinds = torch.cat([s[:, CELLS], s.new_full((s.shape[0], 1), BOUNDARY)], dim=1)
    agent = s[:, AGENT_ROW] * INTERIOR_SIZE + s[:, AGENT_COL]
    return kinds.gather(1, windows.index_select(0, agent))


@functools.cache
def _entry_tables(device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What every state's entries share, on `device`, built once: they depend on no state or on the
    agent's cell alone, so a state costs a few gathers instead of building its padded board.

    - sources [N_CELLS, N_CELL_ENTRIES]: per agent cell, the cells its entries read: the 5x5 window
      centred on it, then the whole grid with its border, both row-major
    - offsets [N_CELL_ENTRIES]: the feature a cell entry's kind is added to: window cell w's one-hot
      at w * N_KINDS, a grid cell's count at its block's EGO_DIM + block * N_KINDS
    - inventory [14]: the features of the carried kinds
    """
    import torch

    window = _window_cells(WINDOW)
    grid_row, grid_col = np.divmod(np.arange(GRID_SIZE * GRID_SIZE), GRID_SIZE)
    grid = _interior_cell(grid_row - 1, grid_col - 1)
    sources = np.concatenate([window, np.broadcast_to(grid, (N_CELLS, grid.size))], axis=1)
    block = (grid_row // BLOCK) * N_BLOCKS + grid_col // BLOCK
    offsets = np.concatenate([np.arange(WINDOW * WINDOW) * N_KINDS, EGO_DIM + block * N_KINDS])
    inventory = EGO_DIM + MAP_DIM + np.arange(INVENTORY_FIRST_KIND, N_KINDS)
    return tuple(torch.as_tensor(table, dtype=torch.long, device=device) for table in (sources, offsets, inventory))


def ompn_active_entries(state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The OMPN features of compact states [..., 81] as N_ACTIVE (index, value) pairs per state:
    a scatter-add of these builds the features in one op (4x faster than stacking one-hots).

    Every state sets the same number of entries: 25 window cells, 100 grid cells (each adds 1 to
    its block's count of its kind; repeated indices add up), 14 inventory counts and the facing.
    Returns index [..., N_ACTIVE] int64 and value [..., N_ACTIVE] float32.
    """
    import torch

    lead = state.shape[:-1]
    s = state.reshape(-1, OBS_DIM).long()
    b = s.shape[0]
    sources, offsets, inventory = _entry_tables(s.device)
    cells = offsets + _window_kinds(s, sources)
    facing = FACING_FEATURE + s[:, FACING, None]
    index = torch.cat([cells, inventory.expand(b, -1), facing], dim=1)
    value = torch.ones(index.shape, dtype=torch.float32, device=s.device)
    value[:, N_CELL_ENTRIES:-1] = s[:, INVENTORY].float()
    return index.reshape(*lead, N_ACTIVE), value.reshape(*lead, N_ACTIVE)


def ompn_features(state: torch.Tensor) -> torch.Tensor:
    """Map compact states [..., 81] (any int dtype) to OMPN features [..., 1075] float32."""
    import torch

    index, value = ompn_active_entries(state)
    dense = torch.zeros((*index.shape[:-1], OMPN_DIM), dtype=torch.float32, device=index.device)
    return dense.scatter_add_(-1, index, value)


@functools.cache
def _full_view_window(device: torch.device) -> torch.Tensor:
    """`_window_cells(FULL_WINDOW)` on `device`, built once."""
    import torch

    return torch.as_tensor(_window_cells(FULL_WINDOW), dtype=torch.long, device=device)


def full_view_features(state: torch.Tensor) -> torch.Tensor:
    """Map compact states [..., 81] (any int dtype) to the exact egocentric view [..., 4750] float32:
    the 15x15 window one-hot, the inventory counts and the facing (layout in the module docstring)."""
    import torch

    lead = state.shape[:-1]
    s = state.reshape(-1, OBS_DIM).long()
    b = s.shape[0]
    cells = _window_kinds(s, _full_view_window(s.device))
    window_offsets = torch.arange(FULL_WINDOW * FULL_WINDOW, device=s.device) * N_KINDS
    features = torch.zeros((b, FULL_VIEW_DIM), dtype=torch.float32, device=s.device)
    features.scatter_(1, window_offsets + cells, 1.0)
    features[:, FULL_EGO_DIM + INVENTORY_FIRST_KIND:FULL_EGO_DIM + N_KINDS] = s[:, INVENTORY].float()
    features.scatter_(1, FULL_EGO_DIM + N_KINDS + s[:, FACING, None], 1.0)
    return features.reshape(*lead, FULL_VIEW_DIM)
