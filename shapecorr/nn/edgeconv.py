"""EdgeConv with residual MLP blocks over mesh edges, and the ResnetEC network of NeuroMorph.

NeuroMorph (Eisenberger et al., CVPR 2021, docs/neuromorph.md §3) uses one architecture, "ResnetECPos", for
both of its networks: a per-vertex linear lift, then a stack of EdgeConv layers (Wang et al., "Dynamic Graph
CNN", 2019) whose message function is a pre-activation residual MLP block

    block(m) = shortcut(m) + fc1(relu(fc0(relu(m)))),     m_ij = [u_i, u_j - u_i],

aggregated with a max over the mesh neighbours j of vertex i. Between layers the features are concatenated
with a pooled copy of themselves and with the network input.

Pooling: a deviation from the original code (docs/neuromorph.md §8). The original takes the max over dim 1 of
an ``(n, h)`` tensor, i.e. over the *channels* of each vertex (a batched ``(T, n, h)`` left-over). We default to
the paper's intent, a true **global max-pool over the vertices** (``pool="global"``): every vertex then
sees a descriptor of the whole shape. ``pool="channel"`` reproduces the original. Both give the layers the
same weight shapes, so checkpoints stay interchangeable in shape (not in meaning).

Channel layout. A layer after the first receives the per-vertex channels ``x = [net, p]`` (features and
network input) and the pooled channels ``s``, in this order: its message is ``[x_i, s_i, x_j - x_i,
s_j - s_i]``. (The original orders its concatenation ``[net, pool, p]``;
:func:`shapecorr.nn.neuromorph_weights.load_original_neuromorph_weights` permutes the input columns of ``fc0``
and ``shortcut`` accordingly.)

Fast path (``fast=True``, default). Exact algebraic restructurings of the same function (tests compare
it with the plain per-edge formulation, values and gradients, in float64):

1. ``shortcut`` is linear in m: ``Ws m_ij = (Wa - Wb) u_i + Wb u_j`` with ``Ws = [Wa | Wb]``. Both are
   per-vertex ``(n, .)`` products; the ``u_i`` term (and ``fc1``'s bias) is the same for every message of
   vertex i and moves out of the max.
2. ``fc0`` acts on ``relu(m) = [relu(u_i), relu(u_j - u_i)]`` (pre-activation: fc0 is *not* linear in m,
   contrary to a first reading of the block). But ``relu(u_j - u_i) = max(u_i, u_j) - u_i``, so
   ``fc0(relu(m_ij)) = [W0a relu(u_i) - W0b u_i + b0] + W0b max(u_i, u_j)``: a per-vertex term plus a
   per-edge term that is **symmetric** in (i, j). One GEMM per undirected edge serves both directions.
3. Pooled channels shared by all vertices (global pooling) have ``s_j - s_i = 0``: they enter only
   through per-vertex terms, and the per-edge GEMM runs on ``h + dim`` instead of ``2h + dim`` channels.
4. Duplicate edges do not change a max, so edges are passed deduplicated, once per undirected edge
   (:func:`shapecorr.geometry.mesh_graph.undirected_edges`); the original's face-listed edges count every
   interior edge twice per direction.
5. Channels constant over the vertices may be passed as shared channels whatever the layer was built with
   (only ``in + shared`` must match): the interpolator's time ``t`` is such a channel.
6. A batch whose elements differ only by a row added to every vertex (``u_b = x + o_b``, the first layer of
   the interpolator: ``fc_pos([x, Pi y - x, t_b])`` = base + ``t_b w``) shares all edge work:
   ``max(u_i, u_j) - u_i = max(x_i, x_j) - x_i``, so the edge GEMM, its gathers and the ``-W0b u_i`` term
   use the base once, and the shortcut products are the base product plus one row per batch element;
   only ``relu(u_b)`` needs every element (:meth:`ResnetEC.forward_separable`). With T + 1 = 8 time steps
   this removes 7/8 of the first layer's edge and per-vertex GEMMs.

Per layer, the per-edge work is one ``(E, c) x (c, h)`` GEMM (undirected edges) and the ``(2E, h) x (h, h)``
GEMM of ``fc1`` (directed messages), against ``(4E, 2c) x (2c, h)`` twice plus ``(4E, h) x (h, h)`` in the
original (E undirected edges, face-listed duplicates). The max aggregation is
``Tensor.scatter_reduce_(..., "amax", include_self=False)`` (native torch, no compiled extension). Two
backward passes are hand-written because torch's generic ones dominated the CPU profile (torch 2.13): the
max (torch's ``scatter_reduce`` backward over an expanded index, ~20x its forward) and ``torch.maximum``
(bool-mask selects, ~20x its forward); the per-edge half of the layer runs in one autograd node that reuses
its large buffers in place (in its backward the max mask's buffer takes the hidden gradient, and the first
half of the message gradient's buffer the edge gradient: every fresh large CPU buffer is a new ``mmap``
whose page faults cost about as much as the arithmetic on it; 10-15% of a layer, measured). Batched inputs
are flattened to rows, because scatters and gathers along dim -2 of 3-D tensors take a slow generic path on
CPU. (Tried and dropped, measured on the 2000-vertex benchmark mesh: messages grouped by receiver degree
so that the max is a dense reduction, where the max backward loses its two gathers but the edge term needs
one and the per-vertex sums get slower, 14.8 ms against 14.0 ms for these parts per layer; argmax indices
with element-wise gathers, 4x slower than the row gathers used; a vertex-major layout ``(n, B * c)`` for
batches, 10-20% faster gathers but not worth a second code path.)
``fast=False`` runs the plain per-edge formulation with torch's own autograd and is kept as the reference.

Shapes: features are ``(..., n, c)`` with any leading batch dimensions (e.g. the time steps of the
interpolator), ``edges`` is ``(E, 2)`` int64 of undirected vertex pairs; messages flow both ways.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from shapecorr.errors import ConfigError

#: Width of the hidden layers of both NeuroMorph networks (NeuroMorph code: ResnetECPos, hidden_dim=128).
DEFAULT_HIDDEN = 128
#: Number of EdgeConv layers of ResnetECPos (NeuroMorph code: block_0 plus four pooled blocks).
DEFAULT_N_BLOCKS = 5
#: Pooling modes: a true max over vertices (paper) or the original code's max over channels per vertex.
POOL_MODES = ("global", "channel")
#: Initialization of the residual branch's last layer ``fc1``: "zero" (weight and bias, ours: the block is exactly
#: its shortcut at initialization) or "original" (the NeuroMorph code, ResnetBlockFC: only the weight is zeroed,
#: the bias keeps torch's default uniform initialization, so the branch starts as a constant per channel).
RESIDUAL_INITS = ("zero", "original")


class ResnetBlockFC(nn.Module):
    """Pre-activation residual MLP block: ``shortcut(m) + fc1(relu(fc0(relu(m))))``.

    With ``residual_init="zero"`` (default) ``fc1`` (weight and bias) is zero-initialized, so at initialization
    the block is its shortcut. ``"original"`` zeroes ``fc1.weight`` only, as the NeuroMorph code does (the
    bias keeps torch's default initialization: the branch starts as a constant per output channel). Both draw
    the same random numbers (torch's default initialization of every layer, in the same order), so a seed gives
    the same ``fc0`` and shortcut either way. The shortcut is a bias-free linear map when the input and output
    widths differ, the identity otherwise.

    Parameters
    ----------
    in_channels, out_channels : int
    hidden_channels : int, optional
        Width of ``fc0``'s output; defaults to ``min(in_channels, out_channels)`` (NeuroMorph code).
    residual_init : {"zero", "original"}
    """

    def __init__(
        self, in_channels: int, out_channels: int, hidden_channels: int | None = None, residual_init: str = "zero"
    ):
        super().__init__()
        if residual_init not in RESIDUAL_INITS:
            raise ConfigError(f"residual_init must be one of {RESIDUAL_INITS}, got {residual_init!r}")
        hidden = min(in_channels, out_channels) if hidden_channels is None else hidden_channels
        self.in_channels, self.out_channels, self.hidden_channels = in_channels, out_channels, hidden
        self.fc0 = nn.Linear(in_channels, hidden)
        self.fc1 = nn.Linear(hidden, out_channels)
        nn.init.zeros_(self.fc1.weight)
        if residual_init == "zero":
            nn.init.zeros_(self.fc1.bias)
        self.shortcut = nn.Linear(in_channels, out_channels, bias=False) if in_channels != out_channels else None

    def forward(self, m: torch.Tensor) -> torch.Tensor:
        """Apply the block.

        Parameters
        ----------
        m : (..., in_channels) float

        Returns
        -------
        (..., out_channels) float
        """
        skip = m if self.shortcut is None else self.shortcut(m)
        return skip + self.fc1(F.relu(self.fc0(F.relu(m))))

    def shortcut_weight(self) -> torch.Tensor:
        """The shortcut as a matrix ``(out_channels, in_channels)`` (the identity when it is one)."""
        if self.shortcut is not None:
            return self.shortcut.weight
        return torch.eye(self.out_channels, dtype=self.fc0.weight.dtype, device=self.fc0.weight.device)


class _Graph(NamedTuple):
    """A validated undirected edge list: endpoints, which vertices have an edge, how many do."""

    a: torch.Tensor
    b: torch.Tensor
    has_edge: torch.Tensor  # (n, 1) bool
    n_receiving: int


def _edge_index(edges: torch.Tensor, n_verts: int, device: torch.device) -> _Graph:
    """Validate an undirected edge list once (the checks synchronize a GPU) for all layers using it."""
    if edges.ndim != 2 or edges.shape[1] != 2 or edges.shape[0] == 0:
        raise ConfigError(f"edges must be a non-empty (E, 2) index tensor, got shape {tuple(edges.shape)}")
    if edges.dtype.is_floating_point:
        raise ConfigError(f"edges must be integer indices, got dtype {edges.dtype}")
    edges = edges.to(device=device, dtype=torch.int64)
    if int(edges.min()) < 0 or int(edges.max()) >= n_verts:
        raise ConfigError(f"edges index vertices outside [0, {n_verts})")
    has_edge = torch.zeros(n_verts, 1, dtype=torch.bool, device=device)
    has_edge[edges.reshape(-1)] = True
    return _Graph(edges[:, 0], edges[:, 1], has_edge, int(has_edge.sum()))


def _flat_rows(index: torch.Tensor, n_rows: int, n_batch: int) -> torch.Tensor:
    """Row indices into a ``(n_batch * n_rows, c)`` flattening of ``(n_batch, n_rows, c)``: ``(n_batch * E,)``.

    Scatters and gathers along dim -2 of a 3-D tensor take a slow generic path on CPU (15x slower than the
    2-D row kernels for EdgeConv sizes, torch 2.13), so batched features are flattened to rows. ``n_rows = 0``
    repeats the index for every batch element (rows of a tensor shared by the batch).
    """
    if n_batch == 1:
        return index
    offsets = torch.arange(n_batch, device=index.device, dtype=index.dtype) * n_rows
    return (index.unsqueeze(0) + offsets.unsqueeze(1)).reshape(-1)


def _max_backward(
    grad_out: torch.Tensor,
    values: torch.Tensor,
    out: torch.Tensor,
    receivers: torch.Tensor,
    n_winners: int,
    keep_mask: bool = False,
):
    """Gradient of ``out = row-wise max of values (R, c) by receivers`` w.r.t. ``values``.

    The gradient flows to the value(s) equal to the maximum, split evenly among ties as in torch's own amax
    backward. The mask is a float tensor (``torch.eq`` with a float ``out=``): products and selects with bool
    masks are 3-8x slower on CPU (torch 2.13). Ties are counted only when there are more winners than
    (receiver, channel) pairs, which continuous data never produces (but identical neighbours do).
    ``keep_mask`` also returns the mask's buffer (``(R, c)``, free for reuse by the caller).
    """
    winners = out.index_select(0, receivers)
    torch.eq(values, winners, out=winners)
    if int(winners.sum()) != n_winners:
        counts = torch.zeros_like(grad_out).index_add_(0, receivers, winners)
        grad_out = grad_out / counts.clamp_min(1)
    grad = grad_out.index_select(0, receivers).mul_(winners)
    return (grad, winners) if keep_mask else grad


class _MaxAggregate(torch.autograd.Function):
    """Row-wise max of ``values (R, c)`` into ``(n_out, c)`` by ``receivers (R,)``, with a fast backward.

    Forward is ``Tensor.scatter_reduce_(0, ..., "amax", include_self=False)``. Its built-in backward is
    generic (several scatters and gathers over an expanded index) and was the largest single cost of a
    training step on CPU (about 40 ms of 45 ms for 15k x 128 values, one thread); here it is
    :func:`_max_backward`, a row gather and a mask.
    """

    @staticmethod
    def forward(ctx, values: torch.Tensor, receivers: torch.Tensor, n_out: int, n_winners: int):
        out = values.new_zeros(n_out, values.shape[1])
        out.scatter_reduce_(0, receivers.unsqueeze(1).expand_as(values), values, reduce="amax", include_self=False)
        ctx.save_for_backward(values, receivers, out)
        ctx.n_winners = n_winners
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        values, receivers, out = ctx.saved_tensors
        return _max_backward(grad_out, values, out, receivers, ctx.n_winners), None, None, None


class _GatherMax(torch.autograd.Function):
    """``max(x[ia], x[ib])`` row-wise for index pairs, with a cheap backward.

    ``torch.maximum``'s backward costs ~20x its forward on CPU (bool-mask selects, torch 2.13); here it is a
    float mask multiply and two row ``index_add_``. At exact ties the gradient goes to ``x[ia]`` (a valid
    subgradient).
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, ia: torch.Tensor, ib: torch.Tensor):
        xa, xb = x.index_select(0, ia), x.index_select(0, ib)
        b_wins = torch.empty_like(xa)
        torch.gt(xb, xa, out=b_wins)
        torch.maximum(xa, xb, out=xa)
        ctx.save_for_backward(ia, ib, b_wins)
        ctx.n_rows = x.shape[0]
        return xa

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        ia, ib, b_wins = ctx.saved_tensors
        grad_b = grad_out * b_wins
        grad_a = grad_out - grad_b
        grad_x = grad_out.new_zeros(ctx.n_rows, grad_out.shape[1])
        grad_x.index_add_(0, ia, grad_a).index_add_(0, ib, grad_b)
        return grad_x, None, None


class _MessagesMax(torch.autograd.Function):
    """The per-edge half of the fast EdgeConv, fused, with a hand-written backward.

    From per-vertex and per-edge pre-activations to the max-aggregated messages.

    ``out[r] = max_{k: receivers[k] = r} (neigh[senders[k]] + W1 relu(pre_vertex[receivers[k]] + edge[k mod E]))``

    per batch element; ``edge`` is ``(B * E, h)``, or ``(E, h)`` shared by the batch (``edge_shared``). Same
    math as composing torch ops, but every large ``(2E, h)`` buffer is reused in place where autograd would
    allocate a new one (a fresh large CPU buffer costs page faults comparable to the arithmetic on it), and
    the max gradient is :func:`_max_backward`.
    """

    @staticmethod
    def forward(ctx, pre_vertex, edge_term, neigh_term, w1, receivers, senders, n_batch, n_winners, edge_shared):
        # One dtype for the in-place arithmetic (under autocast the inputs may mix bfloat16 and float32;
        # autograd casts the returned gradients back to each input's dtype).
        dtype = functools.reduce(torch.promote_types, (pre_vertex.dtype, edge_term.dtype, neigh_term.dtype, w1.dtype))
        pre_vertex, edge_term, neigh_term, w1 = (t.to(dtype) for t in (pre_vertex, edge_term, neigh_term, w1))
        hid, out_ch = pre_vertex.shape[1], neigh_term.shape[1]
        hidden = pre_vertex.index_select(0, receivers)
        hidden.view(n_batch, 2, -1, hid).add_(edge_term.view(1 if edge_shared else n_batch, 1, -1, hid)).relu_()
        messages = neigh_term.index_select(0, senders).addmm_(hidden, w1.T)
        out = messages.new_zeros(neigh_term.shape[0], out_ch)
        out.scatter_reduce_(0, receivers.unsqueeze(1).expand_as(messages), messages, "amax", include_self=False)
        ctx.save_for_backward(hidden, messages, out, w1, receivers, senders)
        ctx.n_batch, ctx.n_winners, ctx.n_pre, ctx.edge_shared = n_batch, n_winners, pre_vertex.shape[0], edge_shared
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        hidden, messages, out, w1, receivers, senders = ctx.saved_tensors
        grad_msg, winners = _max_backward(grad_out, messages, out, receivers, ctx.n_winners, keep_mask=True)
        grad_neigh = torch.zeros_like(grad_out).index_add_(0, senders, grad_msg)
        grad_w1 = grad_msg.T @ hidden
        # The mask's buffer is free now (same shape when hidden and output widths agree, as in ResnetEC).
        grad_hidden = torch.mm(grad_msg, w1, out=winners if winners.shape[1] == w1.shape[1] else None)
        torch.ops.aten.threshold_backward.grad_input(grad_hidden, hidden, 0, grad_input=grad_hidden)
        hid = hidden.shape[1]
        n_edges = hidden.shape[0] // (2 * ctx.n_batch)
        halves = grad_hidden.view(ctx.n_batch, 2, n_edges, hid)
        if ctx.edge_shared:  # summed over both directions and the batch
            grad_edge = halves.sum((0, 1))
        elif grad_msg.shape[1] == hid:  # the two directions of each edge, into grad_msg's (free) buffer
            free = grad_msg.view(-1)[: ctx.n_batch * n_edges * hid].view(ctx.n_batch, n_edges, hid)
            grad_edge = torch.add(halves[:, 0], halves[:, 1], out=free).view(-1, hid)
        else:
            grad_edge = halves.sum(1).view(-1, hid)
        del grad_msg
        grad_pre = grad_hidden.new_zeros(ctx.n_pre, hid).index_add_(0, receivers, grad_hidden)
        return grad_pre, grad_edge, grad_neigh, grad_w1, None, None, None, None, None


def max_aggregate(values: torch.Tensor, receivers: torch.Tensor, n_verts: int) -> torch.Tensor:
    """Per-vertex max of per-edge values (the EdgeConv aggregation).

    Parameters
    ----------
    values : (..., E, c) float
        One row per directed message.
    receivers : (E,) int64
        Receiving vertex of each message.
    n_verts : int

    Returns
    -------
    (..., n_verts, c) float
        Max over the messages of each vertex; 0 for a vertex that receives none (the PyTorch Geometric
        convention). Differentiable once (the gradient goes to the maxima, split evenly among ties).
    """
    batch, c = values.shape[:-2], values.shape[-1]
    n_batch = math.prod(batch)
    rows = _flat_rows(receivers, n_verts, n_batch)
    n_winners = n_batch * c * int(torch.unique(receivers).numel())
    out = _MaxAggregate.apply(values.reshape(-1, c), rows, n_batch * n_verts, n_winners)
    return out.view(*batch, n_verts, c)


class EdgeConv(nn.Module):
    """EdgeConv layer: ``out_i = max_{j ~ i} block([u_i, u_j - u_i])`` with ``u = [x, s]``.

    Parameters
    ----------
    in_channels : int
        Per-vertex input channels ``x``.
    out_channels : int
    shared_channels : int
        Channels ``s`` of a vector shared by all vertices (a global pool), appended after ``x``; 0 for none.
    hidden_channels : int, optional
        Hidden width of the residual block (default ``min(2 (in + shared), out)``).
    residual_init : {"zero", "original"}
        See :class:`ResnetBlockFC`.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        shared_channels: int = 0,
        hidden_channels: int | None = None,
        residual_init: str = "zero",
    ):
        super().__init__()
        self.in_channels, self.out_channels, self.shared_channels = in_channels, out_channels, shared_channels
        self.block = ResnetBlockFC(2 * (in_channels + shared_channels), out_channels, hidden_channels, residual_init)

    def forward(
        self,
        x: torch.Tensor,
        edges: torch.Tensor,
        shared: torch.Tensor | None = None,
        fast: bool = True,
    ) -> torch.Tensor:
        """Apply the layer.

        Parameters
        ----------
        x : (..., n, in_channels) float
            Per-vertex features.
        edges : (E, 2) int64
            Undirected vertex pairs; messages flow both ways. Duplicates are allowed (they do not change the
            result, only the cost). A vertex in no edge gets the zero vector, as in PyTorch Geometric.
        shared : (..., shared_channels) float, optional
            Required when ``shared_channels > 0``: one vector per batch element, seen by every vertex.
        fast : bool
            Use the restructured computation (module docstring); False runs the plain per-edge reference.

        Returns
        -------
        (..., n, out_channels) float
        """
        if x.shape[-1] != self.in_channels:
            raise ConfigError(f"EdgeConv expects {self.in_channels} input channels, got {x.shape[-1]}")
        if (shared is None) != (self.shared_channels == 0):
            raise ConfigError(
                f"EdgeConv built with shared_channels={self.shared_channels} but shared="
                f"{'None' if shared is None else tuple(shared.shape)}"
            )
        if shared is not None and shared.shape != (*x.shape[:-2], self.shared_channels):
            raise ConfigError(
                f"shared must have shape {(*x.shape[:-2], self.shared_channels)}, got {tuple(shared.shape)}"
            )
        return self._apply_graph(x, _edge_index(edges, x.shape[-2], x.device), shared, fast)

    def _apply_graph(self, x: torch.Tensor, graph: _Graph, shared: torch.Tensor | None, fast: bool) -> torch.Tensor:
        if fast:
            return self._forward_fast(x, graph, shared)
        return self._forward_reference(x, graph.a, graph.b, shared)

    def _forward_reference(
        self, x: torch.Tensor, a: torch.Tensor, b: torch.Tensor, shared: torch.Tensor | None
    ) -> torch.Tensor:
        """Plain EdgeConv: the full block on every directed message, then the max (torch's own autograd)."""
        batch, n = x.shape[:-2], x.shape[-2]
        n_batch = math.prod(batch)
        u = x if shared is None else torch.cat((x, shared.unsqueeze(-2).expand(*x.shape[:-1], -1)), dim=-1)
        u = u.reshape(n_batch * n, -1)
        receivers = _flat_rows(torch.cat((a, b)), n, n_batch)
        senders = _flat_rows(torch.cat((b, a)), n, n_batch)
        u_i, u_j = u.index_select(0, receivers), u.index_select(0, senders)
        messages = self.block(torch.cat((u_i, u_j - u_i), dim=-1))
        out = messages.new_zeros(n_batch * n, self.out_channels)
        index = receivers.unsqueeze(1).expand_as(messages)
        out = out.scatter_reduce(0, index, messages, reduce="amax", include_self=False)
        return out.view(*batch, n, self.out_channels)

    def _forward_fast(
        self,
        x: torch.Tensor,
        graph: _Graph,
        shared: torch.Tensor | None,
        offset: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Restructured EdgeConv (module docstring, items 1-6); same function as the reference.

        ``x (..., n, c)`` and ``shared (..., s)`` with ``c + s`` the layer's input width: the split between
        per-vertex and shared channels may differ from the constructor's (channels constant over the vertices
        may be passed as shared ones). With ``offset (B, c)``, ``x (n, c)`` is a base shared by the batch and
        batch element b sees ``x + offset[b]`` (item 6).
        """
        blk = self.block
        if offset is None:
            batch, (n, c) = x.shape[:-2], x.shape[-2:]
        else:
            batch, (n, c) = offset.shape[:-1], x.shape
        n_batch = math.prod(batch)
        n_shared = 0 if shared is None else shared.shape[-1]
        cu = c + n_shared
        if cu != self.in_channels + self.shared_channels:
            raise ConfigError(f"EdgeConv expects {self.in_channels + self.shared_channels} channels, got {cu}")
        w_short = blk.shortcut_weight()
        w_sa, w_sb = w_short[:, :cu], w_short[:, cu:]
        w0a, w0b = blk.fc0.weight[:, :cu], blk.fc0.weight[:, cu:]
        out_ch, hid = self.out_channels, blk.hidden_channels

        # Per-vertex products: one GEMM for x (both shortcut halves and -W0b), one for relu(x).
        stacked = torch.cat((w_sa[:, :c] - w_sb[:, :c], w_sb[:, :c], -w0b[:, :c]), dim=0)
        if offset is None:
            x2 = x.reshape(n_batch * n, c)
            self_term, neigh_term, pre_vertex = torch.split(x2 @ stacked.T, (out_ch, out_ch, hid), dim=-1)
            pre_vertex = torch.addmm(pre_vertex + blk.fc0.bias, F.relu(x2), w0a[:, :c].T)
            edge_src, edge_shared = x2, False
        else:
            # u_b = x + o_b: the shortcut halves are linear (base product once, plus a row per batch element);
            # max(u_i, u_j) - u_i = max(x_i, x_j) - x_i does not depend on o_b, so the -W0b term and the edge
            # term use the base only; only relu(u_b) needs every batch element.
            prod = x @ stacked.T
            rows = offset.reshape(n_batch, 1, c) @ stacked[: 2 * out_ch].T
            self_term = (prod[:, :out_ch] + rows[..., :out_ch]).reshape(-1, out_ch)
            neigh_term = (prod[:, out_ch : 2 * out_ch] + rows[..., out_ch:]).reshape(-1, out_ch)
            relu_u = F.relu(x + offset.reshape(n_batch, 1, c))
            pre_vertex = (relu_u @ w0a[:, :c].T + (prod[:, 2 * out_ch :] + blk.fc0.bias)).reshape(-1, hid)
            edge_src, edge_shared = x, True
        # fc1's bias is the same for every message of a vertex: it moves out of the max.
        self_term = self_term + blk.fc1.bias
        if shared is not None:
            # s_j - s_i = 0: the shared channels act through w_sa (the w_sb parts of u_i and u_j cancel) and
            # through the relu(u_i) half of fc0 only.
            s2 = shared.reshape(n_batch, 1, n_shared)
            self_term = (self_term.view(n_batch, n, out_ch) + s2 @ w_sa[:, c:].T).view(-1, out_ch)
            pre_vertex = (pre_vertex.view(n_batch, n, hid) + F.relu(s2) @ w0a[:, c:].T).view(-1, hid)

        # fc0 of the message i <- j is W0a relu(x_i) + W0b relu(x_j - x_i) + b0, and relu(x_j - x_i) + x_i =
        # max(x_i, x_j): it equals pre_vertex_i + W0b max(x_i, x_j), whose per-edge part is symmetric in
        # (i, j): one GEMM per undirected edge serves both directions.
        n_src = 1 if edge_shared else n_batch
        fa, fb = _flat_rows(graph.a, n, n_src), _flat_rows(graph.b, n, n_src)
        edge_term = _GatherMax.apply(edge_src, fa, fb) @ w0b[:, :c].T
        # Directed messages in the order: all (receiver a <- sender b), then all (b <- a), per batch element.
        receivers = _flat_rows(torch.cat((graph.a, graph.b)), n, n_batch)
        senders = _flat_rows(torch.cat((graph.b, graph.a)), n, n_batch)
        n_winners = n_batch * out_ch * graph.n_receiving
        aggregated = _MessagesMax.apply(
            pre_vertex, edge_term, neigh_term, blk.fc1.weight, receivers, senders, n_batch, n_winners, edge_shared
        )
        # A vertex without edges gets 0 (no message), not its shortcut term.
        out = aggregated.view(n_batch, n, out_ch) + self_term.view(n_batch, n, out_ch) * graph.has_edge.to(x.dtype)
        return out.view(*batch, n, out_ch)


class ResnetEC(nn.Module):
    """NeuroMorph's ResnetECPos: a linear lift, ``n_blocks`` EdgeConv layers with pooling, a linear head.

    ``net = fc_pos(p)``; ``net = EdgeConv_0(net)``; then ``n_blocks - 1`` times
    ``net = EdgeConv_k([net, p], pooled=pool(net))``; output ``fc_out(relu(net))``.

    Parameters
    ----------
    in_channels : int
        Input channels per vertex (6 for the feature net: xyz + normal; 7 for the interpolator).
    out_channels : int
    hidden_channels : int
        Width ``h`` (the lift has 2h channels).
    n_blocks : int
        Number of EdgeConv layers (>= 1).
    pool : {"global", "channel"}
        Global max over vertices (default, the paper's intent) or the original code's per-vertex max over
        channels broadcast to h columns (module docstring).
    residual_init : {"zero", "original"}
        Initialization of the residual blocks (:class:`ResnetBlockFC`).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        hidden_channels: int = DEFAULT_HIDDEN,
        n_blocks: int = DEFAULT_N_BLOCKS,
        pool: str = "global",
        residual_init: str = "zero",
    ):
        super().__init__()
        if pool not in POOL_MODES:
            raise ConfigError(f"pool must be one of {POOL_MODES}, got {pool!r}")
        if n_blocks < 1:
            raise ConfigError(f"n_blocks must be >= 1, got {n_blocks}")
        h = hidden_channels
        self.in_channels, self.out_channels, self.pool = in_channels, out_channels, pool
        self.fc_pos = nn.Linear(in_channels, 2 * h)
        layers = [EdgeConv(2 * h, h, residual_init=residual_init)]
        for _ in range(n_blocks - 1):
            if pool == "global":
                layers.append(EdgeConv(h + in_channels, h, shared_channels=h, residual_init=residual_init))
            else:
                layers.append(EdgeConv(2 * h + in_channels, h, residual_init=residual_init))
        self.blocks = nn.ModuleList(layers)
        self.fc_out = nn.Linear(h, out_channels)

    def forward(self, p: torch.Tensor, edges: torch.Tensor, fast: bool = True) -> torch.Tensor:
        """Run the network.

        Parameters
        ----------
        p : (..., n, in_channels) float
        edges : (E, 2) int64
            Undirected mesh edges (:func:`shapecorr.geometry.mesh_graph.undirected_edges`).
        fast : bool
            Restructured EdgeConv (default) or the per-edge reference.

        Returns
        -------
        (..., n, out_channels) float
        """
        if p.shape[-1] != self.in_channels:
            raise ConfigError(f"ResnetEC expects {self.in_channels} input channels, got {p.shape[-1]}")
        graph = _edge_index(edges, p.shape[-2], p.device)
        net = self.blocks[0]._apply_graph(self.fc_pos(p), graph, None, fast)
        for layer in self.blocks[1:]:
            if self.pool == "global":
                net = layer._apply_graph(torch.cat((net, p), dim=-1), graph, net.amax(dim=-2), fast)
            else:
                pooled = net.amax(dim=-1, keepdim=True).expand_as(net)
                net = layer._apply_graph(torch.cat((net, p, pooled), dim=-1), graph, None, fast)
        return self.fc_out(F.relu(net))

    def forward_separable(
        self, p_static: torch.Tensor, p_batch: torch.Tensor, edges: torch.Tensor, fast: bool = True
    ) -> torch.Tensor:
        """Run the network on a batch whose inputs differ only in channels constant over the vertices.

        Batch element b gets the per-vertex input ``[p_static, p_batch[b]]`` (the last ``p_batch.shape[1]``
        input channels equal ``p_batch[b]`` at every vertex), e.g. NeuroMorph's interpolator, whose inputs
        ``[x, Pi y - x, t]`` differ between time steps only in ``t``. Same result as :meth:`forward` on the
        concatenated input; with ``fast`` and global pooling, the work that does not depend on b runs once
        (module docstring, item 6).

        Parameters
        ----------
        p_static : (n, c_s) float
        p_batch : (B, c_b) float
            ``c_s + c_b = in_channels``.
        edges : (E, 2) int64
        fast : bool

        Returns
        -------
        (B, n, out_channels) float
        """
        if p_static.ndim != 2 or p_batch.ndim != 2 or p_static.shape[1] + p_batch.shape[1] != self.in_channels:
            raise ConfigError(
                f"ResnetEC expects p_static (n, c_s) and p_batch (B, c_b) with c_s + c_b = {self.in_channels}, "
                f"got {tuple(p_static.shape)} and {tuple(p_batch.shape)}"
            )
        (n, c_s), n_b = p_static.shape, p_batch.shape[0]
        if not fast or self.pool != "global":
            p = torch.cat((p_static.expand(n_b, n, c_s), p_batch.unsqueeze(1).expand(n_b, n, -1)), dim=-1)
            return self.forward(p, edges, fast=fast)
        graph = _edge_index(edges, n, p_static.device)
        # fc_pos([p_static, p_batch[b]]) = (W_s p_static + bias) + W_b p_batch[b]: a base plus a row per b.
        base = F.linear(p_static, self.fc_pos.weight[:, :c_s], self.fc_pos.bias)
        offset = p_batch @ self.fc_pos.weight[:, c_s:].T
        net = self.blocks[0]._forward_fast(base, graph, None, offset=offset)
        p_static_b = p_static.expand(n_b, n, c_s)
        for layer in self.blocks[1:]:
            # Layer input [net, p_static, p_batch] + pooled: p_batch is constant over the vertices, so it
            # joins the shared channels (same channel order, hence the same weights).
            shared = torch.cat((p_batch, net.amax(dim=-2)), dim=-1)
            net = layer._forward_fast(torch.cat((net, p_static_b), dim=-1), graph, shared)
        return self.fc_out(F.relu(net))
