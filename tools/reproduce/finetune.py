"""`ocn-reproduce s1` and `ocn-reproduce s2`: reusing cloned skills with PPO (paper section 4.1, figures 4-5).

S1: each method is cloned from the S1 demonstrations ({AC, CD, DA}); its skills are frozen and a
fresh controller learns the new tasks ADC, CAD and DCA by PPO. S2: one model is cloned from {AB, BA}
and one from {CD, DC}, their skills are pooled, and the controller learns BADC, ACBD and CABD.
The methods: OCN; MoE and HIL (`--policy.hierarchy=moe|hil`: OCN's network and recipe, with the
terms only OCN's terminations use left out); compILE, whose skills are its frozen decoder given each
latent; OMPN, which has no skills to freeze, so its RL form finetunes the whole network (S1 only,
as in the paper: it has nothing to pool); and flat PPO (`ocn-finetune --flat`), which learns from
scratch on primitive actions. Every clone is a plain `lerobot-train` run (`clones.py`: S1's OCN
clone is `imitation-s1`'s main run), S2's OCN-family clones with `--policy.n_options=2` (two
subtasks per recording). Every PPO run is a plain `ocn-finetune` of the same env-frame budget and
envs, under each reward (sparse, dense) and each seed (the clone's seed is the PPO seed).

Defaults, chosen for the 2-core VM:
- S1: 500,000 env frames, 64 envs. At 300k frames OCN's sparse success was on the 0.9 bar's edge
  (0.955 / 0.937 / 0.857, results/archive/finetune_s1_dart_300k) and at 1.5M well above it (0.985 / 1.000 /
  0.984, results/archive/finetune_s1_dart), its curve passing 0.9 near 150k. More frames cost little for
  the others, but OMPN's RL form runs at about 130 frames/s: 64 minutes per run at 500k.
- S2: 3,000,000 env frames, 256 envs: the setting under which OCN's sparse success held 0.8 on
  every task on three seeds (results/archive/finetune_s2_envs256; 64 envs fell short at 1.5M and 3M).
- Seeds 1, 2, 3.

What that costs on the 2-core VM (every command single-threaded, so two invocations side by side,
joined by `ocn-reproduce combine`, take half the wall time): a clone 20-25 min (6,000 steps at about
0.21 s of CPU, `runs.WORKERS`), OMPN's about 33; PPO at the frames/s of results/archive/finetune_s1_dart_300k
(64 envs) and results/archive/finetune_s2_envs256 (256 envs). S1, per seed: four clones (OCN's is
imitation-s1's) about 2 h, twelve PPO runs about 3 h, two of them OMPN's (2 h 10 min); about 14
CPU-hours for three seeds, 8 without OMPN. S2, per seed: eight clones about 3 h, ten PPO runs about
3 h 10 min; about 18 CPU-hours for three seeds.

The checks: OCN's sparse success >= 0.9 (S1) or 0.8 (S2) on each task, mean over seeds at the
budget; each baseline's sparse success below OCN's; and on S1, sample efficiency under the dense
reward (`curves.sample_efficiency`): OCN's env frames to 90% of its final return against the best
baseline's frames to that return, <= 0.5x. Writes `results/finetune_{s1,s2}.{json,md,png}`.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import RESULTS
from lerobot_policy_ocn.tools.reproduce import curves
from lerobot_policy_ocn.tools.reproduce.clones import (
    Demos, Model, Size, add_size_arguments, clone, record, seed_list, size_of,
)
from lerobot_policy_ocn.tools.reproduce.imitation import S1, SIZE
from lerobot_policy_ocn.tools.reproduce.report import (
    check, checks_table, mean_std, origin_words, provenance, write_results,
)
from lerobot_policy_ocn.tools.reproduce.runs import Finetuning

REWARDS = ("sparse", "dense")
# The methods by their key on the command line: the clone each finetunes (None: flat PPO, no clone).
CLONED = {"ocn": Model("OCN"), "moe": Model("MoE", flags={"hierarchy": "moe"}),
          "hil": Model("HIL", flags={"hierarchy": "hil"}), "compile": Model("compILE", "compile"),
          "ompn": Model("OMPN", "ompn"), "flat": None}
NAMES = {**{key: model.name for key, model in CLONED.items() if model is not None}, "flat": "flat PPO"}
# For `ocn-reproduce combine` (as `imitation.STUDIES`).
ROWS = {"runs": ("method", "reward", "seed")}
VARYING = ("seeds", "baseline_seeds", "methods", "rewards", "workdir", "results")


@dataclass(frozen=True)
class Setting:
    """A finetuning experiment: the recordings its clones come from, their model-size flags, the new tasks,
    the methods it compares, its PPO defaults and the bar OCN's sparse success must clear."""

    name: str
    demos: tuple[Demos, ...]
    tasks: str
    methods: tuple[str, ...]
    frames: int
    envs: int
    success_bar: float
    clone_flags: dict[str, Any] = field(default_factory=dict)
    ppo: tuple[str, ...] = ()  # further `ocn-finetune` arguments, PPO's own settings (Dial's discount)

    @property
    def labels(self) -> list[str]:
        return self.tasks.split(",")


SETTINGS = {
    "s1": Setting("s1", (S1,), "ADC,CAD,DCA", tuple(CLONED), 500_000, 64, 0.9),
    "s2": Setting("s2", (Demos("craft_s2_ab", ("--tasks", "AB,BA")), Demos("craft_s2_cd", ("--tasks", "CD,DC"))),
                  "BADC,ACBD,CABD", ("ocn", "moe", "hil", "compile", "flat"), 3_000_000, 256, 0.8, {"n_options": 2}),
}
STUDIES = tuple(f"finetune_{name}" for name in SETTINGS)


def finetune_run(args: argparse.Namespace, setting: Setting, method: str, reward: str, seed: int) -> dict[str, Any]:
    """Clone the method on each of the setting's recordings (unless done), finetune over the clones
    (unless done) and return the run's row: its commands, wall times and learning curve."""
    model, clones = CLONED[method], []
    if model is not None:
        for demos in setting.demos:
            data = record(args.workdir, demos, size_of(args))
            clones.append(clone(args.workdir, demos, data, model.with_flags(**setting.clone_flags), seed,
                                size_of(args)))
    skills = [word for run in clones for word in ("--checkpoint", run.checkpoint)] or ["--flat"]
    arguments = ["--tasks", setting.tasks, "--reward", reward, "--frames", str(args.frames), "--envs", str(args.envs),
                 "--seed", str(seed), *setting.ppo, *skills]
    folder = f"finetune/{setting.name}/{args.frames}frames_{args.envs}envs/{method}_{reward}/seed{seed}"
    job = Finetuning(args.workdir, folder, arguments).run()
    summary = job.summary()
    return {"method": method, "reward": reward, "seed": seed, "command": job.shown,
            "clone_commands": [run.shown for run in clones], "clone_wall_s": [run.wall_s for run in clones],
            "wall_s": summary["wall_s"], "frames_per_s": summary["frames_per_s"],
            "curve": curves.read_curve(job.curve, setting.labels)}


def summarise(runs: list[dict[str, Any]], labels: list[str]) -> dict[str, dict[str, Any]]:
    """Per method and reward: its seeds, the value at the budget (mean and std over seeds), the curves
    over seeds and the PPO throughput."""
    summary = {}
    for method in NAMES:
        for reward in REWARDS:
            mine = [run for run in runs if (run["method"], run["reward"]) == (method, reward)]
            if not mine:
                continue
            finals = [curves.at_budget(run["curve"], labels) for run in mine]
            summary[f"{method} | {reward}"] = {
                "method": method, "reward": reward, "seeds": [run["seed"] for run in mine],
                "at_budget": {key: mean_std([final[key] for final in finals]) for key in finals[0]},
                "curves": curves.over_seeds([run["curve"] for run in mine], labels),
                "frames_per_s": mean_std([run["frames_per_s"] for run in mine])["mean"],
            }
    return summary


def success_checks(summary: dict[str, dict[str, Any]], labels: list[str], bar: float) -> list[dict[str, Any]]:
    """OCN's sparse success >= `bar` on each task, and each baseline's sparse success below OCN's."""
    ours = summary.get("ocn | sparse")
    lowest = None if ours is None else min(ours["at_budget"][f"success[{label}]"]["mean"] for label in labels)
    found = [check(f"OCN, sparse: success >= {bar} on each of {', '.join(labels)}", lowest, lambda v: v >= bar)]
    if ours is not None:
        mean = ours["at_budget"]["success"]["mean"]
        found += [check(f"sparse: {NAMES[row['method']]}'s success below OCN's ({mean:.3f})",
                        row["at_budget"]["success"]["mean"], lambda v: v < mean)
                  for row in summary.values() if row["reward"] == "sparse" and row["method"] != "ocn"]
    return found


def efficiency_check(summary: dict[str, dict[str, Any]]) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The dense-reward sample-efficiency check (`curves.sample_efficiency`) and its details."""
    name = (f"dense: OCN's env frames to {curves.REACH:.0%} of its final return / the best baseline's to that "
            f"return <= {curves.EFFICIENCY_GOAL}")
    ours = summary.get("ocn | dense")
    baselines = {row["method"]: row for row in summary.values() if row["method"] != "ocn" and row["reward"] == "dense"}
    if ours is None or not baselines:
        return check(name, None, bool), None
    found = curves.sample_efficiency(ours, baselines)
    if found["ratio_is_bound"]:
        name += " (no baseline reached it: the ratio is at most OCN's frames / the budget)"
    return check(name, found["ratio"], lambda v: v <= curves.EFFICIENCY_GOAL), found


def study(setting: Setting, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The results of these runs: summary, checks and, on S1, the sample-efficiency details."""
    order = list(NAMES)
    runs = sorted(runs, key=lambda run: (run["seed"], order.index(run["method"]), REWARDS.index(run["reward"])))
    summary = summarise(runs, setting.labels)
    found = success_checks(summary, setting.labels, setting.success_bar)
    result = {"study": f"finetune_{setting.name}", "runs": runs, "summary": summary}
    if setting.name == "s1":
        efficiency, details = efficiency_check(summary)
        found.append(efficiency)
        result["sample_efficiency"] = details
    return {**result, "checks": found}


def restudy(name: str, rows: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """The study made again from the rows of several results files (`ocn-reproduce combine`)."""
    return study(SETTINGS[name.removeprefix("finetune_")], rows["runs"])


def budget_table(summary: dict[str, dict[str, Any]], labels: list[str]) -> list[str]:
    """Markdown lines: per method and reward, mean (std) over seeds at the budget, and PPO frames/s."""
    lines = ["| method | reward | seeds | mean return | success | " + " | ".join(labels) + " | PPO frames/s |",
             "|---|---|---|---|---|" + "---|" * len(labels) + "---|"]
    for row in summary.values():
        cells = {key: f"{value['mean']:.3f} ({value['std']:.3f})" for key, value in row["at_budget"].items()}
        lines.append(f"| {NAMES[row['method']]} | {row['reward']} | {', '.join(map(str, row['seeds']))} | "
                     f"{cells['mean_return']} | {cells['success']} | "
                     f"{' | '.join(cells[f'success[{label}]'] for label in labels)} | {row['frames_per_s']:.0f} |")
    return lines


def efficiency_words(details: dict[str, Any] | None) -> list[str]:
    """The sample-efficiency race in a sentence per method."""
    if details is None:
        return []
    def frames(value: float | None) -> str:
        return "not within the budget" if value is None else f"{value:,.0f} frames"

    each = "; ".join(f"{NAMES[method]} {frames(value)}" for method, value in details["baseline_frames"].items())
    return [f"Sample efficiency (dense): {curves.REACH:.0%} of OCN's final return is {details['target_return']:.3f}; "
            f"OCN reaches it in {frames(details['ocn_frames'])}; {each}.", ""]


def markdown(result: dict[str, Any], setting: Setting) -> str:
    """The results in words: the checks first, then the values at the budget."""
    settings = result["settings"]
    lines = [
        f"# Finetuning on Craft {setting.name.upper()}: {setting.tasks}", "",
        f"{origin_words(result)} Skills cloned by plain `lerobot-train` ({settings['steps']} steps of "
        f"{settings['batch_size']} episodes) from {', '.join(f'`{demos.name}`' for demos in setting.demos)} "
        f"({settings['episodes_per_task']} demonstrations per task); PPO by plain `ocn-finetune`, "
        f"{settings['frames']:,} env frames per run, {settings['envs']} envs. Values at the budget: the mean of each "
        f"run's last {curves.FINAL_ROWS} PPO iterations, then mean (std) over seeds.", "",
        "## Checks", "", *checks_table(result["checks"]), "",
        *efficiency_words(result.get("sample_efficiency")),
        "## At the budget", "", *budget_table(result["summary"], setting.labels), "",
        f"Curves: `{result['study']}.png` (mean and one std over seeds).", "",
    ]
    return "\n".join(lines)


def write(results: Path, result: dict[str, Any]) -> None:
    """The results files of an S1 or S2 study (`result["study"]` names it)."""
    setting = SETTINGS[result["study"].removeprefix("finetune_")]
    title = f"Finetuning in Craft {setting.name.upper()} ({setting.tasks}): mean and std over seeds"
    write_results(results, result["study"], result, markdown(result, setting),
                  lambda path: curves.plot(result["summary"], NAMES, setting.labels, title, path))


def check_plan(args: argparse.Namespace, setting: Setting) -> None:
    """Refuse an unknown method or reward, a method the setting does not hold (OMPN in S2), or a plan of
    no run at all."""
    wrong = sorted(set(args.methods) - set(setting.methods)) + sorted(set(args.rewards) - set(REWARDS))
    if wrong:
        raise SystemExit(f"ocn-reproduce {setting.name}: unknown {wrong}; methods are {list(setting.methods)}, "
                         f"rewards {list(REWARDS)}")
    if not (args.seeds and args.methods and args.rewards):
        raise SystemExit(f"ocn-reproduce {setting.name}: no run planned (--seeds, --methods, --rewards)")


def planned(args: argparse.Namespace) -> list[tuple[int, str]]:
    """The (seed, method) pairs to run, seed by seed: OCN on `--seeds`, each baseline on `--baseline-seeds`.
    The baselines' PPO runs cost up to 25 times OCN's (results/archive/finetune_s2_dart_seeds: MoE and flat
    PPO at about 390 frames/s against OCN's 1,900; OMPN's RL form at about 130), so by default they run on
    one seed and OCN on three."""
    seeds = sorted(set(args.seeds) | set(args.baseline_seeds))
    return [(seed, method) for seed in seeds for method in args.methods
            if seed in (args.seeds if method == "ocn" else args.baseline_seeds)]


def reproduce(args: argparse.Namespace) -> int:
    """Every planned run in turn, seed by seed, the results rewritten after each."""
    setting = SETTINGS[args.study]
    check_plan(args, setting)
    started, settings = time.perf_counter(), settings_of(args)
    runs = []
    for seed, method in planned(args):
        for reward in args.rewards:
            runs.append(finetune_run(args, setting, method, reward, seed))
            result = {**provenance(args.argv, settings), **study(setting, runs),
                      "wall_s": round(time.perf_counter() - started)}
            write(args.results, result)
    print(markdown(result, setting))
    return 0


def settings_of(args: argparse.Namespace) -> dict[str, Any]:
    """What the results say this invocation measured with."""
    names = ("seeds", "baseline_seeds", "methods", "rewards", "frames", "envs", "episodes_per_task", "steps",
             "batch_size")
    return {**{name: getattr(args, name) for name in names}, "workdir": str(args.workdir),
            "results": str(args.results)}


def add_ppo_arguments(parser: argparse.ArgumentParser, setting: Setting, size: Size) -> None:
    """The options of a finetuning study: its size, PPO budget, rewards and methods."""
    add_size_arguments(parser, size)
    parser.add_argument("--baseline-seeds", type=seed_list, default="1",
                        help="comma-separated seeds of the baselines' runs (OCN's are --seeds)")
    parser.add_argument("--frames", type=int, default=setting.frames, help="env frames per PPO run")
    parser.add_argument("--envs", type=int, default=setting.envs, help="envs per PPO iteration")
    parser.add_argument("--rewards", type=lambda text: text.split(","), default=",".join(REWARDS),
                        help="comma-separated, of sparse,dense")
    parser.add_argument("--methods", type=lambda text: text.split(","), default=",".join(setting.methods),
                        help=f"comma-separated, of {','.join(setting.methods)}")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The `s1` and `s2` subcommands."""
    for name, setting in SETTINGS.items():
        parser = sub.add_parser(name, help=f"finetuning on {setting.tasks} over cloned skills",
                                description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        add_ppo_arguments(parser, setting, SIZE)
        parser.add_argument("--results", type=Path, default=RESULTS, help=f"folder of finetune_{name}.{{json,md,png}}")
        parser.set_defaults(func=reproduce, study=name)
