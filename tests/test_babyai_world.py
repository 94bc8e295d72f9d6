"""BabyAI as a world of the tools (tools/worlds.py, tools/rl/babyai_rollouts.py): the batch the rollouts step
follows minigrid's own verdicts, with the bot acting in it, and the bot's rate comes through
`lerobot_policy_ocn.envs.babyai.rollout.run_missions` on the same (mission, seed) pairs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lerobot_policy_ocn.envs.babyai import minigrid_installed
from lerobot_policy_ocn.envs.babyai.missions import MISSIONS, SUBGOALS

pytestmark = pytest.mark.skipif(not minigrid_installed(), reason="minigrid is not installed: uv sync --extra babyai")


def test_the_batch_follows_the_bot_to_minigrids_success():
    from lerobot_policy_ocn.envs.babyai.minigrid_api import BabyAIBot
    from lerobot_policy_ocn.tools.rl.babyai_rollouts import BABYAI_WORLD

    missions = [MISSIONS[0].text, MISSIONS[40].text, "pick_key"]
    batch, obs = BABYAI_WORLD.start(missions, [7, 8, 9])
    assert obs.shape == (3, 148) and batch.task_len.tolist() == [2, 3, 1]
    assert batch.task_of(2) == (SUBGOALS.index("pick up the grey key"),)
    bots = [BabyAIBot(env.level) for env in batch.envs]
    steps = 0
    while not batch.done.all():
        actions = np.array([[0 if done else bot.replan()] for bot, done in zip(bots, batch.done, strict=True)])
        before = batch.progress.copy()
        obs, reward, terminated, truncated, info = batch.step(BABYAI_WORLD.env_action(actions))
        assert (batch.progress >= before).all() and not truncated.any()
        assert np.array_equal(reward > 0, terminated)  # sparse: paid on the step that completes the mission
        steps += 1
    assert (batch.progress == batch.task_len).all() and 0 < steps <= 64 * 3
    assert np.array_equal(obs[0], batch.envs[0].level.gen_obs()["image"].reshape(-1).tolist() + [
        batch.envs[0].level.agent_dir])


def test_the_bots_rate_is_read_on_the_rollouts_pairs():
    from lerobot_policy_ocn.tools.rl.babyai_rollouts import bot_success

    rates = bot_success([MISSIONS[3].text, MISSIONS[100].text], episodes=2, seed=100_000)
    assert rates == {MISSIONS[3].text: 1.0, MISSIONS[100].text: 1.0}


def test_a_babyai_dataset_is_the_babyai_world(tmp_path: Path):
    from lerobot_policy_ocn.tools.worlds import world_of

    root = tmp_path / "ds" / "meta"
    root.mkdir(parents=True)
    (root / "info.json").write_text(json.dumps({"robot_type": "babyai", "features": {}}))
    world = world_of(tmp_path / "ds")
    assert world.name == "babyai" and world.subtask_labels == SUBGOALS and world.rollouts is not None
    task = MISSIONS[130].text
    assert world.task_description(world.task_subtasks(task)) == task
    assert world.parse_task_list(f"{MISSIONS[0].text}; {task}") == [MISSIONS[0].subgoals, MISSIONS[130].subgoals]
    assert world.used_subtasks([task]) == [world.subtask_codes[s] for s in MISSIONS[130].subgoals]
