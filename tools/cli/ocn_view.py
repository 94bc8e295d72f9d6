"""`ocn-view`: recorded demonstrations in rerun, with a trained OCN's options drawn over them.

Logs the selected episodes of a dataset, with or without a policy, to an .rrd file (--save), a
spawned viewer (--spawn) or a served web viewer (--serve); --png draws the segmentation of a few
episodes with matplotlib (tools/viz/segmentation_plot.py) instead of or besides the recording.

Timeline `frame` (a sequence): the logged episodes laid one after another, so step t of an
episode is frame offset + t, its offset being the summed lengths of the episodes logged before
it; scrubbing or playing runs through all of them. The `segments/episode` lane and the
`log/episode` lines show where each episode starts, and a frame after the last step ends the
lanes. The world (read from the dataset) draws its own scene and series (`tools/viz/scenes.py`:
Craft's grid and action; Dial's fingertip and keys in 3D, joint angles, fingertip-to-key distances
and motor controls; BabyAI and the datasets of worlds the tools do not know, the action alone). A
dataset without ground-truth subtask columns has no subtask lane nor usage per subtask: the option
lane and the switches alone. Every world's entity paths ([model]: only with --policy;
[truth]: only where the dataset has ground truth):

    segments/episode         StateChange   "episode 16: get wood, get iron", from the episode's first step
    segments/subtask         StateChange   the true subtask ("A get wood", "press 1"), from the first step of each
                                           segment [truth]
    segments/option          StateChange   the chosen option argmax p^c ("option 2"), from each switch [model]
    p_c/option_<k>           Scalars       p^c_t of option k, the controller's option distribution [model]
    termination/e_t          Scalars       e_t, the termination probability (1 at an episode's first step) [model]
    termination/switch       Scalars       e_t at the steps where the chosen option switches, as points [model]
    log/episode              TextLog       one line per episode, at its first step
    log/switch               TextLog       one line per option switch: episode, step, old and new option [model]
    summary/table            TextDocument  what was logged and, with a model, the option usage per subtask
    summary/usage/<code>     BarChart      share of the subtask's steps spent in each chosen option [model, truth]
                                           (code: Craft's letter, Dial's digit)

Styles (series names and colours, the state lanes' colours, the image format) and the summary
are static. Subtask and option colours are those of the PNG. The default blueprint puts the scene,
the summary and the event log on the left, and on the right the segmentation lanes (true subtask
against chosen option) above the p^c and e_t plots and the world's own plots.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from tqdm import tqdm

from lerobot_policy_ocn.ocn_data.episodes_table import read_info
from lerobot_policy_ocn.ocn_data.preflight import check_can_create, check_repo_id
from lerobot_policy_ocn.tools.eval.metrics import segment_starts
from lerobot_policy_ocn.tools.viz.segmentation_plot import (
    SWITCH_COLOUR, EpisodeView, option_colours, plot_segmentation, subtask_colours,
)
from lerobot_policy_ocn.tools.worlds import World, world_of

if TYPE_CHECKING:
    from lerobot_policy_ocn.ocn_data.episodes_table import EpisodeArrays
    from lerobot_policy_ocn.tools.eval.parsing import EpisodeParse
    from lerobot_policy_ocn.tools.viz.scenes import Scene

TIMELINE = "frame"
TERMINATION_COLOUR = (90, 90, 90)
# A contiguous range of episodes and how many of them to read.
Selected = tuple[range, int]


@dataclass
class Episode:
    """One episode to log, cut to its real steps: state [T, S] (None where the dataset has no
    `observation.state`), action [T, A], subtask_index and subtask_id [T] (None without ground truth),
    and the policy's parse (None without a policy)."""

    index: int
    task: str
    state: np.ndarray | None
    action: np.ndarray
    subtask_index: np.ndarray | None
    subtask_id: np.ndarray | None
    parse: EpisodeParse | None

    @property
    def length(self) -> int:
        """Steps of the episode (the action may hold several values per step)."""
        return len(self.action)

    @property
    def title(self) -> str:
        """How lanes, logs and the PNG name the episode."""
        return f"episode {self.index}: {self.task}"


def _episode_selection(text: str) -> int | list[int]:
    """--episodes: a count ("20") or a comma-separated list of episode indices ("3,8,12", "5,")."""
    try:
        if "," in text:
            selection = [int(part) for part in text.split(",") if part.strip()]
        else:
            selection = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a count nor a comma-separated list") from None
    if selection == [] or (isinstance(selection, int) and selection < 1):
        raise argparse.ArgumentTypeError(f"{text!r} selects no episode")
    return selection


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ocn-view", description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--root", type=Path, required=True, help="the LeRobot dataset's folder")
    parser.add_argument("--repo-id", required=True, help="the dataset's repo id, named in the recording")
    parser.add_argument("--split", default="val", help="split of meta/info.json to view: train, val or all")
    parser.add_argument("--episodes", type=_episode_selection, default=20,
                        help="N: the split's first N episodes; or a comma-separated list of episode indices "
                             "(3,8,12; 5, for episode 5 alone), whatever their split")
    parser.add_argument("--policy", type=Path, default=None,
                        help="a pretrained_model folder of an ocn checkpoint; without it, ground truth only")
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument("--save", type=Path, metavar="FILE", help="write the recording to this .rrd file")
    sink.add_argument("--spawn", action="store_true", help="send the recording to a newly spawned rerun viewer")
    sink.add_argument("--serve", action="store_true",
                      help="serve the recording over gRPC with a web viewer, until Ctrl-C")
    parser.add_argument("--png", type=Path, metavar="FILE", help="draw the segmentation of a few episodes to this PNG")
    parser.add_argument("--png-episodes", type=int, default=4, help="how many of the first episodes the PNG draws")
    parser.add_argument("--batch-size", type=int, default=1024, help="episodes per parsing batch")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    if not (args.save or args.spawn or args.serve or args.png):
        parser.error("nothing to do: pass --save FILE, --spawn or --serve, and/or --png FILE")
    if args.png_episodes < 1:
        parser.error("--png-episodes must be at least 1")
    return args


def _episode_ranges(root: Path, info: dict[str, Any], split: str, selection: int | list[int]) -> list[Selected]:
    """The split's first `selection` episodes as one group, or each listed episode as its own group
    (episodes are read as contiguous ranges; listed episodes may lie far apart): (range, at most)."""
    from lerobot_policy_ocn.ocn_data.episodes_table import split_episodes

    if isinstance(selection, int):
        return [(split_episodes(root, split), selection)]
    total = info["total_episodes"]
    outside = sorted({i for i in selection if not 0 <= i < total})
    if outside:
        raise ValueError(f"Episodes {outside} are not in {root}, which has episodes 0 to {total - 1}.")
    return [(range(i, i + 1), 1) for i in selection]


def _episodes_of(group: EpisodeArrays, parses: list[EpisodeParse | None]) -> list[Episode]:
    def cut(values: np.ndarray | None, i: int, n: int) -> np.ndarray | None:
        return None if values is None else values[i, :n]

    return [
        Episode(
            index=int(group.episode_index[i]),
            task=group.tasks[i],
            state=cut(group.state, i, n),
            action=group.action[i, :n],
            subtask_index=cut(group.subtask_index, i, n),
            subtask_id=cut(group.subtask_id, i, n),
            parse=parse,
        )
        for i, (n, parse) in enumerate(zip(group.lengths, parses, strict=True))
    ]


def load_view(args: argparse.Namespace, info: dict[str, Any]) -> list[Episode]:
    """The selected episodes, parsed by the policy when one is given (read with every input it reads).
    Everything that can fail on bad input happens here, before any file or viewer is opened."""
    ranges = _episode_ranges(args.root, info, args.split, args.episodes)
    if args.policy is None:
        from lerobot_policy_ocn.ocn_data.episodes_table import LABELS, load_episodes

        if not all(key in info["features"] for key in LABELS):
            raise ValueError(f"{args.root} has no ground-truth subtask columns, so without --policy there is nothing "
                             "to draw: pass a policy to see its option switches.")
        groups = [load_episodes(args.root, episodes, most) for episodes, most in ranges]
        return [e for group in groups for e in _episodes_of(group, [None] * len(group.tasks))]
    # torch and LeRobot: only with a policy
    from lerobot_policy_ocn.tools.eval.parsing import load_ocn, parse_episodes, policy_episodes

    policy, preprocessor, _ = load_ocn(args.policy, args.device)
    groups = [policy_episodes(policy, args.root, episodes, most) for episodes, most in ranges]
    return [
        e for group in groups
        for e in _episodes_of(group, parse_episodes(policy, preprocessor, group, args.batch_size))
    ]


def option_label(option: int) -> str:
    """How the option lane, the series and the summary name an option."""
    return f"option {option}"


def option_usage(episodes: list[Episode], n_subtasks: int, n_options: int) -> np.ndarray:
    """Steps of each subtask (rows, by subtask id) spent in each chosen option (columns)."""
    counts = np.zeros((n_subtasks, n_options), dtype=np.int64)
    for episode in episodes:
        np.add.at(counts, (episode.subtask_id, episode.parse.option), 1)
    return counts


def _at(offset: int, steps: np.ndarray | list[int]) -> list[rr.TimeColumn]:
    return [rr.TimeColumn(TIMELINE, sequence=offset + np.asarray(steps, dtype=np.int64))]


def _log_styles(rec: rr.RecordingStream, n_options: int, world: World, scene: Scene) -> None:
    """Static styles shared by every episode's columns: logged once, not per step."""
    scene.log_styles(rec)
    labels = world.subtask_labels
    rec.log("segments/subtask", rr.StateConfiguration(
        values=list(labels), colors=subtask_colours(len(labels))), static=True)
    if n_options == 0:
        return
    labels = [option_label(k) for k in range(n_options)]
    colours = option_colours(n_options)
    rec.log("segments/option", rr.StateConfiguration(values=labels, colors=colours), static=True)
    for k, colour in enumerate(colours):
        rec.log(f"p_c/option_{k}", rr.SeriesLines(names=labels[k], colors=colour, widths=2), static=True)
    rec.log("termination/e_t", rr.SeriesLines(names="e_t", colors=TERMINATION_COLOUR, widths=2), static=True)
    rec.log("termination/switch", rr.SeriesPoints(
        names="option switch", colors=SWITCH_COLOUR, markers="cross", marker_sizes=6), static=True)


def _log_episode(rec: rr.RecordingStream, episode: Episode, offset: int, world: World, scene: Scene) -> None:
    """One episode from frame `offset` on, as one send_columns call per entity."""
    steps = np.arange(episode.length)
    scene.log_steps(rec, episode, _at(offset, steps))
    rec.send_columns("segments/episode", indexes=_at(offset, [0]),
                     columns=rr.StateChange.columns(state=[episode.title]))
    line = f"{episode.title} ({steps.size} steps)"
    if episode.subtask_index is not None:
        starts = segment_starts(episode.subtask_index)
        truth = [world.subtask_labels[s] for s in episode.subtask_id[starts]]
        rec.send_columns("segments/subtask", indexes=_at(offset, starts), columns=rr.StateChange.columns(state=truth))
        line += f": subtasks {', '.join(truth)}"
    rec.send_columns("log/episode", indexes=_at(offset, [0]),
                     columns=rr.TextLog.columns(text=[line], level=["INFO"]))
    if episode.parse is not None:
        _log_parse(rec, episode, offset)


def _log_parse(rec: rr.RecordingStream, episode: Episode, offset: int) -> None:
    """The policy's hierarchy over one episode: option lane, p^c, e_t and the option switches."""
    parse = episode.parse
    steps = np.arange(parse.option.size)
    starts = np.append(0, parse.switches)
    chosen = [option_label(o) for o in parse.option[starts]]
    rec.send_columns("segments/option", indexes=_at(offset, starts), columns=rr.StateChange.columns(state=chosen))
    for k in range(parse.p_c.shape[1]):
        rec.send_columns(f"p_c/option_{k}", indexes=_at(offset, steps),
                         columns=rr.Scalars.columns(scalars=parse.p_c[:, k]))
    rec.send_columns("termination/e_t", indexes=_at(offset, steps), columns=rr.Scalars.columns(scalars=parse.end))
    switches = parse.switches
    if switches.size == 0:
        return
    rec.send_columns("termination/switch", indexes=_at(offset, switches),
                     columns=rr.Scalars.columns(scalars=parse.end[switches]))
    lines = [
        f"episode {episode.index} step {t}: option {parse.option[t - 1]} -> {parse.option[t]} (e_t {parse.end[t]:.2f})"
        for t in switches
    ]
    rec.send_columns("log/switch", indexes=_at(offset, switches),
                     columns=rr.TextLog.columns(text=lines, level=["INFO"] * len(lines)))


def _summary_markdown(
    episodes: list[Episode], usage: np.ndarray | None, args: argparse.Namespace, world: World
) -> str:
    """What was logged and, with a policy, the share of each subtask's steps per chosen option."""
    steps = sum(e.length for e in episodes)
    policy = f"policy `{args.policy}`" if args.policy else "no policy (ground truth only)"
    text = f"**{args.repo_id}** (`{args.root}`): {len(episodes)} episodes, {steps} steps; {policy}.\n"
    if usage is None and episodes[0].parse is not None:
        options = np.concatenate([e.parse.option for e in episodes])
        shares = np.bincount(options, minlength=episodes[0].parse.p_c.shape[1]) / options.size
        return text + "\nNo ground-truth subtasks; share of the steps spent in each chosen option (argmax p^c): " + \
            ", ".join(f"{option_label(k)} {share:.2f}" for k, share in enumerate(shares)) + ".\n"
    if usage is None:
        return text
    options = [option_label(k) for k in range(usage.shape[1])]
    rows = [
        f"| {world.subtask_labels[s]} | {usage[s].sum()} | "
        + " | ".join(f"{p:.2f}" for p in usage[s] / usage[s].sum()) + " |"
        for s in np.flatnonzero(usage.sum(1))
    ]
    return "\n".join([
        text,
        "Share of each subtask's steps spent in each chosen option (argmax p^c):\n",
        "| subtask | steps | " + " | ".join(options) + " |",
        "|---" * (len(options) + 2) + "|",
        *rows,
    ]) + "\n"


def _log_summary(rec: rr.RecordingStream, episodes: list[Episode], args: argparse.Namespace, world: World) -> None:
    """Static cross-episode summary: the table, and one bar chart of option usage per subtask."""
    parse = episodes[0].parse
    labelled = episodes[0].subtask_id is not None
    usage = None if parse is None or not labelled else \
        option_usage(episodes, len(world.subtask_codes), parse.p_c.shape[1])
    markdown = _summary_markdown(episodes, usage, args, world)
    rec.log("summary/table", rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)
    if usage is None:
        return
    colours = subtask_colours(len(world.subtask_codes))
    for s in np.flatnonzero(usage.sum(1)):
        share = usage[s] / usage[s].sum()
        rec.log(f"summary/usage/{world.subtask_codes[s]}", rr.BarChart(share, color=colours[s]), static=True)


def log_episodes(
    rec: rr.RecordingStream, episodes: list[Episode], args: argparse.Namespace, world: World, scene: Scene
) -> None:
    """Everything of the recording, episode after episode on the `frame` timeline."""
    parse = episodes[0].parse
    _log_styles(rec, 0 if parse is None else parse.p_c.shape[1], world, scene)
    _log_summary(rec, episodes, args, world)
    offset = 0
    for episode in tqdm(episodes, desc="ocn-view", unit="ep"):
        _log_episode(rec, episode, offset, world, scene)
        offset += episode.length
    lanes = ["segments/episode"] + (["segments/subtask"] if episodes[0].subtask_id is not None else []) + \
        ([] if parse is None else ["segments/option"])
    for lane in lanes:  # an empty state ends the last segment of every lane
        rec.send_columns(lane, indexes=_at(offset, [0]), columns=rr.StateChange.columns(state=[""]))


def blueprint(subtasks: list[int], has_model: bool, fps: float, world: World, scene: Scene) -> rrb.Blueprint:
    """Default layout: scene, summary and event log on the left; on the right the segmentation
    lanes above the p^c and e_t plots and the world's own plots, all following the `frame` cursor."""
    summary = [rrb.TextDocumentView(origin="summary/table", name="summary")]
    if has_model:
        summary.append(rrb.Grid(
            *[rrb.BarChartView(origin=f"summary/usage/{world.subtask_codes[s]}",
                               name=f"{world.subtask_labels[s]}: options")
              for s in subtasks],
            name="option usage per subtask",
        ))
    left = rrb.Vertical(
        scene.view(),
        rrb.Tabs(*summary),
        rrb.TextLogView(origin="log", name="episodes and option switches"),
        row_shares=[3, 2, 2],
    )
    unit = rrb.ScalarAxis(range=(-0.05, 1.05), zoom_lock=True)
    plots = [rrb.StateTimelineView(origin="segments", name="segmentation: true subtask against chosen option")]
    if has_model:
        plots += [
            rrb.TimeSeriesView(origin="p_c", name="controller's option distribution p^c", axis_y=unit),
            rrb.TimeSeriesView(origin="termination", name="termination e_t and option switches", axis_y=unit),
        ]
    own = scene.plots()
    right = rrb.Vertical(*plots, *own, row_shares=[2] * len(plots) + [1] * len(own))
    return rrb.Blueprint(
        rrb.Horizontal(left, right, column_shares=[2, 3]),
        rrb.TimePanel(timeline=TIMELINE, fps=fps, state="expanded"),
        rrb.SelectionPanel(state="collapsed"),
    )


def _open_recording(args: argparse.Namespace, layout: rrb.Blueprint) -> rr.RecordingStream:
    """The recording stream, connected to the sink chosen on the command line."""
    rec = rr.RecordingStream("ocn_view")
    if args.save:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        rec.save(args.save, default_blueprint=layout)
    elif args.spawn:
        rec.spawn(default_blueprint=layout)
    else:
        address = rec.serve_grpc(default_blueprint=layout)
        rr.serve_web_viewer(open_browser=False, connect_to=address)
        print(f"serving {address}; open http://localhost:9090/?url={quote(address, safe='')} (Ctrl-C to stop)")
    rec.send_recording_name(args.repo_id)
    return rec


def write_recording(episodes: list[Episode], args: argparse.Namespace, fps: float, world: World) -> rr.RecordingStream:
    """Log everything to the chosen sink and flush. Returns the stream: a served one lives only as
    long as it does."""
    subtasks = sorted({int(s) for e in episodes if e.subtask_id is not None for s in np.unique(e.subtask_id)})
    scene = world.scene()
    rec = _open_recording(args, blueprint(subtasks, episodes[0].parse is not None, fps, world, scene))
    log_episodes(rec, episodes, args, world, scene)
    rec.flush()
    return rec


def write_png(episodes: list[Episode], args: argparse.Namespace, world: World) -> None:
    """The segmentation of the first --png-episodes episodes, drawn with matplotlib."""
    views = [EpisodeView(e.title, e.subtask_index, e.subtask_id, e.parse) for e in episodes[: args.png_episodes]]
    args.png.parent.mkdir(parents=True, exist_ok=True)
    truth = "true subtasks" if episodes[0].subtask_id is not None else "no ground truth"
    title = f"{args.repo_id}: {truth} against chosen options\npolicy {args.policy}"
    plot_segmentation(views, args.png, title if args.policy else f"{args.repo_id}: {truth}",
                      world.subtask_codes, world.subtask_labels)


def _wait_for_interrupt() -> None:
    """A served recording lives as long as this process: keep it up until Ctrl-C."""
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


def check_outputs(args: argparse.Namespace) -> None:
    """Refuse, before any work, a repo id that is not ORG/NAME and an output that cannot be written."""
    check_repo_id(args.repo_id)
    for path, flag in ((args.save, "--save"), (args.png, "--png")):
        if path is not None:
            check_can_create(path, flag)


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    try:
        check_outputs(args)
        world = world_of(args.root)
        info = read_info(args.root)
        episodes = load_view(args, info)
    except (FileNotFoundError, ValueError) as error:
        print(f"ocn-view: {error}", file=sys.stderr)
        return 2
    if args.png:
        write_png(episodes, args, world)
        print(f"wrote {args.png}")
    if not (args.save or args.spawn or args.serve):
        return 0
    started = time.perf_counter()
    rec = write_recording(episodes, args, float(info["fps"]), world)
    steps = sum(e.length for e in episodes)
    target = args.save or ("the spawned viewer" if args.spawn else "the server")
    print(f"logged {len(episodes)} episodes ({steps} steps) to {target} in {time.perf_counter() - started:.1f} s")
    if args.serve:
        _wait_for_interrupt()
    rec.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())
