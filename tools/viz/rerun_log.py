"""What `ocn-view` logs to rerun: the episodes on one timeline, the world's scene, the true subtasks and a
policy's options.

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

from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from tqdm import tqdm

from lerobot_policy_ocn.tools.eval.metrics import segment_starts
from lerobot_policy_ocn.tools.viz.episode import Episode
from lerobot_policy_ocn.tools.viz.segmentation_plot import SWITCH_COLOUR, option_colours, subtask_colours

if TYPE_CHECKING:
    from lerobot_policy_ocn.tools.viz.scenes import Scene
    from lerobot_policy_ocn.tools.worlds import World

TIMELINE = "frame"
TERMINATION_COLOUR = (90, 90, 90)


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


def _summary_markdown(episodes: list[Episode], usage: np.ndarray | None, source: str, world: World) -> str:
    """What was logged (`source` names the dataset and the policy) and, with a policy, the share of
    each subtask's steps per chosen option."""
    steps = sum(e.length for e in episodes)
    text = f"{source}: {len(episodes)} episodes, {steps} steps.\n"
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


def _log_summary(rec: rr.RecordingStream, episodes: list[Episode], source: str, world: World) -> None:
    """Static cross-episode summary: the table, and one bar chart of option usage per subtask."""
    parse = episodes[0].parse
    labelled = episodes[0].subtask_id is not None
    usage = None if parse is None or not labelled else \
        option_usage(episodes, len(world.subtask_codes), parse.p_c.shape[1])
    markdown = _summary_markdown(episodes, usage, source, world)
    rec.log("summary/table", rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)
    if usage is None:
        return
    colours = subtask_colours(len(world.subtask_codes))
    for s in np.flatnonzero(usage.sum(1)):
        share = usage[s] / usage[s].sum()
        rec.log(f"summary/usage/{world.subtask_codes[s]}", rr.BarChart(share, color=colours[s]), static=True)


def log_episodes(rec: rr.RecordingStream, episodes: list[Episode], source: str, world: World, scene: Scene) -> None:
    """Everything of the recording, episode after episode on the `frame` timeline; `source` heads the
    summary (which dataset, which policy)."""
    parse = episodes[0].parse
    _log_styles(rec, 0 if parse is None else parse.p_c.shape[1], world, scene)
    _log_summary(rec, episodes, source, world)
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
