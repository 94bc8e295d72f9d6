"""The bi-level option-controller recurrence (paper eq. 8-17) as a soft, fully differentiable step.

Every step computes both branches of eq. 17: "not done" (options continue from their own states,
the controller keeps its state and p^c_{t-1}) and "done" (the controller steps, the options restart
from their learned initial states), and mixes them with e_t = sum_i p^c_{t-1,i} e_{i,t} (eq. 12).
Step t = 1 (eq. 8-10) is the "done" branch alone, which is what a step with e_t forced to 1 gives,
so episode starts are a per-row `start` flag rather than a separate code path. The baselines with
options of a fixed length L (`skill_length`: 1 for MoE, L for HIL) are the same recurrence with e_t
set by a schedule instead: 1 at steps t = 1, 1 + L, 1 + 2L, ... of each row's episode, counted by a
per-row step counter in the recurrent state, and 0 at every other step.

`hard_step` is the sampled counterpart used by the RL phase (appendix A.1) and by hard execution:
one option runs at a time, and the controller only steps where that option's sampled termination
fires (and at t = 1).
"""

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn

from .cell import CellOutput, StackedCell
from .heads import sample_index


@dataclass
class OCNState:
    """Recurrent state after a step: h^c [B, d_hid], p^c [B, N], option states h^o [N, B, d_hid],
    and `steps` [B] (long), the steps taken since the row's episode started, for fixed skill lengths."""

    controller_h: Tensor
    p_c: Tensor
    option_h: Tensor
    steps: Tensor


class StepOutput(NamedTuple):
    """What a step emits. The action distribution is a mixture over 2N option components: first
    the N continuing options (weights (1 - e_t) p^c_{t-1}), then the N restarted options (weights
    e_t p'^c_t). `weights` [B, 2N], `params` [2N, B, n_params] (option output heads), `p_c` [B, N]
    (mixed p^c_t), `end` [B] (e_t, 1 at starts), `option_end` [B, N] (e_{i,t} of continuing options)."""

    weights: Tensor
    params: Tensor
    p_c: Tensor
    end: Tensor
    option_end: Tensor


@dataclass
class HardState:
    """Sampled hierarchy after a step: h^c [B, d_hid] (it advances only at decisions), p^c [B, N] of
    the latest decision, the running option [B] (long), the option states h^o [N, B, d_hid] and the
    steps [B] (long) taken since the row's episode started (`OCNState.steps`)."""

    controller_h: Tensor
    p_c: Tensor
    option: Tensor
    option_h: Tensor
    steps: Tensor


class HardStepOutput(NamedTuple):
    """What a hard step emits: `params` [B, n_params] (the running option's output head), `decided`
    [B] (the controller chose an option this step: t = 1 or a fired termination), `end` [B] (e_{i,t}
    of the option that was running before this step; 1 at starts)."""

    params: Tensor
    decided: Tensor
    end: Tensor


class TeacherForced(NamedTuple):
    """Time-major outputs of `OCNCore.teacher_forced`: the controller's tempered logits [T, B, N] (its
    choice where a decision falls), the given option's output head [T, B, n_params], and `end` [T, B],
    e_{i,t} of the option given at t - 1 (meaningless at t = 0, where no option ran before)."""

    controller_logits: Tensor
    params: Tensor
    end: Tensor


def scatter_frames(rows: Tensor, real: Tensor) -> Tensor:
    """Per-module rows [N, R, d] of the R frames where `real` [T, B] holds, as [T, N, B, d] with zeros elsewhere."""
    out = rows.new_zeros(*real.shape, rows.shape[0], rows.shape[-1])
    out[real] = rows.transpose(0, 1)
    return out.transpose(1, 2)


def state_rows(state: OCNState, rows: Tensor | slice) -> OCNState:
    """The recurrent state of the batch rows `rows` (an index or a slice)."""
    return OCNState(state.controller_h[rows], state.p_c[rows], state.option_h[:, rows], state.steps[rows])


def padded_rows(out: StepOutput, batch: int) -> StepOutput:
    """A step's outputs for the first rows of a batch as outputs for all `batch` rows, zeros for the rest."""

    def pad(field: Tensor, dim: int) -> Tensor:
        missing = batch - field.shape[dim]
        if not missing:
            return field
        shape = list(field.shape)
        shape[dim] = missing
        return torch.cat([field, field.new_zeros(shape)], dim)

    return StepOutput(pad(out.weights, 0), pad(out.params, 1), pad(out.p_c, 0), pad(out.end, 0), pad(out.option_end, 0))


class Projected(NamedTuple):
    """First-layer observation terms: controller [..., 1, B, d_mlp], options [..., N, B, d_mlp]."""

    controller: Tensor
    options: Tensor


def spread_frames(rows: Projected, real: Tensor) -> Projected:
    """First-layer terms of the frames where `real` [T, B] holds ([., R, d_mlp] each) as [T, ., B, d_mlp],
    zeros elsewhere."""
    return Projected(*(scatter_frames(part, real) for part in rows))


def _mix(end: Tensor, done: Tensor, not_done: Tensor) -> Tensor:
    """Eq. 17: e_t * done + (1 - e_t) * not_done, `end` already shaped to broadcast against them."""
    return torch.lerp(not_done, done, end)


def _initial_states(rows: int, size: int) -> nn.Parameter:
    """Learned initial states [rows, size], starting at zero."""
    return nn.Parameter(torch.zeros(rows, size))


class OCNCore(nn.Module):
    """Shared controller (N = 1 cell over options), N option cells, and the learned initial states.

    `skill_length` L fixes how long every option runs (see `schedule`): 1 for the MoE baseline, where
    every step is then a start, L for HIL; None (OCN) leaves termination to the options. `options`
    replaces the option cells by another pool with their interface (`n_modules`, `project`, `step`),
    such as the frozen compILE decoders of `latent_options`. The learned initial states (per task for
    the controller, per option) start at 0.
    """

    def __init__(
        self,
        obs_dim: int,
        n_tasks: int,
        n_options: int,
        hidden_size: int,
        mlp_hidden_size: int,
        mlp_depth: int,
        n_params: int,
        temperature: float,
        skill_length: int | None = None,
        options: nn.Module | None = None,
    ) -> None:
        super().__init__()
        if skill_length is not None and skill_length < 1:
            raise ValueError(f"skill_length must be >= 1 or None, got {skill_length}.")
        if options is not None and options.n_modules != n_options:
            raise ValueError(f"The option pool holds {options.n_modules} options, not n_options = {n_options}.")
        self.n_options = n_options
        self.temperature = temperature
        self.skill_length = skill_length
        self.controller = StackedCell(
            1, obs_dim, hidden_size, mlp_hidden_size, mlp_depth, n_out=n_options, with_end=False
        )
        self.options = options if options is not None else StackedCell(
            n_options, obs_dim, hidden_size, mlp_hidden_size, mlp_depth, n_out=n_params
        )
        self.controller_init = _initial_states(n_tasks, hidden_size)
        self.option_init = _initial_states(n_options, hidden_size)

    def initial_state(self, task_index: Tensor) -> OCNState:
        """State before t = 1: h^c_{tau,0} per row's task, no steps taken; p^c and h^o are unused
        there (e_1 = 1)."""
        batch = task_index.shape[0]
        uniform = torch.full((batch, self.n_options), 1.0 / self.n_options, device=task_index.device)
        option_h = self.option_init.unsqueeze(1).expand(-1, batch, -1)
        steps = torch.zeros(batch, dtype=torch.long, device=task_index.device)
        return OCNState(self.controller_init[task_index], uniform, option_h, steps)

    def initial_hard_state(self, task_index: Tensor) -> HardState:
        """Hard state before t = 1: h^c_{tau,0} per row's task; the option fields are unused (e_1 = 1)."""
        soft = self.initial_state(task_index)
        option = torch.zeros(task_index.shape[0], dtype=torch.long, device=task_index.device)
        return HardState(soft.controller_h, soft.p_c, option, soft.option_h, soft.steps)

    def schedule(self, start: Tensor, steps: Tensor) -> tuple[Tensor, Tensor]:
        """Rows [B] whose e_t is 1 this step whatever the options say, and each row's step count after it.

        `start` [B] marks episode starts (t = 1), which reset the count `steps` [B] of steps taken; a
        row's own count makes rows that start at different times keep their own schedules. Under a
        fixed skill length L, steps t = 1 + kL are forced too.
        """
        steps = torch.where(start, 0, steps)
        forced = start if self.skill_length is None else start | (steps % self.skill_length == 0)
        return forced, steps + 1

    def termination(self, forced: Tensor, learned: Tensor) -> Tensor:
        """e_t [B]: 1 where `forced`; elsewhere the options' `learned` e_t [B], or 0 under a fixed skill
        length (the option runs on, so its termination head is unused)."""
        return torch.where(forced, 1.0, learned if self.skill_length is None else torch.zeros_like(learned))

    def decide(self, x_controller: Tensor, controller_h: Tensor) -> tuple[Tensor, Tensor]:
        """One controller step from projected observations [1, B, d_mlp] and h^c [B, d_hid]:
        tempered logits (log p^c up to a constant) [B, N] and the new h^c [B, d_hid]."""
        out = self.controller.step(x_controller, controller_h.unsqueeze(0))
        return out.logits[0] / self.temperature, out.hidden[0]

    def hard_step(
        self, state: HardState, x: Projected, start: Tensor, greedy: bool
    ) -> tuple[HardState, HardStepOutput]:
        """One step of the sampled hierarchy; `start` [B] marks t = 1 (the controller always chooses,
        as it does wherever `schedule` forces e_t = 1).

        Sampling draws e ~ Bernoulli(e_{i,t}) and i ~ p^c; `greedy` fires at e_{i,t} > 0.5 and takes
        argmax p^c instead. Every row's branches are computed and selected with `torch.where`, so a
        step costs the same whichever rows decide.
        """
        rows = torch.arange(start.shape[0], device=start.device)
        forced, steps = self.schedule(start, state.steps)
        restarted = self.restarts(x.options)
        # One-step options (MoE, and the flat and compILE pools built on it) never continue: every
        # row decides at every step, so the continuing branch would be computed only to be discarded.
        continued = self._continued(x.options, state.option_h, restarted, self.skill_length == 1)
        end = self.termination(forced, continued.end[state.option, rows])
        fired = end > 0.5 if greedy else torch.bernoulli(end).bool()
        decided = forced | fired
        logits, controller_h = self.decide(x.controller, state.controller_h)
        p_c = torch.softmax(logits, dim=-1)
        choice = p_c.argmax(-1) if greedy else sample_index(p_c)
        option = torch.where(decided, choice, state.option)
        gate = decided[None, :, None]
        option_params = torch.where(gate, restarted.logits, continued.logits)
        next_state = HardState(
            controller_h=torch.where(decided[:, None], controller_h, state.controller_h),
            p_c=torch.where(decided[:, None], p_c, state.p_c),
            option=option,
            option_h=torch.where(gate, restarted.hidden, continued.hidden),
            steps=steps,
        )
        return next_state, HardStepOutput(option_params[option, rows], decided, end)

    def _continued(
        self, x_options: Tensor, option_h: Tensor, restarted: CellOutput, never: bool = False
    ) -> CellOutput:
        """The options' "not done" step from their own states h^o, or the restarted step itself where
        options `never` continue."""
        return restarted if never else self.options.step(x_options, option_h)

    def project(self, x: Tensor) -> Projected:
        """Observation parts for x [..., B, obs_dim], computed once per window outside the time loop."""
        return Projected(self.controller.project(x), self.options.project(x))

    def restarts(self, x_options: Tensor) -> CellOutput:
        """The options' "done" branch, a step from their learned initial states h^o_0, for projected
        observations x_options [N, M, d_mlp] of any M frames. It reads no recurrent state, so the
        unrolls compute it for every frame of a window in one call before the time loop, and each step
        only does the work that depends on the step before."""
        return self.options.step(x_options, self.option_init.unsqueeze(1))

    def restarts_ahead(self, x_options: Tensor, rows: list[int]) -> list[CellOutput]:
        """`restarts` of consecutive steps' frames x_options [N, sum(rows), d_mlp] in one call, split into
        one output per step of rows[t] frames."""
        fields = (field.split(rows, dim=1) for field in self.restarts(x_options))
        return [CellOutput(*step) for step in zip(*fields, strict=True)]

    def step(
        self, state: OCNState, x: Projected, start: Tensor, restarted: CellOutput | None = None
    ) -> tuple[OCNState, StepOutput]:
        """One step from projected observations x ([1, B, .], [N, B, .]); `start` [B] marks t = 1, where
        e_t = 1 (as wherever `schedule` forces it). `restarted`: this step's `restarts`, where the caller
        computed them ahead (None: computed here)."""
        forced, steps = self.schedule(start, state.steps)
        restarted = self.restarts(x.options) if restarted is None else restarted
        continued = self._continued(x.options, state.option_h, restarted)
        ctrl = self.controller.step(x.controller, state.controller_h.unsqueeze(0))
        new_p_c = torch.softmax(ctrl.logits[0] / self.temperature, dim=-1)
        option_end = continued.end.transpose(0, 1)
        end = self.termination(forced, (state.p_c * option_end).sum(-1))
        gate = end.unsqueeze(-1)
        next_state = OCNState(
            controller_h=_mix(gate, ctrl.hidden[0], state.controller_h),
            p_c=_mix(gate, new_p_c, state.p_c),
            option_h=_mix(gate.unsqueeze(0), restarted.hidden, continued.hidden),
            steps=steps,
        )
        weights = torch.cat([(1.0 - gate) * state.p_c, gate * new_p_c], dim=-1)
        params = torch.cat([continued.logits, restarted.logits], dim=0)
        return next_state, StepOutput(weights, params, next_state.p_c, end, option_end)

    def teacher_forced(self, projected: Projected, state: OCNState, option: Tensor, decided: Tensor) -> TeacherForced:
        """Run the hierarchy with its choices given: `option` [T, B] runs at each step and `decided`
        [T, B] marks the steps where it was chosen (True at t = 0). There the controller steps and the
        option restarts from h^o_0; elsewhere the controller keeps its state and the option continues.
        This is eq. 17 with e_t and p^c set to one-hot ground truth, for training on labelled segments
        (`labelled_forward`: the Dial recipe teaches a split found without labels this way).
        MoE's one-step options take a choice at every step (`decided` all True); other fixed-length
        options (HIL) have no terminations to teach and are refused."""
        one_step = self.skill_length == 1
        if self.skill_length is not None and not (one_step and bool(decided.all())):
            raise ValueError("Teacher forcing gives the options' terminations; options of a fixed length have none "
                             "(MoE's one-step options only take a choice given at every step).")
        rows = torch.arange(option.shape[1], device=option.device)
        controller_h, option_h, previous = state.controller_h, state.option_h, option[0]
        steps = zip(projected.controller.unbind(0), projected.options.unbind(0), option.unbind(0), decided.unbind(0),
                    strict=True)
        outputs = []
        for x_controller, x_options, current, decide in steps:
            logits, stepped_h = self.decide(x_controller, controller_h)
            controller_h = torch.where(decide[:, None], stepped_h, controller_h)
            restarted = self.restarts(x_options)
            continued = self._continued(x_options, option_h, restarted, one_step)
            gate = decide[None, :, None]
            params = torch.where(gate, restarted.logits, continued.logits)[current, rows]
            option_h = torch.where(gate, restarted.hidden, continued.hidden)
            outputs.append((logits, params, continued.end[previous, rows]))
            previous = current
        return TeacherForced(*(torch.stack(field) for field in zip(*outputs, strict=True)))

    def project_frames(self, x: Tensor, real: Tensor) -> Projected:
        """`project` of the real frames only (`real` [T, B]) of time-major x [T, B, obs_dim], zeros
        elsewhere: training windows are mostly padding after their episode's end, whose outputs no
        loss reads, and this matmul over every frame is the largest single cost of a training step."""
        return spread_frames(self.project(x[real]), real)

    def unroll(self, x: Tensor, state: OCNState, start: Tensor) -> tuple[OCNState, StepOutput]:
        """Run over time-major x [T, B, obs_dim] with `start` [T, B]; outputs are stacked over T."""
        return self.unroll_projected(self.project(x), state, start)

    def unroll_projected(self, projected: Projected, state: OCNState, start: Tensor) -> tuple[OCNState, StepOutput]:
        """`unroll` from the first layer's observation terms [T, ., B, d_mlp], every row at every step."""
        # unbind, not indexing: indexing's backward would zero-fill the whole window at every step.
        n_steps, n_options, batch, width = projected.options.shape
        frames = projected.options.transpose(0, 1).reshape(n_options, n_steps * batch, width)
        restarted = self.restarts_ahead(frames, [batch] * n_steps)
        steps = zip(projected.controller.unbind(0), projected.options.unbind(0), start.unbind(0), restarted,
                    strict=True)
        outputs = []
        for controller_x, options_x, step_start, step_restarted in steps:
            state, out = self.step(state, Projected(controller_x, options_x), step_start, step_restarted)
            outputs.append(out)
        return state, StepOutput(*(torch.stack(field) for field in zip(*outputs, strict=True)))

    def unroll_frames(self, x: Tensor, state: OCNState, start: Tensor, real: Tensor) -> StepOutput:
        """`unroll`'s outputs at the real frames `real` [T, B] of time-major x, zeros at the others, computing
        the real frames only: training windows are mostly padding after their episode's end.

        Each row's real frames must come first and the rows longest first (`longest_first` orders a batch
        so). The first layer then projects the real frames alone (`project_frames`) and each step runs only
        the rows still in their episode, a prefix of the batch that shrinks as episodes end.
        """
        lengths = real.sum(0)
        steps = torch.arange(real.shape[0], device=real.device)
        if (lengths[1:] > lengths[:-1]).any() or not torch.equal(real, steps[:, None] < lengths):
            raise ValueError("unroll_frames needs each row's real frames first and the rows longest first.")
        real_x = self.project(x[real])
        projected = spread_frames(real_x, real)
        running = real.sum(1).tolist()
        # The real frames, time-major, are each step's running rows in turn.
        restarted = self.restarts_ahead(real_x.options, running)
        frames = zip(projected.controller.unbind(0), projected.options.unbind(0), start.unbind(0), running, restarted,
                     strict=True)
        outputs = []
        for controller_x, options_x, step_start, rows, step_restarted in frames:
            state = state_rows(state, slice(0, rows))
            x_rows = Projected(controller_x[:, :rows], options_x[:, :rows])
            state, out = self.step(state, x_rows, step_start[:rows], step_restarted)
            outputs.append(padded_rows(out, real.shape[1]))
        return StepOutput(*(torch.stack(field) for field in zip(*outputs, strict=True)))


def longest_first(real: Tensor) -> tuple[Tensor, Tensor]:
    """The order of the rows of `real` [B, T] (batch-major) by their number of real frames, longest first,
    and its inverse, which puts outputs computed in that order back in the batch's order."""
    order = torch.argsort(real.sum(1), descending=True, stable=True)
    return order, torch.argsort(order)
