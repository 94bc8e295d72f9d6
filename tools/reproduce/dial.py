"""`ocn-reproduce dial`: skills cloned from 2-digit PINs, reused by PPO on 3-digit PINs (paper section
4.2, figure 6).

The recording: expert demonstrations of every 2-digit PIN over the digits 1, 2, 4, 8 with no digit
twice (12 PINs, 500 each: every ordered pair of digits, equally often in both splits). The clones,
per seed: OCN and MoE (`--policy.hierarchy=moe`), each a plain `lerobot-train` run of 5,000 steps of
32 episodes, with one of two splits (`--split`):

- `affine` (the default): the policy's Dial recipe, with no flag. Its options are taught the split of
  a switching affine policy fitted to the recording without its labels, then trained on the paper's
  loss at 0.03x the rate over the final 20% (`OCNConfig.recipe`). Writes `results/dial.{json,md,png}`.
- `induced`: the paper's path, `--policy.recipe=paper` with the 4 options of the digits (the paper
  recipe's count is Craft's 3): the options must split the digits from the NLL alone. It writes no
  headline set: `--results` is required and may not be the headline folder; the files are
  `dial_induced.*`.

OCN's clone is scored by `ocn-eval` on the validation split (F1@1, NMI, free-run success on the
2-digit PINs, option x digit table; 100 env episodes per PIN and per cell: Dial's physics is slow).
Each clone's frozen options then get a fresh controller trained by plain `ocn-finetune` on the
3-digit PINs 124, 481 and 842 under the sparse and the dense reward, 500,000 env frames, 64 envs.
The PINs: no digit follows itself (as in the recording), each starts on a different digit, all four
digits are used and the three hold six different ordered pairs, so no two share a transition. The
paper compares OCN with OMPN and MoE; OMPN has no option pool and flat PPO over 9 continuous torques
is not in its figure, so MoE is the baseline.

PPO's discount is 0.995 (`ocn-finetune --gamma`, a PPO setting, not the recipe's): a 3-digit PIN
takes about 90 steps of 40 ms (the expert's median for two digits is 59, results/bench_dial.md), so
the paper's 0.97 discounts the sparse reward to about 0.06 at the first decision; over the same
options, results/archive/dial_keys measured 0.34 success at 0.97 and 0.97 at 0.995.

Per seed on the 2-core VM (from results/archive/dial_induced_2026-12-06 and dial_affine_2026-12-06):
two clones of 20-35 min
(plus the affine fit, about 6 min, if the policy makes it per run), 8 min of scoring, and four PPO
runs of 8-18 min (OCN about 1,900 frames/s, MoE 630): about 2 hours, 6 CPU-hours for three seeds.

The checks, with the bars of results/archive/dial_affine_2026-12-06: OCN's imitation F1@1 >= 0.9, NMI >= 0.8 and
2-digit success >= 0.8 (means over seeds); OCN's sparse 3-digit success >= 0.7 at the budget, and
MoE's below it.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import RESULTS
from lerobot_policy_ocn.tools.reproduce import curves, finetune
from lerobot_policy_ocn.tools.reproduce.clones import Demos, Size, clone, record, scored, size_of
from lerobot_policy_ocn.tools.reproduce.finetune import (
    CLONED, Setting, add_ppo_arguments, budget_table, finetune_run, summarise,
)
from lerobot_policy_ocn.tools.reproduce.report import (
    check, checks_table, mean_std, origin_words, provenance, rates_cell, seconds_cell, write_results,
)

SIZE = Size(episodes_per_task=500, steps=5000, batch_size=32)
ROLLOUTS = 100
N_DIGITS = 4  # the options of the paper's Dial: one per digit of (1, 2, 4, 8)
SPLITS = {"affine": {}, "induced": {"recipe": "paper", "n_options": N_DIGITS}}
SETTINGS = {split: Setting(f"dial_{split}" if split != "affine" else "dial", (), "124,481,842", ("ocn", "moe"),
                           500_000, 64, 0.7, flags, ("--gamma", "0.995")) for split, flags in SPLITS.items()}
SCORES = {"f1_tol0": "F1@0", "f1_tol1": "F1@1", "align_acc": "align", "nmi": "NMI",
          "mean_success_rate": "2-digit success", "diagonal_mean": "option x digit diagonal"}
IMITATION_BARS = {"f1_tol1": 0.9, "nmi": 0.8, "mean_success_rate": 0.8}
# For `ocn-reproduce combine` (as `imitation.STUDIES`).
STUDIES = tuple(setting.name for setting in SETTINGS.values())
ROWS = {**finetune.ROWS, "imitation": ("seed",)}
VARYING = finetune.VARYING


def demos() -> Demos:
    """The 2-digit recording: every PIN over (1, 2, 4, 8) with no digit twice."""
    from lerobot_policy_ocn.envs.dial.task import DEFAULT_DIGITS, pin_code

    pins = ",".join(pin_code((a, b)) for a in DEFAULT_DIGITS for b in DEFAULT_DIGITS if a != b)
    return Demos("dial2", ("--env", "dial", "--tasks", pins))


def split_report(data: Path) -> dict[str, Any] | None:
    """The switching affine fit's report on the recording `data` (its cost, wall time and scores against
    the digits, read for the report only), shown above the checks. `lerobot_policy_ocn.ocn.taught` will give it;
    until then the results hold none."""
    return None


def checks(imitation: list[dict[str, Any]], summary: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The five checks (not run: their runs are not in the results)."""
    def mean(key: str) -> float | None:
        return mean_std([row["scores"][key] for row in imitation])["mean"] if imitation else None

    def success(method: str) -> float | None:
        row = summary.get(f"{method} | sparse")
        return None if row is None else row["at_budget"]["success"]["mean"]

    ours = success("ocn")
    return [*(check(f"OCN imitation: {SCORES[key]} >= {bar}", mean(key), lambda v, bar=bar: v >= bar)
              for key, bar in IMITATION_BARS.items()),
            check("OCN, sparse: 3-digit success >= 0.7", ours, lambda v: v >= 0.7),
            check("sparse: MoE's 3-digit success below OCN's", success("moe") if ours is not None else None,
                  lambda v: v < ours)]


def study(setting: Setting, imitation: list[dict[str, Any]], runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The results of these clones and runs: imitation summary, finetuning summary and the checks."""
    imitation = sorted(imitation, key=lambda row: row["seed"])
    runs = sorted(runs, key=lambda run: (run["seed"], list(CLONED).index(run["method"]), run["reward"]))
    summary = summarise(runs, setting.labels)
    scores = {key: mean_std([row["scores"][key] for row in imitation]) for key in SCORES} if imitation else {}
    return {"study": setting.name, "imitation": imitation, "imitation_summary": scores, "runs": runs,
            "summary": summary, "checks": checks(imitation, summary)}


def restudy(name: str, rows: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """The study made again from the rows of several results files (`ocn-reproduce combine`)."""
    setting = next(setting for setting in SETTINGS.values() if setting.name == name)
    return study(setting, rows["imitation"], rows["runs"])


def markdown(result: dict[str, Any]) -> str:
    """The results in words: the checks first, then the imitation table and the values at the budget."""
    settings, setting = result["settings"], SETTINGS[result["settings"]["split"]]
    lines = [
        f"# Dial: skills from 2-digit PINs ({settings['split']} split), finetuned on {setting.tasks}", "",
        f"{origin_words(result)} Demonstrations: the 12 two-digit PINs over 1, 2, 4, 8, "
        f"{settings['episodes_per_task']} each; clones: plain `lerobot-train`, {settings['steps']} steps of "
        f"{settings['batch_size']} episodes; "
        f"imitation scores: `ocn-eval` on the validation split ({settings['rollouts']} env episodes per PIN and per "
        f"option-table cell); finetuning: plain `ocn-finetune --gamma 0.995`, {settings['frames']:,} env frames, "
        f"{settings['envs']} envs.", "",
    ]
    if result.get("split_report"):
        lines += ["The switching affine fit: " + ", ".join(f"{key} {value}" for key, value in
                                                          result["split_report"].items()) + ".", ""]
    lines += ["## Checks", "", *checks_table(result["checks"]), "",
              "## Imitation: OCN's clones on the validation split", "",
              "| seed | " + " | ".join(SCORES.values()) + " | success per PIN | train s |",
              "|---|" + "---|" * len(SCORES) + "---|---|"]
    for row in result["imitation"]:
        scores = row["scores"]
        lines.append(f"| {row['seed']} | " + " | ".join(f"{scores[key]:.3f}" for key in SCORES)
                     + f" | {rates_cell(scores['success_rate'])} | {seconds_cell(row['train_wall_s'])} |")
    lines += ["", "## Finetuning at the budget", "", *budget_table(result["summary"], setting.labels), "",
              f"Curves: `{result['study']}.png` (mean and one std over seeds).", ""]
    return "\n".join(lines)


def write(results: Path, result: dict[str, Any]) -> None:
    setting = SETTINGS[result["settings"]["split"]]
    title = f"Dial ({result['settings']['split']} split): finetuning on {setting.tasks}, mean and std over seeds"
    write_results(results, result["study"], result, markdown(result),
                  lambda path: curves.plot(result["summary"], {m: finetune.NAMES[m] for m in setting.methods},
                                           setting.labels, title, path))


def results_folder(args: argparse.Namespace) -> Path:
    """Where this split's results go: `results/` for the affine default; a folder of their own for
    the induced split, which makes no headline set."""
    if args.split == "affine":
        return args.results or RESULTS
    if args.results is None or args.results.resolve() == RESULTS.resolve():
        raise SystemExit("ocn-reproduce dial --split induced writes no headline set: pass --results with a folder "
                         f"other than {RESULTS} (e.g. results/archive/dial_induced).")
    return args.results


def reproduce(args: argparse.Namespace) -> int:
    """Record the 2-digit PINs; per seed, clone each method, score OCN's clone, finetune under each reward;
    the results are rewritten after every finetuning run."""
    setting = dataclasses.replace(SETTINGS[args.split], demos=(demos(),))
    finetune.check_plan(args, setting)
    results, started = results_folder(args), time.perf_counter()
    settings = {**finetune.settings_of(args), "split": args.split, "rollouts": args.rollouts,
                "results": str(results)}
    data = record(args.workdir, setting.demos[0], size_of(args))
    imitation: list[dict[str, Any]] = []
    runs: list[dict[str, Any]] = []
    for seed, method in finetune.planned(args):
        if method == "ocn":
            model = CLONED["ocn"].with_flags(**setting.clone_flags)
            trained = clone(args.workdir, setting.demos[0], data, model, seed, size_of(args))
            imitation.append({"seed": seed, **scored(args.workdir, setting.demos[0], data, trained, args.rollouts)})
        for reward in args.rewards:
            runs.append(finetune_run(args, setting, method, reward, seed))
            result = {**provenance(args.argv, settings), "split_report": split_report(args.workdir / data.root),
                      **study(setting, imitation, runs), "wall_s": round(time.perf_counter() - started)}
            write(results, result)
    print(markdown(result))
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `dial` subcommand."""
    parser = sub.add_parser("dial", help="Dial: OCN and MoE cloned from 2-digit PINs, finetuned on 3-digit PINs",
                            description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--split", choices=tuple(SPLITS), default="affine",
                        help="affine: the policy's Dial recipe (headline results); induced: the paper's loss alone")
    add_ppo_arguments(parser, SETTINGS["affine"], SIZE)
    parser.add_argument("--rollouts", type=int, default=ROLLOUTS,
                        help="ocn-eval env episodes per 2-digit PIN and per option-table cell")
    parser.add_argument("--results", type=Path, default=None,
                        help=f"folder of the results files (affine: {RESULTS}; induced: required, not that one)")
    parser.set_defaults(func=reproduce)
