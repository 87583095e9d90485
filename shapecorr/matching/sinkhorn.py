"""Entropic optimal transport by a fixed number of Sinkhorn iterations (the Deep Shells soft matching).

Algorithm (Deep Shells, Eisenberger et al. NeurIPS 2020; docs/deep_shells.md §5): given a cost matrix
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

Plan-free form (:func:`sinkhorn_sq_euclidean_products`). Where the plans are only used through products
with thin matrices (the Deep Shells layer: ``P [Y_k, Phi_Y]``, ``P_adj [X*, Phi_X]``), they are never formed:
with ``P = diag(a) K diag(b)``, ``P V = (K (b * V)) / (K b)``, which is the last row normalization and the
product in one thin product with ``K``. Backward is in low-rank form: the plans' gradients ``G V^T`` have the
rank of the values, so ``dL = K * (A B^T)`` with thin ``A, B`` (the dense terms and the rank-one terms of the
unrolled normalizations together), and the sums the potentials' adjoints need are thin products with ``K``.
With ``num_iters = 3`` that is 9 passes over an ``n x m`` matrix forward (kernel, 6 matrix-vector and 2
thin products) and 10 backward (kernel rebuilt, see below), instead of ~22 and ~20 with the plans formed.

Memory (``n x m`` buffers): :func:`sinkhorn` / :func:`sinkhorn_sq_euclidean` keep the kernel ``K`` plus the
two outputs (``plan``, ``plan_adj``, which downstream matmuls keep alive anyway); :func:`sinkhorn` additionally
keeps the input cost for the gradient of ``mean(D)``, :func:`sinkhorn_sq_euclidean` does not (it never
materializes the cost). Their backward allocates two more ``n x m`` temporaries (the gradient and the
low-rank product). :func:`sinkhorn_sq_euclidean_products` keeps none: backward rebuilds ``K`` from the thin
factors of ``log K`` (a product and an exponential, in row blocks that stay in the L2 cache, bitwise equal to
the forward one) and writes the gradient into it; so a multi-level layer holds one ``n x m`` buffer at a
time (on CPUs this also avoids the page faults of a fresh 16 MB buffer per level, ~7 ms each here). The
plain autograd version (:func:`sinkhorn_log_reference`) keeps ``2 num_iters + 3`` buffers for backward.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch.autograd.function import once_differentiable

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.finiteness import all_finite

#: Deep Shells ``sigma_sink`` (param.py DiffParam; stored in the released checkpoint's ``par``).
DEFAULT_SIGMA = 0.1
#: Deep Shells ``num_sink`` of the released checkpoint (DeepParam; DiffParam's default was 10).
DEFAULT_NUM_ITERS = 3


#: Kernel entries are kept within ``exp(0.7 * log(tiny))`` of their row maximum (~1e-27 in float32, ~1e-215 in
#: float64): far below the dtype's resolution, far above its subnormal range (slow arithmetic on x86).
_LOG_FLOOR_FRACTION = 0.7
#: Plan entries below ``tiny ** 0.7`` are flushed to 0 for the same reason.
_PLAN_FLOOR_EXPONENT = 0.7
#: Size of the row blocks in which the kernel is built on CPUs (1 MiB: half of a typical 2 MB per-core L2).
_BLOCK_BYTES = 1 << 20


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


class SinkhornProducts(NamedTuple):
    """Soft maps applied to values (:func:`sinkhorn_sq_euclidean_products`).

    Attributes
    ----------
    py : (n, p) float
        ``plan @ values_y``: values of Y transported to X.
    qx : (m, q) float
        ``plan_adj @ values_x``: values of X transported to Y.
    plan : (n, m) float or None
        The plan itself (detached), if requested.
    plan_adj : (m, n) float or None
    """

    py: torch.Tensor
    qx: torch.Tensor
    plan: torch.Tensor | None
    plan_adj: torch.Tensor | None


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


def _sq_euclidean_kernel(x: torch.Tensor, y: torch.Tensor, sigma: float):
    """Gibbs kernel of the squared distances without forming them; returns ``(K, scale, mean)``."""
    left, right, scale, mean = _sq_euclidean_factors(x, y, sigma)
    return _blocked_gibbs_kernel(left, right), scale, mean


def _sq_euclidean_factors(x: torch.Tensor, y: torch.Tensor, sigma: float):
    """Thin ``left, right`` with ``left @ right^T = L`` (the log-kernel), and ``(scale, mean)``."""
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
    return left, right, scale, float(mean)


def _row_block(n: int, m: int, like: torch.Tensor) -> int:
    """Rows per block of an ``n x m`` matrix so that a block stays in the L2 cache (all rows off the CPU)."""
    if like.device.type != "cpu":
        return max(1, n)
    return max(1, _BLOCK_BYTES // max(1, m * like.element_size()))


def _blocked_gibbs_kernel(left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """:func:`_gibbs_kernel` of ``left @ right^T``, built in row blocks that stay in the CPU's L2 cache.

    The row maximum, shift, floor and exponential then run on cached data instead of four passes over the
    ``n x m`` matrix (~1.6x faster for 2000 x 2000 on a 2 MB-L2 Xeon). One block on other devices.
    """
    n, m = left.shape[0], right.shape[0]
    kernel = left.new_empty(n, m)
    rows = _row_block(n, m, left)
    floor = _LOG_FLOOR_FRACTION * math.log(torch.finfo(left.dtype).tiny)
    right_t = right.transpose(0, 1)
    for start in range(0, n, rows):
        block = kernel[start:start + rows]
        torch.mm(left[start:start + rows], right_t, out=block)
        block.sub_(block.amax(1, keepdim=True)).clamp_min_(floor).exp_()
    return kernel


def _thin_t(kernel: torch.Tensor, thin: torch.Tensor) -> torch.Tensor:
    """``K^T @ thin`` as ``(thin^T K)^T``: BLAS is ~1.5x faster with the long dimension of K contiguous."""
    return (thin.transpose(0, 1) @ kernel).transpose(0, 1)


def _sq_euclidean_input_grads(lbar, x, y, scale, mean, need_x, need_y):
    """Gradients w.r.t. ``x``, ``y`` of ``L = -D / (2 sigma^2 mean(D))``, ``D = |x_i - y_j|^2``, given ``Lbar``.

    Includes the gradient through ``mean(D)``; one thin product over ``Lbar`` per side that needs a gradient
    (the sums the mean's gradient needs come with it).
    """
    n, m = lbar.shape
    s = scale
    xx, yy = (x * x).sum(1), (y * y).sum(1)
    # sum_ij Lbar_ij D_ij = sum_i rs_i |x_i|^2 + sum_j cs_j |y_j|^2 - 2 sum_ij Lbar_ij x_i.y_j (rs, cs: row and
    # column sums); each side's product with Lbar also gives the other side's squared-norm term.
    ly = ltx = None
    if need_x or not need_y:
        ly = lbar @ torch.cat([y, y.new_ones(m, 1), yy[:, None]], 1)  # (n, d + 2)
        rs, y_term, ly = ly[:, -2], ly[:, -1].sum(), ly[:, :-2]
        inner = torch.dot(rs, xx) + y_term - 2.0 * (x * ly).sum()
    if need_y:
        ltx = _thin_t(lbar, torch.cat([x, x.new_ones(n, 1), xx[:, None]], 1))  # (m, d + 2)
        cs, x_term, ltx = ltx[:, -2], ltx[:, -1].sum(), ltx[:, :-2]
        if ly is None:
            inner = torch.dot(cs, yy) + x_term - 2.0 * (y * ltx).sum()
    const = s * inner / (mean * n * m)  # = dmean-term: Dbar = -s Lbar + const
    # Dbar = -s * Lbar + const; x_bar_i = 2 (sum_j Dbar_ij x_i - (Dbar y)_i), y_bar alike.
    x_bar = y_bar = None
    if need_x:
        row = -s * rs + const * m
        x_bar = 2.0 * (row[:, None] * x - (-s * ly + const * y.sum(0)[None, :]))
    if need_y:
        col = -s * cs + const * n
        y_bar = 2.0 * (col[:, None] * y - (-s * ltx + const * x.sum(0)[None, :]))
    return x_bar, y_bar


def _normalize_and_apply(kernel: torch.Tensor, log_pot: torch.Tensor, values: torch.Tensor, transpose: bool):
    """The last normalization of a side fused with its plan's product with ``values``.

    With ``w = exp(p - max p)``: the new potential is ``-log(K w) - max p`` and the normalized plan applied
    to ``values`` is ``(K (w * values)) / (K w)`` (``K^T`` if ``transpose``): one thin product.
    """
    shift = log_pot.max()
    w = torch.exp(log_pot - shift)[:, None]
    rhs = torch.cat([w, w * values], 1)
    z = _thin_t(kernel, rhs) if transpose else kernel @ rhs
    s = z[:, 0]
    if not bool((s >= torch.finfo(kernel.dtype).tiny ** 0.5).all()):
        raise _KernelUnderflow
    return -(torch.log(s) + shift), z[:, 1:] / s[:, None]


def _iterate_products(kernel, num_iters, values_y, values_x):
    """Forward iterations; returns ``(plan @ values_y, plan_adj @ values_x, us, vs)`` (plans not formed)."""
    v = kernel.new_zeros(kernel.shape[1])
    us: list[torch.Tensor] = []
    vs: list[torch.Tensor] = [v]
    for _ in range(num_iters):
        u = _neg_log_apply(kernel, v, transpose=False)
        v = _neg_log_apply(kernel, u, transpose=True)
        us.append(u)
        vs.append(v)
    u, py = _normalize_and_apply(kernel, v, values_y, transpose=False)
    v_adj, qx = _normalize_and_apply(kernel, u, values_x, transpose=True)
    us.append(u)
    vs.append(v_adj)
    return py, qx, us, vs


def _products_log_kernel_grad(kernel, us, vs, values_y, values_x, py, qx, g_py, g_qx):
    """:func:`_log_kernel_grad` for outputs ``py = P values_y``, ``qx = P_adj values_x``, in low-rank form.

    With ``P = K * (alpha beta^T)`` and ``P_adj^T = K * (alpha' beta'^T)``, the plans' gradients
    ``g_py values_y^T`` and ``values_x g_qx^T`` are rank-``p`` and rank-``q``, so every term of ``Lbar`` is
    ``K * (a b^T)`` with thin ``a, b``, and the row/column sums the potentials' adjoints need are thin products
    with ``K``. Returns ``(Lbar, grad values_y, grad values_x)`` (``None`` where no gradient arrives);
    ``Lbar`` is written into ``kernel``'s memory (the kernel is destroyed).
    """
    if g_py is None and g_qx is None:
        return None, None, None
    n, m = kernel.shape
    num_iters = len(us) - 1
    u_star, v_last, v_adj = us[-1], vs[-2], vs[-1]
    fa: list[torch.Tensor] = []  # Lbar = K * (cat(fa) @ cat(fb)^T), columns of (n, .) and (m, .)
    fb: list[torch.Tensor] = []
    gv_x = gv_y = None
    u_bar = kernel.new_zeros(n)
    if g_qx is not None:
        a, b = _factors(u_star, v_adj)
        v_adj_bar = (g_qx * qx).sum(1)  # column sums of (values_x g_qx^T) * P_adj^T
        z = kernel @ torch.cat([b[:, None] * g_qx, (b * v_adj_bar)[:, None]], 1)
        gv_x = a[:, None] * z[:, :-1]  # P_adj^T g_qx
        # v_adj = -logsumexp_i(L + u_star): its plan is P_adj^T.
        u_bar = (values_x * gv_x).sum(1) - a * z[:, -1]
        fa += [a[:, None] * values_x, -a[:, None]]
        fb += [b[:, None] * g_qx, (b * v_adj_bar)[:, None]]
    a, b = _factors(u_star, v_last)
    if g_py is not None:
        u_bar = u_bar + (g_py * py).sum(1)
        au = (a * u_bar)[:, None]
        z = _thin_t(kernel, torch.cat([a[:, None] * g_py, au], 1))
        gv_y = b[:, None] * z[:, :-1]  # P^T g_py
        # u_star = -logsumexp_j(L + v_last): its plan is P.
        v_bar = (values_y * gv_y).sum(1) - b * z[:, -1]
        fa += [a[:, None] * g_py, -au]
        fb += [b[:, None] * values_y, b[:, None]]
    else:
        v_bar = -(b * torch.mv(kernel.transpose(0, 1), a * u_bar))
        fa.append(-(a * u_bar)[:, None])
        fb.append(b[:, None])
    for t in reversed(range(num_iters)):
        u_t, v_t, v_prev = us[t], vs[t + 1], vs[t]
        a, b = _factors(u_t, v_t)
        fa.append(-a[:, None])
        fb.append((b * v_bar)[:, None])
        u_bar = -(a * torch.mv(kernel, b * v_bar))
        a, b = _factors(u_t, v_prev)
        fa.append(-(a * u_bar)[:, None])
        fb.append(b[:, None])
        if t > 0:
            v_bar = -(b * torch.mv(kernel.transpose(0, 1), a * u_bar))
    # Lbar overwrites the kernel, row block by row block (the low-rank block stays in cache).
    fa_all, fb_t = torch.cat(fa, 1), torch.cat(fb, 1).transpose(0, 1)
    rows = _row_block(n, m, kernel)
    for start in range(0, n, rows):
        kernel[start:start + rows].mul_(fa_all[start:start + rows] @ fb_t)
    return kernel, gv_y, gv_x


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
        kernel, scale, mean = _sq_euclidean_kernel(x, y, sigma)
        plan, plan_adj_t, us, vs = _iterate(kernel, num_iters)
        plan_adj = plan_adj_t.transpose(0, 1)
        ctx.save_for_backward(x, y, kernel, plan, plan_adj)
        ctx.potentials = (us, vs)
        ctx.scale, ctx.mean = scale, mean
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
        x_bar, y_bar = _sq_euclidean_input_grads(lbar, x, y, ctx.scale, ctx.mean, *ctx.needs_input_grad[:2])
        return x_bar, y_bar, None, None


class _SinkhornProducts(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, values_y, values_x, sigma, num_iters, return_plans):
        left, right, scale, mean = _sq_euclidean_factors(x, y, sigma)
        kernel = _blocked_gibbs_kernel(left, right)
        py, qx, us, vs = _iterate_products(kernel, num_iters, values_y, values_x)
        if return_plans:
            plan = _scaled_kernel(kernel, us[-1], vs[-2])
            plan_adj = _scaled_kernel(kernel, us[-1], vs[-1]).transpose(0, 1)
        else:
            plan = plan_adj = kernel.new_empty(0)
        del kernel  # rebuilt in backward from the thin factors (bitwise the same: same blocks, same ops)
        ctx.mark_non_differentiable(plan, plan_adj)
        ctx.set_materialize_grads(False)  # an unused output gets None, not a zero gradient to work through
        ctx.save_for_backward(x, y, values_y, values_x, left, right, py, qx)
        ctx.potentials = (us, vs)
        ctx.scale, ctx.mean = scale, mean
        return py, qx, plan, plan_adj

    @staticmethod
    @once_differentiable
    def backward(ctx, g_py, g_qx, _g_plan, _g_plan_adj):
        x, y, values_y, values_x, left, right, py, qx = ctx.saved_tensors
        us, vs = ctx.potentials
        if g_py is None and g_qx is None:
            return None, None, None, None, None, None, None
        kernel = _blocked_gibbs_kernel(left, right)
        lbar, gv_y, gv_x = _products_log_kernel_grad(kernel, us, vs, values_y, values_x, py, qx, g_py, g_qx)
        need = ctx.needs_input_grad
        x_bar = y_bar = None
        if lbar is not None and (need[0] or need[1]):
            x_bar, y_bar = _sq_euclidean_input_grads(lbar, x, y, ctx.scale, ctx.mean, need[0], need[1])
        return x_bar, y_bar, gv_y if need[2] else None, gv_x if need[3] else None, None, None, None


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
    if not all_finite(plan, plan_adj):
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


def sinkhorn_sq_euclidean_products(
    x: torch.Tensor,
    y: torch.Tensor,
    values_y: torch.Tensor,
    values_x: torch.Tensor,
    sigma: float = DEFAULT_SIGMA,
    num_iters: int = DEFAULT_NUM_ITERS,
    return_plans: bool = False,
) -> SinkhornProducts:
    """The soft maps of :func:`sinkhorn_sq_euclidean` applied to values, without forming the plans.

    ``plan @ values_y`` and ``plan_adj @ values_x`` are what the Deep Shells layer needs of the plans; with
    ``P = diag(a) K diag(b)`` they are thin products with the Gibbs kernel (the last row normalization and
    the product share one pass over ``K``), and the backward pass is in low-rank form: the plans' gradients
    are rank ``p`` and ``q``, so the gradient w.r.t. the log-kernel is ``K * (A B^T)`` with thin ``A, B``
    (module docstring). Equal to ``plans.plan @ values_y`` etc. up to rounding; gradients flow to ``x``,
    ``y``, ``values_y`` and ``values_x``. No ``n x m`` buffer is kept for backward: the kernel is rebuilt
    there from thin factors (one matrix product and an exponential, cheaper on CPUs than keeping a fresh
    buffer per call alive) and the gradient overwrites it.

    Parameters
    ----------
    x : (n, d) float
    y : (m, d) float
    values_y : (m, p) float
        Values on Y to transport to X (e.g. ``[Y_k, Phi_Y]``).
    values_x : (n, q) float
        Values on X to transport to Y.
    sigma, num_iters
        See :func:`sinkhorn`.
    return_plans : bool
        Also form the two plans (detached: no gradient flows through them; two extra ``n x m`` buffers).

    Returns
    -------
    SinkhornProducts
        ``py (n, p)``, ``qx (m, q)``; ``plan (n, m)`` and ``plan_adj (m, n)`` if ``return_plans`` else None.
    """
    _check_args(sigma, num_iters)
    if x.dim() != 2 or y.dim() != 2 or x.shape[1] != y.shape[1]:
        raise ConfigError(f"sinkhorn_sq_euclidean_products: need (n, d) and (m, d), got {tuple(x.shape)}, "
                          f"{tuple(y.shape)}")
    if values_y.dim() != 2 or values_y.shape[0] != y.shape[0] or values_x.dim() != 2 \
            or values_x.shape[0] != x.shape[0]:
        raise ConfigError(f"sinkhorn_sq_euclidean_products: need values_y ({y.shape[0]}, p) and values_x "
                          f"({x.shape[0]}, q), got {tuple(values_y.shape)}, {tuple(values_x.shape)}")
    if len({x.dtype, y.dtype, values_y.dtype, values_x.dtype}) != 1:
        raise ConfigError("sinkhorn_sq_euclidean_products: all inputs need the same dtype")
    try:
        py, qx, plan, plan_adj = _SinkhornProducts.apply(x, y, values_y, values_x, float(sigma), int(num_iters),
                                                         bool(return_plans))
    except _KernelUnderflow:
        plans = sinkhorn_log_reference(pairwise_sq_dists(x, y), sigma, num_iters)
        py, qx = plans.plan @ values_y, plans.plan_adj @ values_x
        plan, plan_adj = plans.plan.detach(), plans.plan_adj.detach()
    if not all_finite(py, qx):
        raise NumericalError("sinkhorn_sq_euclidean_products: the transported values contain NaN or Inf")
    if not return_plans:
        plan = plan_adj = None
    return SinkhornProducts(py, qx, plan, plan_adj)
