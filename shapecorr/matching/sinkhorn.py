"""Entropic optimal transport by a fixed number of Sinkhorn iterations (the Deep Shells soft matching).

Algorithm (Deep Shells, Eisenberger et al. NeurIPS 2020; methods-digest §2.3): given a cost matrix
``D (n, m) >= 0`` (squared distances of embeddings),

1. ``D <- D / mean(D)`` (scale invariance of the temperature);
2. ``log P = -D / (2 sigma^2)``;
3. ``num_iters`` times: normalize the rows of ``P`` to sum 1, then the columns (in the log domain);
4. a last row normalization gives ``plan`` (rows sum to 1); one more column normalization of that, transposed,
   gives ``plan_adj`` ``(m, n)`` (rows sum to 1).

With uniform marginals and few iterations the plans are not doubly stochastic; they are what the original
layer uses and what it backpropagates through (gradients of the unrolled iterations, not of the fixed point).

Implementation. Every normalization only changes a row potential ``u`` or a column potential ``v``:
``log P = L + u 1^T + 1 v^T`` with ``L = -D / (2 sigma^2 mean(D))``. :func:`sinkhorn` keeps ``u, v`` in
the log domain but applies the Gibbs kernel ``K = exp(L)`` (computed once, rows scaled to sum 1 -- a row
factor is absorbed by the first row normalization) by matrix-vector products,
``u = -log(K exp(v - c)) - c`` with ``c = max(v)``, which is exact and costs one pass over ``K`` instead of the
several passes of a ``logsumexp``. ``L <= 0``, so nothing overflows; rows whose sum underflows (every cost of
the row far above the mean, e.g. untrained high-dimensional features) are instead shifted by their maximum;
if a column still underflows (a point of Y whose costs to all of X exceed their nearest-neighbour costs by
more than ~43 (float32) or ~350 (float64) in units of ``2 sigma^2 mean(D)``) the call falls back to the plain
log-domain iterations of :func:`sinkhorn_log_reference`, which are exact in that regime too.
The backward pass is written by hand (a custom ``autograd.Function``): the gradient of the unrolled
iterations is ``dL = G_P * P + G_Q * Q - K * (sum_r a_r b_r^T)``, a sum of rank-one terms that are
accumulated as two thin ``(n, r)``, ``(m, r)`` factors (``r = 2 num_iters + 2``) and applied with one matrix
product; the potentials' adjoints need one matrix-vector product per normalization.

Memory (``n x m`` buffers): forward keeps the kernel ``K`` plus the two outputs (``plan``, ``plan_adj``,
which downstream matmuls keep alive anyway); :func:`sinkhorn` additionally keeps the input cost for the
gradient of ``mean(D)``, :func:`sinkhorn_sq_euclidean` does not (it never materializes the cost).
Backward allocates two more ``n x m`` temporaries (the gradient and the low-rank product). The plain
autograd version (:func:`sinkhorn_log_reference`) keeps ``2 num_iters + 3`` buffers for backward.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch.autograd.function import once_differentiable

from shapecorr.errors import ConfigError, NumericalError

#: Deep Shells ``sigma_sink`` (param.py DiffParam; stored in the released checkpoint's ``par``).
DEFAULT_SIGMA = 0.1
#: Deep Shells ``num_sink`` of the released checkpoint (DeepParam; DiffParam's default was 10).
DEFAULT_NUM_ITERS = 3


#: Kernel entries are kept within ``exp(0.7 * log(tiny))`` of their row maximum (~1e-27 in float32, ~1e-215 in
#: float64): far below the dtype's resolution, far above its subnormal range (slow arithmetic on x86).
_LOG_FLOOR_FRACTION = 0.7
#: Plan entries below ``tiny ** 0.7`` are flushed to 0 for the same reason.
_PLAN_FLOOR_EXPONENT = 0.7


class SinkhornPlans(NamedTuple):
    """The two row-stochastic soft maps of a Sinkhorn run.

    Attributes
    ----------
    plan : (n, m) float
        Soft map X -> Y, rows sum to 1.
    plan_adj : (m, n) float
        Soft map Y -> X, rows sum to 1.
    """

    plan: torch.Tensor
    plan_adj: torch.Tensor


class _KernelUnderflow(Exception):
    """A row or column of the Gibbs kernel underflowed; use the log-domain iterations instead."""


def pairwise_sq_dists(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean distances between two point sets, clamped at 0.

    Uses ``|x|^2 + |y|^2 - 2 x.y`` (one matrix product, no ``(n, m, d)`` intermediate); the rounding of that
    expansion can give tiny negative values, which are clamped to 0.

    Parameters
    ----------
    x : (n, d) float
    y : (m, d) float

    Returns
    -------
    (n, m) float
    """
    if x.dim() != 2 or y.dim() != 2 or x.shape[1] != y.shape[1]:
        raise ConfigError(f"pairwise_sq_dists: need (n, d) and (m, d), got {tuple(x.shape)} and {tuple(y.shape)}")
    d = torch.addmm((x * x).sum(1, keepdim=True), x, y.transpose(0, 1), alpha=-2.0)
    d = d + (y * y).sum(1)[None, :]
    return d.clamp_min(0.0)


def _check_args(sigma: float, num_iters: int) -> None:
    if not sigma > 0:
        raise ConfigError(f"sinkhorn: sigma must be positive, got {sigma}")
    if num_iters < 0:
        raise ConfigError(f"sinkhorn: num_iters must be >= 0, got {num_iters}")


def _check_mean(mean: torch.Tensor) -> None:
    value = float(mean)
    if value != value or value in (float("inf"), float("-inf")):
        raise NumericalError("sinkhorn: the cost matrix contains NaN or Inf")
    if value <= 0:
        raise NumericalError(
            "sinkhorn: the mean cost is zero (all embeddings coincide); the temperature D/mean(D) is undefined"
        )


def _neg_log_apply(kernel: torch.Tensor, log_pot: torch.Tensor, transpose: bool) -> torch.Tensor:
    """``-log(K exp(p))`` (or with ``K^T``) for a log-potential ``p``, shifting ``p`` by its max."""
    shift = log_pot.max()
    w = torch.exp(log_pot - shift)
    s = torch.mv(kernel.transpose(0, 1) if transpose else kernel, w)
    floor = torch.finfo(kernel.dtype).tiny ** 0.5
    # NaN also fails this test; the log-domain fallback then reports it.
    if not bool((s >= floor).all()):
        raise _KernelUnderflow
    return -(torch.log(s) + shift)


def _factors(u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``exp(u + c), exp(v - c)`` with ``c = max(v)``: ``K * outer`` of them is ``exp(L + u + v)``."""
    c = v.max()
    return torch.exp(u + c), torch.exp(v - c)


def _scaled_kernel(kernel: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The plan ``exp(L + u + v)``; entries below ``tiny**0.7`` (~1e-27 in float32) are set to 0 (subnormals)."""
    a, b = _factors(u, v)
    out = kernel * a[:, None]
    out.mul_(b[None, :])
    return torch.nn.functional.threshold_(out, torch.finfo(out.dtype).tiny ** _PLAN_FLOOR_EXPONENT, 0.0)


def _gibbs_kernel(log_kernel: torch.Tensor) -> torch.Tensor:
    """Row-shifted Gibbs kernel ``K = exp(max(L - rowmax(L), -F))``, in place.

    The iterations start with a row normalization, so a per-row factor of the kernel changes no plan (the
    first row potential absorbs it); with every row maximum at 1 nothing overflows or underflows for
    concentrated high-dimensional costs (every entry of a row far below 0, e.g. untrained features).
    Entries more than ``F`` below their row maximum (``exp(-F)`` is ~1e-27 in float32, far below float32
    resolution even summed over a row) are raised to ``exp(-F)``: on x86 CPUs, arithmetic on subnormal
    numbers is ~20-100x slower, and they would otherwise fill a few percent of every kernel.
    """
    floor = _LOG_FLOOR_FRACTION * math.log(torch.finfo(log_kernel.dtype).tiny)
    row_max = log_kernel.amax(1, keepdim=True)
    return torch.clamp(log_kernel, min=row_max + floor, out=log_kernel).sub_(row_max).exp_()


def _iterate(kernel: torch.Tensor, num_iters: int):
    """Forward iterations on the kernel; returns (plan, plan_adj^T, row potentials, column potentials)."""
    v = kernel.new_zeros(kernel.shape[1])
    us: list[torch.Tensor] = []
    vs: list[torch.Tensor] = [v]
    for _ in range(num_iters + 1):
        u = _neg_log_apply(kernel, v, transpose=False)
        v = _neg_log_apply(kernel, u, transpose=True)
        us.append(u)
        vs.append(v)
    # the last round is the final row normalization (-> plan) and one more column one (-> plan_adj)
    plan = _scaled_kernel(kernel, us[-1], vs[-2])
    plan_adj_t = _scaled_kernel(kernel, us[-1], vs[-1])
    return plan, plan_adj_t, us, vs


def _log_kernel_grad(kernel, plan, plan_adj_t, us, vs, g_plan, g_plan_adj_t):
    """Gradient w.r.t. the log-kernel ``L`` of the unrolled iterations (see the module docstring).

    Each normalization ``u = -logsumexp_j(L + v)`` has Jacobians ``-S`` (w.r.t. ``L``, row-broadcast) and
    ``-S`` (w.r.t. ``v``) with ``S = exp(L + u + v)`` the row-normalized plan of that step (columns alike).
    """
    n, m = kernel.shape
    num_iters = len(us) - 1
    u_star, v_adj = us[-1], vs[-1]
    v_last = vs[-2]
    zeros_m = kernel.new_zeros(m)
    if g_plan is None and g_plan_adj_t is None:
        return None
    v_bar = zeros_m
    v_adj_bar = zeros_m
    if g_plan is not None:
        grad = torch.mul(g_plan, plan)
        v_bar = grad.sum(0)
        if g_plan_adj_t is not None:
            # In place (one n x m buffer less); the column sums of the second term are the difference.
            v_adj_bar = grad.addcmul_(g_plan_adj_t, plan_adj_t).sum(0) - v_bar
    else:
        grad = torch.mul(g_plan_adj_t, plan_adj_t)
        v_adj_bar = grad.sum(0)
    u_bar = grad.sum(1)
    fa: list[torch.Tensor] = []
    fb: list[torch.Tensor] = []
    # v_adj = -logsumexp_i(L + u_star): its plan is plan_adj^T.
    a, b = _factors(u_star, v_adj)
    fa.append(a)
    fb.append(b * v_adj_bar)
    u_bar = u_bar - a * torch.mv(kernel, b * v_adj_bar)
    # u_star = -logsumexp_j(L + v_last): its plan is `plan`.
    a, b = _factors(u_star, v_last)
    fa.append(a * u_bar)
    fb.append(b)
    v_bar = v_bar - b * torch.mv(kernel.transpose(0, 1), a * u_bar)
    for t in reversed(range(num_iters)):
        u_t, v_t, v_prev = us[t], vs[t + 1], vs[t]
        a, b = _factors(u_t, v_t)
        fa.append(a)
        fb.append(b * v_bar)
        u_bar = -(a * torch.mv(kernel, b * v_bar))
        a, b = _factors(u_t, v_prev)
        fa.append(a * u_bar)
        fb.append(b)
        if t > 0:
            v_bar = -(b * torch.mv(kernel.transpose(0, 1), a * u_bar))
    low_rank = torch.stack(fa, 1) @ torch.stack(fb, 1).transpose(0, 1)
    return grad.addcmul_(kernel, low_rank, value=-1.0)


class _SinkhornCost(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cost, sigma, num_iters):
        mean = cost.mean()
        _check_mean(mean)
        scale = 1.0 / (2.0 * sigma * sigma * float(mean))
        kernel = _gibbs_kernel(cost * (-scale))
        plan, plan_adj_t, us, vs = _iterate(kernel, num_iters)
        plan_adj = plan_adj_t.transpose(0, 1)
        ctx.save_for_backward(cost, kernel, plan, plan_adj)
        ctx.potentials = (us, vs)
        ctx.scale, ctx.mean = scale, float(mean)
        return plan, plan_adj

    @staticmethod
    @once_differentiable
    def backward(ctx, g_plan, g_plan_adj):
        cost, kernel, plan, plan_adj = ctx.saved_tensors
        us, vs = ctx.potentials
        g_adj_t = None if g_plan_adj is None else g_plan_adj.transpose(0, 1)
        lbar = _log_kernel_grad(kernel, plan, plan_adj.transpose(0, 1), us, vs, g_plan, g_adj_t)
        if lbar is None:
            return None, None, None
        # L = -scale * D with scale = 1/(2 sigma^2 mean(D)):  dL/dD = -scale, dL/dmean = scale * D / mean.
        inner = torch.einsum("ij,ij->", lbar, cost)
        const = ctx.scale * float(inner) / (ctx.mean * cost.numel())
        return lbar.mul_(-ctx.scale).add_(const), None, None


class _SinkhornSqEuclidean(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, sigma, num_iters):
        xx = (x * x).sum(1)
        yy = (y * y).sum(1)
        # mean_ij |x_i - y_j|^2 without forming the matrix.
        mean = xx.mean() + yy.mean() - 2.0 * torch.dot(x.mean(0), y.mean(0))
        _check_mean(mean)
        scale = 1.0 / (2.0 * sigma * sigma * float(mean))
        # log K = -scale * (|x|^2 + |y|^2 - 2 x.y) as one product of augmented matrices
        # [x, |x|^2, 1] [2 s y, -s, -s |y|^2]^T (rounding can make it slightly positive: K <= 1 + ~1e-6).
        ones_x, ones_y = x.new_ones(x.shape[0], 1), y.new_ones(y.shape[0], 1)
        left = torch.cat([x, xx[:, None], ones_x], 1)
        right = torch.cat([y * (2.0 * scale), ones_y * -scale, (yy * -scale)[:, None]], 1)
        kernel = _gibbs_kernel(left @ right.transpose(0, 1))
        plan, plan_adj_t, us, vs = _iterate(kernel, num_iters)
        plan_adj = plan_adj_t.transpose(0, 1)
        ctx.save_for_backward(x, y, kernel, plan, plan_adj)
        ctx.potentials = (us, vs)
        ctx.scale, ctx.mean = scale, float(mean)
        return plan, plan_adj

    @staticmethod
    @once_differentiable
    def backward(ctx, g_plan, g_plan_adj):
        x, y, kernel, plan, plan_adj = ctx.saved_tensors
        us, vs = ctx.potentials
        g_adj_t = None if g_plan_adj is None else g_plan_adj.transpose(0, 1)
        lbar = _log_kernel_grad(kernel, plan, plan_adj.transpose(0, 1), us, vs, g_plan, g_adj_t)
        if lbar is None:
            return None, None, None, None
        n, m = lbar.shape
        s = ctx.scale
        # row/column sums of Lbar come with the products (one pass over Lbar each)
        ly = lbar @ torch.cat([y, y.new_ones(m, 1)], 1)  # (n, d + 1)
        ltx = lbar.transpose(0, 1) @ torch.cat([x, x.new_ones(n, 1)], 1)  # (m, d + 1)
        rs, ly = ly[:, -1], ly[:, :-1]
        cs, ltx = ltx[:, -1], ltx[:, :-1]
        xx, yy = (x * x).sum(1), (y * y).sum(1)
        # sum_ij Lbar_ij D_ij, with D = |x|^2 + |y|^2 - 2 x.y
        inner = torch.dot(rs, xx) + torch.dot(cs, yy) - 2.0 * (x * ly).sum()
        const = s * inner / (ctx.mean * n * m)  # = dmean-term: Dbar = -s Lbar + const
        # Dbar = -s * Lbar + const; x_bar_i = 2 (sum_j Dbar_ij x_i - (Dbar y)_i), y_bar alike.
        row = -s * rs + const * m
        col = -s * cs + const * n
        x_bar = 2.0 * (row[:, None] * x - (-s * ly + const * y.sum(0)[None, :]))
        y_bar = 2.0 * (col[:, None] * y - (-s * ltx + const * x.sum(0)[None, :]))
        return x_bar, y_bar, None, None


def sinkhorn_log_reference(
    cost: torch.Tensor, sigma: float = DEFAULT_SIGMA, num_iters: int = DEFAULT_NUM_ITERS
) -> SinkhornPlans:
    """Plain log-domain Sinkhorn with autograd (the original algorithm, op by op).

    Slower and ``O(num_iters)`` times more memory-hungry than :func:`sinkhorn`; kept as the test oracle and
    as the fallback where the kernel underflows.

    Parameters
    ----------
    cost : (n, m) float
        Non-negative cost.
    sigma, num_iters
        See :func:`sinkhorn`.

    Returns
    -------
    SinkhornPlans
        ``plan (n, m)`` and ``plan_adj (m, n)``, both row-stochastic.
    """
    _check_args(sigma, num_iters)
    mean = cost.mean()
    _check_mean(mean.detach())
    log_p = cost / mean * (-1.0 / (2.0 * sigma * sigma))
    for _ in range(num_iters):
        log_p = log_p - torch.logsumexp(log_p, dim=1, keepdim=True)
        log_p = log_p - torch.logsumexp(log_p, dim=0, keepdim=True)
    log_p = log_p - torch.logsumexp(log_p, dim=1, keepdim=True)
    plan = torch.exp(log_p)
    plan_adj = torch.exp(log_p - torch.logsumexp(log_p, dim=0, keepdim=True)).transpose(0, 1)
    if not (torch.isfinite(plan).all() and torch.isfinite(plan_adj).all()):
        raise NumericalError("sinkhorn: the transport plan contains NaN or Inf")
    return SinkhornPlans(plan, plan_adj)


def sinkhorn(
    cost: torch.Tensor, sigma: float = DEFAULT_SIGMA, num_iters: int = DEFAULT_NUM_ITERS
) -> SinkhornPlans:
    """Deep Shells Sinkhorn on a cost matrix (log-domain potentials, hand-written backward).

    Parameters
    ----------
    cost : (n, m) float
        Non-negative cost, e.g. :func:`pairwise_sq_dists` of two embeddings. It is divided by its mean.
    sigma : float
        Temperature: ``log P = -cost / mean(cost) / (2 sigma^2)``.
    num_iters : int
        Number of (row, column) normalization rounds before the final row normalization.

    Returns
    -------
    SinkhornPlans
        ``plan (n, m)`` rows sum to 1 (soft map X -> Y), ``plan_adj (m, n)`` rows sum to 1 (Y -> X).

    Raises
    ------
    NumericalError
        If the cost contains NaN/Inf or is identically zero.

    Notes
    -----
    Memory: see the module docstring (kernel + cost + outputs kept for backward).
    """
    _check_args(sigma, num_iters)
    if cost.dim() != 2:
        raise ConfigError(f"sinkhorn: cost must be (n, m), got {tuple(cost.shape)}")
    try:
        plan, plan_adj = _SinkhornCost.apply(cost, float(sigma), int(num_iters))
    except _KernelUnderflow:
        return sinkhorn_log_reference(cost, sigma, num_iters)
    return SinkhornPlans(plan, plan_adj)


def sinkhorn_sq_euclidean(
    x: torch.Tensor, y: torch.Tensor, sigma: float = DEFAULT_SIGMA, num_iters: int = DEFAULT_NUM_ITERS
) -> SinkhornPlans:
    """:func:`sinkhorn` on the squared Euclidean distances of two embeddings, without forming the cost.

    Equal to ``sinkhorn(pairwise_sq_dists(x, y), sigma, num_iters)`` up to rounding, one ``(n, m)``
    buffer and a few passes cheaper; gradients flow to ``x`` and ``y``.

    Parameters
    ----------
    x : (n, d) float
    y : (m, d) float
    sigma, num_iters
        See :func:`sinkhorn`.

    Returns
    -------
    SinkhornPlans
        ``plan (n, m)``, ``plan_adj (m, n)``, both row-stochastic.
    """
    _check_args(sigma, num_iters)
    if x.dim() != 2 or y.dim() != 2 or x.shape[1] != y.shape[1]:
        raise ConfigError(f"sinkhorn_sq_euclidean: need (n, d) and (m, d), got {tuple(x.shape)}, {tuple(y.shape)}")
    if x.dtype != y.dtype:
        raise ConfigError(f"sinkhorn_sq_euclidean: dtype mismatch {x.dtype} vs {y.dtype}")
    try:
        plan, plan_adj = _SinkhornSqEuclidean.apply(x, y, float(sigma), int(num_iters))
    except _KernelUnderflow:
        return sinkhorn_log_reference(pairwise_sq_dists(x, y), sigma, num_iters)
    return SinkhornPlans(plan, plan_adj)
