"""Correspondence and deformation metrics (pure numpy functions).

Geodesic error (Princeton benchmark; docs/evaluation.md §1)
    For a pair (X, Y), reference points r = 1..R with vertex indices ``ref_x[r]`` on X and ``ref_y[r]`` on Y,
    and a point-to-point map ``p2p`` from X to Y, the error of reference point r is
    ``e_r = d_Y(p2p[ref_x[r]], ref_y[r]) / sqrt(area(Y))`` with ``d_Y`` the geodesic distance on Y. The
    *symmetric* variant uses the mirrored ground truth (``.sym.vts``) as ``ref_y``; it is a separate number,
    never mixed into the main error (no per-pair minimum of the two).

PCK curve
    The fraction of reference points with ``e_r <= t`` for thresholds ``t`` in [0, 0.25], and its area under
    the curve divided by the threshold range, so that a perfect map has AUC 1.

Conformal distortion (scale-invariant; a choice documented here)
    The Hamiltonian-interpolation evaluation (docs/evaluation.md §3) measures, per triangle,
    ``tr(M^T M) / det(M) - 3`` with ``M = G + n n^T``, G the pull-back metric of the deformed triangle
    in the rest triangle's plane. With singular values s1 >= s2 of the triangle's Jacobian, G has eigenvalues
    s1², s2² and the normal direction contributes an eigenvalue 1, which is what makes that number
    scale-dependent: a pure scaling by s gives 1/s⁴ - 1 instead of 0. We drop the normal block and evaluate the
    same expression on the 2x2 metric alone::

        D = tr(G²) / det(G) - 2 = (s1/s2 - s2/s1)² = (K - 1/K)²,   K = s1/s2 (quasi-conformal dilatation)

    D is 0 exactly for conformal (angle-preserving) triangles, invariant to any uniform scaling of either
    shape, to rigid motions, and to reflections. It is computed without an SVD from the rest and deformed
    Gram matrices g, h of the edge vectors e1 = v1 - v0, e2 = v2 - v0:
    ``tr(g⁻¹h)² / det(g⁻¹h) - 4``. Collapsed triangles (a p2p map sending two corners to one vertex) have
    infinite dilatation; like the original we clamp per-triangle values at 10. Means are weighted by the rest
    triangle areas, so the number does not depend on how finely X is triangulated. For a map between two
    different triangulations the "deformed" triangle is the source triangle with its corners moved to their
    images on the target (:func:`map_conformal_distortion`).

Chamfer distance
    Two-sided: ``mean_a min_b |a - b| + mean_b min_a |b - a|`` (unsquared, in the units of the points).
    One-sided (the variant of the interpolation papers, docs/evaluation.md §4): only the first term, from the
    deformed source to the target.

Volume change and cycle consistency
    Relative volume change ``V(deformed)/V(rest) - 1`` of a closed mesh, the symmetric score
    ``V1/V0 + V0/V1 - 2`` of the interpolation papers, and the geodesic distance between each vertex of X and
    its image under the composition X -> Y -> Z -> X, normalized by sqrt(area(X)).

All functions accept numpy arrays or CPU/GPU torch tensors (converted with ``np.asarray`` after moving to the
CPU), compute in float64 and return numpy arrays or Python floats. Non-finite results raise
:class:`~shapecorr.errors.NumericalError`.
"""

from __future__ import annotations

import numpy as np
import scipy.integrate
from scipy.spatial import cKDTree

from shapecorr.errors import CorrespondenceError, InvalidMeshError, NumericalError
from shapecorr.geometry.mesh import as_numpy, triangle_areas
from shapecorr.geometry.mesh import check_index as _check_index

#: Largest PCK threshold, as a fraction of sqrt(area) (docs/evaluation.md §2: thresholds 0..0.25).
PCK_MAX_THRESHOLD = 0.25
#: Number of PCK thresholds: steps of 0.0025 over [0, 0.25].
PCK_N_THRESHOLDS = 101
#: Per-triangle conformal distortion is clamped at this value, as in the evaluation of the Hamiltonian
#: interpolation paper (docs/evaluation.md §3: ``min(|...|, 10)``); collapsed triangles get it.
CONFORMAL_DISTORTION_CLAMP = 10.0
#: A rest triangle whose area is below this fraction of the mean triangle area has no defined shape; it gets
#: the clamp value and weight zero in means.
DEGENERATE_AREA_RTOL = 1e-12


def _check_finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(values)):
        bad = int((~np.isfinite(values)).sum())
        raise NumericalError(f"{what}: {bad} of {values.size} values are NaN or infinite")
    return values


# --------------------------------------------------------------------------------------------------------
# Geodesic error and PCK
# --------------------------------------------------------------------------------------------------------
def surface_area(verts, faces) -> float:
    """Total area of a triangle mesh.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int

    Returns
    -------
    float
    """
    return float(triangle_areas(as_numpy(verts, np.float64), as_numpy(faces)).sum())


def geodesic_errors(p2p, dist_y, ref_x, ref_y, sqrt_area_y: float) -> np.ndarray:
    """Per-reference-point geodesic error of a point-to-point map (Princeton protocol).

    Parameters
    ----------
    p2p : (n_x,) int
        For each vertex of X its matched vertex of Y (zero-based).
    dist_y : (n_y, n_y) float, or SourceDistances
        Geodesic distances on Y: a full matrix (``dist_y[a, b]`` is used with a = prediction, b = ground
        truth), or the rows from Y's ground-truth points (:class:`~shapecorr.geometry.geodesics.SourceDistances`,
        whose sources must include every ``ref_y``; then ``d(ref_y[r], p2p[ref_x[r]])`` is read from row
        ``ref_y[r]``, memory ``O(R n_y)``).
    ref_x : (R,) int
        Vertex of X of each reference point.
    ref_y : (R,) int
        Ground-truth vertex of Y of each reference point (``.vts``; ``.sym.vts`` for the symmetric variant).
    sqrt_area_y : float
        sqrt of the total area of Y, in the units of ``dist_y``.

    Returns
    -------
    (R,) float64
        ``d_Y(p2p[ref_x], ref_y) / sqrt_area_y``.
    """
    rows = callable(getattr(dist_y, "lookup", None))
    if rows:
        n_y = dist_y.n_verts
    else:
        dist_y = as_numpy(dist_y)
        if dist_y.ndim != 2 or dist_y.shape[0] != dist_y.shape[1]:
            raise CorrespondenceError(f"dist_y must be a square (n_y, n_y) matrix, got shape {dist_y.shape}")
        n_y = dist_y.shape[0]
    p2p = _check_index(p2p, n_y, "p2p (map X -> Y)")
    ref_x = _check_index(ref_x, p2p.shape[0], "reference points on X")
    ref_y = _check_index(ref_y, n_y, "reference points on Y")
    if ref_x.shape != ref_y.shape:
        raise CorrespondenceError(
            f"ground truth lengths differ: {ref_x.shape[0]} reference points on X, {ref_y.shape[0]} on Y"
        )
    if not sqrt_area_y > 0:
        raise NumericalError(f"sqrt(area) of the target must be positive, got {sqrt_area_y}")
    if rows:
        errors = dist_y.lookup(ref_y, p2p[ref_x]) / float(sqrt_area_y)
    else:
        errors = dist_y[p2p[ref_x], ref_y].astype(np.float64) / float(sqrt_area_y)
    return _check_finite(errors, "geodesic errors (is the target mesh disconnected?)")


def pck_curve(errors, thresholds=None) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative error curve: fraction of points with error <= threshold.

    Parameters
    ----------
    errors : (m,) float
        Per-point errors (pooled over pairs), as fractions of sqrt(area).
    thresholds : (t,) float, optional
        Increasing thresholds; default ``linspace(0, PCK_MAX_THRESHOLD, PCK_N_THRESHOLDS)``.

    Returns
    -------
    thresholds : (t,) float64
    fractions : (t,) float64 in [0, 1], non-decreasing
    """
    errors = _check_finite(as_numpy(errors, np.float64).ravel(), "errors")
    if errors.size == 0:
        raise CorrespondenceError("cannot build a PCK curve from zero errors")
    if thresholds is None:
        thresholds = np.linspace(0.0, PCK_MAX_THRESHOLD, PCK_N_THRESHOLDS)
    thresholds = as_numpy(thresholds, np.float64).ravel()
    if thresholds.size < 2 or np.any(np.diff(thresholds) <= 0):
        raise CorrespondenceError("PCK thresholds must be at least two strictly increasing values")
    fractions = np.searchsorted(np.sort(errors), thresholds, side="right") / errors.size
    return thresholds, fractions


def pck_auc(thresholds, fractions) -> float:
    """Normalized area under a PCK curve: the trapezoid integral divided by the threshold range (1 = perfect).

    Parameters
    ----------
    thresholds : (t,) float
    fractions : (t,) float

    Returns
    -------
    float in [0, 1]
    """
    t = as_numpy(thresholds, np.float64)
    f = as_numpy(fractions, np.float64)
    return float(scipy.integrate.trapezoid(f, t) / (t[-1] - t[0]))


# --------------------------------------------------------------------------------------------------------
# Conformal distortion
# --------------------------------------------------------------------------------------------------------
def _gram(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entries (g11, g12, g22) of the Gram matrix of the edges e1 = v1 - v0, e2 = v2 - v0 of each triangle."""
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    return (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)


def conformal_distortion(verts_rest, faces, verts_deformed, clamp: float = CONFORMAL_DISTORTION_CLAMP) -> np.ndarray:
    """Per-triangle scale-invariant conformal distortion ``(K - 1/K)²`` (see the module docstring).

    Parameters
    ----------
    verts_rest : (n, 3) float
        Rest positions.
    faces : (f, 3) int
        Triangles (shared by both states).
    verts_deformed : (n, 3) float
        Deformed positions (or the images of the vertices under a map).
    clamp : float
        Upper bound of the per-triangle value; collapsed and degenerate triangles get it.

    Returns
    -------
    (f,) float64 in [0, clamp]
    """
    rest = _check_finite(as_numpy(verts_rest, np.float64), "rest vertices")
    deformed = _check_finite(as_numpy(verts_deformed, np.float64), "deformed vertices")
    faces = as_numpy(faces).astype(np.int64, copy=False)
    if rest.shape != deformed.shape or rest.ndim != 2 or rest.shape[1] != 3:
        raise InvalidMeshError(f"rest and deformed vertices must both be (n, 3), got {rest.shape} and {deformed.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.size == 0:
        raise InvalidMeshError(f"faces must be a non-empty (f, 3) array, got shape {faces.shape}")
    _check_index(faces.ravel(), rest.shape[0], "face indices")
    g11, g12, g22 = _gram(rest, faces)
    h11, h12, h22 = _gram(deformed, faces)
    det_g = g11 * g22 - g12 * g12  # (2 * rest area)^2
    det_h = h11 * h22 - h12 * h12
    # det(g) tr(g^-1 h) = g22 h11 - 2 g12 h12 + g11 h22, so tr(g^-1 h)^2 / det(g^-1 h) = num^2 / (det g det h).
    num = g22 * h11 - 2.0 * g12 * h12 + g11 * h22
    den = det_g * det_h
    rest_degenerate = det_g <= (DEGENERATE_AREA_RTOL * np.mean(np.sqrt(np.maximum(det_g, 0.0)))) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        value = np.where(den > 0, num * num / np.where(den > 0, den, 1.0) - 4.0, np.inf)
    value = np.where(rest_degenerate, clamp, value)
    return np.clip(value, 0.0, clamp)


def mean_conformal_distortion(verts_rest, faces, verts_deformed, clamp: float = CONFORMAL_DISTORTION_CLAMP) -> float:
    """Rest-area-weighted mean of :func:`conformal_distortion` (degenerate rest triangles have weight 0).

    Parameters
    ----------
    verts_rest : (n, 3) float
    faces : (f, 3) int
    verts_deformed : (n, 3) float
    clamp : float

    Returns
    -------
    float in [0, clamp]
    """
    values = conformal_distortion(verts_rest, faces, verts_deformed, clamp)
    weights = triangle_areas(as_numpy(verts_rest, np.float64), as_numpy(faces))
    if not weights.sum() > 0:
        raise InvalidMeshError("the rest mesh has zero total area")
    return float((values * weights).sum() / weights.sum())


def map_conformal_distortion(verts_x, faces_x, verts_y, p2p, clamp: float = CONFORMAL_DISTORTION_CLAMP) -> float:
    """Conformal distortion of a point-to-point map: the triangles of X with their corners moved to their images.

    Parameters
    ----------
    verts_x : (n_x, 3) float
    faces_x : (f_x, 3) int
    verts_y : (n_y, 3) float
    p2p : (n_x,) int
        Map X -> Y.
    clamp : float

    Returns
    -------
    float in [0, clamp]
        Area-weighted mean over the triangles of X.
    """
    verts_y = as_numpy(verts_y, np.float64)
    p2p = _check_index(p2p, verts_y.shape[0], "p2p (map X -> Y)")
    verts_x = as_numpy(verts_x, np.float64)
    if p2p.shape[0] != verts_x.shape[0]:
        raise CorrespondenceError(f"the map has {p2p.shape[0]} entries but X has {verts_x.shape[0]} vertices")
    return mean_conformal_distortion(verts_x, faces_x, verts_y[p2p], clamp)


# --------------------------------------------------------------------------------------------------------
# Chamfer, volume, cycle consistency
# --------------------------------------------------------------------------------------------------------
def nearest_neighbor_distances(points, targets) -> np.ndarray:
    """Euclidean distance from each point to its nearest target point (k-d tree).

    Parameters
    ----------
    points : (n, d) float
    targets : (m, d) float

    Returns
    -------
    (n,) float64
    """
    points = _check_finite(as_numpy(points, np.float64), "points")
    targets = _check_finite(as_numpy(targets, np.float64), "target points")
    if len(points) == 0 or len(targets) == 0:
        raise CorrespondenceError("nearest-neighbour distances need non-empty point sets")
    dist, _ = cKDTree(targets).query(points, k=1)
    return dist


def chamfer_distance(points_a, points_b, one_sided: bool = False) -> float:
    """Chamfer distance between two point sets (unsquared mean nearest-neighbour distances).

    Parameters
    ----------
    points_a : (n, 3) float
        E.g. the deformed source at t = 1.
    points_b : (m, 3) float
        E.g. the target.
    one_sided : bool
        False: ``mean_a d(a, B) + mean_b d(b, A)``. True: ``mean_a d(a, B)`` only, the variant reported by
        the interpolation papers (docs/evaluation.md §4; they average 10000 samples drawn with replacement,
        we average over all points).

    Returns
    -------
    float, in the units of the points
    """
    forward = float(nearest_neighbor_distances(points_a, points_b).mean())
    if one_sided:
        return forward
    return forward + float(nearest_neighbor_distances(points_b, points_a).mean())


def mesh_volume(verts, faces, path=None) -> float:
    """Signed volume enclosed by a closed, consistently oriented triangle mesh (positive for outward normals).

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    path : optional
        Named in the error message.

    Returns
    -------
    float

    Raises
    ------
    InvalidMeshError
        The mesh is not watertight (has boundary or non-manifold edges) or not consistently oriented.
    """
    import trimesh

    mesh = trimesh.Trimesh(as_numpy(verts, np.float64), as_numpy(faces).astype(np.int64), process=False)
    if not mesh.is_watertight:
        raise InvalidMeshError("the enclosed volume needs a closed (watertight) mesh", path)
    if not mesh.is_winding_consistent:
        raise InvalidMeshError("the enclosed volume needs consistently oriented faces", path)
    # trimesh.triangles.mass_properties: divergence-theorem volume, signed by the face orientation.
    return float(trimesh.triangles.mass_properties(mesh.triangles, skip_inertia=True).volume)


def relative_volume_change(verts_rest, faces, verts_deformed) -> float:
    """``V(deformed) / V(rest) - 1`` of a closed mesh (0 = volume preserved; signed).

    Parameters
    ----------
    verts_rest : (n, 3) float
    faces : (f, 3) int
    verts_deformed : (n, 3) float

    Returns
    -------
    float
    """
    v0 = mesh_volume(verts_rest, faces)
    v1 = mesh_volume(verts_deformed, faces)
    if v0 == 0:
        raise NumericalError("the rest mesh encloses zero volume; the relative volume change is undefined")
    return _check_finite(np.asarray(v1 / v0 - 1.0), "relative volume change").item()


def volume_change_score(verts_rest, faces, verts_deformed) -> float:
    """Symmetric volume score ``r + 1/r - 2`` with ``r = V(deformed)/V(rest)`` (docs/evaluation.md §4).

    Zero when the volume is preserved, the same for shrinking and growing by the same factor.

    Returns
    -------
    float >= 0
    """
    r = relative_volume_change(verts_rest, faces, verts_deformed) + 1.0
    if r <= 0:
        raise NumericalError(f"the deformed mesh is inverted (volume ratio {r:.3g} <= 0)")
    return float(r + 1.0 / r - 2.0)


def compose_maps(*maps) -> np.ndarray:
    """Compose point-to-point maps in order: ``compose_maps(p_xy, p_yz)[i] = p_yz[p_xy[i]]``.

    Parameters
    ----------
    *maps : (n_k,) int
        Consecutive maps; the values of each index the next.

    Returns
    -------
    (n_0,) int64
    """
    if not maps:
        raise CorrespondenceError("compose_maps needs at least one map")
    out = as_numpy(maps[0]).astype(np.int64)
    for k, nxt in enumerate(maps[1:], 1):
        nxt = as_numpy(nxt).astype(np.int64)
        out = nxt[_check_index(out, nxt.shape[0], f"map {k - 1} of the composition")]
    return out


def cycle_consistency_errors(p_xy, p_yz, p_zx, dist_x, sqrt_area_x: float) -> np.ndarray:
    """Geodesic distance between each vertex of X and its image under X -> Y -> Z -> X.

    Parameters
    ----------
    p_xy : (n_x,) int
    p_yz : (n_y,) int
    p_zx : (n_z,) int
    dist_x : (n_x, n_x) float
        Geodesic distances on X.
    sqrt_area_x : float

    Returns
    -------
    (n_x,) float64
        ``dist_x[i, p_zx[p_yz[p_xy[i]]]] / sqrt_area_x`` (0 for a cycle-consistent triple).
    """
    cycle = compose_maps(p_xy, p_yz, p_zx)
    dist_x = as_numpy(dist_x)
    if dist_x.shape != (cycle.shape[0], cycle.shape[0]):
        raise CorrespondenceError(f"dist_x has shape {dist_x.shape} but X has {cycle.shape[0]} vertices")
    cycle = _check_index(cycle, cycle.shape[0], "cycle X -> Y -> Z -> X")
    return geodesic_errors(cycle, dist_x, np.arange(cycle.shape[0]), np.arange(cycle.shape[0]), sqrt_area_x)
