"""Ground truth of the synthetic shapes: dense and sparse.

Dense: every vertex traced back to the template surface; sparse: ``.vts`` reference points in the FAUST_r
format, plus the mirrored ``.sym.vts``.

* **Dense.** A remeshed vertex lies on the posed template surface (the remesher projects onto it); its
  closest point there gives a template triangle and barycentric coordinates, i.e. a point of the canonical
  template, shared by every subject and pose of the class.
* **Sparse.** The reference points are ``R`` template vertices chosen by farthest point sampling (so any
  prefix of the list is itself well spread). On each shape, reference point ``r`` is the vertex nearest to
  template vertex ``ref[r]``, measured in the subject's *rest pose* (the dense trace places every remeshed
  vertex there), where separate body parts never touch; in the pose itself a hand resting on a thigh would
  make "nearest in 3D" ambiguous.
* **Mirror.** The creatures are left/right symmetric, so the mirrored ground truth maps reference point
  ``r`` to the template vertex nearest to the mirror image of ``ref[r]``.
* **Across classes.** Quadruped bones carry the names of their human homologues (forelimb = arm, hind
  limb = leg), and each template vertex has bone-local *chart* coordinates (position along its body
  part's bone, angle around it in the bone frame). A human reference vertex is mapped to the quadruped
  vertex of the same body part with the closest chart coordinates. This correspondence is semantic, not
  isometric (the quadruped tail has no human counterpart and is never a reference point).
"""

from __future__ import annotations

import igl
import numpy as np
from scipy.spatial import cKDTree

from shapecorr.data.synthetic.skeleton import plan_frames
from shapecorr.data.synthetic.templates import Template
from shapecorr.errors import ConfigError, NumericalError

#: Weight of the angular part of the chart coordinates relative to the normalized position along the bone
#: (an angle of 1 rad counts like 0.5 bone length).
CHART_ANGLE_WEIGHT = 0.5


def trace_to_surface(
    points: np.ndarray, verts: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point of each query point on a triangle mesh, as a face index and barycentric coordinates.

    Parameters
    ----------
    points : (m, 3) float
    verts : (n, 3) float
    faces : (f, 3) int

    Returns
    -------
    face : (m,) int64
    bary : (m, 3) float64, non-negative, rows sum to one
    dist : (m,) float64 distance to the surface
    """
    p = np.ascontiguousarray(points, np.float64)
    v = np.ascontiguousarray(verts, np.float64)
    f = np.ascontiguousarray(faces, np.int64)
    sq, face, closest = igl.point_mesh_squared_distance(p, v, f)
    tri = v[f[face]]
    bary = igl.barycentric_coordinates(
        np.ascontiguousarray(closest), np.ascontiguousarray(tri[:, 0]), np.ascontiguousarray(tri[:, 1]),
        np.ascontiguousarray(tri[:, 2]),
    )
    bary = np.clip(bary, 0.0, None)
    total = bary.sum(1, keepdims=True)
    if not (np.isfinite(bary).all() and np.all(total > 0)):
        raise NumericalError("barycentric coordinates of traced points are degenerate (zero-area triangle?)")
    return face.astype(np.int64), bary / total, np.sqrt(np.maximum(sq, 0.0))


def interpolate(values: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Evaluate per-vertex values at surface points given as (face, barycentric).

    Parameters
    ----------
    values : (n, k) float
    faces : (f, 3) int
    face : (m,) int
    bary : (m, 3) float

    Returns
    -------
    (m, k) float64
    """
    vals = np.asarray(values, np.float64)
    return np.einsum("mj,mjk->mk", np.asarray(bary, np.float64), vals[np.asarray(faces)[np.asarray(face)]])


def nearest_vertices(targets: np.ndarray, points: np.ndarray, candidates: np.ndarray | None = None) -> np.ndarray:
    """Index of the point nearest to every target (optionally among a subset of candidate points).

    Parameters
    ----------
    targets : (r, 3) float
    points : (m, 3) float
    candidates : (c,) int, optional

    Returns
    -------
    (r,) int64 indices into ``points``.
    """
    pts = np.asarray(points, np.float64)
    cand = np.arange(len(pts)) if candidates is None else np.asarray(candidates, np.int64)
    if len(cand) == 0:
        raise ConfigError("no candidate vertices to match the reference points to")
    _, idx = cKDTree(pts[cand]).query(np.asarray(targets, np.float64))
    return cand[idx].astype(np.int64)


def chart_coordinates(template: Template) -> np.ndarray:
    """Bone-local coordinates of the template vertices, comparable across creature classes.

    For vertex ``v`` of body part (dominant bone) ``b`` with joint ``h``, frame ``(lat, ref, axis)`` and length
    ``L``: ``t = (v - h) . axis / L`` and the angle ``phi`` of ``v - h`` around the axis, measured from ``lat``
    towards ``ref``.

    Returns
    -------
    (n, 3) float64 embedding ``(t, w cos phi, w sin phi)`` with ``w = CHART_ANGLE_WEIGHT``.
    """
    plan = template.plan
    frames = plan_frames(plan)
    heads, tails = plan.heads, plan.tails
    b = template.dominant
    rel = template.verts - heads[b]
    local = np.einsum("nij,ni->nj", frames[b], rel)
    length = np.linalg.norm(tails - heads, axis=1)[b]
    phi = np.arctan2(local[:, 1], local[:, 0])
    return np.column_stack([local[:, 2] / length, CHART_ANGLE_WEIGHT * np.cos(phi), CHART_ANGLE_WEIGHT * np.sin(phi)])


def chart_map(source: Template, target: Template, source_vertices: np.ndarray) -> np.ndarray:
    """Semantic correspondence of template vertices across classes through bone-local chart coordinates.

    Parameters
    ----------
    source, target : Template
    source_vertices : (r,) int
        Vertices of the source template.

    Returns
    -------
    (r,) int64 vertices of the target template (same body part, nearest chart coordinates).

    Raises
    ------
    ConfigError
        A source body part has no counterpart in the target.
    """
    idx = np.asarray(source_vertices, np.int64)
    src_chart, dst_chart = chart_coordinates(source), chart_coordinates(target)
    src_names = np.array(source.plan.bone_names)[source.dominant[idx]]
    dst_names = np.array(target.plan.bone_names)[target.dominant]
    out = np.empty(len(idx), dtype=np.int64)
    for name in np.unique(src_names):
        rows = np.flatnonzero(src_names == name)
        cand = np.flatnonzero(dst_names == name)
        if len(cand) == 0:
            raise ConfigError(f"body part {name!r} of {source.plan.name!r} has no counterpart in {target.plan.name!r}")
        _, nn = cKDTree(dst_chart[cand]).query(src_chart[idx[rows]])
        out[rows] = cand[nn]
    return out
