"""The one place that imports minigrid: everything lerobot_policy_ocn.envs.babyai uses from it, re-exported.

Where minigrid is missing, importing this module (and so any module built on it) raises
`MinigridMissing` with its install hint instead of a bare ModuleNotFoundError.
"""

from lerobot_policy_ocn.envs.babyai import MinigridMissing

try:
    from minigrid.core.actions import Actions
    from minigrid.core.constants import COLOR_NAMES, COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX
    from minigrid.envs.babyai.core.roomgrid_level import RoomGridLevel
    from minigrid.envs.babyai.core.verifier import ActionInstr, AndInstr, BeforeInstr, Instr
    from minigrid.envs.babyai.core.verifier import ObjDesc, OpenInstr, PickupInstr
    from minigrid.utils.baby_ai_bot import BabyAIBot
except ModuleNotFoundError as error:
    if error.name is None or error.name.partition(".")[0] != "minigrid":
        raise
    raise MinigridMissing() from None

__all__ = [
    "COLOR_NAMES",
    "COLOR_TO_IDX",
    "OBJECT_TO_IDX",
    "STATE_TO_IDX",
    "ActionInstr",
    "Actions",
    "AndInstr",
    "BabyAIBot",
    "BeforeInstr",
    "Instr",
    "ObjDesc",
    "OpenInstr",
    "PickupInstr",
    "RoomGridLevel",
]
