"""Smooth shells: low-pass spectral reconstructions of a shape's coordinates.

Given an eigenbasis ``Phi`` (n, K) orthonormal w.r.t. the lumped mass ``A`` (``Phi^T A Phi = I``), the
spectral coefficients of the coordinates are ``xi = Phi^T A X`` (K, 3). A *shell* of size k keeps the low
frequencies: the hard truncation ``X_k = Phi[:, :k] xi[:k]``, or the sigmoid-weighted version of Smooth
Shells (Eisenberger et al., CVPR 2020, eq. 8) ``X_k = Phi[:, :k'] (w * xi[:k'])`` whose weights fall from 1
to 0 around index k.

Sigmoid weights (docs/deep_shells.md §4): with truncation threshold ``eps = 1e-2`` and smoothing width s = 10,

- k >= s: slope t = -ln(1/(1-eps) - 1)/(s-1); w_j = 1/(1+exp(t j)) for j = -(k-1) .. s-1 (k+9 weights);
- 2 <= k < s: slope t = -ln(1/(1-eps) - 1)/(k-1); j = -(k-1) .. k-1 (2k-1 weights);
- k = 1: w = [1].

The MATLAB original uses those inclusive ranges; the Python ports of Deep Shells / G-MSM drop the last
index (k+8 and 2k-2 weights). ``inclusive=True`` (default) is the MATLAB convention, ``inclusive=False`` the
Python one (needed for parity with the Deep Shells checkpoints).

All functions are differentiable torch functions; they work on any device and dtype.
"""

from __future__ import annotations

import math

import torch

from shapecorr.errors import ConfigError

#: Smooth Shells: the weights fall below 1 - eps before the shell size and above eps after it.
SHELL_TRUNCATION_EPS = 1e-2
#: Smooth Shells: width (in eigen-indices) of the sigmoid transition for large shells.
SHELL_SMOOTH_WIDTH = 10


def sigmoid_shell_weights(
    k: int,
    inclusive: bool = True,
    eps: float = SHELL_TRUNCATION_EPS,
    width: int = SHELL_SMOOTH_WIDTH,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Sigmoid low-pass weights of a smooth shell of size ``k`` (Smooth Shells eq. 8).

    Parameters
    ----------
    k : int
        Shell size (>= 1): the weight at (0-based) index k-1 is 0.5.
    inclusive : bool
        MATLAB index ranges (True) or the one-shorter ranges of the Python ports (False).

    Returns
    -------
    (k',) tensor of weights in (0, 1], decreasing; k' = k+width-1 (inclusive) or k+width-2 when k >= width,
    2k-1 or 2k-2 when 2 <= k < width, and 1 when k == 1.
    """
    if k < 1:
        raise ConfigError(f"shell size k must be >= 1, got {k}")
    if k == 1:
        return torch.ones(1, dtype=dtype, device=device)
    upper = width - 1 if k >= width else k - 1
    slope = -math.log(1.0 / (1.0 - eps) - 1.0) / upper
    stop = upper + 1 if inclusive else upper
    j = torch.arange(-(k - 1), stop, dtype=dtype, device=device)
    return torch.sigmoid(-slope * j)


def spectral_coefficients(evecs: torch.Tensor, mass: torch.Tensor, signal: torch.Tensor) -> torch.Tensor:
    """Coefficients of a per-vertex signal in a mass-orthonormal basis: ``Phi^T A f``.

    Parameters
    ----------
    evecs : (n, K) float
        Eigenfunctions with ``Phi^T diag(mass) Phi = I``.
    mass : (n,) float
        Lumped vertex areas.
    signal : (n, c) float

    Returns
    -------
    (K, c) float
    """
    return evecs.transpose(0, 1) @ (mass[:, None] * signal)


def smooth_shell(
    evecs: torch.Tensor,
    mass: torch.Tensor,
    verts: torch.Tensor,
    k: int,
    mode: str = "sigmoid",
    inclusive: bool = True,
    coefficients: torch.Tensor | None = None,
) -> torch.Tensor:
    """Smooth shell of size ``k`` of a shape.

    Parameters
    ----------
    evecs : (n, K) float
        Mass-orthonormal eigenfunctions, ascending eigenvalues.
    mass : (n,) float
        Lumped vertex areas.
    verts : (n, 3) float
        Vertex positions (ignored when ``coefficients`` is given).
    k : int
        Shell size.
    mode : {"sigmoid", "hard"}
        Sigmoid-weighted low pass (Smooth Shells eq. 8) or hard truncation to the first k eigenfunctions.
    inclusive : bool
        Sigmoid index-range convention, see :func:`sigmoid_shell_weights`.
    coefficients : (K, 3) float, optional
        Precomputed ``spectral_coefficients(evecs, mass, verts)``.

    Returns
    -------
    (n, 3) float
        Vertex positions of the shell. If the sigmoid needs more coefficients than the basis has, the
        weights are truncated to K (the lost weights are < eps by construction only when K >= k'+...).
    """
    xi = spectral_coefficients(evecs, mass, verts) if coefficients is None else coefficients
    n_basis = evecs.shape[1]
    if mode == "hard":
        if k > n_basis:
            raise ConfigError(f"shell size k={k} exceeds the {n_basis} available eigenfunctions")
        return evecs[:, :k] @ xi[:k]
    if mode != "sigmoid":
        raise ConfigError(f"smooth_shell mode must be 'sigmoid' or 'hard', got {mode!r}")
    w = sigmoid_shell_weights(k, inclusive=inclusive, dtype=evecs.dtype, device=evecs.device)
    m = min(w.shape[0], n_basis)
    return evecs[:, :m] @ (w[:m, None] * xi[:m])
