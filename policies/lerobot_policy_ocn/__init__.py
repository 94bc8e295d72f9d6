"""LeRobot plugin entry point.

LeRobot's CLIs import every installed distribution named `lerobot_policy_*` by that name; importing
this package registers the project's Craft and Dial envs with gymnasium, the `ocn`, `ompn` and
`compile` policy types and the `craft` and `dial` env types (`--env.type=craft`, `--env.type=dial`).
"""

import envs  # noqa: F401  (registers the OCN/Craft*, OCN/Dial* gymnasium ids)
import envs.craft.lerobot_config  # noqa: F401  (registers the `craft` env type)
import envs.dial.lerobot_config  # noqa: F401  (registers the `dial` env type)
import policies.ocn  # noqa: F401  (registers the `ocn` policy type)
import policies.ompn  # noqa: F401  (registers the `ompn` policy type)
import policies.compile  # noqa: F401  (registers the `compile` policy type)
