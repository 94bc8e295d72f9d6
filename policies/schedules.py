"""Learning-rate schedules that LeRobot does not ship, registered with its scheduler registry so that
`lerobot-train` builds them from a policy's preset and a resumed run reads them back from its
`train_config.json`."""

from dataclasses import dataclass

from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR

from lerobot.optim.schedulers import LRSchedulerConfig


@LRSchedulerConfig.register_subclass("step_decay")
@dataclass
class StepDecaySchedulerConfig(LRSchedulerConfig):
    """Every parameter group keeps its lr for `decay_step` optimizer steps, then runs at `factor` times it."""

    decay_step: int = 1
    factor: float = 0.1
    num_warmup_steps: int | None = None

    def build(self, optimizer: Optimizer, num_training_steps: int) -> LambdaLR:
        return LambdaLR(optimizer, lambda step: 1.0 if step < self.decay_step else self.factor)
