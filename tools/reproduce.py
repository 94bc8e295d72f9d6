"""`ocn-reproduce`: the paper's experiments end to end, from recording to the committed results.

`ocn-reproduce imitation-s1` records (or reuses) the S1 demonstrations ({AC, CD, DA}, 6000 each),
trains OCN with `lerobot-train` on the train split for each seed and each ablation (2, 3 and 6
options; temperature 1 against 10), scores every run with `ocn-eval` on the validation split and
writes `results/imitation_s1.{json,md}` with plots. Finished runs are reused, so an interrupted
reproduction continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tools import console_script

from tools.bench import RESULTS, machine

S1_TASKS = "AC,CD,DA"
SAVE_EVERY = 1000  # lerobot-train checkpoints this often, so a stopped run resumes from its last one
METRICS = ("f1_tol0", "f1_tol1", "align_acc", "nmi", "diagonal_mean", "off_diagonal_max", "mean_success_rate")


@dataclass
class Variant:
    """One configuration of the study: its name, `--policy.*` overrides and how many seeds it gets."""

    name: str
    overrides: dict[str, Any] = field(default_factory=dict)
    main: bool = False


VARIANTS = (
    Variant("3 options, T=10", {"n_options": 3, "temperature": 10.0}, main=True),
    Variant("2 options, T=10", {"n_options": 2, "temperature": 10.0}),
    Variant("6 options, T=10", {"n_options": 6, "temperature": 10.0}),
    Variant("3 options, T=1", {"n_options": 3, "temperature": 1.0}),
)


def _slug(name: str) -> str:
    return name.replace(", ", "_").replace(" ", "").replace("=", "")


def record_s1(root: Path, episodes_per_task: int, seed: int) -> None:
    """Record the S1 demonstrations unless `root` already holds a finished dataset."""
    if (root / "meta" / "info.json").exists():
        print(f"reusing the S1 dataset in {root}", flush=True)
        return
    subprocess.run(
        [console_script("record_demos"), "--env", "craft", "--tasks", S1_TASKS, "--episodes-per-task", str(episodes_per_task),
         "--root", str(root), "--repo-id", "local/craft_s1", "--seed", str(seed)],
        check=True,
    )


def train_command(args: argparse.Namespace, data: Path, out: Path, variant: Variant, seed: int) -> list[str]:
    """The `lerobot-train` call of one run, on the dataset's train split."""
    from ocn_data.episodes_table import split_episodes

    train = split_episodes(data, "train")
    command = [
        console_script("lerobot-train"), "--policy.type=ocn", "--dataset.repo_id=local/craft_s1", f"--dataset.root={data}",
        f"--dataset.episodes=[{','.join(map(str, train))}]", "--policy.device=cpu", "--policy.push_to_hub=false",
        "--wandb.enable=false", "--env_eval_freq=0", f"--steps={args.steps}", f"--batch_size={args.batch_size}",
        f"--num_workers={args.num_workers}", f"--save_freq={min(args.steps, SAVE_EVERY)}", "--log_freq=50", f"--seed={seed}",
        f"--policy.window_size={args.window_size}", f"--policy.controller_lr_scale={args.controller_lr_scale}",
        f"--output_dir={out}",
    ]
    return command + [f"--policy.{key}={value}" for key, value in variant.overrides.items()]


def run_one(args: argparse.Namespace, data: Path, variant: Variant, seed: int) -> dict[str, Any]:
    """Train (unless done before) and evaluate one seed of one variant; returns its record."""
    run_dir = args.workdir / "imitation_s1" / _slug(variant.name) / f"seed{seed}"
    checkpoint = run_dir / "train" / "checkpoints" / "last" / "pretrained_model"
    record_path = run_dir / "record.json"
    command = train_command(args, data, run_dir / "train", variant, seed)
    shown = " ".join(command[:4] + ["--dataset.episodes=[<train split>]"] + command[5:])
    _check_reusable(run_dir, shown)
    if record_path.exists():
        return json.loads(record_path.read_text())
    train_s = train(args, command, shown, run_dir)
    eval_json = run_dir / "eval.json"
    started = time.perf_counter()
    subprocess.run(
        [console_script("ocn-eval"), "--policy", str(checkpoint), "--root", str(data), "--repo-id", "local/craft_s1",
         "--split", "val", "--out", str(eval_json), "--rollouts", str(args.rollouts)],
        check=True,
    )
    from tools.parsing_metrics import option_table_summary

    scores = json.loads(eval_json.read_text())
    scores.update(option_table_summary(np.array(scores["option_subtask_success"]["table"])))
    record = {
        "variant": variant.name,
        "seed": seed,
        "train_wall_s": train_s,
        "eval_wall_s": round(time.perf_counter() - started, 1),
        "train_command": shown,
        "scores": scores,
    }
    record_path.write_text(json.dumps(record, indent=2) + "\n")
    return record


def _trained_steps(train_dir: Path) -> int:
    """The step of the run's latest lerobot-train checkpoint (0 if it has none)."""
    path = train_dir / "checkpoints" / "last" / "training_state" / "training_step.json"
    return json.loads(path.read_text())["step"] if path.exists() else 0


def train(args: argparse.Namespace, command: list[str], shown: str, run_dir: Path) -> float | None:
    """Run lerobot-train until the run has all its steps: from scratch, or resumed from the last
    checkpoint of a stopped run (a run folder with no checkpoint yet starts over). Returns the wall
    seconds of every training invocation of this run added up (None if an earlier reproduction
    trained it all)."""
    train_dir, times_path = run_dir / "train", run_dir / "train_wall_s.json"
    done = _trained_steps(train_dir)
    if done >= args.steps:
        return json.loads(times_path.read_text())["total"] if times_path.exists() else None
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "train_command.txt").write_text(shown + "\n")
    if done == 0:
        shutil.rmtree(train_dir, ignore_errors=True)
        print(f"training {run_dir}", flush=True)
    else:
        config = train_dir / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
        command = [command[0], f"--config_path={config}", "--resume=true"]
        print(f"resuming {run_dir} from step {done}", flush=True)
    times = json.loads(times_path.read_text()) if times_path.exists() else {"invocations": [], "total": 0.0}
    started = time.perf_counter()
    with open(run_dir / "train.log", "a") as log:
        subprocess.run(command, check=True, stdout=log, stderr=subprocess.STDOUT, env=_train_env(args))
    wall = round(time.perf_counter() - started, 1)
    times["invocations"].append({"from_step": done, "wall_s": wall})
    times["total"] = round(times["total"] + wall, 1)
    times_path.write_text(json.dumps(times, indent=2) + "\n")
    return times["total"]


def _check_reusable(run_dir: Path, command: str) -> None:
    """Refuse to reuse a run that was trained by another command (other steps, seed, overrides...)."""
    record_path, command_path = run_dir / "record.json", run_dir / "train_command.txt"
    if record_path.exists():
        before = json.loads(record_path.read_text())["train_command"]
    elif command_path.exists():
        before = command_path.read_text().strip()
    else:
        return
    if _settings(before) != _settings(command):
        raise SystemExit(
            f"{run_dir} holds a run trained with other settings:\n  {before}\nwhile this reproduction "
            f"would run:\n  {command}\nMove that folder away or pass another --workdir."
        )


def _settings(command: str) -> list[str]:
    """A training command without what does not change the trained model: its paths (program, data
    root, output dir), which may move, and how often it logs and saves."""
    ignored = ("--dataset.root=", "--output_dir=", "--save_freq=", "--log_freq=")
    return [word for word in command.split()[1:] if not word.startswith(ignored)]


def _train_env(args: argparse.Namespace) -> dict[str, str]:
    """One math thread per process: the data workers already fill the other cores."""
    return {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and standard deviation of each metric per variant."""
    summary = {}
    for variant in VARIANTS:
        mine = [r for r in records if r["variant"] == variant.name]
        if not mine:
            continue
        values = {m: np.array([r["scores"][m] for r in mine], dtype=float) for m in METRICS}
        summary[variant.name] = {
            "seeds": [r["seed"] for r in mine],
            **{m: {"mean": float(v.mean()), "std": float(v.std())} for m, v in values.items()},
            "success_rate_min": float(min(min(r["scores"]["success_rate"].values()) for r in mine)),
        }
    return summary


def must_show(summary: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's bars, each with the measured value and whether it holds."""
    main, checks = summary.get(VARIANTS[0].name), []
    if main:
        for label, metric, bar, above in (
            ("NMI >= 0.95", "nmi", 0.95, True),
            ("F1@1 >= 0.99", "f1_tol1", 0.99, True),
            ("task alignment >= 0.98", "align_acc", 0.98, True),
            ("option x subtask diagonal >= 0.95", "diagonal_mean", 0.95, True),
            ("option x subtask off-diagonal <= 0.1", "off_diagonal_max", 0.1, False),
        ):
            value = main[metric]["mean"]
            checks.append({"check": f"3 options, T=10: {label}", "value": value, "holds": value >= bar if above else value <= bar})
        value = main["success_rate_min"]
        checks.append({"check": "3 options, T=10: free-run success >= 0.95 on every task", "value": value, "holds": value >= 0.95})
    for name, label, test in (
        ("6 options, T=10", "NMI >= 0.9", lambda v: v >= 0.9),
        ("2 options, T=10", "NMI clearly (0.1) below 3 options'", lambda v: main is not None and v <= main["nmi"]["mean"] - 0.1),
        ("3 options, T=1", "NMI below T=10's", lambda v: main is not None and v < main["nmi"]["mean"]),
    ):
        if name in summary:
            value = summary[name]["nmi"]["mean"]
            checks.append({"check": f"{name}: {label}", "value": value, "holds": bool(test(value))})
    return checks


def plot(records: list[dict[str, Any]], path: Path) -> None:
    """Per-variant bars (mean) with every seed as a dot, one panel per metric."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = ("f1_tol1", "align_acc", "nmi", "diagonal_mean", "mean_success_rate")
    names = [v.name for v in VARIANTS if any(r["variant"] == v.name for r in records)]
    fig, axes = plt.subplots(1, len(shown), figsize=(3.2 * len(shown), 3.4), sharey=True)
    for ax, metric in zip(axes, shown, strict=True):
        for k, name in enumerate(names):
            values = [r["scores"][metric] for r in records if r["variant"] == name]
            ax.bar(k, np.mean(values), color=f"C{k}", alpha=0.6)
            ax.scatter(np.full(len(values), k), values, color="k", s=12, zorder=3)
        ax.set_xticks(range(len(names)), [n.replace(", ", "\n") for n in names], fontsize=8)
        ax.set_title(metric)
        ax.set_ylim(0, 1.05)
    fig.suptitle("OCN imitation on Craft S1 (validation episodes)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(result: dict[str, Any]) -> str:
    """The human-readable results file."""
    lines = [
        "# OCN imitation on Craft S1 ({AC, CD, DA})",
        "",
        f"Written by `{result['command']}` on {result['machine']['cpu']} ({result['machine']['cores']} cores), "
        f"{result['date']}. Training: `lerobot-train`, {result['settings']['steps']} steps of "
        f"{result['settings']['batch_size']} windows (episodes), controller learning-rate scale "
        f"{result['settings']['controller_lr_scale']}; scores: `ocn-eval` on the validation split "
        f"({result['settings']['rollouts']} env episodes per task and per option-table cell). Runs finished: "
        f"{result['runs_finished']} of {result['runs_planned']}; wall time of this invocation "
        f"{result['wall_s'] / 60:.0f} min (runs finished before it were reused; each run's training time is below).",
        "",
        "## Must-show checks",
        "",
        "| check | measured | holds |",
        "|---|---|---|",
    ]
    lines += [f"| {c['check']} | {c['value']:.3f} | {'yes' if c['holds'] else 'NO'} |" for c in result["must_show"]]
    lines += ["", "## Mean (std) over seeds", "", "| variant | seeds | " + " | ".join(METRICS) + " |",
              "|---|---|" + "---|" * len(METRICS)]
    for name, row in result["summary"].items():
        cells = " | ".join(f"{row[m]['mean']:.3f} ({row[m]['std']:.3f})" for m in METRICS)
        lines.append(f"| {name} | {len(row['seeds'])} | {cells} |")
    lines += ["", "## Every run", "", "| variant | seed | F1@0 | F1@1 | align | NMI | diagonal | success per task | train s |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in result["runs"]:
        s = r["scores"]
        success = ", ".join(f"{v:.2f}" for v in s["success_rate"].values())
        lines.append(
            f"| {r['variant']} | {r['seed']} | {s['f1_tol0']:.3f} | {s['f1_tol1']:.3f} | {s['align_acc']:.3f} | "
            f"{s['nmi']:.3f} | {', '.join(f'{d:.2f}' for d in s['diagonal'])} | {success} | {r['train_wall_s']} |"
        )
    lines += ["", "Plots: `imitation_s1.png` (every metric, seeds as dots), `imitation_s1_option_table.png` "
              "(option x subtask success of the first main-variant seed).", ""]
    return "\n".join(lines)


def imitation_s1(args: argparse.Namespace) -> int:
    """Every planned run in turn; the results files are rewritten after each one, so a reproduction
    stopped part-way leaves results for the runs it finished (the files say how many)."""
    started = time.perf_counter()
    data = args.workdir / "craft_s1"
    record_s1(data, args.episodes_per_task, args.data_seed)
    planned = [
        (variant, seed)
        for variant in VARIANTS
        if variant.main or args.ablation_seeds > 0
        for seed in range(1, 1 + (args.seeds if variant.main else args.ablation_seeds))
    ]
    records: list[dict[str, Any]] = []
    for variant, seed in planned:
        records.append(run_one(args, data, variant, seed))
        result = write_results(args, records, len(planned), time.perf_counter() - started)
    print(markdown(result))
    return 0


def write_results(args: argparse.Namespace, records: list[dict[str, Any]], planned: int, wall_s: float) -> dict[str, Any]:
    """`results/imitation_s1.{json,md,png}` (and the option table) from the runs finished so far."""
    summary = summarise(records)
    result = {
        "command": "ocn-reproduce " + " ".join(sys.argv[1:] if args.argv is None else args.argv),
        "date": time.strftime("%Y-%m-%d"),
        "machine": machine(),
        "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if k not in ("func", "argv")},
        "runs_finished": len(records),
        "runs_planned": planned,
        "summary": summary,
        "must_show": must_show(summary),
        "runs": records,
        "wall_s": round(wall_s, 1),
    }
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "imitation_s1.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.results / "imitation_s1.md").write_text(markdown(result))
    plot(records, args.results / "imitation_s1.png")
    first = args.workdir / "imitation_s1" / _slug(VARIANTS[0].name) / "seed1" / "eval.png"
    if first.exists():
        (args.results / "imitation_s1_option_table.png").write_bytes(first.read_bytes())
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="ocn-reproduce", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="experiment", required=True)
    s1 = sub.add_parser("imitation-s1", help="OCN imitation on S1 with the paper's ablations",
                        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    s1.add_argument("--seeds", type=int, default=5, help="seeds of the main variant (3 options, T=10)")
    s1.add_argument("--ablation-seeds", type=int, default=1, help="seeds of each ablation; 0 skips them")
    s1.add_argument("--steps", type=int, default=5000, help="lerobot-train steps per run")
    s1.add_argument("--batch-size", type=int, default=128, help="windows (episodes) per step")
    s1.add_argument("--window-size", type=int, default=24, help="longest episode a window holds")
    s1.add_argument("--controller-lr-scale", type=float, default=1.0,
                    help="controller learning rate / the options' (see OCNConfig.controller_lr_scale)")
    s1.add_argument("--num-workers", type=int, default=2, help="lerobot-train data workers")
    s1.add_argument("--threads", type=int, default=1, help="math threads of each process")
    s1.add_argument("--episodes-per-task", type=int, default=6000)
    s1.add_argument("--data-seed", type=int, default=0)
    s1.add_argument("--rollouts", type=int, default=200, help="env episodes per task and per option-table cell")
    s1.add_argument("--workdir", type=Path, default=Path("outputs/reproduce"))
    s1.add_argument("--results", type=Path, default=RESULTS)
    s1.set_defaults(func=imitation_s1)
    args = parser.parse_args(argv)
    args.argv = argv
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
