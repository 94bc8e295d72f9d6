"""The training clock of a recipe with phases: which phase a training step is in.

A recipe may end its run with a phase of its own loss (OCN's settling on Craft, the paper's loss
after the taught options on Dial) over the final part of `lerobot-train --steps`. The policy cannot
see `--steps`; the learning-rate scheduler can: LeRobot builds it with the run's number of steps and
steps it once per update, saves its state in every checkpoint and restores it on `--resume`. So the
policy's scheduler preset is `PhaseScheduleConfig`, whose scheduler doubles as the clock: `build`
files it under the parameters it steps (`clock_of`), and the policy reads its step count from there.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

from torch import Tensor
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR

from lerobot.optim.schedulers import LRSchedulerConfig

# Scheduler of the run that trains each parameter, by the parameter's id; an entry goes with its parameter
# (tensors compare element-wise, so they cannot be dictionary keys themselves).
_CLOCKS: dict[int, PhaseClock] = {}


def final_steps(total_steps: int, final_fraction: float) -> int:
    """How many of `total_steps` the final phase takes: the fraction, rounded, and 0 for no phase."""
    return round(total_steps * final_fraction)


class PhaseClock(LambdaLR):
    """A `LambdaLR` that knows the run's length. The policy sets its recipe's final phase on it
    (`set_final_phase`) before the first update; the lr is then 1 times the preset's before that phase
    and `final_lr_scale` times it in it."""

    def __init__(self, optimizer: Optimizer, total_steps: int) -> None:
        self.total_steps = total_steps
        self.first_final_step = total_steps
        self.final_lr_scale = 1.0
        super().__init__(optimizer, lambda step: self.final_lr_scale if step >= self.first_final_step else 1.0)

    def set_final_phase(self, final_fraction: float, final_lr_scale: float) -> None:
        """The last `final_fraction` of the run's steps is the final phase, at `final_lr_scale` times the lr."""
        self.first_final_step = self.total_steps - final_steps(self.total_steps, final_fraction)
        self.final_lr_scale = final_lr_scale

    @property
    def step_count(self) -> int:
        """Updates made so far (the next update's 0-based index)."""
        return self.last_epoch

    @property
    def in_final_phase(self) -> bool:
        return self.step_count >= self.first_final_step


@LRSchedulerConfig.register_subclass("ocn_phases")
@dataclass
class PhaseScheduleConfig(LRSchedulerConfig):
    """A constant lr with a final phase that the policy's recipe sets (`PhaseClock`)."""

    num_warmup_steps: int | None = None

    def build(self, optimizer: Optimizer, num_training_steps: int) -> PhaseClock:
        clock = PhaseClock(optimizer, num_training_steps)
        for group in optimizer.param_groups:
            for parameter in group["params"]:
                if id(parameter) not in _CLOCKS:
                    weakref.finalize(parameter, _CLOCKS.pop, id(parameter), None)
                _CLOCKS[id(parameter)] = clock
        return clock


def clock_of(parameter: Tensor) -> PhaseClock | None:
    """The clock of the run that trains `parameter`, if a `PhaseScheduleConfig` scheduler was built for it."""
    return _CLOCKS.get(id(parameter))
