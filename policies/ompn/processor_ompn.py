"""Pre/post-processing pipelines of the OMPN policy: OCN's, since both map raw task strings to
per-task parameters inside the policy (LeRobot looks the factory up by the `ompn` name)."""

from lerobot_policy_ocn.ocn.processor_ocn import make_ocn_pre_post_processors as make_ompn_pre_post_processors

__all__ = ["make_ompn_pre_post_processors"]
