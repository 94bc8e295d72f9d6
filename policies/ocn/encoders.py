"""Observation encoders: turn a frame's input vector (`SequencePolicy.observation`: the state features,
then each image's pixels) into the cell input x_t.

Craft datasets store a compact symbolic state (81 ints), which is expanded inside the policy: far
cheaper to record and load than the one-hot itself. `craft` gives OMPN's 1075-float observation (the
paper's); `craft_full_view` gives the exact egocentric map (4750 floats), in which the scripted
expert's action is a function of the observation (objects beyond OMPN's 5x5 window are placed only to
their 2x2 block there).

Dial's 39 floats go in standardised by the preprocessor (`identity`), as the paper's model reads them,
or raw (`dial_keys`), from which `DialKeyEncoder` adds each key's log L1 distance: the quantity the env
presses a key on.

Integer states of few values per element (BabyAI's 7 x 7 symbolic view: object, colour and door state
codes) are one-hot per element (`categorical`), as Craft's ids are, rather than read as magnitudes:
code 5 (key) is not "more" than code 4 (door). Images go through a small convolutional network
(`ConvEncoder`) sized for CPU training; with states beside them, the two encodings are concatenated
(`InputEncoder`).
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


class NoStateEncoder(nn.Module):
    """No state feature (images alone): an empty encoding."""

    out_dim = 0

    def forward(self, state: Tensor) -> Tensor:
        return state[..., :0].float()


class CategoricalEncoder(nn.Module):
    """Integer state [..., S] -> the one-hot of each element [..., sum(vocab)], element i over its
    `vocab[i]` values (0 .. vocab[i] - 1, from the dataset's stats). A value outside that range (never
    seen in training) leaves its element's block zero. Parameter-free, like `CraftEncoder`."""

    def __init__(self, vocab: list[int]) -> None:
        super().__init__()
        sizes = torch.tensor(vocab, dtype=torch.long)
        self.register_buffer("sizes", sizes, persistent=False)
        self.register_buffer("offsets", torch.cumsum(sizes, 0) - sizes, persistent=False)
        self.out_dim = int(sizes.sum())

    def forward(self, state: Tensor) -> Tensor:
        ids = state.round().long() if state.is_floating_point() else state.long()
        valid = (ids >= 0) & (ids < self.sizes)
        index = torch.minimum(ids.clamp_min(0), self.sizes - 1) + self.offsets
        out = torch.zeros(*ids.shape[:-1], self.out_dim, device=ids.device)
        return out.scatter_add_(-1, index, valid.float())


class ConvEncoder(nn.Module):
    """Image [N, C, S, S] (pixel values 0-255) -> [N, `out_dim`]: a 4 x 4 patch embedding of stride 4
    (16 channels; at 40 px a patch is one of Craft's tiles), a 3 x 3 convolution of stride 2 (32
    channels) and a linear layer, with ReLUs. Sized for CPU training: forward and backward over 2,600
    frames of 40 x 40 (a batch of 128 Craft episodes) take about a fifth of the time of three 3 x 3
    convolutions of stride 2 (16, 32, 32 channels) of about as many weights, whose first layer at
    20 x 20 dominates (the measurement, with and without the training shift, is in
    results/bench_images.md).

    In training each frame is shifted by up to `SHIFT` px each way (edges repeated), a random shift of
    its own. Why: without it the model learnt Craft's training episodes by heart from their pixels
    (action NLL 0.19 on training episodes, 1.80 on held-out ones; results/archive/
    craft_images_memorised_2026-12-07); a shift of half a tile leaves every object and the inventory
    border in view but no pixel where it was, as random shifts do for pixel-based RL (DrQ)."""

    SHIFT = 2

    def __init__(self, channels: int, size: int, out_dim: int = 128) -> None:
        super().__init__()
        patches = (size - 4) // 4 + 1
        cells = (patches + 1) // 2
        self.net = nn.Sequential(
            nn.Conv2d(channels, 16, 4, stride=4), nn.ReLU(), nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Flatten(), nn.Linear(32 * cells * cells, out_dim), nn.ReLU(),
        )
        self.out_dim = out_dim

    def forward(self, pixels: Tensor) -> Tensor:
        if self.training:
            pixels = random_shift(pixels, self.SHIFT)
        return self.net(pixels / 255.0)


def random_shift(pixels: Tensor, shift: int) -> Tensor:
    """Each image [N, C, H, W] moved by its own random offset in [-shift, shift] px along each axis, the
    edge pixels repeated into the space it leaves. The images that share an offset are copied as one
    slice: at Craft's batch (2,600 frames of 40 x 40) it took half the time of one gather over all."""
    _, _, height, width = pixels.shape
    padded = nn.functional.pad(pixels, (shift, shift, shift, shift), mode="replicate")
    span = 2 * shift + 1
    offsets = torch.randint(0, span * span, pixels.shape[:1], device=pixels.device)
    moved = torch.empty_like(pixels)
    for offset in range(span * span):
        rows, cols = divmod(offset, span)
        chosen = (offsets == offset).nonzero().squeeze(1)
        moved[chosen] = padded[chosen, :, rows : rows + height, cols : cols + width]
    return moved


class InputEncoder(nn.Module):
    """An input vector of states and images [..., W] -> the state encoding and each image's `ConvEncoder`
    encoding, side by side [..., out_dim]."""

    def __init__(self, state: nn.Module, state_dim: int, images: list[tuple[int, int]]) -> None:
        super().__init__()
        self.state, self.state_dim = state, state_dim
        self.shapes = [(channels, size, size) for channels, size in images]
        self.images = nn.ModuleList(ConvEncoder(channels, size) for channels, size in images)
        self.out_dim = state.out_dim + sum(image.out_dim for image in self.images)

    def forward(self, x: Tensor) -> Tensor:
        lead = x.shape[:-1]
        parts = [self.state(x[..., : self.state_dim])]
        start = self.state_dim
        for shape, image in zip(self.shapes, self.images, strict=True):
            width = math.prod(shape)
            pixels = x[..., start : start + width].reshape(-1, *shape)
            parts.append(image(pixels.float()).reshape(*lead, image.out_dim))
            start += width
        return torch.cat(parts, dim=-1)


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


def state_encoder(config: SequenceConfig) -> nn.Module:
    """Encoder of the state features named by `config.obs_encoder`; it exposes its output width as `out_dim`."""
    if config.obs_encoder in CRAFT_ENCODERS:
        return CraftEncoder(full_view=config.obs_encoder == "craft_full_view")
    if config.obs_encoder == "dial_keys":
        return DialKeyEncoder()
    if config.obs_encoder == "categorical":
        return CategoricalEncoder(config.state_vocab)
    if config.obs_encoder == "none":
        return NoStateEncoder()
    return IdentityEncoder(config.state_dim)


def make_encoder(config: SequenceConfig) -> nn.Module:
    """The encoder of the config's inputs: the state encoder alone where there is no image (Craft and Dial
    as they always were), else `InputEncoder`. It exposes its output width as `out_dim`."""
    state = state_encoder(config)
    if not config.image_keys:
        return state
    images = [(config.image_channels(key), config.image_size) for key in config.image_keys]
    return InputEncoder(state, config.state_dim, images)
