"""`ocn-eval`: how well a trained policy (OCN, or a baseline) parses held-out demonstrations, and how well it acts.

On the split's episodes (default "val"; a dataset that names no "val" split: its last fifth, then
marked not held out when the policy trained on them) it runs the policy over each whole episode and
reports what needs no ground truth (`label_free`: option usage, segments per episode, segment
lengths, switches per frame; and the mean NLL per frame of the demonstrated actions, `action_nll`:
OCN, OMPN). Where the dataset has the ground-truth subtask columns, it scores the parse against them
with the shared parsing metrics: F1 at tolerance 0 and 1 and task alignment from the predicted
boundaries, NMI from per-step labels (OCN: the chosen option argmax p^c); without them those are
null, and "not_applicable" says why.
In the dataset's world (Craft, Dial or BabyAI, read from the dataset; `lerobot_policy_ocn.tools.worlds`) it measures the
whole policy's free-run success per task (Dial: per PIN) and, for a policy made of
options, each frozen option alone on each subtask (paper table 1; Dial: each digit), drawn as a
PNG beside the JSON. With --oracle-tasks it also runs the frozen options on other tasks (the
finetuning tasks, say) under an oracle controller (`lerobot_policy_ocn.tools.rl.rollouts.oracle_controller_success`):
the ceiling a finetuned controller over these options can reach. Every model type parses through
`lerobot_policy_ocn.tools.eval.parsing` (OMPN: the top-k steps of its expected expansion; compILE: its argmax
segment boundaries, labelled by its concrete latents; --boundary-threshold gives OMPN a read-out
that is not told the number of subtasks); what does not apply to a model (OMPN has
no labels, OMPN and compILE no options, compILE no per-step NLL) is null in the JSON, with the
reason under "not_applicable".
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_policy_ocn.ocn_data.durable import write_atomic
from lerobot_policy_ocn.ocn_data.preflight import check_can_create, check_repo_id


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ocn-eval", description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--policy", type=Path, required=True,
                        help="a pretrained_model folder of an ocn, ompn or compile checkpoint")
    parser.add_argument("--root", type=Path, required=True, help="the LeRobot dataset's folder")
    parser.add_argument("--repo-id", required=True, help="the dataset's repo id, recorded in the output")
    parser.add_argument("--split", default="val", help="split of meta/info.json to parse: train, val or all")
    parser.add_argument("--out", type=Path, required=True,
                        help="JSON file to write (must not exist unless --force); the PNG goes beside it")
    parser.add_argument("--force", action="store_true", help="overwrite an existing --out JSON and its PNG")
    parser.add_argument("--max-episodes", type=int, default=None, help="parse at most this many split episodes")
    parser.add_argument("--rollouts", type=int, default=200, help="env episodes per task and per table cell")
    parser.add_argument("--seed", type=int, default=100_000,
                        help="first env seed (away from recording seeds); also seeds the policy's sampling")
    parser.add_argument("--batch-size", type=int, default=1024, help="episodes per parsing batch")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--oracle-tasks", default=None,
                        help="also measure the frozen options on these tasks (e.g. ADC,CAD,DCA or 124,481) under an "
                             "oracle controller that starts, at every decision, the option with the best option x "
                             "subtask success on the current subtask: the ceiling of finetuning over these options")
    parser.add_argument("--oracle-switch", choices=("termination", "progress"), default="termination",
                        help="where --oracle-tasks' oracle chooses: where the running option's termination fires, or "
                             "where the env's subtask completes (the options' terminations left out: how well each "
                             "option carries out its subtask)")
    parser.add_argument("--boundary-threshold", type=float, default=None,
                        help="an ompn checkpoint's count-free read-out: one boundary per run of steps whose scaled "
                             "expected expansion height exceeds this value in (0, 1) (default: its checkpoint's "
                             "`boundary_threshold`; None there means top-k, told each episode's number of subtasks)")
    parser.add_argument("--mcap", type=Path, default=None,
                        help="also log every free-run step (state, action, p^c, option, termination, reward) to "
                             "this MCAP file, which must not exist")
    return parser.parse_args(argv)


def plot_option_table(table: np.ndarray, subtasks: list[str], path: Path, title: str) -> None:
    """Heat map of option x subtask success rates, values printed in the cells."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(1.2 + 1.1 * len(subtasks), 1.0 + 0.8 * table.shape[0]))
    ax.imshow(table, vmin=0.0, vmax=1.0, cmap="viridis")
    for (i, j), value in np.ndenumerate(table):
        ax.text(j, i, f"{value:.2f}", ha="center", va="center", color="white" if value < 0.6 else "black")
    ax.set_xticks(range(len(subtasks)), subtasks)
    ax.set_yticks(range(table.shape[0]), [f"option {i}" for i in range(table.shape[0])])
    ax.set_xlabel("subtask")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    image = io.BytesIO()
    fig.savefig(image, format="png", dpi=120)
    plt.close(fig)
    write_atomic(path, image.getvalue())


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse, before any work, an id that is not ORG/NAME, a result that exists (unless --force:
    results are not overwritten by accident), an output folder that cannot be written, an MCAP log
    that exists."""
    from lerobot_policy_ocn.ocn_data.mcap_log import check_new_log

    check_repo_id(args.repo_id)
    if not args.force:
        for path in (args.out, args.out.with_suffix(".png")):
            if path.exists():
                raise FileExistsError(f"--out: {path} already exists; ocn-eval does not overwrite a result: choose "
                                      "another --out, or pass --force to replace it.")
    check_can_create(args.out, "--out")
    if args.mcap is not None:
        check_new_log(args.mcap)
        check_can_create(args.mcap, "--mcap")


GROUND_TRUTH = (
    "the dataset has no ground-truth subtask columns (subtask.index, subtask.id): F1, alignment and NMI score a "
    "parse against them, so only the label-free figures are reported"
)


def evaluate(args: argparse.Namespace) -> dict[str, Any]:
    """Everything `ocn-eval` reports, as the JSON it writes."""
    import torch

    from lerobot_policy_ocn.ocn_data.episodes_table import held_out, read_info, split_episodes
    from lerobot_policy_ocn.tools.rl import rollouts
    from lerobot_policy_ocn.tools.eval.parsing import (
        PARSERS, action_nll, label_free_figures, load_policy, parse_statistics, parser_of, policy_episodes,
        score_segmentations,
    )
    from lerobot_policy_ocn.tools.worlds import world_of

    check_outputs(args)
    world = world_of(args.root)
    info = read_info(args.root)
    policy, preprocessor, postprocessor = load_policy(args.policy, args.device, types=tuple(PARSERS))
    parser = parser_of(policy)
    readout = {}
    if policy.name == "ompn":
        if args.boundary_threshold is not None:  # a new config, so that its checks run on the value
            policy.config = dataclasses.replace(policy.config, boundary_threshold=args.boundary_threshold)
        readout = {"boundary_threshold": policy.config.boundary_threshold}
    elif args.boundary_threshold is not None:
        raise ValueError(f"--boundary-threshold sets an ompn checkpoint's read-out; `{policy.name}` has none.")
    has_options = isinstance(policy, rollouts.OptionPolicy)
    cannot_act = acting_problem(world, policy)
    acts = cannot_act is None
    if (args.mcap is not None or args.oracle_tasks is not None) and not acts:
        raise ValueError(f"--mcap and --oracle-tasks run the policy in its world's env, and {cannot_act}: leave them "
                         "out.")
    if args.mcap is not None and not has_options:
        raise ValueError(f"--mcap logs the option choices of a policy made of options; `{policy.name}` has none.")
    oracle_tasks = None
    if args.oracle_tasks is not None:
        if not has_options:
            raise ValueError(f"--oracle-tasks runs frozen options; `{policy.name}` has none.")
        if args.oracle_switch == "termination":
            rollouts.check_self_terminating(policy)  # now, not after the parse and the free runs
        oracle_tasks = world.parse_task_list(args.oracle_tasks)
    torch.manual_seed(args.seed)  # the policy samples its actions: same seed, same rollouts
    started = time.perf_counter()
    selected = split_episodes(args.root, args.split)
    episodes = policy_episodes(policy, args.root, selected, args.max_episodes)
    parses = parser.segment(policy, preprocessor, episodes, args.batch_size)
    scores = score_segmentations(episodes, parses)

    dataset_tasks = sorted(set(episodes.tasks), key=policy.config.tasks.index)
    tasks = [world.task_key(task) for task in dataset_tasks]
    subtasks = world.used_subtasks(dataset_tasks)
    if oracle_tasks is not None:
        unmeasured = sorted({world.subtask_codes[s] for task in oracle_tasks for s in task} - set(subtasks))
        if unmeasured:
            raise ValueError(f"--oracle-tasks uses subtask(s) {unmeasured} that no task of the dataset holds, so no "
                             f"option is measured on them (the option table's subtasks: {subtasks}).")
    option_table = None
    not_applicable = {} if episodes.labelled else {"parsing_scores": GROUND_TRUTH}
    if has_options and acts and subtasks:
        table = rollouts.option_subtask_success(
            policy, preprocessor, postprocessor, world.rollouts(), subtasks, args.rollouts, args.seed
        )
        option_table = {
            "subtasks": subtasks,
            "rows": [f"option {i}" for i in range(table.success.shape[0])],
            "table": table.success.round(4).tolist(),
            "stopped_by_termination": table.stopped.round(4).tolist(),
        }
    elif not has_options:
        not_applicable["option_subtask_success"] = (
            f"`{policy.name}` has no options that act alone; the table runs each frozen option on each subtask"
        )
    else:
        not_applicable["option_subtask_success"] = f"{cannot_act}: the table runs each frozen option in the world's env"
    if scores["nmi"] is None and parser.no_labels and episodes.labelled:
        not_applicable["nmi"] = parser.no_labels
    nll = None
    if parser.no_action_nll:
        not_applicable["action_nll"] = parser.no_action_nll
    else:
        nll = action_nll(parses)
    success = None
    if acts:
        success = free_runs(args, policy, preprocessor, postprocessor, world, tasks, info)
    else:
        not_applicable["success_rate"] = f"{cannot_act}: free-run success needs the policy acting in its world"
    oracle = None  # after the free runs, so that asking for it leaves every other figure as it was
    if oracle_tasks is not None:
        oracle = rollouts.oracle_report(
            policy, preprocessor, postprocessor, world.rollouts(), [world.task_code(task) for task in oracle_tasks],
            option_table["subtasks"], np.asarray(option_table["table"]), world.subtask_codes, args.rollouts, args.seed,
            args.oracle_switch,
        )
    return {
        **scores,
        "action_nll": nll,
        "held_out": held_out(args.root, selected),
        "label_free": label_free_figures(episodes, parses),
        "parse_statistics": parse_statistics(episodes, parses) if episodes.labelled else None,
        "option_subtask_success": option_table,
        **({"oracle_controller": oracle} if oracle is not None else {}),
        **({"not_applicable": not_applicable} if not_applicable else {}),
        "success_rate": success,
        "mean_success_rate": None if success is None else float(np.mean(list(success.values()))),
        "episodes_parsed": len(parses),
        "frames_parsed": int(episodes.lengths.sum()),
        "split": args.split,
        "episodes": [selected.start, selected.stop],
        "rollouts_per_cell": args.rollouts,
        "policy": str(args.policy),
        "policy_type": policy.name,
        **readout,
        "world": world.name,
        "dataset": {"root": str(args.root), "repo_id": args.repo_id},
        "wall_s": round(time.perf_counter() - started, 2),
    }


def acting_problem(world: Any, policy: Any) -> str | None:
    """Why the policy cannot act in the dataset's world (None: it can): a dataset of no world these tools
    know, or a policy that reads more than the `observation.state` the batch worlds give."""
    from lerobot.utils.constants import OBS_STATE

    from lerobot_policy_ocn.tools.eval.parsing import input_keys

    if world.rollouts is None:
        return f"the dataset is of no world these tools know (robot_type {world.name!r} in meta/info.json)"
    if input_keys(policy) != [OBS_STATE]:
        return f"the {world.name} env gives `{OBS_STATE}` alone and the policy reads {input_keys(policy)}"
    return None


def free_runs(args: argparse.Namespace, policy: Any, preprocessor: Any, postprocessor: Any, world: Any,
              tasks: list[str], info: dict[str, Any]) -> dict[str, float]:
    """The whole policy's success per task in its world, logged to --mcap when asked."""
    from lerobot_policy_ocn.tools.rl import rollouts

    log = None
    if args.mcap is not None:
        from lerobot_policy_ocn.tools.viz.rollout_mcap import RolloutMcapWriter

        state_names = info["features"]["observation.state"]["names"]
        log = RolloutMcapWriter(args.mcap, info["fps"], list(state_names), str(args.policy))
    try:
        return rollouts.free_run_success(
            policy, preprocessor, postprocessor, world.rollouts(), tasks, args.rollouts, args.seed, log
        )
    finally:
        if log is not None:
            log.close()


def summary_line(result: dict[str, Any]) -> str:
    """The one line ocn-eval prints: the parsing scores where there is ground truth, the label-free
    figures always, success where the world runs."""
    def figure(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.3f}"

    free = result["label_free"]
    parts = [] if result["f1_tol1"] is None else [
        f"F1@0 {figure(result['f1_tol0'])}  F1@1 {figure(result['f1_tol1'])}  align {figure(result['align_acc'])}  "
        f"NMI {figure(result['nmi'])}"]
    parts.append(f"NLL {figure(result['action_nll'])}{'' if result['held_out'] else ' (not held out)'}  "
                 f"segments/episode {free['segments_per_episode']:.2f}  "
                 f"mean segment {free['segment_length']['mean']:.1f} frames  switches/frame {free['switch_rate']:.3f}")
    if "option_usage" in free:
        parts.append("option usage " + " ".join(f"{share:.2f}" for share in free["option_usage"]))
    if result["success_rate"] is not None:
        parts.append(f"success {result['mean_success_rate']:.3f}")
    if result["f1_tol1"] is None:
        parts.append("(no ground-truth subtask columns: F1, alignment and NMI need them)")
    return "  ".join(parts)


def write_result(result: dict[str, Any], args: argparse.Namespace) -> list[Path]:
    """The JSON and, for a policy made of options, the option table's PNG beside it, each written
    atomically; a PNG an earlier result left there is removed (--force). Returns what was written."""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, json.dumps(result, indent=2) + "\n")
    table = result["option_subtask_success"]
    png = args.out.with_suffix(".png")
    if table is None:
        png.unlink(missing_ok=True)
        return [args.out]
    run = "/".join(args.policy.parts[-6:-3])
    plot_option_table(np.array(table["table"]), table["subtasks"], png, f"option x subtask success\n{run}")
    return [args.out, png]


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    try:
        result = evaluate(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"ocn-eval: {error}", file=sys.stderr)
        return 2
    try:
        written = write_result(result, args)
    except OSError as error:
        print(json.dumps(result, indent=2))  # the evaluation is not lost with the file
        print(f"ocn-eval: cannot write {error.filename or args.out} ({error.strerror or error}); the result is on "
              "stdout above: free space or choose another --out", file=sys.stderr)
        return 1
    print(summary_line(result))
    print(f"wrote {' and '.join(map(str, written))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
