"""Ground truth for evaluation only: which subgoal of the mission each frame works on.

minigrid's verifier keeps no per-clause record, but each sequencing node does: `BeforeInstr` and
`AndInstr` hold `a_done` / `b_done`, the last status ("success", "continue", or False before it
was first checked) of their two children, and once "success" it stays so. A clause (an action
instruction) is completed when its parent's flag for it reads "success"; the root clause of a
one-subgoal mission when the episode succeeds. Reading these flags after every step gives the
step at which each clause completed.

Frames are then labelled in hindsight: frame t's `subtask.index` is the number of clauses
completed by the actions before it, and its `subtask.id` the subgoal of the clause completed next,
so the frame whose action completes a clause still belongs to that clause, as in Craft. Hindsight
matters only for "A and B, then C", where A and B may be done in either order: the bot does them
as written, but its labels follow whatever order the verifier saw.
"""

from __future__ import annotations

import numpy as np

from lerobot_policy_ocn.envs.babyai.minigrid_api import ActionInstr, AndInstr, BeforeInstr, Instr

SUCCESS = "success"


def clause_flags(instr: Instr, own: object) -> list[object]:
    """The status flag of each clause of an instruction tree, left to right; `own` is the tree's own
    status as its parent (or the episode, for the root) reports it."""
    if isinstance(instr, ActionInstr):
        return [own]
    if isinstance(instr, BeforeInstr | AndInstr):
        return clause_flags(instr.instr_a, instr.a_done) + clause_flags(instr.instr_b, instr.b_done)
    raise TypeError(f"{type(instr).__name__} is not an instruction this level builds")


class SubgoalTracker:
    """Follows one episode's clauses step by step; `subgoals` are their ids, left to right."""

    def __init__(self, instrs: Instr, subgoals: tuple[int, ...]) -> None:
        self.instrs = instrs
        self.subgoals = subgoals
        self.completed_at: list[int | None] = [None] * len(subgoals)
        self.steps = 0

    def update(self, success: bool) -> int:
        """Record the step just taken (`success`: the episode's mission is done); returns how many
        clauses it completed."""
        flags = clause_flags(self.instrs, SUCCESS if success else None)
        if len(flags) != len(self.subgoals):
            raise ValueError(f"the instruction has {len(flags)} clauses, the mission {len(self.subgoals)}")
        newly = 0
        for k, flag in enumerate(flags):
            if flag == SUCCESS and self.completed_at[k] is None:
                self.completed_at[k] = self.steps
                newly += 1
        self.steps += 1
        return newly

    @property
    def progress(self) -> int:
        """Clauses completed so far."""
        return sum(step is not None for step in self.completed_at)

    def labels(self) -> tuple[np.ndarray, np.ndarray]:
        """Per frame of a finished, successful episode: `subtask.index` and `subtask.id` (int64 [T]).

        Two clauses completed by one action would leave a segment of no frames; that (and an
        unfinished episode) is a ValueError rather than a label that skips a subgoal.
        """
        if self.progress < len(self.subgoals):
            raise ValueError(f"only {self.progress} of {len(self.subgoals)} subgoals were completed")
        ends = np.array(self.completed_at, dtype=np.int64)
        order = np.argsort(ends, kind="stable")
        ends = ends[order]
        if np.any(np.diff(ends) == 0):
            raise ValueError(f"two subgoals were completed by the same step (steps {ends.tolist()})")
        index = np.searchsorted(ends, np.arange(self.steps), side="left")
        return index, np.asarray(self.subgoals, dtype=np.int64)[order][index]
