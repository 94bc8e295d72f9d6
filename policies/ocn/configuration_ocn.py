"""Configuration of the Option-Controller Network (OCN) policy, registered with LeRobot as `ocn`."""

from dataclasses import dataclass
from typing import ClassVar

from lerobot.configs import PreTrainedConfig

from policies.sequence import SequenceConfig, check_choice

EXECUTIONS = ("soft", "hard")
HIERARCHIES = ("ocn", "moe", "hil")
TERMINATION_PENALTIES = ("linear", "log")


# What the usage balance may count as an option's use of a frame (`OCNConfig.usage_balance_source`).
USAGE_BALANCE_SOURCES = ("controller", "posterior", "untempered")


@PreTrainedConfig.register_subclass("ocn")
@dataclass
class OCNConfig(SequenceConfig):
    """Hyperparameters of OCN (paper section 3, appendix A.2) plus the LeRobot plumbing.

    The window fields, the encoder and action head choices, the task list and the optimiser preset
    are `SequenceConfig`'s (see its docstring for how a training window becomes a sequence).

    `hierarchy` selects the model family:
    - "ocn" (default): the paper's model; options run until their learned termination fires.
    - "moe": the Mixture-of-Experts baseline (paper section 4 and appendix A.3): the same network
      without termination, so the controller re-chooses its option distribution at every step. The
      termination e_t is fixed at 1 at every step, in training (eq. 17 then always takes its "done"
      branch: the controller steps and every option restarts from h^o_0, so an option only sees the
      current observation) and in both executions: under "hard" the controller samples an option
      at every step, so in PPO finetuning every option lasts exactly one step. The options keep
      their (then untrained and unused) termination heads so that the checkpoint layout is OCN's.
    - "hil": the HIL baseline (the paper's section 4 after Le et al. 2018): a high level over
      low-level skills of fixed length `skill_length` (L). e_t is fixed at 1 at steps t = 1, 1 + L,
      1 + 2L, ... of the episode (counted from its first frame, or from the window's first frame
      under `window_start="any"`) and at 0 at every other step, in training, in parsing and in both
      executions: under "hard" the controller samples an option every L steps, so in PPO
      finetuning every option lasts exactly L steps (the episode's end may cut the last one short).
      At the steps in between eq. 17 takes its "not done" branch, so, as under "moe", the options'
      termination heads are kept but unused. Le et al. train their low level on expert subgoal
      labels; this baseline, as the OCN paper describes it, learns its fixed-length skills from
      the demonstrations alone, without labels. "moe" is the same schedule with L = 1.

    `decoder_latents` > 0 makes the options frozen compILE decoders instead of OCN cells
    (`latent_options.LatentDecoderPool`): option d * K + k is compILE decoder d given the one-hot
    latent k, K = `decoder_latents`, each decoder an MLP of width `decoder_hidden_size`. It is how
    `ocn-finetune` runs compILE's RL form (a fresh controller choosing a latent at every step, so
    `hierarchy` must be "moe"); nothing trains such a pool by behaviour cloning.
    """

    model_name: ClassVar[str] = "OCN"

    n_options: int = 3
    hidden_size: int = 128
    mlp_hidden_size: int = 128
    mlp_depth: int = 2
    # The options' own MLP width and depth (0: the controller's mlp_hidden_size and mlp_depth; the paper
    # gives both one size), and `affine_options`: MLP layers without their tanh, so that an option's
    # action parameters and termination logit are affine in its input. Options of less capacity each fit
    # fewer kinds of motion. On Dial an affine map of the observation per digit explains most of the
    # expert's control, and per group of key-to-key moves (what wide options settle on) less
    # (results/dial_option_capacity/), so affine options make one digit's skill the cheapest thing for an
    # option to be.
    option_mlp_hidden_size: int = 0
    option_mlp_depth: int = 0
    affine_options: bool = False
    temperature: float = 10.0
    # Whether each option carries its hidden state h^o from step to step (eq. 1-3, the paper). False
    # feeds every option step its learned initial state instead, so an option is a function of the
    # current observation alone. It is for worlds where a recurrent option can read its target off
    # its own past motion, and so never has to become one skill (Dial: a PID reach reveals its joint
    # targets within a few steps, and the options stop splitting by digit); Craft keeps the default.
    # Measured on Dial (results/dial_memoryless/): with `dial_keys`, a unit std, the usage balance and
    # termination_cost=1, memoryless options are the first that induction splits by digit from
    # scratch (on two of five seeds); without the cost they hand over at most steps and do not.
    option_memory: bool = True
    # Training-time probability, per step and window row, that e_t is forced to 1 (0: never, the
    # paper): the controller chooses again and the options restart mid-subtask. A regulariser for the
    # same Dial failure: options that must take over mid-reach from their initial states have to
    # carry their digit themselves. Parsing and acting never force.
    forced_restart_rate: float = 0.0
    # Spread of the learned initial states (the controller's per task, the options') at construction:
    # 0 starts them all at zero (every task then first picks the same options), > 0 draws them from
    # N(0, std^2). The paper does not say.
    initial_state_std: float = 0.0
    # Added to the loss: this weight times the mean of e_t over each window's real frames after the
    # first (0: the paper's loss). Within a subtask a termination costs the NLL nothing when the
    # controller picks the same option again, so the paper's loss leaves the options free to end
    # mid-subtask, which fails them when they run alone (the option x subtask table, and finetuning,
    # where the new controller may then pick another). A cost per termination (option-critic's
    # "deliberation cost") keeps only the terminations that the actions pay for: the subtask ends.
    termination_cost: float = 0.0
    # What the termination cost charges per frame: "linear", e_t itself; "log", -log(1 - e_t), the NLL
    # of "go on" under a Bernoulli(e_t). The linear cost's gradient in the termination logit,
    # e_t (1 - e_t), vanishes where a termination is confident, so it hardly moves the confident
    # mid-subtask terminations that fail an option run alone; the log cost's, e_t, does not. Either way
    # a termination is kept where restarting raises the action likelihood by more than the cost.
    termination_penalty: str = "linear"
    # Added to the loss: this weight times sum_i p^c_{t-1,i} e_{i,t} p_i(a_t) over each window's real
    # frames after the first, p_i(a_t) being the continuing option's own probability of the demonstrated
    # action (p^c and p_i held fixed, so only the terminations move). Where the continuing option and the
    # next one both explain the action, the NLL does not care which acts and a termination one step early
    # costs it nothing; this charges a termination by how well the option it ends would have done, so an
    # option keeps the steps it can explain and ends where it cannot (0: the paper's loss). Measured on
    # S1 (results/imitation_s1_dart/, "Two more probes"): it made boundaries late and left the early ones;
    # from step 0 it suppresses the switches instead (results/imitation_s1_dart/explained_cost_screen/).
    explained_termination_cost: float = 0.0
    # Added to the loss: this weight times 0.5 ||p^c_t - p^c_{t-1}||_1 over each window's real frames
    # after the first, the probability mass that changes option at step t (0: the paper's loss). It is
    # 0 wherever the controller picks the running option again, however often options terminate, and
    # 0 at initialisation, where every p^c is near uniform, so unlike a termination cost it does not
    # hold the split back. Where a restart explains the action as well whichever option the controller
    # picks, it tips the choice to the running option, so that option keeps (and learns) the step.
    # Measured on S1's DART recording (results/imitation_s1_switch_cost/): at 0.3 it keeps the `use`
    # after a vertical move with its own subtask's option on seeds where the study's recipe hands it to
    # the next (seeds 1 and 2, alignment 0.955 and 0.902 to 0.981 and 0.978), at the price of a few
    # missed switches before short final subtasks; seed 2 still hands a third of those steps over
    # after step 3,000, and seed 4 stalls in a shared pair, so the study does not use it by default.
    switch_cost: float = 0.0
    # Added to the loss: this weight times KL(u || uniform), u being the batch's mean p^c over its
    # real frames (0: the paper's loss). Under the NLL alone, the option that first fits a little
    # better is picked more, so it trains more and is picked more still: within a few hundred
    # steps one option takes most frames and learns to infer its subtask from the observation,
    # and the others wait for a split that may or may not come (the load-balancing term of
    # mixture-of-experts models, on the option shares).
    usage_balance: float = 0.0
    # How many options' worth of usage the balance asks for, K (0: all n_options). The term becomes
    # max(0, ln K - H(u)), which is KL(u || uniform) = ln N - H(u) at K = N. At K < N it lets the
    # spare options go idle: KL to the uniform asks every one of 6 options for a sixth of the frames,
    # so over 3 subtasks it puts each subtask on two options, and caps NMI near 0.76. Measured at T = 10
    # (results/imitation_s1_6options_spare/): the tempered p^c keeps the shares' entropy above ln 3, so
    # at K = 3 the term never charged, and two of 6 options took the three subtasks.
    usage_balance_options: int = 0
    # With K < N: charge |ln K - H(u)| instead of the floor max(0, ln K - H(u)), so that usage spread
    # over more than K options' worth is charged too. Its gradient moves share from the rarer options
    # to the commoner ones, which merges two options that each hold the same subtask in some episodes.
    # Measured on 6 options (results/imitation_s1_6options_settled/): after the full balance has split
    # them, K = 3 exact merged the pairs where the floor left one subtask on two options.
    usage_balance_exact: bool = False
    # What the balance counts as an option's use of a frame. "controller": its weight p^c_t.
    # "untempered": p^c_t without the temperature, softmax(T log p^c_t), which where the controller
    # decides afresh is softmax of its logits: near its actual pick even while the tempered p^c is
    # soft. "posterior": the option's responsibility for the demonstrated action, its components'
    # share w_k p_k(a_t) / p^a_t(a_t) of the mixed likelihood. The last two are sharp where the
    # tempered weights are not, so that a floor of K < N options can charge a pool that has put
    # three subtasks on two options. Measured on 6 options at K = 3 from step 0 (results/
    # imitation_s1_6options_settled/, screen): the posterior charged nothing before the options
    # differed, as the controller's weight did not, and the untempered one kept NMI under 0.02 to
    # step 2,000; what split 6 options is the full balance first and K = 3 only once they have split.
    usage_balance_source: str = "controller"
    # Added to the loss: this weight times the expected NLL under the mixture weights,
    # sum_k w_k (-log p_k(a_t)), averaged like the NLL (0: the paper's loss alone). Over discrete
    # actions the mixture of the options' categoricals is itself one categorical, so under the
    # mixture NLL the options may cooperate: two options that each know only part of a subtask can
    # predict the action together, in weights that the task-aware controller sets. The expected NLL
    # charges every weighted option for its own prediction. Measured on S1 (results/
    # imitation_s1_split_time/, third part): it sharpened one blurred split and broke no stuck pair.
    # From step 0 on S1's DART recording (results/imitation_s1_dart/explained_cost_screen/) it leaves
    # no boundary early; at 1 and 0.3 the options split by position first and by subtask late or not at
    # all. At 0.1, through lerobot-train on five seeds (results/imitation_s1_expected_nll/), every
    # boundary is on time and every 3-option imitation bar holds (NMI 0.998, alignment 0.999).
    expected_nll_weight: float = 0.0
    # Train on given option labels instead of inducing them (`OCNPolicy.labelled_forward`): each
    # frame's NLL under its labelled option, the controller's cross-entropy at each labelled change and
    # the running option's termination as a binary cross-entropy, weighted by `taught_termination_weight`.
    # The labels come from a labelled packed view (`ocn_data.packed_view --option-labels`, which needs
    # window_start="packed"), such as those `tools.affine_segmentation` fits without the subtask labels:
    # on Dial, where the paper's loss rarely splits the digits, models taught them and then trained on
    # the paper's loss met the imitation bars on two seeds of four (results/dial_affine_labels/). The
    # other loss terms above are not used while it is on.
    taught_options: bool = False
    taught_termination_weight: float = 1.0

    # How `select_action` runs the hierarchy. "soft": the differentiable eq. 17 mixture that training
    # uses. "hard": the option-level semantics of the RL phase (appendix A.1): the controller samples
    # one option, which acts alone until its sampled termination fires, then the controller (whose
    # state advances only at these decisions) samples the next one, which restarts from h^o_0.
    # `forward` and `parse` are the soft recurrence in both cases.
    execution: str = "soft"
    hierarchy: str = "ocn"
    # Steps per skill under hierarchy="hil" (ignored otherwise). 4 by default: in the S1 demonstrations
    # that record_demos writes (paper mode) a subtask takes 4.4 steps on average (median 4, 2-7 for
    # the middle 80%) and an episode 8.8, so L = 4 is the typical subtask length, puts a skill
    # boundary within 2 steps of every true subtask end and gives 2-3 controller decisions per
    # demonstration.
    skill_length: int = 4

    # The controller's learning rate is optimizer_lr * controller_lr_scale. The paper slows the
    # controller by dividing its logits by T, which also shrinks its gradients; Adam normalises
    # gradient scale away, so this is the way to keep the controller slower under Adam.
    controller_lr_scale: float = 1.0

    # Options that are compILE decoders' latents (0: OCN cells); see the class docstring.
    decoder_latents: int = 0
    decoder_hidden_size: int = 128

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("execution", self.execution, EXECUTIONS)
        if self.n_options < 1 or self.mlp_depth < 1:
            raise ValueError(f"n_options and mlp_depth must be >= 1, got {self.n_options} and {self.mlp_depth}.")
        if self.option_mlp_hidden_size < 0 or self.option_mlp_depth < 0:
            raise ValueError(f"option_mlp_hidden_size and option_mlp_depth must be >= 0 (0: the controller's), got "
                             f"{self.option_mlp_hidden_size} and {self.option_mlp_depth}.")
        check_choice("hierarchy", self.hierarchy, HIERARCHIES)
        if self.skill_length < 1:
            raise ValueError(f"skill_length must be >= 1, got {self.skill_length}.")
        if self.controller_lr_scale <= 0:
            raise ValueError(f"controller_lr_scale must be > 0, got {self.controller_lr_scale}.")
        if not 0.0 <= self.forced_restart_rate < 1.0:
            raise ValueError(f"forced_restart_rate must be in [0, 1), got {self.forced_restart_rate}.")
        check_choice("termination_penalty", self.termination_penalty, TERMINATION_PENALTIES)
        if self.termination_cost < 0:
            raise ValueError(f"termination_cost must be >= 0, got {self.termination_cost}.")
        if self.explained_termination_cost < 0:
            raise ValueError(f"explained_termination_cost must be >= 0, got {self.explained_termination_cost}.")
        if self.switch_cost < 0:
            raise ValueError(f"switch_cost must be >= 0, got {self.switch_cost}.")
        for name in ("forced_restart_rate", "termination_cost", "explained_termination_cost", "switch_cost"):
            if getattr(self, name) and self.hierarchy != "ocn":
                raise ValueError(f"{name} is for hierarchy='ocn', whose options end by themselves, "
                                 f"not {self.hierarchy!r}.")
        if self.usage_balance < 0:
            raise ValueError(f"usage_balance must be >= 0, got {self.usage_balance}.")
        if not 0 <= self.usage_balance_options <= self.n_options:
            raise ValueError(
                f"usage_balance_options must be in [0, n_options = {self.n_options}], got {self.usage_balance_options}."
            )
        if self.usage_balance_exact and not 0 < self.usage_balance_options < self.n_options:
            raise ValueError(f"usage_balance_exact needs 0 < usage_balance_options < n_options = {self.n_options}, "
                             f"got usage_balance_options = {self.usage_balance_options}.")
        check_choice("usage_balance_source", self.usage_balance_source, USAGE_BALANCE_SOURCES)
        if self.expected_nll_weight < 0:
            raise ValueError(f"expected_nll_weight must be >= 0, got {self.expected_nll_weight}.")
        if self.initial_state_std < 0:
            raise ValueError(f"initial_state_std must be >= 0, got {self.initial_state_std}.")
        if self.temperature <= 0:
            raise ValueError(f"temperature must be > 0, got {self.temperature}.")
        if self.taught_options and self.hierarchy not in ("ocn", "moe"):
            raise ValueError(f"taught_options teaches OCN or MoE their options, not hierarchy={self.hierarchy!r}.")
        if self.taught_options and not self.packed:
            raise ValueError("taught_options reads the labels of a labelled packed view: train it with "
                             f"--policy.window_start=packed, not {self.window_start!r}.")
        if self.taught_termination_weight < 0:
            raise ValueError(f"taught_termination_weight must be >= 0, got {self.taught_termination_weight}.")
        if self.taught_termination_weight != 1.0 and self.hierarchy == "moe":
            raise ValueError("taught_termination_weight weighs the terminations' loss, which MoE, whose options "
                             "last one step, does not have.")
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
    def option_mlp(self) -> tuple[int, int]:
        """The options' MLP width and depth, the controller's where `option_mlp_hidden_size` or
        `option_mlp_depth` is 0."""
        return self.option_mlp_hidden_size or self.mlp_hidden_size, self.option_mlp_depth or self.mlp_depth

    @property
    def fixed_skill_length(self) -> int | None:
        """Steps every option runs for when the hierarchy fixes them (1 under "moe", `skill_length`
        under "hil"); None under "ocn", whose options end where their learned termination fires."""
        return {"ocn": None, "moe": 1, "hil": self.skill_length}[self.hierarchy]
