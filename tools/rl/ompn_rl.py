"""OMPN's RL form (paper appendix A.3): the whole OMPN finetuned by PPO on primitive actions.

OMPN's levels talk through continuous memory, bottom-up and top-down, so it cannot be split into
options under a new controller; the paper keeps its high level and finetunes it. `ocn-finetune
--checkpoint OMPN_CKPT` checks the checkpoint (`finetunable_ompn`: one checkpoint, Craft only), gives
it the new tasks (`ompn_for_tasks`) and `lerobot_policy_ocn.tools.rl.ppo` trains it through `MemoryActor`: every env
decides at every step, its choice is the primitive action it sampled, and every weight is trained
with the critic. The result stays an `ompn` checkpoint.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot_policy_ocn.ompn import OMPNPolicy

TASK_EMBEDDING = "memory.task_embedding.weight"


def ompn_for_tasks(policy: OMPNPolicy, tasks: Sequence[str]) -> OMPNPolicy:
    """A sampling copy of `policy` for the new `tasks`: every weight kept, and one task embedding per
    new task, each the mean of the trained embeddings.

    The mean rather than a fresh draw: the new tasks chain the trained subtasks, and the kept cells
    only ever read embeddings in the trained ones' span, where a fresh N(0, 1) vector need not lie;
    and, like OCN's new controller states (all zero), every new task starts from the same point, so
    none gets an arbitrary head start before PPO tells them apart.
    """
    config = dataclasses.replace(policy.config, tasks=list(tasks), inference_mode="sample", pretrained_path=None)
    copy = OMPNPolicy(config)
    state = policy.state_dict()
    state[TASK_EMBEDDING] = state[TASK_EMBEDDING].mean(0, keepdim=True).expand(len(tasks), -1).clone()
    copy.load_state_dict(state)
    return copy.eval()


def finetunable_ompn(
    policies: Sequence[PreTrainedPolicy], names: Sequence[str], temperature: float | None
) -> OMPNPolicy:
    """The one OMPN among `policies` (checkpoints named `names`), after refusing what OMPN's RL form
    cannot do: pool it with other checkpoints, run outside Craft, take a temperature. Called before
    --tasks is read, so that a Dial OMPN is refused for what it is, not for its PINs."""
    if len(policies) > 1:
        raise ValueError(
            f"Cannot pool {', '.join(names)}: an `ompn` checkpoint has no options to pool, so its whole network "
            "is finetuned alone (the paper leaves OMPN out of S2); give it as the only --checkpoint."
        )
    policy, name = policies[0], names[0]
    config = policy.config
    if config.obs_encoder != "craft" or config.action_type != "discrete":
        raise ValueError(
            f"{name} is an OMPN with the {config.obs_encoder} encoder and {config.action_type} actions: OMPN's "
            "RL form is finetuned in Craft only (discrete actions, the craft encoder)."
        )
    if temperature is not None:
        raise ValueError("--temperature is the OCN controller's: an `ompn` checkpoint has no controller to temper.")
    return policy


class MemoryActor:
    """PPO's actor for an OMPN (see `lerobot_policy_ocn.tools.rl.ppo.Actor`): every row decides at every step, and the
    choice is the primitive action `select_action` sampled from the actor's categorical logits."""

    def __init__(self, policy: OMPNPolicy) -> None:
        self.policy = policy
        self.critic_size = 3 * policy.config.hidden_size  # the actor's input [m_0, e, x_t]

    def check(self) -> None:
        config = self.policy.config
        if config.action_type != "discrete" or config.inference_mode != "sample":
            raise ValueError(
                "PPO finetuning of an OMPN needs discrete actions and inference_mode='sample', got "
                f"{config.action_type!r} and {config.inference_mode!r}."
            )

    def choices(self, action: Tensor) -> tuple[np.ndarray, np.ndarray]:
        index = action[:, 0].long().cpu().numpy()
        return np.ones(index.shape, dtype=bool), index

    def replay(self, critic: nn.Module, state: Tensor, task_index: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
        """The memory unrolled over each episode's real steps from its task's full expansion, as
        `select_action` ran it: the actor's logits and the critic on what the actor read (padding is
        not run; PPO masks it)."""
        mask = torch.arange(state.shape[1], device=state.device) < count[:, None]
        out = self.policy.unroll(state, mask, task_index)
        return out.params.transpose(0, 1), critic(out.actor_input.transpose(0, 1))

    def trainable(self) -> list[nn.Parameter]:
        """Every weight: the paper re-initialises no part of OMPN in RL."""
        params = list(self.policy.parameters())
        for param in params:
            param.requires_grad_(True)
        return params
