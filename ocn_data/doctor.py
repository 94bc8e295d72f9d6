"""`ocn-doctor`: does a folder hold a LeRobot v3.0 dataset that loads, and if it was damaged, repair it.

`ocn-doctor DATASET` checks what `LeRobotDataset(repo_id, root=DATASET)` and `lerobot-train` need,
without loading anything into LeRobot (which, when a local file is missing, falls back to the Hub
and fails far from the cause): `meta/info.json`, `meta/tasks.parquet` and `meta/stats.json` read;
the episode tables list episodes 0..N-1 with contiguous frame ranges; every data file reads and
holds exactly the rows its episodes claim, no data file is left over, every video file opens; the
totals and the splits of `meta/info.json` agree with the tables. Each problem is one line naming
the file. Exit code 0: sound; 1: damaged (run with --repair); 2: nothing to check or not repairable.

`--repair` keeps the longest run of sound episodes from episode 0 and drops the tail after it: the
files that hold only dropped episodes, the rows of dropped episodes in files that also hold kept
ones, files no episode table lists (data written before its metadata), partial files of interrupted
writes and what an interrupted swap left beside the folder. It rewrites `meta/info.json` (totals,
splits) and `meta/stats.json` (aggregated, as LeRobot does, from the kept episodes' own statistics)
and, for a `record_demos` dataset, appends the repair to `meta/ocn_recording.json` and rebuilds the
card. Nothing else is touched, and the repair is itself one atomic swap
(`lerobot_policy_ocn.ocn_data.durable.FolderTransaction`). A damaged `meta/info.json` or `meta/tasks.parquet` cannot be
rebuilt: restore it from a copy.

`ocn-doctor LOG.mcap` checks an MCAP log of `record_demos` or `ocn-eval`: a log whose writer was
killed has every flushed message but no summary, and `--repair` rewrites it as a finished log.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from lerobot_policy_ocn.ocn_data.durable import PARTIAL_SUFFIX, FolderTransaction, leftovers, previous_path, recover
from lerobot_policy_ocn.ocn_data.dataset_files import INFO_PATH, STATS_PATH, TASKS_PATH, split_ranges
from lerobot_policy_ocn.ocn_data.provenance import PROVENANCE, load_provenance, write_provenance

# What interrupted writes leave inside a dataset: ours, and the `.parquet.tmp` of writers before them.
PARTIAL_PATTERNS = (f"*{PARTIAL_SUFFIX}", "*.parquet.tmp")
INFO_KEYS = ("codebase_version", "fps", "features", "total_episodes", "total_frames", "data_path")
ROW_COLUMNS = ["episode_index", "length", "dataset_from_index", "dataset_to_index", "data/chunk_index",
               "data/file_index"]


class NotRepairableError(ValueError):
    """The dataset's own description (info, tasks) is damaged: only a copy can restore it."""


@dataclass
class Diagnosis:
    """What `diagnose` found: `findings` (one line each, naming the file), the sound episodes kept
    by a repair (`kept`), and what the repair would drop, trim (rewrite without the dropped
    episodes' rows) and rewrite."""

    root: Path
    findings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    listed: int = 0
    listed_frames: int = 0
    kept: int = 0
    kept_frames: int = 0
    drop: list[str] = field(default_factory=list)
    trim: list[str] = field(default_factory=list)
    rewrite_metadata: bool = False
    leftovers: list[Path] = field(default_factory=list)

    @property
    def sound(self) -> bool:
        return not self.findings


def _relative(root: Path, path: Path) -> str:
    return str(path.relative_to(root))


def _read_info(root: Path) -> dict[str, Any]:
    path = root / INFO_PATH
    if not path.is_file():
        raise NotRepairableError(f"{root} is not a LeRobot dataset: {INFO_PATH} is missing.")
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise NotRepairableError(f"{path} is not valid JSON ({error}); restore it from a copy of the dataset.") \
            from None
    missing = [key for key in INFO_KEYS if key not in info]
    if missing:
        raise NotRepairableError(f"{path} lacks {', '.join(missing)}; restore it from a copy of the dataset.")
    if info["codebase_version"] != "v3.0":
        raise NotRepairableError(f"{path}: a LeRobot {info['codebase_version']} dataset; ocn-doctor checks v3.0 ones.")
    return info


def _check_tasks(root: Path) -> int:
    path = root / TASKS_PATH
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as error:
        raise NotRepairableError(f"{path} cannot be read ({error}); restore it from a copy of the dataset.") from None
    if "task_index" not in table.column_names:
        raise NotRepairableError(f"{path} has no task_index column; restore it from a copy of the dataset.")
    return table.num_rows


def _episode_rows(root: Path, diagnosis: Diagnosis) -> list[dict[str, Any]]:
    """The episode tables' rows in order, up to the first table that cannot be read or the first row
    that breaks the sequence (episode i at row i, each frame range starting where the last ended)."""
    rows: list[dict[str, Any]] = []
    for path in sorted((root / "meta" / "episodes").glob("*/*.parquet")):
        try:
            table = pq.read_table(path)
            missing = [column for column in ROW_COLUMNS if column not in table.column_names]
            if missing:
                raise ValueError(f"no {', '.join(missing)} column")
        except (OSError, ValueError, pa.ArrowException) as error:
            diagnosis.findings.append(f"{path}: cannot be read ({error}).")
            return rows
        columns = [c for c in table.column_names if not c.startswith("stats/")]
        for row in table.select(columns).to_pylist():
            expected_from = rows[-1]["dataset_to_index"] if rows else 0
            if (row["episode_index"] != len(rows) or row["dataset_from_index"] != expected_from
                    or row["dataset_to_index"] - row["dataset_from_index"] != row["length"] or row["length"] < 1):
                diagnosis.findings.append(
                    f"{path}: episode {row['episode_index']} does not follow episode {len(rows) - 1} "
                    f"(frames {row['dataset_from_index']}:{row['dataset_to_index']}, length {row['length']})."
                )
                return rows
            rows.append({**row, "table": _relative(root, path)})
    return rows


def _data_file_cut(path: Path, episodes: list[dict[str, Any]], features: list[str]) -> tuple[int, str]:
    """How many of `episodes` (those the tables place in the data file `path`, in order) the file
    holds exactly, and if not all, why."""
    if not path.is_file():
        return 0, "is missing"
    try:
        table = pq.read_table(path, columns=["episode_index", "index"])
        names = set(pq.read_schema(path).names)
    except (OSError, pa.ArrowException) as error:
        return 0, f"cannot be read ({error})"
    missing = sorted(set(features) - names)
    if missing:
        return 0, f"lacks the columns {missing} that meta/info.json declares"
    episode = table["episode_index"].to_numpy()
    index = table["index"].to_numpy()
    for kept, row in enumerate(episodes):
        rows = episode == row["episode_index"]
        if rows.sum() != row["length"]:
            return kept, (f"holds {int(rows.sum())} frames of episode {row['episode_index']}, its table says "
                          f"{row['length']}")
        expected = np.arange(row["dataset_from_index"], row["dataset_to_index"])
        if not np.array_equal(np.sort(index[rows]), expected):
            return kept, f"holds other frame indices for episode {row['episode_index']} than its table"
    return len(episodes), ""


def _video_cut(root: Path, info: dict[str, Any], rows: list[dict[str, Any]], diagnosis: Diagnosis) -> int:
    """How many leading episodes have every video file they point to present and openable."""
    import av

    keys = [key for key, ft in info["features"].items() if ft["dtype"] == "video"]
    opened: dict[Path, str] = {}
    for position, row in enumerate(rows):
        for key in keys:
            path = root / info["video_path"].format(
                video_key=key, chunk_index=row[f"videos/{key}/chunk_index"], file_index=row[f"videos/{key}/file_index"]
            )
            if path not in opened:
                try:
                    with av.open(str(path)) as container:
                        opened[path] = "" if container.streams.video else "has no video stream"
                except (OSError, av.error.FFmpegError) as error:
                    opened[path] = f"cannot be opened ({error})"
            if opened[path]:
                diagnosis.findings.append(f"{path}: {opened[path]}; episode {row['episode_index']} needs it.")
                return position
    return len(rows)


def _stats_readable(root: Path) -> bool:
    try:
        json.loads((root / STATS_PATH).read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return False
    return True


def diagnose(root: str | Path) -> Diagnosis:
    """Check the dataset at `root`; a missing folder is a FileNotFoundError, a damaged description
    a NotRepairableError."""
    root = Path(root)
    diagnosis = Diagnosis(root, leftovers=leftovers(root))
    if not root.exists():
        if previous_path(root) in diagnosis.leftovers:
            diagnosis.findings.append(f"{root} is missing: a swap cut off by a kill left the dataset at "
                                      f"{previous_path(root)}.")
            return diagnosis
        raise FileNotFoundError(f"{root} does not exist: pass the folder of a LeRobot dataset (its --root).")
    if not root.is_dir():
        raise NotRepairableError(f"{root} is a file, not a dataset folder.")
    info = diagnosis.info = _read_info(root)
    total_tasks = _check_tasks(root)
    rows = _episode_rows(root, diagnosis)
    diagnosis.listed = len(rows)
    diagnosis.listed_frames = rows[-1]["dataset_to_index"] if rows else 0
    features = [key for key, ft in info["features"].items() if ft["dtype"] != "video"]
    cut = len(rows)
    by_file: dict[tuple[int, int], list[dict[str, Any]]] = {}
    for row in rows:
        by_file.setdefault((row["data/chunk_index"], row["data/file_index"]), []).append(row)
    for (chunk, file), episodes in by_file.items():
        path = root / info["data_path"].format(chunk_index=chunk, file_index=file)
        held, problem = _data_file_cut(path, episodes, features)
        if problem:
            lost = episodes[held]["episode_index"]
            diagnosis.findings.append(f"{path}: {problem}; episodes from {lost} on cannot be read.")
            cut = min(cut, lost)
    if info.get("video_path"):
        cut = min(cut, _video_cut(root, info, rows[:cut], diagnosis))
    diagnosis.kept = cut
    diagnosis.kept_frames = rows[cut - 1]["dataset_to_index"] if cut else 0
    _plan_drops(root, info, rows, diagnosis)
    _check_totals(root, info, total_tasks, diagnosis)
    _check_provenance(root, diagnosis)
    for pattern in PARTIAL_PATTERNS:
        for path in sorted(root.rglob(pattern)):
            diagnosis.findings.append(f"{path}: a partial file left by an interrupted write.")
            diagnosis.drop.append(_relative(root, path))
    for leftover in diagnosis.leftovers:
        diagnosis.findings.append(f"{leftover}: left beside the dataset by a write cut off by a kill.")
    return diagnosis


def _data_file(info: dict[str, Any], row: dict[str, Any]) -> str:
    return info["data_path"].format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])


def _video_files(info: dict[str, Any], row: dict[str, Any]) -> list[str]:
    keys = [key for key, ft in info["features"].items() if ft["dtype"] == "video"]
    return [info["video_path"].format(video_key=key, chunk_index=row[f"videos/{key}/chunk_index"],
                                      file_index=row[f"videos/{key}/file_index"]) for key in keys]


def _plan_drops(root: Path, info: dict[str, Any], rows: list[dict[str, Any]], diagnosis: Diagnosis) -> None:
    """Which files a repair removes (no kept episode in them) or trims (kept episodes and others),
    and a finding for each file that no episode table lists."""
    kept = rows[: diagnosis.kept]
    kept_rows_per_table: dict[str, int] = {}
    kept_frames_per_file: dict[str, int] = {}
    for row in kept:
        kept_rows_per_table[row["table"]] = kept_rows_per_table.get(row["table"], 0) + 1
        kept_frames_per_file[_data_file(info, row)] = kept_frames_per_file.get(_data_file(info, row), 0) + row["length"]
    for path in sorted((root / "meta" / "episodes").glob("*/*.parquet")):
        relative = _relative(root, path)
        if relative not in kept_rows_per_table:
            diagnosis.drop.append(relative)
        elif pq.read_metadata(path).num_rows > kept_rows_per_table[relative]:
            diagnosis.trim.append(relative)
    listed_data = {_data_file(info, row) for row in rows}
    for path in sorted((root / "data").glob("*/*.parquet")):
        relative = _relative(root, path)
        if relative not in kept_frames_per_file:
            diagnosis.drop.append(relative)
            if relative not in listed_data:
                diagnosis.findings.append(f"{path}: holds frames that no episode table lists (data written "
                                          "before its metadata was).")
        elif pq.read_metadata(path).num_rows > kept_frames_per_file[relative]:
            diagnosis.trim.append(relative)
            if diagnosis.kept == len(rows):
                diagnosis.findings.append(f"{path}: holds frames that no episode table lists.")
    if not info.get("video_path"):
        return
    kept_videos = {video for row in kept for video in _video_files(info, row)}
    listed_videos = {video for row in rows for video in _video_files(info, row)}
    for path in sorted((root / "videos").glob("*/*/*.mp4")):
        relative = _relative(root, path)
        if relative not in kept_videos:
            diagnosis.drop.append(relative)
            if relative not in listed_videos:
                diagnosis.findings.append(f"{path}: a video that no episode table lists.")


def _check_totals(root: Path, info: dict[str, Any], total_tasks: int, diagnosis: Diagnosis) -> None:
    """meta/info.json's totals and splits against the episode tables; meta/stats.json readable."""
    path = root / INFO_PATH
    totals = (info["total_episodes"], info["total_frames"])
    diagnosis.rewrite_metadata = totals != (diagnosis.kept, diagnosis.kept_frames)
    if diagnosis.listed == 0:
        diagnosis.findings.append(f"{root}: its episode tables list no episode; LeRobot cannot load a dataset "
                                  "without episodes (and would look for it on the Hub).")
    if totals != (diagnosis.listed, diagnosis.listed_frames):
        diagnosis.findings.append(
            f"{path}: says {totals[0]} episodes and {totals[1]} frames; the episode tables list {diagnosis.listed} "
            f"episodes and {diagnosis.listed_frames} frames."
        )
    if info.get("total_tasks", total_tasks) != total_tasks:
        diagnosis.findings.append(f"{path}: says {info['total_tasks']} tasks; {TASKS_PATH} holds {total_tasks}.")
        diagnosis.rewrite_metadata = True
    for name, span in (info.get("splits") or {}).items():
        start, stop = (int(part) for part in str(span).split(":"))
        if totals[0] == diagnosis.listed and not 0 <= start <= stop <= totals[0]:
            diagnosis.findings.append(
                f"{path}: split {name} {span} lies outside its {info['total_episodes']} episodes."
            )
            diagnosis.rewrite_metadata = True
    if not _stats_readable(root):
        diagnosis.findings.append(f"{root / STATS_PATH}: missing or not valid JSON.")
        diagnosis.rewrite_metadata = True


def _check_provenance(root: Path, diagnosis: Diagnosis) -> None:
    """A record_demos dataset's sessions must account for its episodes, or `--resume` repeats seeds."""
    path = root / PROVENANCE
    if not path.is_file():
        return
    try:
        sessions = load_provenance(root)["sessions"]
        accounted = sum(session["episodes"] for session in sessions)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as error:
        raise NotRepairableError(f"{path} cannot be read ({error}); restore it from a copy of the dataset "
                                 "(record_demos --resume needs it).") from None
    if accounted < diagnosis.listed:
        diagnosis.notes.append(
            f"{path} accounts for {accounted} of the {diagnosis.listed} episodes: a session was cut off before "
            "record_demos committed its record with each chunk. `record_demos --resume` refuses such a dataset "
            "unless given a --seed that no session used."
        )


def _kept_stats(root: Path, info: dict[str, Any], diagnosis: Diagnosis) -> dict[str, dict[str, np.ndarray]]:
    """The dataset statistics of the kept episodes, aggregated from their own (as LeRobot's writer
    aggregates them), read from the episode tables the repair keeps."""
    from lerobot.datasets.compute_stats import aggregate_stats

    kept = diagnosis.kept
    per_episode: list[dict[str, dict[str, np.ndarray]]] = []
    for path in sorted((root / "meta" / "episodes").glob("*/*.parquet")):
        if _relative(root, path) in diagnosis.drop:
            continue
        table = pq.read_table(path)
        for row in table.to_pylist():
            if row["episode_index"] >= kept:
                break
            stats: dict[str, dict[str, np.ndarray]] = {}
            for column, value in row.items():
                if column.startswith("stats/"):
                    key, stat = column[len("stats/"):].rsplit("/", 1)
                    image = info["features"][key]["dtype"] in ("image", "video") and stat != "count"
                    stats.setdefault(key, {})[stat] = np.asarray(value).reshape((3, 1, 1) if image else (-1,))
            per_episode.append(stats)
    return aggregate_stats(per_episode)


def repair(diagnosis: Diagnosis) -> list[str]:
    """Keep the sound episodes of a diagnosed dataset and drop the rest, in one atomic swap; returns
    a line per thing done."""
    from lerobot.datasets.io_utils import write_stats

    root, info = diagnosis.root, diagnosis.info
    done = recover(root)
    if not info:  # the folder itself was missing: recovering it was the repair
        return done
    if diagnosis.kept == 0:
        raise NotRepairableError(f"{root}: no episode is sound, so a repair would keep nothing; record it again.")
    transaction = FolderTransaction(root)
    try:
        for relative in dict.fromkeys(diagnosis.drop):
            transaction.remove(relative)
        for relative in diagnosis.trim:
            _trim(root, relative, transaction, diagnosis.kept)
        if diagnosis.rewrite_metadata or diagnosis.trim or diagnosis.kept != diagnosis.listed:
            info = {**info, "total_episodes": diagnosis.kept, "total_frames": diagnosis.kept_frames,
                    "total_tasks": pq.read_metadata(root / TASKS_PATH).num_rows,
                    "splits": split_ranges(diagnosis.kept, _val_fraction(root, info))}
            transaction.fresh(INFO_PATH).write_text(json.dumps(info, indent=4, ensure_ascii=False))
            transaction.fresh(STATS_PATH)
            write_stats(_kept_stats(root, info, diagnosis), transaction.staging)
            _record_repair(root, transaction, diagnosis)
        transaction.publish()
    finally:
        transaction.discard()
    dropped = diagnosis.listed - diagnosis.kept
    done.append(f"kept episodes 0-{diagnosis.kept - 1} ({diagnosis.kept_frames} frames)"
                + (f", dropped {dropped} listed episode(s)" if dropped else "")
                + (f"; removed {', '.join(dict.fromkeys(diagnosis.drop))}" if diagnosis.drop else "")
                + (f"; trimmed {', '.join(diagnosis.trim)}" if diagnosis.trim else ""))
    return done


def _trim(root: Path, relative: str, transaction: FolderTransaction, kept: int) -> None:
    """Rewrite a data file or an episode table without the rows of episodes from `kept` on."""
    table = pq.read_table(root / relative)
    keep = np.asarray(table["episode_index"].to_numpy() < kept)
    pq.write_table(table.filter(pa.array(keep)), transaction.fresh(relative), compression="snappy")


def _val_fraction(root: Path, info: dict[str, Any]) -> float:
    """The validation share the repaired splits keep: the recording's `--val-fraction` where its
    provenance has it, else the share of the current validation split."""
    sessions = load_provenance(root)["sessions"] if (root / PROVENANCE).is_file() else []
    if sessions and "val_fraction" in sessions[-1]:
        return sessions[-1]["val_fraction"]
    val = (info.get("splits") or {}).get("val")
    if val is None:
        return 0.0
    start, stop = (int(part) for part in val.split(":"))
    return (stop - start) / stop


def _record_repair(root: Path, transaction: FolderTransaction, diagnosis: Diagnosis) -> None:
    """A record_demos dataset notes the repair in its provenance and gets its card rebuilt."""
    if not (root / PROVENANCE).is_file():
        return
    from lerobot_policy_ocn.ocn_data.datacard import dataset_card

    provenance = load_provenance(root)
    provenance.setdefault("repairs", []).append({
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "kept_episodes": diagnosis.kept,
        "dropped_episodes": diagnosis.listed - diagnosis.kept,
        "removed": list(dict.fromkeys(diagnosis.drop)),
        "trimmed": diagnosis.trim,
    })
    transaction.fresh(PROVENANCE)
    write_provenance(transaction.staging, provenance)
    if (root / "README.md").is_file():
        repo_id = _card_repo_id(root)
        transaction.fresh("README.md").write_text(dataset_card(transaction.staging, repo_id))


def _card_repo_id(root: Path) -> str:
    """The repo id the dataset's card names (its title line), to rebuild the card under the same one."""
    for line in (root / "README.md").read_text().splitlines():
        if line.startswith("# ") and ":" in line:
            return line[2:].split(":", 1)[0].strip()
    return f"local/{root.name}"


def _describe_log(path: Path, repair_it: bool) -> tuple[int, list[str]]:
    """Check (and with `repair_it`, finish) an MCAP log; returns the exit code and the lines to print."""
    from lerobot_policy_ocn.ocn_data.mcap_log import finish_log, log_is_finished, read_mcap_messages

    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist.")
    messages = read_mcap_messages(path)
    episodes = {message["episode_index"] for topic in messages.values() for message in topic
                if "episode_index" in message}
    held = (f"{sum(len(topic) for topic in messages.values())} messages on {len(messages)} topics, "
            f"{len(episodes)} episodes")
    if log_is_finished(path):
        return 0, [f"{path}: a finished MCAP log: {held}."]
    if not repair_it:
        return 1, [f"{path}: an unfinished MCAP log (its writer was killed): {held} in complete records, no "
                   f"summary; run `ocn-doctor --repair {path}` to finish it."]
    kept = finish_log(path)
    return 0, [f"{path}: finished the log with its {kept} complete messages ({len(episodes)} episodes)."]


def _describe_dataset(root: Path, repair_it: bool) -> tuple[int, list[str]]:
    """Check (and with `repair_it`, repair) a dataset; returns the exit code and the lines to print."""
    diagnosis = diagnose(root)
    lines = list(diagnosis.findings)
    if diagnosis.sound:
        info = diagnosis.info
        splits = ", ".join(f"{name} {span}" for name, span in (info.get("splits") or {}).items()) or "none"
        return 0, [*diagnosis.notes, f"{root}: a sound LeRobot v3.0 dataset: {info['total_episodes']} episodes, "
                                     f"{info['total_frames']} frames, splits {splits}."]
    if not repair_it:
        keep = f"keep episodes 0-{diagnosis.kept - 1}" if diagnosis.kept else "keep nothing"
        dropping = diagnosis.listed - diagnosis.kept
        return 1, [*lines, *diagnosis.notes,
                   f"run `ocn-doctor --repair {root}` to {keep}"
                   + (f", drop {dropping} damaged or unlisted episode(s)" if dropping else "")
                   + " and remove the leftovers named above."]
    done = repair(diagnosis)
    code, after = _describe_dataset(root, repair_it=False)
    return code, [*lines, *(f"repaired: {line}" for line in done), *after]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ocn-doctor", description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("path", type=Path, help="a LeRobot dataset folder (its --root), or an MCAP log (.mcap)")
    parser.add_argument("--repair", action="store_true",
                        help="drop the damaged tail and leftovers of a dataset (keeping every sound episode from "
                             "episode 0), or finish an MCAP log whose writer was killed")
    args = parser.parse_args(argv)
    try:
        if args.path.suffix == ".mcap":
            code, lines = _describe_log(args.path, args.repair)
        else:
            code, lines = _describe_dataset(args.path, args.repair)
    except (FileNotFoundError, NotRepairableError) as error:
        print(f"ocn-doctor: {error}", file=sys.stderr)
        return 2
    for line in lines:
        print(f"ocn-doctor: {line}", file=sys.stderr if code else sys.stdout)
    return code


if __name__ == "__main__":
    sys.exit(main())
