"""The recordings and behaviour-cloned models the studies share, and where each lives in the workdir.

A recording is `data/NAME` (`record_demos` with its tasks and the study's episodes per task, at the
recorder's defaults: Craft with DART noise 0.1, the data the recipe was measured on). A clone is
`train/NAME/MODEL/seedN`, MODEL named after the policy type and its flags (`ocn`, `ocn_n_options-2`,
`ocn_hierarchy-moe`, `compile`), so that two studies asking for the same model on the same data
with the same seed and size find one run: `imitation-s1`'s main variant is `s1`'s OCN clone.

The size of a study (episodes per task, steps, batch) is on its command line; the defaults are the
issue's budget for Craft: 2,000 demonstrations per task, 6,000 steps of 128 episodes. A workdir
holds one size: a run of another size in the same folder is refused (`runs.Job`). A clone's scores
(`ocn-eval` on the validation split) live in its folder too, `.../eval`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.reproduce.runs import Evaluation, Recording, Training, train_command

# What a clone's row keeps of `ocn-eval`'s JSON, beside the option table and its reading.
EVAL_KEYS = ("f1_tol0", "f1_tol1", "align_acc", "nmi", "mean_success_rate", "success_rate")


@dataclass(frozen=True)
class Demos:
    """A recording: its name in the workdir and `record_demos`' arguments that say what it holds."""

    name: str
    arguments: tuple[str, ...]

    @property
    def repo_id(self) -> str:
        return f"local/{self.name}"


@dataclass(frozen=True)
class Model:
    """How a clone is trained: its policy type and `--policy.*` flags (model size and baselines only,
    `runs.POLICY_FLAGS`), and its name in the results."""

    name: str
    policy_type: str = "ocn"
    flags: dict[str, Any] = field(default_factory=dict)

    @property
    def folder(self) -> str:
        return "_".join([self.policy_type, *(f"{key}-{value}" for key, value in self.flags.items())])

    def with_flags(self, **flags: Any) -> Model:
        """The same model with more flags (S2's two options per clone); compILE and OMPN have no options
        to size, so they keep their own defaults."""
        return Model(self.name, self.policy_type, {**self.flags, **flags} if self.policy_type == "ocn" else self.flags)


@dataclass(frozen=True)
class Size:
    """How big a study's recordings and trainings are."""

    episodes_per_task: int
    steps: int
    batch_size: int


def record(workdir: Path, demos: Demos, size: Size) -> Recording:
    """The recording of `demos` in the workdir, made unless it is there."""
    arguments = [*demos.arguments, "--episodes-per-task", str(size.episodes_per_task), "--repo-id", demos.repo_id]
    return Recording(workdir, f"data/{demos.name}", arguments).run()


def clone(workdir: Path, demos: Demos, data: Recording, model: Model, seed: int, size: Size) -> Training:
    """The model trained on `demos` with `seed`, trained unless it is there (or resumed)."""
    folder = f"train/{demos.name}/{model.folder}/seed{seed}"
    command = train_command(model.policy_type, data.root, demos.repo_id, folder, size.steps, size.batch_size, seed,
                            model.flags)
    return Training(workdir, folder, command).run()


def scored(workdir: Path, demos: Demos, data: Recording, trained: Training, rollouts: int) -> dict[str, Any]:
    """A clone's row in a study's results: its commands, training wall seconds and `ocn-eval`'s scores on
    its recording's validation split (scored unless done), with the option x subtask table read
    (`option_table_summary`: each subtask's best option, the diagonal, the off-diagonal)."""
    from lerobot_policy_ocn.tools.eval.metrics import option_table_summary

    job = Evaluation(workdir, f"{trained.folder}/eval", trained.checkpoint, data.root, demos.repo_id, rollouts).run()
    scores = job.scores()
    table = scores["option_subtask_success"]
    return {"train_command": trained.shown, "train_wall_s": trained.wall_s, "eval_command": job.shown,
            "scores": {**{key: scores[key] for key in EVAL_KEYS}, "option_table": table,
                       **option_table_summary(table["table"])}}


def add_size_arguments(parser: argparse.ArgumentParser, size: Size) -> None:
    """The options every study has: its size, seeds (1, 2, 3 by default) and folders."""
    parser.add_argument("--seeds", type=seed_list, default="1,2,3", help="comma-separated seeds")
    parser.add_argument("--episodes-per-task", type=int, default=size.episodes_per_task,
                        help="demonstrations recorded per task (80/20 train/val split)")
    parser.add_argument("--steps", type=int, default=size.steps, help="lerobot-train steps per clone")
    parser.add_argument("--batch-size", type=int, default=size.batch_size, help="episodes per lerobot-train step")
    parser.add_argument("--workdir", type=Path, default=Path("outputs/reproduce"),
                        help="where recordings and runs live; finished ones there are reused")


def size_of(args: argparse.Namespace) -> Size:
    return Size(args.episodes_per_task, args.steps, args.batch_size)


def seed_list(text: str) -> list[int]:
    """`1,2,3` as [1, 2, 3]."""
    return [int(seed) for seed in text.split(",") if seed]
