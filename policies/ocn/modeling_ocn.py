"""OCN as a LeRobot policy: batch plumbing, the NLL loss (eq. 18), stateful inference and parsing.

Batch plumbing shared with the other whole-episode policies (windows, masks, task table) is
`policies.sequence`'s.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE

from ocn_data.packed_view import PACKED_OPTION
from policies.sequence import SequencePolicy, frame_mask, training_windows, window_nll

from .configuration_ocn import OCNConfig
from .encoders import make_encoder
from .heads import expected_log_prob, make_action_head, mixture_log_prob, option_responsibilities
from .latent_options import LatentDecoderPool
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


def termination_penalty(config: OCNConfig, end: Tensor) -> Tensor:
    """What the termination cost charges for each e_t (`OCNConfig.termination_penalty`). The log form
    is clamped below e_t = 1, which only the forced first step reaches (and the cost leaves out)."""
    if config.termination_penalty == "linear":
        return end
    return -torch.log1p(-end.clamp_max(1.0 - 1e-6))


def explained_terminations(out: StepOutput, component: Tensor) -> Tensor:
    """sum_i p^c_{t-1,i} e_{i,t} p_i(a_t) [T, B] (`OCNConfig.explained_termination_cost`), from time-major
    outputs and `_component_log_prob`'s log p_k(a_t) [T, 2N, B], whose first N are the continuing options.
    Only e_{i,t} carries a gradient. Row t = 0 (no option runs before the start) is meaningless."""
    n_options = out.p_c.shape[-1]
    explained = component[:, :n_options].transpose(1, 2).exp().detach()
    previous = torch.cat([out.p_c[:1], out.p_c[:-1]]).detach()
    return (previous * out.option_end * explained).sum(-1)


def option_switches(p_c: Tensor) -> Tensor:
    """0.5 ||p^c_t - p^c_{t-1}||_1 [T, B] of time-major p^c [T, B, N] (`OCNConfig.switch_cost`): the
    probability mass that moves to another option at step t. Row t = 0 (the first choice) is 0."""
    change = 0.5 * (p_c[1:] - p_c[:-1]).abs().sum(-1)
    return torch.cat([torch.zeros_like(change[:1]), change])


def usage_imbalance(p_c: Tensor, mask: Tensor, options: int = 0, exact: bool = False) -> Tensor:
    """KL(u || uniform) of the options' share u = the mean of p^c [T, B, N] (or of another per-frame
    use of the options, `OCNConfig.usage_balance_source`) over real frames mask [B, T]:
    0 when every option takes as many frames as the others, log N when one takes them all. With
    `options` K < N, max(0, KL - ln(N / K)) = max(0, ln K - H(u)): 0 while u spreads over at least K
    options' worth of entropy (`OCNConfig.usage_balance_options`); `exact` charges |ln K - H(u)|, usage
    spread wider than K options' worth too (`OCNConfig.usage_balance_exact`)."""
    weights = mask.transpose(0, 1).unsqueeze(-1).to(p_c.dtype)
    share = (p_c * weights).sum((0, 1)) / weights.sum().clamp_min(1.0)
    n_options = p_c.shape[-1]
    kl = (share * torch.log(share.clamp_min(1e-12) * n_options)).sum()
    if 0 < options < n_options:
        excess = kl - math.log(n_options / options)
        return excess.abs() if exact else excess.clamp_min(0.0)
    return kl


def option_usage(config: OCNConfig, out: StepOutput, component: Tensor) -> Tensor:
    """Each option's use of each frame [T, B, N] as the usage balance counts it (`OCNConfig.usage_balance_source`),
    from time-major outputs and `_component_log_prob`'s log p_k(a_t)."""
    if config.usage_balance_source == "posterior":
        return option_responsibilities(out.weights, component)
    if config.usage_balance_source == "untempered":
        return torch.softmax(config.temperature * torch.log(out.p_c.clamp_min(torch.finfo(out.p_c.dtype).tiny)), -1)
    return out.p_c


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
            option_mlp=config.option_mlp,
            affine_options=config.affine_options,
            n_params=self.head.n_params,
            temperature=config.temperature,
            skill_length=config.fixed_skill_length,
            option_memory=config.option_memory,
            forced_restart_rate=config.forced_restart_rate,
            initial_state_std=config.initial_state_std,
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

    def get_optim_params(self) -> list[dict[str, Any]]:
        """Two parameter groups: the controller (with its per-task initial states) and the rest."""
        controller = [self.core.controller_init, *self.core.controller.parameters()]
        chosen = {id(p) for p in controller}
        rest = [p for p in self.parameters() if id(p) not in chosen]
        scaled = self.config.optimizer_lr * self.config.controller_lr_scale
        return [{"params": rest}, {"params": controller, "lr": scaled}]

    def reset(self) -> None:
        """Forget the recurrent state: the next `select_action` is t = 1 of new episodes."""
        self._state: OCNState | HardState | None = None
        self.last_step: StepReport | None = None

    def _unroll(self, state: Tensor, tasks: Sequence[str], real: Tensor | None = None) -> StepOutput:
        """Recurrence over windows [B, T, S] that each start an episode; outputs are time-major.
        `real` [B, T]: the frames whose outputs are read, each row's first ones (None: all); then only
        those are computed (`OCNCore.unroll_frames`) and the others' outputs are zeros."""
        batch, steps = state.shape[:2]
        task_index = self.task_index(tasks, batch)
        start = torch.zeros(steps, batch, dtype=torch.bool, device=state.device)
        start[0] = True
        if real is None:
            # Transpose the stored state rather than the (wider) features: the encoder then writes time-major.
            x = self.encoder(state.transpose(0, 1).contiguous())
            return self.core.unroll(x, self.core.initial_state(task_index), start)[1]
        order, inverse = longest_first(real)
        x = self.encoder(state[order].transpose(0, 1).contiguous())
        out = self.core.unroll_frames(x, self.core.initial_state(task_index[order]), start, real[order].transpose(0, 1))
        return StepOutput(out.weights[:, inverse], out.params[:, :, inverse], out.p_c[:, inverse], out.end[:, inverse],
                          out.option_end[:, inverse])

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
        """NLL of the mixed action distribution: mean over each window's real frames, then over windows;
        with `taught_options`, `labelled_forward`'s loss on the labels of the batch's packed view."""
        mask, state, action = training_windows(self.config, batch)
        if self.config.taught_options:
            return self._taught_forward(batch, mask, state, action)
        out = self._unroll(state, batch["task"], mask)
        penalties = {}
        if self.config.termination_cost:
            penalties["termination_penalty"] = (self.config.termination_cost, termination_penalty(self.config, out.end))
        component = self._component_log_prob(out, action)
        if self.config.explained_termination_cost:
            penalties["explained_terminations"] = (self.config.explained_termination_cost,
                                                   explained_terminations(out, component))
        if self.config.switch_cost:
            penalties["option_switches"] = (self.config.switch_cost, option_switches(out.p_c))
        loss, stats = window_nll(self._action_log_prob(out, component), mask, reduction, {"mean_end": out.end},
                                 penalties, packed=self.config.packed)
        usage = option_usage(self.config, out, component)
        imbalance = usage_imbalance(usage, mask, self.config.usage_balance_options, self.config.usage_balance_exact)
        stats["usage_imbalance"] = imbalance.item()
        if self.config.usage_balance:
            loss = loss + self.config.usage_balance * imbalance
        if self.config.expected_nll_weight:
            expected_lp = expected_log_prob(out.weights, component).transpose(0, 1)
            expected, expected_stats = window_nll(expected_lp, mask, reduction, {}, packed=self.config.packed)
            stats["expected_nll"] = expected_stats["nll"]
            loss = loss + self.config.expected_nll_weight * expected
        return loss, stats

    def _taught_forward(self, batch: dict[str, Any], mask: Tensor, state: Tensor,
                        action: Tensor) -> tuple[Tensor, dict[str, float]]:
        """`labelled_forward` on the training windows of a labelled packed view's rows."""
        if PACKED_OPTION not in batch:
            raise ValueError(f"taught_options needs each frame's option label, the `{PACKED_OPTION}` column of a "
                             "labelled packed view (python -m ocn_data.packed_view --option-labels FILE); this "
                             "batch has none.")
        option = batch[PACKED_OPTION].reshape(mask.shape[0], -1)[:, : mask.shape[1]].long()
        if (option[mask] < 0).any():
            raise ValueError("taught_options: an episode of the batch has frames without an option label; the "
                             "label file must cover every training episode (train on the split it labelled).")
        if int(option.max()) >= self.config.n_options:
            raise ValueError(f"taught_options: a frame is labelled option {int(option.max())}, but the policy has "
                             f"n_options = {self.config.n_options}.")
        taught = {OBS_STATE: state, ACTION: action, "task": batch["task"]}
        return self.labelled_forward(taught, option.masked_fill(~mask, -1), self.config.taught_termination_weight)

    def labelled_forward(
        self, batch: dict[str, Any], option: Tensor, termination_weight: float = 1.0
    ) -> tuple[Tensor, dict[str, float]]:
        """The loss with the split given instead of induced (`OCNCore.teacher_forced`): each frame's NLL
        under its labelled option, the controller's cross-entropy at each labelled switch, and the
        running option's termination as a binary cross-entropy at every later frame (target 1 where the
        label changes), weighted by `termination_weight`. Each term is a mean over its frames. `batch`
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
        nll = -self.head.log_prob(out.params.unsqueeze(1), action.transpose(0, 1)).squeeze(1)[mask].mean()
        choice = torch.nn.functional.cross_entropy(out.controller_logits[mask & decided], option[mask & decided])
        stats = {"nll": nll.item(), "choice_ce": choice.item(), "frames_used": int(mask.sum())}
        if moe:
            return nll + choice, stats
        later = mask.clone()
        later[0] = False
        termination = torch.nn.functional.binary_cross_entropy(out.end[later], decided[later].to(out.end.dtype))
        stats |= {"termination_bce": termination.item(), "mean_end": out.end[later].mean().item(),
                  "mean_end_at_switch": out.end[later & decided].mean().item(),
                  "mean_end_elsewhere": out.end[later & ~decided].mean().item()}
        return nll + choice + termination_weight * termination, stats

    @torch.no_grad()
    def parse(self, batch: dict[str, Any]) -> dict[str, Tensor]:
        """Per-step hierarchy of whole episodes (each row starts at its episode's first frame).

        Returns batch-major p_c [B, T, N], option = argmax p^c [B, T], end = e_t [B, T] (1 at t = 1,
        where the controller always chooses), option_end = e_{i,t} [B, T, N], mask [B, T], and when the
        batch has actions action_log_prob [B, T] and component_log_prob [B, T, 2N], each mixture
        component's log p_k(a_t): the N continuing options, then the N restarted ones.
        """
        out = self._unroll(batch[OBS_STATE], batch["task"])
        result = {
            "p_c": out.p_c.transpose(0, 1),
            "option": out.p_c.argmax(-1).transpose(0, 1),
            "end": out.end.transpose(0, 1),
            "option_end": out.option_end.transpose(0, 1),
            "mask": frame_mask(batch),
        }
        if ACTION in batch:
            component = self._component_log_prob(out, batch[ACTION])
            result["action_log_prob"] = self._action_log_prob(out, component)
            result["component_log_prob"] = component.permute(2, 0, 1)
        return result

    def _episode_starts(self, batch: dict[str, Any]) -> Tensor:
        """Rows [B] starting an episode this step (all of them right after `reset()`), creating the
        state of the configured execution then; a batch-size or execution change needs a reset."""
        size = batch[OBS_STATE].shape[0]
        hard = self.config.execution == "hard"
        start = self._state is None
        if start:
            task_index = self.task_index(batch.get("task"), size)
            self._state = self.core.initial_hard_state(task_index) if hard else self.core.initial_state(task_index)
        elif isinstance(self._state, HardState) != hard:
            raise ValueError("The execution mode changed without reset().")
        elif self._state.p_c.shape[0] != size:
            raise ValueError(f"Batch size changed from {self._state.p_c.shape[0]} to {size} without reset().")
        return torch.full((size,), start, dtype=torch.bool, device=batch[OBS_STATE].device)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """Advance every env's recurrence by one step and return its action as a chunk [B, 1, A]:
        the soft eq. 17 step, or under hard execution one sampled-hierarchy step (`OCNCore.hard_step`)."""
        starts = self._episode_starts(batch)
        projected = self.core.project(self.encoder(batch[OBS_STATE]))
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
