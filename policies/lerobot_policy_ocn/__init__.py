"""LeRobot plugin entry point.

LeRobot's CLIs import every installed distribution named `lerobot_policy_*` by that name; importing
this package registers the project's Craft envs with gymnasium, the `ocn` and `ompn` policy types
and the `craft` env type (`--env.type=craft`).
"""

import envs  # noqa: F401  (registers OCN/Craft-v0, OCN/CraftFull-v0 and OCN/CraftLeRobot-v0)
import envs.craft.lerobot_config  # noqa: F401  (registers the `craft` env type)
import policies.ocn  # noqa: F401  (registers the `ocn` policy type)
import policies.ompn  # noqa: F401  (registers the `ompn` policy type)
