"""Speed measurements of the OCN policy, as functions for benchmark tools to call.

The baseline for the stacked cell is `LoopedCell`: the same parameter values held per module and
evaluated one module at a time in a Python loop, i.e. what a list of per-option networks would cost.
"""

import copy
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any

import torch
from torch import Tensor, nn

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE

from envs.craft.observation import OMPN_DIM

from .cell import CellOutput, StackedCell, split_heads
from .configuration_ocn import OCNConfig
from .modeling_ocn import OCNPolicy

BENCH_TASKS = ["task 0", "task 1", "task 2"]


class LoopedCell(nn.Module):
    """The cells of a `StackedCell` as N separate networks, each with its own parameters, evaluated one
    after another: what a list of per-option modules would cost (the per-option loop baseline)."""

    def __init__(self, cell: StackedCell) -> None:
        super().__init__()
        self.n_modules, self.hidden_size, self.n_out, self.with_end = (
            cell.n_modules, cell.hidden_size, cell.n_out, cell.with_end)

        def per_module(stacked: Tensor) -> nn.ParameterList:
            return nn.ParameterList(nn.Parameter(part.detach().clone()) for part in stacked.unbind(0))

        self.w_x, self.b_in, self.w_h, self.w_out, self.b_out = (
            per_module(w) for w in (cell.w_x, cell.b_in, cell.w_h, cell.w_out, cell.b_out))
        self.w_mlp = nn.ModuleList(per_module(w) for w in cell.w_mlp)
        self.b_mlp = nn.ModuleList(per_module(b) for b in cell.b_mlp)

    def project(self, x: Tensor) -> Tensor:
        return torch.stack([x @ w + b for w, b in zip(self.w_x, self.b_in, strict=True)], dim=-3)

    def step(self, x_proj: Tensor, h: Tensor) -> CellOutput:
        outs = []
        for i, (x_i, h_i) in enumerate(zip(x_proj.unbind(0), h.unbind(0), strict=True)):
            act = torch.tanh(x_i + h_i @ self.w_h[i])
            for weights, biases in zip(self.w_mlp, self.b_mlp, strict=True):
                act = torch.tanh(act @ weights[i] + biases[i])
            outs.append(act @ self.w_out[i] + self.b_out[i])
        return split_heads(torch.stack(outs), self.n_out, self.hidden_size, self.with_end)


def use_looped_cells(policy: OCNPolicy) -> OCNPolicy:
    """Swap the policy's controller and option cells for looped copies with the same weights."""
    policy.core.controller = LoopedCell(policy.core.controller)
    policy.core.options = LoopedCell(policy.core.options)
    return policy


def make_bench_policy(
    n_options: int = 3,
    hidden_size: int = 128,
    obs_dim: int = OMPN_DIM,
    n_actions: int = 5,
    window: int = 32,
    device: str = "cpu",
) -> OCNPolicy:
    """A discrete-action OCN on float observations of Craft's OMPN width (identity encoder), on `device`."""
    config = OCNConfig(
        device=device,
        n_options=n_options,
        hidden_size=hidden_size,
        mlp_hidden_size=hidden_size,
        window_size=window,
        window_start="any",
        obs_encoder="identity",
        n_actions=n_actions,
        tasks=list(BENCH_TASKS),
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (obs_dim,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))},
    )
    return OCNPolicy(config).to(device)


def random_batch(policy: OCNPolicy, batch_size: int, window: int) -> dict:
    """A training batch of random one-hot-like observations and actions, no padding, on the policy's device."""
    obs_dim = policy.encoder.out_dim
    device = policy.config.device
    return {
        OBS_STATE: (torch.rand(batch_size, window, obs_dim, device=device) < 0.05).float(),
        ACTION: torch.randint(0, policy.config.n_actions, (batch_size, window, 1), device=device).float(),
        f"{ACTION}_is_pad": torch.zeros(batch_size, window, dtype=torch.bool, device=device),
        "task": [BENCH_TASKS[i % len(BENCH_TASKS)] for i in range(batch_size)],
    }


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Temporarily run torch's CPU ops on `threads` threads."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def synchronize(device: str) -> None:
    """Wait for the device's queued kernels, so that a wall-clock timing covers the work it launched."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def train_frames_per_second(policy: OCNPolicy, batch: dict, repeats: int = 3) -> float:
    """Frames per second of forward + backward: the fastest of `repeats` timed runs after a warm-up.

    The fastest run, not the median, because these machines share their cores with other jobs and
    contention only ever slows a run down.
    """
    frames = batch[OBS_STATE].shape[0] * batch[OBS_STATE].shape[1]
    device = policy.config.device
    times = []
    for run in range(repeats + 1):
        policy.zero_grad(set_to_none=True)
        synchronize(device)
        begin = time.perf_counter()
        loss, _ = policy.forward(batch)
        loss.backward()
        synchronize(device)
        if run:
            times.append(time.perf_counter() - begin)
    return frames / min(times)


@contextmanager
def stepping_every_row(policy: OCNPolicy) -> Iterator[OCNPolicy]:
    """Within, the policy's training forward steps every row of its windows through every step, padding
    after a row's end included (the first layer still projects the real frames alone), for the same
    loss (tested): the update as it was before `OCNCore.unroll_frames`, the baseline of that speed-up."""
    core = policy.core

    def every_row(x: Tensor, state: Any, start: Tensor, real: Tensor) -> Any:
        return core.unroll_projected(core.project_frames(x, real), state, start)[1]

    policy.core.unroll_frames = every_row
    try:
        yield policy
    finally:
        del policy.core.unroll_frames


@contextmanager
def restarting_in_each_step(policy: OCNPolicy) -> Iterator[OCNPolicy]:
    """Within, each step of the policy's training forward computes the options' restarted branch itself,
    for the same loss (tested): the update as it was before `OCNCore.restarts_ahead` computed that branch
    for a whole window in one call, the baseline of that speed-up."""
    policy.core.restarts_ahead = lambda x_options, rows: [None] * len(rows)
    try:
        yield policy
    finally:
        del policy.core.restarts_ahead


def best_in_alternation(
    policy: OCNPolicy, batch: dict, baseline: Callable[[OCNPolicy], AbstractContextManager], rounds: int = 3
) -> tuple[float, float]:
    """The best training throughput (frames of the padded batch per second) of the policy as it is and
    inside `baseline(policy)`, same weights and batch, measured in alternation for `rounds` rounds so
    that both see the same load."""
    best = [0.0, 0.0]
    for _ in range(rounds):
        best[0] = max(best[0], train_frames_per_second(policy, batch, repeats=1))
        with baseline(policy):
            best[1] = max(best[1], train_frames_per_second(policy, batch, repeats=1))
    return best[0], best[1]


def compare_running_vs_every_row(policy: OCNPolicy, batch: dict, rounds: int = 3) -> dict[str, float]:
    """Training throughput stepping only the rows still in their episode against stepping every row to
    the window's end (`best_in_alternation`)."""
    running, every = best_in_alternation(policy, batch, stepping_every_row, rounds)
    return {"running_rows_per_s": running, "every_row_per_s": every, "speedup": running / every}


def compare_restarts_ahead_vs_each_step(policy: OCNPolicy, batch: dict, rounds: int = 3) -> dict[str, float]:
    """Training throughput with the options' restarted branch computed for the whole window ahead against
    computed in each step (`best_in_alternation`)."""
    ahead, each = best_in_alternation(policy, batch, restarting_in_each_step, rounds)
    return {"restarts_ahead_per_s": ahead, "restarts_each_step_per_s": each, "speedup": ahead / each}


def compare_stacked_vs_loop(
    batch_size: int = 512,
    window: int = 32,
    n_options: int = 3,
    hidden_size: int = 128,
    threads: int = 2,
    rounds: int = 3,
    device: str = "cpu",
) -> dict[str, float]:
    """Training throughput of the stacked cells vs. the per-option loop, same weights and batch.

    The two are measured in alternation for `rounds` rounds so that both see the same load.
    """
    with torch_threads(threads):
        stacked = make_bench_policy(n_options=n_options, hidden_size=hidden_size, window=window, device=device)
        looped = use_looped_cells(copy.deepcopy(stacked))
        batch = random_batch(stacked, batch_size, window)
        best = {"stacked": 0.0, "loop": 0.0}
        for _ in range(rounds):
            best["stacked"] = max(best["stacked"], train_frames_per_second(stacked, batch, repeats=1))
            best["loop"] = max(best["loop"], train_frames_per_second(looped, batch, repeats=1))
    return {
        "stacked_frames_per_s": best["stacked"],
        "loop_frames_per_s": best["loop"],
        "speedup": best["stacked"] / best["loop"],
    }


def select_action_latency(
    policy: OCNPolicy, batch_size: int = 1, steps: int = 200, threads: int = 1
) -> float:
    """Seconds per `select_action` call for `batch_size` envs (median over `steps` calls), made
    under `torch.inference_mode` as `lerobot-eval` makes them; on a GPU each call is timed until its
    kernels finish."""
    obs_dim = policy.encoder.out_dim
    device = policy.config.device
    observation = {
        OBS_STATE: (torch.rand(batch_size, obs_dim, device=device) < 0.05).float(),
        "task": [policy.config.tasks[0]] * batch_size,
    }
    times = []
    with torch_threads(threads), torch.inference_mode():
        policy.eval()
        policy.reset()
        for _ in range(steps):
            begin = time.perf_counter()
            policy.select_action(observation)
            synchronize(device)
            times.append(time.perf_counter() - begin)
    return statistics.median(times)
