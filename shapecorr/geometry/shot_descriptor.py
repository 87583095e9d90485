"""SHOT: Signature of Histograms of OrienTations, computed at every vertex of a triangle mesh.

Tombari, Salti, Di Stefano, "Unique Signatures of Histograms for Local Surface Description", ECCV 2010.
The mesh vertices are both the feature points and the point set that is described.

For a vertex p with neighbours q_j (mesh vertices with 0 < |q_j - p| <= R):

1. **Local reference frame** (paper sec. 3): the eigenvectors of the distance-weighted scatter matrix
   M = sum_j w_j (q_j - p)(q_j - p)^T / sum_j w_j, w_j = R_lrf - |q_j - p|, centred on p itself (not
   on the neighbours' mean). x is the eigenvector of the largest eigenvalue, z that of the smallest.
   Each of x and z is oriented so that at least half of the neighbours satisfy (q_j - p) . axis >= 0;
   on a tie (not covered by the paper) the sum of the projections decides. y = z cross x.
2. **Spatial grid** (paper sec. 4): an isotropic sphere of radius R split into 8 azimuth x 2 elevation x 2
   radial = 32 sectors, in the local frame. Sector index = 4 * azimuth + 2 * radial + elevation, with
   azimuth sector a covering the angles [-pi + a pi/4, -pi + (a+1) pi/4), radial = 1 beyond R/2,
   elevation = 1 for z > 0.
3. **Histogram per sector** of cos(theta_j) = n_j . z (n_j the vertex normal of the neighbour), over
   ``n_bins + 1`` slots whose centres are the integers 0..n_bins of the coordinate
   (1 + cos) n_bins / 2, which is what the authors' implementation (and PCL) does; that gives
   32 * (n_bins + 1) = 352 values for 10 bins.
4. **Interpolation** ("quadrilinear", paper sec. 4) as implemented by the authors: every neighbour adds
   four independent 1-D linear interpolations -- along the cosine, radial distance, elevation angle and
   azimuth -- each putting weight 1 - d on its own bin and d on the adjacent one (d = distance to the
   bin centre in bin units). Along the radial distance and the elevation, beyond the outermost bin
   centres the count only loses weight (no neighbour bin). It is a sum of four 1-D weights, not their
   product, exactly as in the reference C++ code.
5. Each row is L2-normalized. A vertex with fewer than ``min_neighbors`` neighbours within R, or fewer
   than ``min_lrf_neighbors`` within the frame radius, gets an all-zero row (as in the original code,
   which leaves those descriptors empty); those rows are the only ones that are not unit norm.

``legacy=True`` (the default) reproduces three quirks of the C++ implementation that produced the SHOT
of the Smooth Shells / Deep Shells preprocessing (Rodola's ``calc_shot`` mex over the authors' code,
docs/deep_shells.md §2), so that features match the published pipelines and their checkpoints:

- the frame weights use *squared* distances, w_j = R_lrf - |q_j - p|^2 (the FLANN radius search
  returns squared distances and the frame code treats them as distances). This depends on the units,
  so in legacy mode the mesh is first scaled to the total area at which the pipeline computed SHOT
  (``reference_area`` = 1.93e4; R scales with it), which keeps the function scale-invariant;
- the azimuth interpolation wraps modulo 28 sectors instead of 32 (so sector 6 passes weight to
  sector 0, sector 7 to sector 1 and sector 0 to sector 6 instead of their true neighbours);
- the cosine interpolation wraps modulo ``n_bins`` (bin 9 passes weight to bin 0 instead of bin 10);
  PCL has this one as well.

``legacy=False`` uses the paper's weights R_lrf - |q_j - p|, the circular 8-sector azimuth and a
non-wrapping cosine interpolation.

Conventions. Neighbours are the other vertices with |q - p| <= R (the centre itself is excluded;
duplicated vertices at distance ~0 count as neighbours for ``min_neighbors`` and the frame, as in the
original, but add nothing to the histogram). The pair computations run in float64 (bin assignments are
discontinuous in the coordinates, and the reference is double precision); the result is float32.

Parity (benchmarks/shot_parity.py, four FAUST_r shapes of the Deep Shells reference data): with the
defaults, the per-vertex cosine to the original SHOT has median 1.0 and about 97 % of the vertices
above 0.999. The rest are frame-sign ties, where the original keeps the arbitrary sign of its eigen-solver
(Eigen) and we use the tie-break described in item 1; with Eigen's own eigenvectors substituted in the
frame step, the same histogram code reproduced all vertices (mean cosine 0.9999996). ``normals="area"``
lowers the median to 0.989 and ``legacy=False`` to 0.74 (the squared-distance weights give very
different frames).

Why hand-written: no library in the environment (libigl, trimesh, gpytoolbox, potpourri3d, scipy)
computes SHOT. The neighbour search is scipy's KD-tree; the frames use numpy's batched ``eigh``; the
vertex normals come from libigl. Everything is evaluated as flat array operations over the (p, q)
neighbour pairs (``np.bincount`` accumulation), with no Python loop over vertices.
"""

from __future__ import annotations

import itertools

import igl
import numpy as np
import torch
from scipy.spatial import cKDTree

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError

#: Support radius as a fraction of sqrt(total surface area) (Smooth/Deep Shells MATLAB preprocessing,
#: docs/deep_shells.md §2: radius = 5 * sqrt(area) / 100).
SHOT_RADIUS_FRACTION = 0.05
#: Number of cosine bins (Tombari et al. 2010; Deep Shells preprocessing).
SHOT_N_BINS = 10
#: Fewer neighbours within the support than this gives an all-zero descriptor (Deep Shells preprocessing).
SHOT_MIN_NEIGHBORS = 3
#: The original C++ refuses to build a local frame from fewer than 5 neighbours (descriptor left zero).
SHOT_MIN_LRF_NEIGHBORS = 5
#: Total area at which the MATLAB pipeline computed SHOT (docs/deep_shells.md §2); only used by
#: ``legacy=True``, whose squared-distance frame weights depend on the units.
SHOT_REFERENCE_AREA = 1.93e4
#: Spatial grid of the paper: 8 azimuth x 2 elevation x 2 radial sectors.
N_AZIMUTH = 8
N_ELEVATION = 2
N_RADIAL = 2
N_SECTORS = N_AZIMUTH * N_ELEVATION * N_RADIAL
#: Sector-index strides: sector = AZIMUTH_STRIDE * azimuth + RADIAL_STRIDE * radial + elevation.
AZIMUTH_STRIDE = N_ELEVATION * N_RADIAL
RADIAL_STRIDE = N_ELEVATION
#: The original C++ wraps the azimuth interpolation modulo this many sector indices (a bug: 32 is right).
LEGACY_AZIMUTH_WRAP = 28
#: Neighbours closer than this fraction of the support radius are the query point itself (duplicated
#: vertices); they have no direction and are skipped in the histogram, as in the original code.
COINCIDENT_REL_TOL = 1e-6
#: Neighbour pairs processed at once in the histogram step (bounds the memory of the temporaries; not a
#: published parameter, any value gives the same result).
PAIR_BLOCK = 1 << 16
#: Centre vertices whose neighbourhoods are gathered at once (bounds the memory of the neighbour pairs: at
#: the 5 % radius a 150k-vertex mesh has ~1200 neighbours per vertex, 170 M pairs for the whole mesh, ~10 GB
#: of temporaries; one block holds ~2.5 M). Not a published parameter: results do not depend on it.
CENTRE_BLOCK = 2048

_AZIMUTH_SPAN = 2.0 * np.pi / N_AZIMUTH
_ELEVATION_SPAN = np.pi / N_ELEVATION
_NORMAL_WEIGHTINGS = ("uniform", "area")


def shot_descriptor_length(n_bins: int = SHOT_N_BINS) -> int:
    """Length of a SHOT row: 32 sectors x (n_bins + 1) slots (352 for 10 bins)."""
    return N_SECTORS * (n_bins + 1)


def shot(
    verts,
    faces,
    radius: float | None = None,
    n_bins: int = SHOT_N_BINS,
    lrf_radius: float | None = None,
    min_neighbors: int = SHOT_MIN_NEIGHBORS,
    *,
    normals="uniform",
    legacy: bool = True,
    radius_fraction: float = SHOT_RADIUS_FRACTION,
    min_lrf_neighbors: int = SHOT_MIN_LRF_NEIGHBORS,
    reference_area: float = SHOT_REFERENCE_AREA,
):
    """SHOT descriptor at every vertex of a triangle mesh.

    Parameters
    ----------
    verts : (n, 3) float
        Vertex positions (numpy array or torch tensor on any device).
    faces : (f, 3) int
        Zero-based triangles; used for the vertex normals and the total area.
    radius : float, optional
        Support radius, in the units of ``verts``. Default ``radius_fraction * sqrt(total area)``
        (5 %, the Smooth/Deep Shells setting), which makes the descriptor scale-invariant.
    n_bins : int
        Cosine bins (10 in the paper); each sector stores ``n_bins + 1`` slots.
    lrf_radius : float, optional
        Radius of the support of the local reference frame; default ``radius``.
    min_neighbors : int
        Vertices with fewer neighbours within ``radius`` (itself excluded) get an all-zero row.
    normals : {"uniform", "area"} or (n, 3) float
        Vertex normals used for the cosines: ``"uniform"`` is the normalized sum of the unit normals of
        the adjacent faces (what the original C++ mesh class computes), ``"area"`` the area-weighted
        sum; an array is used as given (it should hold unit vectors). Vertices in no face get a zero
        normal (cosine 0).
    legacy : bool
        Reproduce the original C++ implementation's quirks (module docstring); ``False`` follows the
        paper.
    radius_fraction : float
        Default support radius as a fraction of sqrt(total area).
    min_lrf_neighbors : int
        Vertices with fewer neighbours within ``lrf_radius`` get an all-zero row (5 in the original).
    reference_area : float
        ``legacy`` only: total area the mesh is scaled to before computing (1.93e4 in the pipeline).

    Returns
    -------
    (n, 32 * (n_bins + 1)) float32
        One row per vertex, unit L2 norm, or all zeros for vertices without enough neighbours (see
        ``min_neighbors``). numpy in, numpy out; a torch tensor in gives a tensor on its device.

    Raises
    ------
    InvalidMeshError
        Malformed or non-finite vertices/faces, or zero total area when it is needed.
    ConfigError
        Invalid parameters.
    NumericalError
        NaN/Inf in the result.
    """
    as_torch = isinstance(verts, torch.Tensor)
    device = verts.device if as_torch else None
    v, f = _validate_mesh(verts, faces)
    _validate_params(radius, n_bins, lrf_radius, min_neighbors, min_lrf_neighbors, radius_fraction)

    area = None
    if radius is None or legacy:
        area = _total_area(v, f)
    if radius is None:
        radius = radius_fraction * np.sqrt(area)
    if lrf_radius is None:
        lrf_radius = radius
    if legacy:
        if not reference_area > 0:
            raise ConfigError(f"reference_area must be positive, got {reference_area}")
        # The squared-distance frame weights of the original depend on the units: scale everything to the
        # units in which the pipeline computed SHOT.
        s = np.sqrt(reference_area / area)
        v, radius, lrf_radius = v * s, radius * s, lrf_radius * s

    n_verts = vertex_normals_for_shot(v, f, normals)
    desc = _shot_core(
        v,
        n_verts,
        radius=float(radius),
        lrf_radius=float(lrf_radius),
        n_bins=int(n_bins),
        min_neighbors=int(min_neighbors),
        min_lrf_neighbors=int(min_lrf_neighbors),
        squared_lrf_weights=legacy,
        azimuth_wrap=LEGACY_AZIMUTH_WRAP if legacy else N_SECTORS,
        wrap_cosine=legacy,
    )
    if as_torch:
        return torch.from_numpy(desc).to(device)
    return desc


def shot_lrf(
    verts,
    radius: float,
    squared_distance_weights: bool = False,
    min_lrf_neighbors: int = SHOT_MIN_LRF_NEIGHBORS,
) -> tuple[np.ndarray, np.ndarray]:
    """SHOT local reference frames (paper sec. 3) of every point of a point set.

    Parameters
    ----------
    verts : (n, 3) float
    radius : float
        Support radius of the frame.
    squared_distance_weights : bool
        Weights ``radius - d**2`` (the original C++ quirk) instead of ``radius - d``.
    min_lrf_neighbors : int
        Points with fewer neighbours (itself excluded) get no frame.

    Returns
    -------
    frames : (n, 3, 3) float64
        Rows are the x, y, z axes (right-handed, orthonormal); zero for points without a frame.
    valid : (n,) bool
        Whether the point has a frame.
    """
    v, _ = _validate_mesh(verts, np.zeros((0, 3), dtype=np.int64))
    if not (np.isfinite(radius) and radius > 0):
        raise ConfigError(f"SHOT frame radius must be a positive number, got {radius}")
    frames, valid = np.zeros((v.shape[0], 3, 3)), np.zeros(v.shape[0], dtype=bool)
    for lo, hi, i, j, d in _neighbourhood_blocks(v, radius):
        frames[lo:hi], valid[lo:hi] = _local_frames(v, i, j, d, radius, squared_distance_weights, min_lrf_neighbors,
                                                    lo, hi - lo)
    return frames, valid


def vertex_normals_for_shot(verts: np.ndarray, faces: np.ndarray, normals="uniform") -> np.ndarray:
    """Vertex normals as used by :func:`shot`.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    normals : {"uniform", "area"} or (n, 3) float
        See :func:`shot`.

    Returns
    -------
    (n, 3) float64
        Unit normals; zero for vertices in no face.
    """
    v = np.asarray(verts, dtype=np.float64)
    if isinstance(normals, str):
        if normals not in _NORMAL_WEIGHTINGS:
            raise ConfigError(
                f"SHOT normals must be one of {_NORMAL_WEIGHTINGS} or an (n, 3) array, got {normals!r}"
            )
        weighting = (
            igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_UNIFORM
            if normals == "uniform"
            else igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_AREA
        )
        nrm = igl.per_vertex_normals(v, np.ascontiguousarray(faces, dtype=np.int64), weighting)
        # libigl gives NaN for vertices referenced by no face (and zero-area faces contribute nothing);
        # the original C++ gives them a zero normal, and so do we.
        return np.nan_to_num(nrm, nan=0.0, posinf=0.0, neginf=0.0)
    nrm = normals.detach().cpu().numpy() if isinstance(normals, torch.Tensor) else np.asarray(normals)
    nrm = nrm.astype(np.float64)
    if nrm.shape != v.shape:
        raise ConfigError(f"SHOT normals array must have shape {v.shape}, got {nrm.shape}")
    if not np.isfinite(nrm).all():
        raise InvalidMeshError("SHOT normals contain NaN or Inf")
    return nrm


# ----------------------------------------------------------------------------------------------------
# Implementation
# ----------------------------------------------------------------------------------------------------


def _shot_core(
    v: np.ndarray,
    nrm: np.ndarray,
    radius: float,
    lrf_radius: float,
    n_bins: int,
    min_neighbors: int,
    min_lrf_neighbors: int,
    squared_lrf_weights: bool,
    azimuth_wrap: int,
    wrap_cosine: bool,
) -> np.ndarray:
    """SHOT rows for points ``v`` (n, 3) float64 with unit normals ``nrm`` (n, 3); see :func:`shot`.

    Centres are processed in blocks of ``CENTRE_BLOCK`` (a descriptor depends only on its centre's
    neighbourhood), each from its ordered pairs (centre i, neighbour j) within the larger of the two radii.
    """
    desc = np.zeros((v.shape[0], N_SECTORS * (n_bins + 1)), dtype=np.float32)
    for lo, hi, i, j, d in _neighbourhood_blocks(v, max(radius, lrf_radius)):
        in_lrf = d <= lrf_radius
        frames, has_frame = _local_frames(
            v, i[in_lrf], j[in_lrf], d[in_lrf], lrf_radius, squared_lrf_weights, min_lrf_neighbors, lo, hi - lo
        )
        in_support = d <= radius
        desc[lo:hi] = _histograms(
            v, nrm, frames, has_frame, i[in_support], j[in_support], d[in_support], radius, n_bins, min_neighbors,
            azimuth_wrap, wrap_cosine, lo, hi - lo,
        )
    return desc


def _histograms(
    v: np.ndarray,
    nrm: np.ndarray,
    frames: np.ndarray,
    has_frame: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    d: np.ndarray,
    radius: float,
    n_bins: int,
    min_neighbors: int,
    azimuth_wrap: int,
    wrap_cosine: bool,
    offset: int,
    n: int,
) -> np.ndarray:
    """Normalized SHOT rows (n, 32 (n_bins + 1)) float32 of the centres ``offset .. offset + n - 1``.

    From their frames (n, 3, 3) and support pairs (sorted by centre ``i``, global vertex indices).
    """
    length = N_SECTORS * (n_bins + 1)
    i = i - offset  # local centre indices from here on
    described = has_frame & (np.bincount(i, minlength=n) >= min_neighbors)
    keep = described[i] & (d > COINCIDENT_REL_TOL * radius)
    i, j, d = i[keep], j[keep], d[keep]

    # Blocks of consecutive centres with about PAIR_BLOCK pairs each bound the temporaries' memory
    # (a few hundred bytes per pair); a loop over blocks, not over vertices.
    first_pair = np.searchsorted(i, np.arange(n + 1))
    cuts = np.searchsorted(first_pair, np.arange(PAIR_BLOCK, i.size, PAIR_BLOCK), side="right") - 1
    bounds = np.unique(np.concatenate([[0], cuts, [n]]))
    desc = np.zeros((n, length))
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        block = slice(first_pair[lo], first_pair[hi])
        desc[lo:hi] = _histogram_block(
            v, nrm, frames, i[block], j[block], d[block], lo, hi - lo, radius, n_bins, azimuth_wrap,
            wrap_cosine, offset,
        )

    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    desc = np.divide(desc, norm, out=np.zeros_like(desc), where=norm > 0)
    if not np.isfinite(desc).all():
        raise NumericalError("SHOT produced NaN/Inf values (degenerate neighbourhoods?)")
    return desc.astype(np.float32)


def _histogram_block(
    v: np.ndarray,
    nrm: np.ndarray,
    frames: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    d: np.ndarray,
    first: int,
    n_rows: int,
    radius: float,
    n_bins: int,
    azimuth_wrap: int,
    wrap_cosine: bool,
    offset: int,
) -> np.ndarray:
    """Unnormalized histograms (n_rows, 32 (n_bins + 1)) float64.

    Of the centres first .. first + n_rows - 1 (indices into ``frames``; vertex ``offset + i``), from their pairs
    (i, j) at distances d (``j``: vertex indices).
    """
    slots = n_bins + 1
    length = N_SECTORS * slots
    q = v[j] - v[offset + i]
    frame = frames[i]  # (m, 3, 3): rows x, y, z
    local = np.einsum("mab,mb->ma", frame, q)
    x, y, z = local[:, 0], local[:, 1] + 0.0, local[:, 2]  # "+ 0.0" turns -0.0 into 0.0 for atan2

    # Cosine between the neighbour's normal and the frame's z-axis, as a position on the slot axis.
    cos = np.clip(np.einsum("ma,ma->m", nrm[j], frame[:, 2]), -1.0, 1.0)
    bin_pos = (1.0 + cos) * n_bins / 2.0
    step = np.floor(bin_pos + 0.5).astype(np.int64)  # nearest slot centre, halves rounded up
    frac = bin_pos - step  # in [-0.5, 0.5]

    # Sector of the neighbour.
    azimuth = np.arctan2(y, x)
    az_sector = np.clip(np.floor((azimuth + np.pi) / _AZIMUTH_SPAN).astype(np.int64), 0, N_AZIMUTH - 1)
    outer = d > radius / 2.0
    upper = z > 0
    sector = AZIMUTH_STRIDE * az_sector + RADIAL_STRIDE * outer + upper

    # Weight of the main bin: the sum of the four 1-D interpolation weights (module docstring, item 4).
    # Every other contribution is (centre vertex, slot, weight), accumulated at the end in one bincount.
    main_w = 1.0 - np.abs(frac)
    rows, slot_idx, weights = [], [], []

    # 1) cosine: the adjacent slot in the same sector.
    nb_step = step + np.where(frac > 0, 1, -1)
    nb_step = np.mod(nb_step, n_bins) if wrap_cosine else np.clip(nb_step, 0, n_bins)
    rows.append(i)
    slot_idx.append(sector * slots + nb_step)
    weights.append(np.abs(frac))

    # 2) radial: shell centres at R/4 and 3R/4, one shell width (R/2) apart. Beyond the outermost centres
    #    (d < R/4 or d > 3R/4) the count only loses weight.
    shell = radius / N_RADIAL
    rad_dist = np.where(outer, d - (radius - shell / 2.0), d - shell / 2.0) / shell
    toward = np.where(outer, rad_dist < 0, rad_dist >= 0)
    main_w += 1.0 - np.abs(rad_dist)
    other = sector + np.where(outer, -RADIAL_STRIDE, RADIAL_STRIDE)
    rows.append(i[toward])
    slot_idx.append((other * slots + step)[toward])
    weights.append(np.abs(rad_dist)[toward])

    # 3) elevation: polar angle from +z, half-space centres at 45 and 135 degrees; same rule at the poles.
    inclination = np.arccos(np.clip(z / d, -1.0, 1.0))
    el_centre = np.where(upper, 0.5 * _ELEVATION_SPAN, 1.5 * _ELEVATION_SPAN)
    el_dist = (inclination - el_centre) / _ELEVATION_SPAN
    toward = np.where(upper, el_dist >= 0, el_dist < 0)
    main_w += 1.0 - np.abs(el_dist)
    other = sector + np.where(upper, -1, 1)
    rows.append(i[toward])
    slot_idx.append((other * slots + step)[toward])
    weights.append(np.abs(el_dist)[toward])

    # 4) azimuth: sector centres at -pi + (a + 1/2) pi/4, circular (modulo 32 sector indices, 28 in legacy
    #    mode). A neighbour on the z-axis has no azimuth and adds no azimuth weight at all.
    has_az = (x != 0) | (y != 0)
    az_centre = -np.pi + (az_sector + 0.5) * _AZIMUTH_SPAN
    az_dist = np.clip((azimuth - az_centre) / _AZIMUTH_SPAN, -0.5, 0.5)
    main_w += np.where(has_az, 1.0 - np.abs(az_dist), 0.0)
    other = np.mod(sector + np.where(az_dist > 0, AZIMUTH_STRIDE, -AZIMUTH_STRIDE), azimuth_wrap)
    rows.append(i[has_az])
    slot_idx.append((other * slots + step)[has_az])
    weights.append(np.abs(az_dist)[has_az])

    rows.append(i)
    slot_idx.append(sector * slots + step)
    weights.append(main_w)

    flat = (np.concatenate(rows) - first) * length + np.concatenate(slot_idx)
    hist = np.bincount(flat, weights=np.concatenate(weights), minlength=n_rows * length)
    return hist.astype(np.float64, copy=False).reshape(n_rows, length)  # bincount of nothing is int64


def _validate_mesh(verts, faces) -> tuple[np.ndarray, np.ndarray]:
    """``verts`` as (n, 3) float64 and ``faces`` as (f, 3) int64 numpy arrays, checked."""
    v = verts.detach().cpu().numpy() if isinstance(verts, torch.Tensor) else np.asarray(verts)
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise InvalidMeshError(f"SHOT needs vertices of shape (n, 3) with n >= 1, got {v.shape}")
    if not np.issubdtype(v.dtype, np.floating) and not np.issubdtype(v.dtype, np.integer):
        raise InvalidMeshError(f"SHOT vertices must be numeric, got dtype {v.dtype}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        n_bad = int((~np.isfinite(v)).any(axis=1).sum())
        raise InvalidMeshError(f"SHOT input has {n_bad} vertices with NaN/Inf coordinates")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InvalidMeshError(f"SHOT needs faces of shape (f, 3), got {f.shape}")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        raise InvalidMeshError(f"SHOT faces must be integer indices, got dtype {f.dtype}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise InvalidMeshError(
            f"SHOT faces index vertices {int(f.min())}..{int(f.max())}, outside 0..{v.shape[0] - 1}"
        )
    return v, f


def _validate_params(radius, n_bins, lrf_radius, min_neighbors, min_lrf_neighbors, radius_fraction) -> None:
    for name, value in (("radius", radius), ("lrf_radius", lrf_radius)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ConfigError(f"SHOT {name} must be a positive number, got {value}")
    if not (np.isfinite(radius_fraction) and radius_fraction > 0):
        raise ConfigError(f"SHOT radius_fraction must be a positive number, got {radius_fraction}")
    if int(n_bins) != n_bins or n_bins < 1:
        raise ConfigError(f"SHOT n_bins must be a positive integer, got {n_bins}")
    for name, value in (("min_neighbors", min_neighbors), ("min_lrf_neighbors", min_lrf_neighbors)):
        if int(value) != value or value < 0:
            raise ConfigError(f"SHOT {name} must be a non-negative integer, got {value}")


def _total_area(v: np.ndarray, f: np.ndarray) -> float:
    """Total surface area; raises if it is zero (no radius can be derived from it)."""
    area = 0.5 * float(igl.doublearea(v, f).sum()) if f.size else 0.0
    if not area > 0:
        raise InvalidMeshError(
            "SHOT: the mesh has zero total area, which the default radius and legacy=True scale by"
        )
    return area


def _neighbourhood_blocks(v: np.ndarray, radius: float):
    """Neighbour pairs per block of ``CENTRE_BLOCK`` consecutive centres.

    Yields ``lo, hi, i, j, d``: the ordered pairs (i, j) with ``lo <= i < hi``, ``j != i`` and
    |v_j - v_i| <= radius, sorted by i, then j; ``i, j`` (m,) int64 vertex indices, ``d`` (m,) float64 distances.
    """
    tree = cKDTree(v)
    for lo in range(0, v.shape[0], CENTRE_BLOCK):
        hi = min(v.shape[0], lo + CENTRE_BLOCK)
        balls = tree.query_ball_point(v[lo:hi], radius, return_sorted=True)
        counts = np.fromiter((len(b) for b in balls), dtype=np.int64, count=len(balls))
        j = np.fromiter(itertools.chain.from_iterable(balls), dtype=np.int64, count=int(counts.sum()))
        i = np.repeat(np.arange(lo, hi, dtype=np.int64), counts)
        other = j != i
        i, j = i[other], j[other]
        yield lo, hi, i, j, np.linalg.norm(v[j] - v[i], axis=1)


def _local_frames(
    v: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    d: np.ndarray,
    radius: float,
    squared_distance_weights: bool,
    min_lrf_neighbors: int,
    offset: int,
    n: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Frames (n, 3, 3) of the centres ``offset .. offset + n - 1``.

    From their neighbour pairs (i, j) (vertex indices) at distances d (all <= radius); see :func:`shot_lrf`.
    """
    q = v[j] - v[i]
    i = i - offset  # local centre indices from here on
    w = radius - (d * d if squared_distance_weights else d)
    count = np.bincount(i, minlength=n)
    sum_w = np.bincount(i, weights=w, minlength=n)
    # Weighted scatter about the point itself (not the neighbours' mean), upper triangle then mirrored.
    scatter = np.zeros((n, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            scatter[:, a, b] = scatter[:, b, a] = np.bincount(i, weights=w * q[:, a] * q[:, b], minlength=n)
    # The division by sum(w) matters only through its sign (it can be negative with squared-distance
    # weights, which reverses the eigenvalue order); it is kept to reproduce the original exactly.
    valid = (count >= max(min_lrf_neighbors, 1)) & (sum_w != 0)
    scatter[valid] /= sum_w[valid, None, None]
    scatter[~valid] = np.eye(3)
    _, evecs = np.linalg.eigh(scatter)  # ascending eigenvalues, eigenvectors in columns
    x_axis = evecs[:, :, 2]
    z_axis = evecs[:, :, 0]
    if not (np.isfinite(x_axis).all() and np.isfinite(z_axis).all()):
        raise NumericalError("SHOT local reference frame: eigen-decomposition gave NaN/Inf")
    # Sign disambiguation (paper sec. 3): point each axis towards the majority of the neighbours; a
    # neighbour exactly on the plane counts for the positive side. A tie (even count, half on each side;
    # a few % of the vertices of a FAUST mesh) is not covered by the paper: the original C++ keeps the
    # eigen-solver's arbitrary sign, PCL looks at the neighbours of median distance. We break it with the
    # sign of the sum of the projections, which is rotation-invariant and needs no sorting.
    for axis in (x_axis, z_axis):
        proj = np.einsum("ma,ma->m", q, axis[i])
        balance = 2 * np.bincount(i, weights=(proj >= 0), minlength=n) - count
        tie_sign = np.bincount(i, weights=proj, minlength=n)
        flip = (balance < 0) | ((balance == 0) & (tie_sign < 0))
        axis[flip] *= -1.0
    y_axis = np.cross(z_axis, x_axis)
    frames = np.stack([x_axis, y_axis, z_axis], axis=1)
    frames[~valid] = 0.0
    return frames, valid
