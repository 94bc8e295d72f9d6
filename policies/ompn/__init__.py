"""The Ordered Memory Policy Network baseline for LeRobot; importing this registers the `ompn` policy type."""

from .configuration_ompn import OMPNConfig
from .modeling_ompn import OMPNPolicy
from .processor_ompn import make_ompn_pre_post_processors

__all__ = ["OMPNConfig", "OMPNPolicy", "make_ompn_pre_post_processors"]
