"""`python -m tools.fast_imitation`: OCN behaviour cloning on whole episodes held in memory, for
trying training recipes quickly; the reproductions train with `lerobot-train`.

On 2 CPU cores `lerobot-train` spends most of each step waiting for LeRobot's windowed loading
(`results/bench_train.md`), so one 5,000-step S1 run takes about an hour. This loop trains the
same policy on the same objective about six times faster: `policy.forward` on batches of whole
episodes, each drawn with probability proportional to its length (what sampling a window at every
frame with `window_start=episode` gives), LeRobot's Adam preset with the policy's gradient clip,
and every `--eval-every` steps the shared parsing metrics on the validation episodes. It writes
the curve as JSON; `plot` draws curves of several runs. Craft's processors are identities, so the
batches go to the policy as they are stored.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lerobot.utils.constants import ACTION, OBS_STATE

CURVE_METRICS = ("nmi", "f1_tol1", "align_acc")
# The last training batch's statistics kept at each evaluation (--supervise-options: no usage
# imbalance, and the controller's and terminations' supervised losses).
TRAINING_STATS = ("nll", "mean_end", "usage_imbalance", "choice_ce", "termination_bce", "mean_end_at_switch",
                  "mean_end_elsewhere")
# Curve metrics that are fractions, drawn on a 0-1 axis (the others, such as nll, on their own range).
FRACTIONS = {"nmi", "f1_tol0", "f1_tol1", "align_acc", "mean_success_rate", "mean_end"}
# Curve metrics where lower is better (the best of several runs is their least).
LOWER_IS_BETTER = {"nll", "val_nll"}


def world_settings(world: str) -> list[str]:
    """`FIELD=VALUE` policy settings of a world's imitation study, under `--set`: Craft's S1 main variant
    (3 options, T = 10), Dial's base (`tools.reproduce.dial.DIAL_POLICY`: 4 options, T = 10, identity
    encoder, continuous actions, long episodes cut; `ocn-reproduce dial` adds its induction recipe)."""
    if world == "dial":
        from tools.reproduce.dial import DIAL_POLICY, N_OPTIONS

        return [f"n_options={N_OPTIONS}", "temperature=10.0", *(f"{key}={value}" for key, value in DIAL_POLICY.items())]
    return ["n_options=3", "temperature=10.0"]


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """`key=value` pairs of OCNConfig fields, each value cast to its field's default's type."""
    from policies.ocn import OCNConfig

    fields = {field.name: field for field in dataclasses.fields(OCNConfig)}
    overrides: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in fields:
            raise SystemExit(f"--set {pair!r}: expected FIELD=VALUE with an OCNConfig field.")
        default = fields[key].default
        if isinstance(default, bool):
            if value.lower() not in ("true", "false"):
                raise SystemExit(f"--set {pair!r}: {key} takes true or false.")
            overrides[key] = value.lower() == "true"
        else:
            overrides[key] = type(default)(value) if isinstance(default, int | float | str) else value
    return overrides


def episode_batch(split: Any, rows: np.ndarray, width: int | None = None) -> dict[str, Any]:
    """A training batch of whole episodes (rows of an `ocn_data.episodes_table.EpisodeArrays`), as
    `policy.forward` takes it, cut after the longest one or after `width` frames."""
    used = min(int(split.lengths[rows].max()), width or split.state.shape[1])
    return {OBS_STATE: torch.from_numpy(split.state[rows, :used]).float(),
            ACTION: torch.from_numpy(split.action[rows, :used]).float(),
            f"{ACTION}_is_pad": torch.from_numpy(~split.mask[rows, :used]),
            "task": [split.tasks[i] for i in rows.tolist()]}


def frame_options(split: Any, subtask_ids: np.ndarray, labels_file: Path | None = None) -> np.ndarray:
    """Each frame's option under `--supervise-options` [E, T] (-1 on padding): the rank of its
    ground-truth subtask id among `subtask_ids` (the training split's, sorted), or the labels that
    `labels_file` (written by `tools.affine_segmentation`) holds for the split's episodes."""
    if labels_file is not None:
        from ocn_data.option_labels import read_labels

        return read_labels(labels_file, split.episode_index, split.lengths, split.mask.shape[1])
    return np.where(split.mask, np.searchsorted(subtask_ids, split.subtask_id), -1)


def option_labels(options: np.ndarray, rows: np.ndarray, lengths: np.ndarray, width: int | None = None) -> torch.Tensor:
    """The rows of `frame_options` in a batch [B, T], cut as `episode_batch` cuts."""
    used = min(int(lengths[rows].max()), width or options.shape[1])
    return torch.from_numpy(options[rows, :used])


def episode_draws(lengths: np.ndarray, batch_size: int, sampler: str, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """Rows of the episodes of each batch, each episode drawn in proportion to its length.

    "replacement": every batch drawn independently. "epoch": as LeRobot's `EpisodeAwareSampler`
    under `lerobot-train`, a shuffled pass over every frame (a frame stands for its episode's window),
    batches cut from it in order, then the next pass (here a batch may span two passes)."""
    if sampler == "replacement":
        weights = lengths / lengths.sum()
        while True:
            yield rng.choice(len(lengths), batch_size, p=weights)
    frame_episodes = np.repeat(np.arange(len(lengths)), lengths)
    queue = np.empty(0, dtype=np.int64)
    while True:
        while len(queue) < batch_size:
            queue = np.concatenate([queue, rng.permutation(frame_episodes)])
        yield queue[:batch_size]
        queue = queue[batch_size:]


def train(args: argparse.Namespace) -> dict[str, Any]:
    """Train one seed, scoring the parse every `eval_every` steps; returns (and writes) the curve."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from ocn_data.episodes_table import load_episodes, split_episodes
    from policies.ocn import OCNConfig, OCNPolicy
    from tools.episode_parsing import action_nll, parse_statistics, score_segmentations, segment_episodes
    from tools.rollouts import free_run_success
    from tools.worlds import world_of

    if args.termination_weight != 1.0 and not args.supervise_options:
        raise SystemExit("--termination-weight weighs the supervised terminations' loss; it needs --supervise-options.")
    if args.option_labels is not None and not args.supervise_options:
        raise SystemExit("--option-labels replaces the ground truth that --supervise-options trains on; it needs it.")
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    torch.set_num_threads(args.threads)
    world = world_of(args.root)
    meta = LeRobotDatasetMetadata(args.repo_id, root=args.root)
    # Every batch row starts at its episode's first frame, which is how window_start="any" reads a row.
    overrides = {**parse_overrides(args.set), "window_start": "any"}
    if args.init is None:
        config = OCNConfig(device="cpu", window_size=args.window_size,
                           **{**parse_overrides(world_settings(world.name)), **overrides})
        policy = make_policy(config, ds_meta=meta)
    else:
        config = dataclasses.replace(PreTrainedConfig.from_pretrained(args.init), device="cpu", **overrides)
        policy = OCNPolicy.from_pretrained(args.init, config=config)
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=meta.stats)
    optimizer = config.get_optimizer_preset().build(policy.get_optim_params())
    schedule = config.get_scheduler_preset()
    scheduler = schedule.build(optimizer, num_training_steps=args.steps) if schedule is not None else None
    train_split = load_episodes(args.root, split_episodes(args.root, "train"))
    val_split = load_episodes(args.root, split_episodes(args.root, "val"), max_episodes=args.val_episodes)
    draw = episode_draws(np.minimum(train_split.lengths, config.window_size), args.batch_size, args.sampler, rng)
    tasks = [world.task_key(task) for task in sorted(set(val_split.tasks), key=config.tasks.index)]
    subtask_ids = np.unique(train_split.subtask_id[train_split.mask])
    if args.supervise_options and args.option_labels is None and len(subtask_ids) > config.n_options:
        raise SystemExit(f"--supervise-options gives each of the {len(subtask_ids)} subtasks its own option; "
                         f"n_options is {config.n_options}.")
    options = frame_options(train_split, subtask_ids, args.option_labels) if args.supervise_options else None
    if options is not None and options.max() >= config.n_options:
        raise SystemExit(f"{args.option_labels} labels frames with option {options.max()}; "
                         f"n_options is {config.n_options}.")
    curve: list[dict[str, Any]] = []
    result = {"command": "python -m tools.fast_imitation " + " ".join(args.argv), "world": world.name,
              "settings": dataclasses.asdict(config) | {"seed": args.seed, "batch_size": args.batch_size,
                                                        "steps": args.steps, "sampler": args.sampler,
                                                        "supervise_options": args.supervise_options,
                                                        "option_labels": str(args.option_labels)
                                                        if args.option_labels is not None else None,
                                                        "termination_weight": args.termination_weight}, "curve": curve}
    started, frames = time.perf_counter(), 0
    for step in range(1, args.steps + 1):
        rows = next(draw)
        batch = preprocessor(episode_batch(train_split, rows, config.window_size))
        policy.train()
        if args.supervise_options:
            labels = option_labels(options, rows, train_split.lengths, config.window_size)
            loss, stats = policy.labelled_forward(batch, labels, args.termination_weight)
        else:
            loss, stats = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), config.optimizer_grad_clip_norm)
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        frames += stats["frames_used"]
        if step % args.eval_every == 0 or step == args.steps:
            policy.eval()
            parses = segment_episodes(policy, preprocessor, val_split)
            shape = parse_statistics(val_split, parses)
            point = {"step": step, "lr": optimizer.param_groups[0]["lr"],
                     **{key: stats[key] for key in TRAINING_STATS if key in stats},
                     "val_nll": action_nll(parses), **score_segmentations(val_split, parses),
                     "option_share": shape.get("label_share"), "option_by_subtask": shape.get("label_by_subtask"),
                     "option_by_subtask_third": shape.get("label_by_subtask_third"),
                     "option_by_transition": shape.get("label_by_transition"),
                     "boundary_offsets": shape["boundary_offsets"],
                     "boundary_offsets_by_previous_action": shape.get("boundary_offsets_by_previous_action"),
                     "train_frames_per_s": frames / (time.perf_counter() - started)}
            if args.rollouts:
                success = free_run_success(policy, preprocessor, postprocessor, world.rollouts(), tasks,
                                           args.rollouts, args.seed)
                point |= {"success_rate": success, "mean_success_rate": float(np.mean(list(success.values())))}
            curve.append(point)
            print(json.dumps(point), flush=True)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            # default=str: a config read from a resumed lerobot-train checkpoint holds its pretrained_path as a Path.
            args.out.write_text(json.dumps(result, indent=1, default=str) + "\n")
            if args.save is not None:
                policy.save_pretrained(args.save)
                for processor in (preprocessor, postprocessor):
                    processor.save_pretrained(args.save)
    return result


def split_table(paths: list[Path], threshold: float, metrics: tuple[str, ...] = CURVE_METRICS) -> str:
    """Markdown: per curve file, the first scored step whose NMI reaches `threshold` (when the options
    split) and the training episodes drawn by then, and the last point's `metrics`."""
    lines = [f"| run | batch | first step with NMI >= {threshold:g} | episodes drawn by then | last step | "
             + " | ".join(metrics) + " |", "|---|---|---|---|---|" + "---|" * len(metrics)]
    for path in paths:
        result = json.loads(path.read_text())
        curve, batch = result["curve"], result["settings"]["batch_size"]
        split = next((point["step"] for point in curve if point["nmi"] >= threshold), None)
        when = "not within the run | -" if split is None else f"{split} | {split * batch:,}"
        last = curve[-1]
        lines.append(f"| {path.stem} | {batch} | {when} | {last['step']} | "
                     + " | ".join(f"{last[metric]:.3f}" for metric in metrics) + " |")
    return "\n".join(lines)


def peak_table(paths: list[Path], peak: str, metrics: tuple[str, ...] = CURVE_METRICS) -> str:
    """Markdown: per curve file, the first scored point where `peak` is highest and `metrics` there,
    for runs whose last point is not their best (a run that diverges late)."""
    lines = [f"| run | step of highest {peak} | " + " | ".join(metrics) + " |", "|---|---|" + "---|" * len(metrics)]
    for path in paths:
        curve = json.loads(path.read_text())["curve"]
        best = max(curve, key=lambda point: point[peak])
        lines.append(f"| {path.stem} | {best['step']} | "
                     + " | ".join(f"{best[metric]:.3f}" for metric in metrics) + " |")
    return "\n".join(lines)


def _point(path: Path, curve: list[dict[str, Any]], step: int | None) -> dict[str, Any]:
    """The curve's evaluation at `step` (its last one for None)."""
    if step is None:
        return curve[-1]
    at = next((point for point in curve if point["step"] == step), None)
    if at is None:
        raise SystemExit(f"{path} has no evaluation at step {step}.")
    return at


def restart_rows(paths: list[Path], select_step: int,
                 score_step: int | None) -> list[tuple[float, str, dict[str, Any]]]:
    """Per curve file, its validation NLL at `select_step`, its name and its point at `score_step`
    (the last one for None), ordered by that NLL: the first is the restart `runs.Restarts` keeps."""
    rows = []
    for path in paths:
        curve = json.loads(path.read_text())["curve"]
        rows.append((_point(path, curve, select_step)["val_nll"], path.stem, _point(path, curve, score_step)))
    return sorted(rows, key=lambda row: row[0])


def restart_table(rows: list[tuple[float, str, dict[str, Any]]], select_step: int,
                  metrics: tuple[str, ...] = CURVE_METRICS) -> str:
    """Markdown: the `restart_rows` of curve files read as restarts of one recipe, in their order by
    validation NLL at `select_step` (the first row is the one `ocn-reproduce dial` keeps), with `metrics`
    at their scored point: whether the likeliest restarts parse best."""
    lines = [f"| run | val NLL at step {select_step} | scored at step | " + " | ".join(metrics) + " |",
             "|---|---|---|" + "---|" * len(metrics)]
    for nll, name, point in rows:
        scores = " | ".join(f"{point[metric]:.3f}" for metric in metrics)
        lines.append(f"| {name} | {nll:.3f} | {point['step']} | {scores} |")
    return "\n".join(lines)


def restart_gain(rows: list[tuple[float, str, dict[str, Any]]], metric: str, count: int) -> dict[str, float]:
    """What choosing among `count` restarts by validation NLL is worth, over every set of `count` of
    the `restart_rows`: the mean `metric` (at their scored point) of one restart, of the likeliest of
    the set, and of the set's best by `metric` itself (for a parsing score, which reads the labels, the
    ceiling of any choice)."""
    from itertools import combinations

    if not 1 <= count <= len(rows):
        raise SystemExit(f"--restarts {count}: choose among 1..{len(rows)} curve files.")
    sets = list(combinations([point[metric] for _, _, point in rows], count))  # each set in NLL order
    return {"sets": len(sets), "one": float(np.mean([point[metric] for _, _, point in rows])),
            "likeliest": float(np.mean([values[0] for values in sets])),
            "best": float(np.mean([(min if metric in LOWER_IS_BETTER else max)(values) for values in sets]))}


def plot(args: argparse.Namespace) -> None:
    """One panel per metric of `--metrics`, one line per curve file, labelled by the file's stem,
    against training steps or (`--x episodes`) the episodes drawn, which compares runs of different
    batch sizes; prints `split_table` (and `peak_table`, `restart_table` when asked)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = tuple(args.metrics.split(","))
    curves = {path: json.loads(path.read_text()) for path in args.curves}
    wanted = metrics + ((args.peak,) if args.peak else ())
    for path, result in curves.items():
        missing = [metric for metric in wanted if metric not in result["curve"][-1]]
        if missing:
            raise SystemExit(f"{path} has no {', '.join(missing)} in its curve (free-run success needs --rollouts).")
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.5 * len(metrics), 3.6), squeeze=False)
    if len(curves) > 10:  # past the default cycle's 10 colours, so that no two runs share one
        for ax in axes[0]:
            ax.set_prop_cycle(color=plt.get_cmap("tab20").colors)
    for path, result in curves.items():
        scale = result["settings"]["batch_size"] if args.x == "episodes" else 1
        curve = result["curve"]
        for ax, metric in zip(axes[0], metrics, strict=True):
            ax.plot([p["step"] * scale for p in curve], [p[metric] for p in curve], marker=".", label=path.stem)
    for ax, metric in zip(axes[0], metrics, strict=True):
        ax.set_title(metric)
        ax.set_xlabel("training step" if args.x == "step" else "training episodes drawn")
        if metric in FRACTIONS:
            ax.set_ylim(0, 1.02)
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.png, dpi=110)
    plt.close(fig)
    print(split_table(args.curves, args.split_nmi, metrics))
    if args.peak:
        print()
        print(peak_table(args.curves, args.peak, metrics))
    if args.select_step:
        print()
        rows = restart_rows(args.curves, args.select_step, args.score_step)
        print(restart_table(rows, args.select_step, metrics))
        for metric in metrics:
            gain = restart_gain(rows, metric, args.restarts)
            print(f"\n{metric} over all {gain['sets']} sets of {args.restarts}: one restart {gain['one']:.3f}, the "
                  f"likeliest at step {args.select_step} {gain['likeliest']:.3f}, the best {gain['best']:.3f}")


def main(argv: list[str] | None = None) -> int:
    import sys

    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m tools.fast_imitation", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("train", help="train one seed and write its curve",
                         formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    run.add_argument("--root", type=Path, required=True,
                     help="a record_demos dataset (Craft or Dial) with train/val splits")
    run.add_argument("--repo-id", default="local/craft_s1")
    run.add_argument("--out", type=Path, required=True, help="curve JSON, rewritten at every evaluation")
    run.add_argument("--steps", type=int, default=5000)
    run.add_argument("--batch-size", type=int, default=128, help="episodes per step")
    run.add_argument("--window-size", type=int, default=24,
                     help="frames per episode trained on; longer episodes train on their first ones")
    run.add_argument("--seed", type=int, default=1)
    run.add_argument("--sampler", choices=("replacement", "epoch"), default="replacement",
                     help="episodes of a batch drawn independently, or LeRobot's shuffled passes over all frames")
    run.add_argument("--eval-every", type=int, default=500)
    run.add_argument("--val-episodes", type=int, default=1200, help="validation episodes scored (the first ones)")
    run.add_argument("--threads", type=int, default=1)
    run.add_argument("--rollouts", type=int, default=0,
                     help="env episodes per validation task for free-run success at every evaluation (0: none)")
    run.add_argument("--init", type=Path, default=None,
                     help="continue an ocn pretrained_model folder (its config, then --set) instead of a fresh policy; "
                          "the optimizer starts afresh")
    run.add_argument("--save", type=Path, default=None,
                     help="also save the policy here as a pretrained_model folder (for ocn-eval, ocn-view) at every "
                          "evaluation, so the folder holds the latest one")
    run.add_argument("--supervise-options", action="store_true",
                     help="give the split instead of inducing it: each frame's option is its ground-truth subtask's "
                          "(one option per subtask of the training split), the controller learns the labelled choice "
                          "at each switch and the options' terminations the switches (OCNPolicy.labelled_forward; "
                          "under hierarchy=moe the controller learns the label at every frame); "
                          "evaluation runs the model as usual. What the model can do once the split is found")
    run.add_argument("--option-labels", type=Path, default=None,
                     help="with --supervise-options: train on these per-frame options (an .npz of "
                          "`python -m tools.affine_segmentation`, which reads no labels) instead of the ground truth")
    run.add_argument("--termination-weight", type=float, default=1.0,
                     help="with --supervise-options: the weight of the terminations' cross-entropy in the loss")
    run.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                     help="OCNConfig fields, over the world's imitation settings (Craft: n_options=3, "
                          "temperature=10.0; Dial: 4 options, T = 10 and DIAL_POLICY of tools/reproduce/dial.py) "
                          "or over --init's config")
    draw = sub.add_parser("plot", help="draw the curves of several runs into one PNG and print when each split")
    draw.add_argument("curves", type=Path, nargs="+")
    draw.add_argument("--png", type=Path, required=True)
    draw.add_argument("--x", choices=("step", "episodes"), default="step",
                      help="the curves' axis: training steps, or episodes drawn (steps times the run's batch size)")
    draw.add_argument("--metrics", default=",".join(CURVE_METRICS),
                      help="comma-separated curve metrics, one panel each (also nll, mean_end, f1_tol0, and "
                           "mean_success_rate for runs trained with --rollouts)")
    draw.add_argument("--split-nmi", type=float, default=0.9,
                      help="the NMI at which the printed table counts the options as split")
    draw.add_argument("--peak", metavar="METRIC",
                      help="also print each run's point where this curve metric is highest, with --metrics there")
    draw.add_argument("--select-step", type=int,
                      help="also print the runs as restarts ordered by their validation NLL at this step, with "
                           "--metrics at --score-step, and what choosing the likeliest of --restarts runs is worth")
    draw.add_argument("--score-step", type=int, help="with --select-step: the step scored (default: each run's last)")
    draw.add_argument("--restarts", type=int, default=3, help="with --select-step: the restarts chosen among")
    args = parser.parse_args(argv)
    args.argv = argv
    if args.command == "train":
        train(args)
    else:
        plot(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
