"""Options that are frozen compILE action decoders, one per latent category: compILE's RL form.

compILE (Kipf et al. 2019) decodes a segment's latent z and the observation features o into an
action through an MLP, head(W_out relu(W_obs o + b_obs + W_z z) + b_out) (`CompILEPolicy._decode`).
With concrete (categorical) latents, z = one-hot(k) picks row k of W_z, so one decoder is a pool of
K one-step policies: option k acts as the decoder given latent k. The OCN paper's RL form of compILE
freezes the decoder and trains a re-initialised encoder to predict the latent; here that encoder is
OCN's controller choosing one of these options at every step (`hierarchy="moe"`), trained by the
same PPO as every other method.

`LatentDecoderPool` has the option interface of `StackedCell` (`n_modules`, `project`, `step`), so
the recurrence, hard execution, `act_with_options`, the rollouts and the checkpoint are OCN's own.
Several decoders are stacked along a leading axis (option d * K + k is decoder d with latent k),
so pools merge by concatenating every parameter along it, as OCN's stacked options do (S2). The
options have neither state nor termination: `step` hands the recurrent state back unchanged and
reports e = 0 (an option run alone never stops by itself); under `hierarchy="moe"` the controller
chooses again at every step regardless.
"""

import torch
from torch import Tensor, nn

from .cell import CellOutput, SideBySide, stacked_linear, stacked_uniform


class LatentDecoderPool(nn.Module):
    """`n_decoders` compILE decoders (observation features `in_dim` -> `width` -> `n_out` head
    parameters) as `n_decoders * latent_dim` one-step options; `hidden_size` is the width of the
    (unused) option state that OCN's recurrence carries."""

    def __init__(self, n_decoders: int, latent_dim: int, in_dim: int, width: int, n_out: int, hidden_size: int) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.n_modules = n_decoders * latent_dim
        self.hidden_size = hidden_size
        self.n_out = n_out
        self.obs_weight = stacked_uniform(n_decoders, in_dim, in_dim, width)
        self.obs_bias = stacked_uniform(n_decoders, in_dim, 1, width)
        self.latent_weight = stacked_uniform(n_decoders, latent_dim, latent_dim, width)
        self.out_weight = stacked_uniform(n_decoders, width, width, n_out)
        self.out_bias = stacked_uniform(n_decoders, width, 1, n_out)
        self.obs_matrix = SideBySide()

    def project(self, x: Tensor) -> Tensor:
        """Each decoder's observation term W_obs o + b_obs: x [..., B, in] -> [..., D, B, width]."""
        return stacked_linear(x, self.obs_matrix(self.obs_weight), self.obs_bias)

    def step(self, x_proj: Tensor, h: Tensor) -> CellOutput:
        """Every option's head parameters [N, B, n_out] from projected observations x_proj [D, B, width];
        the state h ([N, B, d_hid] or [N, 1, d_hid]) comes back unchanged, the termination is 0."""
        n_decoders, batch, width = x_proj.shape
        act = torch.relu(x_proj.unsqueeze(1) + self.latent_weight.unsqueeze(2))  # [D, K, B, width]
        logits = torch.baddbmm(self.out_bias, act.reshape(n_decoders, -1, width), self.out_weight)
        logits = logits.view(self.n_modules, batch, self.n_out)
        hidden = h.expand(self.n_modules, batch, self.hidden_size)
        return CellOutput(logits, hidden, logits.new_zeros(self.n_modules, batch))

    def forward(self, x: Tensor, h: Tensor) -> CellOutput:
        """One step from raw observation features x [B, in] and states h [N, B, d_hid]."""
        return self.step(self.project(x), h)

    @torch.no_grad()
    def load_decoder(self, index: int, obs: nn.Linear, latent: nn.Linear, out: nn.Linear) -> None:
        """Copy a compILE decoder (its `decoder_obs`, `decoder_latent`, `decoder_out` layers) into
        decoder slot `index`, transposed into the stacked layout; the values are copied unchanged."""
        self.obs_weight[index].copy_(obs.weight.T)
        self.obs_bias[index, 0].copy_(obs.bias)
        self.latent_weight[index].copy_(latent.weight.T)
        self.out_weight[index].copy_(out.weight.T)
        self.out_bias[index, 0].copy_(out.bias)
