"""The identity backbone: a per-vertex descriptor straight through, no parameters.

Deep Shells' "no learning" ablation (SHOT into the OT layer, Eisenberger et al. 2020, Table 1) is
``model=deep_shells model/backbone=identity`` (or ``model=deep_shells_ablation``); it is evaluable without
training. Config: ``configs/model/backbone/identity.yaml``.
"""

from __future__ import annotations

import torch

from shapecorr.errors import ConfigError
from shapecorr.nn.backbone import Backbone, sample_descriptor

#: SHOT length (10 bins x 32 sectors + 32), the descriptor of the Deep Shells ablation.
SHOT_CHANNELS = 352


class IdentityBackbone(Backbone):
    """Returns ``sample.operators[descriptor][descriptor]`` (at ``rows``) unchanged.

    Parameters
    ----------
    descriptor : str
        Descriptor operator (``shot``, ``wks``, ``hks``, ...).
    out_channels : int
        Its length (SHOT: 352, WKS/HKS: their count); checked on every call.
    """

    def __init__(self, descriptor: str = "shot", out_channels: int = SHOT_CHANNELS):
        super().__init__()
        if int(out_channels) < 1:
            raise ConfigError(f"identity backbone: out_channels must be >= 1, got {out_channels}")
        self.descriptor = str(descriptor)
        self.out_channels = int(out_channels)

    @property
    def required_operators(self) -> dict:  # type: ignore[override]
        """``{descriptor: {}}``."""
        return {self.descriptor: {}}

    def forward(self, sample, rows: torch.Tensor | None = None) -> torch.Tensor:
        """The descriptor ``(n, out_channels)`` or ``(len(rows), out_channels)``."""
        features = sample_descriptor(sample, self.descriptor, "the identity backbone")
        if features.dim() != 2 or features.shape[1] != self.out_channels:
            raise ConfigError(f"{sample.name}: the {self.descriptor!r} descriptor has shape {tuple(features.shape)}, "
                              f"the identity backbone expects (n, {self.out_channels}) (model.backbone.out_channels)")
        return features if rows is None else features[rows]
