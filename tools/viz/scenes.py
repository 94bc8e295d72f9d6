"""What `ocn-view` draws of each world's recorded steps: the scene and the world's own series.

A `Scene` logs its static styles once, then each episode's per-step columns on the `frame`
timeline, and names the views the blueprint places them in (`view` on the left, `plots` under the
segmentation on the right). The lanes, p^c, e_t and summaries are the same for every world and
live in `tools/viz/rerun_log.py`. Entity paths:

    Craft
    scene                Image      the grid, drawn from the recorded state by lerobot_policy_ocn.envs.craft.render
    action               Scalars    the action code, as points (0 down, 1 up, 2 left, 3 right, 4 use)

    Dial (no OpenGL: the scene is points, placed from the recorded state and lerobot_policy_ocn.envs.dial.scene)
    scene/keys           Points3D   each key's press point, labelled with its digit (static)
    scene/fingertip      Points3D   the fingertip, coloured as the true digit being dialled
    joints               Scalars    the 9 joint angles (rad), one series per joint
    key_distance         Scalars    L1 distance (m) of the fingertip to each key's press point
    action               Scalars    the 9 recorded motor controls, one series per motor

    BabyAI, and any dataset of a world the tools do not know (`PlainScene`: no scene to draw)
    action               Scalars    the recorded action, one series per dimension
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from lerobot_policy_ocn.envs.craft.observation import AGENT_COL, AGENT_ROW, CELLS, FACING, INVENTORY
from lerobot_policy_ocn.envs.craft.render import TILE, render_batch
from lerobot_policy_ocn.envs.craft.world import ACTION_NAMES, BOUNDARY, GRID_SIZE, INTERIOR_SIZE
from lerobot_policy_ocn.envs.dial.scene import JOINTS, KEY_HALF_SIZE, N_JOINTS, key_positions
from lerobot_policy_ocn.tools.viz.segmentation_plot import subtask_colours

if TYPE_CHECKING:
    from lerobot_policy_ocn.tools.viz.episode import Episode


class Scene(Protocol):
    """A world's part of the recording."""

    def log_styles(self, rec: rr.RecordingStream) -> None:
        """Static styles of the scene's entities, logged once."""

    def log_steps(self, rec: rr.RecordingStream, episode: Episode, indexes: list[rr.TimeColumn]) -> None:
        """One episode's per-step columns, at the frames `indexes`."""

    def view(self) -> rrb.View:
        """The scene's view, top left."""

    def plots(self) -> list[rrb.View]:
        """Time-series views of the world's own series, bottom right."""


class CraftScene:
    """The grid as the env draws it, and the discrete action."""

    def log_styles(self, rec: rr.RecordingStream) -> None:
        side = GRID_SIZE * TILE
        rec.log("scene", rr.Image.from_fields(format=rr.components.ImageFormat(
            width=side, height=side, color_model="RGB", channel_datatype="U8")), static=True)
        codes = ", ".join(f"{code} {name}" for code, name in enumerate(ACTION_NAMES))
        rec.log("action", rr.SeriesPoints(names=f"action ({codes})", marker_sizes=3), static=True)

    def log_steps(self, rec: rr.RecordingStream, episode: Episode, indexes: list[rr.TimeColumn]) -> None:
        scene = craft_scene_images(episode.state).reshape(len(episode.state), -1)
        rec.send_columns("scene", indexes=indexes, columns=rr.Image.columns(buffer=scene))
        rec.send_columns("action", indexes=indexes, columns=rr.Scalars.columns(scalars=episode.action[:, 0]))

    def view(self) -> rrb.View:
        return rrb.Spatial2DView(origin="scene", name="scene")

    def plots(self) -> list[rrb.View]:
        return [rrb.TimeSeriesView(origin="action", name="action",
                                   axis_y=rrb.ScalarAxis(range=(-0.5, len(ACTION_NAMES) - 0.5)))]


def craft_scene_images(states: np.ndarray) -> np.ndarray:
    """Frames [T, 160, 160, 3] uint8 of compact Craft states [T, 81], drawn by the env's own
    renderer (the inventory on the border): the state keeps only the grid's interior (the border is
    always boundary) and the agent's interior coordinates, so both are put back first."""
    n = len(states)
    grid = np.full((n, GRID_SIZE, GRID_SIZE), BOUNDARY, dtype=np.int64)
    grid[:, 1:-1, 1:-1] = states[:, CELLS].reshape(n, INTERIOR_SIZE, INTERIOR_SIZE)
    return render_batch(grid, states[:, [AGENT_ROW, AGENT_COL]] + 1, states[:, FACING], states[:, INVENTORY])


KEY_COLOUR = (200, 200, 190)
FINGERTIP_RADIUS = 0.015


class DialScene:
    """The fingertip among the keys in 3D, the joint angles, the distances to the keys, the controls."""

    def __init__(self) -> None:
        self.keys = key_positions()

    def log_styles(self, rec: rr.RecordingStream) -> None:
        digits = [str(d) for d in range(len(self.keys))]
        rec.log("scene/keys", rr.Points3D(self.keys, radii=KEY_HALF_SIZE[0] / 2, colors=KEY_COLOUR, labels=digits,
                                          show_labels=True), static=True)
        rec.log("joints", rr.SeriesLines(names=[f"q {name}" for name in JOINTS], widths=1.5), static=True)
        rec.log("key_distance", rr.SeriesLines(names=[f"key {d}" for d in digits],
                                               colors=subtask_colours(len(digits)), widths=1.5), static=True)
        rec.log("action", rr.SeriesLines(names=[f"u {name}" for name in JOINTS], widths=1.5), static=True)

    def fingertip(self, states: np.ndarray) -> np.ndarray:
        """Fingertip positions [T, 3] (m): the state's fingertip-minus-key-0 offset plus key 0's press point."""
        return states[:, N_JOINTS:N_JOINTS + 3] + self.keys[0]

    def log_steps(self, rec: rr.RecordingStream, episode: Episode, indexes: list[rr.TimeColumn]) -> None:
        state = episode.state
        offsets = state[:, N_JOINTS:].reshape(len(state), len(self.keys), 3)
        colours = subtask_colours(len(self.keys))[episode.subtask_id] if episode.subtask_id is not None \
            else np.tile(KEY_COLOUR, (len(state), 1))
        rec.send_columns("scene/fingertip", indexes=indexes, columns=rr.Points3D.columns(
            positions=self.fingertip(state), colors=colours, radii=np.full(len(state), FINGERTIP_RADIUS)))
        rec.send_columns("joints", indexes=indexes, columns=rr.Scalars.columns(scalars=state[:, :N_JOINTS]))
        rec.send_columns("key_distance", indexes=indexes,
                         columns=rr.Scalars.columns(scalars=np.abs(offsets).sum(axis=2)))
        rec.send_columns("action", indexes=indexes, columns=rr.Scalars.columns(scalars=episode.action))

    def view(self) -> rrb.View:
        return rrb.Spatial3DView(origin="scene", name="fingertip and keys")

    def plots(self) -> list[rrb.View]:
        return [
            rrb.TimeSeriesView(origin="joints", name="joint angles (rad)"),
            rrb.TimeSeriesView(origin="key_distance", name="fingertip to key press points (L1, m)"),
            rrb.TimeSeriesView(origin="action", name="motor controls",
                               axis_y=rrb.ScalarAxis(range=(-1.05, 1.05))),
        ]


class PlainScene:
    """A world without a drawn scene: the recorded action only, beside the option lanes."""

    def log_styles(self, rec: rr.RecordingStream) -> None:
        rec.log("action", rr.SeriesPoints(names="action", marker_sizes=3), static=True)

    def log_steps(self, rec: rr.RecordingStream, episode: Episode, indexes: list[rr.TimeColumn]) -> None:
        rec.send_columns("action", indexes=indexes, columns=rr.Scalars.columns(scalars=episode.action))

    def view(self) -> rrb.View:
        return rrb.TimeSeriesView(origin="action", name="action")

    def plots(self) -> list[rrb.View]:
        return []
