"""G-MSM's fast pairwise query and the Deep Shells alignment cost of a pair's maps.

Eisenberger, Toker, Leal-Taixé, Cremers, "G-MSM: Unsupervised Multi-Shape Matching with Graph-based Affinity
Priors", CVPR 2023 (docs/gmsm.md §3, §5). Built on the Deep Shells layer (:mod:`shapecorr.matching.deep_shells`):

- :func:`one_level_query`: from the last training level's ``(C, tau)``, maps at full resolution after one
  least-squares level, and their alignment cost (G-MSM's edge weight);
- :func:`two_sided_alignment_cost`: mean squared product-space distance over the two-sided pairs of two maps,
  with :func:`full_resolution_shells` also G-MSM's graph loss;
- :func:`alignment_cost_of_maps`: the same cost for maps computed by any means (the ``(C, tau)`` fitted to the
  maps by least squares), the pair cost of Deep Shells in a multi-shape evaluation (docs/evaluation.md §7).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.spectral_shape import SpectralShape
from shapecorr.matching.deep_shells import (
    DeepShellsConfig,
    DeepShellsMatch,
    _check_eigs,
    _shell,
    deformation_from_pairs,
    product_embedding_maps,
    refine_deep_shells,
)



def full_resolution_shells(
    shape_x: SpectralShape, shape_y: SpectralShape, tau: torch.Tensor, config: DeepShellsConfig = DeepShellsConfig()
) -> tuple[torch.Tensor, torch.Tensor]:
    """The deformed shell ``X* = X_k + Phi_X tau`` and the target shell ``Y_k`` at every vertex.

    Differentiable in ``tau`` (G-MSM's graph loss evaluates the last training level at full resolution).

    Parameters
    ----------
    shape_x, shape_y : SpectralShape
    tau : (k, 3) float
        Spectral deformation of a level of shell size ``k``.
    config : DeepShellsConfig
        Shell conventions (``smooth_x``, ``sigmoid_inclusive``).

    Returns
    -------
    deformed_x : (n_x, 3) float
    shell_y : (n_y, 3) float
    """
    k = int(tau.shape[0])
    if tau.shape != (k, 3):
        raise ConfigError(f"full_resolution_shells: tau must be (k, 3), got {tuple(tau.shape)}")
    _check_eigs(shape_x, (k,), config)
    _check_eigs(shape_y, (k,), config)
    incl = config.sigmoid_inclusive
    shell_x = _shell(shape_x, k, config.smooth_x, incl)
    shell_y = _shell(shape_y, k, "sigmoid", incl)
    deformed = shell_x + shape_x.evecs[:, :k] @ tau.to(shape_x.evecs.dtype)
    return deformed, shell_y


def two_sided_alignment_cost(
    deformed_x: torch.Tensor, shell_y: torch.Tensor, map_x_to_y: torch.Tensor, map_y_to_x: torch.Tensor
) -> torch.Tensor:
    """Mean squared product-space distance over the two-sided pairs of two maps (G-MSM's ``loss_1``).

    ``mean over (a, b) in {(i, map_x_to_y[i])} + {(map_y_to_x[j], j)} of |X*[a] - Y_k[b]|^2``: the G-MSM edge
    weight of a query and, with the composed graph maps as pairs, its graph loss (before its weight).

    Parameters
    ----------
    deformed_x : (n_x, 3) float
    shell_y : (n_y, 3) float
    map_x_to_y : (n_x,) int64
    map_y_to_x : (n_y,) int64

    Returns
    -------
    () float
    """
    n_x, n_y = deformed_x.shape[0], shell_y.shape[0]
    if map_x_to_y.shape != (n_x,) or map_y_to_x.shape != (n_y,):
        raise ConfigError(f"two_sided_alignment_cost: need maps of shapes ({n_x},) and ({n_y},), got "
                          f"{tuple(map_x_to_y.shape)}, {tuple(map_y_to_x.shape)}")
    fwd = (deformed_x - shell_y[map_x_to_y]).square().sum(1)
    bwd = (deformed_x[map_y_to_x] - shell_y).square().sum(1)
    cost = torch.cat([fwd, bwd]).mean()
    if not torch.isfinite(cost):
        raise NumericalError("two_sided_alignment_cost: the cost is NaN or Inf")
    return cost


@dataclass(frozen=True, eq=False)
class OneLevelQuery:
    """Result of :func:`one_level_query`.

    Attributes
    ----------
    match : DeepShellsMatch
        Maps at full resolution after the least-squares level.
    cost : () float
        :func:`two_sided_alignment_cost` of those maps with that level's ``X*`` and ``Y_k``.
    """

    match: DeepShellsMatch
    cost: torch.Tensor


def one_level_query(
    shape_x: SpectralShape,
    shape_y: SpectralShape,
    fmap: torch.Tensor,
    tau: torch.Tensor,
    config: DeepShellsConfig = DeepShellsConfig(),
) -> OneLevelQuery:
    """G-MSM's fast pairwise query from the last training level's ``(C, tau)`` (docs/gmsm.md §3).

    At full resolution and shell size ``k = fmap.shape[0]`` (the last of ``k_array``): nearest neighbours in
    the level's product embedding (:func:`product_embedding_maps`, training weights), one refinement level at
    the same ``k`` (:func:`refine_deep_shells`: one ``(C, tau)`` least squares on those pairs, nearest
    neighbours again, refinement weights), and the alignment cost of the final maps
    (:func:`two_sided_alignment_cost` with that level's ``X*`` and ``Y_k``).

    Parameters
    ----------
    shape_x, shape_y : SpectralShape
    fmap : (k, k) float
    tau : (k, 3) float
        From :class:`DeepShellsOutput` of the training layer on a sample of the pair.
    config : DeepShellsConfig

    Returns
    -------
    OneLevelQuery
    """
    k = int(fmap.shape[0])
    coarse = product_embedding_maps(shape_x, shape_y, fmap, tau, config)
    level = replace(config, refine_k_min=k, refine_k_max=k, refine_levels=1)
    refined = refine_deep_shells(shape_x, shape_y, coarse.map_x_to_y, coarse.map_y_to_x, level)
    with torch.no_grad():
        shell_y = _shell(shape_y, k, "sigmoid", config.sigmoid_inclusive)
        cost = two_sided_alignment_cost(refined.deformed_x, shell_y, refined.map_x_to_y, refined.map_y_to_x)
    return OneLevelQuery(match=refined, cost=cost)


def alignment_cost_of_maps(
    shape_x: SpectralShape,
    shape_y: SpectralShape,
    map_x_to_y: torch.Tensor,
    map_y_to_x: torch.Tensor,
    config: DeepShellsConfig = DeepShellsConfig(),
    k: int | None = None,
) -> torch.Tensor:
    """Alignment cost of a pair's two maps at shell size ``k`` (default: the last training level, ``k_array[-1]``).

    Fits ``(C, tau)`` to the two-sided pairs of the maps by least squares (:func:`deformation_from_pairs`, the
    refinement's solve), deforms ``X* = X_k + Phi_X tau`` and returns :func:`two_sided_alignment_cost` of the
    maps with ``X*`` and ``Y_k``: G-MSM's edge weight, for maps that did not come from its one-level query.

    Parameters
    ----------
    shape_x, shape_y : SpectralShape
    map_x_to_y : (n_x,) int64
    map_y_to_x : (n_y,) int64
    config : DeepShellsConfig
        Shell conventions (``smooth_x``, ``sigmoid_inclusive``), ``ridge`` and ``k_array``.
    k : int, optional

    Returns
    -------
    () float
    """
    k = int(config.k_array[-1] if k is None else k)
    _check_eigs(shape_x, (k,), config)
    _check_eigs(shape_y, (k,), config)
    map_x_to_y = map_x_to_y.to(shape_x.evecs.device)
    map_y_to_x = map_y_to_x.to(shape_x.evecs.device)
    with torch.no_grad():
        shell_x = _shell(shape_x, k, config.smooth_x, config.sigmoid_inclusive)
        shell_y = _shell(shape_y, k, "sigmoid", config.sigmoid_inclusive)
        phi_x = shape_x.evecs[:, :k]
        _, tau = deformation_from_pairs(phi_x, shape_y.evecs[:, :k], shell_x, shell_y, map_x_to_y, map_y_to_x,
                                        config.ridge)
        deformed = shell_x + phi_x @ tau.to(phi_x.dtype)
        return two_sided_alignment_cost(deformed, shell_y, map_x_to_y, map_y_to_x)


__all__ = [
    "OneLevelQuery",
    "alignment_cost_of_maps",
    "full_resolution_shells",
    "one_level_query",
    "two_sided_alignment_cost",
]
