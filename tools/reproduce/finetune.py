"""`ocn-reproduce s1` and `ocn-reproduce s2`: reusing skills with PPO (paper section 4.1, figures 4-5).

S1: OCN, MoE, HIL and compILE are cloned from the S1 demonstrations ({AC, CD, DA}); their options
are frozen and a fresh controller is trained by PPO on ADC, CAD and DCA. OMPN, cloned too, has no
options: its RL form finetunes the whole network on primitive actions (see `tools.ompn_rl`), so it
has nothing to pool and, as in the paper, takes part in S1 only. S2: one model is cloned from
{AB, BA} and one from {CD, DC}; their option pools are merged and the controller learns BADC, ACBD and
CABD. compILE's options are its frozen decoder given each of its categorical latents (its RL form,
see `ocn-finetune`), so S2 merges the two decoders' latent pools as it merges OCN's options.
Flat PPO learns each setting from scratch on the primitive actions, as the reference that shows
why skills matter. Every method gets the same env-frame budget, each reward (sparse, dense) and
each seed; the learning curves and the issue's checks go to `results/finetune_{s1,s2}.{json,md,png}`,
rewritten after every finished run. Finished runs are reused; a run folder made by another command
is refused.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tools import console_script
from tools.bench import RESULTS
from tools.ocn_finetune import FRESH_CONTROLLER_TEMPERATURE, STATE_FILE
from tools.ppo import PPOConfig
from tools.reproduce import imitation
from tools.reproduce.report import checks_table, origin_words, over_seeds, provenance, write_result_files
from tools.reproduce.runs import (Settling, TrainedRun, TrainSettings, record_dataset, same_training, settings_suffix,
                                  settle_policy, train_policy)

GRID_POINTS = 40  # env-frame grid the seeds' curves are interpolated onto before averaging
DEFAULT_ENVS = 64  # envs per PPO iteration unless --envs says otherwise (the paper does not give its number)
FINAL_ROWS = 3  # PPO iterations averaged for the value "at the budget" (one iteration is noisy)


@dataclass(frozen=True)
class Setting:
    """One finetuning experiment: the demonstrations its skills come from and the new tasks."""

    name: str
    demos: tuple[tuple[str, str], ...]  # (dataset folder, its tasks), one cloned model each
    n_options: int  # options per cloned model
    tasks: str


@dataclass(frozen=True)
class Method:
    """How a method gets its skills: cloned as `--policy.type=policy_type` with these `--policy.*`
    overrides, or none (flat); `pools` says whether the skills of several clones can be merged, as
    S2 needs."""

    key: str
    name: str
    overrides: dict[str, Any] | None
    policy_type: str = "ocn"
    pools: bool = True


SETTINGS = {
    "s1": Setting("s1", (("craft_s1", imitation.S1_TASKS),), 3, "ADC,CAD,DCA"),
    "s2": Setting("s2", (("craft_s2_ab", "AB,BA"), ("craft_s2_cd", "CD,DC")), 2, "BADC,ACBD,CABD"),
}
METHODS = (
    Method("ocn", "OCN", {}),
    Method("moe", "MoE", {"hierarchy": "moe"}),
    Method("hil", "HIL", {"hierarchy": "hil"}),
    Method("compile", "compILE", {}, "compile"),
    Method("ompn", "OMPN", {}, "ompn", pools=False),
    Method("flat", "flat PPO", None),
)
REWARDS = ("sparse", "dense")
BASELINES = tuple(method.name for method in METHODS if method.key != "ocn")
# The value of each study setting that results files written before it existed leave out.
SETTING_DEFAULTS = {"window_start": imitation.STUDY_DEFAULTS["window_start"], "usage_balance": 0.0,
                    "switch_cost": imitation.STUDY_DEFAULTS["switch_cost"],
                    "expected_nll_weight": imitation.STUDY_DEFAULTS["expected_nll_weight"],
                    **imitation.UNSETTLED, **imitation.RECORDING_DEFAULTS, "entropy": PPOConfig.entropy_coef,
                    "gamma": PPOConfig.gamma}


def study_settings(result: dict[str, Any]) -> dict[str, Any]:
    """A finetuning results file's settings, with the defaults of settings added after it was written
    (the pool size: its Craft setting's; Dial's files say theirs)."""
    setting = SETTINGS.get(result.get("setting"))
    pool = {} if setting is None else {"n_options": setting.n_options}
    return {**SETTING_DEFAULTS, **pool, **result["settings"]}


def clone_settings(args: argparse.Namespace, setting: Setting, method: Method) -> tuple[TrainSettings, dict[str, Any]]:
    """The `lerobot-train` settings and `--policy.*` overrides of the method's clones.

    The OCN family gets the setting's number of options and T = 10; compILE and OMPN train with their
    own defaults (`CompILEConfig`: 4 segments, 32 categorical latents, lr 1e-4; `OMPNConfig`: 3 slots
    of width 128, lr 1e-3, gradient clip 0.2) on the same data, steps, batch and windows, without
    OCN's controller learning-rate scale, which they have no use for.
    """
    settings, study = imitation.train_settings(args), clone_overrides(args, method)
    if method.policy_type != "ocn":
        return replace(settings, policy={}, policy_type=method.policy_type), {**(method.overrides or {}), **study}
    return settings, {"n_options": setting.n_options, "temperature": 10.0, **(method.overrides or {}), **study}


def balance_override(args: argparse.Namespace) -> dict[str, float]:
    """`--policy.usage_balance` of the OCN-family clones (OCN, MoE, HIL alike), spelled out only
    when it is not the paper's loss, so that runs made before the option existed keep their command."""
    return {"usage_balance": args.usage_balance} if args.usage_balance else {}


def cost_overrides(args: argparse.Namespace, method: Method) -> dict[str, float]:
    """`--policy.switch_cost` and `--policy.expected_nll_weight` of OCN's clones (`--switch-cost`,
    `--expected-nll-weight`), each spelled out only when set. Both are part of OCN's imitation recipe
    (imitation-s1 chose them for OCN): MoE and HIL choose at every step or after a fixed length, so
    there are no terminations whose choice the switch cost could steer, and their clones keep the
    recipe of every study before these options."""
    if method.key != "ocn":
        return {}
    costs = {key: getattr(args, key, imitation.STUDY_DEFAULTS[key]) for key in ("switch_cost", "expected_nll_weight")}
    return {key: cost for key, cost in costs.items() if cost}


def loading_override(args: argparse.Namespace) -> dict[str, str]:
    """`--policy.window_start` of every clone, spelled out only for the packed view (`--window-start
    packed`), so that runs made before the option existed keep their command. Studies without the
    option load windows."""
    start = getattr(args, "window_start", imitation.STUDY_DEFAULTS["window_start"])
    return {} if start == imitation.STUDY_DEFAULTS["window_start"] else {"window_start": start}


def options_override(args: argparse.Namespace, method: Method) -> dict[str, int]:
    """`--policy.n_options` of the OCN-family clones (`--n-options`), spelled out only where it is not the
    setting's, so that the clones of the same pool size as every study before it keep their folders."""
    n_options = getattr(args, "n_options", None)
    if method.policy_type != "ocn" or n_options == getattr(args, "default_n_options", None):
        return {}
    return {"n_options": n_options}


def clone_overrides(args: argparse.Namespace, method: Method) -> dict[str, Any]:
    """The study-wide `--policy.*` settings of the method's clones, each spelled out only when set: the
    usage balance and pool size of the OCN family, the packed view of any clone, OCN's costs (`cost_overrides`)."""
    balance = balance_override(args) if method.policy_type == "ocn" else {}
    return {**balance, **loading_override(args), **cost_overrides(args, method), **options_override(args, method)}


def clone_study_suffix(args: argparse.Namespace, method: Method) -> str:
    """Folder-name suffix of a method's runs over clones made under non-default study settings (the
    usage balance of the OCN family, the packed view of any clone), named as the imitation study names
    its folders, so that they live beside the default ones (flat PPO, which clones nothing: none)."""
    if method.overrides is None:
        return ""
    return settings_suffix(clone_overrides(args, method))


def clone_settling(args: argparse.Namespace, method: Method) -> Settling | None:
    """The settling phase of the method's clones: `--settle-steps`' for OCN, none for the others (MoE and
    HIL have no terminations to settle)."""
    return imitation.settling(args) if method.key == "ocn" else None


def clone_suffix(args: argparse.Namespace, method: Method) -> str:
    """Folder-name suffix of a method's finetuning runs: the balance of its clones and, for OCN, their
    settling phase, so that runs over differently made clones live side by side."""
    settling = clone_settling(args, method)
    settle = {} if settling is None else {"settle_steps": settling.steps, "settle_cost": settling.termination_cost,
                                          **{f"settle_{key}": value for key, value in settling.policy.items()}}
    return clone_study_suffix(args, method) + settings_suffix(settle)


def ppo_suffix(args: argparse.Namespace) -> str:
    """Folder-name suffix of a finetuning run at a budget, an entropy bonus, a number of envs or a
    discount other than the study's default (`_frames1500000_entropy0.01_envs256_gamma0.99`), so that
    runs of several PPO settings live side by side (runs made before a setting entered the name are at
    its default)."""
    changed = {"frames": args.frames} if args.frames != args.default_frames else {}
    if args.entropy != PPOConfig.entropy_coef:
        changed["entropy"] = args.entropy
    if args.envs != DEFAULT_ENVS:
        changed["envs"] = args.envs
    if args.gamma != args.default_gamma:
        changed["gamma"] = args.gamma
    return settings_suffix(changed)


def clone_dir(args: argparse.Namespace, setting: Setting, method: Method, folder: str, seed: int) -> Path:
    """Where the method's clone of one demonstration set trains. S1's OCN is the imitation study's
    variant of as many options (the main one, 3, unless `--n-options` says otherwise) under the same
    usage balance and loading (`imitation-s1 --usage-balance W --window-start S`), so both reproductions
    share those runs, and their settling phase too."""
    if setting.name == "s1" and method.name == "OCN":
        overrides = clone_overrides(args, method)
        variant = imitation.variant_with(overrides.pop("n_options", setting.n_options))
        return imitation.run_dir(args.workdir, variant, seed, overrides)
    return args.workdir / "clone" / folder / f"{method.key}{clone_study_suffix(args, method)}" / f"seed{seed}"


def clone(args: argparse.Namespace, setting: Setting, method: Method, seed: int) -> list[TrainedRun]:
    """The method's behaviour-cloned checkpoints for one seed, one per demonstration set (`clone_dir`),
    settled when `--settle-steps` asks for it (OCN only: MoE and HIL have no terminations to settle)."""
    settings, overrides = clone_settings(args, setting, method)
    runs = []
    for folder, tasks in setting.demos:
        data = args.workdir / folder
        record_dataset(data, tasks, f"local/{folder}", args.episodes_per_task, args.data_seed,
                       dart_noise=args.dart_noise)
        run_dir = clone_dir(args, setting, method, folder, seed)
        run = train_policy(settings, data, f"local/{folder}", run_dir, seed, overrides)
        settling = clone_settling(args, method)
        if settling is not None:
            run = settle_policy(settings, run, data, f"local/{folder}", run_dir, seed, settling)
        runs.append(run)
    return runs


def finetune_command(args: argparse.Namespace, setting: Setting, method: Method, reward: str, seed: int,
                     clones: list[TrainedRun], out: Path) -> list[str]:
    """The `ocn-finetune` call of one run (flat PPO: the same command with `--flat` and no checkpoint).

    Over OCN-type pools (OCN, MoE, HIL) the new controller's temperature is spelled out: it once
    defaulted to the checkpoint's, so a run made then is refused rather than reused. The entropy bonus
    is spelled out only where it is not the paper's, and so is the discount, so that runs made before
    either could change are reused."""
    command = [console_script("ocn-finetune"), "--tasks", setting.tasks, "--reward", reward,
               "--frames", str(args.frames), "--envs", str(args.envs), "--seed", str(seed), "--out", str(out)]
    if args.entropy != PPOConfig.entropy_coef:
        command += ["--entropy", f"{args.entropy:g}"]
    if args.gamma != PPOConfig.gamma:
        command += ["--gamma", f"{args.gamma:g}"]
    if method.overrides is None:
        return command + ["--flat"]
    if method.policy_type == "ocn":
        command += ["--temperature", f"{FRESH_CONTROLLER_TEMPERATURE:g}"]
    return command + [word for run in clones for word in ("--checkpoint", str(run.checkpoint))]


def finetune_run(args: argparse.Namespace, setting: Setting, method: Method, reward: str, seed: int,
                 clones: list[TrainedRun]) -> dict[str, Any]:
    """Finetune (unless done) over the options of `clones` (none for flat PPO) and read back one run's curve.
    A finished run is made again when a clone it used was trained on since (`clones.json` keeps the
    clones' training commands; runs from before it existed are reused as they are). An interrupted run
    of the same command over the same clones goes on from its last PPO iteration (`ocn-finetune --resume`)."""
    folder = f"{method.key}_{reward}{clone_suffix(args, method)}{ppo_suffix(args)}"
    out = args.workdir / f"finetune_{setting.name}" / folder / f"seed{seed}"
    command = finetune_command(args, setting, method, reward, seed, clones, out / "run")
    shown = " ".join(Path(word).name if word.startswith("/") else word for word in command)
    summary_path, command_path = out / "run" / "finetune.json", out / "finetune_command.txt"
    if command_path.exists() and command_path.read_text().strip() != shown:
        raise SystemExit(f"{out} holds a run made by another command:\n  {command_path.read_text().strip()}\n"
                         f"while this reproduction would run:\n  {shown}\nMove it away or pass another --workdir.")
    clones_path = out / "clones.json"
    same_clones = not clones_path.exists() or all(
        same_training(before, run.command)
        for before, run in zip(json.loads(clones_path.read_text()), clones, strict=True)
    )
    if summary_path.exists() and not same_clones:
        print(f"finetuning {out} again: its clones were trained on since", flush=True)
        summary_path.unlink()
    if not summary_path.exists():
        resuming = same_clones and command_path.exists() and (out / "run" / STATE_FILE).exists()
        if not resuming:
            shutil.rmtree(out / "run", ignore_errors=True)
        out.mkdir(parents=True, exist_ok=True)
        command_path.write_text(shown + "\n")
        clones_path.write_text(json.dumps([run.command for run in clones]) + "\n")
        print(f"finetuning {out}{' from where it stopped' if resuming else ''}", flush=True)
        with open(out / "finetune.log", "a" if resuming else "w") as log:
            subprocess.run([*command, "--resume"] if resuming else command, check=True, stdout=log,
                           stderr=subprocess.STDOUT)
    curve = read_curve(out / "run" / "curve.csv", task_labels(setting))
    return {
        "method": method.name, "reward": reward, "seed": seed, "command": shown,
        "clone_commands": [run.command for run in clones],
        "clone_wall_s": [run.train_wall_s for run in clones],
        "clones_trained_on": [run.trained_on for run in clones],
        "summary": json.loads(summary_path.read_text()),
        "at_budget": at_budget(curve, task_labels(setting)),
        "curve": curve,
    }


def task_labels(setting: Setting) -> list[str]:
    return setting.tasks.split(",")


def curve_keys(labels: list[str]) -> list[str]:
    """The learning-curve entries a study reports: mean return and success, overall and per task."""
    return ["mean_return", "success", *(f"success[{label}]" for label in labels)]


def read_curve(path: Path, labels: list[str]) -> list[dict[str, float]]:
    """An `ocn-finetune` curve.csv as rows of env frames and the entries a study reports (`curve_keys`)."""
    keys = ["frames", *curve_keys(labels)]
    with open(path, newline="") as handle:
        return [{key: round(float(row[key]), 4) for key in keys} for row in csv.DictReader(handle)]


def at_budget(curve: list[dict[str, float]], labels: list[str]) -> dict[str, float]:
    """Mean return and success (overall and per task) over a curve's last FINAL_ROWS iterations."""
    return {key: float(np.mean([row[key] for row in curve[-FINAL_ROWS:]])) for key in curve_keys(labels)}


def summarise(runs: list[dict[str, Any]], labels: list[str],
              methods: tuple[Method, ...] = METHODS) -> dict[str, dict[str, Any]]:
    """Per method and reward: the value at the budget (mean and std over seeds) and the curves over
    seeds (mean, std, min and max on a common env-frame grid)."""
    summary: dict[str, dict[str, Any]] = {}
    for method in methods:
        for reward in REWARDS:
            mine = [run for run in runs if run["method"] == method.name and run["reward"] == reward]
            if not mine:
                continue
            finals = [run["at_budget"] for run in mine]
            grid = np.linspace(0, min(run["curve"][-1]["frames"] for run in mine), GRID_POINTS)
            curves = {}
            for key in curve_keys(labels):
                values = np.array([np.interp(grid, [r["frames"] for r in run["curve"]], [r[key] for r in run["curve"]])
                                   for run in mine])
                curves[key] = over_seeds(values)
            summary[f"{method.name} | {reward}"] = {
                "method": method.name, "reward": reward, "seeds": [run["seed"] for run in mine],
                "at_budget": {key: {"mean": float(np.mean([f[key] for f in finals])),
                                    "std": float(np.std([f[key] for f in finals]))} for key in finals[0]},
                "frames_per_s": float(np.mean([run["summary"]["frames_per_s"] for run in mine])),
                "curve_frames": grid.round(0).tolist(),
                "curves": curves,
            }
    return summary


def budget_value(summary: dict[str, dict[str, Any]], method: str, reward: str, key: str) -> float | None:
    """A method's mean over seeds at the budget of one curve entry under one reward (None if it did not run)."""
    row = summary.get(f"{method} | {reward}")
    return None if row is None else row["at_budget"][key]["mean"]


def must_show(setting: Setting, summary: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The issue's checks for this setting, each with its measured values and whether it holds."""
    labels, checks = task_labels(setting), []

    ocn_sparse = [budget_value(summary, "OCN", "sparse", f"success[{label}]") for label in labels]
    if None not in ocn_sparse:
        bar = 0.9 if setting.name == "s1" else 0.8
        checks.append({"check": f"OCN, sparse: success >= {bar} on each of {', '.join(labels)}",
                       "value": min(ocn_sparse), "holds": min(ocn_sparse) >= bar})
        for other in BASELINES:
            theirs = budget_value(summary, other, "sparse", "success")
            if theirs is not None:
                ours = budget_value(summary, "OCN", "sparse", "success")
                checks.append({"check": f"sparse: {other}'s mean success below OCN's ({ours:.3f})",
                               "value": theirs, "holds": theirs < ours})
    ours = budget_value(summary, "OCN", "dense", "mean_return")
    baselines = [v for v in (budget_value(summary, m, "dense", "mean_return") for m in BASELINES) if v is not None]
    if ours is not None and baselines and setting.name == "s1":
        checks.append({"check": "dense: OCN's return at least twice the best baseline's",
                       "value": ours / max(max(baselines), 1e-9), "holds": ours >= 2 * max(baselines)})
        checks.extend(dense_reach(summary, labels))
    return checks


def dense_reach(summary: dict[str, dict[str, Any]], labels: list[str]) -> list[dict[str, Any]]:
    """Whether twice the best baseline's dense return is within reach at any budget: no return exceeds
    the tasks' subtask count (+1 per subtask), and at every budget the best baseline returns at least
    the lowest point of any one baseline's mean curve, so no budget's ratio exceeds their quotient.
    Empty where the summary holds no curves."""
    floors = [min(row["curves"]["mean_return"]["mean"]) for method in BASELINES
              if (row := summary.get(f"{method} | dense")) is not None and "curves" in row]
    if not floors:
        return []
    most = max(len(label) for label in labels)
    return [{"check": f"dense: twice the best baseline's return within reach at some budget (the tasks' highest "
                      f"return, {most}, over the highest low point of a baseline's mean curve)",
             "value": most / max(floors), "holds": most >= 2 * max(floors)}]


def plot(summary: dict[str, dict[str, Any]], methods: tuple[Method, ...], labels: list[str], band: str,
         title: str, path: Path) -> None:
    """Curves like the paper's figures 4-6: one row per reward, success per task and the mean return,
    each method's mean over seeds with a band (`band` "std": one standard deviation; "min-max")."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import EngFormatter

    keys = [*(f"success[{label}]" for label in labels), "mean_return"]
    rewards = [reward for reward in REWARDS if any(row["reward"] == reward for row in summary.values())]
    fig, axes = plt.subplots(len(rewards), len(keys), figsize=(3.2 * len(keys), 2.9 * len(rewards)), squeeze=False)
    for r, reward in enumerate(rewards):
        for c, key in enumerate(keys):
            ax = axes[r][c]
            for k, method in enumerate(methods):
                row = summary.get(f"{method.name} | {reward}")
                if row is None:
                    continue
                curve = {stat: np.array(values) for stat, values in row["curves"][key].items()}
                low, high = ((curve["mean"] - curve["std"], curve["mean"] + curve["std"]) if band == "std"
                             else (curve["min"], curve["max"]))
                ax.plot(row["curve_frames"], curve["mean"], color=f"C{k}", label=method.name)
                ax.fill_between(row["curve_frames"], low, high, color=f"C{k}", alpha=0.2)
            ax.set_title(f"{reward}: {key.replace('success[', 'success ').rstrip(']')}", fontsize=9)
            ax.xaxis.set_major_formatter(EngFormatter())
            ax.grid(alpha=0.3)
            if key != "mean_return":
                ax.set_ylim(-0.02, 1.02)
    axes[0][0].legend(fontsize=8)
    fig.supxlabel("env frames")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(result: dict[str, Any]) -> str:
    """The human-readable results file."""
    setting = SETTINGS[result["setting"]]
    labels = task_labels(setting)
    # compILE's and OMPN's skills differ from the setting's options; say so only in a file that has their rows.
    ran = {row["method"] for row in result["summary"].values()}
    notes = {"compILE": "compILE: one per latent category of its decoder",
             "OMPN": "OMPN: none, its whole network is finetuned"}
    shown = [note for method, note in notes.items() if method in ran]
    skills_note = f" ({'; '.join(shown)})" if shown else ""
    settings = study_settings(result)
    lines = [
        f"# Finetuning on Craft {setting.name.upper()}: {setting.tasks}",
        "",
        f"{origin_words(result)} Skills: {', '.join(f'{{{t}}}' for _, t in setting.demos)} demonstrations, "
        f"{settings['n_options']} options per cloned model{skills_note}, cloned by "
        f"`lerobot-train` on {imitation.loading_words(settings)}{imitation.recording_words(settings)} "
        f"(OCN-family clones' option-usage balance {settings['usage_balance']}; "
        f"OCN's{imitation.cost_words(settings)}: {imitation.settling_words(settings)}); PPO through `ocn-finetune`, "
        f"{settings['frames']} env frames per run, {settings['envs']} envs, entropy bonus {settings['entropy']:g}, "
        f"discount {settings['gamma']:g}. "
        f"Values at the budget are the mean of each run's last {FINAL_ROWS} PPO iterations, then mean (std) over "
        f"seeds. Runs finished: {result['runs_finished']} of {result['runs_planned']}; wall time of "
        f"{'the invocations' if 'sources' in result else 'this invocation'} {result['wall_s'] / 60:.0f} min.",
        "",
        "## Checks",
        "",
        *checks_table(result["must_show"]),
        "",
        "## At the budget",
        "",
        *budget_table(result["summary"], labels),
        "",
        f"Curves: `finetune_{setting.name}.png`.",
        "",
    ]
    return "\n".join(lines)


def budget_table(summary: dict[str, dict[str, Any]], labels: list[str]) -> list[str]:
    """Markdown table lines: per method and reward, mean (std) over seeds at the budget of the return
    and the success, overall and per task, and the PPO throughput."""
    lines = ["| method | reward | seeds | mean return | success | " + " | ".join(labels) + " | PPO frames/s |",
             "|---|---|---|---|---|" + "---|" * len(labels) + "---|"]
    for row in summary.values():
        cells = {key: f"{value['mean']:.3f} ({value['std']:.3f})" for key, value in row["at_budget"].items()}
        per_task = " | ".join(cells[f"success[{label}]"] for label in labels)
        lines.append(f"| {row['method']} | {row['reward']} | {len(row['seeds'])} | {cells['mean_return']} | "
                     f"{cells['success']} | {per_task} | {row['frames_per_s']:.0f} |")
    return lines


def write_results(args: argparse.Namespace, setting: Setting, runs: list[dict[str, Any]], planned: int,
                  wall_s: float) -> dict[str, Any]:
    """`results/finetune_<setting>.{json,md,png}` from the runs finished so far."""
    summary = summarise(runs, task_labels(setting))
    result = {
        **provenance(args),
        "setting": setting.name,
        "runs_finished": len(runs),
        "runs_planned": planned,
        "summary": summary,
        "must_show": must_show(setting, summary),
        "runs": runs,
        "wall_s": round(wall_s, 1),
    }
    write_study_files(args.results, result)
    return result


def write_study_files(results: Path, result: dict[str, Any]) -> None:
    """`finetune_<setting>.{json,md,png}` of a study's result (whose `setting` names it) in the folder `results`."""
    setting = SETTINGS[result["setting"]]
    stem = write_result_files(results, f"finetune_{setting.name}", result, markdown(result))
    title = f"Finetuning in Craft {setting.name.upper()} ({setting.tasks}): mean and std over seeds"
    plot(result["summary"], METHODS, task_labels(setting), "std", title, stem.with_suffix(".png"))


def reproduce(args: argparse.Namespace) -> int:
    """Every planned run in turn, seeds innermost last so that each method's first seed comes early."""
    started = time.perf_counter()
    setting = SETTINGS[args.experiment]
    methods = chosen_methods(args, METHODS)
    unpooled = [method.name for method in methods if len(setting.demos) > 1 and not method.pools]
    if unpooled:
        raise SystemExit(f"ocn-reproduce {setting.name}: {', '.join(unpooled)} cannot pool the skills of several "
                         "cloned models, which this setting merges (the paper leaves OMPN out of S2); drop it "
                         "from --methods.")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    planned = [(m, reward, seed) for seed in seeds for m in methods for reward in args.rewards]
    runs: list[dict[str, Any]] = []
    result: dict[str, Any] = {}
    for method, reward, seed in planned:
        clones = clone(args, setting, method, seed) if method.overrides is not None else []
        runs.append(finetune_run(args, setting, method, reward, seed, clones))
        result = write_results(args, setting, runs, len(planned), time.perf_counter() - started)
    print(markdown(result))
    return 0


def chosen_methods(args: argparse.Namespace, methods: tuple[Method, ...]) -> list[Method]:
    """The methods --methods names, in its order; an unknown method or reward ends the command."""
    known = {method.key: method for method in methods}
    unknown = sorted(set(args.methods) - set(known)) + sorted(set(args.rewards) - set(REWARDS))
    if unknown:
        raise SystemExit(f"ocn-reproduce: unknown method or reward {unknown}; methods are {sorted(known)}, "
                         f"rewards {list(REWARDS)}.")
    return [known[key] for key in args.methods]


def add_finetune_arguments(parser: argparse.ArgumentParser, methods: tuple[Method, ...], frames: int,
                           gamma: float = PPOConfig.gamma) -> None:
    """The options of a finetuning study's PPO runs: seeds, budget, discount, envs, rewards and methods."""
    parser.add_argument("--seeds", type=int, default=3)
    imitation.add_first_seed_argument(parser)
    parser.add_argument("--frames", type=int, default=frames,
                        help="env frames per PPO run (the budget); runs at another budget than the default get "
                             "folders of their own (`ocn_sparse_frames1500000`)")
    parser.set_defaults(default_frames=frames)
    parser.add_argument("--entropy", type=float, default=PPOConfig.entropy_coef,
                        help="PPO's entropy bonus coefficient, the same for every method (ocn-finetune --entropy); "
                             "runs at another value than the paper's get folders of their own")
    parser.add_argument("--gamma", type=float, default=gamma,
                        help="PPO's discount per env step, the same for every method (ocn-finetune --gamma); "
                             "runs at another value than the study's default get folders of their own")
    parser.set_defaults(default_gamma=gamma)
    parser.add_argument("--envs", type=int, default=DEFAULT_ENVS,
                        help="envs stepped together in PPO, one episode each per iteration (the batch of an update); "
                             "runs at another number than the default get folders of their own")
    parser.add_argument("--rewards", type=lambda s: s.split(","), default=list(REWARDS),
                        help="comma-separated: sparse,dense")
    parser.add_argument("--methods", type=lambda s: s.split(","), default=",".join(m.key for m in methods),
                        help="comma-separated: " + ",".join(m.key for m in methods))
    add_usage_balance_argument(parser)


def add_usage_balance_argument(parser: argparse.ArgumentParser) -> None:
    """`--usage-balance` of the studies that clone the OCN family (`balance_override`)."""
    parser.add_argument("--usage-balance", type=float, default=0.0,
                        help="weight of the option-usage balance term in the behaviour cloning of the OCN-family "
                             "clones (OCN, MoE, HIL; OCNConfig.usage_balance); 0 is the paper's loss")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The `s1` and `s2` subcommands."""
    for name, setting in SETTINGS.items():
        parser = sub.add_parser(name, help=f"finetuning on {setting.tasks} over skills cloned from "
                                f"{' and '.join(t for _, t in setting.demos)}",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        runnable = tuple(method for method in METHODS if method.pools or len(setting.demos) == 1)
        add_finetune_arguments(parser, runnable, 300_000)
        parser.add_argument("--n-options", type=int, default=setting.n_options,
                            help="options per OCN-family clone (OCN, MoE, HIL); S1's OCN clones are then "
                                 "imitation-s1's variant of that many, e.g. 6 with --settle-usage-balance-options 3 "
                                 "--settle-usage-balance-exact, its 6-option recipe; clones of another number than "
                                 "the default get folders of their own")
        parser.set_defaults(default_n_options=setting.n_options)
        imitation.add_training_arguments(parser)
        imitation.add_window_start_argument(parser)
        imitation.add_dart_noise_argument(parser)
        imitation.add_switch_cost_argument(parser)
        imitation.add_expected_nll_argument(parser)
        imitation.add_settling_arguments(parser, 0, "OCN's clones (as imitation-s1's, which settles by default)")
        parser.add_argument("--results", type=Path, default=RESULTS)
        parser.set_defaults(func=reproduce)
