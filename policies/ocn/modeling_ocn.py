"""OCN as a LeRobot policy: batch plumbing, the NLL loss (eq. 18), stateful inference and parsing.

Batches arrive as LeRobot builds them: `observation.state` [B, T, S] and `action` [B, T, A]
windows with `*_is_pad` masks [B, T] and the task strings in `batch["task"]`. How a window becomes
a training sequence is `OCNConfig.window_start`'s business (see its docstring).
"""

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from lerobot.datasets.io_utils import load_episodes
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE

from .configuration_ocn import OCNConfig
from .encoders import make_encoder
from .heads import make_action_head, mixture_log_prob
from .recurrence import HardState, OCNCore, OCNState, StepOutput

PAD_KEYS = (f"{ACTION}_is_pad", f"{OBS_STATE}_is_pad")


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


def tasks_from_meta(dataset_meta: Any) -> list[str]:
    """Task strings of a LeRobot dataset, in task-index order."""
    if dataset_meta.tasks is None:
        return []
    return [str(task) for task in dataset_meta.tasks.sort_values("task_index").index]


def frame_mask(batch: dict[str, Any]) -> Tensor:
    """Frames [B, T] that are real data: neither the action nor the state is padding."""
    valid = torch.ones(batch[OBS_STATE].shape[:2], dtype=torch.bool, device=batch[OBS_STATE].device)
    for key in PAD_KEYS:
        if key in batch:
            valid &= ~batch[key].bool()
    return valid


def align_to_first_frame(valid: Tensor, length: int, *windows: Tensor) -> tuple[Tensor, ...]:
    """Shift each row of windows [B, W', ...] so that it starts at its first real frame.

    Returns the mask [B, length] of the shifted rows, then each window cut to [B, length, ...].
    Positions past the window's end read its last frame and are masked out.
    """
    width = valid.shape[1]
    first = valid.int().argmax(dim=1)
    position = first.unsqueeze(1) + torch.arange(length, device=valid.device)
    inside = position < width
    index = position.clamp_max(width - 1)
    mask = valid.gather(1, index) & inside
    shifted = []
    for window in windows:
        gather_index = index.view(*index.shape, *([1] * (window.dim() - 2))).expand(-1, -1, *window.shape[2:])
        shifted.append(window.gather(1, gather_index))
    return (mask, *shifted)


def trim_trailing_padding(mask: Tensor, *windows: Tensor) -> tuple[Tensor, ...]:
    """Cut mask [B, W] and windows [B, W, ...] after the last step that any row uses.

    The recurrence costs the same per step whether a step is padding or not, and windows hold
    whole episodes padded to the longest one the dataset may have: most batches end long before.
    """
    used = int(mask.any(0).nonzero().max().item()) + 1 if mask.any() else 1
    return tuple(window[:, :used] for window in (mask, *windows))


def episode_lengths(dataset_meta: Any) -> list[int]:
    """Frames per episode of a LeRobot dataset (its episode table is read from disk if not loaded yet)."""
    if dataset_meta.total_episodes == 0:
        return []
    episodes = dataset_meta.episodes if dataset_meta.episodes is not None else load_episodes(dataset_meta.root)
    return [int(length) for length in episodes["length"]]


class OCNPolicy(PreTrainedPolicy):
    """Option-Controller Network: a shared controller over N options, one initial state per task."""

    config_class = OCNConfig
    name = "ocn"

    def __init__(
        self,
        config: OCNConfig,
        dataset_stats: dict[str, dict[str, Tensor]] | None = None,
        dataset_meta: Any | None = None,
        **kwargs: Any,
    ) -> None:
        """`dataset_stats` is accepted for LeRobot's factory but unused: normalisation lives in the
        processors. `dataset_meta` fills `config.tasks` when it is empty, so the saved config keeps them."""
        super().__init__(config)
        config.validate_features()
        if not config.tasks and dataset_meta is not None:
            config.tasks = tasks_from_meta(dataset_meta)
        if not config.tasks:
            raise ValueError("OCN needs its task list: set `tasks` or build the policy from a dataset.")
        if dataset_meta is not None and config.window_start == "episode" and not config.skip_long_episodes:
            longest = max(episode_lengths(dataset_meta), default=0)
            if longest > config.window_size:
                raise ValueError(
                    f"The dataset has episodes of up to {longest} frames but window_size is "
                    f"{config.window_size}: with window_start='episode' a window must hold a whole "
                    f"episode. Set --policy.window_size={longest} or more, --policy.skip_long_episodes=true "
                    "or --policy.window_start=any."
                )
        self._task_ids = {task: i for i, task in enumerate(config.tasks)}
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
        )
        self.reset()

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

    def task_index(self, tasks: Sequence[str] | str | None, batch_size: int) -> Tensor:
        """Map task strings to rows of the per-task initial controller states."""
        if tasks is None:
            raise ValueError(f"The batch has no 'task'; OCN needs one of {self.config.tasks}.")
        if isinstance(tasks, str):
            tasks = [tasks] * batch_size
        for task in tasks:
            if task not in self._task_ids:
                raise ValueError(f"Unknown task {task!r}; this OCN knows the tasks {self.config.tasks}.")
        device = self.core.controller_init.device
        return torch.tensor([self._task_ids[task] for task in tasks], dtype=torch.long, device=device)

    def _unroll(self, state: Tensor, tasks: Sequence[str]) -> StepOutput:
        """Recurrence over windows [B, T, S] that each start an episode; outputs are time-major."""
        batch, steps = state.shape[:2]
        # Transpose the stored state rather than the (wider) features: the encoder then writes time-major.
        x = self.encoder(state.transpose(0, 1).contiguous())
        start = torch.zeros(steps, batch, dtype=torch.bool, device=state.device)
        start[0] = True
        initial = self.core.initial_state(self.task_index(tasks, batch))
        return self.core.unroll(x, initial, start)[1]

    def _training_windows(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
        """(mask [B, W], state [B, W, S], action [B, W, ...]) of sequences that each start at t = 1."""
        valid = frame_mask(batch)
        if self.config.window_start == "any":
            windows = (valid, batch[OBS_STATE], batch[ACTION])
        else:
            if self.config.skip_long_episodes:
                # A real first position may mean the episode began before the window: leave it out.
                valid = valid & ~valid[:, :1]
            windows = align_to_first_frame(valid, self.config.window_size, batch[OBS_STATE], batch[ACTION])
        return trim_trailing_padding(*windows)

    def _action_log_prob(self, out: StepOutput, action: Tensor) -> Tensor:
        """log p^a_t(a_t) [B, T] for time-major outputs and batch-major actions [B, T, A].

        LeRobot hands one-wide action features over as [B, T] (no feature axis), hence the reshape.
        """
        action = action.reshape(*action.shape[:2], self.config.action_dim)
        component = self.head.log_prob(out.params, action.transpose(0, 1))
        return mixture_log_prob(out.weights, component).transpose(0, 1)

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """NLL of the mixed action distribution: mean over each window's real frames, then over the
        windows that have any (skipped long-episode windows have none)."""
        mask, state, action = self._training_windows(batch)
        out = self._unroll(state, batch["task"])
        mask = mask.float()
        frames = mask.sum(1)
        nll = -self._action_log_prob(out, action) * mask
        per_window = nll.sum(1) / frames.clamp_min(1.0)
        later = mask[:, 1:]
        end = out.end[1:].detach().transpose(0, 1)
        stats = {
            "nll": per_window.mean().item(),
            "frames_used": int(frames.sum().item()),
            "mean_end": float((end * later).sum() / later.sum().clamp_min(1.0)),
        }
        if reduction == "none":
            return per_window, stats
        return per_window.sum() / (frames > 0).sum().clamp_min(1), stats

    @torch.no_grad()
    def parse(self, batch: dict[str, Any]) -> dict[str, Tensor]:
        """Per-step hierarchy of whole episodes (each row starts at its episode's first frame).

        Returns batch-major p_c [B, T, N], option = argmax p^c [B, T], end = e_t [B, T] (1 at t = 1,
        where the controller always chooses), option_end = e_{i,t} [B, T, N], mask [B, T], and
        action_log_prob [B, T] when the batch has actions.
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
            result["action_log_prob"] = self._action_log_prob(out, batch[ACTION])
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

    @torch.no_grad()
    def select_action(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """One action [B, A] per env; the recurrent state persists until `reset()`."""
        return self.predict_action_chunk(batch)[:, 0]
