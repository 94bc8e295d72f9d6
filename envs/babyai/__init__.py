"""BabyAI (MiniGrid) as an OCN world: the level `OpenPickupSeq`, its observation adapter, ground-truth
subgoals and free runs. See envs/babyai/README.md.

MiniGrid is an optional dependency (the `babyai` extra), so importing this package never imports it:
the gymnasium id is registered (with a string entry point) only where minigrid is installed, and
the modules that need it fail with `MinigridMissing`, whose one-line message says how to install it.
"""

from importlib.util import find_spec

from gymnasium.envs.registration import register, registry

BABYAI_ENV_ID = "OCN/BabyAI-OpenPickupSeq-v0"
INSTALL_HINT = "BabyAI needs the optional minigrid package: pip install '.[babyai]' (or uv sync --extra babyai)"


class MinigridMissing(ImportError):
    """minigrid is not installed; the message is the one line to show a user."""

    def __init__(self) -> None:
        super().__init__(INSTALL_HINT, name="minigrid")


def minigrid_installed() -> bool:
    """Whether minigrid can be imported, found without importing it."""
    return find_spec("minigrid") is not None


if minigrid_installed() and BABYAI_ENV_ID not in registry:
    register(id=BABYAI_ENV_ID, entry_point="lerobot_policy_ocn.envs.babyai.env:BabyAIEnv")
