"""Configuration of the Ordered Memory Policy Network (OMPN) baseline, registered with LeRobot as `ompn`."""

from dataclasses import dataclass
from typing import ClassVar

from lerobot.configs import PreTrainedConfig

from lerobot_policy_ocn.sequence import SequenceConfig


@PreTrainedConfig.register_subclass("ompn")
@dataclass
class OMPNConfig(SequenceConfig):
    """Hyperparameters of OMPN (Lu et al. 2021) plus the LeRobot plumbing it shares with OCN.

    Defaults are OMPN's Craft setup, read from its public code (Ordered-Memory-RL/ompn_craft:
    `ilflagfile`, the `omstack` architecture in `gym_psketch/bots/omdec.py` and `om_utils.py`):
    3 slots of width H = 128, cells with an MLP of width 4H, lr 1e-3 (Adam), gradient-norm clip
    0.2. Its batch size, 256, is lerobot-train's `--batch_size=256`; its 10k steps are `--steps`.
    OMPN truncates backpropagation every 64 steps; the windows here hold whole episodes of at most
    `window_size` frames (Craft demonstrations are far shorter than 64), so nothing is truncated.

    The windows, the encoder (OMPN's 1075-float Craft features, built from the stored compact
    state) and the task list are `SequenceConfig`'s. OMPN's own free runs act greedily; the default
    here samples, as OCN's evaluation does, so that success rates compare (set
    `inference_mode="greedy"` for OMPN's protocol).

    `boundary_threshold` picks the boundary read-out of the parse (`ocn-eval`): None, the top-k
    steps of the expected expansion with k told by each episode's true number of subtasks, as OMPN
    evaluates; a value in (0, 1), the count-free read-out at that threshold of the scaled height
    (`modeling_ompn.threshold_boundaries`), which, like OCN's, is told nothing.
    """

    model_name: ClassVar[str] = "OMPN"

    n_slots: int = 3
    hidden_size: int = 128
    cell_hidden_size: int = 512

    optimizer_lr: float = 1e-3
    optimizer_grad_clip_norm: float = 0.2

    boundary_threshold: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_slots < 2:
            raise ValueError(f"n_slots must be >= 2 (a memory of one slot has no hierarchy), got {self.n_slots}.")
        if self.hidden_size < 1 or self.cell_hidden_size < 1:
            raise ValueError(
                f"hidden_size and cell_hidden_size must be >= 1, got {self.hidden_size} and {self.cell_hidden_size}."
            )
        if self.boundary_threshold is not None and not 0.0 < self.boundary_threshold < 1.0:
            raise ValueError(f"boundary_threshold must lie in (0, 1) or be None, got {self.boundary_threshold}.")
