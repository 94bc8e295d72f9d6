"""Observation encoders: turn the stored `observation.state` into the cell input x_t.

Craft datasets store a compact symbolic state (81 ints), which is expanded inside the policy: far
cheaper to record and load than the one-hot itself. `craft` gives OMPN's 1075-float observation (the
paper's); `craft_full_view` gives the exact egocentric map (4750 floats), in which the scripted
expert's action is a function of the observation (objects beyond OMPN's 5x5 window are placed only to
their 2x2 block there).

Dial's 39 floats go in standardised by the preprocessor (`identity`), as the paper's model reads them,
or raw (`dial_keys`), from which `DialKeyEncoder` adds each key's log L1 distance: the quantity the env
presses a key on.
"""

import math

import torch
from torch import Tensor, nn

from lerobot_policy_ocn.envs.craft.observation import (
    FULL_VIEW_DIM, OMPN_DIM, full_view_features, ompn_active_entries, ompn_features,
)
from lerobot_policy_ocn.envs.dial import OBS_DIM as DIAL_STATE_DIM
from lerobot_policy_ocn.envs.dial import PRESS_L1
from lerobot_policy_ocn.envs.dial.poses import dial_poses
from lerobot_policy_ocn.envs.dial.scene import N_JOINTS

from lerobot_policy_ocn.ocn.cell import SparseRows
from lerobot_policy_ocn.sequence import CRAFT_ENCODERS, SequenceConfig


class CraftEncoder(nn.Module):
    """Compact Craft state [..., 81] -> OMPN features [..., 1075] via `lerobot_policy_ocn.envs.craft.observation`;
    `full_view`: the exact egocentric view [..., 4750] instead."""

    def __init__(self, full_view: bool = False) -> None:
        super().__init__()
        self.features = full_view_features if full_view else ompn_features
        self.out_dim = FULL_VIEW_DIM if full_view else OMPN_DIM

    def forward(self, state: Tensor) -> Tensor:
        return self.features(self._ids(state))

    @staticmethod
    def _ids(state: Tensor) -> Tensor:
        return state.round().long() if state.is_floating_point() else state.long()

    def sparse(self, state: Tensor) -> SparseRows | None:
        """The OMPN features as their 140 set entries (`SparseRows`), for a first layer that sums weight rows
        rather than multiply the 1,075-wide features; None for the full view, which is built dense."""
        if self.features is not ompn_features:
            return None
        return SparseRows(*ompn_active_entries(self._ids(state)))


class IdentityEncoder(nn.Module):
    """Float state used as is (e.g. Dial's 39 floats, already normalised by the preprocessor)."""

    def __init__(self, state_dim: int) -> None:
        super().__init__()
        self.out_dim = state_dim

    def forward(self, state: Tensor) -> Tensor:
        return state.float()


class DialKeyEncoder(nn.Module):
    """Raw Dial state [..., 39] -> [..., 49]: the joint angles from the home pose in units of
    `JOINT_SCALE`, the fingertip's offset from each key's press point in units of `OFFSET_SCALE`, and
    each key's log(L1 distance / `PRESS_L1`).

    Why: a key counts as pressed when the L1 distance falls below `PRESS_L1` = 2 cm, while the
    standardised offsets move by about 0.25 per 2 cm; the frames either side of a press differ by
    millimetres there, and an option's termination has to carve that diamond out of three inputs. In
    the log distance the press is one input crossing 0. The scales are fixed physical units (about
    one standard deviation of the recorded demonstrations), so the encoder holds no statistics and
    needs none from the dataset.
    """

    JOINT_SCALE = 0.3
    OFFSET_SCALE = 0.1
    # Floor of the L1 distance inside the log (metres): the fingertip never sits exactly on a point.
    MIN_DISTANCE = 1e-3

    def __init__(self) -> None:
        super().__init__()
        self.n_keys = (DIAL_STATE_DIM - N_JOINTS) // 3
        self.out_dim = DIAL_STATE_DIM + self.n_keys
        self.register_buffer("home", torch.tensor(dial_poses().home, dtype=torch.float32), persistent=False)

    def forward(self, state: Tensor) -> Tensor:
        state = state.float()
        joints, offsets = state[..., :N_JOINTS], state[..., N_JOINTS:]
        distance = offsets.unflatten(-1, (self.n_keys, 3)).abs().sum(-1)
        log_distance = torch.log(distance.clamp_min(self.MIN_DISTANCE)) - math.log(PRESS_L1)
        return torch.cat([(joints - self.home) / self.JOINT_SCALE, offsets / self.OFFSET_SCALE, log_distance], -1)


def make_encoder(config: SequenceConfig) -> nn.Module:
    """Encoder named by `config.obs_encoder`; it exposes its output width as `out_dim`."""
    if config.obs_encoder in CRAFT_ENCODERS:
        return CraftEncoder(full_view=config.obs_encoder == "craft_full_view")
    if config.obs_encoder == "dial_keys":
        return DialKeyEncoder()
    return IdentityEncoder(config.state_dim)
