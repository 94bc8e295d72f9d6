"""OMPN's ordered memory (Lu et al. 2021): one step, and whole windows.

Slots are numbered from the bottom: slot 0 is the level that acts (the actor reads it), slot n-1
the top (the task level). The memory m is slot-major, [n, B, H]. A step from the observation
encoding x_t and the task embedding e, with context c = [x_t, e]:

1. Bottom-up: cand_0 = Com_0(x_t, m_0 | c), cand_i = Com_i(cand_{i-1}, m_i | c): each slot's new
   content if this step's update reaches it.
2. Expansion: a shared MLP of [c, m_i, cand_i] gives a stopping probability beta_i for every slot
   but the top; stick-breaking from the bottom gives p_i = beta_i prod_{j<i} (1 - beta_j) and the
   top takes the rest, so p sums to 1 over the slots. pos ~ p is the highest slot updated.
3. Top-down: the slots below pos are rebuilt from it by the decomposition cells:
   child_{i-1} = Dec_i(parent_i | c), parent_i = P(pos <= i) cand_i + P(pos > i) child_i.
4. Update, in expectation over pos: m_i <- P(pos < i) m_i + p_i cand_i + P(pos > i) child_i.

The actor reads [m_0, e, x_t]. An episode starts with a full expansion from the initial memory
(top slot LN(e), the others zero): p = one-hot(top) and cand = that memory, so the lower slots are
decomposed from the task. Every cell is gated, cell = LN(sum_j g_j u_j + g_new u_new) with a
non-affine LayerNorm; its gates and new content come from an MLP (width `cell_hidden`) of its
inputs and c, the gates through an affine LayerNorm and a sigmoid.

Two departures from the OMPN code, both deliberate: OMPN's stick leaves mass p_end above the top
slot, which it reads as the probability of an extra DONE action; these datasets have no DONE
action (nor does the OCN paper's Craft), so the top slot takes the rest of the stick instead of
OMPN renormalising p over the slots. And the bottom slot has no decomposition cell (OMPN computes
one and discards its output).
"""

from typing import NamedTuple

import torch
from torch import Tensor, nn
from torch.nn import functional as F
from torch.nn.utils.rnn import PackedSequence, pad_packed_sequence

from lerobot_policy_ocn.ocn.cell import stacked_uniform


class Context(NamedTuple):
    """Each part of the network's first layers that reads only c = [x, e], computed for a whole
    window in one matmul: composition [n, B, F], decomposition [n-1, B, F], expansion [B, H]
    (biases included)."""

    composition: Tensor
    decomposition: Tensor
    expansion: Tensor

    def split(self, sizes: list[int]) -> list["Context"]:
        """Cut along the batch axis into consecutive groups of rows (the steps of a packed window)."""
        return [Context(*parts) for parts in zip(*(part.split(sizes, dim=-2) for part in self), strict=True)]


class MemoryOutput(NamedTuple):
    """Time-major outputs of a window: actor outputs `params` [T, B, n_params], the expansion
    distribution `expansion` [T, B, n] (slot 0 = bottom), and what the actor read, `actor_input`
    [T, B, 3H] (a critic that reads the same features trains the whole network in OMPN's RL form)."""

    params: Tensor
    expansion: Tensor
    actor_input: Tensor


class CellWeights(NamedTuple):
    """The weights of one gated cell: views into its stack's parameters."""

    w_chain: Tensor
    w_out: Tensor
    b_out: Tensor
    gate_weight: Tensor
    gate_bias: Tensor


class GatedCells(nn.Module):
    """One gated cell per slot, stacked ([n, in, out] weights).

    A cell carries k vectors u_1..u_k of width H: u_1 is the chain input (from the neighbouring
    slot, so the cells run slot by slot), the other k-1 (`side`) and the context are known before
    the chain, so their share of the first layer is computed for every slot at once.
    """

    def __init__(self, n_cells: int, n_carried: int, hidden: int, context: int, cell_hidden: int) -> None:
        super().__init__()
        self.hidden = hidden
        self.n_carried = n_carried
        fan_in = n_carried * hidden + context
        self.w_chain = stacked_uniform(n_cells, fan_in, hidden, cell_hidden)
        self.w_side = stacked_uniform(n_cells, fan_in, (n_carried - 1) * hidden, cell_hidden) if n_carried > 1 else None
        self.w_context = stacked_uniform(n_cells, fan_in, context, cell_hidden)
        self.b_in = stacked_uniform(n_cells, fan_in, 1, cell_hidden)
        width = (n_carried + 2) * hidden  # k + 1 gates and the new content
        self.w_out = stacked_uniform(n_cells, cell_hidden, cell_hidden, width)
        self.b_out = stacked_uniform(n_cells, cell_hidden, 1, width)
        self.gate_weight = nn.Parameter(torch.ones(n_cells, 1, (n_carried + 1) * hidden))
        self.gate_bias = nn.Parameter(torch.zeros(n_cells, 1, (n_carried + 1) * hidden))

    def project(self, context: Tensor) -> Tensor:
        """Context share of the first layer, bias included: [..., B, C] -> [..., n, B, cell_hidden]."""
        n, in_dim, width = self.w_context.shape
        flat = context.reshape(-1, in_dim) @ self.w_context.transpose(0, 1).reshape(in_dim, n * width)
        return flat.view(*context.shape[:-1], n, width).movedim(-2, -3) + self.b_in

    def prepare(self, projected: Tensor, side: Tensor | None) -> Tensor:
        """Add the side inputs' share [n, B, (k-1)H] to the projected context [n, B, cell_hidden]."""
        return projected if side is None else torch.baddbmm(projected, side, self.w_side)

    def unbound(self) -> list[CellWeights]:
        """Every cell's weights, cut from the stacks once (`unbind`). A recurrence takes its cells from
        here rather than indexing the stacks at every step: in the backward pass each index writes a
        zero-filled gradient of its whole stack, which made a backward through many steps several
        times slower than its arithmetic."""
        stacks = (self.w_chain, self.w_out, self.b_out, self.gate_weight, self.gate_bias)
        return [CellWeights(*views) for views in zip(*(stack.unbind(0) for stack in stacks), strict=True)]

    def cell(self, weights: CellWeights, chain: Tensor, prepared: Tensor, side: Tensor | None = None) -> Tensor:
        """The cell of `weights` (from `unbound`) on its chain input [B, H], its prepared first layer
        [B, cell_hidden] and its side inputs [B, (k-1)H] -> [B, H]."""
        act = torch.relu(torch.addmm(prepared, chain, weights.w_chain))
        out = torch.addmm(weights.b_out, act, weights.w_out)
        gate_logits, new = out.split([(self.n_carried + 1) * self.hidden, self.hidden], dim=-1)
        gate_logits = F.layer_norm(gate_logits, gate_logits.shape[-1:]) * weights.gate_weight + weights.gate_bias
        gates = torch.sigmoid(gate_logits).chunk(self.n_carried + 1, dim=-1)
        carried = (chain,) if side is None else (chain, *side.chunk(self.n_carried - 1, dim=-1))
        total = gates[-1] * new
        for gate, value in zip(gates[:-1], carried, strict=True):
            total = total + gate * value
        return F.layer_norm(total, (self.hidden,))


def stick_breaking(beta: Tensor) -> Tensor:
    """Stopping probabilities beta [n-1, B] of every slot but the top -> expansion p [n, B], summing to
    1: p_i = beta_i prod_{j<i} (1 - beta_j), the top slot takes the rest."""
    ones = torch.ones_like(beta[:1])
    return torch.cat([beta, ones]) * torch.cat([ones, torch.cumprod(1.0 - beta, dim=0)])


class OrderedMemory(nn.Module):
    """The whole OMPN: observation projection, task embedding, ordered memory and actor."""

    def __init__(
        self, obs_dim: int, n_tasks: int, n_slots: int, hidden_size: int, cell_hidden_size: int, n_params: int
    ) -> None:
        super().__init__()
        self.n_slots = n_slots
        self.hidden_size = hidden_size
        context = 2 * hidden_size
        self.obs_projection = nn.Linear(obs_dim, hidden_size)
        self.task_embedding = nn.Embedding(n_tasks, hidden_size)
        self.compose = GatedCells(n_slots, 2, hidden_size, context, cell_hidden_size)
        self.decompose = GatedCells(n_slots - 1, 1, hidden_size, context, cell_hidden_size)
        self.expansion_context = nn.Linear(context, hidden_size)
        self.expansion_memory = nn.Linear(2 * hidden_size, hidden_size, bias=False)
        self.expansion_out = nn.Linear(hidden_size, 1)
        self.actor = nn.Linear(3 * hidden_size, n_params)

    def context(self, x: Tensor, task: Tensor) -> Context:
        """Context projections for observation encodings x [B, H] and task embeddings e [B, H]."""
        c = torch.cat([x, task], dim=-1)
        return Context(self.compose.project(c), self.decompose.project(c), self.expansion_context(c))

    def initial_memory(self, task: Tensor) -> Tensor:
        """[n, B, H]: LN(e) in the top slot, zeros below."""
        memory = task.new_zeros(self.n_slots, *task.shape)
        memory[-1] = F.layer_norm(task, (self.hidden_size,))
        return memory

    def cells(self) -> tuple[list[CellWeights], list[CellWeights]]:
        """The composition and decomposition cells' weights, for the steps of one pass (see `unbound`)."""
        return self.compose.unbound(), self.decompose.unbound()

    def _composed(self, memory: Tensor, x: Tensor, projected: Tensor, cells: list[CellWeights]) -> Tensor:
        """Bottom-up candidates [n, B, H]."""
        prepared = self.compose.prepare(projected, memory)
        candidates, chain = [], x
        for i in range(self.n_slots):
            chain = self.compose.cell(cells[i], chain, prepared[i], memory[i])
            candidates.append(chain)
        return torch.stack(candidates)

    def _expansion(self, memory: Tensor, candidates: Tensor, projected: Tensor) -> Tensor:
        """Expansion distribution p [n, B] from the stopping probabilities of the lower n-1 slots."""
        below_top = torch.cat([memory[:-1], candidates[:-1]], dim=-1)
        hidden = F.leaky_relu(self.expansion_memory(below_top) + projected)
        return stick_breaking(torch.sigmoid(self.expansion_out(hidden).squeeze(-1)))

    def _decomposed(self, candidates: Tensor, reached: Tensor, projected: Tensor, cells: list[CellWeights]) -> Tensor:
        """Top-down children [n, B, H] (zero for the top slot); reached [n, B, 1] = P(pos <= i)."""
        children = [torch.zeros_like(candidates[0])]
        for i in range(self.n_slots - 1, 0, -1):
            parent = reached[i] * candidates[i] + (1.0 - reached[i]) * children[-1]
            children.append(self.decompose.cell(cells[i - 1], parent, projected[i - 1]))
        return torch.stack(children[::-1])

    def step(
        self, memory: Tensor | None, x: Tensor, task: Tensor, context: Context,
        cells: tuple[list[CellWeights], list[CellWeights]] | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """One step from memory [n, B, H] (None: the episode starts now), x [B, H], e [B, H], with the
        cells of `cells()` (a pass of many steps gets them once).

        Returns the new memory [n, B, H], the expansion distribution p [n, B] and the actor's
        outputs [B, n_params].
        """
        composition, decomposition = cells or self.cells()
        if memory is None:
            memory = candidates = self.initial_memory(task)
            p = torch.zeros_like(memory[..., 0])
            p[-1] = 1.0
        else:
            candidates = self._composed(memory, x, context.composition, composition)
            p = self._expansion(memory, candidates, context.expansion)
        reached = p.cumsum(0).unsqueeze(-1)
        chosen = p.unsqueeze(-1)
        children = self._decomposed(candidates, reached, context.decomposition, decomposition)
        memory = (reached - chosen) * memory + chosen * candidates + (1.0 - reached) * children
        return memory, p, self.actor(self.actor_input(memory, task, x))

    @staticmethod
    def actor_input(memory: Tensor, task: Tensor, x: Tensor) -> Tensor:
        """What the actor reads [B, 3H]: the bottom slot, the task embedding and the observation."""
        return torch.cat([memory[0], task, x], dim=-1)

    def unroll(self, features: PackedSequence, task_index: Tensor, total_length: int) -> MemoryOutput:
        """Windows that each start an episode, packed (encoded observations of their real steps, rows
        sorted longest first, so the rows still running at step t are the first batch_sizes[t]), and
        tasks [B]. Outputs are padded back to [total_length, B, ...] in the original row order, with
        zeros past each row's end; no work is spent on the padding."""
        sizes = features.batch_sizes.tolist()
        task = self.task_embedding(task_index)[features.sorted_indices]
        rows = torch.cat([torch.arange(size, device=task.device) for size in sizes])
        x = self.obs_projection(features.data)
        memory, params, expansion, actor_input, cells = None, [], [], [], self.cells()
        steps = zip(x.split(sizes), self.context(x, task[rows]).split(sizes), strict=True)
        for x_t, context_t in steps:
            size = x_t.shape[0]
            memory, p, out = self.step(None if memory is None else memory[:, :size], x_t, task[:size], context_t,
                                       cells)
            params.append(out)
            expansion.append(p.transpose(0, 1))
            actor_input.append(self.actor_input(memory, task[:size], x_t))
        packed = [PackedSequence(torch.cat(parts), *features[1:]) for parts in (params, expansion, actor_input)]
        return MemoryOutput(*(pad_packed_sequence(part, total_length=total_length)[0] for part in packed))
