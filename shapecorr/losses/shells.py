"""Loss terms of the shell-based learned matchers (Deep Shells, G-MSM), as :class:`WeightedLoss` terms.

* :func:`level_energy_loss`: the (weighted) mean of the OT layer's level energies ``E_k`` over the shell
  schedule (Deep Shells: the plain mean, Eisenberger et al. 2020; docs/deep_shells.md §7);
* :func:`graph_alignment_loss`: G-MSM's graph term, ``scale`` times the two-sided alignment cost of a pair over
  the pseudo-correspondences of the composed graph maps (the G-MSM code multiplies it by the sample count 2000;
  docs/gmsm.md §5). A pair without composed maps has no such term (the function returns None and
  :class:`~shapecorr.losses.weighted.WeightedLoss` leaves it out).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from shapecorr.errors import ConfigError

#: G-MSM code: the graph term is multiplied by the subsample count (docs/gmsm.md §5).
GRAPH_LOSS_SCALE = 2000.0


def level_energy_loss(level_energies: torch.Tensor, level_weights: Sequence[float] | None = None) -> torch.Tensor:
    """Weighted mean of the level energies.

    Parameters
    ----------
    level_energies : (L,) float
        ``E_k`` of every level of the shell schedule.
    level_weights : sequence of L floats, optional
        Non-negative weights with a positive sum (normalized to sum 1); None: the plain mean (published).

    Returns
    -------
    () float
    """
    n_levels = level_energies.shape[0]
    if level_weights is None:
        weights = torch.full((n_levels,), 1.0 / n_levels)
    else:
        weights = torch.as_tensor([float(w) for w in level_weights])
        if weights.shape != (n_levels,) or (weights < 0).any() or not weights.sum() > 0:
            raise ConfigError(f"model.loss.terms.shells.fn.level_weights must be {n_levels} non-negative numbers "
                              f"(one per k of model.layer.k_array) with a positive sum, got {list(level_weights)}")
        weights = weights / weights.sum()
    return (weights.to(level_energies) * level_energies).sum()


def graph_alignment_loss(graph_alignment: torch.Tensor | None = None,
                         scale: float = GRAPH_LOSS_SCALE) -> torch.Tensor | None:
    """``scale * graph_alignment``, or None when the pair has no composed graph maps.

    Parameters
    ----------
    graph_alignment : () float, optional
        Mean squared distance between the deformed ``X*`` and ``Y_k`` over the graph's pseudo-pairs (both ways).
    scale : float
        G-MSM code: 2000.
    """
    if graph_alignment is None:
        return None
    if not scale >= 0:
        raise ConfigError(f"model.loss.terms.graph.fn.scale must be >= 0, got {scale}")
    return scale * graph_alignment
