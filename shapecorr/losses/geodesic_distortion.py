"""Geodesic distortion of a soft map (NeuroMorph E_geo).

For a soft map ``Pi`` (n_x, n_y) from x to y and the geodesic distance matrices ``D_x`` (n_x, n_x) and
``D_y`` (n_y, n_y), the distances of y pulled back to x are ``Pi D_y Pi^T``; NeuroMorph (Eisenberger et al.,
CVPR 2021, eq. 7; docs/neuromorph.md §6) penalizes their mean squared deviation from ``D_x``:

    E_geo = mean((Pi D_y Pi^T - D_x)^2)         (the mean over the n_x^2 entries)

with weight 50 during its first 300 epochs. The geodesic matrices are precomputed (dense, n^2 each; the
original uses fast marching, symmetrized, with unreachable pairs set to 2).

Cost. The loss and its gradient are dense ``n^3`` products: ``A = Pi D_y``, ``B = A Pi^T`` and, for the
gradient, ``dL/dPi = 2/N (R Pi D_y^T + R^T Pi D_y)`` with the residual ``R = B - D_x``. A custom backward
keeps exactly ``A`` and ``R`` and needs one product where plain autograd needs three. Geodesic matrices are
symmetric, and then (the fast path, exact up to float rounding; tests compare with plain autograd):

* ``B = Pi D_y Pi^T`` is symmetric: only its upper block triangle is computed, as row panels
  ``B[i, i:] = A_i Pi[i:]^T`` of ``SYMMETRIC_BLOCK`` rows (``(k + 1) / 2k`` of the product for k blocks:
  62.5% at n = 2000). The lower triangle is never formed: the loss counts off-diagonal blocks twice, and the
  gradient ``4/N R A`` reads the missing blocks of R as transposes of stored ones (GEMMs take transposed
  operands for free).
* ``R`` is symmetric when ``D_x`` is, so ``R + R^T = 2 R`` (no transposed n^2 add), and the 4/N scale rides
  on the GEMMs (``alpha``). A non-symmetric ``D_x`` is split into its symmetric part ``S`` and skew part
  ``K``: ``||B - D_x||^2 = ||B - S||^2 + ||K||^2`` exactly (``B - S`` is symmetric, ``K`` skew, so they are
  orthogonal), which keeps the fast path for any ``D_x`` that needs no gradient.

A non-symmetric ``D_y`` (or a ``D_x`` that needs a gradient and is not symmetric) takes the general path.
Symmetry is checked exactly (blockwise, cache-friendly) unless the caller says so.
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError, NumericalError

#: Rows per panel of the symmetric product ``Pi D_y Pi^T`` (project choice, measured on a 2-core Xeon, torch
#: 2.13: 512 keeps each GEMM large enough to run at full speed while skipping 37.5% of the flops at n = 2000).
SYMMETRIC_BLOCK = 512
#: Block size of the exact symmetry check (two 256 x 256 float32 blocks fit in a core's L2 cache).
SYMMETRY_CHECK_BLOCK = 256


def is_symmetric(matrix: torch.Tensor, block: int = SYMMETRY_CHECK_BLOCK) -> bool:
    """Whether a square matrix equals its transpose exactly (NaN entries make it non-symmetric).

    Compares ``M[I, J]`` with ``M[J, I]^T`` block by block: about 2x faster than ``torch.equal(M, M.T)`` on
    CPU, whose transposed read of the whole matrix misses the cache.

    Parameters
    ----------
    matrix : (n, n) tensor

    Returns
    -------
    bool
    """
    n = matrix.shape[0]
    for i in range(0, n, block):
        for j in range(i, n, block):
            if not torch.equal(matrix[i : i + block, j : j + block], matrix[j : j + block, i : i + block].T):
                return False
    return True


def _panels(n: int, block: int) -> list[tuple[int, int]]:
    return [(start, min(start + block, n)) for start in range(0, n, block)]


class _GeodesicDistortionSymmetric(torch.autograd.Function):
    """Fast path: symmetric ``D_y`` and ``D_x`` (module docstring).

    ``const`` is ``sum(K^2)`` of a symmetrized ``D_x`` (0 otherwise).
    """

    @staticmethod
    def forward(ctx, pi, dist_x, dist_y, const: float, block: int):
        n = pi.shape[0]
        bounds = _panels(n, block)
        pulled = pi @ dist_y  # A = Pi D_y
        panels, total = [], pulled.new_zeros(())
        for r0, r1 in bounds:
            # R[i, i:] = A_i Pi[i:]^T - D_x[i, i:]: addmm with beta=-1 fuses the subtraction into the GEMM.
            panel = torch.addmm(dist_x[r0:r1, r0:], pulled[r0:r1], pi[r0:].T, beta=-1.0)
            diag = panel[:, : r1 - r0]
            # Off-diagonal blocks stand for themselves and their mirror images: counted twice.
            total += 2.0 * torch.vdot(panel.reshape(-1), panel.reshape(-1)) - diag.square().sum()
            panels.append(panel)
        ctx.save_for_backward(pi, pulled, *panels)
        ctx.bounds = bounds
        return (total + const) / (n * n)

    @staticmethod
    def _full_residual(panels, bounds, n):
        full = panels[0].new_empty(n, n)
        for (r0, r1), panel in zip(bounds, panels):
            full[r0:r1, r0:] = panel
            full[r1:, r0:r1] = panel[:, r1 - r0 :].T
        return full

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        pi, pulled, *panels = ctx.saved_tensors
        bounds, n = ctx.bounds, pi.shape[0]
        scale = float(grad) * 2.0 / (n * n)
        grad_pi = grad_dx = grad_dy = None
        if ctx.needs_input_grad[0]:
            # dL/dPi = 2/N (R + R^T) A = 4/N R A, R read from its upper block panels.
            grad_pi = torch.empty_like(pulled)
            for i, (r0, r1) in enumerate(bounds):
                rows = grad_pi[r0:r1]
                rows.addmm_(panels[i], pulled[r0:], beta=0.0, alpha=2.0 * scale)  # blocks j >= i
                for j, (c0, _) in enumerate(bounds[:i]):
                    # Block (i, j), j < i, is the transpose of the stored block (j, i).
                    rows.addmm_(panels[j][:, r0 - c0 : r1 - c0].T, pulled[c0 : bounds[j][1]], alpha=2.0 * scale)
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            residual = _GeodesicDistortionSymmetric._full_residual(panels, bounds, n)
            if ctx.needs_input_grad[1]:
                grad_dx = -scale * residual
            if ctx.needs_input_grad[2]:
                grad_dy = scale * (pi.T @ residual @ pi)
        return grad_pi, grad_dx, grad_dy, None, None


class _GeodesicDistortion(torch.autograd.Function):
    """General path (any ``D_y``): ``A = Pi D_y``, ``R = A Pi^T - D_x``; backward from ``A`` and ``R``."""

    @staticmethod
    def forward(ctx, pi: torch.Tensor, dist_x: torch.Tensor, dist_y: torch.Tensor, symmetric_y: bool):
        pulled = pi @ dist_y  # A = Pi D_y
        residual = torch.addmm(dist_x, pulled, pi.T, beta=-1.0)
        ctx.save_for_backward(pi, dist_y, pulled, residual)
        ctx.symmetric_y = symmetric_y
        return torch.vdot(residual.reshape(-1), residual.reshape(-1)) / residual.numel()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        pi, dist_y, pulled, residual = ctx.saved_tensors
        scale = grad * (2.0 / residual.numel())
        grad_pi = grad_dx = grad_dy = None
        if ctx.needs_input_grad[0]:
            if ctx.symmetric_y:
                grad_pi = (residual + residual.T) @ pulled
            else:
                grad_pi = residual @ (pi @ dist_y.T) + residual.T @ pulled
            grad_pi = grad_pi * scale
        if ctx.needs_input_grad[1]:
            grad_dx = -scale * residual
        if ctx.needs_input_grad[2]:
            grad_dy = scale * (pi.T @ residual @ pi)
        return grad_pi, grad_dx, grad_dy, None


def geodesic_distortion_loss(
    pi_x_to_y: torch.Tensor,
    dist_x: torch.Tensor,
    dist_y: torch.Tensor,
    symmetric_dist_y: bool | None = None,
    symmetric_dist_x: bool | None = None,
) -> torch.Tensor:
    """Mean squared distortion of geodesic distances under a soft map: ``mean((Pi D_y Pi^T - D_x)^2)``.

    Parameters
    ----------
    pi_x_to_y : (n_x, n_y) float
        Row-stochastic soft map x -> y.
    dist_x : (n_x, n_x) float
        Geodesic distances on x.
    dist_y : (n_y, n_y) float
        Geodesic distances on y.
    symmetric_dist_y, symmetric_dist_x : bool, optional
        Whether ``dist_y`` / ``dist_x`` are exactly symmetric (enables the faster path, module docstring);
        checked when None (about 10 ms each at n = 2000 on one CPU core). Passing True for a non-symmetric
        matrix gives a wrong result.

    Returns
    -------
    () float
        0 for the identity map between a shape and itself (``Pi = I``, ``D_x = D_y``).
    """
    n_x, n_y = pi_x_to_y.shape if pi_x_to_y.ndim == 2 else (-1, -1)
    if pi_x_to_y.ndim != 2 or dist_x.shape != (n_x, n_x) or dist_y.shape != (n_y, n_y):
        raise ConfigError(
            f"expected pi (n_x, n_y), dist_x (n_x, n_x), dist_y (n_y, n_y); got {tuple(pi_x_to_y.shape)}, "
            f"{tuple(dist_x.shape)}, {tuple(dist_y.shape)}"
        )
    for name, d in (("dist_x", dist_x), ("dist_y", dist_y)):
        # min/max propagate NaN and Inf: one fast reduction instead of a bool mask of n^2 entries (8x slower).
        if not bool(torch.isfinite(torch.stack(torch.aminmax(d))).all()):
            raise NumericalError(f"{name} contains NaN or Inf (unreachable vertices must be given a finite value)")
    dist_x, dist_y = dist_x.to(pi_x_to_y.dtype), dist_y.to(pi_x_to_y.dtype)
    if symmetric_dist_y is None:
        symmetric_dist_y = is_symmetric(dist_y)
    if symmetric_dist_y:
        if symmetric_dist_x is None:
            symmetric_dist_x = is_symmetric(dist_x)
        const = 0.0
        if not symmetric_dist_x and not dist_x.requires_grad:
            skew = 0.5 * (dist_x - dist_x.T)
            const = float(torch.vdot(skew.reshape(-1), skew.reshape(-1)))
            dist_x, symmetric_dist_x = dist_x - skew, True
        if symmetric_dist_x:
            loss = _GeodesicDistortionSymmetric.apply(pi_x_to_y, dist_x, dist_y, const, SYMMETRIC_BLOCK)
        else:
            loss = _GeodesicDistortion.apply(pi_x_to_y, dist_x, dist_y, True)
    else:
        loss = _GeodesicDistortion.apply(pi_x_to_y, dist_x, dist_y, False)
    if not bool(torch.isfinite(loss)):
        raise NumericalError("geodesic distortion loss is not finite (NaN/Inf in the soft map?)")
    return loss
