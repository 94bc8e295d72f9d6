"""What `ocn-finetune`'s command line shows before any work starts: PPO's hyperparameters, the fresh
controller's temperature and the resume file. Apart from the finetuning itself (`finetuning`, which
loads torch and LeRobot), so that `ocn-finetune --help` answers at once."""

from dataclasses import dataclass

# The new controller's softmax temperature unless --temperature says otherwise (module docstring).
FRESH_CONTROLLER_TEMPERATURE = 1.0

# What --resume goes on from, in --out.
STATE_FILE = "training_state.pt"


@dataclass
class PPOConfig:
    """PPO hyperparameters; defaults from the paper's appendix A.2 (table 3) where it gives them."""

    lr: float = 3e-4
    epochs: int = 4
    batch_size: int = 256  # controller decisions per minibatch (whole episodes, so about this many)
    gamma: float = 0.97
    gae_lambda: float = 0.95
    clip: float = 0.2
    entropy_coef: float = 1e-3
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    value_hidden: int = 64

    def __post_init__(self) -> None:
        if self.lr <= 0 or self.epochs < 1 or self.batch_size < 1:
            raise ValueError("lr must be > 0, epochs and batch_size >= 1.")
        if not (0 < self.gamma <= 1 and 0 <= self.gae_lambda <= 1 and self.clip > 0):
            raise ValueError("gamma must be in (0, 1], gae_lambda in [0, 1] and clip > 0.")
