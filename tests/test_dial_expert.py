"""IK poses and the scripted Dial expert (PD to hover / press targets, DART noise), on real MuJoCo."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from lerobot_policy_ocn.envs.dial import PRESS_L1, DialBatch, DialExpert, dial_model, dial_poses, key_positions
from lerobot_policy_ocn.envs.dial.expert import NOISE_HOLD, NOISE_LEVELS, PRESS_BLEND
from lerobot_policy_ocn.envs.dial.poses import HOVER_HEIGHT


def fingertip(qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fingertip position and hand axis at joint angles `qpos`."""
    model = dial_model()
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    site = model.site("fingertip").id
    return data.site_xpos[site].copy(), data.site_xmat[site].reshape(3, 3)[:, 2].copy()


def test_ik_poses_reach_their_points_pointing_down():
    poses = dial_poses()
    for digit, point in enumerate(key_positions()):
        tip, axis = fingertip(poses.press[digit])
        np.testing.assert_allclose(tip, point, atol=1e-5)
        np.testing.assert_allclose(axis, [0, 0, 1], atol=1e-5)
        tip, _ = fingertip(poses.hover[digit])
        np.testing.assert_allclose(tip, point + [0, 0, HOVER_HEIGHT], atol=1e-5)
    model = dial_model()
    limited = model.jnt_limited.astype(bool)
    for pose in (poses.home, *poses.hover, *poses.press):
        inside = (pose >= model.jnt_range[:, 0]) & (pose <= model.jnt_range[:, 1])
        assert inside[limited].all()


def run(pins: list[str], noise_levels: tuple[float, ...], seed: int = 0):
    """Play the expert (with DART noise executed) until every env is done."""
    batch = DialBatch(len(pins))
    seeds = [seed + i for i in range(len(pins))]
    batch.reset(seeds=seeds, tasks=pins)
    expert = DialExpert(batch, noise_levels)
    expert.reset(seeds=seeds)
    success = np.zeros(len(pins), dtype=bool)
    labels = [[] for _ in pins]
    while not batch.done.all():
        active = ~batch.done
        _, _, terminated, _, info = batch.step(expert.perturb(expert.act()))
        for i in np.flatnonzero(active):
            labels[i].append(int(batch.tasks[i, info["subtask_index"][i]]))
        success |= terminated
    return batch, success, labels


def test_expert_dials_pins():
    pins = ["12", "84", "41", "28", "124", "8142", "36", "90"]
    batch, success, labels = run(pins, (0.0,))
    assert success.all()
    for pin, steps, label in zip(pins, batch.t, labels, strict=True):
        assert steps < 60 * len(pin)
        digits = [int(d) for d in pin]
        assert [d for k, d in enumerate(label) if k == 0 or label[k - 1] != d] == digits  # one segment per digit


def test_expert_recovers_under_dart_noise():
    _, success, _ = run(["12", "48", "81", "24", "42", "18"], (max(NOISE_LEVELS),), seed=100)
    assert success.all()


def test_dart_noise_levels_and_holds():
    batch = DialBatch(64)
    batch.reset(seeds=list(range(64)))
    expert = DialExpert(batch)
    expert.reset(seeds=list(range(64)))
    assert set(expert.noise_level.tolist()) == set(NOISE_LEVELS)
    clean = np.zeros((64, 9))
    noise = np.stack([expert.perturb(clean) for _ in range(80)])  # (steps, envs, 9)
    quiet = expert.noise_level == 0.0
    assert (noise[:, quiet] == 0).all() and (noise[:, ~quiet] != 0).any(axis=(0, 2)).all()
    for i in np.flatnonzero(~quiet)[:10]:
        changes = np.flatnonzero((np.diff(noise[:, i], axis=0) != 0).any(axis=1)) + 1
        holds = np.diff(np.concatenate([[0], changes]))
        assert holds.min() >= NOISE_HOLD[0] and holds.max() <= NOISE_HOLD[1]

    again = DialExpert(batch)
    again.reset(seeds=list(range(64)))
    np.testing.assert_array_equal(np.stack([again.perturb(clean) for _ in range(80)]), noise)


@pytest.mark.parametrize("digit", [0, 5, 9])
def test_expert_targets_the_press_pose_over_the_key_and_the_hover_pose_away_from_it(digit):
    """The target follows the fingertip's horizontal distance to the key, which the observation holds:
    over the key the press pose, 2 PRESS_BLEND or more away the hover pose, linearly in between."""
    poses = dial_poses()
    batch = DialBatch(1)
    batch.reset(seeds=[0], tasks=[str(digit)])
    expert = DialExpert(batch, (0.0,))
    expert.reset(seeds=[0])
    batch.set_qpos([0], poses.hover[digit])
    np.testing.assert_allclose(expert.targets()[0], poses.press[digit])
    far = (digit + 1) % 10
    batch.set_qpos([0], poses.hover[far])
    assert np.abs(batch.tip[0, :2] - key_positions()[digit, :2]).sum() >= 2 * PRESS_BLEND
    np.testing.assert_allclose(expert.targets()[0], poses.hover[digit])
    halfway = np.array(poses.hover[digit])
    halfway[0] += 0.08  # turn the base: the fingertip swings sideways off the key, into the blend
    batch.set_qpos([0], halfway)
    offset = np.abs(batch.tip[0, :2] - key_positions()[digit, :2]).sum()
    lift = offset / PRESS_BLEND - 1.0
    assert 0.1 < lift < 0.5
    np.testing.assert_allclose(expert.targets()[0],
                               poses.press[digit] + lift * (poses.hover[digit] - poses.press[digit]))
    batch.set_qpos([0], poses.hover[digit])
    for _ in range(60):
        _, _, terminated, _, _ = batch.step(expert.act())
        if terminated[0]:
            break
    assert terminated[0] and np.abs(batch.tip[0] - key_positions()[digit]).sum() < PRESS_L1


def test_expert_controls_change_smoothly():
    """A policy must be able to imitate the expert: while it works on one digit, no control flips
    between the limits from one step to the next (the PID it replaced flipped them every few steps).
    When the next digit starts, the target jumps to its key, and the controls with it."""
    batch, _, _ = run(["12", "48", "81", "24"], (0.0,))
    assert (batch.t < 60).all()
    batch = DialBatch(4)
    batch.reset(seeds=[0, 1, 2, 3], tasks=["12", "48", "81", "24"])
    expert = DialExpert(batch, (0.0,))
    expert.reset(seeds=[0, 1, 2, 3])
    controls, digits = [], []
    while not batch.done.all():
        controls.append(expert.act())
        digits.append(batch.current_digit())
        batch.step(controls[-1])
    steps = np.abs(np.diff(np.array(controls)[:40], axis=0))
    same_digit = np.diff(np.array(digits)[:40], axis=0) == 0
    assert steps[same_digit].max() < 1.0 and steps[same_digit].mean() < 0.1
    assert steps.max() > 1.0  # the switch itself does jump, so leaving it out is what lets the check above pass
