"""compILE as a LeRobot policy: the segment-by-segment inference network, its loss, the parse that
the shared parsing metrics read, and an online form for `select_action`.

The model (Kipf et al. 2019; see `CompILEConfig` for where each hyperparameter comes from):
- Each step t is embedded from its observation features and its action; an LSTM runs over the
  embedded episode once per segment. Before segment i starts, its LSTM state is multiplied by the
  probability that segment i has begun, so each segment's encoding starts afresh at its start.
- Segment i's boundary b_i is a distribution over positions p = 0..L of an episode of L steps:
  b_i = p means segment i ends at step p - 1 and the next one starts at p. Position 0 (an empty
  first segment) and positions past the episode are masked; p = L means "the segment runs to the
  end" (the later segments are then empty), the role of the end-of-sequence element in compILE's
  own data. The last segment's boundary is fixed at L: it ends at the episode's end. Its logit at
  p is read from the encoding of step p - 1; in training b_i is a Gumbel-softmax (relaxed one-hot)
  sample, otherwise its argmax.
- The latent z_i is read from the encoding of the segment's last step (the b_i-weighted encoding
  of step p - 1): concrete (Gumbel-softmax over `latent_dim` categories, argmax outside training)
  or Gaussian (reparameterised, its mean outside training).
- An MLP decodes z_i and the observation o_t into the action distribution of step t (the shared
  heads of `lerobot_policy_ocn.ocn.heads`: categorical for Craft, diagonal Gaussian for continuous actions).
- Loss per episode: sum over steps and segments of -log p(a_t | o_t, z_i) weighted by the soft
  probability that step t lies in segment i, + kl_z_weight * sum_i KL(q(z_i) || prior) (uniform
  categorical or standard normal) + kl_b_weight * sum over the inner boundaries of
  KL(q(b_i) || Poisson length prior); averaged over the batch's episodes as compILE does (a sum
  over each episode's steps, not a per-step mean, so that the KL weights keep their meaning).
  compILE's code scores only the first boundary's KL and multiplies it by the number of segments
  (a stand-in it marks as a to-do); here each inner boundary gets the prior of its own segment's
  length, given where the sampled boundaries before it start that segment (`length_prior`): for
  the first boundary it is compILE's prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION
from lerobot_policy_ocn.ocn.encoders import make_encoder
from lerobot_policy_ocn.ocn.heads import make_action_head
from lerobot_policy_ocn.sequence import SequencePolicy, batch_mean, frame_mask

from .configuration_compile import CompILEConfig

# A finite log 0: masked logits get exactly zero probability, and 0 * NEG stays 0 in the KLs.
NEG = -1e30


@dataclass
class CompILEOutput:
    """One pass of the inference network over windows [B, T] (n segments, P = T + 1 positions).

    boundary_logits: [n - 1, B, P] masked logits of the inner boundaries.
    boundaries: [n, B, P] boundary samples (relaxed or hard one-hot); the last is one-hot at L.
    latent_params: [n, B, Z] concrete logits, or [n, B, 2Z] Gaussian mean and log-variance.
    latents: [n, B, Z] latent samples.
    action_log_prob: [n, B, T] log p(a_t | o_t, z_i) under each segment's decoder.
    """

    boundary_logits: Tensor
    boundaries: Tensor
    latent_params: Tensor
    latents: Tensor
    action_log_prob: Tensor


def allowed_positions(lengths: Tensor, steps: int) -> Tensor:
    """Positions [B, steps + 1] a boundary may take: 1..L for an episode of L real steps (never 0,
    an empty first segment, nor past the episode's end)."""
    positions = torch.arange(steps + 1, device=lengths.device)
    return (positions >= 1) & (positions <= lengths[:, None])


def segment_probabilities(boundaries: Tensor) -> tuple[Tensor, Tensor]:
    """From boundaries [n, B, P]: the probability [n, B, P] that position p lies in segment i, and
    the probability [n, B, P] that segment i has started by p.

    With C_j the cumulative sum of b_j over positions, segment i has started where every earlier
    boundary has passed (prod_{j<i} C_j) and still runs where its own has not (1 - C_i). The
    probabilities of all segments telescope to 1 when the last boundary lies past p.
    """
    passed = boundaries.cumsum(-1)
    started = torch.cat([torch.ones_like(passed[:1]), passed[:-1].cumprod(0)])
    return started * (1.0 - passed).clamp_min(0.0), started


def poisson_log_pmf(k: Tensor, rate: float) -> Tensor:
    """log Poisson(k; rate) for integer-valued k >= 0."""
    return k * math.log(rate) - rate - torch.lgamma(k + 1.0)


def length_prior(start: Tensor, allowed: Tensor, rate: float) -> Tensor:
    """log prior [..., B, P] of a segment's boundary p given the distribution `start` [..., B, P] of
    the position s where the segment starts: its length p - s >= 1 is Poisson(rate), renormalised
    over the allowed positions [B, P]. For the first segment (s = 0) this is compILE's prior.

    Positions where the segment would be empty or end before it starts have prior 0; their log is
    clamped at the log of the smallest normal float (about -87 in float32), a large finite penalty
    in the KL instead of an infinite one."""
    positions = torch.arange(start.shape[-1], dtype=start.dtype, device=start.device)
    length = positions - positions[:, None]  # [s, p]
    pmf = torch.where(length >= 1, poisson_log_pmf(length.clamp_min(0.0), rate).exp(), 0.0)
    log_prior = torch.log((start @ pmf).clamp_min(torch.finfo(start.dtype).tiny)).masked_fill(~allowed, NEG)
    return log_prior - torch.logsumexp(log_prior, dim=-1, keepdim=True)


def boundary_kl(boundary_logits: Tensor, boundaries: Tensor, allowed: Tensor, rate: float) -> Tensor:
    """KL(q(b_i) || length prior) [n - 1, B] of each inner boundary: q = softmax of its logits, the
    prior's start is where segment i starts under the sampled boundaries before it."""
    _, started = segment_probabilities(boundaries)
    start = torch.diff(started[:-1], dim=-1, prepend=torch.zeros_like(started[:-1, ..., :1]))
    log_q = torch.log_softmax(boundary_logits, dim=-1)
    kl = log_q.exp() * (log_q - length_prior(start, allowed, rate))
    return kl.masked_fill(~allowed, 0.0).sum(-1)


def latent_kl(latent_params: Tensor, latent_type: str) -> Tensor:
    """KL [n, B] of each segment's latent posterior from its prior: uniform over the categories
    (concrete) or the standard normal (Gaussian)."""
    if latent_type == "concrete":
        log_q = torch.log_softmax(latent_params, dim=-1)
        return (log_q.exp() * log_q).sum(-1) + math.log(latent_params.shape[-1])
    mean, log_var = latent_params.chunk(2, dim=-1)
    return 0.5 * (mean.square() + log_var.exp() - log_var - 1.0).sum(-1)


def compile_loss(out: CompILEOutput, mask: Tensor, config: CompILEConfig) -> tuple[Tensor, dict[str, Tensor]]:
    """compILE's loss per window [B] for windows whose real steps (mask [B, T]) are a prefix, and its
    terms per window: `nll` (segment-weighted, summed over the steps), `kl_z`, `kl_b`."""
    mask = mask.float()
    in_segment, _ = segment_probabilities(out.boundaries)
    weights = in_segment[..., :-1] * mask
    nll = -(weights * out.action_log_prob).sum((0, 2))
    kl_z = latent_kl(out.latent_params, config.latent_type).sum(0)
    allowed = allowed_positions(mask.sum(1).long(), mask.shape[1])
    kl_b = boundary_kl(out.boundary_logits, out.boundaries, allowed, config.poisson_rate).sum(0)
    loss = nll + config.kl_z_weight * kl_z + config.kl_b_weight * kl_b
    return loss, {"nll": nll, "kl_z": kl_z, "kl_b": kl_b}


class CompILEPolicy(SequencePolicy, PreTrainedPolicy):
    """compILE: segments with one latent each, inferred from the whole demonstration, decoded into actions."""

    config_class = CompILEConfig
    name = "compile"

    def __init__(self, config: CompILEConfig, **kwargs: Any) -> None:
        super().__init__(config, **kwargs)
        self.encoder = make_encoder(config)
        self.head = make_action_head(config)
        width, features = config.hidden_size, self.encoder.out_dim
        self.obs_embed = nn.Linear(features, width)
        if config.action_type == "discrete":
            self.action_embed: nn.Module = nn.Embedding(config.n_actions, width)
        else:
            self.action_embed = nn.Linear(config.action_dim, width)
        self.lstm = nn.LSTMCell(width, width)
        self.boundary_head = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, 1))
        latent_width = config.latent_dim * (1 if config.latent_type == "concrete" else 2)
        self.latent_head = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, latent_width))
        # The decoder MLP over [o_t, z_i], its first layer split so the observation part is computed once.
        self.decoder_obs = nn.Linear(features, width)
        self.decoder_latent = nn.Linear(config.latent_dim, width, bias=False)
        self.decoder_out = nn.Linear(width, self.head.n_params)
        self.reset()

    def get_optim_params(self) -> list[Tensor]:
        """One group: compILE trains every part at the same rate."""
        return list(self.parameters())

    def reset(self) -> None:
        """Forget the history: the next `select_action` is t = 1 of new episodes."""
        self._history: tuple[Tensor, Tensor] | None = None
        self.last_latent: Tensor | None = None

    def _embed_action(self, action: Tensor) -> Tensor:
        if self.config.action_type == "discrete":
            return self.action_embed(action[..., 0].round().long())
        return self.action_embed(action.float())

    def _encode(self, embedded: Tensor, started: Tensor) -> Tensor:
        """LSTM outputs [B, T, H] over embedded steps [B, T, H], its state scaled after each step by
        the probability [B, T] that the segment has started (zero before it: a fresh start)."""
        batch, steps, width = embedded.shape
        hidden = cell = embedded.new_zeros(batch, width)
        outputs = []
        for t in range(steps):
            hidden, cell = self.lstm(embedded[:, t], (hidden, cell))
            keep = started[:, t, None]
            hidden, cell = hidden * keep, cell * keep
            outputs.append(hidden)
        return torch.stack(outputs, dim=1)

    def _sample_latent(self, params: Tensor, hard: bool) -> Tensor:
        config = self.config
        if config.latent_type == "concrete":
            if hard:
                return F.one_hot(params.argmax(-1), config.latent_dim).to(params.dtype)
            return F.gumbel_softmax(params, tau=config.latent_temperature)
        mean, log_var = params.chunk(2, dim=-1)
        return mean if hard else mean + torch.exp(0.5 * log_var) * torch.randn_like(mean)

    def _decode(self, features: Tensor, latents: Tensor) -> Tensor:
        """Action-head parameters [n, B, T, P] of each latent [n, B, Z] at each step's features [B, T, F]."""
        hidden = self.decoder_obs(features).unsqueeze(0) + self.decoder_latent(latents).unsqueeze(2)
        return self.decoder_out(torch.relu(hidden))

    def _run(self, state: Tensor, action: Tensor, mask: Tensor, hard: bool) -> CompILEOutput:
        """The inference network and the decoder over windows [B, T] whose real steps (mask) are a
        prefix: relaxed samples when `hard` is False (training), argmax ones otherwise."""
        config = self.config
        action = action.reshape(*action.shape[:2], config.action_dim)
        batch, steps = mask.shape
        lengths = mask.sum(1)
        allowed = allowed_positions(lengths, steps)
        features = self.encoder(state)
        embedded = torch.relu(self.obs_embed(features) + self._embed_action(action))
        started = torch.ones(batch, steps + 1, dtype=embedded.dtype, device=embedded.device)
        logits_all, boundaries_all, params_all, latents_all = [], [], [], []
        for segment in range(config.n_segments):
            encoded = self._encode(embedded, started[:, :steps])
            if segment < config.n_segments - 1:
                logits = F.pad(self.boundary_head(encoded).squeeze(-1), (1, 0)).masked_fill(~allowed, NEG)
                if hard:
                    boundary = F.one_hot(logits.argmax(-1), steps + 1).to(embedded.dtype)
                else:
                    boundary = F.gumbel_softmax(logits, tau=config.boundary_temperature)
                logits_all.append(logits)
            else:
                boundary = F.one_hot(lengths, steps + 1).to(embedded.dtype)
            params = self.latent_head((boundary[:, 1:, None] * encoded).sum(1))
            latents_all.append(self._sample_latent(params, hard))
            boundaries_all.append(boundary)
            params_all.append(params)
            started = started * boundary.cumsum(-1)
        latents = torch.stack(latents_all)
        decoded = self._decode(features, latents).flatten(1, 2)
        log_prob = self.head.log_prob(decoded, action.flatten(0, 1)).view(config.n_segments, batch, steps)
        boundary_logits = torch.stack(logits_all) if logits_all else embedded.new_zeros(0, batch, steps + 1)
        return CompILEOutput(boundary_logits, torch.stack(boundaries_all), torch.stack(params_all), latents, log_prob)

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """compILE's loss: per episode window, then the mean over windows with real frames (reduction
        "none": per window [B]). Relaxed samples in training mode, argmax ones in eval mode."""
        mask, state, action, _, _ = self.training_windows(batch)
        out = self._run(state, action, mask, hard=not self.training)
        per_window, terms = compile_loss(out, mask, self.config)
        frames = mask.sum(1)
        used = (frames > 0).float()
        windows = used.sum().clamp_min(1.0)
        terms = {name: value.detach() for name, value in terms.items()}
        stats = {
            "nll": float(terms["nll"].sum() / frames.sum().clamp_min(1)),
            "kl_z": float((terms["kl_z"] * used).sum() / windows),
            "kl_b": float((terms["kl_b"] * used).sum() / windows),
            "frames_used": int(frames.sum()),
        }
        if reduction == "none":
            return per_window * used, stats
        return batch_mean(per_window, frames), stats

    @torch.no_grad()
    def parse(self, batch: dict[str, Any]) -> dict[str, Tensor]:
        """Hard (argmax) segmentation of whole episodes (each row starts at its episode's first frame).

        Returns batch-major `segment` [B, T] (the segment each step lies in, non-decreasing),
        `label` [B, T] (concrete latents: the category of that segment's latent), both -1 on
        padding and `label` -1 throughout for Gaussian latents, `boundary` [B, n] (each segment's
        argmax boundary position: the step the next one starts at) and `mask` [B, T].
        """
        if ACTION not in batch:
            raise ValueError("compILE parses demonstrations: its encoder reads the actions, and the batch has none.")
        observation = self.observation(batch)
        mask = frame_mask(batch, observation)
        out = self._run(observation, batch[ACTION], mask, hard=True)
        in_segment, _ = segment_probabilities(out.boundaries)
        segment = in_segment[..., :-1].argmax(0)
        if self.config.latent_type == "concrete":
            label = out.latents.argmax(-1).transpose(0, 1).gather(1, segment).masked_fill(~mask, -1)
        else:
            label = torch.full_like(segment, -1)
        boundary = out.boundaries.argmax(-1).transpose(0, 1)
        return {"segment": segment.masked_fill(~mask, -1), "label": label, "boundary": boundary, "mask": mask}

    def _current_latents(self, size: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
        """Mixture weights [B, K] and latents [K, B, Z] to act with now: the latent of the segment
        the history's last step lies in, or, with no history yet, the prior (concrete: every
        category, equally weighted; Gaussian: its mean, zero)."""
        config, one = self.config, torch.ones(size, 1, dtype=dtype, device=device)
        if self._history is None:
            if config.latent_type == "gaussian":
                return one, torch.zeros(1, size, config.latent_dim, dtype=dtype, device=device)
            categories = torch.eye(config.latent_dim, dtype=dtype, device=device).unsqueeze(1).expand(-1, size, -1)
            return one.expand(-1, config.latent_dim) / config.latent_dim, categories
        states, actions = self._history
        mask = torch.ones(states.shape[:2], dtype=torch.bool, device=device)
        out = self._run(states, actions, mask, hard=True)
        in_segment, _ = segment_probabilities(out.boundaries)
        current = in_segment[:, :, -2].argmax(0)
        return one, out.latents[current, torch.arange(size, device=device)].unsqueeze(0)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """One action per env as a chunk [B, 1, A], online: the history so far (the observations and
        the policy's own actions since `reset()`) is segmented as in `parse`, the latent of the
        segment its last step lies in (the open one) is decoded with the current observation. At
        t = 1 there is no evidence yet and the prior's latents are decoded instead. The history is
        re-segmented at every step (n_segments LSTM passes over it): quadratic in the episode's
        length, which Craft's episodes of at most 100 steps afford."""
        state = self.observation(batch)
        size = state.shape[0]
        if self._history is not None and self._history[0].shape[0] != size:
            raise ValueError(f"Batch size changed from {self._history[0].shape[0]} to {size} without reset().")
        features = self.encoder(state)
        weights, latents = self._current_latents(size, features.dtype, features.device)
        params = self._decode(features.unsqueeze(1), latents).squeeze(2)
        action = self.head.choose(weights, params, self.config.inference_mode == "greedy")
        self.last_latent = (weights.unsqueeze(-1) * latents.transpose(0, 1)).sum(1)
        step = (state.unsqueeze(1), action.unsqueeze(1))
        if self._history is not None:
            step = tuple(torch.cat(pair, dim=1) for pair in zip(self._history, step, strict=True))
        self._history = step
        return action.unsqueeze(1)
