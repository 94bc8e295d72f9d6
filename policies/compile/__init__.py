"""The compILE baseline for LeRobot; importing this registers the `compile` policy type."""

from .configuration_compile import CompILEConfig
from .modeling_compile import CompILEPolicy
from .processor_compile import make_compile_pre_post_processors

__all__ = ["CompILEConfig", "CompILEPolicy", "make_compile_pre_post_processors"]
