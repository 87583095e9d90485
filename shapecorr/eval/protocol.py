"""Per-pair evaluation: run a matcher on one ordered pair, score its map against the ground truth, store it.

Protocol (docs/evaluation.md §1): for a pair (X, Y) the map X -> Y is scored at
the reference points of the ground truth (``corres/<name>.vts``; the identity for shapes sharing their
connectivity without ``.vts``) with geodesic distances on Y from the shape cache, normalized by sqrt(area(Y))
computed from Y's faces. The cache holds, per target, the rows from its ground-truth points only
(``e_r = d_Y(p(gx[r]), gy[r])`` is read from row ``gy[r]``; ``R x n`` float32, never ``n x n``).
Reference points on small islands of X or Y (connected components other than the largest) are excluded and
counted (``n_excluded`` per pair, ``n_excluded_points`` in ``metrics.json``); a prediction that lands on an
island of Y is scored at the nearest vertex of Y's largest component. When Y has a mirrored ground truth
(``.sym.vts``) the same map is also scored against it; that number is reported separately and never mixed into
the main error.

Per pair, under the output folder::

    maps/<x>__<y>.txt, maps/<x>__<y>.npy     the map (see :mod:`shapecorr.eval.export`)
    interp/<x>__<y>/t_XX.ply, times.txt      interpolation frames, for matchers returning a deformation
    pairs/<x>__<y>.npz                       per-reference-point errors (``errors``, ``errors_sym``)
    pairs/<x>__<y>.json                      the :class:`PairRecord`, written last

Interpolating matchers: a matcher *interpolates* when it has a method
``interpolate(x, y, times: (T,) float tensor) -> MatchResult`` whose ``deformation (T, n_x, 3)`` holds x's
vertices at those times (t = 0: x, t = 1: x deformed onto y, t > 1: an extrapolation); its ``match(x, y)``
returns the same maps and its default frames. With ``EvalSettings.interp_times`` set, :func:`run_matcher`
calls ``interpolate`` at those times, adding t = 1 when it is not among them (the metrics need that frame;
only the requested frames are written). Without ``interp_times``, or for a matcher that only has ``match``,
the frames of ``match`` are used. The deformation metrics (:func:`score_deformation`) compare the frame at
t = 1 with y and average the conformal distortion over the frames with 0 <= t <= 1 (extrapolated frames are
written, not scored).

A pair is *done* when its record exists (every file is written atomically and the record last), so an
interrupted run resumes with the pairs that are missing.

Parallelism: :func:`evaluate_pairs` runs pairs in ``workers`` CPU processes (each holding a copy of the
matcher and the dataset); with ``workers=0`` everything runs in the calling process, which is what a
matcher on a GPU needs. Under DDP every rank evaluates its shard (:func:`shard_pairs`) into the same folder;
the records are the per-pair results that rank 0 merges afterwards (``shapecorr.cli.evaluate``).
"""

from __future__ import annotations

import itertools
import json
import multiprocessing
import os
import time
import warnings
from collections import OrderedDict
from concurrent.futures import FIRST_EXCEPTION, wait
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import check_pair_names, pair_name
from shapecorr.data.ground_truth import ground_truth_indices
from shapecorr.data.validation import MeshWarning
from shapecorr.data.workers import process_pool, submit_all
from shapecorr.errors import ConfigError, CorrespondenceError, InvalidMeshError, NumericalError
from shapecorr.eval import metrics
from shapecorr.eval.export import write_map_files, write_sequence
from shapecorr.matching.result import MatchResult

RECORDS_DIR = "pairs"
#: Number of ShapeSamples (eigenbasis + descriptors) kept in memory per process (~5 MB each at 5k vertices).
DEFAULT_SAMPLE_CACHE = 32
#: Number of per-shape geodesic rows (from the ground-truth points, 4 R n bytes: 70 MB for FAUST_r) kept in memory
#: per process.
DEFAULT_GEODESIC_CACHE = 2
GEODESIC_METHODS = ("heat", "exact")
#: The time of the frame compared with the target (x fully deformed onto y).
UNIT_TIME = 1.0
#: ``MatchResult.extras`` key of a post-processed matcher's map before its refinement (scored as
#: ``PairRecord.initial_mean_error``).
INITIAL_MAP_KEY = "initial_p2p"
#: ``MatchResult.extras`` key: seconds spent on the map before ``match`` (a multi-shape matcher's queries), added
#: to the pair's ``seconds``.
PRECOMPUTED_SECONDS_KEY = "precomputed_seconds"
#: Two frame times closer than this are the same time (float32 tensors carry times to ~1e-7).
TIME_ATOL = 1e-6
START_METHODS = ("spawn", "forkserver", "fork")


@dataclass
class PairRecord:
    """Scalar results of one evaluated pair (the row of ``per_pair.csv``).

    Attributes
    ----------
    source, target : str
        Shape names; the map goes from source to target.
    mean_error, median_error : float
        Over the reference points, as fractions of sqrt(area(target)).
    n_points : int
        Number of reference points.
    seconds : float
        Wall time of the matcher alone (``match``, or ``interpolate`` at the interpolation times), including
        moving the pair to the device.
    eval_seconds : float
        Wall time of everything else for this pair (loading, scoring, writing).
    conformal_distortion : float
        Area-weighted conformal distortion of the map (:func:`shapecorr.eval.metrics.map_conformal_distortion`).
    mean_error_sym : float or None
        Mean error against the mirrored ground truth, when the target has one.
    chamfer, chamfer_one_sided, volume_change, deformation_conformal_distortion : float or None
        For matchers returning a deformation (interpolating matchers), from :func:`score_deformation`:
        two-sided / one-sided Chamfer distance between the frame at t = 1 and the target (fractions of
        sqrt(area(target))), relative volume change of that frame (closed meshes only), and the conformal
        distortion of the frames with 0 <= t <= 1 averaged over those frames. None otherwise.
    n_excluded : int
        Reference points excluded because they lie on a small island of the source or target mesh.
    volume_score : float or None
        ``V_1/V_0 + V_0/V_1 - 2`` of the frame at t = 1 (closed meshes only; interpolating matchers).
    curve_times, curve_conformal_distortion, curve_volume_score : list or None
        Interpolating matchers: the time of every computed frame (extrapolated ones and an added t = 1
        included) and that frame's conformal distortion and volume score (None entries: open mesh or
        inverted frame). Kept in ``pairs/<x>__<y>.json``; not columns of ``per_pair.csv``.
    initial_mean_error : float or None
        Post-processed matchers (``postprocess=``, whose result carries ``extras["initial_p2p"]``): the mean
        error of the wrapped matcher's map before the refinement, on the same reference points; None otherwise.
    """

    source: str
    target: str
    mean_error: float
    median_error: float
    n_points: int
    seconds: float
    eval_seconds: float
    conformal_distortion: float
    mean_error_sym: float | None = None
    chamfer: float | None = None
    chamfer_one_sided: float | None = None
    volume_change: float | None = None
    deformation_conformal_distortion: float | None = None
    n_excluded: int = 0
    volume_score: float | None = None
    curve_times: list[float] | None = None
    curve_conformal_distortion: list[float] | None = None
    curve_volume_score: list[float | None] | None = None
    initial_mean_error: float | None = None

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PairRecord":
        """Record from a dict (e.g. a parsed JSON line); keys that are not fields are ignored."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


@dataclass(frozen=True)
class EvalSettings:
    """How pairs are evaluated.

    Attributes
    ----------
    geodesics : {"heat", "exact"}
        Geodesic distances used for the errors (``exact`` for final numbers, docs/evaluation.md §1).
    conformal_clamp : float
        Per-triangle clamp of the conformal distortion.
    write_maps : bool
        Write ``maps/<x>__<y>.txt`` and ``.npy``.
    write_interp : bool
        Write the interpolation frames of matchers returning a deformation as
        ``interp/<x>__<y>/t_XX.ply`` + ``times.txt`` (in x's input units).
    interp_times : tuple of float, optional
        Times at which interpolating matchers are evaluated and their frames written (finite, strictly
        increasing, t > 1 allowed); None: the frames ``match`` returns.
    device : str
        Device the pair is moved to before ``match`` (``cpu``, ``cuda:0``, ...).
    sample_cache, geodesic_cache : int
        In-memory LRU sizes per process.
    """

    geodesics: str = "heat"
    conformal_clamp: float = metrics.CONFORMAL_DISTORTION_CLAMP
    write_maps: bool = True
    write_interp: bool = True
    interp_times: tuple[float, ...] | None = None
    device: str = "cpu"
    sample_cache: int = DEFAULT_SAMPLE_CACHE
    geodesic_cache: int = DEFAULT_GEODESIC_CACHE

    def __post_init__(self):
        if self.geodesics not in GEODESIC_METHODS:
            raise ConfigError(f"geodesics must be one of {GEODESIC_METHODS}, got {self.geodesics!r}")
        if self.sample_cache < 1 or self.geodesic_cache < 1:
            raise ConfigError("sample_cache and geodesic_cache must be >= 1")
        if self.interp_times is not None:
            object.__setattr__(self, "interp_times", check_interp_times(self.interp_times))


# --------------------------------------------------------------------------------------------------------
# Scoring one map
# --------------------------------------------------------------------------------------------------------
def score_map(p2p, x, y, dist_y, clamp: float = metrics.CONFORMAL_DISTORTION_CLAMP) -> dict[str, Any]:
    """Score a map x -> y against the ground truth of the pair.

    Parameters
    ----------
    p2p : (n_x,) int
        Map x -> y.
    x, y : ShapeSample
        The pair (``corres``/``corres_sym`` give the ground truth).
    dist_y : (n_y, n_y) float, or SourceDistances
        Geodesic distances on y: a full matrix, or the rows from y's ground-truth points
        (:meth:`~shapecorr.data.datasets.ShapeDataset.ground_truth_geodesics`).
    clamp : float
        Conformal-distortion clamp.

    Returns
    -------
    dict with ``errors (R',)``, ``errors_sym (R',)`` or None, ``conformal_distortion`` (float) and
    ``n_excluded`` (int): reference points on a small island (a connected component other than the
    largest one) of x or y are excluded from the errors (see :func:`island_points`), ``R' = R - n_excluded``.
    """
    p2p = np.asarray(p2p.detach().cpu().numpy() if hasattr(p2p, "detach") else p2p)
    n_x, n_y = x.shape.n_verts, y.shape.n_verts
    if p2p.shape != (n_x,):
        raise CorrespondenceError(
            f"the map of pair {pair_name(x.name, y.name)} has {p2p.shape[0] if p2p.ndim else 0} entries but "
            f"{x.name} has {n_x} vertices"
        )
    shape_of = (dist_y.n_verts,) if hasattr(dist_y, "n_verts") else np.shape(dist_y)
    if shape_of not in ((n_y,), (n_y, n_y)):
        raise CorrespondenceError(f"geodesic distances of {y.name} have shape {shape_of}, expected ({n_y}, {n_y})")
    as_np = lambda t: None if t is None else t.detach().cpu().numpy()  # noqa: E731
    if (x.corres is None) != (y.corres is None):
        missing, other = (x, y) if x.corres is None else (y, x)
        where = missing.shape.path.parent.parent if missing.shape.path is not None else None
        raise CorrespondenceError(
            f"ground truth corres/{missing.name}.vts is missing for {missing.name} but present for {other.name}: "
            f"add it, or evaluate only shapes that all have (or all lack) ground truth",
            where,
        )
    faces_x, faces_y = as_np(x.shape.faces), as_np(y.shape.faces)
    verts_x, verts_y = as_np(x.shape.verts), as_np(y.shape.verts)
    ref_x, ref_y = ground_truth_indices(as_np(x.corres), as_np(y.corres), n_x, n_y, faces_x, faces_y)
    sym_y = as_np(y.corres_sym) if (y.corres_sym is not None and x.corres is not None) else None
    keep = np.ones(ref_x.shape, dtype=bool)
    for sample, refs in ((x, ref_x), (y, ref_y), (y, sym_y)):
        if refs is not None:
            on_body = island_points(sample, refs)
            _warn_islands_once(sample, int((~on_body).sum()), on_body.size)
            keep &= on_body
    n_excluded = int((~keep).sum())
    sqrt_area_y = float(np.sqrt(metrics.surface_area(verts_y, faces_y)))
    mapped = _onto_main_component(y, p2p)
    errors = metrics.geodesic_errors(mapped, dist_y, ref_x[keep], ref_y[keep], sqrt_area_y)
    errors_sym = None
    if sym_y is not None:
        errors_sym = metrics.geodesic_errors(mapped, dist_y, ref_x[keep], sym_y[keep], sqrt_area_y)
    distortion = metrics.map_conformal_distortion(verts_x, faces_x, verts_y, p2p, clamp)
    return {"errors": errors, "errors_sym": errors_sym, "conformal_distortion": distortion, "n_excluded": n_excluded}


class IslandWarning(UserWarning):
    """Reference points on small islands of a mesh were excluded from the errors (one warning per file)."""


#: Files already warned about by :func:`_warn_islands_once` in this process.
_WARNED_ISLANDS: set[str] = set()


def _warn_islands_once(sample, n_off: int, n_refs: int) -> None:
    where = str(sample.shape.path or sample.name)
    if n_off == 0 or where in _WARNED_ISLANDS:
        return
    _WARNED_ISLANDS.add(where)
    warnings.warn(
        f"{where}: {n_off} of {n_refs} reference points lie on small islands (connected components other than "
        "the largest); they are excluded from the geodesic errors of every pair with this shape (counted in "
        "n_excluded_points of metrics.json)",
        IslandWarning,
        stacklevel=3,
    )


def _main_component(sample) -> np.ndarray | None:
    """``(n,)`` bool mask of the largest connected component of a sample's mesh, or None when connected."""
    from shapecorr.geometry.geodesics import vertex_components

    n_comp, labels = vertex_components(sample.shape.n_verts, sample.shape.faces.detach().cpu().numpy())
    if n_comp == 1:
        return None
    return labels == np.argmax(np.bincount(labels))


def island_points(sample, refs) -> np.ndarray:
    """``(R,)`` bool: True for the reference vertices ``refs (R,)`` on the largest component of the mesh.

    Scans often carry tiny floating pieces beside the body; the geodesic distance from the body to them is
    infinite, so reference points there cannot be scored and are excluded (and counted).
    """
    main = _main_component(sample)
    refs = np.asarray(refs, dtype=np.int64)
    return np.ones(refs.shape, dtype=bool) if main is None else main[refs]


def _onto_main_component(y, p2p: np.ndarray) -> np.ndarray:
    """``p2p`` with the vertices mapped onto small islands of y moved to y's largest component.

    Every vertex mapped onto a small island of y goes to the nearest (Euclidean) vertex of y's largest
    component, so that its error is finite and large rather than infinite.
    """
    main = _main_component(y)
    if main is None:
        return p2p
    off = ~main[p2p]
    if not off.any():
        return p2p
    from scipy.spatial import cKDTree

    verts = y.shape.verts.detach().cpu().numpy()
    body = np.flatnonzero(main)
    _, nearest = cKDTree(verts[body]).query(verts[p2p[off]])
    out = p2p.copy()
    out[off] = body[nearest]
    return out


def unit_time_index(times, atol: float = TIME_ATOL) -> int | None:
    """Index of the frame at t = 1 in ``times (T,)``, or None when there is none."""
    times = metrics.as_numpy(times, np.float64).reshape(-1)
    hits = np.flatnonzero(np.abs(times - UNIT_TIME) <= atol)
    return int(hits[0]) if hits.size else None


def score_deformation(
    frames, x, y, clamp: float = metrics.CONFORMAL_DISTORTION_CLAMP, times=None
) -> dict[str, float | None]:
    """Metrics of an interpolation of x towards y (docs/evaluation.md §4, scale-invariant where it matters).

    Parameters
    ----------
    frames : (T, n_x, 3) float
        Positions of x's vertices over time (normalized units).
    x, y : ShapeSample
    clamp : float
        Per-triangle clamp of the conformal distortion.
    times : (T,) float, optional
        Time of each frame. Given: the frame at t = 1 is compared with y and the conformal distortion is
        averaged over the frames with 0 <= t <= 1 (extrapolated frames are not scored). None: the last
        frame is compared with y and every frame is averaged.

    Returns
    -------
    dict with ``chamfer`` and ``chamfer_one_sided`` (frame at t = 1 vs y, fractions of sqrt(area(y))),
    ``volume_change`` (relative, that frame vs x; None when x is not a closed mesh), ``volume_score``
    (``V_1/V_0 + V_0/V_1 - 2`` of that frame; None likewise), ``deformation_conformal_distortion`` (mean over
    the scored frames) and the curves over every frame, extrapolated ones included: ``curve_times (T,)``,
    ``curve_conformal_distortion (T,)`` and ``curve_volume_score (T,)`` (lists of float; a volume entry is None
    for an open x or an inverted frame). Without ``times`` the frames are taken evenly spaced over [0, 1].

    Raises
    ------
    CorrespondenceError
        ``times`` does not match the frames or has no frame at t = 1.
    """
    frames = metrics.as_numpy(frames, np.float64)
    if times is None:
        unit, scored = frames.shape[0] - 1, np.ones(frames.shape[0], dtype=bool)
    else:
        times = metrics.as_numpy(times, np.float64).reshape(-1)
        if times.shape[0] != frames.shape[0]:
            raise CorrespondenceError(f"{frames.shape[0]} frames but {times.shape[0]} times")
        unit = unit_time_index(times)
        if unit is None:
            raise CorrespondenceError(
                f"the interpolation of {pair_name(x.name, y.name)} has no frame at t = 1 (times {times.tolist()})"
            )
        scored = (times >= -TIME_ATOL) & (times <= UNIT_TIME + TIME_ATOL)
    verts_x = metrics.as_numpy(x.shape.verts, np.float64)
    faces_x = metrics.as_numpy(x.shape.faces)
    verts_y = metrics.as_numpy(y.shape.verts, np.float64)
    sqrt_area_y = float(np.sqrt(metrics.surface_area(verts_y, metrics.as_numpy(y.shape.faces))))
    last = frames[unit]
    try:
        volume = metrics.relative_volume_change(verts_x, faces_x, last)
    except InvalidMeshError:
        volume = None  # open or non-manifold source: the enclosed volume is undefined
    distortion_t = [metrics.mean_conformal_distortion(verts_x, faces_x, f, clamp) for f in frames]
    volume_t = [None if volume is None else _volume_score_or_none(verts_x, faces_x, f) for f in frames]
    frame_times = np.linspace(0.0, UNIT_TIME, frames.shape[0]) if times is None else times
    return {
        "chamfer": metrics.chamfer_distance(last, verts_y) / sqrt_area_y,
        "chamfer_one_sided": metrics.chamfer_distance(last, verts_y, one_sided=True) / sqrt_area_y,
        "volume_change": volume,
        "volume_score": volume_t[unit],
        "deformation_conformal_distortion": float(np.mean(np.asarray(distortion_t)[scored])),
        "curve_times": [float(t) for t in frame_times],
        "curve_conformal_distortion": [float(d) for d in distortion_t],
        "curve_volume_score": volume_t,
    }


def _volume_score_or_none(verts_x: np.ndarray, faces_x: np.ndarray, frame: np.ndarray) -> float | None:
    """``V_t/V_0 + V_0/V_t - 2`` of one frame of a closed x; None when the frame is inverted (V_t <= 0)."""
    try:
        return metrics.volume_change_score(verts_x, faces_x, frame)
    except NumericalError:
        return None


# --------------------------------------------------------------------------------------------------------
# Running a matcher on one pair
# --------------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------------
# Records on disk
# --------------------------------------------------------------------------------------------------------
def record_paths(out_dir: str | os.PathLike, source: str, target: str) -> tuple[Path, Path]:
    """``(json, npz)`` paths of a pair's record."""
    folder, stem = Path(out_dir) / RECORDS_DIR, pair_name(source, target)
    return folder / f"{stem}.json", folder / f"{stem}.npz"


def is_done(out_dir: str | os.PathLike, source: str, target: str) -> bool:
    """True when the pair's record and errors exist (it is skipped on re-run)."""
    js, npz = record_paths(out_dir, source, target)
    return js.is_file() and npz.is_file()


def write_record(
    out_dir: str | os.PathLike, record: PairRecord, errors: np.ndarray, errors_sym: np.ndarray | None
) -> None:
    """Write a pair's errors then its record (atomic files; the record marks the pair as done)."""
    js, npz = record_paths(out_dir, record.source, record.target)
    js.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"errors": np.asarray(errors, dtype=np.float32)}
    if errors_sym is not None:
        arrays["errors_sym"] = np.asarray(errors_sym, dtype=np.float32)
    with atomic_open(npz) as fh:
        np.savez(fh, **arrays)
    with atomic_open(js) as fh:
        fh.write(json.dumps(asdict(record), indent=1).encode())


def load_record(
    out_dir: str | os.PathLike, source: str, target: str
) -> tuple[PairRecord, np.ndarray, np.ndarray | None]:
    """Read back ``(record, errors, errors_sym)`` of a done pair."""
    js, npz = record_paths(out_dir, source, target)
    try:
        record = PairRecord.from_dict(json.loads(js.read_text()))
        with np.load(npz, allow_pickle=False) as data:
            errors = data["errors"].astype(np.float64)
            errors_sym = data["errors_sym"].astype(np.float64) if "errors_sym" in data.files else None
    except (OSError, ValueError, KeyError, TypeError) as err:
        problem = f"unreadable evaluation record ({err}); delete it to recompute the pair"
        raise CorrespondenceError(problem, js) from None
    return record, errors, errors_sym


# --------------------------------------------------------------------------------------------------------
# Running pairs
# --------------------------------------------------------------------------------------------------------
class _LRU:
    """A small least-recently-used cache of ``key -> value`` computed by a function."""

    def __init__(self, compute, size: int):
        self.compute, self.size, self.items = compute, size, OrderedDict()

    def __call__(self, key):
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        value = self.compute(key)
        self.items[key] = value
        while len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class PairEvaluator:
    """Evaluates pairs (i, j) of a ShapeDataset with one matcher and writes their outputs to ``out_dir``.

    Parameters
    ----------
    shapes : ShapeDataset
    matcher : Matcher
    out_dir : path
    settings : EvalSettings
    """

    def __init__(self, shapes, matcher, out_dir: str | os.PathLike, settings: EvalSettings = EvalSettings()):
        self.shapes, self.matcher, self.out_dir, self.settings = shapes, matcher, Path(out_dir), settings
        self.device = torch.device(settings.device)
        self.sample = _LRU(lambda i: shapes[i], settings.sample_cache)
        self.geodesics = _LRU(lambda j: shapes.ground_truth_geodesics(j, method=settings.geodesics),
                              settings.geodesic_cache)

    def __call__(self, i: int, j: int) -> PairRecord:
        """Match, score and write pair ``(i, j)`` (maps, sequence, per-pair record); return its record."""
        start = time.perf_counter()
        x, y = self.sample(i), self.sample(j)
        name = pair_name(x.name, y.name)
        t0 = time.perf_counter()
        xd, yd = x.to(self.device), y.to(self.device)
        with torch.no_grad():
            run = run_matcher(self.matcher, xd, yd, self.settings.interp_times)
        _synchronize(self.device)
        seconds = time.perf_counter() - t0 + float(run.result.extras.get(PRECOMPUTED_SECONDS_KEY, 0.0))
        result = run.result.cpu().validate(x.shape.n_verts, y.shape.n_verts, name)
        run = replace(run, result=result)
        scores = score_map(result.p2p, x, y, self.geodesics(j), self.settings.conformal_clamp)
        extra: dict[str, float | None] = {}
        if result.deformation is not None:
            extra = score_deformation(result.deformation, x, y, self.settings.conformal_clamp, times=result.times)
            if self.settings.write_interp:
                frames, times = run.sequence()
                write_sequence(self.out_dir, x.name, y.name, frames, x.shape.faces, times, shape=x.shape)
        if self.settings.write_maps:
            write_map_files(self.out_dir, x.name, y.name, result.p2p)
        errors, errors_sym = scores["errors"], scores["errors_sym"]
        initial = result.extras.get(INITIAL_MAP_KEY)
        if initial is not None:  # a post-processed matcher: score the map it started from as well
            initial_scores = score_map(initial, x, y, self.geodesics(j), self.settings.conformal_clamp)
            extra["initial_mean_error"] = float(initial_scores["errors"].mean())
        record = PairRecord(
            source=x.name,
            target=y.name,
            mean_error=float(errors.mean()),
            median_error=float(np.median(errors)),
            n_points=int(errors.shape[0]),
            n_excluded=int(scores["n_excluded"]),
            seconds=seconds,
            eval_seconds=0.0,
            conformal_distortion=float(scores["conformal_distortion"]),
            mean_error_sym=None if errors_sym is None else float(errors_sym.mean()),
            **extra,
        )
        record.eval_seconds = time.perf_counter() - start - seconds
        write_record(self.out_dir, record, errors, errors_sym)
        return record


_WORKER: PairEvaluator | None = None


def _init_worker(shapes, matcher, out_dir, settings, threads: int) -> None:
    global _WORKER
    import signal

    # Ctrl-C reaches the whole process group: the parent stops the workers and the run (one line, see
    # shapecorr.cli.evaluate) instead of each worker printing a traceback (already ignored from the start when
    # submitted with shapecorr.data.workers.submit_all).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # the calling process has loaded every mesh of the run and reported its warnings (ShapeDataset.prepare)
    warnings.simplefilter("ignore", MeshWarning)
    torch.set_num_threads(threads)
    _WORKER = PairEvaluator(shapes, matcher, out_dir, settings)


def _run_in_worker(i: int, j: int) -> PairRecord:
    assert _WORKER is not None, "worker not initialized"
    return _WORKER(i, j)


def evaluate_pairs(
    matcher,
    shapes,
    pairs: Sequence[tuple[int, int]],
    out_dir: str | os.PathLike,
    settings: EvalSettings = EvalSettings(),
    workers: int = 0,
    start_method: str = "spawn",
    progress: bool = True,
) -> list[PairRecord]:
    """Evaluate ordered pairs of ``shapes`` (skipping pairs already done) and return all their records.

    Parameters
    ----------
    matcher : Matcher
    shapes : ShapeDataset
    pairs : list of (i, j)
        Indices into ``shapes``; the map goes from i to j.
    out_dir : path
    settings : EvalSettings
    workers : int
        CPU worker processes; 0 runs in this process (required for a matcher on a GPU).
    start_method : {"spawn", "forkserver", "fork"}
        How worker processes start (spawn is safe with threaded libraries; fork starts faster on Linux).
    progress : bool
        Show a progress bar.

    Returns
    -------
    list of PairRecord, in the order of ``pairs``
    """
    if start_method not in START_METHODS:
        raise ConfigError(f"start_method must be one of {START_METHODS}, got {start_method!r}")
    if workers < 0:
        raise ConfigError(f"workers must be >= 0, got {workers}")
    if workers > 0 and torch.device(settings.device).type != "cpu":
        raise ConfigError(f"parallel workers evaluate on the CPU only; use workers=0 with device={settings.device}")
    names = [(shapes.names[i], shapes.names[j]) for i, j in pairs]
    check_pair_names(names, getattr(shapes, "root", None))  # two pairs must never share one record
    todo = [p for p, (a, b) in zip(pairs, names) if not is_done(out_dir, a, b)]
    # Grouping by target lets each process reuse the target's geodesic matrix across consecutive pairs.
    todo.sort(key=lambda p: (p[1], p[0]))
    bar = tqdm(total=len(pairs), initial=len(pairs) - len(todo), desc="evaluating", unit="pair", disable=not progress)
    try:
        if workers == 0 or len(todo) <= 1:
            evaluator = PairEvaluator(shapes, matcher, out_dir, settings)
            for i, j in todo:
                evaluator(i, j)
                bar.update()
        else:
            # each worker gets its share of the CPUs, never more torch threads than this process has (which
            # honours OMP_NUM_THREADS): oversubscribed OpenMP threads spin and slow everything down
            threads = max(1, min(torch.get_num_threads(), (os.cpu_count() or 1) // workers))
            ctx = multiprocessing.get_context(start_method)
            # Ctrl-C: the workers ignore it and are terminated at once (shapecorr.data.workers); the pairs they
            # were running are lost (their files are written atomically), the finished ones are kept
            with process_pool(min(workers, len(todo)), ctx, _init_worker,
                              (shapes, matcher, str(out_dir), settings, threads)) as pool:
                pending = set(submit_all(pool, _run_in_worker, todo))
                while pending:
                    done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                    for future in done:
                        if future.exception() is not None:
                            raise future.exception()
                        bar.update()
    finally:
        bar.close()
    return [load_record(out_dir, a, b)[0] for a, b in names]


# --------------------------------------------------------------------------------------------------------
# DDP sharding
# --------------------------------------------------------------------------------------------------------
def count_done(out_dir: str | os.PathLike, names: Sequence[tuple[str, str]]) -> int:
    """How many of the pairs ``names`` (source, target) already have a record in ``out_dir``."""
    return sum(is_done(out_dir, a, b) for a, b in names)


def distributed_context() -> tuple[int, int]:
    """``(rank, world_size)``: from torch.distributed when initialized, else from the launcher's environment.

    The environment fallback reads ``RANK`` (set by torchrun; ``LOCAL_RANK`` when only that is set) and
    ``WORLD_SIZE``; without them the run is a single process ``(0, 1)``.
    """
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", os.environ.get("LOCAL_RANK", "0")))
    except ValueError as err:
        raise ConfigError(f"RANK / LOCAL_RANK / WORLD_SIZE must be integers: {err}") from None
    if world < 1 or not 0 <= rank < world:
        raise ConfigError(f"invalid distributed setting: rank {rank} of world size {world}")
    return rank, world


def shard_pairs(pairs: Sequence[Any], rank: int, world_size: int) -> list[Any]:
    """The pairs a rank evaluates: every ``world_size``-th pair starting at ``rank``.

    The shards are disjoint, cover every pair, keep the input order, and differ in size by at most one.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise ConfigError(f"invalid shard: rank {rank} of world size {world_size}")
    return list(pairs[rank::world_size])



# --------------------------------------------------------------------------------------------------------
# Run identity (resuming an output folder)
# --------------------------------------------------------------------------------------------------------
def data_settings(shapes) -> dict[str, Any]:
    """The settings of a :class:`~shapecorr.data.datasets.ShapeDataset` that change an evaluation's numbers.

    Folder, normalization, the resolved parameters of every operator it provides (``data.operators.*`` merged with
    the matcher's request), ``data.reference_points`` and ``data.validation.*``: part of ``run.json``, so that a
    resumed run never averages pairs computed with different settings.
    """
    return {
        "data_root": str(Path(shapes.root).resolve()),
        "normalization": repr(shapes.normalization),
        "operators": shapes.operators.resolve(),
        "reference_points": shapes.reference_points,
        "validation": asdict(shapes.validation),
    }


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict) and value:
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(_flat(item, f"{prefix}.{key}" if prefix else str(key)))
        return out
    return {prefix: value}


def fingerprint_changes(previous: Any, current: dict[str, Any]) -> list[str]:
    """``["key: old -> new", ...]`` for every setting (dotted keys, sorted) that differs between two run records.

    ``previous`` is the parsed ``run.json`` (anything else, e.g. None for an unreadable file, differs in every
    key); ``current`` is compared as JSON stores it (tuples are lists). Missing keys show as ``(unset)``.
    """
    current = json.loads(json.dumps(current))
    old, new = _flat(previous if isinstance(previous, dict) else {}), _flat(current)
    changes = []
    for key in sorted(set(old) | set(new)):
        if old.get(key, _UNSET) != new.get(key, _UNSET):
            show = [_UNSET_TEXT if v is _UNSET else json.dumps(v)[:60] for v in (old.get(key, _UNSET),
                                                                                 new.get(key, _UNSET))]
            changes.append(f"{key}: {show[0]} -> {show[1]}")
    return changes


_UNSET = object()
_UNSET_TEXT = "(unset)"
