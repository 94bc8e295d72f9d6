"""The Option-Controller Network policy for LeRobot; importing this registers the `ocn` policy type."""

from .configuration_ocn import OCNConfig
from .modeling_ocn import OCNPolicy
from .processor_ocn import make_ocn_pre_post_processors

__all__ = ["OCNConfig", "OCNPolicy", "make_ocn_pre_post_processors"]
