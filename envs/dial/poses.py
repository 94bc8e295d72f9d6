"""Joint-space poses of the Dial scene, found by inverse kinematics on the fingertip site.

Damped least squares on a 6-row task: the fingertip position and the hand's axis (its z axis,
along which the closed fingers point away) held vertical, so the hand always points straight down
at the pad. Only the six arm joints move; the fingers stay at `FINGERS_CLOSED`.

The home pose (fingertip 0.25 m above the pad centre) is solved from a fixed elbow-up seed; each
key's hover pose (fingertip `HOVER_HEIGHT` above the press point) from the home pose and its press
pose from the hover pose, so all poses lie on the same arm branch and hover-to-press is a short
vertical move. The 21 solves take well under a second, so they are computed lazily, once per
process, and memoised (`dial_poses()`); nothing is written to disk.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mujoco
import numpy as np

from lerobot_policy_ocn.envs.dial.scene import (
    FINGERTIP_SITE, N_ARM_JOINTS, N_JOINTS, PAD_CENTER, dial_model, key_positions,
)

HOVER_HEIGHT = 0.1
HOME_TIP = PAD_CENTER + np.array([0.0, 0.0, 0.25])
FINGERS_CLOSED = 1.2
# Elbow up, forearm over the pad: the IK seed of the home pose.
IK_SEED = np.array([0.0, 2.5, 4.5, 0.0, 0.0, 0.0, FINGERS_CLOSED, FINGERS_CLOSED, FINGERS_CLOSED])
UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class DialPoses:
    """Joint targets (9 angles each): `home`, and `hover[d]` / `press[d]` for every digit d."""

    home: np.ndarray
    hover: np.ndarray
    press: np.ndarray


def solve_ik(
    model: mujoco.MjModel,
    target: np.ndarray,
    seed: np.ndarray,
    *,
    iterations: int = 500,
    damping: float = 0.05,
    max_step: float = 0.2,
    tolerance: float = 1e-7,
) -> np.ndarray:
    """Joint angles putting the fingertip at `target` with the hand pointing down, from `seed`.

    Raises if the solve does not converge: a silent near-miss would become a wrong expert target.
    """
    data = mujoco.MjData(model)
    site = model.site(FINGERTIP_SITE).id
    arm = slice(0, N_ARM_JOINTS)
    limited = model.jnt_limited[arm].astype(bool)
    low, high = model.jnt_range[arm, 0], model.jnt_range[arm, 1]
    jac_pos = np.zeros((3, model.nv))
    jac_rot = np.zeros((3, model.nv))
    q = np.array(seed, dtype=np.float64)
    for _ in range(iterations):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        axis = data.site_xmat[site].reshape(3, 3)[:, 2]
        error = np.concatenate([target - data.site_xpos[site], np.cross(axis, UP)])
        if np.linalg.norm(error) < tolerance:
            return q
        mujoco.mj_jacSite(model, data, jac_pos, jac_rot, site)
        jac = np.vstack([jac_pos, jac_rot])[:, arm]
        step = jac.T @ np.linalg.solve(jac @ jac.T + damping**2 * np.eye(6), error)
        step *= min(1.0, max_step / max(np.linalg.norm(step), 1e-12))
        q[arm] = np.where(limited, np.clip(q[arm] + step, low, high), q[arm] + step)
    raise RuntimeError(f"Dial IK did not converge for fingertip target {target} (residual {np.linalg.norm(error):.2e})")


@functools.cache
def dial_poses() -> DialPoses:
    """Home, hover and press poses of the shared Dial model (solved on first use, then memoised)."""
    model = dial_model()
    home = solve_ik(model, HOME_TIP, IK_SEED)
    hover, press = np.zeros((2, len(key_positions()), N_JOINTS))
    for digit, point in enumerate(key_positions()):
        hover[digit] = solve_ik(model, point + [0.0, 0.0, HOVER_HEIGHT], home)
        press[digit] = solve_ik(model, point, hover[digit])
    for array in (home, hover, press):
        array.setflags(write=False)
    return DialPoses(home=home, hover=hover, press=press)
