"""`ocn-reproduce parsing-s1`: how OCN and the baselines parse the S1 demonstrations over the course
of training (the paper's figure 7).

Uses the S1 demonstrations of `imitation-s1` ({AC, CD, DA}, the same recording in the same workdir,
so both commands share one dataset) and trains each method with `lerobot-train` on the train split,
with the same steps, batch and windows for all, keeping a checkpoint every `--eval-every` steps:

  ocn      OCN with 3 options and T = 10 (the imitation study's main settings)
  ompn     OMPN (`--policy.type=ompn`) with its own defaults (OMPNConfig: OMPN's Craft setup)
  compile  compILE (`--policy.type=compile`) with its own defaults (CompILEConfig: tkipf/compile
           and OMPN's Craft baseline)
  hil      HIL (`--policy.type=ocn --policy.hierarchy=hil`), the default skill length, and OCN's
           3 options and T = 10

Every saved checkpoint is then parsed on the validation split, in this process, and scored with
the shared parsing metrics only (`tools.episode_parsing`): F1@0, F1@1, task alignment and NMI (NMI
only for a model with per-step labels: OMPN has none). No env rollouts are run: they would cost far
more than the parse at every checkpoint. OMPN's checkpoints are read out twice: top-k, told each
episode's true number of subtasks as in OMPN's own evaluation, and count-free, as OCN's parse is,
with the threshold of `threshold_boundaries` chosen at each checkpoint on as many training episodes
as the validation split holds (`choose_boundary_threshold`); the count-free read-out is the row
"OMPN, count-free". `--dart-noise` reads the DART recording of `imitation-s1 --dart-noise`.

Writes results/parsing_s1.json (every method, seed and step with the four metrics, each method's
hyperparameters and where they come from, the checks), results/parsing_s1.md (the checks, the final
values as mean ± std over seeds, every baseline win, the commands, the machine, wall times) and
results/parsing_s1.png (one panel per metric against the training step: each method's mean over
seeds with its min-max band), rewritten after every finished run. The checks: OCN's F1@1 and NMI at
or above OMPN's at the end of training, under both of OMPN's read-outs (NMI cannot be compared with
OMPN, which has no labels, so it is compared with compILE's and HIL's instead), and every metric
where any baseline ends above OCN.

Finished runs and their scores are reused, so an interrupted reproduction continues (a stopped
training run resumes from its last checkpoint); a run folder trained with other settings is refused,
and so is one whose checkpoints are not the ones `--eval-every` asks for. Methods or seeds run in
separate invocations (and workdirs) join into one study with `ocn-reproduce combine`.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ocn_data.episodes_table import EpisodeArrays, load_episodes, split_episodes
from tools.bench import RESULTS
from tools.reproduce import finetune, imitation
from tools.reproduce.finetune import Method
from tools.reproduce.report import (checks_table, origin_words, over_seeds, provenance, train_time_words,
                                   write_result_files)
from tools.reproduce.runs import TrainSettings, train_policy, training_record

METRICS = {"f1_tol0": "F1@0", "f1_tol1": "F1@1", "align_acc": "task alignment", "nmi": "NMI"}
_FINETUNED = {method.key: method for method in finetune.METHODS}
METHODS = (_FINETUNED["ocn"], _FINETUNED["ompn"], _FINETUNED["compile"], _FINETUNED["hil"])
OCN = METHODS[0].name
OMPN_COUNT_FREE = "OMPN, count-free"  # OMPN's runs under the count-free read-out (the rows' `count_free`)
# The rows of a study's summary, in order: each method, and OMPN's second read-out after it.
ROWS = (OCN, "OMPN", OMPN_COUNT_FREE, *(method.name for method in METHODS[2:]))
# Per method: the config fields reported as its hyperparameters (read back from the trained
# checkpoint's config.json) and where their values come from.
HYPERPARAMETERS: dict[str, tuple[tuple[str, ...], str]] = {
    "ocn": (
        ("n_options", "temperature", "hidden_size", "mlp_hidden_size", "mlp_depth", "optimizer_lr",
         "controller_lr_scale"),
        "OCN paper appendix A.2 (hidden size 128, cell MLP depth 2, controller temperature T = 10, Adam, "
        "lr 1e-3); 3 options for S1's 3 subtasks, the imitation study's main variant; the controller "
        "learning-rate scale is this command's --controller-lr-scale (OCNConfig.controller_lr_scale)",
    ),
    "ompn": (
        ("n_slots", "hidden_size", "cell_hidden_size", "optimizer_lr", "optimizer_grad_clip_norm"),
        "OMPN's Craft setup in its public code, Ordered-Memory-RL/ompn_craft (ilflagfile, "
        "gym_psketch/bots/omdec.py, om_utils.py): 3 slots of width 128, cell MLP width 4 x 128, lr 1e-3, "
        "gradient clip 0.2 (OMPNConfig's defaults and docstring)",
    ),
    "compile": (
        ("n_segments", "latent_type", "latent_dim", "hidden_size", "kl_z_weight", "kl_b_weight", "poisson_rate",
         "boundary_temperature", "latent_temperature", "optimizer_lr"),
        "tkipf/compile's defaults (latent_dim 32, beta_z = beta_b = 0.1, Poisson prior rate 3, Gumbel "
        "temperatures 1) and OMPN's Craft compILE baseline (4 segments, concrete latents, lr 1e-4, width 128) "
        "(CompILEConfig's defaults and docstring)",
    ),
    "hil": (
        ("hierarchy", "skill_length", "n_options", "temperature", "hidden_size", "mlp_hidden_size", "mlp_depth",
         "optimizer_lr", "controller_lr_scale"),
        "policies/ocn/configuration_ocn.py: hierarchy 'hil' with the default skill_length 4 (below Craft's "
        "shortest subtask of about 5 steps, so a skill boundary lies within 2 steps of every subtask end); "
        "the network is OCN's (3 options, T = 10, appendix A.2's widths), as in ocn-reproduce s1's HIL clones",
    ),
}

EXPERIMENT = "parsing-s1"  # the subcommand, kept in a results file's settings as its kind
# Settings that change what a run measures: the results files `ocn-reproduce combine` merges agree on each.
RECIPE = ("experiment", "steps", "batch_size", "window_size", "eval_every", "controller_lr_scale", "episodes_per_task",
          "data_seed", "dart_noise", "window_start", "usage_balance")

# How each model's boundaries are read, said beside every comparison: OMPN is given a count.
READOUT_NOTE = (
    "How the boundaries are read: OMPN's are its top-k expansions with k the episode's true number of "
    "subtasks, as in its own evaluation (`tools.episode_parsing`), so it is told how many to place; "
    "\"OMPN, count-free\" reads the same models with no count, at the expansion threshold chosen on training "
    "episodes; OCN's and HIL's are where the chosen option changes, compILE's its argmax segment ends, with no "
    "count given."
)


def study_settings(result: dict[str, Any]) -> dict[str, Any]:
    """A parsing results file's settings, with the defaults of settings added after it was written."""
    return {**imitation.RECORDING_DEFAULTS, **result["settings"]}


def method_settings(args: argparse.Namespace, method: Method) -> tuple[TrainSettings, dict[str, Any]]:
    """A method's `lerobot-train` settings and `--policy.*` overrides: those of `ocn-reproduce s1`'s
    S1 clones (OCN and HIL: 3 options, T = 10; OMPN and compILE: their own defaults), with a
    checkpoint every `--eval-every` steps."""
    settings, overrides = finetune.clone_settings(args, finetune.SETTINGS["s1"], method)
    return replace(settings, save_every=args.eval_every), overrides


def run_dir(args: argparse.Namespace, method: Method, seed: int) -> Path:
    """Where one method's seed trains and keeps its scores: this study's own, since imitation-s1 and
    s1 keep too few checkpoints to draw a curve from (OCN-family runs under the usage balance apart)."""
    return args.workdir / "parsing_s1" / f"{method.key}{finetune.clone_study_suffix(args, method)}" / f"seed{seed}"


def scored_steps(steps: int, every: int) -> list[int]:
    """The steps lerobot-train saves a checkpoint at: every `every` steps and the last."""
    return sorted({*range(every, steps + 1, every), steps})


def checkpoints(train_dir: Path) -> dict[int, Path]:
    """The run's saved checkpoints (`checkpoints/<step>/pretrained_model`) by step."""
    folder = train_dir / "checkpoints"
    found = folder.iterdir() if folder.is_dir() else []
    return {int(path.name): path / "pretrained_model" for path in found if path.name.isdigit()}


def score_checkpoint(checkpoint: Path, episodes: EpisodeArrays, threads: int,
                     tuning: EpisodeArrays | None = None) -> dict[str, Any]:
    """One checkpoint's parse of the episodes, scored with the shared metrics; `no_labels` says why
    NMI is missing when the model gives no per-step labels. With `tuning` (training episodes), also
    `count_free`: the scores of OMPN's count-free read-out at the threshold that parses `tuning` best,
    with that threshold and every tried threshold's F1@1 there."""
    import dataclasses

    import torch

    from tools.episode_parsing import (choose_boundary_threshold, load_policy, parser_of, score_segmentations,
                                       segment_episodes)

    torch.set_num_threads(threads)
    started = time.perf_counter()
    policy, preprocessor, _ = load_policy(checkpoint)

    def scored() -> dict[str, Any]:
        scores = score_segmentations(episodes, segment_episodes(policy, preprocessor, episodes))
        return {metric: scores[metric] for metric in METRICS}

    row = scored()
    if row["nmi"] is None:
        row["no_labels"] = parser_of(policy).no_labels
    if tuning is not None:
        threshold, tuned = choose_boundary_threshold(policy, preprocessor, tuning)
        policy.config = dataclasses.replace(policy.config, boundary_threshold=threshold)
        row["count_free"] = {**scored(), "threshold": threshold,
                             "tuning_f1_tol1": {str(key): value for key, value in tuned.items()}}
    return {**row, "wall_s": round(time.perf_counter() - started, 2)}


def score_run(folder: Path, steps: list[int], episodes: EpisodeArrays, threads: int,
              tuning: EpisodeArrays | None = None) -> list[dict[str, Any]]:
    """Every wanted checkpoint of a trained run, scored (or read back from `parsing.json`, where each
    score is kept as soon as it is made; a kept score without the count-free read-out that `tuning`
    asks for is made again). A run without a checkpoint at every wanted step was trained with another
    checkpoint interval and is refused."""
    saved = checkpoints(folder / "train")
    missing = [step for step in steps if step not in saved]
    if missing:
        raise SystemExit(
            f"{folder} has no checkpoint at steps {missing} (it has {sorted(saved)}): it was trained with another "
            f"--eval-every. Pass that interval, move the folder away or pass another --workdir."
        )
    cache = folder / "parsing.json"
    rows = {row["step"]: row for row in json.loads(cache.read_text())} if cache.exists() else {}
    for step in steps:
        if step not in rows or (tuning is not None and "count_free" not in rows[step]):
            rows[step] = {"step": step, **score_checkpoint(saved[step], episodes, threads, tuning)}
            cache.write_text(json.dumps(sorted(rows.values(), key=lambda row: row["step"]), indent=2) + "\n")
    return [rows[step] for step in steps]


def hyperparameters(method: Method, checkpoint: Path, settings: TrainSettings) -> dict[str, Any]:
    """The method's hyperparameters as trained (its checkpoint's config), the shared training budget,
    and where the values come from."""
    fields, source = HYPERPARAMETERS[method.key]
    config = json.loads((checkpoint / "config.json").read_text())
    return {
        "policy_type": method.policy_type,
        "values": {name: config[name] for name in fields},
        "source": source,
        "training": {"steps": settings.steps, "batch_size": settings.batch_size, "window_size": settings.window_size,
                     "checkpoint_every": settings.save_every},
    }


def run_one(args: argparse.Namespace, data: Path, episodes: EpisodeArrays, method: Method, seed: int,
            tuning: EpisodeArrays | None = None) -> dict[str, Any]:
    """Train (unless done) one method and seed, then score every checkpoint (unless done); OMPN's also
    under the count-free read-out tuned on `tuning`."""
    folder = run_dir(args, method, seed)
    settings, overrides = method_settings(args, method)
    trained = train_policy(settings, data, imitation.S1_REPO_ID, folder, seed, overrides)
    scored = score_run(folder, scored_steps(settings.steps, settings.save_every), episodes, args.threads,
                       tuning if method.key == "ompn" else None)
    return {
        "method": method.name, "seed": seed, "train_command": trained.command, **training_record(trained),
        "score_wall_s": round(sum(row["wall_s"] for row in scored), 1),
        "hyperparameters": hyperparameters(method, trained.checkpoint, settings),
        "checkpoints": scored,
    }


def count_free_runs(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """OMPN's runs as read out count-free: one run per OMPN run whose checkpoints all carry the
    `count_free` scores, named `OMPN_COUNT_FREE`, with those scores and thresholds as its checkpoints."""
    return [
        {"method": OMPN_COUNT_FREE, "seed": run["seed"],
         "checkpoints": [{"step": row["step"], **row["count_free"], "no_labels": "as OMPN's (the same models)"}
                         for row in run["checkpoints"]]}
        for run in runs
        if run["method"] == "OMPN" and all("count_free" in row for row in run["checkpoints"])
    ]


def summarise(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per row of `ROWS`: the curves over seeds (mean, std, min, max at each step) and the final values
    (mean and std over seeds at the last step); a metric the method cannot have is None. OMPN's runs
    give a second row under the count-free read-out where they were scored with it."""
    runs = runs + count_free_runs(runs)
    summary: dict[str, dict[str, Any]] = {}
    for name in ROWS:
        mine = [run for run in runs if run["method"] == name]
        if not mine:
            continue
        steps = [row["step"] for row in mine[0]["checkpoints"]]
        curves: dict[str, Any] = {}
        final: dict[str, Any] = {}
        for metric in METRICS:
            if any(row[metric] is None for run in mine for row in run["checkpoints"]):
                curves[metric] = final[metric] = None
                continue
            values = np.array([[row[metric] for row in run["checkpoints"]] for run in mine])
            curves[metric] = over_seeds(values)
            final[metric] = {"mean": float(values[:, -1].mean()), "std": float(values[:, -1].std())}
        summary[name] = {"seeds": [run["seed"] for run in mine], "steps": steps, "curves": curves, "final": final}
    return summary


def _final(summary: dict[str, dict[str, Any]], method: str, metric: str) -> float | None:
    value = summary[method]["final"][metric]
    return None if value is None else value["mean"]


def compare(summary: dict[str, dict[str, Any]], metric: str, baseline: str, why: str = "") -> dict[str, Any]:
    """The check "OCN's `metric` at or above the baseline's at the end of training": OCN's final mean
    as the value; a baseline without the metric makes it a check that cannot be made (holds None)."""
    ours, theirs = _final(summary, OCN, metric), _final(summary, baseline, metric)
    if theirs is None:
        return {"check": f"OCN's {METRICS[metric]} at or above {baseline}'s at the end: cannot be compared, "
                         f"{baseline} has no per-step labels{why}", "metric": metric, "baseline": baseline,
                "value": None, "baseline_value": None, "holds": None}
    return {"check": f"OCN's {METRICS[metric]} at or above {baseline}'s ({theirs:.3f}) at the end{why}",
            "metric": metric, "baseline": baseline, "value": ours, "baseline_value": theirs,
            "holds": ours is not None and ours >= theirs}


def must_show(summary: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Issue 7's checks against OMPN (F1@1 and NMI at the end of training); OMPN has no labels, so
    NMI is also compared with compILE's and HIL's."""
    if OCN not in summary:
        return []
    checks = []
    if "OMPN" in summary:
        checks += [compare(summary, "f1_tol1", "OMPN"),
                   compare(summary, "nmi", "OMPN", " (NMI is compared with compILE and HIL instead)")]
    if OMPN_COUNT_FREE in summary:
        checks.append(compare(summary, "f1_tol1", OMPN_COUNT_FREE, " (neither told the number of subtasks)"))
    checks += [compare(summary, "nmi", baseline, " (in place of OMPN, which has no labels)")
               for baseline in ("compILE", "HIL") if baseline in summary]
    return checks


def baseline_wins(summary: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Every metric where a baseline's final mean is above OCN's: the results say so plainly."""
    if OCN not in summary:
        return []
    wins = []
    for baseline in summary:
        for metric in METRICS:
            ours, theirs = _final(summary, OCN, metric), _final(summary, baseline, metric)
            if baseline != OCN and ours is not None and theirs is not None and theirs > ours:
                wins.append({"baseline": baseline, "metric": metric, "baseline_value": theirs, "ocn_value": ours})
    return wins


def plot(summary: dict[str, dict[str, Any]], path: Path) -> None:
    """Figure 7's form: one panel per metric against the training step, each method's mean over seeds
    with its min-max band (a method without the metric, OMPN's NMI, is left out of that panel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.4 * len(METRICS), 3.2), sharey=True)
    colours = {**{method.name: f"C{k}" for k, method in enumerate(METHODS)}, OMPN_COUNT_FREE: "C1"}
    for ax, (metric, label) in zip(axes, METRICS.items(), strict=True):
        for name in ROWS:
            row = summary.get(name)
            if row is None or row["curves"][metric] is None:
                continue
            curve = row["curves"][metric]
            ax.plot(row["steps"], curve["mean"], color=colours[name], marker=".", label=name,
                    linestyle="--" if name == OMPN_COUNT_FREE else "-")
            ax.fill_between(row["steps"], curve["min"], curve["max"], color=colours[name], alpha=0.2)
        ax.set_title(label + (" (OMPN: no labels)" if metric == "nmi" and "OMPN" in summary else ""), fontsize=9)
        ax.set_xlabel("training step")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Parsing the S1 validation episodes during imitation: mean and min-max over seeds")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _cell(value: dict[str, float] | None) -> str:
    return "n/a" if value is None else f"{value['mean']:.3f} ± {value['std']:.3f}"


def markdown(result: dict[str, Any]) -> str:
    """The human-readable results file."""
    settings = result["settings"]
    lines = [
        "# Parsing S1 over training: OCN against OMPN, compILE and HIL",
        "",
        f"{origin_words(result)} Every method trained by `lerobot-train` on the S1 train split for {settings['steps']} "
        f"steps of {settings['batch_size']} {imitation.loading_words(settings)}{imitation.recording_words(settings)} "
        f"(window {settings['window_size']}), "
        f"a checkpoint every {settings['eval_every']} steps; each checkpoint's parse of the "
        f"{result['val_episodes']} validation episodes "
        f"scored with the shared metrics (`tools.episode_parsing`), no env rollouts. Runs finished: "
        f"{result['runs_finished']} of {result['runs_planned']}; wall time of "
        + ("the invocations" if "sources" in result else "this invocation")
        + f" {result['wall_s'] / 60:.1f} min (runs an invocation found finished were reused).",
        "",
        "## Checks (issue 7)",
        "",
        *checks_table(result["must_show"]),
        "",
        "## Where a baseline beats OCN at the end of training",
        "",
        READOUT_NOTE,
        "",
    ]
    wins = result["baseline_wins"]
    lines += [f"- {w['baseline']} beats OCN on {METRICS[w['metric']]}: {w['baseline_value']:.3f} against "
              f"{w['ocn_value']:.3f}" for w in wins] or ["- Nowhere: OCN is at or above every baseline on every metric."
                                                         if OCN in result["summary"] else "- OCN was not run."]
    lines += ["", "## At the end of training (mean ± std over seeds)", "",
              "| method | seeds | step | " + " | ".join(METRICS.values()) + " |",
              "|---|---|---|" + "---|" * len(METRICS)]
    for name, row in result["summary"].items():
        cells = " | ".join(_cell(row["final"][metric]) for metric in METRICS)
        lines.append(f"| {name} | {len(row['seeds'])} | {row['steps'][-1]} | {cells} |")
    lines += [""] + [f"{method}'s NMI is n/a: {reason}" for method, reason in result["not_applicable"].items()]
    lines += ["", "## Methods", "", "| method | hyperparameters | from | first seed's training command |",
              "|---|---|---|---|"]
    for name, method in result["methods"].items():
        values = ", ".join(f"{key}={value}" for key, value in method["values"].items())
        lines.append(f"| {name} | {values} | {method['source']} | `{method['train_command']}` |")
    lines += ["", "## Every run", "", "| method | seed | checkpoints | train s | scoring s | final "
              + " | final ".join(METRICS.values()) + " |", "|---|---|---|---|---|" + "---|" * len(METRICS)]
    for run in result["runs"]:
        last = run["checkpoints"][-1]
        cells = " | ".join("n/a" if last[m] is None else f"{last[m]:.3f}" for m in METRICS)
        lines.append(f"| {run['method']} | {run['seed']} | {len(run['checkpoints'])} | {train_time_words(run)} | "
                     f"{run['score_wall_s']} | {cells} |")
    tuned = [(run["seed"], run["checkpoints"][-1]) for run in count_free_runs(result["runs"])]
    if tuned:
        lines += ["", f"{OMPN_COUNT_FREE}, at the last checkpoint: "
                  + "; ".join(f"seed {seed} threshold {row['threshold']:g} (F1@1 on the training episodes "
                              f"{row['tuning_f1_tol1'][str(row['threshold'])]:.3f}, on validation {row['f1_tol1']:.3f})"
                              for seed, row in tuned) + "."]
    lines += ["", "Curves: `parsing_s1.png`; every checkpoint's scores: `parsing_s1.json`.", ""]
    return "\n".join(lines)


def study(runs: list[dict[str, Any]], planned: int, val_episodes: int, wall_s: float) -> dict[str, Any]:
    """A study's result from its runs, without the provenance of the command that made it: the
    summary over seeds, the checks, the baseline wins and each method's hyperparameters."""
    summary = summarise(runs)
    methods = {}
    for run in runs:
        if run["method"] not in methods:
            methods[run["method"]] = {**run["hyperparameters"], "train_command": run["train_command"]}
    not_applicable = {run["method"]: row["no_labels"] for run in runs + count_free_runs(runs)
                      for row in run["checkpoints"] if row.get("no_labels")}
    return {
        "runs_finished": len(runs),
        "runs_planned": planned,
        "val_episodes": val_episodes,
        "methods": methods,
        "summary": summary,
        "must_show": must_show(summary),
        "baseline_wins": baseline_wins(summary),
        "not_applicable": not_applicable,
        "runs": runs,
        "wall_s": round(wall_s, 1),
    }


def write_study_files(results: Path, result: dict[str, Any]) -> None:
    """`parsing_s1.{json,md,png}` of a study's result in the folder `results`."""
    stem = write_result_files(results, "parsing_s1", result, markdown(result))
    plot(result["summary"], stem.with_suffix(".png"))


def write_results(args: argparse.Namespace, runs: list[dict[str, Any]], planned: int, val_episodes: int,
                  wall_s: float) -> dict[str, Any]:
    """`results/parsing_s1.{json,md,png}` from the runs finished so far."""
    result = {**provenance(args), **study(runs, planned, val_episodes, wall_s)}
    write_study_files(args.results, result)
    return result


def parsing_s1(args: argparse.Namespace) -> int:
    """Every planned run in turn (seeds outermost, so that each method's first seed comes early), the
    results rewritten after each one."""
    started = time.perf_counter()
    known = {method.key: method for method in METHODS}
    unknown = sorted(set(args.methods) - set(known))
    if unknown:
        raise SystemExit(f"ocn-reproduce parsing-s1: unknown methods {unknown}; the methods are {list(known)}.")
    if args.eval_every < 1:
        raise SystemExit(f"ocn-reproduce parsing-s1: --eval-every must be >= 1, got {args.eval_every}.")
    data = imitation.s1_data(args)
    episodes = load_episodes(data, split_episodes(data, "val"))
    # OMPN's count-free threshold is chosen on as many training episodes as the validation split holds.
    tuning = (load_episodes(data, split_episodes(data, "train")[:len(episodes.tasks)]) if "ompn" in args.methods
              else None)
    planned = [(known[key], seed) for seed in range(args.first_seed, args.first_seed + args.seeds)
               for key in args.methods]
    runs: list[dict[str, Any]] = []
    result: dict[str, Any] = {}
    for number, (method, seed) in enumerate(planned, 1):
        runs.append(run_one(args, data, episodes, method, seed, tuning))
        last = runs[-1]["checkpoints"][-1]
        scores = "  ".join(f"{label} {'n/a' if last[m] is None else f'{last[m]:.3f}'}" for m, label in METRICS.items())
        print(f"[{number}/{len(planned)}] {method.name} seed {seed}: {len(runs[-1]['checkpoints'])} checkpoints "
              f"scored, at step {last['step']}: {scores}", flush=True)
        result = write_results(args, runs, len(planned), len(episodes.tasks), time.perf_counter() - started)
    print(markdown(result))
    return 0


_EPILOG = """\
--episodes-per-task, --data-seed and --workdir say which S1 recording to use: with imitation-s1's
values and workdir both commands read the same dataset (workdir/craft_s1, recorded on first use).
--controller-lr-scale applies to the OCN family (ocn, hil) only; OMPN and compILE keep their own
learning rates. Runs live in workdir/parsing_s1/<method>/seed<k>/ (train/, train.log,
train_command.txt, train_wall_s.json, and parsing.json with each checkpoint's scores)."""


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults shown, and the description's own line breaks kept."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `parsing-s1` subcommand."""
    parser = sub.add_parser(EXPERIMENT, help="parsing of S1 over training, OCN against OMPN, compILE and HIL "
                            "(figure 7)", description=__doc__, epilog=_EPILOG, formatter_class=_HelpFormatter)
    parser.add_argument("--seeds", type=int, default=3, help="seeds per method")
    imitation.add_first_seed_argument(parser)
    parser.add_argument("--methods", type=lambda s: s.split(","), default=",".join(m.key for m in METHODS),
                        help="comma-separated: " + ",".join(m.key for m in METHODS))
    parser.add_argument("--eval-every", type=int, default=500,
                        help="lerobot-train steps between saved checkpoints (its --save_freq); each is scored, and "
                             "the last step always is")
    imitation.add_training_arguments(parser)
    imitation.add_window_start_argument(parser)
    imitation.add_dart_noise_argument(parser)
    finetune.add_usage_balance_argument(parser)
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of parsing_s1.{json,md,png}")
    parser.set_defaults(func=parsing_s1)
