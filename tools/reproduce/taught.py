"""`ocn-reproduce dial --split affine`: clones taught a split found without labels, then the paper's loss.

Where the paper's loss alone rarely splits Dial's digits (results/dial_memoryless/), a switching affine
policy fitted to the demonstrations does, without reading a subtask label (`tools.affine_segmentation`,
results/dial_affine_labels/). This path of the reproduction fits it once on the recording, writes its
labels into a labelled packed view, and trains each clone in two `lerobot-train` runs:

1. taught (`--policy.taught_options=true`, `OCNPolicy.labelled_forward`): `--steps` steps at a constant
   lr of 1e-3, OCN's terminations weighted `TAUGHT_TERMINATION_WEIGHT`; MoE, given the same labels,
   learns its per-step choice;
2. continued on the paper's loss (no labels) for `--continue-steps` at `--continue-lr`.

The paper's loss sharpened the taught split on two seeds of four and broke it on one, whose validation
NLL rose from 8.45 to 9.20 (results/dial_affine_labels/). So the continued model is kept only if it
clones the validation demonstrations at least as well as the taught one (`validation_nll`, which reads
no label); the choice is kept in the clone's `continuation.json`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from tools.reproduce import finetune
from tools.reproduce.finetune import Method
from tools.reproduce.runs import (
    Restarts,
    TrainedRun,
    TrainSettings,
    continue_policy,
    same_training,
    train_best_restart,
)

# The taught clones' settings over Dial's base policy (`tools.reproduce.dial.DIAL_POLICY`): those of
# results/dial_affine_labels/ (recurrent options, the dial_keys encoder, unit-std actions).
TAUGHT_RECIPE = {"obs_encoder": "dial_keys", "log_std_min": 0.0, "log_std_max": 0.0, "inference_mode": "greedy",
                 "window_start": "packed", "lr_schedule": "constant", "taught_options": True}
# Terminations that learn the label changes at five times the weight of the other terms fired where
# they should on the ground-truth split (results/dial_split_given/); MoE has none.
TAUGHT_TERMINATION_WEIGHT = 5.0
METHOD_TAUGHT = {"ocn": {"taught_termination_weight": TAUGHT_TERMINATION_WEIGHT}, "moe": {}}
# The continuation's rate. At 1e-4 it diverged through `lerobot-train` on both seeds of the first full-size
# run (gradient norms up to 9e7, validation NLL 8.45 to 9.6). On both taught models about one batch in
# twenty has a gradient norm over ten times the median; the worst comes from one episode, nearly all of it
# on the options' weights (results/dial_affine_gradient_spikes/). A lower rate bounds what each spike moves: at
# 3e-5 the continuation lowered the validation NLL on seeds 1 and 3 and ended just above the taught model's
# on seed 2, which the guard then keeps (results/dial_affine.md).
CONTINUE_LR = 3e-5
# The files of a fit's folder (`labels_folder`).
LABELS_FILE, REPORT_FILE = "labels.npz", "report.json"
# Validation episodes that the continuation's guard scores (`Restarts.val_episodes`' count).
GUARD_EPISODES = Restarts.val_episodes


def option_labels(args: argparse.Namespace, data: Path, n_options: int) -> Path:
    """The labels of the recording's training split (`tools.affine_segmentation`, fit seed
    `--segmentation-seed`), fitted on first use into their own folder (`ocn_data.training_view.derived_dataset`):
    a fit made with other settings or on another recording is made again, and reproductions run side by
    side wait for one fit."""
    from ocn_data.training_view import derived_dataset
    from tools import affine_segmentation

    fit = ["--n-options", str(n_options), "--seed", str(args.segmentation_seed)]

    def write(folder: Path) -> None:
        folder.mkdir(parents=True)
        print(f"fitting the switching affine policy on {data} (about 6 min on 2 cores)", flush=True)
        affine_segmentation.main(["--root", str(data), "--out", str(folder / LABELS_FILE),
                                  "--report", str(folder / REPORT_FILE), *fit])

    args.workdir.joinpath("affine_labels").mkdir(parents=True, exist_ok=True)
    return derived_dataset(data, labels_folder(args, data), {"fit": fit}, write, marker="made_by.json") / LABELS_FILE


def labels_folder(args: argparse.Namespace, data: Path) -> Path:
    """Where the fit on the recording `data` lives: a folder of the workdir's `affine_labels/` holding
    the labels (`LABELS_FILE`) and the fit's report (`REPORT_FILE`)."""
    return args.workdir / "affine_labels" / f"{data.name}_seed{args.segmentation_seed}"


def labels_report(args: argparse.Namespace, data: Path) -> dict[str, Any] | None:
    """The switching affine fit's report (`tools.affine_segmentation --report`) for the results file:
    its cost, wall time and scores against the ground truth (evaluation only); None before the fit."""
    path = labels_folder(args, data) / REPORT_FILE
    if not path.exists():
        return None
    report = json.loads(path.read_text())
    return {key: report[key] for key in ("seed", "cost", "start_costs", "split_and_merge_moves_kept", "label_share",
                                         "train_scores", "val_scores", "seconds")}


def labels_words(report: dict[str, Any]) -> str:
    """The results file's sentence on the fitted labels."""
    val = report["val_scores"]
    return (f"The switching affine fit (seed {report['seed']}) ended at cost {report['cost']:,.0f} (best random start "
            f"{min(report['start_costs']):,.0f}, {report['split_and_merge_moves_kept']} split-and-merge moves kept) in "
            f"{report['seconds']:.0f} s; against the digits, read for this report only, its labels of the validation "
            f"split score F1@1 {val['f1_tol1']:.3f}, align {val['align_acc']:.3f} and NMI {val['nmi']:.3f}.")


def taught_settings(args: argparse.Namespace, base: dict[str, Any], labels: Path) -> TrainSettings:
    """The taught runs' `lerobot-train` settings: `base` (Dial's policy) under `TAUGHT_RECIPE`, on the
    packed view that holds `labels`."""
    return TrainSettings(args.steps, args.batch_size, args.window_size, args.num_workers, args.threads,
                         {"controller_lr_scale": args.controller_lr_scale, **base, **TAUGHT_RECIPE},
                         option_labels=labels)


def taught_overrides(method: Method) -> dict[str, Any]:
    """The method's own settings of its taught run."""
    return METHOD_TAUGHT[method.key]


def continuation_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The continued run's settings over the taught run's config: the paper's loss at `--continue-lr`."""
    return {"taught_options": False, "optimizer_lr": args.continue_lr}


def taught_clone(args: argparse.Namespace, settings: TrainSettings, data: Path, repo_id: str, run_dir: Path,
                 seed: int, overrides: dict[str, Any], restarts: Restarts) -> tuple[TrainedRun, dict[str, Any]]:
    """The clone in `run_dir`: taught (the best of `restarts`), then continued, and of the two the continued
    one unless its validation NLL is higher; returns it and the record of both choices: the restarts'
    (None with one) and the continuation's."""
    taught, restart_choice = train_best_restart(settings, data, repo_id, run_dir, seed, overrides, restarts)
    continued = continue_policy(settings, taught, data, repo_id, run_dir / "continued", seed, args.continue_steps,
                                continuation_overrides(args))
    guard = continuation_guard(run_dir / "continuation.json", taught, continued, data)
    return (continued if guard["kept"] == "continued" else taught), {"restarts": restart_choice,
                                                                    "continuation": guard}


def continuation_guard(path: Path, taught: TrainedRun, continued: TrainedRun, data: Path) -> dict[str, Any]:
    """Both models' validation NLL (first `GUARD_EPISODES` episodes) and which is kept, written to `path`
    and reused while both commands stay the same."""
    if path.exists():
        guard = json.loads(path.read_text())
        if same_training(guard["taught_command"], taught.command) and \
                same_training(guard["continued_command"], continued.command):
            return guard
    from tools.episode_parsing import validation_nll

    nlls = {name: validation_nll(run.checkpoint, data, GUARD_EPISODES)
            for name, run in (("taught", taught), ("continued", continued))}
    guard = {"val_episodes": GUARD_EPISODES, "taught_val_nll": nlls["taught"], "continued_val_nll": nlls["continued"],
             "kept": "continued" if nlls["continued"] <= nlls["taught"] else "taught",
             "taught_command": taught.command, "continued_command": continued.command}
    path.write_text(json.dumps(guard, indent=2) + "\n")
    return guard


def guard_words(guard: dict[str, Any]) -> str:
    """The imitation table's cell on the continuation: both validation NLLs and the model kept."""
    return f"{guard['taught_val_nll']:.3f} / {guard['continued_val_nll']:.3f}: {guard['kept']}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `--split affine`."""
    parser.add_argument("--split", choices=("induced", "affine"), default="induced",
                        help="how the clones' options split the digits: induced by the paper's loss (the "
                             "induction recipe), or taught the labels of a switching affine policy fitted without "
                             "subtask labels, then the paper's loss (tools/reproduce/taught.py); affine writes "
                             "results/dial_affine.*")
    parser.add_argument("--segmentation-seed", type=int, default=0,
                        help="with --split affine: the seed of the switching affine fit")
    parser.add_argument("--continue-steps", type=int, default=1000,
                        help="with --split affine: steps on the paper's loss after the taught ones")
    parser.add_argument("--continue-lr", type=float, default=CONTINUE_LR,
                        help="with --split affine: the constant learning rate of those steps")


def study_suffix(args: argparse.Namespace, method: Method) -> str:
    """Folder-name suffix of a taught clone: `_taught_affine`, then the study-wide settings' suffix."""
    return "_taught_affine" + finetune.clone_study_suffix(args, method)
