"""Batched Dial simulator: every rule of the task lives here, applied to all envs at once.

``DialBatch`` holds ``n`` MuJoCo ``MjData`` of one shared model and steps each with
``mj_step(nstep=FRAME_SKIP)`` (the action is held for 20 physics steps of 2 ms, so one env step is
0.04 s); key presses, rewards and limits are then decided for the whole batch with array
operations. The gymnasium wrappers (a single env is a batch of one), the expert and the recorder
all drive this class, so the rules cannot drift apart.

Rules, per env and step:

* The action is 9 motor controls in [-1, 1] (clipped), torques of the motor gears.
* A key is pressed when the fingertip comes within `PRESS_L1` (L1 distance, metres) of its press
  point, judged after each env step. A pressed key must be left (fingertip farther than
  `RELEASE_L1`) before it can count again; an env that starts near a key must leave it first.
* Pressing the PIN's next digit completes that subtask. Any other key press (a wrong digit, or a
  digit of the PIN out of order) counts for nothing: no reward, no penalty, progress kept, as in
  the OMPN / TACO Dial env, which only checks the current target. `info["key"]` reports it.
* Reward is +1 per correct key in order ("dense") or 1 once the whole PIN is dialled ("sparse").
  An env terminates when the PIN is dialled and truncates at its step limit
  (`STEPS_PER_DIGIT` per digit unless overridden).

Envs that are done are frozen (no physics, reward 0, terminated and truncated False) until reset.
The public arrays (``qpos``, ``tip``, ...) mirror the simulator state after the last step or reset.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from lerobot_policy_ocn.envs.batching import EpisodeBatch, env_rng, reset_ids
from lerobot_policy_ocn.envs.dial.poses import dial_poses
from lerobot_policy_ocn.envs.dial.scene import FINGERTIP_SITE, N_JOINTS, TIMESTEP, dial_model, key_positions
from lerobot_policy_ocn.envs.dial.task import (
    DEFAULT_DIGITS, REWARDS, default_max_steps, parse_digits, parse_pin, sample_pin,
)

FRAME_SKIP = 20
CONTROL_DT = FRAME_SKIP * TIMESTEP
PRESS_L1 = 0.02
RELEASE_L1 = 0.04
# Uniform half-width (radians) of the random offset of every joint from the home pose at reset.
RESET_NOISE = 0.1
OBS_DIM = N_JOINTS + 3 * len(key_positions())

PinSpec = Sequence[int] | str | None


class DialBatch(EpisodeBatch):
    """State and rules of ``num_envs`` Dial envs, each with its own PIN and Generator."""

    def __init__(
        self,
        num_envs: int,
        reward: str = "dense",
        max_steps: int | None = None,
        digits: str | Sequence[int] = DEFAULT_DIGITS,
        pin_length: int = 2,
    ):
        if pin_length < 1:
            raise ValueError(f"pin_length must be >= 1, got {pin_length}")
        super().__init__(num_envs, reward, REWARDS, max_steps)
        n = num_envs
        self.digits = parse_digits(digits)
        self.pin_length = pin_length
        self.model = dial_model()
        self.data = [mujoco.MjData(self.model) for _ in range(n)]
        self.keys = key_positions()
        self._site = self.model.site(FINGERTIP_SITE).id
        self._low = np.where(self.model.jnt_limited, self.model.jnt_range[:, 0], -np.inf)
        self._high = np.where(self.model.jnt_limited, self.model.jnt_range[:, 1], np.inf)
        self.qpos = np.zeros((n, N_JOINTS))
        self.qvel = np.zeros((n, N_JOINTS))
        self.tip = np.zeros((n, 3))
        self.armed = np.zeros((n, len(self.keys)), dtype=bool)

    def reset(
        self,
        seeds: Sequence[int | None] | None = None,
        tasks: Sequence[PinSpec] | None = None,
        env_ids: Sequence[int] | np.ndarray | None = None,
    ) -> np.ndarray:
        """Start new episodes in the selected envs (default: all) and return all observations.

        ``seeds[i]`` reseeds env ``env_ids[i]``'s Generator (``None`` continues it); it draws the
        start pose (home plus uniform ``RESET_NOISE``) and any random PIN. ``tasks[i]`` is a PIN
        (digits, a string, or None for a random PIN of ``pin_length`` from ``digits``); no tasks
        means random PINs for all.
        """
        ids = reset_ids(self.num_envs, env_ids, seeds=seeds, tasks=tasks)
        home = dial_poses().home
        pins = []
        for k, i in enumerate(ids.tolist()):
            rng = self.rngs[i] = env_rng(self.rngs[i], None if seeds is None else seeds[k])
            spec = None if tasks is None else tasks[k]
            pins.append(self._pin(spec, rng))
            data = self.data[i]
            mujoco.mj_resetData(self.model, data)
            data.qpos[:] = np.clip(home + rng.uniform(-RESET_NOISE, RESET_NOISE, N_JOINTS), self._low, self._high)
            mujoco.mj_forward(self.model, data)
        self._set_tasks(ids, pins)
        self._sync(ids)
        self.armed[ids] = self._key_distance(ids) > RELEASE_L1
        self._restart(ids)
        return self.observe()

    def set_qpos(self, env_ids: Sequence[int] | np.ndarray, qpos: np.ndarray) -> np.ndarray:
        """Place envs' joints at ``qpos`` (one row per env) at rest, for scripted scenarios and tests;
        press detection then judges the new fingertip at the next step. Returns all observations."""
        ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        for i, row in zip(ids.tolist(), np.broadcast_to(qpos, (len(ids), N_JOINTS)), strict=True):
            data = self.data[i]
            data.qpos[:] = row
            data.qvel[:] = 0.0
            mujoco.mj_forward(self.model, data)
        self._sync(ids)
        return self.observe()

    def _pin(self, spec: PinSpec, rng: np.random.Generator) -> tuple[int, ...]:
        if spec is None:
            return sample_pin(rng, self.pin_length, self.digits)
        pin = parse_pin(spec) if isinstance(spec, str) else tuple(int(d) for d in spec)
        if not pin or any(d < 0 or d >= len(self.keys) for d in pin):
            raise ValueError(f"a Dial PIN holds digits 0-9, got {spec!r}")
        return pin

    def _set_tasks(self, ids: np.ndarray, pins: list[tuple[int, ...]]) -> None:
        """Store PINs in the task table, with one spare -1 column: the "finished" target."""
        self._store_tasks(ids, pins, default_max_steps, spare=1)

    def current_digit(self) -> np.ndarray:
        """Digit each env must press next; -1 once its PIN is dialled."""
        return self.tasks[self._arange, self.progress]

    def _sync(self, ids: np.ndarray) -> None:
        """Copy the joint state and fingertip of envs ``ids`` into the batch arrays."""
        for i in ids.tolist():
            data = self.data[i]
            self.qpos[i] = data.qpos
            self.qvel[i] = data.qvel
            self.tip[i] = data.site_xpos[self._site]

    def _key_distance(self, ids: np.ndarray | slice = slice(None)) -> np.ndarray:
        """L1 distance from the fingertip to every key's press point, (len(ids), 10)."""
        return np.abs(self.tip[ids, None, :] - self.keys[None]).sum(axis=2)

    def observe(self) -> np.ndarray:
        """State (n, 39) float32: 9 joint angles, then fingertip minus each key's press point (10 x 3)."""
        n = self.num_envs
        obs = np.empty((n, OBS_DIM), dtype=np.float32)
        obs[:, :N_JOINTS] = self.qpos
        obs[:, N_JOINTS:] = (self.tip[:, None, :] - self.keys[None]).reshape(n, -1)
        return obs

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Advance every env by one action; returns (obs, reward, terminated, truncated, info)."""
        n = self.num_envs
        if (self.task_len == 0).any():
            raise RuntimeError("reset every env before stepping")
        controls = np.asarray(actions, dtype=np.float64).reshape(n, N_JOINTS)
        if not np.isfinite(controls).all():
            raise ValueError("Dial actions must be finite")
        controls = np.clip(controls, -1.0, 1.0)
        active = ~self.done
        ids = np.flatnonzero(active)
        for i in ids.tolist():
            data = self.data[i]
            data.ctrl[:] = controls[i]
            mujoco.mj_step(self.model, data, nstep=FRAME_SKIP)
            mujoco.mj_kinematics(self.model, data)
        self._sync(ids)

        distance = self._key_distance()
        near = distance < PRESS_L1
        hit = near & self.armed & active[:, None]
        self.armed = np.where(active[:, None], (self.armed & ~near) | (distance > RELEASE_L1), self.armed)
        key = np.where(hit.any(axis=1), hit.argmax(axis=1), -1)

        sub_done = (key >= 0) & (key == self.current_digit())
        reward, terminated, truncated, info = self._advance(sub_done, active)
        return self.observe(), reward, terminated, truncated, {**info, "key": key}
