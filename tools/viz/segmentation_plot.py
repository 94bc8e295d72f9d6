"""Segmentation of a few episodes as a static PNG: true subtasks against the OCN's chosen options.

One column per episode. The top panel has two bars of coloured segments: the ground-truth
subtasks (upper bar) and the chosen option argmax p^c (lower bar); below it the controller's option
distribution p^c over time and the termination probability e_t, with the steps where the chosen
option switches marked. Without a model only the subtask bar is drawn; without ground truth, only
the option bar. The colours are shared
with `ocn-view`'s rerun recording, so a subtask or an option looks the same in both.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lerobot_policy_ocn.tools.eval.metrics import segment_starts

if TYPE_CHECKING:  # the parse module loads torch and LeRobot; drawing needs neither
    from lerobot_policy_ocn.tools.eval.parsing import EpisodeParse

# Subtask colours by subtask id (matplotlib's tab10: Craft's 8 subtasks, Dial's 10 digits), option
# colours by option index (Dark2): two different palettes, since option k is not subtask k.
SUBTASK_COLOURS = np.array(
    [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
     (148, 103, 189), (140, 86, 75), (227, 119, 194), (188, 189, 34),
     (127, 127, 127), (23, 190, 207)],
    dtype=np.uint8,
)
OPTION_COLOURS = np.array(
    [(27, 158, 119), (217, 95, 2), (117, 112, 179), (231, 41, 138),
     (102, 166, 30), (230, 171, 2), (166, 118, 29), (102, 102, 102)],
    dtype=np.uint8,
)
SWITCH_COLOUR = (200, 0, 0)


def option_colours(n_options: int) -> np.ndarray:
    """RGB uint8 [n_options, 3]; the palette repeats past 8 options."""
    return OPTION_COLOURS[np.arange(n_options) % len(OPTION_COLOURS)]


def subtask_colours(n_subtasks: int) -> np.ndarray:
    """RGB uint8 [n_subtasks, 3] of a world's subtask ids 0 .. n_subtasks - 1."""
    if n_subtasks > len(SUBTASK_COLOURS):
        raise ValueError(f"{n_subtasks} subtasks, but the palette has {len(SUBTASK_COLOURS)} colours.")
    return SUBTASK_COLOURS[:n_subtasks]


@dataclass
class EpisodeView:
    """What the PNG draws of one episode: subtask_index [T] (which position in the task, so
    repeated subtasks stay apart) and subtask_id [T] (which subtask), None without ground truth, and
    the parse if any (one of the two at least)."""

    title: str
    subtask_index: np.ndarray | None
    subtask_id: np.ndarray | None
    parse: EpisodeParse | None


def _rgb(colour: Sequence[int]) -> tuple[float, ...]:
    return tuple(c / 255 for c in colour)


def _draw_bar(ax, starts: np.ndarray, labels: np.ndarray, length: int, y: float, colours: np.ndarray,
              names: Sequence[str]) -> None:
    """One row of segments from `starts` to the next start, coloured and named by their label."""
    stops = np.append(starts[1:], length)
    for start, stop in zip(starts, stops, strict=True):
        label = int(labels[start])
        ax.broken_barh([(start - 0.5, stop - start)], (y, 0.8), facecolors=_rgb(colours[label]), edgecolor="white")
        ax.text((start + stop - 1) / 2, y + 0.4, names[label], ha="center", va="center", fontsize=7, color="white")


def _draw_episode(axes: Sequence, episode: EpisodeView, codes: Sequence[str]) -> None:
    """The column of one episode: bars (subtasks named by their `codes`), then p^c and e_t when
    there is a parse."""
    bars = axes[0]
    bars.set_title(episode.title, fontsize=8)
    labelled = episode.subtask_id is not None
    if labelled:
        _draw_bar(bars, segment_starts(episode.subtask_index), episode.subtask_id, episode.subtask_id.size, 1.1,
                  SUBTASK_COLOURS, codes)
        bars.set_yticks([1.5], ["subtask"])
    if episode.parse is None:
        bars.set_ylim(1.0, 2.0)
        bars.set_xlabel("step")
        return
    parse = episode.parse
    length = parse.option.size
    bars.set_ylim(0.0, 2.0 if labelled else 1.0)
    colours = option_colours(parse.p_c.shape[1])
    _draw_bar(bars, np.append(0, parse.switches), parse.option, length, 0.1, colours,
              [f"o{k}" for k in range(parse.p_c.shape[1])])
    bars.set_yticks([0.5, 1.5] if labelled else [0.5], ["option", "subtask"] if labelled else ["option"])
    steps = np.arange(length)
    for k in range(parse.p_c.shape[1]):
        axes[1].plot(steps, parse.p_c[:, k], color=_rgb(colours[k]), lw=1.5)
    axes[1].set_ylim(-0.05, 1.05)
    axes[1].set_ylabel("p^c", fontsize=8)
    axes[2].plot(steps, parse.end, color="0.3", lw=1.2)
    switches = parse.switches
    axes[2].scatter(switches, parse.end[switches], marker="x", color=_rgb(SWITCH_COLOUR), zorder=3)
    axes[2].set_ylim(-0.05, 1.05)
    axes[2].set_ylabel("e_t", fontsize=8)
    axes[2].set_xlabel("step")
    for ax in axes[1:]:
        for switch in switches:
            ax.axvline(switch, color=_rgb(SWITCH_COLOUR), lw=0.6, ls=":")


def _legend_handles(episodes: Sequence[EpisodeView], labels: Sequence[str]) -> list:
    """Patches for the subtasks drawn (named by their `labels`) and lines for the options, one
    legend for the figure."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    used = sorted({int(s) for episode in episodes if episode.subtask_id is not None
                   for s in np.unique(episode.subtask_id)})
    handles = [Patch(color=_rgb(SUBTASK_COLOURS[s]), label=labels[s]) for s in used]
    parse = episodes[0].parse
    if parse is not None:
        colours = option_colours(parse.p_c.shape[1])
        handles += [Line2D([], [], color=_rgb(c), lw=2, label=f"option {k} (o{k})") for k, c in enumerate(colours)]
        handles.append(Line2D([], [], color=_rgb(SWITCH_COLOUR), marker="x", ls=":", label="option switch"))
    return handles


def plot_segmentation(
    episodes: Sequence[EpisodeView], path: Path, title: str, codes: Sequence[str], labels: Sequence[str]
) -> None:
    """Write the PNG of `episodes`, one column each; a world's subtask ids are named by their short
    `codes` on the bars ("A", "1") and by their `labels` in the legend ("A get wood", "press 1")."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    rows = 1 if episodes[0].parse is None else 3
    ratios = [1.0] if rows == 1 else [1.0, 1.6, 1.0]
    fig, axes = plt.subplots(
        rows, len(episodes), figsize=(1.0 + 3.4 * len(episodes), 1.6 + 1.5 * rows), sharex="col", squeeze=False,
        gridspec_kw={"height_ratios": ratios},
    )
    for column, episode in enumerate(episodes):
        _draw_episode(axes[:, column], episode, codes)
        axes[-1, column].xaxis.set_major_locator(MaxNLocator(integer=True))
    handles = _legend_handles(episodes, labels)
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.12 if rows == 1 else 0.08, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
