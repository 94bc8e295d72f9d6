"""Configuration of the Option-Controller Network (OCN) policy, registered with LeRobot as `ocn`.

Its defaults are the project's measured recipe: plain `lerobot-train --policy.type=ocn` on a Craft
dataset trains what `results/imitation_s1.md` reports. The paper's loss alone is one switch away,
`--policy.recipe=paper`.
"""

from dataclasses import dataclass
from typing import Any, ClassVar

from lerobot.configs import PreTrainedConfig

from lerobot_policy_ocn.schedules import PhaseScheduleConfig
from lerobot_policy_ocn.sequence import AUTO, SequenceConfig, check_choice

EXECUTIONS = ("soft", "hard")
HIERARCHIES = ("ocn", "moe", "hil")
RECIPES = (AUTO, "craft", "dial", "paper")


@dataclass(frozen=True)
class Recipe:
    """What a recipe adds to the paper's loss (eq. 18, the NLL of the mixed action distribution), and its
    final phase: the last `final_fraction` of the run's steps, with its own loss and lr scale.

    `usage_balance` w adds w KL(u || uniform), u the batch's mean p^c over its real frames. Under the
    NLL alone, the option that first fits a little better is picked more, trains more and is picked
    more still, so one option soon takes most frames and the others may wait for a split that comes
    late or never; the term keeps every option in use while they specialise.
    `expected_nll_weight` w adds w sum_k w_k (-log p_k(a_t)), the expected NLL under the mixture
    weights. Over discrete actions the options' mixed categoricals are one categorical, so under the
    NLL two options that each know part of a subtask can cooperate through the weights; the expected
    NLL charges each weighted option for its own prediction, which puts every boundary on time.
    `settle_termination_cost` c (final phase) adds c times the mean of -log(1 - e_t) over the frames
    after the first. Within a subtask a termination costs the NLL nothing when the controller picks
    the same option again, so the options are left free to end mid-subtask, which fails them when they
    run alone (finetuning); once they have split, the cost removes those terminations. From the first
    step, it keeps them from splitting (the reason it waits for the final phase).
    `taught` trains the options on a split found without labels first (Dial; see `lerobot_policy_ocn.ocn.taught`),
    its terminations weighted `taught_termination_weight`; the final phase then trains the paper's
    loss at `final_lr_scale` times the rate.
    """

    usage_balance: float = 0.0
    expected_nll_weight: float = 0.0
    final_fraction: float = 0.0
    settle_termination_cost: float = 0.0
    final_lr_scale: float = 1.0
    taught: bool = False
    taught_termination_weight: float = 1.0
    n_options: int = 3


# The measured recipes (the archive's index, results/archive/README.md, says what each part showed).
RECIPE_TABLE: dict[str, Recipe] = {
    # results/imitation_s1.md: NMI >= 0.95 and F1@1 >= 0.95 on every seed from the plain command.
    "craft": Recipe(usage_balance=1.0, expected_nll_weight=0.1, final_fraction=1 / 6, settle_termination_cost=0.1),
    # results/archive/dial_affine_2026-12-06: options taught the switching affine fit's split,
    # then the paper's loss at 3e-5.
    "dial": Recipe(final_fraction=0.2, final_lr_scale=0.03, taught=True, taught_termination_weight=5.0, n_options=4),
    "paper": Recipe(),
}


@PreTrainedConfig.register_subclass("ocn")
@dataclass
class OCNConfig(SequenceConfig):
    """Hyperparameters of OCN (paper section 3, appendix A.2) plus the LeRobot plumbing.

    `recipe` names what trains the model (`Recipe`, `RECIPE_TABLE`): "auto" (the default) takes
    "craft" for discrete actions and "dial" for continuous ones when the policy is built from a
    dataset; "paper" is the paper's loss alone. `n_options` 0 takes the recipe's (3; Dial's 4 digits).
    The window, encoder and action fields that follow from the dataset are `SequenceConfig`'s.

    `hierarchy` selects the model family:
    - "ocn" (default): the paper's model; options run until their learned termination fires.
    - "moe": the Mixture-of-Experts baseline (paper section 4 and appendix A.3): the same network
      with the termination e_t fixed at 1 at every step, in training and in both executions, so the
      controller re-chooses at every step and every option restarts from h^o_0. The options keep
      their (unused) termination heads so that the checkpoint layout is OCN's.
    - "hil": the HIL baseline (after Le et al. 2018): a high level over low-level skills of fixed
      length `skill_length` L: e_t is 1 at steps t = 1, 1 + L, 1 + 2L, ... and 0 elsewhere. As the OCN
      paper describes it, the skills are learned from the demonstrations alone, without labels.
    The baselines train on the recipe's loss with the terms that only OCN's own terminations use
    (the settling cost, the taught terminations' weight) left out.

    `decoder_latents` > 0 makes the options frozen compILE decoders instead of OCN cells
    (`latent_options.LatentDecoderPool`): option d * K + k is compILE decoder d given the one-hot
    latent k, K = `decoder_latents`. It is how `ocn-finetune` runs compILE's RL form (a fresh
    controller choosing a latent at every step, so `hierarchy` must be "moe"); nothing trains such a
    pool by behaviour cloning.
    """

    model_name: ClassVar[str] = "OCN"

    recipe: str = AUTO
    n_options: int = 0
    hidden_size: int = 128
    mlp_hidden_size: int = 128
    mlp_depth: int = 2
    temperature: float = 10.0

    # How `select_action` runs the hierarchy. "soft": the differentiable eq. 17 mixture that training
    # uses. "hard": the option-level semantics of the RL phase (appendix A.1): the controller samples
    # one option, which acts alone until its sampled termination fires, then the controller (whose
    # state advances only at these decisions) samples the next one, which restarts from h^o_0.
    # `forward` and `parse` are the soft recurrence in both cases.
    execution: str = "soft"
    hierarchy: str = "ocn"
    # Steps per skill under hierarchy="hil" (ignored otherwise). 4 by default: in the S1 demonstrations
    # a subtask takes 4.4 steps on average (median 4), so L = 4 puts a skill boundary within 2 steps of
    # every true subtask end.
    skill_length: int = 4

    # Options that are compILE decoders' latents (0: OCN cells); see the class docstring.
    decoder_latents: int = 0
    decoder_hidden_size: int = 128

    def __post_init__(self) -> None:
        check_choice("recipe", self.recipe, RECIPES)
        if self.recipe != AUTO and not self.n_options:
            self.n_options = RECIPE_TABLE[self.recipe].n_options
        super().__post_init__()
        check_choice("execution", self.execution, EXECUTIONS)
        check_choice("hierarchy", self.hierarchy, HIERARCHIES)
        if self.n_options < 0 or self.mlp_depth < 1:
            raise ValueError(f"n_options must be >= 1 (0: the recipe's) and mlp_depth >= 1, got {self.n_options} "
                             f"and {self.mlp_depth}.")
        if self.skill_length < 1:
            raise ValueError(f"skill_length must be >= 1, got {self.skill_length}.")
        if self.temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {self.temperature}.")
        if self.recipe == "dial" and self.hierarchy == "hil":
            raise ValueError("The dial recipe teaches OCN or MoE their options, not hierarchy='hil'.")
        if self.decoder_latents < 0 or self.decoder_hidden_size < 1:
            raise ValueError(
                f"decoder_latents must be >= 0 and decoder_hidden_size >= 1, got {self.decoder_latents} "
                f"and {self.decoder_hidden_size}."
            )
        if self.decoder_latents and (self.n_options % self.decoder_latents or self.hierarchy != "moe"):
            raise ValueError(
                f"Options that are compILE decoders' latents last one step and come {self.decoder_latents} per "
                f"decoder: they need hierarchy='moe' and n_options a multiple of decoder_latents, got "
                f"{self.hierarchy!r} and {self.n_options}."
            )

    @property
    def resolved(self) -> bool:
        return super().resolved and self.recipe != AUTO and self.n_options > 0

    def resolve_from_dataset(self, dataset_meta: Any) -> None:
        """The "auto" fields of `SequenceConfig`, then the recipe by the action type and its option count."""
        super().resolve_from_dataset(dataset_meta)
        if self.recipe == AUTO:
            self.recipe = "craft" if self.action_type == "discrete" else "dial"
        if not self.n_options:
            self.n_options = RECIPE_TABLE[self.recipe].n_options
        if self.recipe == "dial" and self.obs_encoder == "identity" and dataset_meta.robot_type == "dial":
            # Dial's raw state with each key's log distance (encoders.DialKeyEncoder), which the taught
            # split was measured with; the normalisation that follows from it is the raw state's.
            self.obs_encoder = "dial_keys"
            self.normalization_mapping = self._default_normalization()

    @property
    def recipe_terms(self) -> Recipe:
        """The resolved recipe's terms (`RECIPE_TABLE`)."""
        if self.recipe == AUTO:
            raise ValueError("recipe='auto' is resolved when the policy is built from a dataset.")
        return RECIPE_TABLE[self.recipe]

    def get_scheduler_preset(self) -> PhaseScheduleConfig:
        """A constant lr that is also the policy's training clock (`lerobot_policy_ocn.schedules`): the policy sets
        its recipe's final phase on it, once the recipe is known."""
        return PhaseScheduleConfig()

    @property
    def fixed_skill_length(self) -> int | None:
        """Steps every option runs for when the hierarchy fixes them (1 under "moe", `skill_length`
        under "hil"); None under "ocn", whose options end where their learned termination fires."""
        return {"ocn": None, "moe": 1, "hil": self.skill_length}[self.hierarchy]
