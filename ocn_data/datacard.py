"""Render a dataset card (Hugging Face `README.md` with YAML front matter) from `datacards/`."""

from __future__ import annotations

from pathlib import Path

import jinja2

DATACARDS = Path(__file__).resolve().parent.parent / "datacards"


def render_card(template: str, context: dict) -> str:
    """Fill `datacards/<template>.md` with `context`; a missing value is an error, not a blank."""
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(DATACARDS), undefined=jinja2.StrictUndefined, keep_trailing_newline=True
    )
    return env.get_template(f"{template}.md").render(**context)


def write_card(root: str | Path, template: str, context: dict) -> Path:
    """Write the rendered card as the dataset root's `README.md`."""
    path = Path(root) / "README.md"
    path.write_text(render_card(template, context))
    return path
