"""Scoring one map (and one interpolation) of a pair against its ground truth.

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
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from shapecorr.data.datasets import pair_name
from shapecorr.data.ground_truth import ground_truth_indices
from shapecorr.errors import CorrespondenceError, InvalidMeshError, NumericalError
from shapecorr.eval import metrics
from shapecorr.eval.matcher_run import TIME_ATOL, UNIT_TIME, unit_time_index


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
