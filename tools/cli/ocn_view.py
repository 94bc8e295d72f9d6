"""`ocn-view`: recorded demonstrations in rerun, with a trained OCN's options drawn over them.

Logs the selected episodes of a dataset, with or without a policy, to an .rrd file (--save), a
spawned viewer (--spawn) or a served web viewer (--serve); --png draws the segmentation of a few
episodes with matplotlib (tools/viz/segmentation_plot.py) instead of or besides the recording.

What the recording holds (entity paths, styles, layout): `tools/viz/rerun_log.py`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from lerobot_policy_ocn.ocn_data.episodes_table import read_info
from lerobot_policy_ocn.ocn_data.preflight import check_can_create, check_repo_id
from lerobot_policy_ocn.tools.viz.rerun_log import Episode, blueprint, log_episodes
from lerobot_policy_ocn.tools.viz.segmentation_plot import EpisodeView, plot_segmentation
from lerobot_policy_ocn.tools.worlds import World, world_of

if TYPE_CHECKING:
    from lerobot_policy_ocn.ocn_data.episodes_table import EpisodeArrays
    from lerobot_policy_ocn.tools.eval.parsing import EpisodeParse

# A contiguous range of episodes and how many of them to read.
Selected = tuple[range, int]


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
    source = f"**{args.repo_id}** (`{args.root}`); " + (f"policy `{args.policy}`" if args.policy else "no policy")
    log_episodes(rec, episodes, source, world, scene)
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
