"""Smooth Shells as post-processing of any matcher's map (``evaluate.py postprocess=smooth_shells``).

:class:`SmoothShellsPostprocess` wraps a matcher (learned or not): ``match(x, y)`` runs the wrapped matcher,
then :func:`shapecorr.axiomatic.smooth_shells.refine` initialized from its maps (the layered matching from
shell size ``k_start`` on; no rigid stage, no random search), as NeuroMorph's paper refines its maps
(docs/smooth_shells.md §3 ``refine`` and §4).
"""

from __future__ import annotations

from shapecorr.axiomatic.smooth_shells import K_START, SmoothShells, refine, shape_from_sample
from shapecorr.data.operators import merge_requests
from shapecorr.errors import ConfigError
from shapecorr.eval.protocol import INITIAL_MAP_KEY
from shapecorr.matching.result import MatchResult


class SmoothShellsPostprocess:
    """A matcher whose map is the wrapped matcher's map refined by Smooth Shells' layered matching.

    Parameters
    ----------
    matcher : Matcher
        Any object with ``match(x, y) -> MatchResult``; its ``required_operators`` are merged with Smooth Shells'
        (eigenbasis of ``num_eigs = k_max + 9`` pairs, SHOT when ``lambda_feat > 0``) and its
        ``needs_ground_truth`` is passed through. Its ``p2p`` (and ``p2p_inv`` when it has one) start the
        refinement.
    k_start : int
        Shell size of the first layer (``<= k_max``); the published schedule's sizes above it follow.
    **settings
        :class:`~shapecorr.axiomatic.smooth_shells.SmoothShellsConfig` fields (the rigid and random-search ones
        are ignored by :func:`~shapecorr.axiomatic.smooth_shells.refine`).

    Notes
    -----
    The result holds the refined maps only: frames of an interpolating wrapped matcher are dropped (they belong
    to the unrefined map), so the wrapper is not an interpolating matcher; ``extras["deformed_x"]`` is X*.
    """

    def __init__(self, matcher, k_start: int = K_START, **settings):
        if not callable(getattr(matcher, "match", None)):
            raise ConfigError("postprocess=smooth_shells wraps a matcher (with a match(x, y) method), got "
                              f"{type(matcher).__name__}")
        self.matcher = matcher
        self.shells = SmoothShells(**settings)
        self.config = self.shells.config
        if not 1 <= int(k_start) <= self.config.k_max:
            raise ConfigError(f"postprocess.k_start must be in [1, k_max = {self.config.k_max}], got {k_start}")
        self.k_start = int(k_start)

    @property
    def required_operators(self) -> dict:
        """The wrapped matcher's operator request merged with Smooth Shells' (larger eigenbasis wins)."""
        return merge_requests(getattr(self.matcher, "required_operators", None) or {},
                              self.shells.required_operators)

    @property
    def needs_ground_truth(self) -> bool:
        """Whether the wrapped matcher needs the ground truth."""
        return bool(getattr(self.matcher, "needs_ground_truth", False))

    def match(self, x, y) -> MatchResult:
        """The wrapped matcher's maps x -> y (and y -> x), refined from shell size ``k_start`` on."""
        initial = self.matcher.match(x, y)
        need = self.config.lambda_feat > 0
        res = refine(shape_from_sample(x, need), shape_from_sample(y, need), initial.p2p, k_start=self.k_start,
                     initial_map_inv=initial.p2p_inv, config=self.config)
        return MatchResult(p2p=res.map_x_to_y, p2p_inv=res.map_y_to_x,
                           extras={INITIAL_MAP_KEY: initial.p2p, "deformed_x": res.deformed_x,
                                   "k_array": res.k_array, "level_objectives": res.level_objectives})
