"""OMPN as a LeRobot policy: the masked NLL over whole-episode windows, stateful inference, and the
boundary read-out of its expansion distribution.

Batch plumbing (windows, masks, task table) is `lerobot_policy_ocn.sequence`'s, shared with OCN; the
observation encoder and the action head are OCN's (`lerobot_policy_ocn.ocn.encoders`, `lerobot_policy_ocn.ocn.heads`),
the head with a single component.
"""

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.nn.utils.rnn import PackedSequence, pack_padded_sequence

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION
from lerobot_policy_ocn.ocn.encoders import make_encoder
from lerobot_policy_ocn.ocn.heads import make_action_head
from lerobot_policy_ocn.sequence import SequencePolicy, frame_mask, window_nll

from .configuration_ompn import OMPNConfig
from .memory import MemoryOutput, OrderedMemory


def expected_depth(expansion: Tensor) -> Tensor:
    """Expected expansion position sum_i i p_i [...] of distributions [..., n] (0: the bottom slot
    alone is updated, n-1: the whole memory)."""
    levels = torch.arange(expansion.shape[-1], dtype=expansion.dtype, device=expansion.device)
    return (expansion * levels).sum(-1)


def expansion_boundaries(depth: np.ndarray, count: int) -> np.ndarray:
    """OMPN's boundary read-out of one episode with `count` true boundaries, in the convention every
    model is scored in (a boundary is the last step of a segment, and the episode's last step ends
    its last segment, as `boundaries_from_labels` gives OCN's option switches).

    OMPN's top-k of the expected expansion height (the negative expected position, slots numbered
    from the top) marks where a new subtask starts: the step whose observation shows the previous
    one done. So the count - 1 inner boundaries are the steps just before the count - 1 highest
    expansions (ties go to the earlier step; step 0, a full expansion by construction, never
    counts), and the final one is the episode's last step, which OMPN's own data marks with an
    extra DONE action that these datasets do not have.
    """
    depth = np.array(depth, dtype=np.float64)
    if not 1 <= count <= depth.size:
        raise ValueError(f"Cannot pick {count} boundaries in an episode of {depth.size} steps.")
    depth[:1] = -np.inf
    starts = np.sort(np.argsort(-depth, kind="stable")[: count - 1])
    return np.append(starts - 1, depth.size - 1).astype(np.int64)


def threshold_boundaries(depth: np.ndarray, threshold: float) -> np.ndarray:
    """OMPN's count-free read-out of one episode, in the same convention as `expansion_boundaries`.

    The expected expansion height is scaled to [0, 1] over the episode (the episode's lowest height
    to 0, its highest to 1); every run of consecutive steps above `threshold` starts one new subtask, at the run's
    highest step (ties to the earlier), so the boundary is the step before it. The run that holds
    step 0 (a full expansion by construction) is the episode's own start and adds none. OMPN's code
    thresholds the same scaled height (at 0.4, 0.5 and 0.6), but ends each segment at its run's last
    step and keeps at most the true number of boundaries; here nothing is told the count.
    """
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"The boundary threshold must lie in (0, 1), got {threshold}.")
    depth = np.asarray(depth, dtype=np.float64)
    span = depth.max() - depth.min()
    high = (depth - depth.min()) / span > threshold if span > 0 else np.zeros(depth.size, dtype=bool)
    high[0] = True
    # Steps after which `high` changes: the first run (from step 0) ends at the first, and the
    # others alternate: a later run starts after each odd-numbered one and ends at the next.
    edges = np.flatnonzero(np.diff(high.astype(np.int8))) + 1
    run_starts = edges[1::2]
    run_ends = np.append(edges[2::2], depth.size)[: run_starts.size]
    starts = [start + int(np.argmax(depth[start:end])) for start, end in zip(run_starts, run_ends, strict=True)]
    return np.append(np.asarray(starts, dtype=np.int64) - 1, depth.size - 1).astype(np.int64)


class OMPNPolicy(SequencePolicy, PreTrainedPolicy):
    """Ordered Memory Policy Network: a few memory slots updated up to a soft, learned height each step."""

    config_class = OMPNConfig
    name = "ompn"

    def __init__(self, config: OMPNConfig, **kwargs: Any) -> None:
        super().__init__(config, **kwargs)
        self.encoder = make_encoder(config)
        self.head = make_action_head(config)
        self.memory = OrderedMemory(
            obs_dim=self.encoder.out_dim,
            n_tasks=len(config.tasks),
            n_slots=config.n_slots,
            hidden_size=config.hidden_size,
            cell_hidden_size=config.cell_hidden_size,
            n_params=self.head.n_params,
        )
        self.reset()

    def get_optim_params(self) -> list[Tensor]:
        """One group: OMPN trains every part at the same rate."""
        return list(self.parameters())

    def reset(self) -> None:
        """Forget the memory: the next `select_action` is t = 1 of new episodes."""
        self._memory: Tensor | None = None
        self.last_expansion: Tensor | None = None

    def _unroll(self, state: Tensor, mask: Tensor, tasks: Sequence[str]) -> MemoryOutput:
        """`unroll` for the task strings of a batch."""
        return self.unroll(state, mask, self.task_index(tasks, state.shape[0]))

    def unroll(self, state: Tensor, mask: Tensor, task_index: Tensor) -> MemoryOutput:
        """The memory over windows [B, T, S] that each start an episode and whose real frames (mask
        [B, T]) are a prefix, as LeRobot's windows and whole-episode batches are: only those frames
        are encoded and run. Tasks are rows [B] of the task table (PPO replays episodes by them).
        Outputs are time-major."""
        lengths = mask.sum(1).clamp_min(1).cpu()
        packed = pack_padded_sequence(state.transpose(0, 1), lengths, enforce_sorted=False)
        features = PackedSequence(self.encoder(packed.data), *packed[1:])
        return self.memory.unroll(features, task_index, state.shape[1])

    def _action_log_prob(self, params: Tensor, action: Tensor) -> Tensor:
        """log p(a_t) [B, T] for time-major actor outputs [T, B, P] and actions [B, T, A] (LeRobot hands
        one-wide action features over as [B, T], hence the reshape)."""
        action = action.reshape(*action.shape[:2], self.config.action_dim).transpose(0, 1)
        return self.head.log_prob(params.unsqueeze(1), action).squeeze(1).transpose(0, 1)

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """NLL of the actions: mean over each window's real frames, then over windows."""
        mask, state, action, tasks, _ = self.training_windows(batch)
        out = self._unroll(state, mask, tasks)
        depth = expected_depth(out.expansion)
        return window_nll(self._action_log_prob(out.params, action), mask, reduction, {"mean_depth": depth})

    @torch.no_grad()
    def parse(self, batch: dict[str, Any]) -> dict[str, Tensor]:
        """Per-step expansion of whole episodes (each row starts at its episode's first frame).

        Returns batch-major `expansion` [B, T, n] (slot 0 = bottom; one-hot on the top slot at t = 1;
        zeros on padding), `depth` = its expected position [B, T], `mask` [B, T], and
        `action_log_prob` [B, T] when the batch has actions.
        """
        observation = self.observation(batch)
        mask = frame_mask(batch, observation)
        out = self._unroll(observation, mask, batch["task"])
        expansion = out.expansion.transpose(0, 1)
        result = {"expansion": expansion, "depth": expected_depth(expansion), "mask": mask}
        if ACTION in batch:
            result["action_log_prob"] = self._action_log_prob(out.params, batch[ACTION])
        return result

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """Advance every env's memory by one step and return its action as a chunk [B, 1, A]."""
        state = self.observation(batch)
        size = state.shape[0]
        if self._memory is not None and self._memory.shape[1] != size:
            raise ValueError(f"Batch size changed from {self._memory.shape[1]} to {size} without reset().")
        task = self.memory.task_embedding(self.task_index(batch.get("task"), size))
        x = self.memory.obs_projection(self.encoder(state))
        self._memory, expansion, params = self.memory.step(self._memory, x, task, self.memory.context(x, task))
        self.last_expansion = expansion.transpose(0, 1)
        weights = torch.ones(size, 1, dtype=params.dtype, device=params.device)
        return self.head.choose(weights, params.unsqueeze(0), self.config.inference_mode == "greedy").unsqueeze(1)
