"""The OCN cell network (paper eq. 3-6), stacked over a leading module dimension.

The N options are one `StackedCell` with weights of shape [N, in, out], so one time step of every
option is a handful of batched matmuls instead of a Python loop; the controller is the same class
with N = 1. Tensors inside the cell are module-major: [N, B, features].
"""

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn


@dataclass(frozen=True)
class SparseRows:
    """Input rows given by their nonzero entries: row r is sum_k value[r, k] e_{index[r, k]}, index and value
    [..., K]. Craft's OMPN features are 1,075 wide with 140 entries set, so the first layer reads them as a
    sum of 140 weight rows (`StackedCell.project`) instead of multiplying the whole width."""

    index: Tensor
    value: Tensor

    def __getitem__(self, key: Any) -> "SparseRows":
        return SparseRows(self.index[key], self.value[key])


class _SparseRowsProduct(torch.autograd.Function):
    """`SparseRows` (index, value [R, K]) times a weight [in, out]: the forward sums each row's weight rows
    (`embedding_bag`); the backward forms the rows densely and takes the weight's gradient as one matmul.
    On the CPU `embedding_bag`'s own backward sorts the indices first and is the slower of the two
    (`ocn-bench first-layer`, results/bench_first_layer.md, times the whole training step both ways)."""

    @staticmethod
    def forward(ctx: Any, index: Tensor, value: Tensor, weight: Tensor) -> Tensor:
        ctx.save_for_backward(index, value)
        ctx.in_dim = weight.shape[0]
        return torch.nn.functional.embedding_bag(index, weight, per_sample_weights=value, mode="sum")

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[None, None, Tensor | None]:
        if not ctx.needs_input_grad[2]:
            return None, None, None
        index, value = ctx.saved_tensors
        rows = grad.new_zeros(index.shape[0], ctx.in_dim).scatter_add_(1, index, value)
        return None, None, rows.T @ grad


def sparse_rows_product(index: Tensor, value: Tensor, weight: Tensor) -> Tensor:
    """Rows given by their set entries (index, value [R, K]) times weight [in, out] -> [R, out]."""
    return _SparseRowsProduct.apply(index, value, weight)


class CellOutput(NamedTuple):
    """One step of N cells: raw output head `logits` [N, B, n_out], new state `hidden` [N, B, d_hid],
    termination probability `end` [N, B] (None for cells built without a termination head)."""

    logits: Tensor
    hidden: Tensor
    end: Tensor | None


def stacked_uniform(n_modules: int, fan_in: int, *shape: int) -> nn.Parameter:
    """nn.Linear's default init, drawn independently for each module."""
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(n_modules, *shape).uniform_(-bound, bound))


def side_by_side(weight: Tensor) -> Tensor:
    """Stacked maps [N, in, out] as one matrix [in, N * out], map i in columns i * out to (i + 1) * out (a copy
    for N > 1: the N maps interleave; a view of the one map for N = 1).

    Built from the maps one by one (`unbind`, then `cat`) rather than by transposing the stack, so that the
    gradient comes back in the weight's own layout: the backward of `unbind` stacks the maps' gradients into a
    new [N, in, out] tensor. Through a transpose it came back transposed: AccumulateGrad copied it into the
    weight's layout for N > 1, and for the controller's N = 1 kept it as it came, with strides that differ
    from the weight's (harmless alone, but DDP compares them with its bucket's and warned "Grad strides do
    not match bucket view strides" at every step)."""
    maps = weight.unbind(0)
    return maps[0] if len(maps) == 1 else torch.cat(maps, dim=1)


def stacked_linear(x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    """One input through N stacked affine maps in one matmul: x [..., B, in], weight [in, N * out]
    (`side_by_side`), bias [N, 1, out] -> [..., N, B, out]."""
    n, _, width = bias.shape
    flat = x.reshape(-1, weight.shape[0]) @ weight
    return flat.view(*x.shape[:-1], n, width).movedim(-2, -3) + bias


class SideBySide:
    """`side_by_side` of one weight, kept between calls where no gradient is needed.

    The copy costs more than the matmul itself for one env (a fresh 1.6 MB at every inference step
    of the default options; the controller's one map is a view, which costs nothing), so outside
    autograd it is reused until the weight changes: in-place updates (optimizer steps,
    `load_state_dict`) bump the weight's version counter and moves give it new storage. Where the
    weight needs a gradient it is copied afresh, inside the graph, and so is a weight made in
    inference mode, which has no version counter. The kept copy is a normal tensor even when made
    in inference mode (as `lerobot-eval` calls `select_action`), so that autograd may use it later.
    """

    def __init__(self) -> None:
        self._key: tuple[int, int] | None = None
        self._matrix: Tensor | None = None

    def __call__(self, weight: Tensor) -> Tensor:
        if (weight.requires_grad and torch.is_grad_enabled()) or weight.is_inference():
            return side_by_side(weight)
        key = (weight.data_ptr(), weight._version)
        if key != self._key:
            with torch.inference_mode(False), torch.no_grad():
                self._matrix, self._key = side_by_side(weight), key
        return self._matrix


def split_heads(out: Tensor, n_out: int, hidden_size: int, with_end: bool) -> CellOutput:
    """A cell's output layer [N, B, n_out + d_hid (+ 1)] as its output head, new state and termination."""
    logits, hidden, *end = out.split([n_out, hidden_size, int(with_end)], dim=-1)
    end_prob = torch.sigmoid(end[0].squeeze(-1)) if with_end else None
    return CellOutput(logits, torch.tanh(hidden), end_prob)


class StackedCell(nn.Module):
    """N independent cells: h^ = MLP([x, h]) (tanh layers), out = W_out h^, h = tanh(W_hid h^),
    e = sigmoid(w_end h^).

    The first MLP layer is split into an observation part and a recurrent part so that the
    observation part, which does not depend on the recurrence, can be computed for a whole window
    in one matmul (`project`) before the time loop; `step` then only does the recurrent work.
    `sparse_product` computes that part for `SparseRows` inputs (`ocn-bench first-layer` swaps it).
    """

    sparse_product = staticmethod(sparse_rows_product)

    def __init__(
        self,
        n_modules: int,
        in_dim: int,
        hidden_size: int,
        mlp_hidden_size: int,
        mlp_depth: int,
        n_out: int,
        with_end: bool = True,
    ) -> None:
        super().__init__()
        self.n_modules = n_modules
        self.hidden_size = hidden_size
        self.n_out = n_out
        self.with_end = with_end
        fan_in = in_dim + hidden_size
        self.w_x = stacked_uniform(n_modules, fan_in, in_dim, mlp_hidden_size)
        self.w_h = stacked_uniform(n_modules, fan_in, hidden_size, mlp_hidden_size)
        self.b_in = stacked_uniform(n_modules, fan_in, 1, mlp_hidden_size)
        self.w_mlp = nn.ParameterList(
            stacked_uniform(n_modules, mlp_hidden_size, mlp_hidden_size, mlp_hidden_size)
            for _ in range(mlp_depth - 1)
        )
        self.b_mlp = nn.ParameterList(
            stacked_uniform(n_modules, mlp_hidden_size, 1, mlp_hidden_size) for _ in range(mlp_depth - 1)
        )
        head_width = n_out + hidden_size + int(with_end)
        self.w_out = stacked_uniform(n_modules, mlp_hidden_size, mlp_hidden_size, head_width)
        self.b_out = stacked_uniform(n_modules, mlp_hidden_size, 1, head_width)
        self.w_x_matrix = SideBySide()

    def project(self, x: Tensor | SparseRows) -> Tensor:
        """Observation part of the first layer, bias included: x [..., B, in] (or its `SparseRows`) ->
        [..., N, B, d_mlp]."""
        weight = self.w_x_matrix(self.w_x)
        if not isinstance(x, SparseRows):
            return stacked_linear(x, weight, self.b_in)
        n, _, width = self.b_in.shape
        entries = x.index.shape[-1]
        flat = self.sparse_product(x.index.reshape(-1, entries), x.value.reshape(-1, entries), weight)
        return flat.view(*x.index.shape[:-1], n, width).movedim(-2, -3) + self.b_in

    def step(self, x_proj: Tensor, h: Tensor) -> CellOutput:
        """One step from projected observations x_proj [N, B, d_mlp] and states h [N, B, d_hid].

        h may also be [N, 1, d_hid], one state shared by the whole batch (the learned initial
        states): its recurrent term is then computed once and broadcast.
        """
        if h.shape[1] == x_proj.shape[1]:
            act = torch.tanh(torch.baddbmm(x_proj, h, self.w_h))
        else:
            act = torch.tanh(x_proj + torch.bmm(h, self.w_h))
        for weight, bias in zip(self.w_mlp, self.b_mlp, strict=True):
            act = torch.tanh(torch.baddbmm(bias, act, weight))
        return split_heads(torch.baddbmm(self.b_out, act, self.w_out), self.n_out, self.hidden_size, self.with_end)

    def forward(self, x: Tensor, h: Tensor) -> CellOutput:
        """One step from raw observations x [B, in] (shared by all modules) and states h [N, B, d_hid]."""
        return self.step(self.project(x), h)
