"""Action distributions of the options and of their mixture.

An option's raw output head (`params`) is read as categorical logits (discrete actions) or as a
diagonal Gaussian's mean and log-std (continuous actions). OCN's action distribution is a mixture
over K option components with weights [B, K] (eq. 10, 13, 16, 17); the heads score actions under
each component, and `mixture_log_prob` combines them in log space for a stable NLL.
"""

import math

import torch
from torch import Tensor

from policies.sequence import SequenceConfig

_LOG_2PI = math.log(2.0 * math.pi)


def mixture_log_prob(weights: Tensor, component_log_prob: Tensor) -> Tensor:
    """log sum_k w_k p_k(a): weights [..., B, K], component_log_prob [..., K, B] -> [..., B]."""
    scores = component_log_prob.transpose(-1, -2)
    top = scores.max(dim=-1, keepdim=True).values.detach()
    total = (weights * torch.exp(scores - top)).sum(dim=-1)
    return top.squeeze(-1) + torch.log(total.clamp_min(torch.finfo(total.dtype).tiny))


class DiscreteHead:
    """Categorical options; actions are stored as one index per frame ([..., 1])."""

    def __init__(self, n_actions: int) -> None:
        self.n_params = n_actions

    def log_prob(self, params: Tensor, action: Tensor) -> Tensor:
        """params [..., K, B, A], action [..., B, 1] -> log p_k(a) [..., K, B]."""
        index = action[..., 0].round().long() if action.is_floating_point() else action[..., 0]
        index = index.unsqueeze(-2).expand(params.shape[:-1]).unsqueeze(-1)
        return torch.log_softmax(params, dim=-1).gather(-1, index).squeeze(-1)

    def choose(self, weights: Tensor, params: Tensor, greedy: bool) -> Tensor:
        """Mixture probabilities sum_k w_k softmax(params_k), then argmax or a sample -> [B, 1] float."""
        probs = torch.einsum("bk,kba->ba", weights, torch.softmax(params, dim=-1))
        index = probs.argmax(dim=-1) if greedy else torch.multinomial(probs, 1).squeeze(-1)
        return index.unsqueeze(-1).float()


class GaussianHead:
    """Diagonal Gaussian options over a D-dim action: params = [mean (D), log-std (D)]."""

    def __init__(self, action_dim: int, log_std_min: float, log_std_max: float) -> None:
        self.n_params = 2 * action_dim
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max

    def split(self, params: Tensor) -> tuple[Tensor, Tensor]:
        mean, log_std = params.chunk(2, dim=-1)
        return mean, log_std.clamp(self.log_std_min, self.log_std_max)

    def log_prob(self, params: Tensor, action: Tensor) -> Tensor:
        """params [..., K, B, 2D], action [..., B, D] -> log p_k(a) [..., K, B]."""
        mean, log_std = self.split(params)
        z = (action.unsqueeze(-3) - mean) * torch.exp(-log_std)
        return (-0.5 * z.square() - log_std - 0.5 * _LOG_2PI).sum(dim=-1)

    def choose(self, weights: Tensor, params: Tensor, greedy: bool) -> Tensor:
        """Greedy: mean of the heaviest component; else sample a component, then the Gaussian -> [B, D]."""
        mean, log_std = self.split(params)
        if greedy:
            component = weights.argmax(dim=-1)
        else:
            component = torch.multinomial(weights, 1).squeeze(-1)
        rows = torch.arange(weights.shape[0], device=weights.device)
        chosen_mean, chosen_log_std = mean[component, rows], log_std[component, rows]
        if greedy:
            return chosen_mean
        return chosen_mean + torch.exp(chosen_log_std) * torch.randn_like(chosen_mean)


def make_action_head(config: SequenceConfig) -> DiscreteHead | GaussianHead:
    """Head named by `config.action_type`."""
    if config.action_type == "discrete":
        return DiscreteHead(config.n_actions)
    return GaussianHead(config.action_dim, config.log_std_min, config.log_std_max)
