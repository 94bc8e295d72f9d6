"""`ocn-reproduce gather`: one finetuning study from `ocn-finetune` output folders run by hand.

`s1`, `s2` and `dial` clone their own skills. Runs over options cloned elsewhere (the Dial clones
of `tools.fast_imitation`, trained with the split given) are plain `ocn-finetune` calls, and their
folders hold what a study needs: `finetune.json` and `curve.csv`. This reads them, names each
run's method from what it finetuned (OCN, MoE, HIL, compILE, OMPN or flat PPO), and writes the
same table and curves as `s1` and `s2`: values at the budget are the mean of each run's last
`FINAL_ROWS` PPO iterations, then mean (std) over seeds. The runs must share their world, tasks,
env count and PPO settings; a method, reward and seed given twice is refused.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

from tools.reproduce import finetune
from tools.reproduce.combine import same_recipe
from tools.reproduce.finetune import FINAL_ROWS, at_budget, budget_table, read_curve, summarise
from tools.reproduce.report import origin_words, provenance, write_result_files

# What the runs of one study must share, as finetune.json spells it.
SHARED = ("world", "tasks", "envs", "ppo")
_HIERARCHY_METHODS = {"ocn": "OCN", "moe": "MoE", "hil": "HIL"}


def method_of(summary: dict[str, Any]) -> str:
    """The study's name of what one `ocn-finetune` run trained, from its finetune.json."""
    if summary["flat"]:
        return "flat PPO"
    if summary["policy_type"] == "ompn":
        return "OMPN"
    if summary["decoder_latents"]:
        return "compILE"
    return _HIERARCHY_METHODS[summary["hierarchy"]]


def read_run(folder: Path) -> dict[str, Any]:
    """One run folder as a study's run: its method, reward, seed, finetune.json, curve and values at the budget."""
    summary_path, curve_path = folder / "finetune.json", folder / "curve.csv"
    for path in (summary_path, curve_path):
        if not path.is_file():
            raise SystemExit(f"ocn-reproduce gather: {folder} has no {path.name}; is it a finished ocn-finetune --out?")
    with open(curve_path, newline="") as handle:
        header = next(csv.reader(handle))
    labels = [name[len("success["):-1] for name in header if name.startswith("success[")]
    summary = json.loads(summary_path.read_text())
    curve = read_curve(curve_path, labels)
    return {"method": method_of(summary), "reward": summary["reward"], "seed": summary["seed"],
            "folder": str(folder), "labels": labels, "summary": summary, "at_budget": at_budget(curve, labels),
            "curve": curve}


def gather(folders: list[Path]) -> dict[str, Any]:
    """The study of the runs in `folders` (without this invocation's provenance)."""
    runs = [read_run(folder) for folder in folders]
    shared = same_recipe({run["folder"]: run["summary"] for run in runs}, SHARED, "ocn-reproduce gather", "runs")
    seen: dict[tuple[str, str, int], str] = {}
    for run in runs:
        key = (run["method"], run["reward"], run["seed"])
        if key in seen:
            raise SystemExit(f"ocn-reproduce gather: {seen[key]} and {run['folder']} are both the {key[0]} run "
                             f"with {key[1]} reward and seed {key[2]}; pass one of them")
        seen[key] = run["folder"]
    methods = tuple(method for method in finetune.METHODS if any(run["method"] == method.name for run in runs))
    labels = runs[0]["labels"]
    return {"labels": labels, "shared": shared,
            "methods": [method.name for method in methods],
            "summary": summarise(runs, labels, methods), "runs": runs}


def markdown(result: dict[str, Any], name: str) -> str:
    """The study's Markdown file: where it came from, the values at the budget and every run."""
    shared = result["shared"]
    lines = [
        f"# Finetuning on {shared['world'].capitalize()}: {', '.join(result['labels'])}",
        "",
        f"{origin_words(result)} Every run is an `ocn-finetune` folder: {shared['envs']} envs per PPO "
        f"iteration, discount {shared['ppo']['gamma']:g}, entropy bonus {shared['ppo']['entropy_coef']:g}. Values "
        f"at the budget are the mean of each run's last {FINAL_ROWS} PPO iterations, then mean (std) over seeds.",
        "",
        "## At the budget",
        "",
        *budget_table(result["summary"], result["labels"]),
        "",
        "## Runs",
        "",
        "| method | reward | seed | env frames | success, last iteration | frames/s | options from | folder |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in result["runs"]:
        summary = run["summary"]
        sources = ", ".join(f"`{path}`" for path in summary["checkpoints"]) or "none"
        lines.append(f"| {run['method']} | {run['reward']} | {run['seed']} | {summary['frames']:,} | "
                     f"{summary['final_success']:.3f} | {summary['frames_per_s']:.0f} | {sources} | "
                     f"`{run['folder']}` |")
    lines += ["", f"Curves: `finetune_{name}.png` (each method's mean over seeds, the band from min to max).", ""]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    result = {**provenance(args), **gather([Path(folder) for folder in args.folders])}
    text = markdown(result, args.name)
    stem = write_result_files(args.results, f"finetune_{args.name}", result, text)
    methods = tuple(method for method in finetune.METHODS if method.name in result["methods"])
    title = f"ocn-finetune on {', '.join(result['labels'])}: mean and min-max over seeds"
    finetune.plot(result["summary"], methods, result["labels"], "min-max", title, stem.with_suffix(".png"))
    print(text)
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `gather` subcommand."""
    parser = sub.add_parser("gather", help="one finetuning study from ocn-finetune output folders run by hand",
                            description=__doc__.splitlines()[0],
                            formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("folders", nargs="+", help="ocn-finetune --out folders, finished")
    parser.add_argument("--name", required=True, help="the files are finetune_NAME.{json,md,png}")
    parser.add_argument("--results", type=Path, required=True, help="folder of the results files")
    parser.set_defaults(func=run)
