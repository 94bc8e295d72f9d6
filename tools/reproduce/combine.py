"""`ocn-reproduce combine`: one finetuning study from the results files of several invocations.

A study's methods need not run in one invocation: on two cores each clone takes most of an hour, and
a workdir does not outlive its machine, so OCN may have run in one session and the baselines in
another. This merges `finetune_{s1,s2}.json` files of the same setting and the same recipe (budget,
envs, recording, cloning), each method and reward taken from exactly one of them, into one results
file whose checks compare every method with OCN, with the table and the curves of all of them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from tools.reproduce.finetune import METHODS, REWARDS, SETTINGS, must_show, write_study_files
from tools.reproduce.report import provenance

# Settings that change what a run measures; the files combined must agree on each of them.
RECIPE = ("frames", "envs", "steps", "batch_size", "window_size", "controller_lr_scale", "episodes_per_task",
          "data_seed", "dart_noise", "window_start", "usage_balance", "settle_steps", "settle_termination_cost")


def load_study(path: Path) -> dict[str, Any]:
    """A finetuning results file; anything else is refused by name."""
    if not path.is_file():
        raise SystemExit(f"ocn-reproduce combine: {path} is not a file")
    result = json.loads(path.read_text())
    if result.get("setting") not in SETTINGS or "summary" not in result:
        raise SystemExit(f"ocn-reproduce combine: {path} is not a results file of `ocn-reproduce s1` or `s2`")
    return result


def combine(studies: dict[Path, dict[str, Any]]) -> dict[str, Any]:
    """The merged study (without this invocation's provenance): the rows of every file in METHODS and
    REWARDS order, the checks made again over all of them, and where each file came from. Files of
    different settings or recipes, and a method and reward found in two files, are refused."""
    settings = {path: study["setting"] for path, study in studies.items()}
    if len(set(settings.values())) > 1:
        raise SystemExit(f"ocn-reproduce combine: the files are of different settings: {_listing(settings)}")
    for key in RECIPE:
        values = {path: study["settings"].get(key) for path, study in studies.items()}
        if len({json.dumps(value) for value in values.values()}) > 1:
            raise SystemExit(f"ocn-reproduce combine: the files differ in {key}: {_listing(values)}")
    rows: dict[str, tuple[Path, dict[str, Any]]] = {}
    for path, study in studies.items():
        for key, row in study["summary"].items():
            if key in rows:
                raise SystemExit(f"ocn-reproduce combine: {key} is in both {rows[key][0]} and {path}; "
                                 "pass one of them")
            rows[key] = (path, row)
    order = [f"{method.name} | {reward}" for method in METHODS for reward in REWARDS]
    summary = {key: rows[key][1] for key in order if key in rows}
    setting = SETTINGS[next(iter(settings.values()))]
    first = next(iter(studies.values()))
    return {
        "setting": setting.name,
        "settings": {key: first["settings"].get(key) for key in RECIPE},
        "sources": [{"file": str(path), "command": study["command"], "date": study["date"],
                     "machine": study["machine"], "methods": _methods(study)}
                    for path, study in studies.items()],
        "runs_finished": sum(study["runs_finished"] for study in studies.values()),
        "runs_planned": sum(study["runs_planned"] for study in studies.values()),
        "summary": summary,
        "must_show": must_show(setting, summary),
        "runs": [run for study in studies.values() for run in study["runs"]],
        "wall_s": round(sum(study["wall_s"] for study in studies.values()), 1),
    }


def _methods(study: dict[str, Any]) -> list[str]:
    """The methods a study has rows of, in METHODS order."""
    ran = {row["method"] for row in study["summary"].values()}
    return [method.name for method in METHODS if method.name in ran]


def _listing(values: dict[Path, Any]) -> str:
    return "; ".join(f"{path}: {value}" for path, value in values.items())


def run(args: argparse.Namespace) -> int:
    if len(set(args.files)) < 2:
        raise SystemExit("ocn-reproduce combine: give at least two different results files")
    merged = combine({path: load_study(path) for path in args.files})
    result = {**provenance(args), **merged}  # the recipe's settings replace this invocation's arguments
    write_study_files(args.results, SETTINGS[merged["setting"]], result)
    print((args.results / f"finetune_{merged['setting']}.md").read_text())
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `combine` subcommand."""
    parser = sub.add_parser("combine", help="one finetuning study (s1 or s2) from the results files of several "
                            "invocations", description=__doc__.splitlines()[0],
                            formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="finetune_s1.json or finetune_s2.json files")
    parser.add_argument("--results", type=Path, required=True, help="folder of the combined results files")
    parser.set_defaults(func=run)
