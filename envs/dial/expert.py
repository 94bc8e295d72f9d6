"""Scripted Dial expert: a joint-space PID controller to IK joint targets, for a whole ``DialBatch``.

For the digit an env must press next, the target is first the key's hover pose (fingertip
`HOVER_HEIGHT` above the press point), then its press pose; the targets come from
`envs.dial.poses.dial_poses()` (IK, solved once per process). The switch to the press pose waits
until the fingertip is over the key (`HOVER_XY_L1` horizontally, `HOVER_Z_TOLERANCE` vertically)
and nearly still (`SETTLED_TIP_STEP` per env step), so the hand comes down vertically instead of
landing off-centre and catching on the key's edge. A new digit starts again from hover.

Control, per joint: ``tau = KP * e + KI * integral(e) - KD * qdot + bias``, where ``bias`` is the
simulator's gravity and Coriolis force (feed-forward gravity compensation) and the integral is
clamped to `INTEGRAL_LIMIT` (rad s) against wind-up; the control sent is ``tau / gear`` clipped
to [-1, 1]. The expert reads the simulator's joint velocities and bias forces, which the 39-float
observation does not hold: it is privileged, as scripted experts are.

DART noise (Laskey et al. 2017), for demonstrations that cover recoveries: each episode draws a
noise level from `NOISE_LEVELS`; the executed control is the expert's plus Gaussian noise of that
standard deviation (in control units), redrawn every 5-30 steps. `act()` returns the clean
control, which is what a demonstration records; `perturb()` adds the noise for execution.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from envs.dial.batch import CONTROL_DT, DialBatch
from envs.dial.poses import HOVER_HEIGHT, dial_poses
from envs.dial.scene import GEARS, N_JOINTS

KP = np.array([1000.0, 2000.0, 2000.0, 400.0, 400.0, 400.0, 5.0, 5.0, 5.0])
KD = np.array([70.0, 120.0, 120.0, 15.0, 15.0, 15.0, 0.5, 0.5, 0.5])
KI = 2.0 * KP
INTEGRAL_LIMIT = 0.005
HOVER_XY_L1 = 0.02
HOVER_Z_TOLERANCE = 0.04
SETTLED_TIP_STEP = 0.004
NOISE_LEVELS = (0.0, 0.2, 0.3)
NOISE_HOLD = (5, 30)

_GEARS = np.array(GEARS)


class DialExpert:
    """Expert controls for every env of ``batch``; call ``reset`` after resetting envs, ``act`` before each step."""

    def __init__(self, batch: DialBatch, noise_levels: Sequence[float] = NOISE_LEVELS):
        self.batch = batch
        self.noise_levels = tuple(float(x) for x in noise_levels)
        n = batch.num_envs
        poses = dial_poses()
        self._hover, self._press = poses.hover, poses.press
        self.pressing = np.zeros(n, dtype=bool)
        self._progress = np.full(n, -1, dtype=np.int64)
        self._integral = np.zeros((n, N_JOINTS))
        self._previous_tip = batch.tip.copy()
        self.noise_level = np.zeros(n)
        self._noise = np.zeros((n, N_JOINTS))
        self._noise_left = np.zeros(n, dtype=np.int64)
        self._rngs = [np.random.default_rng(i) for i in range(n)]

    def reset(self, env_ids: Sequence[int] | np.ndarray | None = None, seeds: Sequence[int | None] | None = None) -> None:
        """Start the selected envs' episodes: hover phase, no integral, a fresh noise level.

        ``seeds[i]`` reseeds env ``env_ids[i]``'s noise Generator, so an episode's noise depends on
        its seed only, not on which batch slot or neighbours it has.
        """
        ids = np.arange(self.batch.num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        for k, i in enumerate(ids.tolist()):
            if seeds is not None and seeds[k] is not None:
                self._rngs[i] = np.random.default_rng([int(seeds[k]), 1])
            self.noise_level[i] = self._rngs[i].choice(self.noise_levels)
        self._progress[ids] = -1
        self._previous_tip[ids] = self.batch.tip[ids]
        self._noise[ids] = 0.0
        self._noise_left[ids] = 0

    def targets(self) -> np.ndarray:
        """Joint targets (n, 9) of the current phase: hover or press pose of each env's next digit."""
        b = self.batch
        digit = np.maximum(b.current_digit(), 0)
        new_digit = b.progress != self._progress
        self._progress = b.progress.copy()
        self.pressing &= ~new_digit
        self._integral[new_digit] = 0.0

        offset = b.tip - b.keys[digit] - [0.0, 0.0, HOVER_HEIGHT]
        moved = np.abs(b.tip - self._previous_tip).sum(axis=1)
        self._previous_tip = b.tip.copy()
        over_key = (np.abs(offset[:, :2]).sum(axis=1) < HOVER_XY_L1) & (np.abs(offset[:, 2]) < HOVER_Z_TOLERANCE)
        start_press = ~self.pressing & over_key & (moved < SETTLED_TIP_STEP)
        self._integral[start_press] = 0.0
        self.pressing |= start_press
        return np.where(self.pressing[:, None], self._press[digit], self._hover[digit])

    def act(self) -> np.ndarray:
        """Clean expert controls (n, 9) in [-1, 1] for the batch's current state."""
        b = self.batch
        error = self.targets() - b.qpos
        self._integral = np.clip(self._integral + error * CONTROL_DT, -INTEGRAL_LIMIT, INTEGRAL_LIMIT)
        torque = KP * error + KI * self._integral - KD * b.qvel + b.bias
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
