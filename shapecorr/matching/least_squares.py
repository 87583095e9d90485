"""Ridge-regularized linear least squares through float64 normal equations.

The shell methods (Deep Shells, Smooth Shells) fit a functional map ``C`` and a spectral deformation
``tau`` to correspondences by linear least squares in a truncated eigenbasis (k <= 500 unknowns per column,
thousands of rows). The original code solved the normal equations ``(A^T A) X = A^T B`` in float32 without
regularization; with duplicated or nearest-neighbour pairs at large k, ``A^T A`` can be badly conditioned.
Here the Gram matrix is accumulated and factorized in float64 and a tiny ridge proportional to its mean
diagonal is added (docs/deep_shells.md §9), which leaves well-posed problems unchanged to far
below float32 precision and makes rank-deficient ones solvable.

The functions are split so that methods can add their own terms (ARAP, descriptor or Laplacian penalties in
Smooth Shells) to the Gram matrix and right-hand side before solving. All are differentiable (torch
autograd through ``cholesky`` and ``cholesky_solve``) and work on any device.
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.finiteness import all_finite

#: Ridge added to the normal equations, relative to the mean diagonal of the Gram matrix. Tiny on purpose:
#: float64 Gram matrices are accurate to ~1e-16 relative, so 1e-8 only matters where the problem is
#: (numerically) rank deficient, and it changes well-posed float32 results far below float32 resolution.
#: The originals use no ridge (docs/deep_shells.md §6, §9).
DEFAULT_RIDGE = 1e-8


def normal_equations(
    a: torch.Tensor, b: torch.Tensor, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gram matrix and right-hand side of a (weighted) linear least-squares problem, in float64.

    Parameters
    ----------
    a : (r, k) float
        Design matrix.
    b : (r, c) float
        Right-hand sides.
    weights : (r,) float, optional
        Non-negative row weights ``w``; the problem is ``min_X sum_i w_i |a_i X - b_i|^2``.

    Returns
    -------
    gram : (k, k) float64
        ``a^T diag(w) a``.
    rhs : (k, c) float64
        ``a^T diag(w) b``.
    """
    if a.dim() != 2 or b.dim() != 2 or a.shape[0] != b.shape[0]:
        raise ConfigError(f"normal_equations: need a (r, k) and b (r, c), got {tuple(a.shape)} and {tuple(b.shape)}")
    a64 = a.to(torch.float64)
    b64 = b.to(torch.float64)
    wa = a64 if weights is None else a64 * weights.to(torch.float64)[:, None]
    at = wa.transpose(0, 1)
    return at @ a64, at @ b64


def solve_normal_equations(
    gram: torch.Tensor, rhs: torch.Tensor, ridge: float = DEFAULT_RIDGE, what: str = "least-squares"
) -> torch.Tensor:
    """Solve ``(G + ridge * mean(diag G) * I) X = rhs`` in float64 by a Cholesky factorization, batched.

    Leading dimensions are a batch of independent systems, each with its own ridge. An all-zero Gram matrix
    (no data in that system) gets the absolute ridge instead, so that its solution is 0 for ``ridge > 0``.

    Parameters
    ----------
    gram : (..., k, k) float
        Symmetric positive semi-definite Gram matrices.
    rhs : (..., k, c) float
    ridge : float
        Relative ridge (>= 0), see :data:`DEFAULT_RIDGE`.
    what : str
        Name of the solve used in error messages (e.g. ``"Deep Shells (C, tau) solve at k=21"``).

    Returns
    -------
    (..., k, c) float64

    Raises
    ------
    NumericalError
        If the inputs contain NaN/Inf, a regularized matrix is not positive definite (e.g. an all-zero
        design matrix with ``ridge = 0``), or the solution is not finite.
    """
    if ridge < 0:
        raise ConfigError(f"ridge must be >= 0, got {ridge}")
    g = gram.to(torch.float64)
    z = rhs.to(torch.float64)
    if not all_finite(g, z):
        raise NumericalError(f"{what}: the normal equations contain NaN or Inf (check the input correspondences)")
    k = g.shape[-1]
    scale = torch.diagonal(g, dim1=-2, dim2=-1).mean(-1)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    if ridge > 0:
        g = g + (ridge * scale)[..., None, None] * torch.eye(k, dtype=g.dtype, device=g.device)
    chol, info = torch.linalg.cholesky_ex(g)
    if bool((info != 0).any()):
        raise NumericalError(
            f"{what}: a {k}x{k} Gram matrix is not positive definite (ridge {ridge}); the correspondences do "
            f"not determine the {k} unknowns"
        )
    sol = torch.cholesky_solve(z, chol)
    if not all_finite(sol):
        raise NumericalError(f"{what}: the solution contains NaN or Inf")
    return sol


def ridge_lstsq(
    a: torch.Tensor,
    b: torch.Tensor,
    weights: torch.Tensor | None = None,
    ridge: float = DEFAULT_RIDGE,
    what: str = "least-squares",
) -> torch.Tensor:
    """Ridge-regularized (weighted) least squares ``argmin_X |W^(1/2) (a X - b)|^2 + ridge' |X|^2``.

    The Gram matrix is built and factorized in float64 (:func:`normal_equations`,
    :func:`solve_normal_equations`); ``ridge' = ridge * mean(diag(a^T W a))``.

    Parameters
    ----------
    a : (r, k) float
    b : (r, c) float
    weights : (r,) float, optional
    ridge : float
    what : str
        Name used in error messages.

    Returns
    -------
    (k, c) tensor in the dtype of ``a``
    """
    gram, rhs = normal_equations(a, b, weights)
    return solve_normal_equations(gram, rhs, ridge=ridge, what=what).to(a.dtype)
