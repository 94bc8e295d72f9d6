"""PPO for a fresh OCN controller over frozen options, in option space (paper 3.3 and appendix A.1).

The environment is a semi-MDP whose actions are options: the controller samples an option, the
option acts alone until its sampled termination fires (or the episode ends), and only then does
the controller choose again. Rollouts run the policy exactly as it is deployed (`select_action`
under `execution="hard"`, through the checkpoint's pre- and post-processors, as `lerobot-eval` and
`ocn-eval` run it), every env of one batch simulator stepped together, and read the policy's
`last_step.decided` to know where the controller chose. The world (Craft or Dial) enters only
through `Acting`: its batch simulator's `reset` and `step`, and its `RolloutWorld.env_action`
(`lerobot_policy_ocn.tools.rl.rollouts`), which turns the postprocessed actions into env actions; the states stored for
the update are the preprocessed ones the policy saw (on Dial, standardised by the dataset's
statistics), so the replay sees exactly what the rollout saw.

One PPO transition is one controller decision. Its reward is the discounted sum of the env
rewards while its option ran, R = sum_k gamma^k r_{t+k}, and the next decision's value is
discounted by gamma^duration (semi-MDP GAE). The controller is recurrent and its state advances
only at decisions, so each episode is stored as its sequence of decisions (the policy's input
state at the decision and the chosen option) and log-probabilities and values are recomputed over
whole episodes, from the task's initial controller state, by `replay_controller`; OCN's episodes
are a few dozen decisions at most (MoE's on Dial: one per step, up to the 450-step limit of a
3-digit PIN). Old log-probabilities and values come from the same replay with the pre-update
weights, so the PPO ratio is exactly 1 before the first gradient step.

Under `hierarchy="moe"` (the MoE baseline, and the flat baseline built on it in `ocn-finetune
--flat`) the controller decides at every step, so every option lasts one step: one transition per
env step with R = r_t and discount gamma, and semi-MDP GAE is ordinary GAE. Under `hierarchy="hil"`
(the HIL baseline) it decides every `skill_length` L steps, so every option lasts L steps (the last
of an episode may be cut short by its end), and semi-MDP GAE discounts by gamma^L.

The critic is a small MLP on h^c (`ValueHead`), trained with the controller (shared h^c, value
loss weighted by `value_coef`). It only serves training and is not part of the saved policy.
Options, their initial states, the encoder and the action head are frozen: `requires_grad` is
switched off and only the controller, its per-task initial states and the critic are optimised.
An episode that reaches the step limit ends like a terminated one (no bootstrap): the limit is
part of the task, as in evaluation.

What PPO needs of a policy is its `Actor` (`as_actor`): where rows decided and what they chose,
the replay of whole episodes' decisions, and what it trains. An OCN's is `OptionController`, all of
the above. An OMPN's is `lerobot_policy_ocn.tools.rl.ompn_rl.MemoryActor`, OMPN's RL form (paper appendix A.3): OMPN
cannot be split into options, so every row decides at every step, its choice is the primitive
action, and the whole network is trained (one transition per env step: ordinary GAE).

A run can save a `RunSnapshot` after every iteration: the policy's and the critic's weights, Adam's
moments, the torch RNG, the env-seed generator and the rows so far. Every iteration starts its envs
afresh from drawn seeds, so nothing else carries over, and a run resumed from its snapshot goes on
exactly as if it had not stopped (bit-identical on the same machine and thread count; tested).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from lerobot_policy_ocn.envs.batching import EpisodeBatch
from lerobot.utils.constants import OBS_STATE
from lerobot_policy_ocn.ocn import OCNPolicy
from lerobot_policy_ocn.ompn import OMPNPolicy
from lerobot_policy_ocn.tools.eval.parsing import Processor
from lerobot_policy_ocn.tools.rl.finetune_settings import PPOConfig
from lerobot_policy_ocn.tools.rl.ompn_rl import MemoryActor
from lerobot_policy_ocn.tools.rl.rollouts import RolloutWorld, policy_inputs, step_envs


class ValueHead(nn.Module):
    """Critic V(h^c): the controller's state after a decision -> the value of that decision point
    (for an OMPN: what its actor reads at a step -> the value of that step)."""

    def __init__(self, hidden_size: int, width: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(hidden_size, width), nn.Tanh(), nn.Linear(width, 1))

    def forward(self, controller_h: Tensor) -> Tensor:
        return self.net(controller_h).squeeze(-1)


def _unchanged(data: Any) -> Any:
    return data


@dataclass(frozen=True)
class Acting:
    """How the policy meets a world's envs: states go through `preprocessor` into the policy, its
    actions through `postprocessor` and `world.env_action` into the envs. A policy built in memory
    (no checkpoint, no dataset statistics) acts through identity processors."""

    world: RolloutWorld
    preprocessor: Processor = _unchanged
    postprocessor: Processor = _unchanged


@dataclass
class Decisions:
    """One batch of finished episodes as padded decision sequences.

    state [E, J, S] (the preprocessed state where the controller chose), option [E, J] (the choice:
    an option, or an OMPN's primitive action), reward [E, J]
    (discounted env reward while that option ran), duration [E, J] (env steps it ran), count [E]
    (decisions per episode; positions >= count are padding), task_index [E] (row of the policy's
    per-task initial controller states), and per-episode totals: return_ [E] (undiscounted),
    success [E], frames [E].
    """

    state: np.ndarray
    option: np.ndarray
    reward: np.ndarray
    duration: np.ndarray
    count: np.ndarray
    task_index: np.ndarray
    return_: np.ndarray
    success: np.ndarray
    frames: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """Real decisions [E, J]."""
        return np.arange(self.state.shape[1])[None, :] < self.count[:, None]


def check_finetunable(policy: OCNPolicy) -> None:
    """PPO needs the sampled hierarchy: hard execution with sampling, not greedy choices."""
    if policy.config.execution != "hard" or policy.config.inference_mode != "sample":
        raise ValueError(
            "PPO finetuning needs execution='hard' and inference_mode='sample', got "
            f"{policy.config.execution!r} and {policy.config.inference_mode!r}."
        )


@torch.no_grad()
def collect(
    policy: OCNPolicy | OMPNPolicy, envs: EpisodeBatch, acting: Acting, tasks: Sequence[str], seeds: Sequence[int],
    gamma: float,
) -> Decisions:
    """Run one episode in every env (env e on env seed seeds[e], task tasks[e]) and record its decisions.

    `tasks` are strings the policy knows (its `config.tasks`); the envs parse them too.
    """
    actor = as_actor(policy)
    actor.check()
    n, tasks = envs.num_envs, list(tasks)
    obs = envs.reset(seeds=list(seeds), tasks=tasks)
    task_index = policy.task_index(tasks, n).cpu().numpy()
    limit = int(envs.max_steps.max())
    state = np.zeros((n, limit, obs.shape[1]), dtype=np.float32)
    option = np.zeros((n, limit), dtype=np.int64)
    reward_sum = np.zeros((n, limit))
    duration = np.zeros((n, limit), dtype=np.int64)
    count = np.zeros(n, dtype=np.int64)
    age = np.zeros(n, dtype=np.int64)
    returns = np.zeros(n)
    policy.reset()
    while not envs.done.all():
        active = ~envs.done
        inputs = policy_inputs(obs, tasks, acting.preprocessor)
        chosen = policy.select_action(inputs)
        decides, choice = actor.choices(chosen)
        action = acting.postprocessor(chosen)
        decided = np.flatnonzero(decides & active)
        state[decided, count[decided]] = inputs[OBS_STATE].cpu().numpy()[decided]
        option[decided, count[decided]] = choice[decided]
        count[decided] += 1
        age[decided] = 0
        obs, reward = step_envs(acting.world, envs, action)
        running = np.flatnonzero(active)
        current = count[running] - 1
        reward_sum[running, current] += gamma ** age[running] * reward[running]
        duration[running, current] += 1
        age[running] += 1
        returns[running] += reward[running]
    policy.reset()
    used = max(int(count.max()), 1)
    return Decisions(
        state=state[:, :used],
        option=option[:, :used],
        reward=reward_sum[:, :used],
        duration=duration[:, :used],
        count=count,
        task_index=task_index,
        return_=returns,
        success=envs.progress == envs.task_len,
        frames=envs.t.copy(),
    )


def semi_mdp_gae(
    reward: Tensor, duration: Tensor, value: Tensor, count: Tensor, gamma: float, lam: float
) -> tuple[Tensor, Tensor]:
    """Advantages and returns [E, J] of decision sequences (positions >= count[e] are padding, zero).

    delta_j = R_j + gamma^d_j V_{j+1} - V_j and A_j = delta_j + gamma^d_j lambda A_{j+1}, with
    V_{j+1} = A_{j+1} = 0 after an episode's last decision.
    """
    steps = reward.shape[1]
    advantage = torch.zeros_like(reward)
    next_value = torch.zeros_like(reward[:, 0])
    next_advantage = torch.zeros_like(reward[:, 0])
    for j in reversed(range(steps)):
        real = j < count
        discount = gamma ** duration[:, j].to(reward.dtype)
        delta = reward[:, j] + discount * next_value - value[:, j]
        step_advantage = torch.where(real, delta + discount * lam * next_advantage, 0.0)
        advantage[:, j] = step_advantage
        next_value = torch.where(real, value[:, j], 0.0)
        next_advantage = step_advantage
    return advantage, advantage + value * (torch.arange(steps) < count[:, None])


def replay_controller(policy: OCNPolicy, critic: ValueHead, state: Tensor, task_index: Tensor) -> tuple[Tensor, Tensor]:
    """Tempered controller logits [E, J, N] and values [E, J] over decision sequences state [E, J, S],
    from each episode's task state h^c_{tau,0}: the controller recurrence of hard execution, replayed.

    Only the recurrence runs step by step; the critic reads all the states h^c at once after it (for
    MoE, whose episodes are a decision per step, about a fifth of the update's time; `ocn-bench ppo`)."""
    core = policy.core
    features = policy.encoder(state.transpose(0, 1).contiguous())
    projected = core.controller.project(features)
    controller_h = core.controller_init[task_index]
    logits, states = [], []
    for x in projected.unbind(0):
        step_logits, controller_h = core.decide(x, controller_h)
        logits.append(step_logits)
        states.append(controller_h)
    return torch.stack(logits, 1), critic(torch.stack(states, 1))


def freeze_options(policy: OCNPolicy) -> list[nn.Parameter]:
    """Freeze everything but the controller and its per-task initial states; return those."""
    for param in policy.parameters():
        param.requires_grad_(False)
    trainable = [policy.core.controller_init, *policy.core.controller.parameters()]
    for param in trainable:
        param.requires_grad_(True)
    return trainable


class Actor(Protocol):
    """What PPO needs of a policy, so that one PPO serves OCN's controller and OMPN's whole network."""

    policy: OCNPolicy | OMPNPolicy
    critic_size: int  # width of the features the critic reads

    def check(self) -> None:
        """Refuse a policy whose rollouts do not sample the choices PPO trains."""

    def choices(self, action: Tensor) -> tuple[np.ndarray, np.ndarray]:
        """After `select_action` returned `action` [B, A]: the rows [B] that decided this step, and
        every row's current choice [B]."""

    def replay(self, critic: nn.Module, state: Tensor, task_index: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
        """Logits [E, J, K] of the choices and the critic's values [E, J] over decision sequences
        state [E, J, S] (count [E] real decisions each) of episodes of tasks task_index [E]."""

    def trainable(self) -> list[nn.Parameter]:
        """Switch `requires_grad` on for what PPO trains and off for the rest; return the former."""


class OptionController:
    """An OCN's actor: its controller, deciding where hard execution's options end, over frozen options."""

    def __init__(self, policy: OCNPolicy) -> None:
        self.policy = policy
        self.critic_size = policy.config.hidden_size

    def check(self) -> None:
        check_finetunable(self.policy)

    def choices(self, action: Tensor) -> tuple[np.ndarray, np.ndarray]:
        step = self.policy.last_step
        return step.decided.cpu().numpy(), step.option.cpu().numpy()

    def replay(self, critic: nn.Module, state: Tensor, task_index: Tensor, count: Tensor) -> tuple[Tensor, Tensor]:
        """`replay_controller`; padding decisions are replayed too (the controller's steps are cheap)."""
        return replay_controller(self.policy, critic, state, task_index)

    def trainable(self) -> list[nn.Parameter]:
        return freeze_options(self.policy)


def as_actor(policy: OCNPolicy | OMPNPolicy) -> Actor:
    """The policy's PPO actor: OMPN's RL form for an OMPN, else the OCN controller."""
    return MemoryActor(policy) if isinstance(policy, OMPNPolicy) else OptionController(policy)


class PPOTrainer:
    """Clipped-surrogate PPO updates of the actor (and critic) from batches of `Decisions`."""

    def __init__(self, policy: OCNPolicy | OMPNPolicy, config: PPOConfig) -> None:
        self.actor = as_actor(policy)
        self.actor.check()
        self.config = config
        self.critic = ValueHead(self.actor.critic_size, config.value_hidden)
        self.trainable = [*self.actor.trainable(), *self.critic.parameters()]
        self.optimizer = torch.optim.Adam(self.trainable, lr=config.lr, eps=1e-5)

    def set_lr_fraction(self, fraction: float) -> float:
        """Linear schedule: lr = fraction * the base lr; returns the lr now in use."""
        lr = self.config.lr * max(fraction, 0.0)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        return lr

    def update(self, batch: Decisions) -> dict[str, float]:
        """`epochs` passes over the batch's episodes in shuffled minibatches of about `batch_size` decisions."""
        cfg = self.config
        state = torch.from_numpy(batch.state)
        option = torch.from_numpy(batch.option)
        count = torch.from_numpy(batch.count)
        task_index = torch.from_numpy(batch.task_index)
        mask = torch.from_numpy(batch.mask)
        with torch.no_grad():
            logits, value = self.actor.replay(self.critic, state, task_index, count)
            old_log_prob = torch.log_softmax(logits, -1).gather(-1, option.unsqueeze(-1)).squeeze(-1)
            advantage, returns = semi_mdp_gae(
                torch.from_numpy(batch.reward).float(), torch.from_numpy(batch.duration), value, count,
                cfg.gamma, cfg.gae_lambda,
            )
        n_minibatches = min(len(batch.count), max(1, round(int(batch.count.sum()) / cfg.batch_size)))
        totals: dict[str, float] = {}
        for _ in range(cfg.epochs):
            for episodes in np.array_split(torch.randperm(len(batch.count)).numpy(), n_minibatches):
                rows = torch.from_numpy(episodes)
                stats = self._step(state[rows], option[rows], task_index[rows], mask[rows], old_log_prob[rows],
                                   advantage[rows], returns[rows])
                for key, value_ in stats.items():
                    totals[key] = totals.get(key, 0.0) + value_
        return {key: total / (cfg.epochs * n_minibatches) for key, total in totals.items()}

    def _step(
        self, state: Tensor, option: Tensor, task_index: Tensor, mask: Tensor, old_log_prob: Tensor,
        advantage: Tensor, returns: Tensor,
    ) -> dict[str, float]:
        """One gradient step on a minibatch of whole episodes; means are over real decisions only."""
        cfg = self.config
        used = int(mask.sum(1).max())
        state, option, mask = state[:, :used], option[:, :used], mask[:, :used]
        old_log_prob, advantage, returns = old_log_prob[:, :used], advantage[:, :used], returns[:, :used]
        logits, value = self.actor.replay(self.critic, state, task_index, mask.sum(1))
        log_probs = torch.log_softmax(logits, -1)
        log_prob = log_probs.gather(-1, option.unsqueeze(-1)).squeeze(-1)
        real_advantage = advantage[mask]
        if real_advantage.numel() > 1:
            advantage = (advantage - real_advantage.mean()) / (real_advantage.std() + 1e-8)
        ratio = torch.exp(log_prob - old_log_prob)
        surrogate = torch.minimum(ratio * advantage, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * advantage)
        entropy = -(log_probs.exp() * log_probs).sum(-1)
        policy_loss = -surrogate[mask].mean()
        value_loss = 0.5 * (value - returns)[mask].square().mean()
        entropy_mean = entropy[mask].mean()
        loss = policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy_mean
        self.optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.trainable, cfg.max_grad_norm)
        self.optimizer.step()
        with torch.no_grad():
            log_ratio = (log_prob - old_log_prob)[mask]
            return {
                "policy_loss": policy_loss.item(),
                "value_loss": value_loss.item(),
                "entropy": entropy_mean.item(),
                "approx_kl": ((log_ratio.exp() - 1) - log_ratio).mean().item(),
                "clip_fraction": ((ratio[mask] - 1).abs() > cfg.clip).float().mean().item(),
            }


def env_tasks(tasks: Sequence[str], n_envs: int) -> list[str]:
    """Tasks dealt round-robin over the envs, so every task gets n_envs / len(tasks) episodes per batch."""
    if n_envs < len(tasks):
        raise ValueError(f"{n_envs} envs cannot run {len(tasks)} tasks: use at least one env per task.")
    return [tasks[e % len(tasks)] for e in range(n_envs)]


def iteration_row(
    batch: Decisions, tasks: Sequence[str], env_task: Sequence[str], labels: Sequence[str]
) -> dict[str, Any]:
    """Curve entries of one batch: mean return, success overall and per task (`success[label]`),
    decisions per episode."""
    row: dict[str, Any] = {
        "episodes": len(batch.count),
        "mean_return": float(batch.return_.mean()),
        "success": float(batch.success.mean()),
        "decisions_per_episode": float(batch.count.mean()),
    }
    env_task_array = np.asarray(env_task, dtype=object)
    for task, label in zip(tasks, labels, strict=True):
        row[f"success[{label}]"] = float(batch.success[env_task_array == task].mean())
    return row


@dataclass
class RunSnapshot:
    """The file where `finetune` keeps, after every iteration, all that its run needs to go on after an
    interruption, and the settings that identify the run (what made it: checkpoints, tasks, budget,
    PPO settings...). A snapshot saved under other settings is refused, so a run never resumes as
    another one."""

    path: Path
    settings: dict[str, Any]

    def load(self) -> dict[str, Any] | None:
        """The saved state (None if there is no file yet); ValueError if its run had other settings."""
        if not self.path.exists():
            return None
        state = torch.load(self.path, weights_only=False)
        saved = state["settings"]
        differ = [f"{key}: {saved.get(key)!r} there, {self.settings.get(key)!r} here"
                  for key in sorted(set(saved) | set(self.settings)) if saved.get(key) != self.settings.get(key)]
        if differ:
            raise ValueError(f"{self.path} was saved by a run with other settings ({'; '.join(differ)}).")
        return state

    def save(self, state: dict[str, Any]) -> None:
        """Write `state` (with the settings) beside the file and move it in place: an interruption during
        the write leaves the previous snapshot whole."""
        partial = self.path.with_name(self.path.name + ".partial")
        torch.save({**state, "settings": self.settings}, partial)
        os.replace(partial, self.path)


def finetune(
    policy: OCNPolicy | OMPNPolicy,
    envs: EpisodeBatch,
    acting: Acting,
    tasks: Sequence[str],
    total_frames: int,
    config: PPOConfig,
    seed: int,
    on_iteration: Callable[[dict[str, Any]], None] | None = None,
    labels: Sequence[str] | None = None,
    snapshot: RunSnapshot | None = None,
    resume: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """PPO until `total_frames` env frames are spent; one iteration = one episode in every env.

    Seeds torch (option, termination and action sampling, initial weights of the critic) and the
    env seeds (Craft's maps, Dial's start poses; drawn per iteration from a numpy Generator seeded
    with `seed`). The learning rate
    decays linearly with the frames spent. Returns one row per iteration (also passed to
    `on_iteration` as it happens): frames so far, lr, the batch's returns and successes (per task
    under `labels`, default the task strings), PPO stats. With `snapshot`, the run's state is saved
    there after every iteration; `resume` (a state `RunSnapshot.load` read) goes on from it, its rows
    returned first but not passed to `on_iteration` again.
    """
    torch.manual_seed(seed)
    env_seeds = np.random.default_rng(seed)
    trainer = PPOTrainer(policy, config)
    env_task = env_tasks(tasks, envs.num_envs)
    frames, rows = 0, []
    if resume is not None:
        policy.load_state_dict(resume["policy"])
        trainer.critic.load_state_dict(resume["critic"])
        trainer.optimizer.load_state_dict(resume["optimizer"])
        torch.set_rng_state(resume["torch_rng"])
        env_seeds.bit_generator.state = resume["env_seeds"]
        frames, rows = resume["frames"], list(resume["rows"])
    while frames < total_frames:
        lr = trainer.set_lr_fraction(1.0 - frames / total_frames)
        batch = collect(policy, envs, acting, env_task, env_seeds.integers(0, 2**31 - 1, envs.num_envs), config.gamma)
        frames += int(batch.frames.sum())
        row = {"iteration": len(rows) + 1, "frames": frames, "lr": lr,
               **iteration_row(batch, tasks, env_task, labels or tasks)}
        row.update(trainer.update(batch))
        rows.append(row)
        if on_iteration is not None:
            on_iteration(row)
        if snapshot is not None:
            snapshot.save({"policy": policy.state_dict(), "critic": trainer.critic.state_dict(),
                           "optimizer": trainer.optimizer.state_dict(), "torch_rng": torch.get_rng_state(),
                           "env_seeds": env_seeds.bit_generator.state, "frames": frames, "rows": rows})
    return rows
