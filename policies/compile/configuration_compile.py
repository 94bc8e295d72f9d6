"""Configuration of the compILE baseline (Kipf et al. 2019), registered with LeRobot as `compile`."""

from dataclasses import dataclass
from typing import ClassVar

from lerobot.configs import PreTrainedConfig

from lerobot_policy_ocn.sequence import SequenceConfig, check_choice

LATENT_TYPES = ("concrete", "gaussian")


@PreTrainedConfig.register_subclass("compile")
@dataclass
class CompILEConfig(SequenceConfig):
    """Hyperparameters of compILE (Kipf et al., ICML 2019) in its behaviour-cloning form, plus the
    LeRobot plumbing it shares with OCN and OMPN (windows, encoder, action head, task list).

    Where each default comes from:
    - `n_segments` = 4 and `latent_type` = "concrete": the compILE baseline of OMPN's Craft setup
      (Lu et al. 2021; their `compile_max_segs` flag), as the OCN paper runs it.
    - `kl_z_weight` = `kl_b_weight` = 0.1 and `poisson_rate` = 3.0 (the mean segment length of the
      prior on boundaries): tkipf/compile's `get_losses` defaults (beta_z, beta_b, prior_rate),
      which OMPN's setup keeps.
    - `optimizer_lr` = 1e-4: the published learning rate of compILE on Craft in OMPN's setup; its
      published batch size, 256, is lerobot-train's `--batch_size=256`.
    - `latent_dim` = 32: tkipf/compile's default `--latent-dim` (for concrete latents, the number
      of categories: the per-step labels NMI reads).
    - `hidden_size` = 128: OMPN's Craft width, which its compILE baseline shares (one `hidden_size`
      flag for both models); it sizes the input embedding, the LSTM and the MLP heads.
    - `boundary_temperature` = `latent_temperature` = 1.0: tkipf/compile's Gumbel-softmax
      temperatures (temp_b, temp_z).
    - Gradient clipping is not part of compILE; `optimizer_grad_clip_norm` keeps the project's
      loose default (10), which LeRobot's optimizer preset needs a value for.

    compILE is task-agnostic: it infers each segment's latent from the demonstration itself, so the
    task list (kept from the dataset for the checkpoint) plays no part in the model. Windows are
    "episode" windows by default (`SequenceConfig`): each sample is one whole episode.
    """

    model_name: ClassVar[str] = "compILE"

    n_segments: int = 4
    latent_dim: int = 32
    latent_type: str = "concrete"
    hidden_size: int = 128
    kl_z_weight: float = 0.1
    kl_b_weight: float = 0.1
    poisson_rate: float = 3.0
    boundary_temperature: float = 1.0
    latent_temperature: float = 1.0

    optimizer_lr: float = 1e-4

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("latent_type", self.latent_type, LATENT_TYPES)
        if self.n_segments < 1 or self.latent_dim < 1 or self.hidden_size < 1:
            raise ValueError(
                "n_segments, latent_dim and hidden_size must be >= 1, got "
                f"{self.n_segments}, {self.latent_dim} and {self.hidden_size}."
            )
        if self.poisson_rate <= 0 or self.boundary_temperature <= 0 or self.latent_temperature <= 0:
            raise ValueError(
                "poisson_rate, boundary_temperature and latent_temperature must be > 0, got "
                f"{self.poisson_rate}, {self.boundary_temperature} and {self.latent_temperature}."
            )
        if self.kl_z_weight < 0 or self.kl_b_weight < 0:
            raise ValueError(
                f"kl_z_weight and kl_b_weight must be >= 0, got {self.kl_z_weight} and {self.kl_b_weight}."
            )
