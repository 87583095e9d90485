"""Optional corruptions of the synthetic shapes for robustness benchmarks.

Vertex noise, holes, and the fusion of touching body parts (topological noise, as in the SHREC'16 TOPKIDS
benchmark).

Ground truth stays valid for what remains: noise moves vertices but keeps their indices; a hole removes
vertices, and a reference point whose vertex disappears is reassigned to the nearest surviving vertex
(measured in the subject's rest pose); in a fused zone, vertices are traced to the closest posed
template point like everywhere else, so the few vertices on a bridge between two parts correspond to a
point of one of them.
"""

from __future__ import annotations

import igl
import numpy as np
import trimesh

from shapecorr.data.synthetic.groundtruth import nearest_vertices
from shapecorr.data.synthetic.meshing import clean_surface, extract_surface
from shapecorr.errors import ConfigError, InvalidMeshError

#: Lipschitz bound of the fusion field: 1 (signed distance) + exp(-1/2) (steepest slope of the bump).
FUSION_LIPSCHITZ = 1.0 + float(np.exp(-0.5))
#: Grid cells of margin added around the posed shape's bounding box for the fused surface.
_FUSION_PADDING = 2.0


def add_noise(verts: np.ndarray, rng: np.random.Generator, std: float) -> np.ndarray:
    """Add isotropic Gaussian noise.

    Parameters
    ----------
    verts : (n, 3) float
    rng : numpy Generator
    std : float
        Standard deviation (same unit as ``verts``).

    Returns
    -------
    (n, 3) float64
    """
    if not std >= 0:
        raise ConfigError(f"noise std must be >= 0, got {std}")
    v = np.asarray(verts, np.float64)
    return v + rng.normal(size=v.shape) * std if std > 0 else v.copy()


def cut_holes(
    verts: np.ndarray,
    faces: np.ndarray,
    rest_positions: np.ndarray,
    rng: np.random.Generator,
    n_holes: int,
    radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Remove the vertices within ``radius`` (in the rest pose) of ``n_holes`` random centre vertices.

    Faces touching a removed vertex go too; only the largest remaining connected piece is kept, so a hole
    that severs a thin part removes that part.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    rest_positions : (n, 3) float
        Where each vertex lies on the subject in its rest pose (distances are measured there, so a hole never
        jumps between touching body parts).
    rng : numpy Generator
    n_holes : int
    radius : float

    Returns
    -------
    keep : (n',) int64
        Indices (increasing) of the surviving vertices.
    faces : (f', 3) int64
        Faces re-indexed into the surviving vertices.
    """
    if n_holes < 0 or not radius >= 0:
        raise ConfigError(f"need n_holes >= 0 and radius >= 0, got {n_holes}, {radius}")
    n = len(verts)
    f = np.asarray(faces, np.int64)
    alive = np.ones(n, dtype=bool)
    if n_holes > 0 and radius > 0:
        centres = rng.choice(n, size=min(n_holes, n), replace=False)
        rest = np.asarray(rest_positions, np.float64)
        for c in centres:
            alive &= np.linalg.norm(rest - rest[c], axis=1) > radius
    kept_faces = f[alive[f].all(axis=1)]
    if len(kept_faces) == 0:
        raise InvalidMeshError("holes removed the whole surface; use fewer or smaller holes")
    mesh = trimesh.Trimesh(np.asarray(verts, np.float64), kept_faces, process=False)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(kept_faces))
    largest = np.argmax(np.bincount(labels))
    kept_faces = kept_faces[labels == largest]
    keep = np.unique(kept_faces)
    remap = np.full(n, -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    return keep, remap[kept_faces]


def reassign_lost(indices: np.ndarray, keep: np.ndarray, rest_positions: np.ndarray) -> np.ndarray:
    """Map vertex indices into the kept set, replacing removed vertices by the nearest kept one.

    Parameters
    ----------
    indices : (r,) int
        Vertex indices before removal.
    keep : (k,) int
        Surviving vertex indices (increasing).
    rest_positions : (n, 3) float
        Rest-pose positions used to find the nearest survivor.

    Returns
    -------
    (r,) int64 indices into the kept vertices.
    """
    idx = np.asarray(indices, np.int64)
    n = len(rest_positions)
    remap = np.full(n, -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    out = remap[idx]
    lost = out < 0
    if lost.any():
        out[lost] = remap[nearest_vertices(np.asarray(rest_positions)[idx[lost]], rest_positions, keep)]
    return out


def fuse_contacts(
    verts: np.ndarray,
    faces: np.ndarray,
    contact_points: np.ndarray,
    bridge: float,
    grid_step: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Surface of the posed solid in which touching body parts are fused.

    The result is a closed, possibly higher-genus surface.

    The new surface is the zero level set of ``s(x) - bridge * k(x)``: ``s`` the signed distance to the
    posed mesh (sign from the winding number, robust to self-intersections), ``k(x)`` a Gaussian bump of
    width ``bridge`` around the nearest contact point. Away from contacts the surface is the original one
    (up to the grid resolution); where two parts are closer than about ``2 bridge`` they merge.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
        The posed (possibly self-intersecting) surface.
    contact_points : (c, 3) float
        Midpoints of the contacts.
    bridge : float
        Width of the fused zone.
    grid_step : float
        Marching-cubes spacing.

    Returns
    -------
    verts : (m, 3) float64
    faces : (g, 3) int64
        Cleaned, single-piece, outward-oriented surface.
    """
    from scipy.spatial import cKDTree

    v = np.ascontiguousarray(verts, np.float64)
    f = np.ascontiguousarray(faces, np.int64)
    centres = np.asarray(contact_points, np.float64).reshape(-1, 3)
    tree = cKDTree(centres) if len(centres) else None

    def field(points: np.ndarray) -> np.ndarray:
        sdist = igl.signed_distance(np.ascontiguousarray(points), v, f,
                                    sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)[0]
        if tree is None:
            return sdist
        dist, _ = tree.query(points)
        return sdist - bridge * np.exp(-0.5 * (dist / bridge) ** 2)

    pad = _FUSION_PADDING * (bridge + grid_step)
    out_v, out_f = extract_surface(field, v.min(0) - pad, v.max(0) + pad, grid_step, lipschitz=FUSION_LIPSCHITZ)
    return clean_surface(out_v, out_f)
