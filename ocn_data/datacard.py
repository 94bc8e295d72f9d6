"""Dataset cards (Hugging Face `README.md` with YAML front matter) from the `datacards/` templates.

A card is always rebuilt from what is on disk (info, episode table, recording provenance, an
`ocn-annotate` record if any), so `record_demos`, `ocn-annotate` and `ocn-push` write the same card
for the same dataset.
"""

from __future__ import annotations

import json
from pathlib import Path

import jinja2

from ocn_data.provenance import PROVENANCE, load_provenance

DATACARDS = Path(__file__).resolve().parent.parent / "datacards"


def render_card(template: str, context: dict) -> str:
    """Fill `datacards/<template>.md` with `context`; a missing value is an error, not a blank."""
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(DATACARDS), undefined=jinja2.StrictUndefined, keep_trailing_newline=True
    )
    return env.get_template(f"{template}.md").render(**context)


ANNOTATION = "meta/ocn_annotation.json"


def craft_observation_layout() -> list[dict]:
    """The card's table of what each range of `observation.state` holds."""
    from envs.craft.observation import AGENT_COL, AGENT_ROW, CELLS, FACING, INVENTORY

    return [
        {"start": CELLS.start, "stop": CELLS.stop, "meaning": "interior cell kinds (8 x 8, row-major; 0 empty, 1 boundary, 2 water, 3 stone, 4 toolshed, 5 workbench, 6 factory, 7 iron, 8 grass, 9 wood, 10 gold, 11 gem, 12-20 crafted items)"},
        {"start": AGENT_ROW, "stop": AGENT_ROW + 1, "meaning": "agent row (interior coordinates 0-7)"},
        {"start": AGENT_COL, "stop": AGENT_COL + 1, "meaning": "agent column (interior coordinates 0-7)"},
        {"start": FACING, "stop": FACING + 1, "meaning": "facing (0 down, 1 up, 2 left, 3 right)"},
        {"start": INVENTORY.start, "stop": INVENTORY.stop, "meaning": "inventory counts of kinds 7-20 (iron ... ladder)"},
    ]


def craft_card_context(root: str | Path, repo_id: str) -> dict:
    """What `datacards/craft.md` needs, read back from a dataset that record_demos wrote.

    Publishing a dataset under a new repo id, or annotating a copy of it, rebuilds its card from
    what is on disk (info, episode table, provenance) instead of trusting a README.md that names
    another repo id or predates a change.
    """
    import pyarrow.parquet as pq

    from envs.craft.observation import OBS_DIM
    from envs.craft.world import parse_task, task_code
    from ocn_data.craft_recorder import IMAGE_KEY

    root = Path(root)
    sessions = load_provenance(root)["sessions"]
    if not sessions:
        raise FileNotFoundError(
            f"{root} has no {PROVENANCE}: only datasets recorded with record_demos have a Craft card."
        )
    info = json.loads((root / "meta" / "info.json").read_text())
    mode = sessions[-1]["mode"]
    tasks = pq.read_table(root / "meta" / "tasks.parquet").to_pandas().sort_values("task_index")
    first_tasks = [
        episode_tasks[0]
        for file in sorted((root / "meta" / "episodes").glob("*/*.parquet"))
        for episode_tasks in pq.read_table(file, columns=["tasks"])["tasks"].to_pylist()
    ]
    image = info["features"].get(IMAGE_KEY)
    splits = info.get("splits") or {}
    return {
        "repo_id": repo_id,
        "mode": mode,
        "reward": sessions[-1]["reward"],
        "fps": info["fps"],
        "total_episodes": info["total_episodes"],
        "total_frames": info["total_frames"],
        "splits": {"train": splits.get("train", "0:0"), "val": splits.get("val")},
        "image_shape": tuple(image["shape"]) if image else None,
        "tasks": [
            {"description": task, "code": task_code(parse_task(task, mode)), "episodes": first_tasks.count(task)}
            for task in tasks.index
        ],
        "obs_dim": OBS_DIM,
        "obs_layout": craft_observation_layout(),
        "failures": sum(s["expert_failures"] for s in sessions),
        "seed": ", ".join(str(s["seed"]) for s in sessions),
        "commands": [s["command"] for s in sessions],
    }


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
    text = render_card("craft", craft_card_context(root, repo_id))
    annotation = Path(root) / ANNOTATION
    if annotation.is_file():
        text = text.rstrip("\n") + "\n\n" + annotation_section(json.loads(annotation.read_text()))
    return text
