"""Scripted Dial expert: a joint-space PD controller to IK joint targets, for a whole ``DialBatch``.

For the digit an env must press next, the joint target lies between the key's hover pose (fingertip
`HOVER_HEIGHT` above the press point) and its press pose (`envs.dial.poses.dial_poses()`, IK solved
once per process), set by the fingertip's horizontal L1 distance d to the key's press point: the
hover pose while d >= 2 `PRESS_BLEND`, the press pose once d <= `PRESS_BLEND`, linearly in between.
So the hand comes down over the key, not on its edge, and a new digit starts from wherever the last
press left the hand.

Control (computed torque): ``tau = M(q) (OMEGA^2 e - 2 DAMPING_RATIO OMEGA qdot) + bias`` on the arm,
``tau = FINGER_KP e - FINGER_KD qdot + bias`` on the fingers (held closed), where ``e`` is the joint
error, ``M`` the joint-space inertia and ``bias`` the simulator's gravity and Coriolis force; the
control sent is ``tau / gear`` clipped to [-1, 1]. Every arm joint then closes on its target like a
critically damped spring of OMEGA = 12 rad/s, OMEGA x 0.04 s = 0.48 per env step. The expert reads
the simulator's joint velocities, inertia and bias forces, which the 39-float observation does not
hold: it is privileged, as scripted experts are.

Why this controller, measured by behaviour cloning (`results/dial_expert/`): a policy has to be able
to imitate it. The earlier expert, a PID with gains 20-40 times higher (its loop near the limit of
stability at one control every 0.04 s, so its controls flipped between the limits) that switched
from hover to press on a hidden event (the fingertip held still over the key), could not be cloned:
a single option trained on one digit reached the hover point and stayed there, success 0. This one
keeps no hidden state (no integral, no phase flag): its target is a function of the digit and of the
fingertip's offset to the key, which the observation holds, and its controls change smoothly.

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

import numpy as np

from envs.dial.batch import DialBatch
from envs.dial.poses import dial_poses
from envs.dial.scene import GEARS, N_ARM_JOINTS, N_JOINTS

OMEGA = 12.0
DAMPING_RATIO = 1.0
PRESS_BLEND = 0.04
FINGER_KP = 5.0
FINGER_KD = 0.5
NOISE_LEVELS = (0.0, 0.1, 0.2)
REFERENCE_NOISE_LEVELS = (0.0, 0.2, 0.3)
NOISE_HOLD = (5, 30)

_GEARS = np.array(GEARS)
_FINGERS = slice(N_ARM_JOINTS, N_JOINTS)


class DialExpert:
    """Expert controls for every env of ``batch``; call ``reset`` after resetting envs, ``act`` before each step."""

    def __init__(self, batch: DialBatch, noise_levels: Sequence[float] = NOISE_LEVELS):
        self.batch = batch
        self.noise_levels = tuple(float(x) for x in noise_levels)
        n = batch.num_envs
        poses = dial_poses()
        self._hover, self._press = poses.hover, poses.press
        self.noise_level = np.zeros(n)
        self._noise = np.zeros((n, N_JOINTS))
        self._noise_left = np.zeros(n, dtype=np.int64)
        self._rngs = [np.random.default_rng(i) for i in range(n)]

    def reset(self, env_ids: Sequence[int] | np.ndarray | None = None, seeds: Sequence[int | None] | None = None) -> None:
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
        acceleration = OMEGA**2 * error - 2.0 * DAMPING_RATIO * OMEGA * b.qvel
        torque = np.einsum("nij,nj->ni", b.mass_matrices(), acceleration) + b.bias
        torque[:, _FINGERS] = FINGER_KP * error[:, _FINGERS] - FINGER_KD * b.qvel[:, _FINGERS] + b.bias[:, _FINGERS]
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
