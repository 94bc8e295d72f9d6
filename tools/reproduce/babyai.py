"""`ocn-reproduce babyai`: OCN, OMPN and compILE cloned from BabyAI bot demonstrations, a world no one here
wrote (envs/babyai/README.md), each parse scored against the bot's own subgoals.

The recording: `python -m lerobot_policy_ocn.ocn_data.record_babyai` (LeRobot's own writer) of the bot on the
150 missions of the level OpenPickupSeq, `--episodes` in all (each mission equally often; the last fifth is the
validation split). The models, each a plain `lerobot-train` run with the policy's defaults on the same
data, seed and size (`--steps` of `--batch-size` episodes):

- OCN, `--policy.type=ocn --policy.n_options=6`: one option per subgoal kind (open one of three doors,
  pick up one of three objects), as the paper sizes OCN (as many options as subtasks, its Craft
  setting; it shows fewer options than subtasks cost NMI). The recipe is the policy's default for
  discrete actions (Craft's): nothing here is tuned for BabyAI. The state encoder follows from the
  dataset: BabyAI's 148 small integer codes are one-hot per element (`categorical`);
- OMPN (`--policy.type=ompn`) and compILE (`--policy.type=compile`) at their published Craft defaults
  (3 memory slots; 4 segments of concrete latents), the only settings the study may pass being model
  sizes (`runs.POLICY_FLAGS`);
- with `--encoder-check`, OCN again with `--policy.obs_encoder=identity` (the codes read as
  standardised numbers): the measurement behind the categorical encoder, an input choice rather than
  the recipe.

Each model is scored by `ocn-eval` on the validation split: F1 at tolerance 0 and 1, task alignment,
NMI (OCN: the chosen option; compILE: its latent; OMPN has no per-step label), free-run success per
mission (`--rollouts` fresh episodes each, env seeds from 100,000) and OCN's option x subgoal table.
The bot's own success on the same (mission, seed) pairs
(`lerobot_policy_ocn.tools.rl.babyai_rollouts.bot_success`, through
`lerobot_policy_ocn.envs.babyai.rollout.run_missions`) is the bar the free runs are read against.

The checks: OCN's NMI >= 0.8; OCN's NMI above compILE's and OCN's F1@1 above OMPN's and compILE's
(OMPN has no NMI); OCN's free-run success within 0.1 of the bot's. Writes `results/babyai.{json,md,png}`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import RESULTS
from lerobot_policy_ocn.tools.reproduce.clones import EVAL_KEYS, Model
from lerobot_policy_ocn.tools.reproduce.report import (
    check, checks_table, origin_words, provenance, seconds_cell, write_results,
)
from lerobot_policy_ocn.tools.reproduce.runs import Evaluation, Job, Training, train_command

STUDY = "babyai"
REPO_ID = "local/babyai"
N_SUBGOALS = 6
MODELS = {
    "ocn": Model("OCN, 6 options", flags={"n_options": N_SUBGOALS}),
    "ompn": Model("OMPN", "ompn"),
    "compile": Model("compILE", "compile"),
}
# The input-encoder measurement (`--encoder-check`): OCN reading the codes as numbers.
IDENTITY = "ocn_identity"
# The study's full size (the defaults): see the module docstring.
FULL = {"episodes": 5000, "steps": 3000, "batch_size": 64, "rollouts": 10}
EVAL_SEED = 100_000  # ocn-eval's default first env seed, which the bot's runs share
SCORES = {"f1_tol0": "F1@0", "f1_tol1": "F1@1", "align_acc": "align", "nmi": "NMI", "mean_success_rate": "success"}


class BabyAIRecording(Job):
    """`python -m lerobot_policy_ocn.ocn_data.record_babyai` into FOLDER/dataset, once; finished once its splits
    are written (the recorder's last act), and recorded again from scratch after an interruption (the recorder
    refuses a folder that exists)."""

    output = "dataset"

    def __init__(self, workdir: Path, folder: str, episodes: int, seed: int) -> None:
        super().__init__(workdir, folder, ["python", "-m", "lerobot_policy_ocn.ocn_data.record_babyai",
                                           "--root", f"{folder}/dataset", "--repo-id", REPO_ID,
                                           "--episodes", str(episodes), "--seed", str(seed)])

    @property
    def root(self) -> str:
        return f"{self.folder}/{self.output}"

    def finished(self) -> bool:
        import json

        info = self.path / self.output / "meta" / "info.json"
        return info.exists() and "val" in (json.loads(info.read_text()).get("splits") or {})


def train(args: argparse.Namespace, data: BabyAIRecording, name: str) -> Training:
    """One model trained (or reused, or resumed) on the recording."""
    identity = name == IDENTITY
    model = MODELS["ocn" if identity else name]
    folder = f"train/babyai/{name}/seed{args.seed}"
    command = train_command(model.policy_type, data.root, REPO_ID, folder, args.steps, args.batch_size, args.seed,
                            model.flags)
    if identity:
        command.append("--policy.obs_encoder=identity")
    return Training(args.workdir, folder, command).run()


def scored(args: argparse.Namespace, data: BabyAIRecording, name: str, trained: Training) -> dict[str, Any]:
    """A model's row: its commands, training wall seconds and ocn-eval's scores on the validation split."""
    job = Evaluation(args.workdir, f"{trained.folder}/eval", trained.checkpoint, data.root, REPO_ID,
                     args.rollouts).run()
    scores = job.scores()
    kept = {key: scores[key] for key in (*EVAL_KEYS, "action_nll", "label_free", "option_subtask_success")}
    return {"model": name, "train_command": trained.shown, "train_wall_s": trained.wall_s, "eval_command": job.shown,
            "eval_wall_s": job.wall_s, "scores": kept}


def checks(rows: dict[str, dict[str, Any]], bot: float | None) -> list[dict[str, Any]]:
    """The study's bars (not run: a model's row is missing)."""
    def score(name: str, key: str) -> float | None:
        return rows[name]["scores"][key] if name in rows else None

    nmi, f1 = score("ocn", "nmi"), score("ocn", "f1_tol1")
    success = score("ocn", "mean_success_rate")
    return [
        check("OCN: NMI >= 0.8", nmi, lambda v: v >= 0.8),
        check("compILE's NMI below OCN's", score("compile", "nmi") if nmi is not None else None, lambda v: v < nmi),
        check("OMPN's F1@1 below OCN's", score("ompn", "f1_tol1") if f1 is not None else None, lambda v: v < f1),
        check("compILE's F1@1 below OCN's", score("compile", "f1_tol1") if f1 is not None else None,
              lambda v: v < f1),
        check(f"OCN: free-run success within 0.1 of the bot's ({'n/a' if bot is None else f'{bot:.3f}'})",
              success if bot is not None else None, lambda v: v >= bot - 0.1),
    ]


def markdown(result: dict[str, Any]) -> str:
    """The results in words: the checks first, then every model's scores and the bot's rate."""
    settings, rows = result["settings"], result["rows"]
    lines = [
        "# BabyAI OpenPickupSeq: OCN, OMPN and compILE against the bot's subgoals", "",
        f"{origin_words(result)} Demonstrations: `python -m lerobot_policy_ocn.ocn_data.record_babyai`, "
        f"{settings['episodes']} bot "
        f"episodes over the 150 missions (the last fifth validates); every model a plain `lerobot-train` run of "
        f"{settings['steps']} steps of {settings['batch_size']} episodes, seed {settings['seed']}, at the policy's "
        f"defaults (OCN: 6 options, one per subgoal kind, as the paper sizes it); scores: `ocn-eval` on the "
        f"validation split, {settings['rollouts']} free-run episodes per mission. Wall time "
        f"{result['wall_s'] / 60:.0f} min.", "",
        *reduced_words(settings),
        "## Checks", "", *checks_table(result["checks"]), "",
        f"The bot's free-run success on the same {150 * settings['rollouts']} (mission, seed) pairs: "
        f"{result['bot_success']:.3f}." if result.get("bot_success") is not None else "", "",
        "## Scores on the validation split", "",
        "| model | " + " | ".join(SCORES.values()) + " | NLL | segments/episode | switches/frame | train s | "
        "command |", "|---|" + "---|" * (len(SCORES) + 5),
    ]
    for name, row in rows.items():
        scores = row["scores"]
        cells = " | ".join("n/a" if scores[key] is None else f"{scores[key]:.3f}" for key in SCORES)
        nll = "n/a" if scores["action_nll"] is None else f"{scores['action_nll']:.3f}"
        free = scores["label_free"]
        lines.append(f"| {model_name(name)} | {cells} | {nll} | {free['segments_per_episode']:.2f} | "
                     f"{free['switch_rate']:.3f} | {seconds_cell(row['train_wall_s'])} | `{row['train_command']}` |")
    table = rows.get("ocn", {}).get("scores", {}).get("option_subtask_success")
    if table:
        lines += ["", "## OCN's options alone on each subgoal (success over the one-subgoal missions)", "",
                  "| option | " + " | ".join(table["subtasks"]) + " |", "|---|" + "---|" * len(table["subtasks"])]
        lines += [f"| {label} | " + " | ".join(f"{v:.2f}" for v in values) + " |"
                  for label, values in zip(table["rows"], table["table"], strict=True)]
    lines += ["", f"Figure: `{STUDY}.png` (each score per model; the bot's success as a line; OCN's option x "
              "subgoal table).", ""]
    return "\n".join(lines)


def reduced_words(settings: dict[str, Any]) -> list[str]:
    """A sentence in the header where the run is smaller than the study's full size, with the command of
    the full size."""
    smaller = [f"{key} {settings[key]} (full: {full})" for key, full in FULL.items() if settings[key] < full]
    if not smaller:
        return []
    return [f"**Reduced size**: {', '.join(smaller)}, to fit one shared CPU core; the full size is "
            f"`ocn-reproduce babyai` with the defaults.", ""]


def model_name(name: str) -> str:
    return "OCN, 6 options, identity encoder" if name == IDENTITY else MODELS[name].name


def figure(result: dict[str, Any], path: Path) -> None:
    """Each score per model as bars (the bot's success as a dashed line), and OCN's option x subgoal table."""
    import matplotlib.pyplot as plt
    import numpy as np

    rows = result["rows"]
    names = list(rows)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [3, 2]})
    width = 0.8 / max(len(names), 1)
    for k, name in enumerate(names):
        values = [rows[name]["scores"][key] for key in SCORES]
        axes[0].bar(np.arange(len(SCORES)) + k * width, [np.nan if v is None else v for v in values], width,
                    label=model_name(name))
    if result.get("bot_success") is not None:
        axes[0].axhline(result["bot_success"], color="k", ls="--", lw=1, label="bot's success")
    axes[0].set_xticks(np.arange(len(SCORES)) + 0.4 - width / 2, list(SCORES.values()))
    axes[0].set_ylim(0, 1.05)
    axes[0].legend(fontsize=8)
    axes[0].set_title("validation split (n/a: no bar)", fontsize=9)
    table = rows.get("ocn", {}).get("scores", {}).get("option_subtask_success")
    if table:
        values = np.array(table["table"])
        axes[1].imshow(values, vmin=0, vmax=1, cmap="viridis")
        for (i, j), value in np.ndenumerate(values):
            axes[1].text(j, i, f"{value:.2f}", ha="center", va="center", fontsize=7,
                         color="white" if value < 0.6 else "black")
        axes[1].set_xticks(range(len(table["subtasks"])), table["subtasks"], rotation=30, fontsize=7)
        axes[1].set_yticks(range(len(values)), table["rows"], fontsize=7)
        axes[1].set_title("OCN: each option alone on each subgoal", fontsize=9)
    else:
        axes[1].set_axis_off()
    fig.suptitle("BabyAI OpenPickupSeq: parses against the bot's subgoals")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def reproduce(args: argparse.Namespace) -> int:
    """Record, then train and score each model in turn, rewriting the results after each; the bot's rate last."""
    from lerobot_policy_ocn.envs.babyai import MinigridMissing, minigrid_installed

    if not minigrid_installed():
        raise SystemExit(f"ocn-reproduce babyai: {MinigridMissing()}")
    started = time.perf_counter()
    settings = {key: getattr(args, key) for key in ("episodes", "steps", "batch_size", "seed", "rollouts")}
    settings |= {"workdir": str(args.workdir), "results": str(args.results)}
    data = BabyAIRecording(args.workdir, "data/babyai", args.episodes, 0).run()
    names = [*MODELS, *([IDENTITY] if args.encoder_check else [])]
    rows: dict[str, dict[str, Any]] = {}
    bot = None
    for name in [*names, "bot"]:
        if name == "bot":
            bot = bot_rate(args.rollouts)
        else:
            rows[name] = scored(args, data, name, train(args, data, name))
        result = {**provenance(args.argv, settings), "study": STUDY, "recording_command": data.shown,
                  "recording_wall_s": data.wall_s, "rows": rows, "bot_success": bot, "checks": checks(rows, bot),
                  "wall_s": round(time.perf_counter() - started)}
        write_results(args.results, STUDY, result, markdown(result), lambda path, result=result: figure(result, path))
    print(markdown(result))
    return 0


def bot_rate(rollouts: int) -> float:
    """The bot's mean success over every mission on ocn-eval's (mission, seed) pairs."""
    from lerobot_policy_ocn.envs.babyai.missions import MISSIONS
    from lerobot_policy_ocn.tools.rl.babyai_rollouts import bot_success

    rates = bot_success([mission.text for mission in MISSIONS], rollouts, EVAL_SEED)
    return sum(rates.values()) / len(rates)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `babyai` subcommand."""
    parser = sub.add_parser("babyai", help="BabyAI: OCN, OMPN and compILE against the bot's subgoals",
                            description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--episodes", type=int, default=FULL["episodes"], help="bot demonstrations recorded (80/20 "
                                                                                "train/val)")
    parser.add_argument("--steps", type=int, default=FULL["steps"], help="lerobot-train steps per model")
    parser.add_argument("--batch-size", type=int, default=FULL["batch_size"], help="episodes per lerobot-train step")
    parser.add_argument("--seed", type=int, default=1, help="lerobot-train seed of every model")
    parser.add_argument("--rollouts", type=int, default=FULL["rollouts"],
                        help="ocn-eval free-run episodes per mission and per option-table cell")
    parser.add_argument("--encoder-check", action="store_true",
                        help="also train and score OCN with the identity encoder (the categorical one's measurement)")
    parser.add_argument("--workdir", type=Path, default=Path("outputs/reproduce"),
                        help="where the recording and runs live; finished ones there are reused")
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of babyai.{json,md,png}")
    parser.set_defaults(func=reproduce)
