"""The integer state vector that `observation.state` holds for BabyAI (no minigrid needed).

minigrid's observation `image` is the agent's 7 x 7 egocentric view, `image[x, y]` = (object
type, colour, door state) of the cell x columns from the left and y rows from the far end (the
agent stands at x = 3, y = 6, facing up the view; its cell shows what it carries). The state is
that array flattened in C order, then the agent's absolute direction (0 right, 1 down, 2 left,
3 up): `state[21 * x + 3 * y + c]` is channel c of cell (x, y), `state[147]` the direction.
Values are minigrid's indices (`OBJECT_TO_IDX`, `COLOR_TO_IDX`, `STATE_TO_IDX`), kept as small
integers so that a policy can embed or one-hot them itself (a stored one-hot would be 10 times
wider and far slower to record and load).
"""

from __future__ import annotations

from typing import Any

import numpy as np

VIEW_SIZE = 7
CHANNELS = ("object", "color", "state")
STATE_DIM = VIEW_SIZE * VIEW_SIZE * len(CHANNELS) + 1
DIRECTION = STATE_DIM - 1
STATE_NAMES = tuple(
    f"view_x{x}_y{y}_{channel}" for x in range(VIEW_SIZE) for y in range(VIEW_SIZE) for channel in CHANNELS
) + ("direction",)


def encode(obs: dict[str, Any]) -> np.ndarray:
    """A minigrid observation dict as the int64 state vector of length `STATE_DIM`."""
    image = np.asarray(obs["image"], dtype=np.int64)
    if image.shape != (VIEW_SIZE, VIEW_SIZE, len(CHANNELS)):
        raise ValueError(f"expected a {VIEW_SIZE}x{VIEW_SIZE}x3 view, got an image of shape {image.shape}")
    return np.concatenate([image.reshape(-1), [int(obs["direction"])]])
