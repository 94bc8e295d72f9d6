"""LeRobot plugin entry point.

LeRobot's CLIs import every installed distribution named `lerobot_policy_*` by that name; importing
this package registers the project's Craft envs with gymnasium (and, as they land, the `ocn`
policy type and the LeRobot env configs).
"""

import envs  # noqa: F401  (registers OCN/Craft-v0 and OCN/CraftFull-v0)
import policies.ocn  # noqa: F401  (registers the `ocn` policy type)
