"""Offscreen RGB frames of the Dial scene (optional: needs an OpenGL backend).

MuJoCo renders through OpenGL. Physics never needs it, but frames do: set `MUJOCO_GL=egl` (a GPU
host, or Mesa's EGL on a CPU host) or `MUJOCO_GL=osmesa` (Debian's `libosmesa6`) before MuJoCo is
imported. Without a working backend, creating a renderer raises one clear error instead of
MuJoCo's own.
"""

from __future__ import annotations

import os

import mujoco
import numpy as np

from lerobot_policy_ocn.envs.dial.scene import CAMERA

HEIGHT, WIDTH = 240, 320


class DialRenderer:
    """Frames of one ``MjData`` from the scene's overview camera."""

    def __init__(self, model: mujoco.MjModel, height: int = HEIGHT, width: int = WIDTH):
        try:
            self._renderer = mujoco.Renderer(model, height, width)
        except Exception as err:  # MuJoCo raises FatalError, AttributeError or ImportError by backend
            backend = os.environ.get("MUJOCO_GL", "unset")
            raise RuntimeError(
                f"Dial rendering needs an OpenGL backend and none works here (MUJOCO_GL={backend}: {err}). "
                "Set MUJOCO_GL=egl or MUJOCO_GL=osmesa before starting Python, or use render_mode=None; "
                "the physics runs without rendering."
            ) from err

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """HxWx3 uint8 frame."""
        self._renderer.update_scene(data, camera=CAMERA)
        return self._renderer.render()

    def close(self) -> None:
        self._renderer.close()
