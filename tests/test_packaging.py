"""The distribution as a wheel install sees it, not as the editable checkout does: a file the code
reads at run time (the card templates) must travel in the wheel, or `pip install` users get a
`record_demos` that records every episode and then fails writing the card."""

import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SOURCES = ["pyproject.toml", "README.md", "ocn_data", "envs", "policies", "tools", "datacards"]
TEMPLATES = sorted(p.name for p in (REPO / "datacards").glob("*.md"))


@pytest.fixture(scope="module")
def unpacked_wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The project's wheel, built by setuptools' PEP 517 backend from a copy of the sources (so that
    the checkout gets no build/ or egg-info), unpacked as pip would lay it into site-packages."""
    work = tmp_path_factory.mktemp("wheel")
    source, dist, installed = work / "source", work / "dist", work / "installed"
    source.mkdir()
    for name in SOURCES:
        origin = REPO / name
        if origin.is_dir():
            shutil.copytree(origin, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(origin, source / name)
    build = "from setuptools import build_meta; print(build_meta.build_wheel(__import__('sys').argv[1]))"
    done = subprocess.run([sys.executable, "-c", build, str(dist)], cwd=source, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    wheel = dist / done.stdout.strip().splitlines()[-1]
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(installed)
    return installed


def test_wheel_ships_every_card_template(unpacked_wheel: Path) -> None:
    shipped = sorted(p.name for p in (unpacked_wheel / "lerobot_policy_ocn" / "datacards").glob("*.md"))
    assert shipped == TEMPLATES


def test_installed_datacard_module_finds_its_templates(unpacked_wheel: Path) -> None:
    """`ocn_data.datacard` imported from the wheel (not the checkout) renders from the wheel's templates."""
    probe = (
        "import jinja2, lerobot_policy_ocn.ocn_data.datacard as d; "
        "print(d.__file__); "
        "print(sorted(jinja2.Environment(loader=jinja2.FileSystemLoader(d.DATACARDS)).list_templates()))"
    )
    # -S skips the .pth files, among them the editable install's import hook that would map
    # ocn_data to the checkout; the environment's packages come after the wheel on the path, and
    # the working directory (first on `-c`'s path) is the wheel's, not the checkout.
    path = [str(unpacked_wheel), *site.getsitepackages()]
    done = subprocess.run([sys.executable, "-S", "-c", probe], capture_output=True, text=True,
                          cwd=unpacked_wheel, env={"PYTHONPATH": os.pathsep.join(path), "PATH": ""})
    assert done.returncode == 0, done.stderr[-2000:]
    module_file, templates = done.stdout.strip().splitlines()
    assert Path(module_file).is_relative_to(unpacked_wheel)
    assert templates == str(TEMPLATES)


def test_a_users_own_envs_and_tools_folders_do_not_shadow_the_plugin(tmp_path: Path) -> None:
    """Installed, the project is one import root, `lerobot_policy_ocn`: a user's project with packages named
    like this repository's folders (`envs`, `tools`, `ocn_data`, `policies`), first on the path as the working
    directory is for `python -c` and `python -m`, changes nothing."""
    for name in ("envs", "tools", "ocn_data", "policies"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"raise ImportError('the user project’s own {name}')\n")
    probe = ("import lerobot, lerobot_policy_ocn; from lerobot.configs.policies import PreTrainedConfig; "
             "from lerobot.envs.configs import EnvConfig; "
             "print(PreTrainedConfig.get_choice_class('ocn').__module__, "
             "EnvConfig.get_choice_class('craft').__module__)")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["lerobot_policy_ocn.ocn.configuration_ocn",
                                   "lerobot_policy_ocn.envs.craft.lerobot_config"]


def test_the_root_registers_only_where_lerobot_is_loaded_so_commands_start_without_torch() -> None:
    probe = ("import sys, lerobot_policy_ocn.tools.cli.ocn_eval; print('torch' in sys.modules); "
             "lerobot_policy_ocn.register(); from lerobot.configs.policies import PreTrainedConfig; "
             "print(PreTrainedConfig.get_choice_class('ocn').__name__)")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False", "OCNConfig"]
