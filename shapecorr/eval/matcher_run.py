"""Running a matcher on one pair, at the interpolation times the evaluation asks for.

A matcher *interpolates* when it has a method
``interpolate(x, y, times: (T,) float tensor) -> MatchResult`` whose ``deformation (T, n_x, 3)`` holds x's
vertices at those times (t = 0: x, t = 1: x deformed onto y, t > 1: an extrapolation); its ``match(x, y)``
returns the same maps and its default frames. With ``EvalSettings.interp_times`` set, :func:`run_matcher`
calls ``interpolate`` at those times, adding t = 1 when it is not among them (the metrics need that frame;
only the requested frames are written). Without ``interp_times``, or for a matcher that only has ``match``,
the frames of ``match`` are used. The deformation metrics
(:func:`shapecorr.eval.scoring.score_deformation`) compare the frame at
t = 1 with y and average the conformal distortion over the frames with 0 <= t <= 1 (extrapolated frames are
written, not scored).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch

from shapecorr.data.datasets import pair_name
from shapecorr.errors import ConfigError, CorrespondenceError
from shapecorr.eval import metrics
from shapecorr.matching.result import MatchResult


#: The time of the frame compared with the target (x fully deformed onto y).
UNIT_TIME = 1.0
#: Two frame times closer than this are the same time (float32 tensors carry times to ~1e-7).
TIME_ATOL = 1e-6


def unit_time_index(times, atol: float = TIME_ATOL) -> int | None:
    """Index of the frame at t = 1 in ``times (T,)``, or None when there is none."""
    times = metrics.as_numpy(times, np.float64).reshape(-1)
    hits = np.flatnonzero(np.abs(times - UNIT_TIME) <= atol)
    return int(hits[0]) if hits.size else None


def interpolates(matcher) -> bool:
    """True when ``matcher`` has an ``interpolate(x, y, times)`` method (see the module docstring)."""
    return callable(getattr(matcher, "interpolate", None))


def check_interp_times(times) -> tuple[float, ...]:
    """Validate interpolation times: a non-empty, strictly increasing list of finite numbers.

    Returns
    -------
    tuple of float

    Raises
    ------
    ConfigError
    """
    try:
        values = tuple(float(t) for t in (times.tolist() if hasattr(times, "tolist") else times))
    except (TypeError, ValueError):
        raise ConfigError(f"interp_times must be a list of numbers, e.g. [0, 0.5, 1, 1.5]; got {times!r}") from None
    if not values:
        raise ConfigError("interp_times is empty; give a list of times, e.g. [0, 0.5, 1], or null")
    if not all(np.isfinite(values)):
        raise ConfigError(f"interp_times must be finite, got {list(values)}")
    if any(b - a <= TIME_ATOL for a, b in itertools.pairwise(values)):
        raise ConfigError(f"interp_times must be strictly increasing, got {list(values)}")
    return values


def with_unit_time(times) -> tuple[tuple[float, ...], np.ndarray]:
    """``times`` plus t = 1 when it is missing.

    Returns
    -------
    all_times : tuple of float
        Sorted, with a frame at t = 1.
    requested : (T,) int64
        Position of each of the given times in ``all_times``.
    """
    times = check_interp_times(times)
    if unit_time_index(times) is not None:
        return times, np.arange(len(times))
    all_times = tuple(sorted(times + (UNIT_TIME,)))
    unit = all_times.index(UNIT_TIME)
    return all_times, np.array([k if k < unit else k + 1 for k in range(len(times))], dtype=np.int64)


def _check_result(result, matcher, method: str) -> MatchResult:
    if result is None or not hasattr(result, "p2p"):
        raise ConfigError(f"{type(matcher).__name__}.{method} returned {type(result).__name__}, not a MatchResult")
    return result


@dataclass(frozen=True, eq=False)
class MatcherRun:
    """The result of :func:`run_matcher` and which of its frames to export.

    Attributes
    ----------
    result : MatchResult
        Maps and, for interpolating matchers, every computed frame (t = 1 included).
    export : (K,) int64 or None
        Indices of the frames to write (the requested times); None: every frame of ``result``.
    export_times : (K,) float64 or None
        Their times exactly as requested (written to ``times.txt``); None: ``result.times``.
    """

    result: MatchResult
    export: np.ndarray | None = None
    export_times: np.ndarray | None = None

    def sequence(self) -> tuple[torch.Tensor, np.ndarray] | None:
        """``(frames (K, n_x, 3), times (K,) float64)`` to write, or None without a deformation."""
        r = self.result
        if r.deformation is None:
            return None
        if self.export is None:
            # str() of a numpy scalar is the shortest decimal of its own precision: a float32 0.2 stays "0.2"
            return r.deformation, np.array([float(str(t)) for t in metrics.as_numpy(r.times).reshape(-1)])
        index = torch.as_tensor(self.export, device=r.deformation.device)
        return r.deformation.index_select(0, index), np.asarray(self.export_times, dtype=np.float64)


def run_matcher(matcher, x, y, interp_times=None) -> MatcherRun:
    """Run a matcher on the pair (x, y), interpolating at ``interp_times`` when it can.

    Parameters
    ----------
    matcher : Matcher
    x, y : ShapeSample
        On the matcher's device.
    interp_times : sequence of float, optional
        Times of the frames wanted from an interpolating matcher (see the module docstring).

    Returns
    -------
    MatcherRun
        Its ``result`` holds a frame at t = 1 whenever the matcher interpolates.

    Raises
    ------
    ConfigError
        The matcher returned something other than a MatchResult.
    CorrespondenceError
        ``interpolate`` returned frames at other times than requested.
    """
    if interp_times is not None and interpolates(matcher):
        return _interpolate(matcher, x, y, interp_times)
    result = _check_result(matcher.match(x, y), matcher, "match")
    if result.deformation is not None and interpolates(matcher) and unit_time_index(result.times) is None:
        return _interpolate(matcher, x, y, metrics.as_numpy(result.times, np.float64).tolist())
    return MatcherRun(result)


def _interpolate(matcher, x, y, requested) -> MatcherRun:
    all_times, export = with_unit_time(requested)
    times = torch.tensor(all_times, dtype=torch.float32, device=x.verts.device)
    result = _check_result(matcher.interpolate(x, y, times), matcher, "interpolate")
    got = None if result.times is None else metrics.as_numpy(result.times, np.float64).reshape(-1)
    if result.deformation is None or got is None or got.shape != times.shape or not np.allclose(
        got, all_times, rtol=0.0, atol=TIME_ATOL
    ):
        raise CorrespondenceError(
            f"{type(matcher).__name__}.interpolate of {pair_name(x.name, y.name)} was asked for frames at "
            f"{list(all_times)} but returned {'no deformation' if result.deformation is None else got.tolist()}"
        )
    return MatcherRun(result, export, np.asarray(check_interp_times(requested), dtype=np.float64))
