"""Random Craft maps, one per reset, drawn from the env's own numpy Generator.

Maps are resampled until every object can be reached by the agent, so that every valid task
is solvable and the scripted expert never has to dig through unrelated resources. Reachability
is a flood fill over a 100-bit Python int (bit ``row * 10 + col``): a handful of big-int
shifts per BFS layer, far cheaper than numpy on a single 10x10 grid.
"""

from __future__ import annotations

import numpy as np

from lerobot_policy_ocn.envs.craft.world import (
    BOUNDARY,
    EMPTY,
    FACTORY,
    GEM,
    GOLD,
    GRASS,
    GRID_SIZE,
    INTERIOR_SIZE,
    IRON,
    STONE,
    TOOLSHED,
    WATER,
    WOOD,
    WORKBENCH,
    check_mode,
)

N_INTERIOR = INTERIOR_SIZE * INTERIOR_SIZE
# Flat grid index of each interior cell, interior row-major.
INTERIOR_FLAT = np.array(
    [(r + 1) * GRID_SIZE + c + 1 for r in range(INTERIOR_SIZE) for c in range(INTERIOR_SIZE)], dtype=np.int64
)
_INTERIOR_BITS = sum(1 << int(f) for f in INTERIOR_FLAT)
_ROWS, _COLS = np.divmod(np.arange(N_INTERIOR), INTERIOR_SIZE)
# Manhattan distance between interior cells; gold and gem at distance >= 3 have disjoint rings.
_MANHATTAN = np.abs(_ROWS[:, None] - _ROWS[None]) + np.abs(_COLS[:, None] - _COLS[None])
# Interior 4-neighbours of each interior cell (border neighbours are walls already).
_NEIGHBOURS = tuple(np.flatnonzero(_MANHATTAN[i] == 1) for i in range(N_INTERIOR))
# A cell followed by its interior neighbours, and the kinds of gold / gem rings placed there.
_RINGS = tuple(np.concatenate(([i], _NEIGHBOURS[i])) for i in range(N_INTERIOR))
_GOLD_RING_KINDS = tuple(np.array([GOLD] + [WATER] * (len(r) - 1), dtype=np.int8) for r in _RINGS)
_GEM_RING_KINDS = tuple(np.array([GEM] + [STONE] * (len(r) - 1), dtype=np.int8) for r in _RINGS)

PAPER_OBJECTS = np.array([WOOD, WOOD, GOLD, GOLD, IRON, IRON, GRASS, GRASS], dtype=np.int8)
FULL_OBJECTS = np.array([TOOLSHED, WORKBENCH, FACTORY, WOOD, WOOD, IRON, IRON, GRASS, GRASS], dtype=np.int8)

EMPTY_BORDERED = np.full((GRID_SIZE, GRID_SIZE), BOUNDARY, dtype=np.int8)
EMPTY_BORDERED[1:-1, 1:-1] = EMPTY


def _bits(flat_cells: np.ndarray) -> int:
    """Bitset of flat grid cells."""
    out = 0
    for f in flat_cells.tolist():
        out |= 1 << f
    return out


def _dilate(bits: int) -> int:
    """Cells equal or 4-adjacent to a set; row wrap only ever lands on border walls."""
    return bits | bits << 1 | bits >> 1 | bits << GRID_SIZE | bits >> GRID_SIZE


def all_reachable(agent: int, occupied: int, required: int) -> bool:
    """Whether every cell in ``required`` touches the empty region the agent can walk in."""
    free = _INTERIOR_BITS & ~occupied
    reach = 1 << agent
    while True:
        grown = _dilate(reach) & free
        if grown == reach:
            break
        reach = grown
    return (required & ~_dilate(reach)) == 0


def sample_map(rng: np.random.Generator, mode: str) -> tuple[np.ndarray, int, int]:
    """Draw a solvable map: (grid (10, 10) int8, agent flat index, facing)."""
    sample = _sample_paper if check_mode(mode) == "paper" else _sample_full
    while True:
        cells, kinds, agent, required = sample(rng)
        if all_reachable(agent, _bits(cells), required):
            grid = EMPTY_BORDERED.copy()
            grid.flat[cells] = kinds
            return grid, agent, int(rng.integers(4))


def _sample_paper(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Two each of wood, gold, iron and grass plus the agent on distinct random cells.

    Returns (object flat cells, their kinds, agent flat cell, bitset of cells to reach).
    """
    cells = INTERIOR_FLAT[rng.permutation(N_INTERIOR)[: len(PAPER_OBJECTS) + 1]]
    objects = cells[:-1]
    return objects, PAPER_OBJECTS, int(cells[-1]), _bits(objects)


def _sample_full(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Gold ringed by water, gem ringed by stone, workshops and two of each basic resource.

    Cells are taken in the order of one random permutation: gold first, then the first cell far
    enough from gold for the two rings not to touch (gem), then the free cells for the rest.
    """
    order = rng.permutation(N_INTERIOR)
    gold = order[0]
    gem = order[np.argmax(_MANHATTAN[gold, order] >= 3)]
    ringed = np.concatenate((_RINGS[gold], _RINGS[gem]))
    taken = np.zeros(N_INTERIOR, dtype=bool)
    taken[ringed] = True
    rest = order[~taken[order]][: len(FULL_OBJECTS) + 1]
    cells = INTERIOR_FLAT[np.concatenate((ringed, rest[:-1]))]
    kinds = np.concatenate((_GOLD_RING_KINDS[gold], _GEM_RING_KINDS[gem], FULL_OBJECTS))
    required = _bits(cells) & ~_bits(INTERIOR_FLAT[[gold, gem]])
    return cells, kinds, int(INTERIOR_FLAT[rest[-1]]), required
