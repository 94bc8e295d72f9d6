"""The BabyAI level `OpenPickupSeq`, built from minigrid's own level classes (`RoomGridLevel`) and
instruction objects (`OpenInstr`, `PickupInstr`, `BeforeInstr`, `AndInstr`).

The agent starts in the middle room of minigrid's 3 x 3 room grid (rooms of 7 x 7 cells with
their walls, a 5 x 5 floor). Three of that room's four walls hold a closed, unlocked door, one
each of red, green and blue (walls and colours drawn per episode); the other rooms stay empty and
only make the doors real doors. The room holds the yellow ball, the purple box and the grey key
(the objects a mission may ask for) and two distractors of other colour-type pairs, so that
"the yellow ball" is always one object and the agent must read colour and type together. Every
object and door can be reached without moving another object, so the bot never has to clear a
blocker (which would pick up objects the mission does not name).

The mission is one of `missions.MISSIONS`, drawn uniformly from the episode's seed, or the one a
reset names (`options={"mission": text}`). The step limit is `STEPS_PER_SUBGOAL` per subgoal.
"""

from __future__ import annotations

from typing import Any

from lerobot_policy_ocn.envs.babyai.minigrid_api import (
    COLOR_NAMES,
    AndInstr,
    BeforeInstr,
    Instr,
    ObjDesc,
    OpenInstr,
    PickupInstr,
    RoomGridLevel,
)
from lerobot_policy_ocn.envs.babyai.missions import (
    AND_THEN, DOOR_COLORS, MISSIONS, PICKUP_OBJECTS, SINGLE, Mission, parse_mission,
)

ROOM_SIZE = 7
CENTER = (1, 1)
N_DISTRACTORS = 2
OBJECT_TYPES = ("ball", "box", "key")
STEPS_PER_SUBGOAL = 64


def subgoal_instr(subgoal: int) -> Instr:
    """The minigrid action clause of one subgoal id (see `missions.SUBGOALS`)."""
    if subgoal < len(DOOR_COLORS):
        return OpenInstr(ObjDesc("door", DOOR_COLORS[subgoal]))
    color, kind = PICKUP_OBJECTS[subgoal - len(DOOR_COLORS)]
    return PickupInstr(ObjDesc(kind, color))


def mission_instr(mission: Mission) -> Instr:
    """The minigrid instruction tree of a mission; its clauses, read left to right, are the
    mission's subgoals in order."""
    clauses = [subgoal_instr(s) for s in mission.subgoals]
    if mission.form == SINGLE:
        return clauses[0]
    if mission.form == AND_THEN:
        return BeforeInstr(AndInstr(clauses[0], clauses[1]), clauses[2])
    return BeforeInstr(clauses[0], clauses[1])


class OpenPickupSeqLevel(RoomGridLevel):
    """One room, three doors, three named objects and two distractors; missions of 2-3 subgoals."""

    def __init__(self, **kwargs: Any) -> None:
        self.requested: Mission | None = None
        self.spec: Mission = MISSIONS[0]
        # A fixed max_steps keeps RoomGridLevel from deriving its own (hundreds of steps a
        # subgoal); reset sets the per-mission limit.
        super().__init__(room_size=ROOM_SIZE, num_rows=3, num_cols=3, max_steps=STEPS_PER_SUBGOAL, **kwargs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        """A new episode; `options={"mission": text}` asks for that mission instead of a random one."""
        text = (options or {}).get("mission")
        self.requested = None if text is None else parse_mission(text)
        obs, info = super().reset(seed=seed)
        self.max_steps = STEPS_PER_SUBGOAL * len(self.spec.subgoals)
        return obs, info

    def gen_mission(self) -> None:
        self.spec = self.requested or self._rand_elem(MISSIONS)
        walls = self._rand_subset(range(4), len(DOOR_COLORS))
        for wall, color in zip(walls, DOOR_COLORS, strict=True):
            self.add_door(*CENTER, door_idx=wall, color=color, locked=False)
        others = [(c, t) for c in COLOR_NAMES for t in OBJECT_TYPES if (c, t) not in PICKUP_OBJECTS]
        while True:
            objects = [*PICKUP_OBJECTS, *self._rand_subset(others, N_DISTRACTORS)]
            placed = [self.add_object(*CENTER, kind, color)[0] for color, kind in objects]
            self.place_agent(*CENTER)
            if self.check_objs_reachable(raise_exc=False):
                break
            for obj in placed:
                self.grid.set(*obj.cur_pos, None)
            self.get_room(*CENTER).objs.clear()
        self.instrs = mission_instr(self.spec)
