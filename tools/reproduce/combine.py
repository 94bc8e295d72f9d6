"""`ocn-reproduce combine`: one finetuning study from the results files of several invocations.

A study's methods need not run in one invocation: on two cores each clone takes most of an hour, and
a workdir does not outlive its machine, so OCN may have run in one session and the baselines in
another, and the seeds of one method may come from several sessions. This merges `finetune_{s1,s2}.json`
files of the same setting and the same recipe (budget, envs, recording, cloning), each run (method,
reward, seed) taken from exactly one of them, into one results file whose rows are over all the seeds
found and whose checks compare every method with OCN, with the table and the curves of all of them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from tools.reproduce.finetune import (METHODS, SETTINGS, curve_keys, markdown, must_show, study_settings, summarise,
                                      task_labels, write_study_files)
from tools.reproduce.report import provenance

# Settings that change what a run measures; the files combined must agree on each of them.
RECIPE = ("frames", "envs", "steps", "batch_size", "window_size", "controller_lr_scale", "episodes_per_task",
          "data_seed", "dart_noise", "window_start", "usage_balance", "settle_steps", "settle_termination_cost", "entropy")


def load_study(path: Path) -> dict[str, Any]:
    """A finetuning results file; anything else is refused by name."""
    if not path.is_file():
        raise SystemExit(f"ocn-reproduce combine: {path} is not a file")
    result = json.loads(path.read_text())
    if result.get("setting") not in SETTINGS or "summary" not in result:
        raise SystemExit(f"ocn-reproduce combine: {path} is not a results file of `ocn-reproduce s1` or `s2`")
    return result


def combine(studies: dict[Path, dict[str, Any]]) -> dict[str, Any]:
    """The merged study (without this invocation's provenance): every file's runs summarised together,
    so that seeds of one method from several files make one row, the checks made again over all rows,
    and where each file came from. Files of different settings or recipes, and a run (method, reward
    and seed) found in two files, are refused."""
    names = {path: study["setting"] for path, study in studies.items()}
    if len(set(names.values())) > 1:
        raise SystemExit(f"ocn-reproduce combine: the files are of different settings: {_listing(names)}")
    setting = SETTINGS[next(iter(names.values()))]
    recipes = {path: study_settings(study) for path, study in studies.items()}
    for key in RECIPE:
        values = {path: recipe.get(key) for path, recipe in recipes.items()}
        if len({json.dumps(value) for value in values.values()}) > 1:
            raise SystemExit(f"ocn-reproduce combine: the files differ in {key}: {_listing(values)}")
    found: dict[tuple[str, str, int], Path] = {}
    runs: list[dict[str, Any]] = []
    sources = []
    for path, study in studies.items():
        mine = study_runs(path, study, task_labels(setting))
        for run in mine:
            key = (run["method"], run["reward"], run["seed"])
            if key in found:
                raise SystemExit(f"ocn-reproduce combine: the {key[0]} run with {key[1]} reward and seed {key[2]} "
                                 f"is in both {found[key]} and {path}; pass one of them")
            found[key] = path
        runs += mine
        sources.append({"file": str(path), "command": study["command"], "date": study["date"],
                        "machine": study["machine"], "methods": ran_methods(mine)})
    summary = summarise(runs, task_labels(setting))
    return {
        "setting": setting.name,
        "settings": {key: recipes[next(iter(studies))].get(key) for key in RECIPE},
        "sources": sources,
        "runs_finished": sum(study["runs_finished"] for study in studies.values()),
        "runs_planned": sum(study["runs_planned"] for study in studies.values()),
        "summary": summary,
        "must_show": must_show(setting, summary),
        "runs": runs,
        "wall_s": round(sum(study["wall_s"] for study in studies.values()), 1),
    }


def study_runs(path: Path, study: dict[str, Any], labels: list[str]) -> list[dict[str, Any]]:
    """A results file's runs, each with its curve and its values at the budget. Files written before
    runs kept their curves have them only as rows over seeds; a row of one seed is that seed's run
    (its curve on the row's grid of env frames), a row of several seeds cannot be split and is refused."""
    if all("curve" in run for run in study["runs"]):
        return study["runs"]
    runs = []
    for key, row in study["summary"].items():
        if len(row["seeds"]) != 1:
            raise SystemExit(f"ocn-reproduce combine: {path} keeps no curve per run (it was written before results "
                             f"files did), and its row {key} is over seeds {row['seeds']}, so its runs cannot be "
                             "told apart; combine files whose rows have one seed each")
        made = next(run for run in study["runs"] if (run["method"], run["reward"]) == (row["method"], row["reward"]))
        curve = [{"frames": frames, **{name: row["curves"][name]["mean"][i] for name in curve_keys(labels)}}
                 for i, frames in enumerate(row["curve_frames"])]
        runs.append({**made, "at_budget": {name: value["mean"] for name, value in row["at_budget"].items()},
                     "curve": curve})
    return runs


def ran_methods(runs: list[dict[str, Any]]) -> list[str]:
    """The methods that have runs, in METHODS order."""
    return [method.name for method in METHODS if any(run["method"] == method.name for run in runs)]


def _listing(values: dict[Path, Any]) -> str:
    return "; ".join(f"{path}: {value}" for path, value in values.items())


def run(args: argparse.Namespace) -> int:
    if len(set(args.files)) < 2:
        raise SystemExit("ocn-reproduce combine: give at least two different results files")
    merged = combine({path: load_study(path) for path in args.files})
    result = {**provenance(args), **merged}  # the recipe's settings replace this invocation's arguments
    write_study_files(args.results, SETTINGS[merged["setting"]], result)
    print(markdown(result))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `combine` subcommand."""
    parser = sub.add_parser("combine", help="one finetuning study (s1 or s2) from the results files of several "
                            "invocations", description=__doc__.splitlines()[0],
                            formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="finetune_s1.json or finetune_s2.json files")
    parser.add_argument("--results", type=Path, required=True, help="folder of the combined results files")
    parser.set_defaults(func=run)
