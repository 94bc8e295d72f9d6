"""The package's layers, read from the source: no import cycles, and commands never lean on research probes.

Every module's imports are read with `ast` (module level and inside functions alike, since a lazy
import still ties two modules together) and mapped to modules of the one import root,
`lerobot_policy_ocn`, whose folders pyproject.toml's package-dir names.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
IMPORT_ROOT = "lerobot_policy_ocn"


def package_folders() -> dict[str, Path]:
    """Import name -> folder, from pyproject.toml's package-dir."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return {name: ROOT / folder for name, folder in config["tool"]["setuptools"]["package-dir"].items()}


def module_files() -> dict[str, Path]:
    """Every module of the import root and its file; a subpackage's folder is not also its parent's."""
    folders = package_folders()
    modules: dict[str, Path] = {}
    for name, folder in sorted(folders.items(), key=lambda item: -len(item[0])):
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            module = ".".join((name, *parts))
            if parts[-1] == "__init__":
                module = ".".join((name, *parts[:-1]))
            modules.setdefault(module, path)
    return modules


def imported_modules(path: Path, module: str, known: set[str]) -> set[str]:
    """The project's modules that `path` imports (the longest known prefix of each imported name; a
    package that Python initialises on the way to its submodule is not counted)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, base]) if base else ".".join(anchor)
            # `from package import module` needs the module; the package's own names need the package.
            for alias in node.names:
                names.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base)
    found = set()
    for name in names:
        while name and name not in known:
            name = name.rpartition(".")[0]
        if name and name != module and name != IMPORT_ROOT:
            found.add(name)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = module_files()
    return {module: imported_modules(path, module, set(files)) for module, path in files.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of the graph, or None (depth-first search with colours)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_the_graph_is_read(graph: dict[str, set[str]]) -> None:
    assert f"{IMPORT_ROOT}.tools.cli.ocn_eval" in graph
    assert f"{IMPORT_ROOT}.tools.eval.parsing" in graph[f"{IMPORT_ROOT}.tools.cli.ocn_eval"]


def test_no_import_cycle(graph: dict[str, set[str]]) -> None:
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph) or [])


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_commands_and_libraries_do_not_import_research_probes(graph: dict[str, set[str]]) -> None:
    research = f"{IMPORT_ROOT}.tools.research"
    leaning = {module: sorted(m for m in imports if m.startswith(research))
               for module, imports in graph.items() if not module.startswith(research)}
    assert not {module: probes for module, probes in leaning.items() if probes}


def test_the_policy_package_does_not_import_the_tools(graph: dict[str, set[str]]) -> None:
    """The policy (what lerobot-train loads) stands below the commands, the envs and the recorder."""
    above = tuple(f"{IMPORT_ROOT}.{name}" for name in ("tools", "ocn_data"))
    policy = [m for m in graph if not m.startswith(tuple(f"{IMPORT_ROOT}.{n}" for n in
                                                            ("tools", "ocn_data", "envs", "datacards")))]
    assert not {m: sorted(i for i in graph[m] if i.startswith(above)) for m in policy
                if any(i.startswith(above) for i in graph[m])}
