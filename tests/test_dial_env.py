"""Dial rules, wrappers, registration and the LeRobot env plugin, on the real MuJoCo scene."""

from __future__ import annotations

import os
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

from lerobot_policy_ocn import envs  # noqa: F401  (registers OCN/Dial-v0)
from lerobot_policy_ocn.envs.dial import (
    GEARS,
    OBS_DIM,
    PRESS_L1,
    DialBatch,
    DialEnv,
    DialVectorEnv,
    RestDynamics,
    default_max_steps,
    dial_poses,
    key_positions,
    parse_digits,
    parse_pin,
    sample_pin,
    task_description,
)


def hold(batch: DialBatch) -> np.ndarray:
    """Controls that cancel gravity at the current pose, so a placed arm stays (nearly) put for a step."""
    gravity = RestDynamics(batch.model)(batch.qpos)[1]
    return np.clip(gravity / np.array(GEARS), -1.0, 1.0)


def place_and_step(batch: DialBatch, qpos: np.ndarray):
    """Put env 0 at `qpos` at rest, hold it there for one env step, and unbatch the result."""
    batch.set_qpos([0], qpos)
    obs, reward, terminated, truncated, info = batch.step(hold(batch))
    return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), {k: v[0] for k, v in info.items()}


def test_observation_layout():
    env = DialEnv(task="12")
    obs, info = env.reset(seed=3)
    assert obs.shape == (OBS_DIM,) == (39,) and obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    data = env.batch.data[0]
    np.testing.assert_allclose(obs[:9], data.qpos, rtol=1e-6)
    tip = data.site_xpos[env.batch.model.site("fingertip").id]
    np.testing.assert_allclose(obs[9:].reshape(10, 3), tip - key_positions(), atol=1e-6)
    assert info == {"subtask": 0, "progress": 0, "is_success": False, "task": "press 1, press 2"}


def test_key_layout_is_a_phone_pad():
    keys = key_positions()
    np.testing.assert_allclose(keys[5], [0.5, 0.07, 0.05])
    np.testing.assert_allclose(keys[[1, 2, 3], 1], [0.21] * 3)  # top row
    np.testing.assert_allclose(keys[[1, 4, 7], 0], [0.36] * 3)  # first column
    np.testing.assert_allclose(keys[0], [0.5, -0.21, 0.05])


def test_press_pose_presses_and_hover_pose_does_not():
    poses = dial_poses()
    batch = DialBatch(1)
    batch.reset(seeds=[0], tasks=["48"])
    _, reward, _, _, info = place_and_step(batch, poses.hover[4])
    assert info["key"] == -1 and reward == 0.0
    _, reward, _, _, info = place_and_step(batch, poses.press[4])
    assert np.abs(batch.tip[0] - key_positions()[4]).sum() < PRESS_L1
    assert info["key"] == 4 and info["subtask_done"] and reward == 1.0 and info["progress"] == 1


def test_key_counts_again_only_after_release():
    poses = dial_poses()
    batch = DialBatch(1)
    batch.reset(seeds=[0], tasks=["858"])
    assert place_and_step(batch, poses.press[8])[4]["key"] == 8
    assert place_and_step(batch, poses.press[8])[4]["key"] == -1  # still held down: no second press
    assert place_and_step(batch, poses.hover[8])[4]["key"] == -1
    assert place_and_step(batch, poses.press[5])[4]["key"] == 5
    assert place_and_step(batch, poses.hover[5])[4]["key"] == -1
    _, _, terminated, _, info = place_and_step(batch, poses.press[8])
    assert info["key"] == 8 and terminated and info["is_success"]


@pytest.mark.parametrize(("reward_mode", "rewards"), [("dense", [0.0, 1.0, 1.0]), ("sparse", [0.0, 0.0, 1.0])])
def test_dense_and_sparse_rewards_and_wrong_keys(reward_mode, rewards):
    poses = dial_poses()
    batch = DialBatch(1, reward=reward_mode)
    batch.reset(seeds=[0], tasks=["12"])
    wrong = place_and_step(batch, poses.press[2])  # 2 before 1: counts for nothing
    assert wrong[4]["key"] == 2 and not wrong[4]["subtask_done"] and wrong[4]["progress"] == 0
    first = place_and_step(batch, poses.press[1])
    place_and_step(batch, poses.hover[1])
    last = place_and_step(batch, poses.press[2])
    assert [wrong[1], first[1], last[1]] == rewards
    assert last[2] and last[4]["is_success"] and last[4]["subtask_index"] == 1
    frozen = batch.step(np.ones((1, 9)))
    assert frozen[1][0] == 0.0 and not frozen[2][0] and not frozen[3][0]


def test_step_limits():
    assert default_max_steps(2) == 300 and default_max_steps(3) == 450
    env = DialEnv(task="124")
    env.reset(seed=0)
    assert env.batch.max_steps[0] == 450
    short = DialEnv(task="12", max_steps=3)
    short.reset(seed=0)
    ends = [short.step(np.zeros(9))[2:4] for _ in range(3)]
    assert ends == [(False, False), (False, False), (False, True)]
    qpos = short.batch.qpos.copy()
    assert short.step(np.ones(9))[2:4] == (False, False)
    np.testing.assert_array_equal(short.batch.qpos, qpos)  # frozen until reset


def test_seeding_is_deterministic():
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, size=(5, 9))

    def rollout(seed: int) -> tuple[np.ndarray, str]:
        env = DialEnv()
        obs = [env.reset(seed=seed)[0]] + [env.step(a)[0] for a in actions]
        return np.stack(obs), env.task

    a, pin_a = rollout(11)
    b, pin_b = rollout(11)
    c, _ = rollout(12)
    np.testing.assert_array_equal(a, b)
    assert pin_a == pin_b and len(pin_a) == 2
    assert not np.allclose(a[0], c[0])
    assert np.abs(a[-1] - a[0]).max() > 1e-3  # the actions move the arm


def test_vector_env_matches_single_envs_and_autoresets():
    venv = DialVectorEnv(2, task=["12", None], max_steps=2)
    obs, info = venv.reset(seed=5)
    for i in range(2):
        single = DialEnv(task="12" if i == 0 else None)
        np.testing.assert_array_equal(obs[i], single.reset(seed=5 + i)[0])
        assert info["task"][i] == single.task_description
    zeros = np.zeros((2, 9))
    venv.step(zeros)
    _, _, _, truncated, _ = venv.step(zeros)
    assert truncated.all()
    obs, reward, terminated, truncated, info = venv.step(zeros)  # next-step autoreset
    assert not truncated.any() and (info["progress"] == 0).all() and (reward == 0).all()
    assert venv.batch.t.tolist() == [0, 0]


def test_task_parsing_and_random_pins():
    assert parse_pin("124") == (1, 2, 4) == parse_pin("press 1, press 2, press 4")
    assert task_description((8, 1)) == "press 8, press 1"
    for bad in ("", "1a", "press 11", "１２"):
        with pytest.raises(ValueError, match="PIN|Dial task"):
            parse_pin(bad)
    assert parse_digits("1,2,4,8") == (1, 2, 4, 8)
    for bad in ("1", "1,1", "1,10", "a,b"):
        with pytest.raises(ValueError, match="digits"):
            parse_digits(bad)
    rng = np.random.default_rng(0)
    pins = [sample_pin(rng, 3, (1, 2, 4, 8)) for _ in range(300)]
    assert all(set(p) <= {1, 2, 4, 8} and p[0] != p[1] and p[1] != p[2] for p in pins)
    assert len(set(pins)) == 4 * 3 * 3


def test_invalid_actions_raise():
    env = DialEnv(task="12")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.full(9, np.nan))
    with pytest.raises(ValueError):
        env.step(np.zeros(8))


def test_gym_registration():
    env = gym.make("OCN/Dial-v0", task="48", reward="sparse")
    obs, info = env.reset(seed=0)
    assert obs.shape == (39,) and info["task"] == "press 4, press 8"
    _, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and {"subtask", "is_success", "key"} <= set(info)
    venv = gym.make_vec("OCN/Dial-v0", num_envs=3, pin_length=3)
    assert isinstance(venv, DialVectorEnv)
    assert venv.reset(seed=0)[0].shape == (3, 39) and all(len(t.split(", ")) == 3 for t in venv.task_descriptions)


def test_lerobot_env_config_make_env():
    import lerobot_policy_ocn  # noqa: F401  (registers --env.type=dial as LeRobot's CLIs do)
    from lerobot.envs.configs import EnvConfig
    from lerobot.envs.factory import make_env

    from lerobot_policy_ocn.envs.dial.lerobot_env import motor_controls

    cfg = EnvConfig.get_choice_class("dial")(task="21", render_mode=None)
    assert cfg.features["agent_pos"].shape == (39,) and cfg.features["action"].shape == (9,)
    venv = make_env(cfg, n_envs=2)["dial"][0]
    obs, _ = venv.reset(seed=0)
    assert obs["agent_pos"].shape == (2, 39)
    assert list(venv.call("task_description")) == ["press 2, press 1"] * 2
    assert list(venv.call("_max_episode_steps")) == [300, 300]
    _, reward, terminated, truncated, info = venv.step(np.zeros((2, 9), dtype=np.float32))
    assert reward.shape == (2,) and not info["is_success"].any()
    with pytest.raises(ValueError, match="9 motor controls"):
        motor_controls(np.zeros(3))


def _render_in_subprocess(backend: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY")}
    if backend:
        env["MUJOCO_GL"] = backend
    code = (
        "from lerobot_policy_ocn.envs.dial import DialEnv\n"
        "e = DialEnv(task='12', render_mode='rgb_array'); e.reset(seed=0)\n"
        "try:\n    f = e.render()\nexcept RuntimeError as err:\n    print('ERROR', err)\n"
        "else:\n    print('FRAME', f.shape, f.dtype, int(f.std() > 10))\n"
    )
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def test_render_without_opengl_is_a_clear_error():
    out = _render_in_subprocess(None).stdout
    assert out.startswith("ERROR Dial rendering needs an OpenGL backend") and "MUJOCO_GL=egl" in out


def test_render_with_egl():
    out = _render_in_subprocess("egl").stdout
    if out.startswith("ERROR"):
        pytest.skip(f"no EGL on this machine: {out.strip()}")
    assert out.strip() == "FRAME (240, 320, 3) uint8 1"
