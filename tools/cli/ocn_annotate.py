"""`ocn-annotate`: write a trained OCN's discovered segmentation into a copy of a LeRobot dataset.

The policy parses every episode (the chosen option, argmax p^c, per step); each maximal run of the
same option becomes one LeRobot subtask annotation, in the native `language_persistent` column
(role "assistant", style "subtask", the segment's name, its start time), with an empty
`language_events` list per frame. Segments are named "option k", or with `--name-by subtask` by the
ground-truth subtask that the option overlaps most over the whole dataset (which needs the dataset's
ground-truth subtask columns). Any LeRobot dataset the policy reads: the world comes from the dataset
(`lerobot_policy_ocn.tools.worlds`), which names its subtasks. The input dataset is never modified: the annotated
dataset is a new copy with its own card (Craft's and Dial's dataset card; any other dataset keeps its
README with the annotation section added) and `meta/ocn_annotation.json`.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import sys
import tempfile
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from lerobot_policy_ocn.ocn_data.episodes_table import LABELS, read_info
from lerobot_policy_ocn.tools.eval.metrics import segment_starts
from lerobot_policy_ocn.tools.worlds import World, world_of

NAME_BY = ("option", "subtask")
# The card section's sentence about the ground truth, left out where the dataset has none.
GROUND_TRUTH_LINE = "The `subtask.*` columns still hold the ground truth."


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ocn-annotate", description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--policy", type=Path, required=True, help="a pretrained_model folder of an ocn checkpoint")
    parser.add_argument("--root", type=Path, required=True, help="the LeRobot dataset to annotate (left unchanged)")
    parser.add_argument("--repo-id", required=True, help="repo id of the annotated dataset, ORG/NAME (for its card)")
    parser.add_argument("--out-root", type=Path, required=True, help="folder of the annotated copy; must not exist")
    parser.add_argument("--name-by", choices=NAME_BY, default="option",
                        help="name segments 'option k', or by the ground-truth subtask each option overlaps most")
    parser.add_argument("--batch-size", type=int, default=1024, help="episodes per parsing batch")
    parser.add_argument("--device", default="cpu")
    return parser.parse_args(argv)


def check_paths(root: Path, out_root: Path, repo_id: str, name_by: str) -> None:
    """Refuse before any parsing: a repo id that is not ORG/NAME, no dataset at root, an existing
    out-root, an out-root inside root or where nothing can be written, or naming segments by subtask
    in a dataset without the ground-truth columns."""
    from lerobot_policy_ocn.ocn_data.preflight import check_can_create, check_repo_id

    check_repo_id(repo_id)
    info = read_info(root)
    if out_root.exists():
        raise FileExistsError(
            f"--out-root {out_root} already exists; ocn-annotate writes a new dataset, choose a new folder."
        )
    if out_root.resolve().is_relative_to(root.resolve()):
        raise ValueError(f"--out-root {out_root} lies inside the dataset {root}; choose a folder outside it.")
    check_can_create(out_root, "--out-root")
    missing = [key for key in LABELS if key not in info["features"]]
    if missing and name_by == "subtask":
        raise ValueError(f"--name-by subtask names each option after the ground-truth subtask it overlaps most, and "
                         f"{root} has no {'/'.join(missing)} columns: name segments by option (the default).")


def option_names(
    options: list[np.ndarray], subtasks: list[np.ndarray] | None, name_by: str, subtask_names: Sequence[str]
) -> dict[int, dict]:
    """Per chosen option: its segment name, frames and segments, and by subtask the share of its
    frames on the subtask it is named after.

    By subtask, each option is matched to the ground-truth subtask it overlaps most over all frames,
    as the parsing metrics' alignment (`tools/eval/metrics.py`) reads a parse (several options may
    share a subtask, a subtask may get no option); ties go to the lower subtask id. `subtask_names` are the
    world's, by subtask id.
    """
    option = np.concatenate(options)
    first = np.concatenate([o[segment_starts(o)] for o in options])
    names = {}
    for k in (int(k) for k in np.unique(option)):
        chosen = option == k
        entry = {"frames": int(chosen.sum()), "segments": int((first == k).sum())}
        if name_by == "option":
            names[k] = {"name": f"option {k}", **entry}
            continue
        overlap = np.bincount(np.concatenate(subtasks)[chosen], minlength=len(subtask_names))
        best = int(overlap.argmax())
        names[k] = {"name": subtask_names[best], **entry, "agreement": float(overlap[best] / entry["frames"])}
    return names


def segments_of(option: np.ndarray, names: dict[int, dict]) -> list[tuple[int, str]]:
    """(start frame, name) of each maximal run of the same option in one episode."""
    return [(int(s), names[int(option[s])]["name"]) for s in segment_starts(option)]


def parse_dataset(
    policy_path: Path, root: Path, world: World, name_by: str, batch_size: int, device: str
) -> tuple[dict, dict]:
    """The policy's segments of every episode of the dataset, by episode index, and the option names."""
    from lerobot_policy_ocn.ocn_data.episodes_table import split_episodes
    from lerobot_policy_ocn.tools.eval.parsing import load_ocn, parse_episodes, policy_episodes

    policy, preprocessor, _ = load_ocn(policy_path, device)
    episodes = policy_episodes(policy, root, split_episodes(root, "all"))
    options = [parse.option for parse in parse_episodes(policy, preprocessor, episodes, batch_size)]
    subtasks = [episodes.subtask_id[i, :n] for i, n in enumerate(episodes.lengths)] if episodes.labelled else None
    names = option_names(options, subtasks, name_by, world.subtask_names)
    segments = {int(e): segments_of(o, names) for e, o in zip(episodes.episode_index, options, strict=True)}
    return segments, names


def rewrite_data_file(path: Path, segments: dict[int, list[tuple[int, str]]], fps: int, schema: pa.Schema) -> None:
    """Replace (or add) the two language columns of one data file, in the column order of `schema`.

    Episodes are contiguous in a LeRobot data file, so one segment list per run of `episode_index`
    spans all of that episode's frames.
    """
    import pyarrow.parquet as pq
    from lerobot.datasets.io_utils import write_table_one_row_group_per_episode
    from lerobot.datasets.language import LANGUAGE_EVENTS, LANGUAGE_PERSISTENT

    from lerobot_policy_ocn.ocn_data.language_rows import empty_events_column, persistent_column

    table = pq.read_table(path)
    episode = table["episode_index"].to_numpy()
    starts = segment_starts(episode)
    lengths = np.diff(np.append(starts, episode.size))
    in_file = [segments[int(e)] for e in episode[starts]]
    language = {
        LANGUAGE_PERSISTENT: persistent_column(in_file, lengths, fps),
        LANGUAGE_EVENTS: empty_events_column(episode.size),
    }
    arrays = [language[field.name] if field.name in language else table[field.name] for field in schema]
    tmp = path.with_suffix(".parquet.tmp")
    write_table_one_row_group_per_episode(pa.Table.from_arrays(arrays, schema=schema), tmp)
    tmp.replace(path)


def write_annotated(root: Path, out_root: Path, segments: dict, annotation: dict, repo_id: str, world: str) -> None:
    """Copy the dataset into a scratch folder beside out_root, annotate it there, then move it into place,
    so a failure leaves no half-written dataset at out_root. A dataset of `world` craft or dial gets its
    dataset card; any other keeps its README with the annotation section added."""
    from lerobot.datasets.feature_utils import get_hf_features_from_features
    from lerobot.datasets.io_utils import load_info, write_info
    from lerobot.datasets.language import language_feature_info

    from lerobot_policy_ocn.ocn_data.datacard import ANNOTATION, CARD_CONTEXTS, annotation_section, dataset_card

    out_root.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{out_root.name}.", dir=out_root.parent))
    try:
        work = scratch / "dataset"
        shutil.copytree(root, work)
        info = load_info(work)
        info.features = {**info.features, **language_feature_info()}
        write_info(info, work)
        schema = get_hf_features_from_features(
            {k: ft for k, ft in info.features.items() if ft["dtype"] != "video"}
        ).arrow_schema
        for path in sorted((work / "data").glob("*/*.parquet")):
            rewrite_data_file(path, segments, info.fps, schema)
        (work / ANNOTATION).write_text(json.dumps(annotation, indent=2) + "\n")
        if world in CARD_CONTEXTS:
            card = dataset_card(work, repo_id)
        else:
            readme = work / "README.md"
            section = annotation_section(annotation)
            if not annotation["ground_truth"]:
                section = section.replace(f"\n{GROUND_TRUTH_LINE}", "")
            card = (readme.read_text().rstrip("\n") if readme.is_file() else f"# {repo_id}") + "\n\n" + section
        (work / "README.md").write_text(card)
        work.rename(out_root)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def annotate(args: argparse.Namespace) -> dict[str, Any]:
    """Parse, then write the annotated copy; returns the annotation record it stores."""
    check_paths(args.root, args.out_root, args.repo_id, args.name_by)
    world = world_of(args.root)  # a dataset of a world ocn-annotate does not know fails here, before parsing
    segments, names = parse_dataset(args.policy, args.root, world, args.name_by, args.batch_size, args.device)
    annotation = {
        "command": args.command,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "policy": str(args.policy),
        "source_root": str(args.root),
        "name_by": args.name_by,
        "ground_truth": all(key in read_info(args.root)["features"] for key in LABELS),
        "episodes": len(segments),
        "segments": sum(len(s) for s in segments.values()),
        "options": [{"option": k, **v} for k, v in sorted(names.items())],
    }
    write_annotated(args.root, args.out_root, segments, annotation, args.repo_id, world.name)
    return annotation


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    args.command = shlex.join(["ocn-annotate", *(sys.argv[1:] if argv is None else argv)])
    try:
        annotation = annotate(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"ocn-annotate: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # a full disk while copying: the scratch copy is gone, --out-root never made
        print(f"ocn-annotate: cannot write {error.filename or args.out_root} ({error.strerror or error}); nothing was "
              f"written to {args.out_root}: free space and run again", file=sys.stderr)
        return 1
    named = ", ".join(f"option {o['option']} -> {o['name']!r}" for o in annotation["options"])
    print(f"wrote {annotation['segments']} segments over {annotation['episodes']} episodes ({named}) "
          f"into {args.out_root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
