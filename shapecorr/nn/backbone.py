"""The backbone interface: a feature extractor a model receives already built (``model/backbone`` config node).

A backbone is an :class:`torch.nn.Module` with

- ``forward(sample, rows=None) -> (n, C)`` or ``(len(rows), C)`` float features of a
  :class:`~shapecorr.data.datasets.ShapeSample` at all its vertices or at the vertex indices ``rows (r,)`` int64;
- ``out_channels``: ``C``;
- ``required_operators``: the per-shape operators it reads from the sample, as an operator request
  ``{operator name: {parameter: value}}`` (see :mod:`shapecorr.data.operators`), e.g.
  ``{"eigenbasis": {"k": 200}, "shot": {}}``. The model merges its backbone's request with its own and the data
  module computes (and caches) exactly that.

Models take the module itself (``hydra.utils.instantiate`` builds it from ``configs/model/backbone/<name>.yaml``),
never a string naming it, so a new backbone is one module plus one config file (``docs/architecture.md`` §4). A
checkpoint rebuilds it from the model's recipe (:mod:`shapecorr.models.recipe`): a backbone records nothing.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from shapecorr.errors import ConfigError

#: An operator request: operator name -> its parameters (an empty dict takes the operator's defaults).
OperatorRequest = Mapping[str, Mapping[str, Any]]


class Backbone(nn.Module):
    """Base class of the feature extractors (see the module docstring); subclasses implement :meth:`forward`."""

    #: Number of output feature channels ``C``.
    out_channels: int
    #: Per-shape operators read from the sample (operator name -> parameters).
    required_operators: OperatorRequest = {}

    def forward(self, sample, rows: torch.Tensor | None = None) -> torch.Tensor:  # pragma: no cover - abstract
        """Features ``(n, C)`` at every vertex, or ``(len(rows), C)`` at the vertices ``rows (r,)`` int64."""
        raise NotImplementedError

    @property
    def trainable(self) -> bool:
        """Whether the backbone has parameters to learn (the identity backbone has none)."""
        return any(p.requires_grad for p in self.parameters())


def sample_descriptor(sample, name: str, who: str) -> torch.Tensor:
    """The per-vertex descriptor ``name`` ``(n, c)`` of a sample (``sample.operators[name][name]``).

    Raises
    ------
    ConfigError
        The sample does not carry it (the message names the shape, the backbone and what the data provides).
    """
    arrays = sample.operators.get(name, {})
    if name not in arrays:
        raise ConfigError(f"{sample.name}: {who} needs the {name!r} descriptor, the data provides operators "
                          f"{sorted(sample.operators)}; declare it in required_operators")
    return arrays[name]
