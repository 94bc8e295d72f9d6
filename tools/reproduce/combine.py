"""`ocn-reproduce combine`: one study from the results files of several invocations.

A study's methods need not run in one invocation: on two cores each clone takes most of an hour, and
a workdir does not outlive its machine, so OCN may have run in one session and the baselines in
another, and the seeds of one method may come from several sessions. This merges results files of one
kind and one recipe (finetuning: `finetune_{s1,s2}.json` of the same setting, budget, envs, recording
and cloning; parsing: `parsing_s1.json` of the same training and recording), each run (method, reward
and seed, or method and seed) taken from exactly one of them, into one results file whose rows are over
all the seeds found and whose checks compare every method with OCN, with the table and the curves of
all of them.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tools.reproduce import finetune, parsing
from tools.reproduce.finetune import SETTINGS, study_settings, task_labels
from tools.reproduce.report import provenance

# Settings that change what a finetuning run measures; the files combined must agree on each.
RECIPE = ("frames", "envs", "steps", "batch_size", "window_size", "controller_lr_scale", "episodes_per_task",
          "data_seed", "dart_noise", "window_start", "usage_balance", "settle_steps", "settle_termination_cost",
          "entropy", "gamma", "n_options", "switch_cost", "settle_usage_balance_options", "settle_usage_balance_exact",
          "settle_switch_cost", "expected_nll_weight")


def kind_of(result: dict[str, Any]) -> str | None:
    """The kind of a results file this command merges ("finetune" or "parsing"); None for any other."""
    if result.get("setting") in SETTINGS and "summary" in result:
        return "finetune"
    if result.get("settings", {}).get("experiment") == parsing.EXPERIMENT and "runs" in result:
        return "parsing"
    return None


def load_study(path: Path) -> dict[str, Any]:
    """A finetuning or parsing results file; anything else is refused by name."""
    if not path.is_file():
        raise SystemExit(f"ocn-reproduce combine: {path} is not a file")
    result = json.loads(path.read_text())
    if kind_of(result) is None:
        raise SystemExit(f"ocn-reproduce combine: {path} is not a results file of `ocn-reproduce s1`, `s2` or "
                         "`parsing-s1`")
    return result


def same_recipe(recipes: dict[Path, dict[str, Any]], keys: tuple[str, ...], command: str = "ocn-reproduce combine",
                sources: str = "files") -> dict[str, Any]:
    """The recipe the files (or run folders: `sources`) share, the first one's values of `keys`; sources
    that differ in any of them are refused by `command`, naming the setting and each source's value."""
    for key in keys:
        values = {path: recipe.get(key) for path, recipe in recipes.items()}
        if len({json.dumps(value, sort_keys=True) for value in values.values()}) > 1:
            raise SystemExit(f"{command}: the {sources} differ in {key}: {_listing(values)}")
    return {key: next(iter(recipes.values())).get(key) for key in keys}


def gather_runs(studies: dict[Path, dict[str, Any]], runs_of: Callable[[Path, dict[str, Any]], list[dict[str, Any]]],
                run_key: tuple[str, ...], method_order: list[str]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every file's runs in one list, and where each file came from (its command, date, machine and
    the methods it ran, in `method_order`). A run (the values of `run_key`) found in two files is
    refused."""
    found: dict[tuple[Any, ...], Path] = {}
    runs: list[dict[str, Any]] = []
    sources = []
    for path, study in studies.items():
        mine = runs_of(path, study)
        for run in mine:
            key = tuple(run[name] for name in run_key)
            if key in found:
                what = " and ".join(f"{name} {value}" for name, value in zip(run_key[1:], key[1:], strict=True))
                raise SystemExit(f"ocn-reproduce combine: the {key[0]} run with {what} is in both {found[key]} and "
                                 f"{path}; pass one of them")
            found[key] = path
        runs += mine
        ran = {run["method"] for run in mine}
        sources.append({"file": str(path), "command": study["command"], "date": study["date"],
                        "machine": study["machine"], "methods": [name for name in method_order if name in ran]})
    return runs, sources


def combine(studies: dict[Path, dict[str, Any]]) -> dict[str, Any]:
    """The merged finetuning study (without this invocation's provenance): every file's runs
    summarised together, so that seeds of one method from several files make one row, the checks made
    again over all rows, and where each file came from. Files of different settings or recipes, and
    a run (method, reward and seed) found in two files, are refused."""
    names = {path: study["setting"] for path, study in studies.items()}
    if len(set(names.values())) > 1:
        raise SystemExit(f"ocn-reproduce combine: the files are of different settings: {_listing(names)}")
    setting = SETTINGS[next(iter(names.values()))]
    labels = task_labels(setting)
    recipe = same_recipe({path: study_settings(study) for path, study in studies.items()}, RECIPE)
    runs, sources = gather_runs(studies, lambda path, study: study_runs(path, study, labels),
                                ("method", "reward", "seed"), [method.name for method in finetune.METHODS])
    summary = finetune.summarise(runs, labels)
    return {
        "setting": setting.name,
        "settings": recipe,
        "sources": sources,
        "runs_finished": sum(study["runs_finished"] for study in studies.values()),
        "runs_planned": sum(study["runs_planned"] for study in studies.values()),
        "summary": summary,
        "must_show": finetune.must_show(setting, summary),
        "runs": runs,
        "wall_s": round(sum(study["wall_s"] for study in studies.values()), 1),
    }


def combine_parsing(studies: dict[Path, dict[str, Any]]) -> dict[str, Any]:
    """The merged parsing study (without this invocation's provenance): every file's runs scored
    together, so that seeds of one method from several files make one curve, the checks and the
    baseline wins made again, and where each file came from. Files of different recipes or
    validation splits, and a run (method and seed) found in two files, are refused."""
    recipe = same_recipe({path: {**parsing.study_settings(study), "val_episodes": study["val_episodes"]}
                          for path, study in studies.items()}, (*parsing.RECIPE, "val_episodes"))
    runs, sources = gather_runs(studies, lambda _, study: study["runs"], ("method", "seed"),
                                [method.name for method in parsing.METHODS])
    merged = parsing.study(runs, sum(study["runs_planned"] for study in studies.values()), recipe.pop("val_episodes"),
                           sum(study["wall_s"] for study in studies.values()))
    return {"settings": recipe, "sources": sources, **merged}


# Per kind of results file: how its files merge, and how the merged study is written and shown.
KINDS = {
    "finetune": (combine, finetune.write_study_files, finetune.markdown),
    "parsing": (combine_parsing, parsing.write_study_files, parsing.markdown),
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
        keys = finetune.curve_keys(labels)
        curve = [{"frames": frames, **{name: row["curves"][name]["mean"][i] for name in keys}}
                 for i, frames in enumerate(row["curve_frames"])]
        runs.append({**made, "at_budget": {name: value["mean"] for name, value in row["at_budget"].items()},
                     "curve": curve})
    return runs


def _listing(values: dict[Path, Any]) -> str:
    return "; ".join(f"{path}: {value}" for path, value in values.items())


def run(args: argparse.Namespace) -> int:
    if len(set(args.files)) < 2:
        raise SystemExit("ocn-reproduce combine: give at least two different results files")
    studies = {path: load_study(path) for path in args.files}
    kinds = {path: kind_of(study) for path, study in studies.items()}
    if len(set(kinds.values())) > 1:
        raise SystemExit(f"ocn-reproduce combine: the files are of different kinds: {_listing(kinds)}")
    merge, write_study_files, markdown = KINDS[next(iter(kinds.values()))]
    result = {**provenance(args), **merge(studies)}  # the recipe's settings replace this invocation's arguments
    write_study_files(args.results, result)
    print(markdown(result))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `combine` subcommand."""
    parser = sub.add_parser("combine", help="one finetuning (s1, s2) or parsing (parsing-s1) study from the results "
                            "files of several invocations", description=__doc__.splitlines()[0],
                            formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path,
                        help="finetune_s1.json, finetune_s2.json or parsing_s1.json files, all of one kind")
    parser.add_argument("--results", type=Path, required=True, help="folder of the combined results files")
    parser.set_defaults(func=run)
