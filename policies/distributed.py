"""Batch statistics over every process of a distributed run, so that a loss is the global batch's.

Under `torchrun` or `accelerate launch` each process computes the loss of its shard of the global
batch and DDP averages the gradients. A term that is a mean over the batch's episodes, or a function
of a batch-wide share, is the global batch's only if its sums run over every shard: these sums do,
with their gradient, and in one process they are the sums themselves.
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
