"""Registration (alignment) loss between a deformed shape and its soft correspondence (NeuroMorph E_align).

NeuroMorph (Eisenberger et al., CVPR 2021, eq. 6; docs/neuromorph.md §6) asks the end point ``X(1)`` of the
interpolation of x towards y to coincide with y *through the soft maps*, both ways:

    E_align = c * ( ||Pi Y - X(1)||^2 + ||Y - Pi_inv X(1)||^2 )

(squared Frobenius norms, i.e. sums over vertices of squared distances). The original code uses
``c = 201 / n_x`` for both terms (``reduction="original"``, the default, so the published loss weights keep
their meaning). Its factor makes the first term a mean over x's vertices times 201, and the second term a
sum over y's vertices divided by n_x; ``reduction="mean"`` is the symmetric alternative
``||Pi Y - X(1)||^2 / n_x + ||Y - Pi_inv X(1)||^2 / n_y`` (mean squared distances), ``"sum"`` uses c = 1.
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError, NumericalError

#: Numerator of the NeuroMorph code's alignment normalization c = 201 / n_x (docs/neuromorph.md §6).
ORIGINAL_ALIGN_NUMERATOR = 201.0
REDUCTIONS = ("original", "mean", "sum")


def registration_loss(
    verts_x_deformed: torch.Tensor,
    verts_y: torch.Tensor,
    pi_x_to_y: torch.Tensor,
    pi_y_to_x: torch.Tensor,
    reduction: str = "original",
    soft_target: torch.Tensor | None = None,
) -> torch.Tensor:
    """Two-way alignment of a deformed x with y through soft maps.

    Parameters
    ----------
    verts_x_deformed : (n_x, 3) float
        End point ``X(1)`` of the deformation of x.
    verts_y : (n_y, 3) float
    pi_x_to_y : (n_x, n_y) float
        Row-stochastic soft map x -> y.
    pi_y_to_x : (n_y, n_x) float
        Row-stochastic soft map y -> x.
    reduction : {"original", "mean", "sum"}
        Normalization, see the module docstring.
    soft_target : (n_x, 3) float, optional
        ``pi_x_to_y @ verts_y`` when the caller already has it (NeuroMorph's interpolator target): reusing
        the same tensor saves an ``n_x x n_y`` product, and in the backward pass the two uses add their
        ``(n_x, 3)`` gradients before the single ``n_x x n_y`` gradient product. Not checked against the
        soft map.

    Returns
    -------
    () float
        The loss; 0 when ``pi_x_to_y @ Y == X(1)`` and ``pi_y_to_x @ X(1) == Y``.
    """
    if reduction not in REDUCTIONS:
        raise ConfigError(f"registration reduction must be one of {REDUCTIONS}, got {reduction!r}")
    n_x, n_y = verts_x_deformed.shape[0], verts_y.shape[0]
    if pi_x_to_y.shape != (n_x, n_y) or pi_y_to_x.shape != (n_y, n_x):
        raise ConfigError(
            f"soft maps must be ({n_x}, {n_y}) and ({n_y}, {n_x}) for {n_x} and {n_y} vertices, got "
            f"{tuple(pi_x_to_y.shape)} and {tuple(pi_y_to_x.shape)}"
        )
    if soft_target is None:
        soft_target = pi_x_to_y @ verts_y
    elif soft_target.shape != verts_x_deformed.shape:
        raise ConfigError(f"soft_target must have shape {tuple(verts_x_deformed.shape)}, "
                          f"got {tuple(soft_target.shape)}")
    term_x = (soft_target - verts_x_deformed).square().sum()
    term_y = (verts_y - pi_y_to_x @ verts_x_deformed).square().sum()
    if reduction == "original":
        loss = (ORIGINAL_ALIGN_NUMERATOR / n_x) * (term_x + term_y)
    elif reduction == "mean":
        loss = term_x / n_x + term_y / n_y
    else:
        loss = term_x + term_y
    if not bool(torch.isfinite(loss)):
        raise NumericalError("registration loss is not finite (NaN/Inf in the vertices or the soft maps)")
    return loss
