"""What a matcher returns, and the matcher protocol every method implements.

The matcher protocol
--------------------
Anything with a method ``match(x: ShapeSample, y: ShapeSample) -> MatchResult`` is a matcher: the baselines
of :mod:`shapecorr.matching.baselines`, axiomatic methods, and every LightningModule of
:mod:`shapecorr.models` (``evaluate.py`` calls ``match`` on each test pair, under ``torch.no_grad()`` and
with the module in eval mode). The map goes **from x to y**: ``p2p[i]`` is the vertex of y matched to
vertex i of x. Two optional attributes let ``evaluate.py`` prepare the data a matcher needs:

``required_operators``
    An operator request ``{operator name: {param: value}}`` (:mod:`shapecorr.data.operators`; ``{}`` takes an
    operator's defaults), e.g. ``{"wks": {}}`` or ``{"eigenbasis": {"k": 500}, "shot": {}}``, merged into the
    data's operators (``ShapePairDataModule.with_operators``) before the data is loaded; the samples then carry
    ``sample.operators[name]``.
``needs_ground_truth``
    True for the self-check matcher that reads the ground truth (``IdentityGT``); such matchers are never
    reported as a method.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import torch

from shapecorr.errors import CorrespondenceError, NumericalError

if TYPE_CHECKING:  # pragma: no cover
    from shapecorr.data.datasets import ShapeSample


@dataclass(frozen=True, eq=False)
class MatchResult:
    """The output of a matcher for one ordered pair (x, y).

    Attributes
    ----------
    p2p : (n_x,) int64 tensor
        Point-to-point map x -> y: for each vertex of x its vertex of y (zero-based).
    p2p_inv : (n_y,) int64 tensor, optional
        The map y -> x, when the method computes one.
    deformation : (T, n_x, 3) float tensor, optional
        Positions of x's vertices along an interpolation towards y (interpolating methods), in the
        normalized units of x; the last frame is the deformed x at ``times[-1]``.
    times : (T,) float tensor, optional
        Time of each deformation frame (0 = x, 1 = matched to y; values above 1 extrapolate); required with
        ``deformation``.
    extras : dict
        Anything else a method wants to hand to its own logging (ignored by the evaluation).
    """

    p2p: torch.Tensor
    p2p_inv: torch.Tensor | None = None
    deformation: torch.Tensor | None = None
    times: torch.Tensor | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.p2p, torch.Tensor):
            object.__setattr__(self, "p2p", torch.as_tensor(self.p2p))
        if self.p2p_inv is not None and not isinstance(self.p2p_inv, torch.Tensor):
            object.__setattr__(self, "p2p_inv", torch.as_tensor(self.p2p_inv))
        if self.deformation is not None and self.times is None:
            raise CorrespondenceError("a MatchResult with a deformation needs its frame times")

    def validate(self, n_x: int, n_y: int, pair: str | None = None) -> "MatchResult":
        """Check sizes, dtypes and ranges against the pair; returns ``self``.

        Parameters
        ----------
        n_x, n_y : int
            Vertex counts of x and y.
        pair : str, optional
            Pair name for the error messages.

        Raises
        ------
        CorrespondenceError
            Wrong length, non-integer dtype or index out of range.
        NumericalError
            Non-finite deformation or times.
        """
        where = f" (pair {pair})" if pair else ""
        _check_map(self.p2p, n_x, n_y, f"p2p{where}")
        if self.p2p_inv is not None:
            _check_map(self.p2p_inv, n_y, n_x, f"p2p_inv{where}")
        if self.deformation is not None:
            d = self.deformation
            if d.ndim != 3 or d.shape[1:] != (n_x, 3):
                raise CorrespondenceError(f"deformation{where} must be (T, {n_x}, 3), got {tuple(d.shape)}")
            if self.times.shape != (d.shape[0],):
                raise CorrespondenceError(f"times{where} must be ({d.shape[0]},), got {tuple(self.times.shape)}")
            if not (torch.isfinite(d).all() and torch.isfinite(self.times).all()):
                raise NumericalError(f"the deformation{where} contains NaN or infinite values")
        return self

    def cpu(self) -> "MatchResult":
        """Copy with every tensor on the CPU and detached from autograd."""
        move = lambda t: None if t is None else t.detach().cpu()  # noqa: E731
        return replace(
            self,
            p2p=move(self.p2p),
            p2p_inv=move(self.p2p_inv),
            deformation=move(self.deformation),
            times=move(self.times),
        )


def _check_map(p2p: torch.Tensor, n_source: int, n_target: int, what: str) -> None:
    if p2p.ndim != 1 or p2p.shape[0] != n_source:
        raise CorrespondenceError(
            f"{what} must have one entry per source vertex ({n_source}), got shape {tuple(p2p.shape)}"
        )
    if p2p.dtype.is_floating_point or p2p.dtype.is_complex or p2p.dtype == torch.bool:
        raise CorrespondenceError(f"{what} must hold integer vertex indices, got dtype {p2p.dtype}")
    if n_source and (int(p2p.min()) < 0 or int(p2p.max()) >= n_target):
        raise CorrespondenceError(
            f"{what} has indices in [{int(p2p.min())}, {int(p2p.max())}] but the target has {n_target} vertices"
        )


@runtime_checkable
class Matcher(Protocol):
    """Anything that maps an ordered pair of shapes (see the module docstring)."""

    def match(self, x: "ShapeSample", y: "ShapeSample") -> MatchResult:  # pragma: no cover - protocol
        """Map ``x`` to ``y``: a MatchResult with ``p2p (n_x,)`` int64 indices into ``y``."""
        ...
