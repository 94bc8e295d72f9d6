"""The OCN models the benchmarks time, and how they time an update: torch's side of `ocn-bench`, imported
only when a benchmark runs (the benchmark modules themselves stay free of torch, for an instant --help).

`LoopedCell` is the baseline of the stacked option cells: the same parameter values held per module
and evaluated one module at a time in a Python loop, i.e. what a list of per-option networks would cost.
`first_layer` swaps the way the cells' first layer reads Craft's sparse features, for `first-layer`'s
baselines.
"""

from __future__ import annotations

import copy
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from lerobot_policy_ocn.envs.craft.observation import OMPN_DIM
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy
from lerobot_policy_ocn.ocn.cell import CellOutput, StackedCell, split_heads
from lerobot_policy_ocn.schedules import PhaseScheduleConfig

BENCH_TASKS = ["task 0", "task 1", "task 2"]
# A run this long never reaches its final phase: the benchmarks time the recipe's main loss.
CLOCK_STEPS = 10**9


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


def on_clock(policy: OCNPolicy) -> OCNPolicy:
    """The policy with a training clock of its own (`lerobot_policy_ocn.schedules`), which a recipe with a final
    phase reads in training; it never reaches that phase (`CLOCK_STEPS`)."""
    PhaseScheduleConfig().build(torch.optim.SGD(policy.parameters(), lr=0.0), CLOCK_STEPS)
    return policy


def use_looped_cells(policy: OCNPolicy) -> OCNPolicy:
    """Swap the policy's controller and option cells for looped copies with the same weights."""
    policy.core.controller = LoopedCell(policy.core.controller)
    policy.core.options = LoopedCell(policy.core.options)
    return policy


def make_bench_policy(n_options: int = 3, hidden_size: int = 128, obs_dim: int = OMPN_DIM, n_actions: int = 5,
                      device: str = "cpu") -> OCNPolicy:
    """A discrete-action OCN under the Craft recipe, on float observations of Craft's OMPN width (the
    identity encoder: the features the Craft encoder computes), on `device`, with its clock."""
    config = OCNConfig(
        device=device,
        recipe="craft",
        n_options=n_options,
        hidden_size=hidden_size,
        mlp_hidden_size=hidden_size,
        obs_encoder="identity",
        action_type="discrete",
        n_actions=n_actions,
        tasks=list(BENCH_TASKS),
        input_features={OBS_STATE: PolicyFeature(FeatureType.STATE, (obs_dim,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (1,))},
    )
    return on_clock(OCNPolicy(config).to(device))


def random_batch(policy: OCNPolicy, batch_size: int, window: int) -> dict[str, Any]:
    """A batch of whole episodes of `window` steps (no padding): sparse 0/1 observations and random
    actions, on the policy's device."""
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


def update_seconds(policy: OCNPolicy, batch: dict[str, Any], repeats: int = 3) -> float:
    """Seconds of one forward + backward of the policy's training loss on `batch`: the fastest of
    `repeats` timed runs after a warm-up (contention on a shared machine only ever slows a run down)."""
    device = policy.config.device
    policy.train()
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
    return min(times)


def compare_stacked_vs_loop(batch_size: int = 512, window: int = 32, n_options: int = 3, hidden_size: int = 128,
                            threads: int = 2, rounds: int = 3, device: str = "cpu") -> dict[str, float]:
    """Training frames per second of the stacked cells against the per-option loop, same weights and
    batch, measured in alternation for `rounds` rounds so that both see the same load; the best of each."""
    with torch_threads(threads):
        stacked = make_bench_policy(n_options=n_options, hidden_size=hidden_size, device=device)
        looped = on_clock(use_looped_cells(copy.deepcopy(stacked)))
        batch = random_batch(stacked, batch_size, window)
        frames = batch_size * window
        best = {"stacked": 0.0, "loop": 0.0}
        for _ in range(rounds):
            best["stacked"] = max(best["stacked"], frames / update_seconds(stacked, batch, repeats=1))
            best["loop"] = max(best["loop"], frames / update_seconds(looped, batch, repeats=1))
    return {"stacked_frames_per_s": best["stacked"], "loop_frames_per_s": best["loop"],
            "speedup": best["stacked"] / best["loop"]}


def dataset_policy(root: Path, repo_id: str, device: str, seed: int = 0) -> OCNPolicy:
    """The default OCN as `lerobot-train` builds it from the dataset at `root` (every field resolved from the
    dataset, its episodes in memory), initialised from `seed`, with its clock."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    torch.manual_seed(seed)
    meta = LeRobotDatasetMetadata(repo_id, root=root)
    return on_clock(make_policy(OCNConfig(device=device), ds_meta=meta))


def sampled_batch(policy: OCNPolicy, size: int, generator: torch.Generator) -> dict[str, Any]:
    """A batch as LeRobot's sampler draws it from the dataset the policy was built from: `size` frames drawn
    uniformly, each standing for its episode (the policy reads the episodes from its memory)."""
    memory = policy._episodes
    episode = torch.multinomial(memory.length.double(), size, replacement=True, generator=generator)
    device = policy.config.device
    return {OBS_STATE: torch.zeros(size, policy.config.state_dim, device=device),
            ACTION: torch.zeros(size, 1, device=device), "episode_index": episode.to(device)}


FIRST_LAYERS = ("matmul_backward", "embedding_bag", "dense")


def embedding_bag_product(index: Tensor, value: Tensor, weight: Tensor) -> Tensor:
    """`sparse_rows_product` with `embedding_bag`'s own backward, the implementation it replaced."""
    return torch.nn.functional.embedding_bag(index, weight, per_sample_weights=value, mode="sum")


@contextmanager
def first_layer(policy: OCNPolicy, variant: str) -> Iterator[None]:
    """Run the policy's first layer on Craft's features as `variant` (`FIRST_LAYERS`) says: the policy's own
    (`sparse_rows_product`), `embedding_bag` both ways, or the dense 1,075-wide features both ways."""
    cells = (policy.core.controller, policy.core.options)
    if variant == "embedding_bag":
        for cell in cells:
            cell.sparse_product = embedding_bag_product
    elif variant == "dense":
        policy.encoder.sparse = lambda state: None
    try:
        yield
    finally:
        for owner in (*cells, policy.encoder):
            vars(owner).pop("sparse_product", None)
            vars(owner).pop("sparse", None)


def compare_first_layers(policy: OCNPolicy, batch_size: int, rounds: int, block: int,
                         seed: int = 0) -> dict[str, float]:
    """Seconds of one training step (forward, backward, gradient clipping, Adam) of the policy with each
    first layer (`FIRST_LAYERS`), on batches sampled from its dataset. The variants take turns, `block`
    steps each after one untimed step, for `rounds` rounds; each variant's median block counts, so that
    all of them see the same load and the same stage of training."""
    preset = policy.config.get_optimizer_preset()
    optimizer = preset.build(policy.get_optim_params())
    policy.config.get_scheduler_preset().build(optimizer, CLOCK_STEPS)
    generator = torch.Generator().manual_seed(seed)
    policy.train()

    def train_step() -> None:
        loss, _ = policy.forward(sampled_batch(policy, batch_size, generator))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), preset.grad_clip_norm)
        optimizer.step()

    blocks: dict[str, list[float]] = {variant: [] for variant in FIRST_LAYERS}
    for _ in range(rounds):
        for variant in FIRST_LAYERS:
            with first_layer(policy, variant):
                train_step()
                begin = time.perf_counter()
                for _ in range(block):
                    train_step()
                blocks[variant].append((time.perf_counter() - begin) / block)
    return {variant: statistics.median(times) for variant, times in blocks.items()}
