"""Observation encoders: turn the stored `observation.state` into the cell input x_t.

Craft datasets store a compact symbolic state (81 ints), which is expanded to OMPN's 1075-float
one-hot observation inside the policy: far cheaper to record and load than the one-hot itself.
"""

from torch import Tensor, nn

from envs.craft.observation import OMPN_DIM, ompn_features

from policies.sequence import SequenceConfig


class CraftEncoder(nn.Module):
    """Compact Craft state [..., 81] -> OMPN features [..., 1075] via `envs.craft.observation`."""

    out_dim = OMPN_DIM

    def forward(self, state: Tensor) -> Tensor:
        ids = state.round().long() if state.is_floating_point() else state.long()
        return ompn_features(ids)


class IdentityEncoder(nn.Module):
    """Float state used as is (e.g. Dial's 39 floats, already normalised by the preprocessor)."""

    def __init__(self, state_dim: int) -> None:
        super().__init__()
        self.out_dim = state_dim

    def forward(self, state: Tensor) -> Tensor:
        return state.float()


def make_encoder(config: SequenceConfig) -> nn.Module:
    """Encoder named by `config.obs_encoder`; it exposes its output width as `out_dim`."""
    if config.obs_encoder == "craft":
        return CraftEncoder()
    return IdentityEncoder(config.state_dim)
