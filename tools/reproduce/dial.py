"""`ocn-reproduce dial`: skills cloned from 2-digit PINs, reused by PPO on 3-digit PINs (paper
section 4.2, figure 6).

Records (or reuses) expert demonstrations of every 2-digit PIN over the paper's digits S = (1, 2,
4, 8) (`record_demos --env dial`: the 12 PINs with no digit repeated, as the env draws random PINs,
`--episodes-per-task` each, with the recorder's DART noise), so that every task appears equally
often in both splits and every ordered pair of digits is demonstrated. For each seed it clones OCN
(4 options, one per digit of S; T = 10) and the MoE baseline (the same network with
`hierarchy="moe"`) with `lerobot-train` on the induction recipe of `results/dial_memoryless/`
(`INDUCTION_RECIPE`: the `dial_keys` encoder, unit-std continuous actions, memoryless options, the
usage balance, lr 1e-3 dropped tenfold at `--lr-decay-step`, episode windows of `--window-size`
frames whose few longer episodes train on their first window; OCN alone adds the termination cost,
which MoE, whose options last one step, has no use for). Each clone is the best of `--restarts`
seeds: every restart trains `--select-step` steps, and the one whose actions fit the validation
split's demonstrations best (lowest NLL; no digit label read) trains on to `--steps`
(`runs.Restarts`), because the recipe splits the digits on some seeds only: on its first five
seeds the two likeliest at step 2,000 were the two that split, and on six more the likeliest of
three gained about a third of what a choice told the labels gains (results/dial_memoryless/). It scores each OCN
clone with `ocn-eval` on the validation split (F1@1, NMI, free-run success on the 2-digit PINs,
option x digit table), then finetunes a fresh controller over each clone's frozen options with
`ocn-finetune` on the 3-digit PINs of `--tasks`, under the sparse and the dense reward, every run
on the same env-frame budget and at the discount `DIAL_GAMMA` (`--gamma`), not the paper's 0.97.
The paper compares OCN with OMPN and MoE; OMPN has no option pool to finetune, and flat PPO over 9
continuous torques is not in its figure, so MoE is the baseline here.

`--split affine` trains the clones another way (`tools/reproduce/taught.py`): taught the split of a
switching affine policy fitted to the recording without its labels, then the paper's loss, kept only
where it does not raise the validation NLL; its results go to results/dial_affine.*.

The default finetuning PINs, 124, 481 and 842: three tasks as in figure 6; no digit directly
follows itself (as the env's random PINs: the demonstrations never press one key twice in a row);
each starts on a different digit, all four digits are used, and the three hold six different
ordered digit pairs, so no two tasks share a transition and each must chain its own three skills.

Writes results/dial.json (provenance, every run, the imitation scores per seed, the finetuning
summary and curves, the checks), results/dial.md (the checks with measured values, the imitation
table, the values at the budget) and results/dial.png (figure 6's form: success per PIN and the
mean return against env frames, each method's mean over seeds with its min-max band), rewritten
after every finished run. The checks: OCN imitation F1@1 >= 0.9, NMI >= 0.8 and 2-digit success
>= 0.8 (means over seeds); OCN's 3-digit success under the sparse reward >= 0.7 at the budget, and
above MoE's. Datasets, trained runs, their scores and finetuning runs are reused, so an interrupted
reproduction continues; a run folder made with other settings is refused.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from envs.dial.task import DEFAULT_DIGITS, parse_pin_list, pin_code
from policies.ocn import OCNConfig
from tools.bench import RESULTS
from tools.reproduce import finetune, imitation, taught
from tools.reproduce.finetune import Method, Setting
from tools.reproduce.report import checks_table, machine_words, provenance, train_time_words, write_result_files
from tools.reproduce.runs import Restarts, TrainedRun, TrainSettings, evaluate_run, record_dataset, train_best_restart

DATA = "dial2"
REPO_ID = f"local/{DATA}"
TWO_DIGIT_PINS = ",".join(pin_code((a, b)) for a in DEFAULT_DIGITS for b in DEFAULT_DIGITS if a != b)
N_OPTIONS = len(DEFAULT_DIGITS)
FINETUNE_PINS = "124,481,842"
# PPO's discount per 40 ms env step. The expert dials a 2-digit PIN in a median of 59 steps
# (results/bench_dial.md), so a 3-digit PIN takes about 90, and the paper's 0.97 discounts its sparse
# reward to 0.97^90 ~ 0.06 at the first decision; results/dial_keys measured 0.34 success at 0.97
# and 0.97 at 0.995 over the same options.
DIAL_GAMMA = 0.995
_FINETUNED = {method.key: method for method in finetune.METHODS}
METHODS = (_FINETUNED["ocn"], _FINETUNED["moe"])
# `--policy.*` values every Dial model needs (README, "OCN on Dial"): `tools.fast_imitation`'s Dial defaults.
DIAL_POLICY = {"obs_encoder": "identity", "action_type": "continuous", "skip_long_episodes": "true"}
# The clones' recipe over DIAL_POLICY: the first under which induction split the digits, on two seeds
# of five (results/dial_memoryless/), with the rate dropped before the collapse seen there at 1e-3.
INDUCTION_RECIPE = {**DIAL_POLICY, "obs_encoder": "dial_keys", "log_std_min": 0.0, "log_std_max": 0.0,
                    "option_memory": "false", "inference_mode": "greedy", "lr_schedule": "step"}
# Settings of one method's clones only: the cost of hand-overs means nothing where every option lasts one step.
METHOD_RECIPE = {"ocn": {"termination_cost": 1.0}, "moe": {}}
USAGE_BALANCE = 1.0
# The clones' rate before and the factor after the drop (OCNConfig's defaults, which the recipe keeps).
LR, DECAY = OCNConfig.optimizer_lr, OCNConfig.lr_decay_factor
# Imitation scores of the OCN clones reported per seed, with their column names.
SCORES = {"f1_tol0": "F1@0", "f1_tol1": "F1@1", "align_acc": "align", "nmi": "NMI",
          "mean_success_rate": "2-digit success", "diagonal_mean": "option x digit diagonal"}


def train_settings(args: argparse.Namespace) -> TrainSettings:
    """The clones' `lerobot-train` settings from the command line."""
    return TrainSettings(args.steps, args.batch_size, args.window_size, args.num_workers, args.threads,
                         {"controller_lr_scale": args.controller_lr_scale, **INDUCTION_RECIPE,
                          "lr_decay_step": args.lr_decay_step})


def dial_data(args: argparse.Namespace) -> Path:
    """The 2-digit demonstrations in the workdir, recorded on first use."""
    data = args.workdir / DATA
    record_dataset(data, TWO_DIGIT_PINS, REPO_ID, args.episodes_per_task, args.data_seed, env="dial")
    return data


def clone_dir(args: argparse.Namespace, method: Method, seed: int) -> Path:
    suffix = taught.study_suffix(args, method) if taught_split(args) else finetune.clone_study_suffix(args, method)
    return args.workdir / "clone" / DATA / f"{method.key}{suffix}" / f"seed{seed}"


def taught_split(args: argparse.Namespace) -> bool:
    """Whether the clones are taught the switching affine policy's split (`--split affine`)."""
    return getattr(args, "split", "induced") == "affine"


def clone_overrides(args: argparse.Namespace, method: Method) -> dict[str, Any]:
    """The `--policy.*` settings of the method's clones over their training settings: the pool, the
    method's own recipe (taught or induced) and the study-wide settings that also name the clone's
    folder (`clone_dir`)."""
    recipe = taught.taught_overrides(method) if taught_split(args) else METHOD_RECIPE[method.key]
    return {"n_options": N_OPTIONS, "temperature": 10.0, **(method.overrides or {}), **recipe,
            **finetune.clone_overrides(args, method)}


def clone(args: argparse.Namespace, data: Path, method: Method, seed: int) -> tuple[TrainedRun, dict[str, Any] | None]:
    """The method's behaviour-cloned checkpoint for one seed (trained unless done before) and how it was
    chosen: among its restarts (None with one restart), or with `--split affine` also between the
    taught and the continued model (`taught.taught_clone`)."""
    if taught_split(args):
        labels = taught.option_labels(args, data, N_OPTIONS)
        return taught.taught_clone(args, taught.taught_settings(args, DIAL_POLICY, labels), data, REPO_ID,
                                   clone_dir(args, method, seed), seed, clone_overrides(args, method),
                                   restarts_of(args))
    return train_best_restart(train_settings(args), data, REPO_ID, clone_dir(args, method, seed), seed,
                              clone_overrides(args, method), restarts_of(args))


def restarts_of(args: argparse.Namespace) -> Restarts:
    """The restarts each clone is chosen from (`--restarts`, `--select-step`)."""
    return Restarts(args.restarts, args.select_step)


def restart_words(choice: dict[str, Any] | None) -> str:
    """The imitation table's cell on a clone's restarts: the chosen seed, then each restart's
    validation NLL at the choice."""
    if choice is None:
        return "one run"
    nlls = ", ".join(f"{r['seed']}: {r['val_nll']:.3f}" for r in choice["restarts"])
    return f"{choice['chosen_seed']} ({nlls})"


def restarts_time_words(choice: dict[str, Any] | None) -> str:
    """The imitation table's cell on the training wall seconds of all of a clone's restarts, the
    restarts that lost included."""
    if choice is None:
        return "one run"
    return "not timed" if choice["train_wall_s"] is None else f"{choice['train_wall_s']:.0f}"


def imitation_summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and std over seeds of each imitation score, and the lowest 2-digit success of any PIN."""
    if not records:
        return {}
    values = {key: np.array([r["scores"][key] for r in records], dtype=float) for key in SCORES}
    return {
        "seeds": [r["seed"] for r in records],
        **{key: {"mean": float(v.mean()), "std": float(v.std())} for key, v in values.items()},
        "success_rate_min": float(min(min(r["scores"]["success_rate"].values()) for r in records)),
    }


def must_show(imitated: dict[str, Any], summary: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The issue's checks, each with the measured value and whether it holds; a check whose runs
    have not finished yet is left out."""
    checks = []
    if imitated:
        for key, bar in (("f1_tol1", 0.9), ("nmi", 0.8), ("mean_success_rate", 0.8)):
            value = imitated[key]["mean"]
            checks.append({"check": f"OCN imitation: {SCORES[key]} >= {bar}", "value": value, "holds": value >= bar})
    ours = finetune.budget_value(summary, "OCN", "sparse", "success")
    if ours is not None:
        checks.append({"check": "OCN, sparse: 3-digit success >= 0.7", "value": ours, "holds": ours >= 0.7})
        theirs = finetune.budget_value(summary, "MoE", "sparse", "success")
        if theirs is not None:
            checks.append({"check": f"sparse: MoE's 3-digit success below OCN's ({ours:.3f}) at the same budget",
                           "value": theirs, "holds": theirs < ours})
    return checks


def selection_words(settings: dict[str, Any]) -> str:
    """How each seed's clone was chosen among its restarts (one run: no choice)."""
    if settings["restarts"] == 1:
        return "one run per seed (no restarts)"
    return f"the best of {settings['restarts']} restarts by validation NLL at step {settings['select_step']}"


def markdown(result: dict[str, Any]) -> str:
    """The human-readable results file."""
    settings = finetune.study_settings(result)
    labels = settings["tasks"].split(",")
    taught_run = settings.get("split") == "affine"
    lines = [
        f"# Dial: skills from 2-digit PINs, finetuned on {', '.join(labels)}",
        "",
        f"Written by `{result['command']}` on {machine_words(result['machine'])}, "
        f"{result['date']}. Demonstrations: the 12 two-digit PINs over 1, 2, 4, 8, "
        f"{settings['episodes_per_task']} each; clones: `lerobot-train` on {imitation.loading_words(settings)}, "
        f"{settings['steps']} steps of {settings['batch_size']} windows of {settings['window_size']} frames, longer "
        f"episodes cut to their first, {N_OPTIONS} options, T = 10, {clone_recipe_words(settings)}, "
        f"{selection_words(settings)}; "
        f"imitation scores: `ocn-eval` on the validation split ({settings['rollouts']} env episodes per PIN and "
        f"per option-table cell); finetuning: `ocn-finetune`, {settings['frames']} env frames per run, "
        f"{settings['envs']} envs, entropy bonus {settings['entropy']:g}, discount {settings['gamma']:g}. "
        f"Values at the budget are the mean of each run's last {finetune.FINAL_ROWS} PPO "
        f"iterations, then mean (std) over seeds. Runs finished: {result['runs_finished']} of "
        f"{result['runs_planned']}; wall time of this invocation {result['wall_s'] / 60:.0f} min.",
        "",
        *([taught.labels_words(result["option_labels"]), ""] if result.get("option_labels") else []),
        "## Checks",
        "",
        *checks_table(result["must_show"]),
        "",
        "## Imitation: OCN clones on the validation split",
        "",
        "| seed | restart chosen (val NLL of each) | " + ("val NLL taught / continued: kept | " if taught_run else "")
        + " | ".join(SCORES.values())
        + " | success per PIN | train s of the chosen restart | train s of all restarts |",
        "|---|---|" + ("---|" if taught_run else "") + "---|" * len(SCORES) + "---|---|---|",
    ]
    for record in result["imitation"]:
        scores = record["scores"]
        per_pin = ", ".join(f"{pin} {rate:.2f}" for pin, rate in scores["success_rate"].items())
        cells = " | ".join(f"{scores[key]:.3f}" for key in SCORES)
        kept = f"{taught.guard_words(record['continuation'])} | " if taught_run else ""
        lines.append(f"| {record['seed']} | {restart_words(record['restarts'])} | {kept}{cells} | {per_pin} | "
                     f"{train_time_words(record)} | {restarts_time_words(record['restarts'])} |")
    lines += [
        "",
        "## Finetuning at the budget",
        "",
        *finetune.budget_table(result["summary"], labels),
        "",
        f"Curves: `{results_name(settings.get('split', 'induced'))}.png` (mean and min-max over seeds).",
        "",
    ]
    return "\n".join(lines)


def clone_recipe_words(settings: dict[str, Any]) -> str:
    """How the clones learned their split, for the results file's opening paragraph."""
    if settings.get("split") == "affine":
        return (f"taught the labels of a switching affine policy fitted without subtask labels "
                f"(`tools.affine_segmentation`, fit seed {settings['segmentation_seed']}) at lr {LR:g} (OCN's "
                f"terminations weighted {taught.TAUGHT_TERMINATION_WEIGHT:g}), then {settings['continue_steps']} "
                f"steps of the paper's loss at lr {settings['continue_lr']:g}, the continued model kept where its "
                f"validation NLL is not higher")
    return (f"the induction recipe (lr {LR:g}, {LR * DECAY:g} from step {settings['lr_decay_step']}), usage balance "
            f"{settings['usage_balance']:g}")


def write_results(args: argparse.Namespace, data: Path, imitated: list[dict[str, Any]], runs: list[dict[str, Any]],
                  planned: int, wall_s: float) -> dict[str, Any]:
    """`results/dial.{json,md,png}` (`dial_affine.*`) from the runs finished so far on the recording `data`."""
    labels = args.tasks.split(",")
    summary = finetune.summarise(runs, labels, METHODS)
    imitation_scores = imitation_summary(imitated)
    result = {
        **provenance(args),
        "runs_finished": len(runs),
        "runs_planned": planned,
        **({"option_labels": taught.labels_report(args, data)} if taught_split(args) else {}),
        "imitation": imitated,
        "imitation_summary": imitation_scores,
        "summary": summary,
        "must_show": must_show(imitation_scores, summary),
        "runs": runs,
        "wall_s": round(wall_s, 1),
    }
    stem = write_result_files(args.results, results_name(args.split), result, markdown(result))
    if summary:
        title = f"Finetuning in Dial ({args.tasks}) over skills from 2-digit PINs: mean and min-max over seeds"
        finetune.plot(summary, METHODS, labels, "min-max", title, stem.with_suffix(".png"))
    return result


def results_name(split: str) -> str:
    """The results files' stem and the finetuning runs' setting: `dial`, or `dial_affine` for `--split affine`."""
    return "dial_affine" if split == "affine" else "dial"


def use_taught_recipe(args: argparse.Namespace) -> None:
    """The study-wide settings of taught clones: the packed view (which holds the labels) and no usage
    balance (the induction recipe's, which a taught split has no use for); another balance is refused."""
    if args.usage_balance not in (0.0, USAGE_BALANCE):
        raise SystemExit(f"--usage-balance {args.usage_balance:g} is the induction recipe's; the clones of "
                         "--split affine are taught their split and train without it.")
    args.usage_balance, args.window_start = 0.0, "packed"


def reproduce_dial(args: argparse.Namespace) -> int:
    """Every planned run in turn, seed by seed: clone each method, score OCN's clone, finetune it
    under each reward; the results files are rewritten after every finetuning run."""
    started = time.perf_counter()
    args.tasks = ",".join(pin_code(pin) for pin in parse_pin_list(args.tasks))
    methods = finetune.chosen_methods(args, METHODS)
    restarts_of(args).check(args.steps)  # before the recording, which takes minutes
    if taught_split(args):
        use_taught_recipe(args)
    setting = Setting(results_name(args.split), ((DATA, TWO_DIGIT_PINS),), N_OPTIONS, args.tasks)
    data = dial_data(args)
    planned = len(methods) * len(args.rewards) * args.seeds
    imitated: list[dict[str, Any]] = []
    runs: list[dict[str, Any]] = []
    result: dict[str, Any] = {}
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for method in methods:
            trained, choice = clone(args, data, method, seed)
            if method.key == "ocn":
                folder = clone_dir(args, method, seed)
                chosen = choice if taught_split(args) else {"restarts": choice}
                imitated.append(evaluate_run(folder, trained, data, REPO_ID, args.rollouts,
                                             {"method": method.name, "seed": seed, **chosen}))
            for reward in args.rewards:
                runs.append(finetune.finetune_run(args, setting, method, reward, seed, [trained]))
                result = write_results(args, data, imitated, runs, planned, time.perf_counter() - started)
    print(markdown(result))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `dial` subcommand."""
    parser = sub.add_parser("dial", help="Dial: OCN and MoE cloned from 2-digit PINs, finetuned on 3-digit PINs",
                            formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    finetune.add_finetune_arguments(parser, METHODS, 500_000, gamma=DIAL_GAMMA)
    parser.add_argument("--tasks", default=FINETUNE_PINS, help="comma-separated PINs to finetune on")
    parser.add_argument("--rollouts", type=int, default=100,
                        help="ocn-eval env episodes per 2-digit PIN and per option-table cell")
    imitation.add_training_arguments(
        parser, batch_size=32, window_size=120, episodes_per_task=500,
        window_help="frames per episode window; longer episodes (under 2%% of the 2-digit demos) train on their first",
        episodes_help="12 PINs x 500: 6000 demonstrations in all",
    )
    imitation.add_window_start_argument(parser)
    parser.add_argument("--lr-decay-step", type=int, default=3000,
                        help="lerobot-train step from which the clones train at a tenth of the rate")
    parser.add_argument("--restarts", type=int, default=3,
                        help="seeds tried per clone; the one with the lowest validation NLL at --select-step trains "
                             "on (restart j of seed s trains with seed s * restarts + j)")
    parser.add_argument("--select-step", type=int, default=2000,
                        help="lerobot-train step at which the restarts of a clone are compared")
    taught.add_arguments(parser)
    parser.add_argument("--results", type=Path, default=RESULTS)
    # No settling phase: the recipe's termination cost is paid from the first step.
    parser.set_defaults(func=reproduce_dial, usage_balance=USAGE_BALANCE, settle_steps=0)
