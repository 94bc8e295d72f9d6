"""Batch statistics over every process of a distributed run, so that a loss is the global batch's.

Under `torchrun` or `accelerate launch` each process computes the loss of its shard of the global
batch and DDP averages the gradients. A term that is a mean over the batch's episodes, or a function
of a batch-wide share, is the global batch's only if its sums run over every shard: these sums do,
with their gradient, and in one process they are the sums themselves.

What DDP needs of a loss is that the average over the processes of their losses' gradients is the
gradient of the global batch's loss. A mean over the global batch's terms (frames, episodes) has that
form when each process divides the sum of its own terms by the global count over the number of
processes (`global_mean_weight`, `global_mean`): the processes' losses then average to the global
mean, whatever share of the terms each one holds. A plain `.mean()` over each shard does not where
shards hold different counts, as they do once the held-out episodes of a shard leave its batch.
"""

import torch
import torch.distributed as dist
from torch import Tensor


def world_size() -> int:
    """How many processes train together (1 outside a distributed run)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def global_sum(value: Tensor) -> Tensor:
    """`value` summed over every process, differentiably: each process's gradient reaches the terms it
    holds. DDP averages the processes' gradients, and every process computes the same function of
    the sum, so a loss term f(global_sum(x)) gets the gradient of one process computing f on the global
    batch (each process's backward through the sum adds the world's N identical upstream gradients,
    which DDP's average divides by N again)."""
    if world_size() == 1:
        return value
    from torch.distributed.nn.functional import all_reduce

    return all_reduce(value)


def global_mean_weight(weight: Tensor) -> Tensor:
    """The divisor that makes DDP's average of per-process sums of `weight`-weighted terms the global
    batch's weighted mean: the global sum of the weights over the number of processes (no gradient)."""
    with torch.no_grad():
        return global_sum(weight.sum()) / world_size()


def global_mean(values: Tensor) -> Tensor:
    """The mean of `values` (every element one term) over every process's terms, in the form whose
    DDP-averaged gradient is that of the global mean: this process's sum over `global_mean_weight`. In
    one process it is `values.mean()`, except that no terms at all give 0 instead of NaN (a shard may
    hold none: its sum is then 0 and the other processes' terms make the mean)."""
    count = global_mean_weight(values.new_full((), float(values.numel())))
    return values.sum() / count.clamp_min(1e-6)
