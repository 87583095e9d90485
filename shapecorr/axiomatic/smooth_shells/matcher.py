"""Smooth Shells as a matcher for evaluate.py (``model=smooth_shells``)."""

from __future__ import annotations


import numpy as np
import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.matching.result import MatchResult

from shapecorr.axiomatic.smooth_shells.config import SmoothShellsConfig
from shapecorr.axiomatic.smooth_shells.pipeline import smooth_shells
from shapecorr.axiomatic.smooth_shells.shapes import SmoothShellsResult, shape_from_sample


class SmoothShells:
    """Smooth Shells as a matcher (``evaluate.py model=smooth_shells``): no training.

    ``match`` returns both maps and, as an interpolating matcher, the frames ``X + t (X* - X)`` from X (in its
    input pose) to the deformed shape X* (in Y's frame); ``interpolate(x, y, times)`` gives any times.
    The keyword arguments are the fields of :class:`SmoothShellsConfig` (published values as defaults;
    configs/model/smooth_shells*.yaml).

    Parameters
    ----------
    interp_times : sequence of float
        Frames of :meth:`match` (the project's one name for frame times, as ``evaluate.py interp_times``).
    **settings
        :class:`SmoothShellsConfig` fields.
    """

    needs_ground_truth = False

    def __init__(self, interp_times=(0.0, 0.25, 0.5, 0.75, 1.0), **settings):
        try:
            self.config = SmoothShellsConfig(**settings)
        except TypeError as err:
            raise ConfigError(f"smooth_shells: {err}") from None
        values = [float(t) for t in interp_times]
        if not values or not all(np.isfinite(values)):
            raise ConfigError(f"smooth_shells.interp_times must be finite numbers, got {values}")
        self.interp_times = tuple(values)

    @property
    def required_operators(self) -> dict:
        """Operator request: the eigenbasis of ``config.num_eigs`` pairs, and SHOT when features are used."""
        out = {"eigenbasis": {"k": self.config.num_eigs}}
        if self.config.lambda_feat > 0:
            out["shot"] = {}
        return out

    def run(self, x, y) -> SmoothShellsResult:
        """The full pipeline on two ``ShapeSample`` objects."""
        need = self.config.lambda_feat > 0
        return smooth_shells(shape_from_sample(x, need), shape_from_sample(y, need), self.config)

    def interpolate(self, x, y, times) -> MatchResult:
        """Maps and frames ``X + t (X* - X)`` at ``times (T,)``."""
        times = torch.as_tensor(times, dtype=x.verts.dtype, device=x.verts.device).reshape(-1)
        if not torch.isfinite(times).all():
            raise NumericalError(f"interpolation times must be finite, got {times.tolist()}")
        res = self.run(x, y)
        step = res.deformed_x - x.verts
        frames = x.verts[None] + times[:, None, None] * step[None]
        return MatchResult(p2p=res.map_x_to_y, p2p_inv=res.map_y_to_x, deformation=frames, times=times,
                           extras={"k_array": res.k_array, "level_objectives": res.level_objectives})

    def match(self, x, y) -> MatchResult:
        """:meth:`interpolate` at the default ``times``."""
        return self.interpolate(x, y, torch.tensor(self.interp_times))
