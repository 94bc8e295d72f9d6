"""Dataset cards (Hugging Face `README.md` with YAML front matter) from the `datacards/` templates.

A card is always rebuilt from what is on disk (info, episode table, recording provenance, an
`ocn-annotate` record if any), so `record_demos`, `ocn-annotate` and `ocn-push` write the same card
for the same dataset.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from pathlib import Path

import jinja2

from lerobot_policy_ocn.ocn_data.episodes_table import dataset_world, read_info
from lerobot_policy_ocn.ocn_data.provenance import PROVENANCE, load_provenance

DATACARDS = Path(__file__).resolve().parent.parent / "datacards"


@functools.cache
def _templates() -> jinja2.Environment:
    """The card templates, compiled once per process (record_demos rebuilds the card with every chunk)."""
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(DATACARDS), undefined=jinja2.StrictUndefined, keep_trailing_newline=True
    )


def render_card(template: str, context: dict) -> str:
    """Fill `datacards/<template>.md` with `context`; a missing value is an error, not a blank."""
    return _templates().get_template(f"{template}.md").render(**context)


ANNOTATION = "meta/ocn_annotation.json"


def craft_observation_layout() -> list[dict]:
    """The card's table of what each range of `observation.state` holds."""
    from lerobot_policy_ocn.envs.craft.observation import AGENT_COL, AGENT_ROW, CELLS, FACING, INVENTORY

    return [
        {"start": CELLS.start, "stop": CELLS.stop,
         "meaning": "interior cell kinds (8 x 8, row-major; 0 empty, 1 boundary, 2 water, 3 stone, 4 toolshed, "
                    "5 workbench, 6 factory, 7 iron, 8 grass, 9 wood, 10 gold, 11 gem, 12-20 crafted items)"},
        {"start": AGENT_ROW, "stop": AGENT_ROW + 1, "meaning": "agent row (interior coordinates 0-7)"},
        {"start": AGENT_COL, "stop": AGENT_COL + 1, "meaning": "agent column (interior coordinates 0-7)"},
        {"start": FACING, "stop": FACING + 1, "meaning": "facing (0 down, 1 up, 2 left, 3 right)"},
        {"start": INVENTORY.start, "stop": INVENTORY.stop,
         "meaning": "inventory counts of kinds 7-20 (iron ... ladder)"},
    ]


def recording_context(root: str | Path, repo_id: str, task_code: Callable[[str, dict], str]) -> dict:
    """The card context every world shares, read back from a dataset that record_demos wrote.

    Publishing a dataset under a new repo id, or annotating a copy of it, rebuilds its card from
    what is on disk (info, episode table, provenance) instead of trusting a README.md that names
    another repo id or predates a change. `task_code(task string, last session)` is the task's
    compact form.
    """
    import pyarrow.parquet as pq

    root = Path(root)
    sessions = load_provenance(root)["sessions"]
    if not sessions:
        raise FileNotFoundError(f"{root} has no {PROVENANCE}: only datasets recorded with record_demos have a card.")
    info = read_info(root)
    tasks = pq.read_table(root / "meta" / "tasks.parquet").to_pandas().sort_values("task_index")
    first_tasks = [
        episode_tasks[0]
        for file in sorted((root / "meta" / "episodes").glob("*/*.parquet"))
        for episode_tasks in pq.read_table(file, columns=["tasks"])["tasks"].to_pylist()
    ]
    splits = info.get("splits") or {}
    return {
        "info": info,
        "session": sessions[-1],
        "repo_id": repo_id,
        "reward": sessions[-1]["reward"],
        "fps": info["fps"],
        "total_episodes": info["total_episodes"],
        "total_frames": info["total_frames"],
        "splits": {"train": splits.get("train", "0:0"), "val": splits.get("val")},
        "tasks": [
            {"description": task, "code": task_code(task, sessions[-1]), "episodes": first_tasks.count(task)}
            for task in tasks.index
        ],
        "failures": sum(s["expert_failures"] for s in sessions),
        "seed": ", ".join(str(s["seed"]) for s in sessions),
        "commands": [s["command"] for s in sessions],
    }


def craft_card_context(root: str | Path, repo_id: str) -> dict:
    """What `datacards/craft.md` needs."""
    from lerobot_policy_ocn.envs.craft.observation import OBS_DIM
    from lerobot_policy_ocn.envs.craft.world import parse_task, task_code
    from lerobot_policy_ocn.ocn_data.recorder import IMAGE_KEY

    context = recording_context(root, repo_id, lambda task, session: task_code(parse_task(task, session["mode"])))
    image = context["info"]["features"].get(IMAGE_KEY)
    return context | {
        "mode": context["session"]["mode"],
        "dart_noise": context["session"].get("dart_noise", 0.0),
        "image_shape": tuple(image["shape"]) if image else None,
        "obs_dim": OBS_DIM,
        "obs_layout": craft_observation_layout(),
    }


def dial_card_context(root: str | Path, repo_id: str) -> dict:
    """What `datacards/dial.md` needs: the shared context plus the scene's constants."""
    from lerobot_policy_ocn.envs.dial import (
        DIGIT_CELLS, FRAME_SKIP, GEARS, PRESS_L1, RELEASE_L1, key_positions, parse_pin, pin_code,
    )
    from lerobot_policy_ocn.envs.dial.expert import NOISE_HOLD
    from lerobot_policy_ocn.envs.dial.task import STEPS_PER_DIGIT

    context = recording_context(root, repo_id, lambda task, session: pin_code(parse_pin(task)))
    session = context["session"]
    layout = [[" "] * 3 for _ in range(4)]
    for digit, (row, column) in enumerate(DIGIT_CELLS):
        layout[row][column] = str(digit)
    return context | {
        "digits": session["digits"],
        "pin_length": session["pin_length"],
        "noise_levels": session["noise_levels"],
        "noise_hold": NOISE_HOLD,
        "keys": [{"digit": d, "point": [round(float(v), 3) for v in p]} for d, p in enumerate(key_positions())],
        "pad_rows": [" ".join(row) for row in layout],
        "gears": GEARS,
        "frame_skip": FRAME_SKIP,
        "press_l1": PRESS_L1,
        "release_l1": RELEASE_L1,
        "steps_per_digit": STEPS_PER_DIGIT,
    }


CARD_CONTEXTS = {"craft": craft_card_context, "dial": dial_card_context}


def annotation_section(annotation: dict) -> str:
    """Card section saying that `language_persistent` holds an OCN's parse (from `ocn-annotate`), not the truth."""
    by_subtask = annotation["name_by"] == "subtask"
    naming = (
        "the ground-truth subtask it overlaps most over the whole dataset"
        if by_subtask
        else "its option number (`option k`)"
    )
    header = "| option | segment name | frames | segments |" + (" share of its frames there |" if by_subtask else "")
    rule = "|---|---|---|---|" + ("---|" if by_subtask else "")
    rows = [
        f"| {o['option']} | {o['name']} | {o['frames']} | {o['segments']} |"
        + (f" {o['agreement']:.3f} |" if by_subtask else "")
        for o in annotation["options"]
    ]
    return "\n".join(
        [
            "## OCN subtask annotations",
            "",
            "In this copy `language_persistent` holds the segmentation discovered by a trained Option-Controller",
            "Network (written by `ocn-annotate`), not the ground truth: one `subtask` row per maximal run of the",
            f"same chosen option (argmax p^c), each named by {naming}.",
            "The `subtask.*` columns still hold the ground truth.",
            f"Policy: `{annotation['policy']}`; {annotation['segments']} segments over "
            f"{annotation['episodes']} episodes.",
            "",
            header,
            rule,
            *rows,
            "",
            "```bash",
            annotation["command"],
            "```",
            "",
        ]
    )


def dataset_card(root: str | Path, repo_id: str) -> str:
    """The README.md of a record_demos dataset published (or annotated) as `repo_id`."""
    world = dataset_world(Path(root))
    text = render_card(world, CARD_CONTEXTS[world](root, repo_id))
    annotation = Path(root) / ANNOTATION
    if annotation.is_file():
        text = text.rstrip("\n") + "\n\n" + annotation_section(json.loads(annotation.read_text()))
    return text
