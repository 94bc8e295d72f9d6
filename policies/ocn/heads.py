"""Action distributions of the options and of their mixture.

An option's raw output head (`params`) is read as categorical logits (discrete actions) or as a
diagonal Gaussian's mean and log-std (continuous actions). OCN's action distribution is a mixture
over K option components with weights [B, K] (eq. 10, 13, 16, 17); the heads score actions under
each component, and `mixture_log_prob` combines them in log space for a stable NLL.
"""

import math

import torch
from torch import Tensor

from lerobot_policy_ocn.sequence import SequenceConfig

_LOG_2PI = math.log(2.0 * math.pi)


def mixture_log_prob(weights: Tensor, component_log_prob: Tensor) -> Tensor:
    """log sum_k w_k p_k(a): weights [..., B, K], component_log_prob [..., K, B] -> [..., B]."""
    scores = component_log_prob.transpose(-1, -2)
    top = scores.max(dim=-1, keepdim=True).values.detach()
    total = (weights * torch.exp(scores - top)).sum(dim=-1)
    return top.squeeze(-1) + torch.log(total.clamp_min(torch.finfo(total.dtype).tiny))


def expected_log_prob(weights: Tensor, component_log_prob: Tensor) -> Tensor:
    """sum_k w_k log p_k(a), the mixture's log-likelihood with the log inside the sum (a lower bound
    on `mixture_log_prob`): weights [..., B, K], component_log_prob [..., K, B] -> [..., B]."""
    return (weights * component_log_prob.transpose(-1, -2)).sum(dim=-1)


def option_responsibilities(weights: Tensor, component_log_prob: Tensor) -> Tensor:
    """Each option's share of the mixed likelihood, w_k p_k(a) / sum_j w_j p_j(a), its continuing and
    restarted components added: weights [..., B, 2N], component_log_prob [..., 2N, B] -> [..., B, N]."""
    scores = component_log_prob.transpose(-1, -2) + torch.log(weights.clamp_min(torch.finfo(weights.dtype).tiny))
    posterior = torch.softmax(scores, dim=-1)
    continuing, restarted = posterior.chunk(2, dim=-1)
    return continuing + restarted


def sample_index(probs: Tensor) -> Tensor:
    """One index per row of probabilities [B, K], drawn as argmax_k p_k / E_k with E_k ~ Exp(1)
    (the exponential race). That is how `torch.multinomial` draws a single sample, so the draws are
    the same for the same generator state; it only skips multinomial's input checks, which cost
    more than the draw itself at one env."""
    return (probs / torch.empty_like(probs).exponential_()).argmax(dim=-1)


class DiscreteHead:
    """Categorical options; actions are stored as one index per frame ([..., 1])."""

    def __init__(self, n_actions: int) -> None:
        self.n_params = n_actions

    def log_prob(self, params: Tensor, action: Tensor) -> Tensor:
        """params [..., K, B, A], action [..., B, 1] -> log p_k(a) [..., K, B]."""
        index = action[..., 0].round().long() if action.is_floating_point() else action[..., 0]
        index = index.unsqueeze(-2).expand(params.shape[:-1]).unsqueeze(-1)
        return torch.log_softmax(params, dim=-1).gather(-1, index).squeeze(-1)

    def mixture(self, weights: Tensor, params: Tensor) -> Tensor:
        """Action probabilities sum_k w_k softmax(params_k): weights [B, K], params [K, B, A] -> [B, A].

        One batched matmul, [1, K] @ [K, A] per row: what einsum would call, without its planning."""
        component_probs = torch.softmax(params, dim=-1).transpose(0, 1)
        return torch.bmm(weights.unsqueeze(1), component_probs).squeeze(1)

    def choose(self, weights: Tensor, params: Tensor, greedy: bool) -> Tensor:
        """The mixture's most likely action or a sample from it -> [B, 1] float."""
        probs = self.mixture(weights, params)
        index = probs.argmax(dim=-1) if greedy else sample_index(probs)
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
        component = weights.argmax(dim=-1) if greedy else sample_index(weights)
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
