"""Scripted Dial expert: a joint-space PD controller to IK joint targets, for a whole ``DialBatch``.

For the digit an env must press next, the joint target lies between the key's hover pose (fingertip
`HOVER_HEIGHT` above the press point) and its press pose (`lerobot_policy_ocn.envs.dial.poses.dial_poses()`, IK solved
once per process), set by the fingertip's horizontal L1 distance d to the key's press point: the
hover pose while d >= 2 `PRESS_BLEND`, the press pose once d <= `PRESS_BLEND`, linearly in between.
So the hand comes down over the key, not on its edge, and a new digit starts from wherever the last
press left the hand.

Control (computed torque at rest): ``tau = M(q) OMEGA^2 e + g(q)`` on the arm, ``tau = FINGER_KP e + g(q)``
on the fingers (held closed), where ``e`` is the joint error, ``M`` the joint-space inertia and ``g`` the
gravity torque, both at the current pose (`RestDynamics`); the control sent is ``tau / gear`` clipped
to [-1, 1]. The scene's joint damping (`lerobot_policy_ocn.envs.dial.scene.ARM_DAMPING`, about 2 OMEGA times each arm
joint's inertia) brings the arm to rest, so every arm joint closes on its target like a spring of
OMEGA = 12 rad/s, near critically damped, OMEGA x 0.04 s = 0.48 per env step.

Why no velocity feedback: the control is then a function of the 39-float observation and the digit
alone, which is what an option sees and what the controller adds. The expert before this one damped
the motion itself (``- 2 OMEGA M(q) qdot``, with Coriolis forces) from joint velocities that the
observation does not hold; a memoryless network predicted 0.79 of its control's variance from the
observation and the digit, and no more with the last step's change of the observation (0.77),
against 0.98 with the velocities (`results/archive/bench_clonability_velocity_pd_2026-12-03/`). A fifth of the
control was noise to every option, and OCN's options did not split by digit on it
(`results/archive/dial_option_split_pd/`). This expert's control is 0.99 explained by the observation and
the digit (`results/archive/bench_clonability_2026-12-03/`).

Why this kind of controller, measured by behaviour cloning (`results/archive/dial_expert/`): the PID expert
of the first Dial sessions, with gains 20-40 times higher (its loop near the limit of stability at
one control every 0.04 s, so its controls flipped between the limits) that switched from hover to
press on a hidden event (the fingertip held still over the key), could not be cloned: a single
option trained on one digit reached the hover point and stayed there, success 0. A smooth
controller without hidden state (no integral, no phase flag) can: its target is a function of the
digit and of the fingertip's offset to the key, which the observation holds.

DART noise (Laskey et al. 2017), for demonstrations that cover recoveries: each episode draws a
noise level from `NOISE_LEVELS`; the executed control is the expert's plus Gaussian noise of that
standard deviation (in control units), redrawn every 5-30 steps. `act()` returns the clean
control, which is what a demonstration records; `perturb()` adds the noise for execution. The
levels are those of the reference demonstrations (`REFERENCE_NOISE_LEVELS`) halved: noise of 0.3 of
full torque, held for up to 30 steps, pushes this softer controller far off its path
(`results/bench_dial.md` runs the expert under both).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from lerobot_policy_ocn.envs.dial.batch import DialBatch
from lerobot_policy_ocn.envs.dial.poses import dial_poses
from lerobot_policy_ocn.envs.dial.scene import GEARS, N_ARM_JOINTS, N_JOINTS

OMEGA = 12.0
PRESS_BLEND = 0.04
FINGER_KP = 5.0
NOISE_LEVELS = (0.0, 0.1, 0.2)
REFERENCE_NOISE_LEVELS = (0.0, 0.2, 0.3)
NOISE_HOLD = (5, 30)

_GEARS = np.array(GEARS)
_FINGERS = slice(N_ARM_JOINTS, N_JOINTS)


class RestDynamics:
    """Joint-space inertia M(q) and gravity torque g(q) of the Dial scene at given poses, at rest.

    Evaluated on a scratch ``MjData`` (pose set, velocities zero, ``mj_forward``), so the result
    depends on the pose alone, never on the state of a simulated env.
    """

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self._data = mujoco.MjData(model)

    def __call__(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(M (n, 9, 9), g (n, 9)) for the poses ``qpos`` (n, 9)."""
        n, dof = qpos.shape
        mass, gravity = np.zeros((n, dof, dof)), np.zeros((n, dof))
        data = self._data
        for i, pose in enumerate(qpos):
            data.qpos[:] = pose
            data.qvel[:] = 0.0
            mujoco.mj_forward(self.model, data)
            mujoco.mj_fullM(self.model, data, mass[i])
            gravity[i] = data.qfrc_bias
        return mass, gravity


class DialExpert:
    """Expert controls for every env of ``batch``; call ``reset`` after resetting envs, ``act`` before each step."""

    def __init__(self, batch: DialBatch, noise_levels: Sequence[float] = NOISE_LEVELS):
        self.batch = batch
        self.noise_levels = tuple(float(x) for x in noise_levels)
        n = batch.num_envs
        poses = dial_poses()
        self._hover, self._press = poses.hover, poses.press
        self._rest = RestDynamics(batch.model)
        self.noise_level = np.zeros(n)
        self._noise = np.zeros((n, N_JOINTS))
        self._noise_left = np.zeros(n, dtype=np.int64)
        self._rngs = [np.random.default_rng(i) for i in range(n)]

    def reset(
        self,
        env_ids: Sequence[int] | np.ndarray | None = None,
        seeds: Sequence[int | None] | None = None,
    ) -> None:
        """Start the selected envs' episodes with a fresh noise level.

        ``seeds[i]`` reseeds env ``env_ids[i]``'s noise Generator, so an episode's noise depends on
        its seed only, not on which batch slot or neighbours it has.
        """
        ids = np.arange(self.batch.num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        for k, i in enumerate(ids.tolist()):
            if seeds is not None and seeds[k] is not None:
                self._rngs[i] = np.random.default_rng([int(seeds[k]), 1])
            self.noise_level[i] = self._rngs[i].choice(self.noise_levels)
        self._noise[ids] = 0.0
        self._noise_left[ids] = 0

    def targets(self) -> np.ndarray:
        """Joint targets (n, 9): each env's next digit's press pose, lifted towards its hover pose by the
        fingertip's horizontal distance to the key (see the module docstring)."""
        b = self.batch
        digit = np.maximum(b.current_digit(), 0)
        horizontal = np.abs(b.tip[:, :2] - b.keys[digit, :2]).sum(axis=1)
        lift = np.clip(horizontal / PRESS_BLEND - 1.0, 0.0, 1.0)[:, None]
        return self._press[digit] + lift * (self._hover[digit] - self._press[digit])

    def act(self) -> np.ndarray:
        """Clean expert controls (n, 9) in [-1, 1] for the batch's current state."""
        b = self.batch
        error = self.targets() - b.qpos
        mass, gravity = self._rest(b.qpos)
        torque = np.einsum("nij,nj->ni", mass, OMEGA**2 * error) + gravity
        torque[:, _FINGERS] = FINGER_KP * error[:, _FINGERS] + gravity[:, _FINGERS]
        return np.clip(torque / _GEARS, -1.0, 1.0)

    def perturb(self, controls: np.ndarray) -> np.ndarray:
        """The controls to execute: ``controls`` plus each env's current DART noise, clipped."""
        redraw = np.flatnonzero(self._noise_left <= 0)
        for i in redraw.tolist():
            rng = self._rngs[i]
            self._noise[i] = rng.normal(0.0, self.noise_level[i], N_JOINTS) if self.noise_level[i] else 0.0
            self._noise_left[i] = rng.integers(NOISE_HOLD[0], NOISE_HOLD[1] + 1)
        self._noise_left -= 1
        return np.clip(controls + self._noise, -1.0, 1.0)
