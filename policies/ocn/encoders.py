"""Observation encoders: turn the stored `observation.state` into the cell input x_t.

Craft datasets store a compact symbolic state (81 ints), which is expanded inside the policy: far
cheaper to record and load than the one-hot itself. `craft` gives OMPN's 1075-float observation (the
paper's); `craft_full_view` gives the exact egocentric map (4750 floats), in which the scripted
expert's action is a function of the observation (objects beyond OMPN's 5x5 window are placed only to
their 2x2 block there).
"""

from torch import Tensor, nn

from envs.craft.observation import FULL_VIEW_DIM, OMPN_DIM, full_view_features, ompn_features

from policies.sequence import CRAFT_ENCODERS, SequenceConfig


class CraftEncoder(nn.Module):
    """Compact Craft state [..., 81] -> OMPN features [..., 1075] via `envs.craft.observation`;
    `full_view`: the exact egocentric view [..., 4750] instead."""

    def __init__(self, full_view: bool = False) -> None:
        super().__init__()
        self.features = full_view_features if full_view else ompn_features
        self.out_dim = FULL_VIEW_DIM if full_view else OMPN_DIM

    def forward(self, state: Tensor) -> Tensor:
        ids = state.round().long() if state.is_floating_point() else state.long()
        return self.features(ids)


class IdentityEncoder(nn.Module):
    """Float state used as is (e.g. Dial's 39 floats, already normalised by the preprocessor)."""

    def __init__(self, state_dim: int) -> None:
        super().__init__()
        self.out_dim = state_dim

    def forward(self, state: Tensor) -> Tensor:
        return state.float()


def make_encoder(config: SequenceConfig) -> nn.Module:
    """Encoder named by `config.obs_encoder`; it exposes its output width as `out_dim`."""
    if config.obs_encoder in CRAFT_ENCODERS:
        return CraftEncoder(full_view=config.obs_encoder == "craft_full_view")
    return IdentityEncoder(config.state_dim)
