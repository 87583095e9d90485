"""Geodesic distortion of a soft map (NeuroMorph E_geo).

For a soft map ``Pi`` (n_x, n_y) from x to y and the geodesic distance matrices ``D_x`` (n_x, n_x) and
``D_y`` (n_y, n_y), the distances of y pulled back to x are ``Pi D_y Pi^T``; NeuroMorph (Eisenberger et al.,
CVPR 2021, eq. 7; methods-digest §4.5) penalizes their mean squared deviation from ``D_x``:

    E_geo = mean((Pi D_y Pi^T - D_x)^2)         (the mean over the n_x^2 entries)

with weight 50 during its first 300 epochs. The geodesic matrices are precomputed (dense, n^2 each; the
original uses fast marching, symmetrized, with unreachable pairs set to 2).

Cost and memory. The loss is three dense ``n^3`` products: ``A = Pi D_y``, ``A Pi^T`` and, for the gradient,
``(R + R^T) A`` with the residual ``R = Pi D_y Pi^T - D_x``. A custom backward keeps exactly ``A`` and ``R``
(``n_x n_y + n_x^2`` values, nothing larger) and needs one product where plain autograd needs three
(``dL/dPi = 2/N (R Pi D_y^T + R^T Pi D_y)`` collapses to ``2/N (R + R^T) A`` for a symmetric ``D_y``; a
non-symmetric ``D_y`` costs one more product).
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError, NumericalError


class _GeodesicDistortion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pi: torch.Tensor, dist_x: torch.Tensor, dist_y: torch.Tensor, symmetric_y: bool):
        pulled = pi @ dist_y  # A = Pi D_y
        residual = pulled @ pi.T
        residual.sub_(dist_x)
        ctx.save_for_backward(pi, dist_y, pulled, residual)
        ctx.symmetric_y = symmetric_y
        return residual.square().mean()

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
    symmetric_dist_y : bool, optional
        Whether ``dist_y`` is exactly symmetric (enables the cheaper backward); checked when None.

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
        symmetric_dist_y = bool(torch.equal(dist_y, dist_y.T))
    loss = _GeodesicDistortion.apply(pi_x_to_y, dist_x, dist_y, symmetric_dist_y)
    if not bool(torch.isfinite(loss)):
        raise NumericalError("geodesic distortion loss is not finite (NaN/Inf in the soft map?)")
    return loss
