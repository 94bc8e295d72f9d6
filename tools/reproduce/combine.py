"""`ocn-reproduce combine`: one study from the results files of several invocations of it.

Every command a study runs is single-threaded, so two invocations side by side use both cores of
the VM: `ocn-reproduce s1 --seeds 1,2` beside `--seeds 3`, or the baselines beside OCN. Each writes
its own results files (give each its own `--results`); this joins their JSONs into the study's one
set, with every run's row, the summary and the checks made again over all of them, and each source's
command, date and machine. Files of different studies, or of one study measured differently (any
setting but the seeds, methods, rewards, variants and folders of the invocation), are refused, and
so is a run found in two files.
"""

from __future__ import annotations

import argparse
import json
from types import ModuleType
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.reproduce import dial, finetune, imitation
from lerobot_policy_ocn.tools.reproduce.report import provenance

# The study modules; each names the studies it makes (`STUDIES`), the row lists of their results with
# the fields that name a row (`ROWS`), the settings that may differ between files (`VARYING`), and
# makes a study again from its rows (`restudy`) and writes it (`write`).
MODULES = (imitation, finetune, dial)


def load(path: Path) -> dict[str, Any]:
    """A study's results JSON; anything else is refused by name."""
    if not path.is_file():
        raise SystemExit(f"ocn-reproduce combine: {path} is not a file")
    result = json.loads(path.read_text())
    if not any(result.get("study") in module.STUDIES for module in MODULES):
        raise SystemExit(f"ocn-reproduce combine: {path} is not the results JSON of an ocn-reproduce study")
    return result


def shared_settings(results: dict[Path, dict[str, Any]], varying: tuple[str, ...]) -> dict[str, Any]:
    """The settings every file measured with (the first file's, without `varying`); a difference is refused."""
    measured = {path: {k: v for k, v in result["settings"].items() if k not in varying}
                for path, result in results.items()}
    first = next(iter(measured.values()))
    for key in sorted({key for settings in measured.values() for key in settings}):
        values = {path: settings.get(key) for path, settings in measured.items()}
        if any(value != first.get(key) for value in values.values()):
            raise SystemExit("ocn-reproduce combine: the files were measured with different settings, " + key + ": "
                             + "; ".join(f"{path}: {value}" for path, value in values.items()))
    return first


def joined(results: dict[Path, dict[str, Any]], lists: dict[str, tuple[str, ...]]) -> dict[str, list[dict[str, Any]]]:
    """Every file's rows of each list; a row (by its naming fields) found in two files is refused."""
    found: dict[str, list[dict[str, Any]]] = {}
    for name, key in lists.items():
        seen: dict[tuple[Any, ...], Path] = {}
        found[name] = []
        for path, result in results.items():
            for row in result[name]:
                which = tuple(row[field] for field in key)
                if which in seen:
                    raise SystemExit(f"ocn-reproduce combine: the {name} row {dict(zip(key, which, strict=True))} is "
                                     f"in both {seen[which]} and {path}; pass one of them")
                seen[which] = path
                found[name].append(row)
    return found


def study_module(name: str) -> ModuleType:
    return next(module for module in MODULES if name in module.STUDIES)


def run(args: argparse.Namespace) -> int:
    """Join the files, make the study again over all their rows and write it to `--results`."""
    if len(set(args.files)) < 2:
        raise SystemExit("ocn-reproduce combine: give at least two different results files")
    results = {path: load(path) for path in args.files}
    studies = {result["study"] for result in results.values()}
    if len(studies) > 1:
        raise SystemExit(f"ocn-reproduce combine: the files are of different studies: {sorted(studies)}")
    name = studies.pop()
    module = study_module(name)
    settings = {**shared_settings(results, module.VARYING), "results": str(args.results)}
    sources = [{key: result[key] for key in ("command", "date", "machine", "settings")} for result in results.values()]
    combined = {**provenance(args.argv, settings), "sources": sources,
                **module.restudy(name, joined(results, module.ROWS)),
                "wall_s": sum(result["wall_s"] for result in results.values())}
    module.write(args.results, combined)
    print(f"wrote {args.results}/{combined['study']}.{{json,md,png}} from {len(results)} files")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `combine` subcommand."""
    parser = sub.add_parser("combine", help="one study from the results JSONs of several invocations of it",
                            description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="results JSONs of one study (e.g. finetune_s1.json)")
    parser.add_argument("--results", type=Path, required=True, help="folder of the combined results files")
    parser.set_defaults(func=run)
