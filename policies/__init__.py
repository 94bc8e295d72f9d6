"""`lerobot_policy_ocn`: the Option-Controller Network for LeRobot, and everything around it.

This folder is the package's root; the repository's other folders are its subpackages
(`lerobot_policy_ocn.envs`, `.ocn_data`, `.tools`, `.datacards`: see pyproject.toml), so that
installed, the project adds one import name to site-packages and a user's own `envs/` or `tools/`
folder cannot shadow it.

LeRobot's CLIs import every installed distribution named `lerobot_policy_*` by that name, after
loading LeRobot, to let it register its types: here the `ocn`, `ompn` and `compile` policies and the
`craft` and `dial` envs (`register`). Those registrations import torch and LeRobot, seconds of work
that this project's own commands must not pay before they have parsed their arguments (`--help`), so
importing the package registers them only where LeRobot is already loaded. Code that imports this
package before LeRobot and then asks LeRobot for an `ocn` policy calls `register()` first.
"""

import sys


def register() -> None:
    """Register the project's policy and env types with LeRobot, and its gymnasium envs."""
    from lerobot_policy_ocn import compile, ocn, ompn  # noqa: F401  (register the `compile`, `ocn`, `ompn` types)
    from lerobot_policy_ocn.envs.craft import lerobot_config as craft  # noqa: F401  (registers `craft`)
    from lerobot_policy_ocn.envs.dial import lerobot_config as dial  # noqa: F401  (registers `dial`)


if "lerobot" in sys.modules:
    register()
