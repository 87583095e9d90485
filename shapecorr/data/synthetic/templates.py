"""Canonical template meshes of the creature classes, with skinning weights and a left/right mirror map.

A template is built once per class: the smooth union of the body plan's primitives is sampled on a grid,
meshed by marching cubes, cleaned to a single watertight manifold genus-0 surface, and remeshed
isotropically. Every subject and pose of the class is a deformation of this one mesh, so the dense
correspondence between all shapes of a class is known exactly through the template's vertices.

Skinning weights: each template vertex is first assigned to the bone of the primitive closest to it
(smallest implicit value), then the one-hot weights are diffused over the surface with a few implicit heat
steps ``(M + tau L) W_{k+1} = M W_k``. Diffusion keeps partition of unity (``L 1 = 0``), blends smoothly across
joints, and never bleeds between parts that are close in space but far apart on the surface (unlike
Euclidean bone-distance weights).
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from scipy.special import logsumexp

from shapecorr.data.synthetic.meshing import clean_surface, extract_surface, topology_report
from shapecorr.data.synthetic.skeleton import BodyPlan, plan_frames
from shapecorr.errors import InvalidMeshError, NumericalError
from shapecorr.geometry.remeshing import remesh

#: Marching-cubes grid spacing (m) of the templates; the thinnest parts (wrists, tail tip) are >= 0.02 m in radius.
DEFAULT_GRID_STEP = 0.01
#: Primitives are evaluated only within this many blend radii of their bounding box (exp(-8) ~ 3e-4).
FIELD_REACH_BLENDS = 8.0
#: Before remeshing, the marching-cubes mesh is decimated to this many faces per target vertex (the
#: remesher's cost grows with its input; decimation moves the surface by < 4 mm on a 1200-vertex template).
DECIMATE_FACES_PER_VERTEX = 6
#: Accepted relative deviation of the template's vertex count from the requested one.
TEMPLATE_COUNT_RTOL = 0.1
#: Skinning blend width: standard deviation of the heat diffusion of the weights, in metres.
DEFAULT_SKIN_BLEND = 0.03
#: Number of implicit heat steps used to diffuse the weights (more steps = closer to a Gaussian kernel).
SKIN_DIFFUSION_STEPS = 4
#: Weights below this are set to zero (then rows are renormalized): keeps each vertex on a few bones.
SKIN_WEIGHT_CUTOFF = 1e-3


@dataclass(frozen=True, eq=False)
class Template:
    """The canonical rest-pose mesh of a creature class.

    Attributes
    ----------
    plan
        The body plan (bones, primitives).
    verts : (n, 3) float64
    faces : (f, 3) int64
    weights : (n, B) float64
        Skinning weights, rows sum to one.
    dominant : (n,) int64
        Bone each vertex was assigned to before diffusion (the body part it belongs to).
    mirror : (n,) int64
        Template vertex nearest to the mirror image (x -> -x) of each vertex.
    part_adjacency : (B, B) bool
        Body parts (dominant-bone regions) at most two steps apart on the surface: the same part, parts
        sharing a mesh edge, or parts both touching a third one (thigh and belly both touch the pelvis).
    """

    plan: BodyPlan
    verts: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    dominant: np.ndarray
    mirror: np.ndarray
    part_adjacency: np.ndarray

    @property
    def n_verts(self) -> int:
        """Number of vertices."""
        return int(len(self.verts))

    @property
    def area(self) -> float:
        """Total surface area."""
        return float(igl.doublearea(self.verts, self.faces).sum() / 2.0)


def primitive_distances(plan: BodyPlan, points: np.ndarray, reach: float | None = None) -> np.ndarray:
    """Approximate signed distances of points to every primitive of a body plan (negative inside).

    Round cones use the distance to the segment minus the linearly interpolated radius (Lipschitz
    constant ``1 + |rb - ra| / |b - a|``); ellipsoids use ``(|q / radii| - 1) * min(radii)`` with ``q`` the point
    in the ellipsoid frame, which is zero exactly on the surface and 1-Lipschitz. These bounds make the
    narrow-band sampling of :func:`shapecorr.data.synthetic.meshing.extract_surface` safe.

    Parameters
    ----------
    plan : BodyPlan
    points : (m, 3) float
    reach : float, optional
        When given, a primitive is only evaluated at points inside its bounding box grown by ``reach``;
        the others get the value ``reach`` (a lower bound of their true distance).

    Returns
    -------
    (P, m) float64, one row per primitive.
    """
    x = np.asarray(points, np.float64)
    frames = plan_frames(plan)
    index = {name: i for i, name in enumerate(plan.bone_names)}
    out = np.full((len(plan.primitives), len(x)), np.inf if reach is None else float(reach))
    for row, prim in enumerate(plan.primitives):
        if reach is None:
            sel = slice(None)
        else:
            lo, hi = _primitive_box(prim)
            sel = np.flatnonzero(np.all((x >= lo - reach) & (x <= hi + reach), axis=1))
        p = x[sel]
        a = np.asarray(prim.a, np.float64)
        if prim.kind == "cone":
            b = np.asarray(prim.b, np.float64)
            ab = b - a
            t = np.clip(((p - a) @ ab) / float(ab @ ab), 0.0, 1.0)
            radius = prim.ra + t * (prim.rb - prim.ra)
            out[row, sel] = np.linalg.norm(p - a - t[:, None] * ab, axis=1) - radius
        else:
            radii = np.asarray(prim.radii, np.float64)
            local = (p - a) @ frames[index[prim.bone]]
            out[row, sel] = (np.linalg.norm(local / radii, axis=1) - 1.0) * float(radii.min())
    return out


def implicit_field(plan: BodyPlan, points: np.ndarray) -> np.ndarray:
    """Smooth union (exponential smooth minimum with radius ``plan.blend``) of the primitives.

    Primitives farther than :data:`FIELD_REACH_BLENDS` blend radii from a point are skipped there (their
    contribution to the smooth minimum is below ``exp(-FIELD_REACH_BLENDS)`` of the blend radius).

    Parameters
    ----------
    points : (m, 3) float

    Returns
    -------
    (m,) float64, negative inside the creature.
    """
    d = primitive_distances(plan, points, reach=FIELD_REACH_BLENDS * plan.blend)
    return -plan.blend * logsumexp(-d / plan.blend, axis=0)


def _primitive_box(prim) -> tuple[np.ndarray, np.ndarray]:
    if prim.kind == "cone":
        r = max(prim.ra, prim.rb)
        pts = np.array([prim.a, prim.b], np.float64)
    else:
        r = max(prim.radii)
        pts = np.array([prim.a], np.float64)
    return pts.min(0) - r, pts.max(0) + r


def plan_bounds(plan: BodyPlan) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box containing every primitive, padded by twice the blend radius."""
    boxes = [_primitive_box(p) for p in plan.primitives]
    pad = 2.0 * plan.blend
    return np.min([b[0] for b in boxes], axis=0) - pad, np.max([b[1] for b in boxes], axis=0) + pad


def skinning_weights(
    plan: BodyPlan,
    verts: np.ndarray,
    faces: np.ndarray,
    blend: float = DEFAULT_SKIN_BLEND,
    steps: int = SKIN_DIFFUSION_STEPS,
    cutoff: float = SKIN_WEIGHT_CUTOFF,
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth skinning weights by diffusing a hard part segmentation over the surface.

    Parameters
    ----------
    plan : BodyPlan
    verts : (n, 3) float
    faces : (f, 3) int
    blend : float
        Standard deviation (m) of the diffusion: total heat time ``blend**2 / 2``.
    steps : int
        Implicit Euler steps.
    cutoff : float
        Smaller weights are dropped before renormalizing.

    Returns
    -------
    weights : (n, B) float64, rows sum to one
    dominant : (n,) int64 hard assignment (bone of the closest primitive)
    """
    v = np.asarray(verts, np.float64)
    f = np.asarray(faces, np.int64)
    bone_of_prim = np.array([plan.index(p.bone) for p in plan.primitives])
    dominant = bone_of_prim[np.argmin(primitive_distances(plan, v), axis=0)]
    w = np.zeros((len(v), len(plan.bones)))
    w[np.arange(len(v)), dominant] = 1.0
    stiffness = -igl.cotmatrix(v, f)  # positive semidefinite
    mass = igl.massmatrix(v, f, igl.MASSMATRIX_TYPE_VORONOI)
    tau = blend**2 / 2.0 / steps
    solver = splu(sp.csc_matrix(mass + tau * stiffness))
    for _ in range(steps):
        w = solver.solve(mass @ w)
    if not np.isfinite(w).all():
        raise NumericalError("skinning weight diffusion produced NaN/Inf (degenerate template triangles?)")
    w[w < cutoff] = 0.0
    total = w.sum(1, keepdims=True)
    if np.any(total <= 0):
        raise NumericalError("a template vertex lost all its skinning weights")
    return w / total, dominant


def mirror_map(verts: np.ndarray) -> np.ndarray:
    """Nearest template vertex to the mirror image ``(-x, y, z)`` of every vertex.

    Parameters
    ----------
    verts : (n, 3) float

    Returns
    -------
    (n,) int64
    """
    v = np.asarray(verts, np.float64)
    _, idx = cKDTree(v).query(v * np.array([-1.0, 1.0, 1.0]))
    return idx.astype(np.int64)


def build_template(
    plan: BodyPlan,
    n_verts: int,
    grid_step: float = DEFAULT_GRID_STEP,
    remesh_iterations: int = 10,
    skin_blend: float = DEFAULT_SKIN_BLEND,
) -> Template:
    """Mesh a body plan into its canonical template.

    Parameters
    ----------
    plan : BodyPlan
    n_verts : int
        Vertex count of the isotropic template mesh.
    grid_step : float
        Marching-cubes grid spacing (m).
    remesh_iterations : int
    skin_blend : float
        See :func:`skinning_weights`.

    Raises
    ------
    InvalidMeshError
        The surface is not a single watertight, manifold, genus-0 surface (a body plan whose primitives
        leave a hole or a handle, or a grid too coarse for the thinnest part).
    """
    lower, upper = plan_bounds(plan)
    verts, faces = extract_surface(lambda p: implicit_field(plan, p), lower, upper, grid_step)
    verts, faces = clean_surface(verts, faces)
    _check_sphere(plan.name, verts, faces, "after marching cubes")
    max_faces = int(DECIMATE_FACES_PER_VERTEX * n_verts)
    if len(faces) > max_faces:
        # Shortest-edge collapses first (fast), so that the remesher works on a mesh of about the target size.
        verts, faces = igl.decimate(verts, faces.astype(np.int32), max_faces)[:2]
        verts, faces = np.asarray(verts, np.float64), np.asarray(faces, np.int64)
    verts, faces = remesh(verts, faces, n_verts, iterations=remesh_iterations, rtol=TEMPLATE_COUNT_RTOL)
    _check_sphere(plan.name, verts, faces, "after remeshing")
    weights, dominant = skinning_weights(plan, verts, faces, blend=skin_blend)
    arrays = (verts, faces, weights, dominant, mirror_map(verts), part_adjacency(faces, dominant, len(plan.bones)))
    for array in arrays:
        array.setflags(write=False)  # templates are shared (cached); nobody may modify them in place
    return Template(plan, *arrays)


def part_adjacency(faces: np.ndarray, part: np.ndarray, n_parts: int) -> np.ndarray:
    """Which body parts are neighbours on the surface (within two steps).

    Parameters
    ----------
    faces : (f, 3) int
    part : (n,) int
        Part of every vertex.
    n_parts : int

    Returns
    -------
    (n_parts, n_parts) bool, symmetric, true on the diagonal: parts at most two steps apart in the graph
    of parts sharing a mesh edge.
    """
    f = np.asarray(faces, np.int64)
    a = part[np.concatenate([f[:, 0], f[:, 1], f[:, 2]])]
    b = part[np.concatenate([f[:, 1], f[:, 2], f[:, 0]])]
    adj = np.eye(n_parts, dtype=np.int64)
    adj[a, b] = 1
    adj[b, a] = 1
    return (adj @ adj) > 0


def _check_sphere(name: str, verts: np.ndarray, faces: np.ndarray, stage: str) -> None:
    report = topology_report(verts, faces)
    if not (report["watertight"] and report["edge_manifold"] and report["vertex_manifold"]
            and report["components"] == 1 and report["genus"] == 0):
        raise InvalidMeshError(f"{name} template {stage} is not a single closed manifold genus-0 surface: {report}")
