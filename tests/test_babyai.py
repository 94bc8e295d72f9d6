"""BabyAI (envs.babyai, ocn_data.record_babyai): the mission language, the one-line errors without
minigrid, and, with minigrid (the `babyai` extra), a tiny dataset recorded through the command and
read back by LeRobot and by lerobot_policy_ocn.ocn_data.episodes_table, ground-truth labels on real episodes and
free runs of the bot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lerobot_policy_ocn.envs.babyai import BABYAI_ENV_ID, INSTALL_HINT, minigrid_installed
from lerobot_policy_ocn.envs.babyai.missions import MISSIONS, SUBGOALS, parse_mission
from lerobot_policy_ocn.envs.babyai.observation import STATE_DIM
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.ocn_data.record_babyai import env_seed, main

ROOT = Path(__file__).resolve().parents[1]
REPO_ID = "local/babyai_test"
EPISODES = 30

needs_minigrid = pytest.mark.skipif(
    not minigrid_installed(), reason="minigrid is not installed: uv sync --extra babyai (or pip install '.[babyai]')"
)


def python(code: str) -> subprocess.CompletedProcess:
    """`code` in a fresh interpreter at the checkout's root."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_mission_language() -> None:
    assert len(SUBGOALS) == 6 and len(MISSIONS) == 150
    assert len({m.text for m in MISSIONS}) == 150
    assert {len(m.subgoals) for m in MISSIONS} == {2, 3}
    assert all(len(set(m.subgoals)) == len(m.subgoals) for m in MISSIONS)
    text = "open the red door and pick up the yellow ball, then open the green door"
    assert parse_mission(text).subgoals == (0, 3, 1)
    assert parse_mission("pick up the grey key").subgoals == (5,)
    with pytest.raises(ValueError, match="not a mission"):
        parse_mission("go to the red door")


def test_without_minigrid_nothing_is_registered_and_errors_say_how_to_install(tmp_path: Path) -> None:
    hide = "import sys; sys.modules['minigrid'] = None; "
    done = python(hide + "import gymnasium, lerobot_policy_ocn.envs.babyai; "
                  f"assert {BABYAI_ENV_ID!r} not in gymnasium.registry; "
                  "import lerobot_policy_ocn.envs.babyai.env")
    assert done.returncode != 0 and f"MinigridMissing: {INSTALL_HINT}" in done.stderr
    args = ["--root", str(tmp_path / "d"), "--repo-id", REPO_ID, "--episodes", "1"]
    done = python(hide + f"from lerobot_policy_ocn.ocn_data.record_babyai import main; sys.exit(main({args!r}))")
    assert done.returncode == 2
    assert done.stderr.splitlines() == [f"record_babyai: {INSTALL_HINT}"]
    assert "pip install '.[babyai]'" in INSTALL_HINT and not (tmp_path / "d").exists()


@needs_minigrid
def test_registration_does_not_import_minigrid() -> None:
    done = python("import sys, gymnasium, lerobot_policy_ocn.envs.babyai; "
                  f"assert {BABYAI_ENV_ID!r} in gymnasium.registry; "
                  "assert 'minigrid' not in sys.modules; env = gymnasium.make(" + repr(BABYAI_ENV_ID) + "); "
                  "state, info = env.reset(seed=1); assert env.observation_space.contains(state), state; "
                  "print(info['mission'])")
    assert done.returncode == 0, done.stderr
    parse_mission(done.stdout.strip())


@needs_minigrid
def test_envs_package_registers_babyai_with_craft_and_dial() -> None:
    done = python("import sys, gymnasium, lerobot_policy_ocn.envs as envs; "
                  f"assert {BABYAI_ENV_ID!r} in gymnasium.registry and envs.BABYAI_ENV_ID == {BABYAI_ENV_ID!r}; "
                  "assert envs.DIAL_ENV_ID in gymnasium.registry; assert 'minigrid' not in sys.modules")
    assert done.returncode == 0, done.stderr


def test_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    existing = tmp_path / "exists"
    existing.mkdir()
    cases = {
        (str(existing), REPO_ID): "already exists",
        (str(tmp_path / "new"), "babyai"): "exactly one slash",
        (str(tmp_path / "new"), "a/b/c"): "exactly one slash",
    }
    for (root, repo_id), message in cases.items():
        assert main(["--root", root, "--repo-id", repo_id, "--episodes", "3"]) == 2
        lines = capsys.readouterr().err.splitlines()
        assert len(lines) == 1 and lines[0].startswith("record_babyai: ") and message in lines[0]
    assert not (tmp_path / "new").exists()


def test_env_seeds_never_repeat() -> None:
    seeds = {env_seed(seed, attempt) for seed in range(3) for attempt in range(1000)}
    assert len(seeds) == 3000 and env_seed(1, 0) > env_seed(0, 2**32 - 1)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 episodes recorded by the command itself, as a user runs it."""
    if not minigrid_installed():
        pytest.skip("minigrid is not installed: uv sync --extra babyai (or pip install '.[babyai]')")
    root = tmp_path_factory.mktemp("babyai") / "data"
    command = [sys.executable, "-m", "lerobot_policy_ocn.ocn_data.record_babyai", "--root", str(root),
               "--repo-id", REPO_ID, "--episodes", str(EPISODES), "--seed", "7"]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return root


def test_lerobot_reads_the_recording(dataset: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    data = LeRobotDataset(REPO_ID, root=dataset)
    assert data.meta.robot_type == "babyai" and data.num_episodes == EPISODES
    features = data.meta.features
    assert features["observation.state"]["dtype"] == "int64"
    assert tuple(features["observation.state"]["shape"]) == (STATE_DIM,)
    for key in ("action", "subtask.index", "subtask.id"):
        assert (features[key]["dtype"], tuple(features[key]["shape"])) == ("int64", (1,))
    assert set(data.meta.tasks.index) == {m.text for m in MISSIONS[:EPISODES]}
    frame = data[0]
    assert frame["observation.state"].shape == (STATE_DIM,) and frame["task"] == MISSIONS[0].text
    assert 0 <= int(frame["action"]) <= 5


def test_split_is_the_last_fifth(dataset: Path) -> None:
    info = json.loads((dataset / "meta" / "info.json").read_text())
    assert info["splits"] == {"train": "0:24", "val": "24:30"}
    assert split_episodes(dataset, "val") == range(24, 30)


def test_ground_truth_follows_each_mission(dataset: Path) -> None:
    episodes = load_episodes(dataset, split_episodes(dataset, "all"))
    assert episodes.state.shape[2] == STATE_DIM and len(episodes.tasks) == EPISODES
    for k, task in enumerate(episodes.tasks):
        n = episodes.lengths[k]
        index, subgoal = episodes.subtask_index[k, :n], episodes.subtask_id[k, :n]
        mission = parse_mission(task)
        steps = np.diff(index)
        assert index[0] == 0 and index[-1] == len(mission.subgoals) - 1
        assert set(steps.tolist()) <= {0, 1}
        starts = np.flatnonzero(np.r_[True, steps > 0])
        assert tuple(subgoal[starts].tolist()) == mission.subgoals
        assert np.all(subgoal == subgoal[starts][index])


@needs_minigrid
def test_mission_strings_are_minigrids_own() -> None:
    from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv

    env = BabyAIEnv()
    for text in [m.text for m in MISSIONS] + list(SUBGOALS):
        env.reset(seed=0, options={"mission": text})
        assert env.task_description == env.level.instrs.surface(env.level) == text


@needs_minigrid
def test_render_draws_the_grid() -> None:
    from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv

    env = BabyAIEnv(mission=MISSIONS[0].text, render_mode="rgb_array")
    env.reset(seed=2)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert env.task_description == MISSIONS[0].text


@needs_minigrid
def test_state_layout_shows_the_carried_object() -> None:
    """Right after a pickup, the agent's own cell (x 3, y 6) of the view holds the object it carries."""
    from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv
    from lerobot_policy_ocn.envs.babyai.expert import demonstrate
    from lerobot_policy_ocn.envs.babyai.minigrid_api import COLOR_TO_IDX, OBJECT_TO_IDX

    demo = demonstrate(BabyAIEnv(), "pick up the purple box, then open the blue door", seed=11)
    t = int(np.flatnonzero(demo.action == 3)[0])
    agent_cell = 21 * 3 + 3 * 6
    assert demo.state[t, agent_cell] == OBJECT_TO_IDX["empty"]
    assert demo.state[t + 1, agent_cell : agent_cell + 2].tolist() == [OBJECT_TO_IDX["box"], COLOR_TO_IDX["purple"]]
    assert demo.subtask_index[t] == 0 and demo.subtask_index[t + 1] == 1


@needs_minigrid
def test_labels_follow_the_order_the_verifier_saw() -> None:
    """In "A and B, then C" either order completes the mission; a bot that does B first (planned on
    the mission with A and B swapped) gets labels in that order."""
    from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv
    from lerobot_policy_ocn.envs.babyai.level import mission_instr
    from lerobot_policy_ocn.envs.babyai.minigrid_api import BabyAIBot

    env = BabyAIEnv()
    env.reset(seed=5, options={"mission": "pick up the yellow ball and open the red door, then open the green door"})
    verifier = env.level.instrs
    env.level.instrs = mission_instr(parse_mission(
        "open the red door and pick up the yellow ball, then open the green door"))
    env.level.instrs.reset_verifier(env.level)
    bot = BabyAIBot(env.level)
    env.level.instrs = verifier
    success = False
    while not env.over:
        success = env.step(bot.replan())[4]["is_success"]
    assert success
    index, subgoal = env.tracker.labels()
    starts = np.flatnonzero(np.r_[True, np.diff(index) > 0])
    assert subgoal[starts].tolist() == [0, 3, 1] and index[-1] == 2


@needs_minigrid
def test_free_runs_of_the_bot_succeed_and_of_a_spinner_fail() -> None:
    from lerobot_policy_ocn.envs.babyai.expert import BotPolicy
    from lerobot_policy_ocn.envs.babyai.rollout import run_missions

    missions = [m.text for m in MISSIONS[::15]] + ["open the blue door"]
    seeds = list(range(100, 100 + len(missions)))
    assert run_missions(BotPolicy(), missions, seeds).all()

    class Spinner:
        def reset(self, envs: list) -> None:
            pass

        def __call__(self, states: np.ndarray, missions: list[str]) -> np.ndarray:
            assert states.shape == (len(missions), STATE_DIM)
            return np.zeros(len(missions), dtype=np.int64)

    assert not run_missions(Spinner(), missions[:3], seeds[:3]).any()
