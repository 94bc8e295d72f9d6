"""OCN as a LeRobot policy: batch plumbing, the NLL loss (eq. 18), stateful inference and parsing.

Batch plumbing shared with the other whole-episode policies (windows, masks, task table) is
`lerobot_policy_ocn.sequence`'s.
"""

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ocn.distributed import global_mean, global_sum
from lerobot_policy_ocn.schedules import clock_of
from lerobot_policy_ocn.sequence import SequencePolicy, frame_mask, window_nll

from .configuration_ocn import OCNConfig
from .encoders import make_encoder
from .cell import SparseRows
from .heads import expected_log_prob, make_action_head, mixture_log_prob
from .latent_options import LatentDecoderPool
from .taught import cached_split
from .recurrence import HardState, OCNCore, OCNState, StepOutput, longest_first


@dataclass
class StepReport:
    """Readout of the latest `select_action` step: p^c [B, N], option = argmax p^c [B], e_t [B].

    Under hard execution: p^c of the latest decision, the running (sampled) option, the previous
    option's termination probability e_{i,t} (1 at t = 1), and `decided` [B], the rows where the
    controller chose this step (None under soft execution, where it chooses softly every step).
    """

    p_c: Tensor
    option: Tensor
    end: Tensor
    decided: Tensor | None = None


def settle_penalty(end: Tensor) -> Tensor:
    """-log(1 - e_t), the NLL of "go on" under a Bernoulli(e_t), which the settling phase charges for each
    termination (`Recipe.settle_termination_cost`). Its gradient in the termination logit, e_t, does not
    vanish where a termination is confident, as a linear cost's e_t (1 - e_t) does. Clamped below e_t = 1,
    which only the forced first step reaches (and the cost leaves out)."""
    return -torch.log1p(-end.clamp_max(1.0 - 1e-6))


def usage_imbalance(p_c: Tensor, mask: Tensor) -> Tensor:
    """KL(u || uniform) of the options' share u, the mean of p^c [T, B, N] over the real frames mask [B, T]
    of the whole (distributed) batch: 0 when every option takes as many frames as the others, log N
    when one takes them all."""
    weights = mask.transpose(0, 1).unsqueeze(-1).to(p_c.dtype)
    share = global_sum((p_c * weights).sum((0, 1))) / global_sum(weights.sum()).clamp_min(1.0)
    return (share * torch.log(share.clamp_min(1e-12) * p_c.shape[-1])).sum()


# The per-frame option labels of a taught recipe, a column of the policy's episode memory.
OPTION = "option"


class OCNPolicy(SequencePolicy, PreTrainedPolicy):
    """Option-Controller Network: a shared controller over N options, one initial state per task."""

    config_class = OCNConfig
    name = "ocn"

    def __init__(self, config: OCNConfig, **kwargs: Any) -> None:
        super().__init__(config, **kwargs)
        self.encoder = make_encoder(config)
        self.head = make_action_head(config)
        self.core = OCNCore(
            obs_dim=self.encoder.out_dim,
            n_tasks=len(config.tasks),
            n_options=config.n_options,
            hidden_size=config.hidden_size,
            mlp_hidden_size=config.mlp_hidden_size,
            mlp_depth=config.mlp_depth,
            n_params=self.head.n_params,
            temperature=config.temperature,
            skill_length=config.fixed_skill_length,
            options=self._latent_options() if config.decoder_latents else None,
        )
        self.reset()

    def _latent_options(self) -> LatentDecoderPool:
        """The frozen compILE decoders that `decoder_latents` > 0 puts in place of the option cells."""
        config = self.config
        return LatentDecoderPool(
            n_decoders=config.n_options // config.decoder_latents,
            latent_dim=config.decoder_latents,
            in_dim=self.encoder.out_dim,
            width=config.decoder_hidden_size,
            n_out=self.head.n_params,
            hidden_size=config.hidden_size,
        )

    def get_optim_params(self) -> list[Tensor]:
        """One group: every part trains at the recipe's rate."""
        return list(self.parameters())

    def in_final_phase(self) -> bool:
        """Whether this training step is in the recipe's final phase (`Recipe.final_fraction`), read from
        the run's training clock (`lerobot_policy_ocn.schedules`), on which it first sets the recipe's phases."""
        terms = self.config.recipe_terms
        if not self.training or not terms.final_fraction:
            return False
        clock = clock_of(self.core.controller_init)
        if clock is None:
            raise ValueError(f"The {self.config.recipe} recipe ends with a phase over the last part of the run's "
                             "steps, which the policy reads from its scheduler preset: train with lerobot-train's "
                             "policy presets (the default), or build config.get_scheduler_preset() for the optimizer.")
        clock.set_final_phase(terms.final_fraction, terms.final_lr_scale)
        return clock.in_final_phase

    def reset(self) -> None:
        """Forget the recurrent state: the next `select_action` is t = 1 of new episodes."""
        self._state: OCNState | HardState | None = None
        self.last_step: StepReport | None = None

    def _unroll(self, state: Tensor, tasks: Sequence[str], real: Tensor | None = None) -> StepOutput:
        """Recurrence over windows [B, T, S] that each start an episode; outputs are time-major.
        `real` [B, T]: the frames whose outputs are read, each row's first ones (None: all); then only
        those are encoded and computed (`OCNCore.unroll_frames`) and the others' outputs are zeros."""
        batch, steps = state.shape[:2]
        task_index = self.task_index(tasks, batch)
        start = torch.zeros(steps, batch, dtype=torch.bool, device=state.device)
        start[0] = True
        if real is None:
            # Transpose the stored state rather than the (wider) features: the encoder then writes time-major.
            x = self.encoder(state.transpose(0, 1).contiguous())
            return self.core.unroll(x, self.core.initial_state(task_index), start)[1]
        order, inverse = longest_first(real)
        real = real[order].transpose(0, 1)
        x = self._training_features(state[order].transpose(0, 1).contiguous(), real)
        out = self.core.unroll_frames(x, self.core.initial_state(task_index[order]), start, real)
        return StepOutput(out.weights[:, inverse], out.params[:, :, inverse], out.p_c[:, inverse], out.end[:, inverse],
                          out.option_end[:, inverse])

    def _training_features(self, state: Tensor, real: Tensor) -> Tensor | SparseRows:
        """The cell input of time-major states [T, B, W] for training: Craft's OMPN features as their set
        entries where the option cells read them (`SparseRows`: the first layer sums 140 weight rows instead
        of multiplying 1,075 columns; results/bench_first_layer.md times the step both ways), else dense.
        Dense inputs encode the real frames ([T, B] `real`) alone, zeros elsewhere (the core reads nothing
        else): an image encoder's cost follows the frames trained on, not the padding of the batch's
        longest episode."""
        sparse = getattr(self.encoder, "sparse", None)
        rows = sparse(state) if sparse is not None and not self.config.decoder_latents else None
        if rows is not None:
            return rows
        frames = self.encoder(state[real])
        return frames.new_zeros(*real.shape, frames.shape[-1]).index_put_((real,), frames)

    def _component_log_prob(self, out: StepOutput, action: Tensor) -> Tensor:
        """log p_k(a_t) [T, 2N, B] of each mixture component, for time-major outputs and batch-major
        actions [B, T, A].

        LeRobot hands one-wide action features over as [B, T] (no feature axis), hence the reshape.
        """
        action = action.reshape(*action.shape[:2], self.config.action_dim)
        return self.head.log_prob(out.params, action.transpose(0, 1))

    @staticmethod
    def _action_log_prob(out: StepOutput, component: Tensor) -> Tensor:
        """log p^a_t(a_t) [B, T], the mixed action distribution's, from `_component_log_prob`'s."""
        return mixture_log_prob(out.weights, component).transpose(0, 1)

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """The recipe's loss (`Recipe`) on the batch's whole episodes: the NLL of the mixed action
        distribution, a mean over each episode's real frames and then over episodes, plus the recipe's
        terms; in the final phase, the settling cost too (or, after taught options, the paper's loss)."""
        mask, state, action, tasks, columns = self.training_windows(batch)
        terms, final = self.config.recipe_terms, self.in_final_phase()
        if terms.taught and not final:
            return self._taught_forward(mask, state, action, tasks, columns)
        out = self._unroll(state, tasks, mask)
        own_terminations = self.config.hierarchy == "ocn"
        penalties = {}
        if final and terms.settle_termination_cost and own_terminations:
            penalties["settle_penalty"] = (terms.settle_termination_cost, settle_penalty(out.end))
        component = self._component_log_prob(out, action)
        loss, stats = window_nll(self._action_log_prob(out, component), mask, reduction, {"mean_end": out.end},
                                 penalties)
        imbalance = usage_imbalance(out.p_c, mask)
        stats |= {"usage_imbalance": imbalance.item(), "final_phase": float(final)}
        if terms.usage_balance:
            loss = loss + terms.usage_balance * imbalance
        if terms.expected_nll_weight:
            expected_lp = expected_log_prob(out.weights, component).transpose(0, 1)
            expected, expected_stats = window_nll(expected_lp, mask, reduction, {})
            stats["expected_nll"] = expected_stats["nll"]
            loss = loss + terms.expected_nll_weight * expected
        return loss, stats

    def _remember_episodes(self, dataset_meta: Any) -> None:
        """The episodes in memory, and under a taught recipe each training frame's option label, from
        the switching affine split of the training episodes (`lerobot_policy_ocn.ocn.taught`); -1 elsewhere."""
        super()._remember_episodes(dataset_meta)
        if not self.config.recipe_terms.taught:
            return
        if not self.config.state_keys:
            raise ValueError("The dial recipe fits its taught split to the state features, and the policy reads "
                             "images alone: take --policy.recipe=paper.")
        memory = self._episodes
        rows = memory.trainable.nonzero().squeeze(1)
        mask, frames, _ = memory.batch(rows)
        state = torch.cat([frames[key].double() for key in self.config.state_keys], dim=-1)
        labels, report = cached_split(state.numpy(), frames[ACTION].double().numpy(), mask.numpy(),
                                      self.config.n_options)
        option = torch.full((len(memory.frames[ACTION]),), -1, dtype=torch.long)
        frame_rows = memory.start[rows, None] + torch.arange(mask.shape[1])
        option[frame_rows[mask]] = torch.from_numpy(labels)[mask]
        memory.frames[OPTION] = option
        logging.info(f"OCN is taught the switching affine split first (cost {report.cost:.6g}, frames per option "
                     f"{report.label_share})")

    def _taught_forward(self, mask: Tensor, state: Tensor, action: Tensor, tasks: list[str],
                        columns: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        """`labelled_forward` on the batch's episodes and their option labels (the taught recipe)."""
        if OPTION not in columns:
            raise ValueError("The taught recipe teaches each training frame's option label, which the policy reads "
                             "when it is built from its dataset; this batch has none.")
        option = columns[OPTION].masked_fill(~mask, -1)
        taught = {OBS_STATE: state, ACTION: action, "task": tasks}
        own_terminations = self.config.hierarchy == "ocn"
        weight = self.config.recipe_terms.taught_termination_weight if own_terminations else 1.0
        return self.labelled_forward(taught, option, weight)

    def labelled_forward(
        self, batch: dict[str, Any], option: Tensor, termination_weight: float = 1.0
    ) -> tuple[Tensor, dict[str, float]]:
        """The loss with the split given instead of induced (`OCNCore.teacher_forced`): each frame's NLL
        under its labelled option, the controller's cross-entropy at each labelled switch, and the
        running option's termination as a binary cross-entropy at every later frame (target 1 where the
        label changes), weighted by `termination_weight`. Each term is a mean over its frames, those of
        the global batch in a distributed run (`lerobot_policy_ocn.distributed.global_mean`). `batch`
        holds whole episodes from their first frame, as `parse` takes them; `option` [B, T] is each
        frame's option index, -1 on padding. The stats include the mean termination at the switches and
        at the other frames, which tell terminations that fire where they should from a mean that only
        matches the switches' rate.

        Under `hierarchy="moe"` the controller chooses at every frame (its cross-entropy is over all of
        them) and there is no termination term: the MoE baseline given the same split."""
        moe = self.config.hierarchy == "moe"
        if moe and termination_weight != 1.0:
            raise ValueError(f"termination_weight {termination_weight} weighs a term MoE's loss does not have.")
        mask = option >= 0
        used = int(mask.sum(1).max())
        mask, option = mask[:, :used].transpose(0, 1), option[:, :used].clamp_min(0).transpose(0, 1)
        decided = torch.ones_like(mask)
        if not moe:
            decided[1:] = option[1:] != option[:-1]
        state = batch[OBS_STATE][:, :used]
        action = batch[ACTION][:, :used].reshape(state.shape[0], used, self.config.action_dim)
        task_index = self.task_index(batch["task"], state.shape[0])
        projected = self.core.project(self.encoder(state.transpose(0, 1).contiguous()))
        out = self.core.teacher_forced(projected, self.core.initial_state(task_index), option, decided)
        nll = global_mean(-self.head.log_prob(out.params.unsqueeze(1), action.transpose(0, 1)).squeeze(1)[mask])
        switches = mask & decided
        choice = global_mean(torch.nn.functional.cross_entropy(out.controller_logits[switches], option[switches],
                                                               reduction="none"))
        stats = {"nll": nll.item(), "choice_ce": choice.item(), "frames_used": int(mask.sum())}
        if moe:
            return nll + choice, stats
        later = mask.clone()
        later[0] = False
        termination = global_mean(torch.nn.functional.binary_cross_entropy(
            out.end[later], decided[later].to(out.end.dtype), reduction="none"))
        with torch.no_grad():
            stats |= {"termination_bce": termination.item(), "mean_end": global_mean(out.end[later]).item(),
                      "mean_end_at_switch": global_mean(out.end[later & decided]).item(),
                      "mean_end_elsewhere": global_mean(out.end[later & ~decided]).item()}
        return nll + choice + termination_weight * termination, stats

    @torch.no_grad()
    def parse(self, batch: dict[str, Any]) -> dict[str, Tensor]:
        """Per-step hierarchy of whole episodes (each row starts at its episode's first frame).

        Returns batch-major p_c [B, T, N], option = argmax p^c [B, T], end = e_t [B, T] (1 at t = 1,
        where the controller always chooses), option_end = e_{i,t} [B, T, N], mask [B, T], and when the
        batch has actions action_log_prob [B, T] and component_log_prob [B, T, 2N], each mixture
        component's log p_k(a_t): the N continuing options, then the N restarted ones.
        """
        observation = self.observation(batch)
        out = self._unroll(observation, batch["task"])
        result = {
            "p_c": out.p_c.transpose(0, 1),
            "option": out.p_c.argmax(-1).transpose(0, 1),
            "end": out.end.transpose(0, 1),
            "option_end": out.option_end.transpose(0, 1),
            "mask": frame_mask(batch, observation),
        }
        if ACTION in batch:
            component = self._component_log_prob(out, batch[ACTION])
            result["action_log_prob"] = self._action_log_prob(out, component)
            result["component_log_prob"] = component.permute(2, 0, 1)
        return result

    def _episode_starts(self, batch: dict[str, Any], observation: Tensor) -> Tensor:
        """Rows [B] starting an episode this step (all of them right after `reset()`), creating the
        state of the configured execution then; a batch-size or execution change needs a reset."""
        size = observation.shape[0]
        hard = self.config.execution == "hard"
        start = self._state is None
        if start:
            task_index = self.task_index(batch.get("task"), size)
            self._state = self.core.initial_hard_state(task_index) if hard else self.core.initial_state(task_index)
        elif isinstance(self._state, HardState) != hard:
            raise ValueError("The execution mode changed without reset().")
        elif self._state.p_c.shape[0] != size:
            raise ValueError(f"Batch size changed from {self._state.p_c.shape[0]} to {size} without reset().")
        return torch.full((size,), start, dtype=torch.bool, device=observation.device)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """Advance every env's recurrence by one step and return its action as a chunk [B, 1, A]:
        the soft eq. 17 step, or under hard execution one sampled-hierarchy step (`OCNCore.hard_step`)."""
        observation = self.observation(batch)
        starts = self._episode_starts(batch, observation)
        projected = self.core.project(self.encoder(observation))
        greedy = self.config.inference_mode == "greedy"
        if self.config.execution == "hard":
            self._state, out = self.core.hard_step(self._state, projected, starts, greedy)
            self.last_step = StepReport(self._state.p_c, self._state.option, out.end, out.decided)
            weights = torch.ones(starts.shape[0], 1, dtype=out.params.dtype, device=starts.device)
            return self.head.choose(weights, out.params.unsqueeze(0), greedy).unsqueeze(1)
        self._state, out = self.core.step(self._state, projected, starts)
        self.last_step = StepReport(out.p_c, out.p_c.argmax(-1), out.end)
        return self.head.choose(out.weights, out.params, greedy).unsqueeze(1)

    @torch.no_grad()
    def act_with_options(
        self, state: Tensor, option: Tensor, option_h: Tensor | None, restart: Tensor, greedy: bool
    ) -> tuple[Tensor, Tensor, Tensor]:
        """One step of a chosen option per row, with no controller: for running frozen options alone.

        state [B, S] (preprocessed), option [B] (index), option_h [N, B, d_hid] from the previous call
        (None at the first), restart [B]: rows whose option starts now from h^o_0. All options step
        (they are one stacked cell); returns the chosen option's action [B, A], every option's new
        state [N, B, d_hid], and the chosen option's termination probability e [B] (not meaningful
        on a restart step, where an option never terminates).
        """
        size = state.shape[0]
        initial = self.core.option_init.unsqueeze(1).expand(-1, size, -1)
        h = initial if option_h is None else torch.where(restart[None, :, None], initial, option_h)
        out = self.core.options.step(self.core.options.project(self.encoder(state)), h)
        weights = torch.nn.functional.one_hot(option, self.config.n_options).to(out.logits.dtype)
        action = self.head.choose(weights, out.logits, greedy)
        return action, out.hidden, out.end.gather(0, option.unsqueeze(0)).squeeze(0)
