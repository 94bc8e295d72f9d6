"""The scripted Craft expert: success rates and the individual decisions it makes."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_policy_ocn.envs.craft import NAMED_TASKS, CraftBatch, CraftExpert, parse_task
from lerobot_policy_ocn.envs.craft.layout import EMPTY_BORDERED
from lerobot_policy_ocn.envs.craft.world import (
    BRIDGE, DOWN, EMPTY, GOLD, IRON, LEFT, RIGHT, STONE, UP, USE, WATER, WOOD,
)

PAPER_TASKS = ["AC", "CD", "DA", "AB", "BA", "DC", "ADC", "CAD", "DCA", "BADC", "ACBD", "CABD"]


def run_to_end(batch: CraftBatch, expert: CraftExpert) -> np.ndarray:
    """Play the expert until every env is done; returns which envs succeeded."""
    success = np.zeros(batch.num_envs, dtype=bool)
    while not batch.done.all():
        success |= batch.step(expert.act())[2]
    return success


def success_per_task(mode: str, specs: list[str], seeds: int) -> dict[str, float]:
    tasks = [parse_task(spec, mode) for spec in specs for _ in range(seeds)]
    batch = CraftBatch(len(tasks), mode=mode)
    batch.reset(seeds=list(range(len(tasks))), tasks=tasks)
    success = run_to_end(batch, CraftExpert(batch)).reshape(len(specs), seeds)
    return dict(zip(specs, success.mean(axis=1).tolist(), strict=True))


def test_expert_solves_every_paper_task():
    rates = success_per_task("paper", PAPER_TASKS, seeds=200)
    assert rates == dict.fromkeys(PAPER_TASKS, 1.0)


def test_expert_solves_every_named_full_task():
    rates = success_per_task("full", list(NAMED_TASKS), seeds=50)
    assert rates == dict.fromkeys(NAMED_TASKS, 1.0)


def blank_batch(task: str, mode: str = "paper", n: int = 1) -> CraftBatch:
    """Envs on an empty bordered map, agent at grid (4, 4) facing up with nothing held."""
    b = CraftBatch(n, mode=mode)
    b.reset(seeds=list(range(n)), tasks=[task] * n)
    b.grid[:] = EMPTY_BORDERED
    b.pos[:] = (4, 4)
    b.facing[:] = UP
    b.inventory[:] = 0
    return b


def test_expert_turns_to_adjacent_target_then_uses_it():
    b = blank_batch("A")
    b.grid[0, 5, 4] = WOOD
    expert = CraftExpert(b)
    assert expert.act()[0] == DOWN
    b.step(np.array([DOWN]))
    assert tuple(b.pos[0]) == (4, 4) and b.facing[0] == DOWN
    assert expert.act()[0] == USE


def test_expert_walks_shortest_path_with_tie_break_in_action_order():
    b = blank_batch("A")
    # Wood two up and two left: up and left both shorten the path, up wins the tie.
    b.grid[0, 2, 2] = WOOD
    expert = CraftExpert(b)
    actions = []
    while not b.done[0]:
        actions.append(int(expert.act()[0]))
        b.step(np.array(actions[-1:]))
    assert actions == [UP, UP, LEFT, USE]


def test_expert_ignores_non_target_resources_on_the_way():
    b = blank_batch("C")
    b.grid[0, 3, 4] = WOOD
    b.grid[0, 2, 4] = IRON
    expert = CraftExpert(b)
    run_to_end(b, expert)
    assert b.inventory[0, IRON] == 1 and b.inventory[0, WOOD] == 0 and b.grid[0, 3, 4] == WOOD


def test_expert_bridges_water_to_reach_gold():
    b = blank_batch("B", mode="full")
    b.grid[0, 2, 4] = GOLD
    b.grid[0, 1, 4], b.grid[0, 2, 3], b.grid[0, 2, 5], b.grid[0, 3, 4] = WATER, WATER, WATER, WATER
    b.inventory[0, BRIDGE] = 1
    expert = CraftExpert(b)
    assert expert.act()[0] == USE  # facing the water ring, path goes straight through it
    assert run_to_end(b, expert)[0]
    assert b.inventory[0, GOLD] == 1 and b.inventory[0, BRIDGE] == 0
    assert (b.grid[0] == WATER).sum() == 3


def test_expert_without_path_plays_use():
    b = blank_batch("B", mode="full")
    b.grid[0, 2, 4] = GOLD
    b.grid[0, 1, 4], b.grid[0, 2, 3], b.grid[0, 2, 5], b.grid[0, 3, 4] = STONE, STONE, STONE, STONE
    b.facing[0] = RIGHT
    assert CraftExpert(b).act()[0] == USE


def test_expert_recomputes_when_grid_or_subtask_changes():
    b = blank_batch("AC", n=2)
    b.grid[:, 4, 7] = WOOD
    expert = CraftExpert(b)
    np.testing.assert_array_equal(expert.act(), [RIGHT, RIGHT])
    b.grid[1, 4, 7] = EMPTY
    b.grid[1, 4, 1] = WOOD
    b.grid[:, 6, 4] = IRON
    np.testing.assert_array_equal(expert.act(), [RIGHT, LEFT])
    b.progress[:] = 1
    np.testing.assert_array_equal(expert.act(), [DOWN, DOWN])


@pytest.mark.parametrize("mode", ["paper", "full"])
def test_expert_is_deterministic(mode):
    def actions() -> np.ndarray:
        b = CraftBatch(8, mode=mode)
        b.reset(seeds=list(range(8)), tasks=["AC"] * 8)
        expert = CraftExpert(b)
        out = []
        while not b.done.all():
            out.append(expert.act())
            b.step(out[-1])
        return np.array(out)

    np.testing.assert_array_equal(actions(), actions())
