"""Pre/post-processing pipelines of the compILE policy: OCN's (LeRobot's defaults; the raw task
strings pass through), looked up by LeRobot under the `compile` name."""

from lerobot_policy_ocn.ocn.processor_ocn import make_ocn_pre_post_processors as make_compile_pre_post_processors

__all__ = ["make_compile_pre_post_processors"]
