"""Rules, wrappers, rendering, task parsing and features of the Craft world."""

from __future__ import annotations

import importlib
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

from lerobot_policy_ocn import envs
from lerobot_policy_ocn.envs.craft import (
    ACTION_NAMES,
    KIND_NAMES,
    NAMED_TASKS,
    OBS_DIM,
    OBS_NAMES,
    CraftBatch,
    CraftEnv,
    CraftExpert,
    CraftVectorEnv,
    ompn_features,
    parse_task,
    task_code,
    task_description,
)
from lerobot_policy_ocn.envs.craft.layout import EMPTY_BORDERED
from lerobot_policy_ocn.envs.craft.observation import (
    AGENT_COL,
    AGENT_ROW,
    CELLS,
    EGO_DIM,
    FACING,
    FULL_VIEW_DIM,
    INVENTORY,
    MAP_DIM,
    OBS_HIGH,
    OMPN_DIM,
    full_view_features,
)
from lerobot_policy_ocn.envs.craft.world import (
    AXE,
    BED,
    BOUNDARY,
    BRIDGE,
    CLOTH,
    DOWN,
    EMPTY,
    FACTORY,
    GEM,
    GOLD,
    GRASS,
    GRID_SIZE,
    INTERIOR_SIZE,
    IRON,
    LADDER,
    LEFT,
    N_KINDS,
    PLANK,
    RIGHT,
    ROPE,
    SHEARS,
    STICK,
    STONE,
    TOOLSHED,
    UP,
    USE,
    WATER,
    WOOD,
    WORKBENCH,
)


def blank_batch(task: str = "AC", mode: str = "paper", max_steps: int | None = None) -> CraftBatch:
    """One env on an empty bordered map, agent at grid (4, 4) facing up with nothing held."""
    b = CraftBatch(1, mode=mode, max_steps=max_steps)
    b.reset(seeds=[0], tasks=[task])
    b.grid[0] = EMPTY_BORDERED
    b.pos[0] = (4, 4)
    b.facing[0] = UP
    b.inventory[0] = 0
    return b


def act(b: CraftBatch, action: int):
    """Step a one-env batch and unbatch the result."""
    obs, reward, terminated, truncated, info = b.step(np.array([action]))
    return obs[0], reward[0], terminated[0], truncated[0], {k: v[0] for k, v in info.items()}


def test_names_and_ids():
    assert len(KIND_NAMES) == 21
    assert (KIND_NAMES[BOUNDARY], KIND_NAMES[WOOD], KIND_NAMES[GEM], KIND_NAMES[LADDER]) == (
        "boundary",
        "wood",
        "gem",
        "ladder",
    )
    assert ACTION_NAMES == ("down", "up", "left", "right", "use")


@pytest.mark.parametrize(
    ("action", "expected"), [(DOWN, (5, 4)), (UP, (3, 4)), (LEFT, (4, 3)), (RIGHT, (4, 5))]
)
def test_move_into_empty_cell_moves_and_turns(action, expected):
    b = blank_batch()
    b.facing[0] = DOWN if action != DOWN else UP
    act(b, action)
    assert tuple(b.pos[0]) == expected
    assert b.facing[0] == action


@pytest.mark.parametrize("kind", [WOOD, GOLD, IRON, GRASS, STONE, WATER, BOUNDARY])
def test_move_into_blocked_cell_only_turns(kind):
    b = blank_batch()
    b.grid[0, 4, 5] = kind
    before = b.grid.copy()
    act(b, RIGHT)
    assert tuple(b.pos[0]) == (4, 4)
    assert b.facing[0] == RIGHT
    np.testing.assert_array_equal(b.grid, before)


def test_move_into_border_wall_only_turns():
    b = blank_batch()
    b.pos[0] = (1, 1)
    act(b, LEFT)
    assert tuple(b.pos[0]) == (1, 1) and b.facing[0] == LEFT
    act(b, UP)
    assert tuple(b.pos[0]) == (1, 1) and b.facing[0] == UP


@pytest.mark.parametrize("kind", [IRON, GRASS, WOOD, GOLD, GEM])
def test_use_gathers_resource(kind):
    b = blank_batch(mode="full")
    b.grid[0, 3, 4] = kind
    act(b, USE)
    assert b.grid[0, 3, 4] == EMPTY
    assert b.inventory[0, kind] == 1
    assert b.inventory[0].sum() == 1


@pytest.mark.parametrize("kind", [EMPTY, WATER, STONE, TOOLSHED, WORKBENCH, FACTORY])
def test_use_without_tools_or_ingredients_does_nothing(kind):
    b = blank_batch(mode="full")
    b.grid[0, 3, 4] = kind
    act(b, USE)
    assert b.grid[0, 3, 4] == kind
    assert b.inventory[0].sum() == 0
    assert tuple(b.pos[0]) == (4, 4)


def test_use_on_border_does_nothing():
    b = blank_batch()
    b.pos[0] = (1, 4)
    act(b, USE)
    np.testing.assert_array_equal(b.grid[0], EMPTY_BORDERED)
    assert b.inventory[0].sum() == 0


def test_bridge_clears_water_and_is_consumed():
    b = blank_batch(mode="full")
    b.grid[0, 3, 4] = WATER
    b.inventory[0, BRIDGE] = 2
    act(b, USE)
    assert b.grid[0, 3, 4] == EMPTY
    assert b.inventory[0, BRIDGE] == 1
    act(b, UP)
    assert tuple(b.pos[0]) == (3, 4)


def test_axe_clears_stone_and_is_kept():
    b = blank_batch(mode="full")
    b.grid[0, 3, 4] = STONE
    b.inventory[0, AXE] = 1
    act(b, USE)
    assert b.grid[0, 3, 4] == EMPTY
    assert b.inventory[0, AXE] == 1


@pytest.mark.parametrize(
    ("workshop", "held", "crafted"),
    [
        # Each case holds the ingredients of several recipes; the first in order wins.
        (TOOLSHED, {WOOD: 1, STICK: 1, IRON: 1, GRASS: 1}, [PLANK, AXE, ROPE, None]),
        (WORKBENCH, {WOOD: 1, PLANK: 1, GRASS: 1, STICK: 1, IRON: 2}, [STICK, BED, SHEARS, SHEARS, None]),
        (FACTORY, {GRASS: 1, WOOD: 1, IRON: 1, PLANK: 1, STICK: 1}, [CLOTH, BRIDGE, LADDER, None]),
    ],
)
def test_crafting_order_and_consumption(workshop, held, crafted):
    """Repeated use crafts recipes in the fixed order, consuming one of each ingredient."""
    b = blank_batch(mode="full")
    b.grid[0, 3, 4] = workshop
    for kind, count in held.items():
        b.inventory[0, kind] = count
    expected = b.inventory[0].copy()
    recipes = {
        PLANK: [WOOD],
        AXE: [STICK, IRON],
        ROPE: [GRASS],
        STICK: [WOOD],
        BED: [PLANK, GRASS],
        SHEARS: [STICK, IRON],
        CLOTH: [GRASS],
        BRIDGE: [WOOD, IRON],
        LADDER: [PLANK, STICK],
    }
    for product in crafted:
        act(b, USE)
        if product is not None:
            expected[recipes[product]] -= 1
            expected[product] += 1
        np.testing.assert_array_equal(b.inventory[0], expected)
    assert b.grid[0, 3, 4] == workshop


def test_events_for_non_current_subtask_do_not_count():
    b = blank_batch(task="AC")
    b.grid[0, 3, 4] = IRON
    b.grid[0, 5, 4] = WOOD
    _, reward, _, _, info = act(b, USE)
    assert b.inventory[0, IRON] == 1
    assert reward == 0 and info["progress"] == 0 and not info["subtask_done"]
    act(b, DOWN)
    _, reward, terminated, _, info = act(b, USE)
    assert reward == 1 and info["subtask_done"] and info["subtask_index"] == 0 and info["progress"] == 1
    assert not terminated


def test_use_subtask_completes_on_craft():
    b = blank_batch(task="make plank", mode="full")
    b.grid[0, 3, 4] = WOOD
    b.grid[0, 5, 4] = TOOLSHED
    _, reward, _, _, info = act(b, USE)
    assert (reward, info["subtask_index"], info["progress"]) == (1, 0, 1)
    act(b, DOWN)
    _, reward, terminated, truncated, info = act(b, USE)
    assert (reward, info["subtask_index"], info["progress"]) == (1, 1, 2)
    assert terminated and not truncated and info["is_success"]
    assert b.inventory[0, PLANK] == 1


def run_expert_episode(reward: str, seed: int = 3, task: str = "ADC"):
    b = CraftBatch(1, reward=reward)
    b.reset(seeds=[seed], tasks=[task])
    expert = CraftExpert(b)
    observations, rewards, dones = [b.observe()[0]], [], []
    while not b.done[0]:
        obs, r, _, _, info = b.step(expert.act())
        observations.append(obs[0])
        rewards.append(r[0])
        dones.append(info["subtask_done"][0])
    return np.array(observations), np.array(rewards), np.array(dones), bool(info["is_success"][0])


def test_dense_and_sparse_rewards_over_expert_episode():
    obs_dense, dense, sub_done, success = run_expert_episode("dense")
    obs_sparse, sparse, _, _ = run_expert_episode("sparse")
    assert success
    np.testing.assert_array_equal(obs_dense, obs_sparse)
    assert dense.dtype == np.float32
    assert dense.sum() == 3 and np.array_equal(dense == 1, sub_done)
    assert sparse.sum() == 1 and sparse[-1] == 1
    assert sub_done[-1]


@pytest.mark.parametrize(("task", "limit"), [("AC", 64), ("ADC", 100), ("BADC", 100), ("D", 64)])
def test_step_limit_truncates(task, limit):
    b = blank_batch(task=task)
    for t in range(limit):
        _, reward, terminated, truncated, _ = act(b, t % 2)
        assert not terminated and reward == 0
        assert truncated == (t == limit - 1)
    assert b.done[0]


def test_step_limit_override_and_frozen_after_done():
    b = blank_batch(task="AC", max_steps=5)
    for _ in range(4):
        assert not act(b, RIGHT)[3]
    assert act(b, RIGHT)[3]
    state = (b.grid.copy(), b.pos.copy(), b.facing.copy(), b.t.copy())
    for _ in range(3):
        _, reward, terminated, truncated, _ = act(b, LEFT)
        assert (reward, terminated, truncated) == (0, False, False)
        assert b.done[0]
        for before, after in zip(state, (b.grid, b.pos, b.facing, b.t), strict=True):
            np.testing.assert_array_equal(before, after)


def test_step_before_reset_raises():
    with pytest.raises(RuntimeError):
        CraftBatch(2).step(np.zeros(2, dtype=np.int64))


def test_invalid_action_raises():
    b = blank_batch()
    with pytest.raises(ValueError):
        b.step(np.array([5]))


def rollout(seed: int, task: str, actions: np.ndarray, mode: str = "paper") -> np.ndarray:
    env = CraftEnv(task, mode=mode)
    obs, _ = env.reset(seed=seed)
    frames = [obs]
    for a in actions:
        frames.append(env.step(int(a))[0])
    return np.array(frames)


@pytest.mark.parametrize("mode", ["paper", "full"])
def test_seeding_is_deterministic_and_seeds_differ(mode):
    actions = np.random.default_rng(0).integers(0, 5, size=40)
    a = rollout(7, "AC", actions, mode)
    np.testing.assert_array_equal(a, rollout(7, "AC", actions, mode))
    assert not np.array_equal(a[0], rollout(8, "AC", actions, mode)[0])


def test_batch_envs_match_single_envs_and_subset_reset():
    seeds = [11, 12, 13]
    b = CraftBatch(3)
    b.reset(seeds=seeds, tasks=["AC", "DA", "BADC"])
    for i, seed in enumerate(seeds):
        np.testing.assert_array_equal(b.observe()[i], CraftEnv("AC").reset(seed=seed)[0])
    before = b.observe()
    b.reset(seeds=[99], env_ids=[1])
    after = b.observe()
    np.testing.assert_array_equal(before[[0, 2]], after[[0, 2]])
    assert not np.array_equal(before[1], after[1])
    assert b.task_of(1) == (3, 0)


@pytest.mark.parametrize("seed", range(5))
def test_map_contents(seed):
    paper = CraftBatch(1)
    paper.reset(seeds=[seed], tasks=["AC"])
    g = paper.grid[0]
    assert (g[0] == BOUNDARY).all() and (g[:, 0] == BOUNDARY).all() and (g[-1] == BOUNDARY).all()
    assert (g[:, -1] == BOUNDARY).all() and (g[1:-1, 1:-1] != BOUNDARY).all()
    counts = np.bincount(g[1:-1, 1:-1].ravel(), minlength=len(KIND_NAMES))
    assert all(counts[k] == 2 for k in (WOOD, GOLD, IRON, GRASS))
    assert counts.sum() - counts[EMPTY] == 8
    assert g[tuple(paper.pos[0])] == EMPTY

    full = CraftBatch(1, mode="full")
    full.reset(seeds=[seed], tasks=["make bed"])
    g = full.grid[0]
    counts = np.bincount(g[1:-1, 1:-1].ravel(), minlength=len(KIND_NAMES))
    assert [counts[k] for k in (TOOLSHED, WORKBENCH, FACTORY, WOOD, IRON, GRASS, GOLD, GEM)] == [1, 1, 1, 2, 2, 2, 1, 1]
    for centre, ring in ((GOLD, WATER), (GEM, STONE)):
        r, c = np.argwhere(g == centre)[0]
        around = [g[r + dr, c + dc] for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        assert all(k in (ring, BOUNDARY) for k in around)


def test_observation_layout():
    b = blank_batch(mode="full")
    b.grid[0, 1, 1] = WOOD
    b.grid[0, 8, 8] = GEM
    b.pos[0] = (2, 3)
    b.facing[0] = LEFT
    b.inventory[0, IRON] = 2
    b.inventory[0, LADDER] = 1
    obs = b.observe()[0]
    assert obs.shape == (OBS_DIM,) == (81,) and obs.dtype == np.int64
    assert obs[CELLS][0] == WOOD and obs[CELLS][63] == GEM and obs[CELLS].sum() == WOOD + GEM
    assert (obs[AGENT_ROW], obs[AGENT_COL], obs[FACING]) == (1, 2, LEFT)
    assert obs[INVENTORY][0] == 2 and obs[INVENTORY][-1] == 1
    assert len(OBS_NAMES) == 81 and OBS_NAMES[0] == "cell_r0_c0" and OBS_NAMES[-1] == "inv_ladder"
    assert OBS_NAMES[AGENT_ROW] == "agent_row" and OBS_NAMES[INVENTORY][0] == "inv_iron"
    assert CraftEnv().observation_space.contains(obs)


def test_vector_env_autoreset_next_step():
    venv = CraftVectorEnv(2, task=["AC", "ADC"], max_steps=3)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, info = venv.reset(seed=0)
    assert obs.shape == (2, 81) and venv.observation_space.contains(obs)
    assert list(info["task"]) == ["get wood, get iron", "get wood, get grass, get iron"]
    for t in range(3):
        obs, reward, terminated, truncated, info = venv.step(np.array([0, 1]))
        assert truncated.tolist() == [t == 2, t == 2]
    final = obs.copy()
    obs, reward, terminated, truncated, info = venv.step(np.array([4, 4]))
    assert not terminated.any() and not truncated.any() and (reward == 0).all()
    assert (venv.batch.t == 0).all() and (info["progress"] == 0).all()
    assert not np.array_equal(obs, final)
    obs, *_ = venv.step(np.array([0, 0]))
    assert (venv.batch.t == 1).all()


def test_vector_env_seeds_match_single_envs():
    venv = CraftVectorEnv(3, task="DC")
    obs, _ = venv.reset(seed=5)
    for i in range(3):
        np.testing.assert_array_equal(obs[i], CraftEnv("DC").reset(seed=5 + i)[0])
    again, _ = venv.reset(seed=5)
    np.testing.assert_array_equal(obs, again)


def test_vector_env_partial_reset_mask():
    venv = CraftVectorEnv(3, task="AC")
    first, _ = venv.reset(seed=1)
    second, _ = venv.reset(seed=[None, 42, None], options={"reset_mask": np.array([False, True, False])})
    np.testing.assert_array_equal(first[[0, 2]], second[[0, 2]])
    np.testing.assert_array_equal(second[1], CraftEnv("AC").reset(seed=42)[0])


def test_render_shows_the_inventory_on_the_border():
    """Each carried kind lights its own border tile in its colour; an empty inventory leaves the border
    plain boundary, and the interior is the same either way."""
    from lerobot_policy_ocn.envs.craft.render import INVENTORY_SLOTS, KIND_TILES
    from lerobot_policy_ocn.envs.craft.world import BOUNDARY

    env = CraftEnv("AC", render_mode="rgb_array")
    env.reset(seed=0)
    env.batch.inventory[0] = 0
    plain = env.render()
    np.testing.assert_array_equal(plain[:16], np.concatenate([KIND_TILES[BOUNDARY]] * 10, axis=1))
    for kind in (7, 8, 20):
        env.batch.inventory[0] = 0
        env.batch.inventory[0, kind] = 2
        frame = env.render()
        row, col = INVENTORY_SLOTS[kind - 7]
        np.testing.assert_array_equal(frame[row * 16:(row + 1) * 16, col * 16:(col + 1) * 16], KIND_TILES[kind])
        assert (frame != plain).any(axis=-1).sum() == 16 * 16
    assert len({tuple(slot) for slot in INVENTORY_SLOTS}) == 14 and all(
        row in (0, 9) and 0 < col < 9 for row, col in INVENTORY_SLOTS)


def test_render_shape_and_facing_marker():
    env = CraftEnv("AC", render_mode="rgb_array")
    env.reset(seed=0)
    frames = []
    for facing in range(4):
        env.batch.facing[0] = facing
        frame = env.render()
        assert frame.shape == (160, 160, 3) and frame.dtype == np.uint8
        frames.append(frame)
    r, c = env.batch.pos[0]
    tiles = [f[r * 16 : (r + 1) * 16, c * 16 : (c + 1) * 16] for f in frames]
    for i in range(4):
        for j in range(i + 1, 4):
            assert not np.array_equal(tiles[i], tiles[j])
    others = np.ones(160, dtype=bool)
    others[r * 16 : (r + 1) * 16] = False
    np.testing.assert_array_equal(frames[0][others], frames[1][others])
    assert CraftEnv("AC").render() is None
    venv = CraftVectorEnv(2, render_mode="rgb_array")
    venv.reset(seed=0)
    images = venv.render()
    assert len(images) == 2 and images[0].shape == (160, 160, 3)


def test_parse_task_forms_and_round_trip():
    assert parse_task("adc") == parse_task("ADC") == (0, 3, 2)
    assert parse_task("make bed", "full") == (0, 4, 3, 5)
    assert parse_task("get gold", "full") == parse_task("CAGB", "full")
    assert parse_task("get gold") == (1,)
    assert parse_task("Get Wood,  get IRON") == (0, 2)
    for task in [(0, 2), (3,), (1, 0, 3, 2)]:
        assert parse_task(task_description(task)) == task
        assert parse_task(task_code(task)) == task
    for name, code in NAMED_TASKS.items():
        assert task_code(parse_task(name, "full")) == code
    assert task_description((0, 2)) == "get wood, get iron" and task_code((0, 2)) == "AC"


@pytest.mark.parametrize(
    ("spec", "mode", "fragment"),
    [
        ("AZ", "paper", "'Z'"),
        ("", "paper", "empty"),
        ("E", "paper", "use toolshed"),
        ("make bed", "paper", "mode='full'"),
        ("get silver", "full", "'get silver'"),
        ("make boat", "full", "make shears"),
    ],
)
def test_parse_task_errors_list_valid_letters(spec, mode, fragment):
    with pytest.raises(ValueError) as err:
        parse_task(spec, mode)
    message = str(err.value)
    assert fragment in message
    assert "A (get wood)" in message and "D (get grass)" in message
    assert ("H (get gem)" in message) == (mode == "full")


def test_ompn_features_hand_built_state():
    state = torch.zeros(81, dtype=torch.long)
    state[CELLS.start + 1] = WOOD  # interior (0, 1), i.e. grid (1, 2)
    state[CELLS.start + 8] = IRON  # interior (1, 0), i.e. grid (2, 1)
    state[AGENT_ROW], state[AGENT_COL], state[FACING] = 0, 0, RIGHT
    state[INVENTORY.start + (WOOD - 7)] = 2
    feats = ompn_features(state)
    assert feats.shape == (1075,) and feats.dtype == torch.float32

    ego = feats[:EGO_DIM].view(5, 5, 21)
    assert (ego.sum(-1) == 1).all()
    assert ego[2, 2, EMPTY] == 1  # the agent's own cell
    assert ego[2, 3, WOOD] == 1 and ego[3, 2, IRON] == 1
    assert ego[0, :, BOUNDARY].all() and ego[:, 1, BOUNDARY].all() and ego[1, :, BOUNDARY].all()
    assert ego[3, 3, EMPTY] == 1 and ego[4, 4, EMPTY] == 1

    blocks = feats[EGO_DIM : EGO_DIM + MAP_DIM].view(5, 5, 21)
    assert blocks.sum() == 100 and (blocks.sum(-1) == 4).all()
    assert blocks[0, 0, BOUNDARY] == 3 and blocks[0, 0, EMPTY] == 1
    assert blocks[0, 1, BOUNDARY] == 2 and blocks[0, 1, WOOD] == 1 and blocks[0, 1, EMPTY] == 1
    assert blocks[1, 0, IRON] == 1 and blocks[1, 0, BOUNDARY] == 2
    assert blocks[2, 2, EMPTY] == 4 and blocks[4, 4, BOUNDARY] == 3

    inventory = feats[EGO_DIM + MAP_DIM : EGO_DIM + MAP_DIM + 21]
    assert inventory[WOOD] == 2 and inventory.sum() == 2
    assert feats[-4:].tolist() == [0, 0, 0, 1]

    batch = torch.stack([state, torch.as_tensor(CraftEnv().reset(seed=0)[0])]).repeat(3, 1, 1)
    out = ompn_features(batch)
    assert out.shape == (3, 2, 1075)
    torch.testing.assert_close(out[2, 0], feats)


def reference_window(state: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The bordered 10x10 grid of one compact state, and the one-hot [size * size * N_KINDS] of the
    size x size window centred on the agent (cells off the grid count as boundary), entry by entry."""
    grid = np.full((GRID_SIZE, GRID_SIZE), BOUNDARY)
    grid[1:-1, 1:-1] = state[CELLS].reshape(INTERIOR_SIZE, INTERIOR_SIZE)
    row, col, radius = state[AGENT_ROW] + 1, state[AGENT_COL] + 1, size // 2
    window = np.zeros(size * size * N_KINDS, dtype=np.float32)
    for i in range(size):
        for j in range(size):
            r, c = row + i - radius, col + j - radius
            kind = grid[r, c] if 0 <= r < GRID_SIZE and 0 <= c < GRID_SIZE else BOUNDARY
            window[(i * size + j) * N_KINDS + kind] = 1
    return grid, window


def reference_ompn_features(state: np.ndarray) -> np.ndarray:
    """OMPN features of one compact state, entry by entry as the observation module documents them."""
    grid, window = reference_window(state, 5)
    feats = np.zeros(OMPN_DIM, dtype=np.float32)
    feats[:EGO_DIM] = window
    for r in range(GRID_SIZE):
        for c in range(GRID_SIZE):
            feats[EGO_DIM + ((r // 2) * 5 + c // 2) * N_KINDS + grid[r, c]] += 1
    feats[EGO_DIM + MAP_DIM + 7 : EGO_DIM + MAP_DIM + N_KINDS] = state[INVENTORY]
    feats[EGO_DIM + MAP_DIM + N_KINDS + state[FACING]] = 1
    return feats


def test_ompn_features_match_the_entry_by_entry_reference_at_every_agent_cell():
    rng = np.random.default_rng(0)
    states = rng.integers(0, OBS_HIGH + 1, size=(4 * INTERIOR_SIZE**2, OBS_DIM))
    states[:, AGENT_ROW], states[:, AGENT_COL] = np.divmod(np.arange(len(states)) % INTERIOR_SIZE**2, INTERIOR_SIZE)
    states[:, FACING] = np.arange(len(states)) // INTERIOR_SIZE**2
    states = np.concatenate([states, CraftEnv().reset(seed=3)[0][None]])
    expected = np.stack([reference_ompn_features(state) for state in states])
    assert np.array_equal(ompn_features(torch.as_tensor(states)).numpy(), expected)
    assert np.array_equal(ompn_features(torch.as_tensor(states, dtype=torch.float32)).numpy(), expected)


def reference_full_view_features(state: np.ndarray) -> np.ndarray:
    """The exact egocentric view of one compact state, entry by entry as the observation module documents it."""
    _, window = reference_window(state, 15)
    feats = np.zeros(FULL_VIEW_DIM, dtype=np.float32)
    feats[: window.size] = window
    feats[window.size + 7 : window.size + N_KINDS] = state[INVENTORY]
    feats[window.size + N_KINDS + state[FACING]] = 1
    return feats


def test_full_view_features_match_the_reference_and_hold_the_whole_map_from_every_agent_cell():
    rng = np.random.default_rng(1)
    states = rng.integers(0, OBS_HIGH + 1, size=(2 * INTERIOR_SIZE**2, OBS_DIM))
    states[:, AGENT_ROW], states[:, AGENT_COL] = np.divmod(np.arange(len(states)) % INTERIOR_SIZE**2, INTERIOR_SIZE)
    states[:, FACING] = np.arange(len(states)) % 4
    expected = np.stack([reference_full_view_features(state) for state in states])
    feats = full_view_features(torch.as_tensor(states)).numpy()
    assert feats.shape == (len(states), FULL_VIEW_DIM) and np.array_equal(feats, expected)
    # Every interior cell is in the window wherever the agent stands: per kind, the window's count
    # of a kind other than the boundary is the map's.
    window = feats[:, : 15 * 15 * N_KINDS].reshape(len(states), 15 * 15, N_KINDS).sum(1)
    counts = np.stack([np.bincount(state[CELLS], minlength=N_KINDS) for state in states])
    kinds = np.arange(N_KINDS) != BOUNDARY
    assert np.array_equal(window[:, kinds], counts[:, kinds])


def test_gym_registration():
    env = gym.make("OCN/Craft-v0", task="AC")
    obs, info = env.reset(seed=0)
    assert obs.shape == (81,) and info["task"] == "get wood, get iron"
    obs, reward, terminated, truncated, info = env.step(0)
    assert isinstance(reward, float) and "subtask_index" in info
    full = gym.make("OCN/CraftFull-v0", task="make bed")
    assert full.unwrapped.task == "AEDF"
    assert full.unwrapped.task_description == "get wood, use toolshed, get grass, use workbench"
    venv = gym.make_vec("OCN/Craft-v0", num_envs=3, task="DA")
    assert isinstance(venv, CraftVectorEnv) and venv.reset(seed=0)[0].shape == (3, 81)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        importlib.reload(envs)
