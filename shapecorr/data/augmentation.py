"""Training-time augmentation of shape pairs: remeshing to random resolutions and a shared rotation.

NeuroMorph (Eisenberger et al., CVPR 2021; docs/neuromorph.md) trains on pairs whose shapes are remeshed
independently to random resolutions (every resolution 200..2000 of its 2000-vertex meshes, one drawn
uniformly per shape and step) and rotated by the *same* random angle about the up axis (y for FAUST).

Remeshing here uses :func:`shapecorr.geometry.remeshing.remesh` (isotropic Botsch-Kobbelt remeshing to a
vertex count). The original decimated with MATLAB's reducepatch and snapped the new vertices onto old ones;
ours moves vertices, so every remesh carries its correspondence to the shape it came from
(:class:`Remeshed`):

* ``source_vertex (m,)``: for each new vertex, the nearest old vertex (maps *into* the original, e.g. to carry
  a map onto a remeshed target back to the full-resolution target);
* ``nearest_vertex (n,)``: for each old vertex, the nearest new vertex (ground truth: reference point r at old
  vertex ``corres[r]`` is at new vertex ``nearest_vertex[corres[r]]``; maps *from* the full-resolution
  source through its remesh);
* ``lift_faces (n,)`` and ``lift_weights (n, 3)``: the triangle of the remesh closest to each old vertex and
  the barycentric coordinates of that closest point, to carry a per-vertex field (a displacement) from the
  remesh back to the original by linear interpolation.

A bounded pool. Remeshing a 5k-vertex FAUST_r shape (~1 s of CPU) and the geodesic matrix of a
2000-vertex remesh (~1.6 s) are cached with :class:`~shapecorr.data.cache.ShapeCache`, keyed by the content
of the shape, the target resolution and the remesher settings. To keep that cache finite, each shape has a
fixed pool of ``variants`` resolutions (default 8), drawn once from the configured range by a generator
seeded with ``(seed, content hash of the shape)``, without replacement; a training step picks one pool entry
per shape. The remesher is deterministic, so the resolution identifies the remesh and the key needs no
variant number. On disk: at most ``shapes x variants`` remeshes (~100 kB each) plus, while the geodesic
loss is on, their geodesic matrices (float32, 16 MB at 2000 vertices, ~6 MB on average over 200..2000:
~4 GB for the 640 entries of 80 FAUST_r shapes x 8). The first epoch fills the pool (~30 min of CPU for
FAUST_r). The range is clipped to the shape's own vertex count (never upsampled: the original only
decimated).

Rotation: an angle drawn uniformly in [0, 2 pi) about the configured axis, applied to both shapes (after
the geodesics are looked up, which do not depend on it).

On the data side. :class:`AugmentedPairDataset` applies a :class:`PairAugmenter` to the training pairs inside
the dataset, so that DataLoader worker processes remesh and compute geodesics in parallel with training. Its
keys are :class:`SampleKey` ``(epoch, position, index)`` (the data module's training sampler yields them):
a step's draws come from a generator seeded with ``(seed, epoch, position)``, ``position`` being the step's
place in the epoch (the batch index), so a run resumed mid-epoch, whose sampler starts at the same position,
draws what the uninterrupted run would have drawn, and the draws are those of the former in-model
augmentation (``default_rng([seed, epoch, batch index])``).

Geodesic matrices (``geodesics``): ``"heat"`` (default) or ``"exact"`` matrices of each remesh itself, or
``"original"``, the NeuroMorph preprocessing: exact geodesics of the *working-resolution* mesh only (the
``max_vertices`` remesh, else the shape as given), entries above 100 (unreachable pairs) set to 2, and for every
lower-resolution remesh the sub-matrix of that matrix at the working-resolution vertex nearest to each remesh
vertex. The original's remesher kept a subset of the working mesh's vertices, so its sub-matrices were exact;
ours moves vertices, so a sub-matrix entry is the exact distance between the nearest working-resolution
vertices (off by at most about one working-resolution edge length). One exact matrix per shape instead of one
per remesh; its cost is measured in ``benchmarks/neuromorph_parity.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import igl
import numpy as np
import torch
from scipy.spatial import cKDTree
from torch.utils.data import Dataset

from shapecorr.data.cache import ShapeCache, content_hash
from shapecorr.data.datasets import PairDataset, PairSample, ShapeSample
from shapecorr.data.operators import OPERATOR_VERSIONS, geodesics_cached
from shapecorr.data.shape import Shape, triangle_areas
from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.remeshing import (
    REMESH_ITERATIONS,
    REMESH_MAX_ROUNDS,
    REMESH_RTOL,
    remesh,
)

#: Version of the cached remeshes (bump when remeshing or the stored correspondence changes).
REMESH_CACHE_VERSION = 1
#: NeuroMorph remeshing augmentation: every resolution from 200 to 2000 vertices (NeuroMorph paper and code).
DEFAULT_RESOLUTION_RANGE = (200, 2000)
#: Remeshes per shape (project choice: a finite pool keeps the cache bounded, see the module docstring).
DEFAULT_REMESH_VARIANTS = 8
#: NeuroMorph FAUST/SHREC'20 rotation axis: y (axis = 1; MANO uses z), NeuroMorph code.
DEFAULT_UP_AXIS = "y"
AXES = {"x": 0, "y": 1, "z": 2}
#: Geodesic method for remeshed shapes (shapecorr.geometry.geodesics; the original used fast marching).
DEFAULT_GEODESICS = "heat"
#: Geodesic matrices of the augmented shapes: per remesh (heat / exact) or the original's preprocessing.
GEODESIC_OPTIONS = ("heat", "exact", "original")
#: NeuroMorph code (data/data.py): distance-matrix entries above 100 (unreachable pairs) are replaced by 2.
ORIGINAL_GEODESIC_CLAMP_ABOVE = 100.0
ORIGINAL_GEODESIC_CLAMP_VALUE = 2.0
#: Barycentric coordinates outside [-tol, 1 + tol] mean a degenerate closest triangle (clamped, renormalized).
BARYCENTRIC_TOL = 1e-6
#: Sub-seed separating the resolution pools from the per-step draws of the same base seed.
_POOL_STREAM = 0x5EED


@dataclass(frozen=True)
class Remeshed:
    """A remesh of a shape and its correspondence to the original (see the module docstring).

    Attributes
    ----------
    verts : (m, 3) float32
    faces : (g, 3) int64
    source_vertex : (m,) int64
        Nearest original vertex of each new vertex.
    nearest_vertex : (n,) int64
        Nearest new vertex of each original vertex.
    lift_faces : (n,) int64
        Remesh triangle closest to each original vertex.
    lift_weights : (n, 3) float32
        Barycentric coordinates (rows sum to 1) of that closest point in its triangle.
    """

    verts: np.ndarray
    faces: np.ndarray
    source_vertex: np.ndarray
    nearest_vertex: np.ndarray
    lift_faces: np.ndarray
    lift_weights: np.ndarray

    @property
    def n_verts(self) -> int:
        """Number of vertices of the remesh."""
        return int(self.verts.shape[0])

    def as_arrays(self) -> dict[str, np.ndarray]:
        """The fields as a dict of arrays by field name."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    def lift(self, values: torch.Tensor) -> torch.Tensor:
        """Carry per-vertex values of the remesh to the original vertices by barycentric interpolation.

        Parameters
        ----------
        values : (..., m, c) float
            Per-vertex values on the remesh (any device).

        Returns
        -------
        (..., n, c) float
        """
        tri = torch.as_tensor(self.faces, device=values.device)[torch.as_tensor(self.lift_faces, device=values.device)]
        weights = torch.as_tensor(self.lift_weights, device=values.device, dtype=values.dtype)
        corners = values.index_select(-2, tri.reshape(-1)).unflatten(-2, tri.shape)  # (..., n, 3, c)
        return (corners * weights.unsqueeze(-1)).sum(-2)


def _barycentric_lift(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest triangle of (verts, faces) to each point and the barycentric coordinates of the closest point."""
    _, tri, closest = igl.point_mesh_squared_distance(points, verts, faces)
    tri = np.asarray(tri, dtype=np.int64)
    corners = verts[faces[tri]]
    weights = igl.barycentric_coordinates(closest, corners[:, 0].copy(), corners[:, 1].copy(), corners[:, 2].copy())
    weights = np.asarray(weights, dtype=np.float64)
    bad = ~np.isfinite(weights).all(axis=1) | (weights < -BARYCENTRIC_TOL).any(axis=1)
    if bad.any():
        # Degenerate (zero-area) closest triangle: fall back to its corner nearest to the point.
        d = np.linalg.norm(corners[bad] - points[bad, None], axis=-1)
        weights[bad] = 0.0
        weights[np.flatnonzero(bad), d.argmin(axis=1)] = 1.0
    weights = np.clip(weights, 0.0, None)
    weights /= weights.sum(axis=1, keepdims=True)
    return tri, weights


def remesh_with_correspondence(
    verts,
    faces,
    n_verts: int,
    iterations: int = REMESH_ITERATIONS,
    rtol: float = REMESH_RTOL,
    max_rounds: int = REMESH_MAX_ROUNDS,
) -> Remeshed:
    """Remesh a shape to about ``n_verts`` vertices and relate the remesh to the original.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    n_verts : int
        Target vertex count (see :func:`shapecorr.geometry.remeshing.remesh` for the achieved tolerance).
    iterations, rtol, max_rounds
        Remesher settings.

    Returns
    -------
    Remeshed
    """
    v = np.asarray(verts.detach().cpu().numpy() if isinstance(verts, torch.Tensor) else verts, dtype=np.float64)
    f = np.asarray(faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else faces, dtype=np.int64)
    new_v, new_f = remesh(v, f, int(n_verts), iterations=iterations, rtol=rtol, max_rounds=max_rounds)
    # Stored positions are float32; relate the float32 positions to the original so that a cache hit and a
    # fresh computation give identical arrays.
    new_v = new_v.astype(np.float32)
    new_v64 = new_v.astype(np.float64)
    _, source = cKDTree(v).query(new_v64, k=1)
    _, nearest = cKDTree(new_v64).query(v, k=1)
    lift_faces, lift_weights = _barycentric_lift(v, new_v64, new_f)
    return Remeshed(
        verts=new_v,
        faces=new_f.astype(np.int64),
        source_vertex=np.asarray(source, dtype=np.int64),
        nearest_vertex=np.asarray(nearest, dtype=np.int64),
        lift_faces=lift_faces,
        lift_weights=lift_weights.astype(np.float32),
    )


def cached_remesh(cache: ShapeCache, verts, faces, n_verts: int) -> Remeshed:
    """:func:`remesh_with_correspondence` through the shape cache (key: shape content + ``n_verts`` + settings).

    Parameters
    ----------
    cache : ShapeCache
    verts : (n, 3) float
    faces : (f, 3) int
    n_verts : int

    Returns
    -------
    Remeshed
        Identical arrays on a hit and on a miss.
    """
    v = verts.detach().cpu().numpy() if isinstance(verts, torch.Tensor) else np.asarray(verts)
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    params = {"n_verts": int(n_verts), "iterations": REMESH_ITERATIONS, "rtol": REMESH_RTOL,
              "max_rounds": REMESH_MAX_ROUNDS}
    arrays = cache.get_or_compute(
        "remesh", v, f, params, REMESH_CACHE_VERSION,
        lambda: remesh_with_correspondence(v, f, n_verts).as_arrays(),
    )
    return Remeshed(**{k: arrays[k] for k in Remeshed.__dataclass_fields__})


def remeshed_sample(sample: ShapeSample, remeshed: Remeshed) -> ShapeSample:
    """A :class:`ShapeSample` of the remesh, with the ground truth carried over.

    The remeshed sample keeps the normalization transform of the original (``denormalize`` still gives input
    units), gets the lumped (barycentric) vertex areas as ``mass`` and carries no eigenbasis (``evals (0,)``,
    ``evecs (m, 0)``) and no descriptors: NeuroMorph needs neither. Its name is ``<name>@<m>``.

    Parameters
    ----------
    sample : ShapeSample
        The original shape (any device; the result is on the CPU).
    remeshed : Remeshed
        A remesh of ``sample``.

    Returns
    -------
    ShapeSample
        ``corres[r] = nearest_vertex[sample.corres[r]]`` (and the same for ``corres_sym``).
    """
    if remeshed.nearest_vertex.shape[0] != sample.shape.n_verts:
        raise ConfigError(
            f"{sample.name}: the remesh relates {remeshed.nearest_vertex.shape[0]} original vertices but the shape "
            f"has {sample.shape.n_verts}"
        )
    verts = torch.from_numpy(np.ascontiguousarray(remeshed.verts, dtype=np.float32))
    faces = torch.from_numpy(np.ascontiguousarray(remeshed.faces, dtype=np.int64))
    m = verts.shape[0]
    mass = np.bincount(remeshed.faces.ravel(), np.repeat(triangle_areas(remeshed.verts, remeshed.faces) / 3.0, 3),
                       minlength=m)
    nearest = torch.from_numpy(remeshed.nearest_vertex)
    def carry(c):
        return None if c is None else nearest[c.detach().cpu()]
    shape = sample.shape
    return ShapeSample(
        shape=Shape(verts=verts, faces=faces, name=f"{shape.name}@{m}", path=shape.path, scale=shape.scale,
                    offset=shape.offset),
        operators={
            "eigenbasis": {
                "evals": torch.zeros(0),
                "evecs": torch.zeros(m, 0),
                "mass": torch.from_numpy(mass.astype(np.float32)),
            },
        },
        corres=carry(sample.corres),
        corres_sym=carry(sample.corres_sym),
    )


def pool_resolutions(
    shape_hash: str,
    n_verts: int,
    resolution_range: tuple[int, int] = DEFAULT_RESOLUTION_RANGE,
    variants: int = DEFAULT_REMESH_VARIANTS,
    seed: int = 0,
) -> np.ndarray:
    """The fixed pool of remesh resolutions of one shape (module docstring).

    Parameters
    ----------
    shape_hash : str
        :func:`~shapecorr.data.cache.content_hash` of the shape.
    n_verts : int
        Its vertex count; the range is clipped to it (no upsampling).
    resolution_range : (lo, hi)
        Inclusive range of target vertex counts.
    variants : int
        Pool size; fewer when the clipped range holds fewer resolutions.
    seed : int

    Returns
    -------
    (k,) int64
        Distinct resolutions, sorted, ``1 <= k <= variants``.
    """
    lo, hi = (min(int(r), int(n_verts)) for r in resolution_range)
    rng = np.random.default_rng([int(seed), _POOL_STREAM, int(shape_hash[:16], 16)])
    count = min(int(variants), hi - lo + 1)
    return np.sort(lo + rng.choice(hi - lo + 1, size=count, replace=False)).astype(np.int64)


def rotation_about_axis(angle: float, axis: str = DEFAULT_UP_AXIS, dtype=torch.float32) -> torch.Tensor:
    """Rotation matrix by ``angle`` (radians, right-handed) about a coordinate axis.

    Returns
    -------
    (3, 3) tensor
        Proper rotation; ``verts @ R.T`` rotates row vectors.
    """
    if axis not in AXES:
        raise ConfigError(f"rotation axis must be one of {sorted(AXES)}, got {axis!r}")
    k = AXES[axis]
    i, j = (k + 1) % 3, (k + 2) % 3
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.eye(3, dtype=torch.float64)
    rot[i, i], rot[i, j], rot[j, i], rot[j, j] = c, -s, s, c
    return rot.to(dtype)


def rotate_sample(sample: ShapeSample, rotation: torch.Tensor) -> ShapeSample:
    """The sample with its vertices rotated, ``verts @ R.T`` (everything else unchanged).

    Parameters
    ----------
    sample : ShapeSample
    rotation : (3, 3) float
    """
    verts = sample.shape.verts @ rotation.to(sample.shape.verts).T
    return replace(sample, shape=replace(sample.shape, verts=verts))


@dataclass(frozen=True)
class AugmentationConfig:
    """Options of :class:`PairAugmenter` (Hydra node ``model.augment`` of NeuroMorph).

    Attributes
    ----------
    remesh : bool
        Remesh each shape of a pair to a random resolution of its pool.
    rotate : bool
        Rotate both shapes by one random angle about ``axis``.
    resolution : (lo, hi)
        Inclusive range of remesh vertex counts (NeuroMorph: 200..2000).
    variants : int
        Pool size per shape.
    axis : {"x", "y", "z"}
        Rotation axis (FAUST: y).
    """

    remesh: bool = True
    rotate: bool = True
    resolution: tuple[int, int] = DEFAULT_RESOLUTION_RANGE
    variants: int = DEFAULT_REMESH_VARIANTS
    axis: str = DEFAULT_UP_AXIS

    def __post_init__(self):
        res = tuple(int(r) for r in self.resolution)
        object.__setattr__(self, "resolution", res)
        if len(res) != 2 or not 4 <= res[0] <= res[1]:
            raise ConfigError(f"augment.resolution must be [lo, hi] with 4 <= lo <= hi, got {list(self.resolution)}")
        if int(self.variants) < 1:
            raise ConfigError(f"augment.variants must be >= 1, got {self.variants}")
        if self.axis not in AXES:
            raise ConfigError(f"augment.axis must be one of {sorted(AXES)}, got {self.axis!r}")

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | AugmentationConfig | None) -> AugmentationConfig:
        """Config from a mapping of augment options (unknown keys raise ConfigError); a config passes through."""
        if isinstance(options, cls):
            return options
        options = dict(options or {})
        unknown = set(options) - set(cls.__dataclass_fields__)
        if unknown:
            allowed = sorted(cls.__dataclass_fields__)
            raise ConfigError(f"unknown augment option(s) {sorted(unknown)}; allowed: {allowed}")
        return cls(**options)


@dataclass(frozen=True, eq=False)
class AugmentedPair:
    """A training pair after augmentation (CPU tensors).

    Attributes
    ----------
    pair : PairSample
        The (remeshed, rotated) shapes.
    dist_x, dist_y : (n_x, n_x), (n_y, n_y) float32 or None
        Geodesic matrices of the shapes (rotation-invariant), when requested.
    remeshed_x, remeshed_y : Remeshed or None
        The remeshes used (None: the shape as given).
    rotation : (3, 3) float32
        Applied to both shapes (the identity without rotation).
    """

    pair: PairSample
    dist_x: torch.Tensor | None
    dist_y: torch.Tensor | None
    remeshed_x: Remeshed | None
    remeshed_y: Remeshed | None
    rotation: torch.Tensor

    @property
    def name(self) -> str:
        """Name of the augmented pair, ``<x>__<y>``."""
        return self.pair.name

    def to(self, device: torch.device | str) -> "AugmentedPair":
        """Copy with the pair and the geodesic matrices on ``device`` (the remeshes stay numpy)."""
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return replace(self, pair=self.pair.to(device), dist_x=move(self.dist_x), dist_y=move(self.dist_y),
                       rotation=self.rotation.to(device))


def _geometry_only(sample: ShapeSample) -> ShapeSample:
    """CPU copy of a sample without its eigenbasis and descriptors (augmented shapes carry none)."""
    def move(t):
        return None if t is None else t.detach().cpu()
    shape = sample.shape.to("cpu")
    return ShapeSample(
        shape=shape,
        operators={
            "eigenbasis": {"evals": torch.zeros(0), "evecs": torch.zeros(shape.n_verts, 0), "mass": move(sample.mass)},
        },
        corres=move(sample.corres),
        corres_sym=move(sample.corres_sym),
    )


class PairAugmenter:
    """Remeshing + shared-rotation augmentation of a pair, with cached remeshes and geodesics.

    Parameters
    ----------
    config : AugmentationConfig or mapping
    cache : ShapeCache
        Where remeshes and geodesic matrices are cached.
    max_vertices : int, optional
        Working resolution: without remeshing augmentation, a shape with more vertices is remeshed to this
        many (deterministically, cached); with it, the resolution range is clipped to it as well.
    seed : int
        Seed of the resolution pools.
    geodesics : {"heat", "exact", "original"}
        Geodesic matrices of each remesh (heat or exact), or the original's preprocessing (module docstring).
    """

    def __init__(
        self,
        config: AugmentationConfig | Mapping[str, Any] | None,
        cache: ShapeCache,
        max_vertices: int | None = None,
        seed: int = 0,
        geodesics: str = DEFAULT_GEODESICS,
    ):
        self.config = AugmentationConfig.from_options(config)
        if max_vertices is not None and int(max_vertices) < 4:
            raise ConfigError(f"the working resolution must be >= 4 vertices, got {max_vertices}")
        self.cache = cache
        self.max_vertices = None if max_vertices is None else int(max_vertices)
        self.seed = int(seed)
        if geodesics not in GEODESIC_OPTIONS:
            raise ConfigError(f"geodesics must be one of {GEODESIC_OPTIONS}, got {geodesics!r}")
        self.geodesics = geodesics

    def resolutions(self, sample: ShapeSample) -> np.ndarray:
        """The remesh pool of a shape (sorted vertex counts)."""
        n = sample.shape.n_verts if self.max_vertices is None else min(sample.shape.n_verts, self.max_vertices)
        verts, faces = sample.shape.verts.detach().cpu(), sample.shape.faces.detach().cpu()
        return pool_resolutions(content_hash(verts, faces), n, self.config.resolution, self.config.variants, self.seed)

    def working_remesh(self, sample: ShapeSample, rng: np.random.Generator | None) -> Remeshed | None:
        """The remesh a step uses for ``sample``: a random pool entry, the working-resolution copy, or None."""
        shape = sample.shape
        if self.config.remesh:
            if rng is None:
                raise ConfigError("remeshing augmentation needs a random generator")
            pool = self.resolutions(sample)
            target = int(pool[rng.integers(pool.shape[0])])
        elif self.max_vertices is not None and shape.n_verts > self.max_vertices:
            target = self.max_vertices
        else:
            return None
        return cached_remesh(self.cache, shape.verts.detach().cpu(), shape.faces.detach().cpu(), target)

    def working_geodesics(self, sample: ShapeSample) -> tuple[np.ndarray, np.ndarray]:
        """The original's distance matrix of a shape: exact geodesics of its working-resolution mesh, clamped.

        Parameters
        ----------
        sample : ShapeSample
            The shape as given (not a remesh), CPU.

        Returns
        -------
        verts : (w, 3) float
            Vertices of the working-resolution mesh (the ``max_vertices`` remesh, else the shape).
        dist : (w, w) float32
            Symmetrized exact geodesics, entries above 100 (unreachable) set to 2 (module docstring).
        """
        verts, faces = sample.shape.verts.detach().cpu(), sample.shape.faces.detach().cpu()
        if self.max_vertices is not None and sample.shape.n_verts > self.max_vertices:
            work = cached_remesh(self.cache, verts, faces, self.max_vertices)
            v, f = work.verts, work.faces
        else:
            v, f = verts.numpy(), faces.numpy()

        def compute():
            from shapecorr.geometry.geodesics import geodesic_distances

            dist = geodesic_distances(v, f, method="exact", allow_disconnected=True)
            dist[~(dist <= ORIGINAL_GEODESIC_CLAMP_ABOVE)] = ORIGINAL_GEODESIC_CLAMP_VALUE
            return {"geodesics": dist.astype(np.float32)}

        params = {"method": "exact", "clamp_above": ORIGINAL_GEODESIC_CLAMP_ABOVE,
                  "clamp_value": ORIGINAL_GEODESIC_CLAMP_VALUE}
        dist = self.cache.get_or_compute("geodesics", v, f, params, OPERATOR_VERSIONS["geodesics"], compute)
        return np.asarray(v), dist["geodesics"]

    def distances(self, sample: ShapeSample, original: ShapeSample | None = None) -> torch.Tensor:
        """Cached all-pairs geodesic matrix ``(n, n)`` float32 of a (CPU) sample.

        Parameters
        ----------
        sample : ShapeSample
            The shape the network sees (a remesh or the shape as given).
        original : ShapeSample, optional
            The shape as given, of which ``sample`` is a remesh; needed by ``geodesics="original"`` (default:
            ``sample`` itself).
        """
        if self.geodesics == "original":
            work_verts, work_dist = self.working_geodesics(sample if original is None else original)
            verts = sample.shape.verts.detach().cpu().numpy()
            if verts.shape == work_verts.shape and np.array_equal(verts, work_verts):
                dist = work_dist
            else:
                _, nearest = cKDTree(work_verts.astype(np.float64)).query(verts.astype(np.float64), k=1)
                dist = work_dist[np.ix_(nearest, nearest)]
        else:
            dist = geodesics_cached(self.cache, sample.shape.verts.detach().cpu().numpy(),
                                    sample.shape.faces.detach().cpu().numpy(), method=self.geodesics)
        if not np.isfinite(dist).all():
            raise NumericalError(f"{sample.name}: geodesic matrix contains NaN/Inf (disconnected remesh?)")
        return torch.from_numpy(np.ascontiguousarray(dist, dtype=np.float32))

    def __call__(self, pair: PairSample, rng: np.random.Generator | None, geodesics: bool = True) -> AugmentedPair:
        """Augment one pair.

        Parameters
        ----------
        pair : PairSample
            Any device; the result is on the CPU and carries geometry, lumped areas and ground truth only
            (no eigenbasis, no descriptors).
        rng : numpy Generator
            Draws the pool entries (x first, then y) and the angle; seed it per step for reproducibility.
        geodesics : bool
            Look up (compute and cache on a miss) the geodesic matrices of the augmented shapes.

        Returns
        -------
        AugmentedPair
        """
        samples, remeshes, originals = [], [], []
        for sample in (pair.x, pair.y):
            sample = _geometry_only(sample)
            remeshed = self.working_remesh(sample, rng)
            remeshes.append(remeshed)
            originals.append(sample)
            samples.append(sample if remeshed is None else remeshed_sample(sample, remeshed))
        dists = [self.distances(s, o) for s, o in zip(samples, originals)] if geodesics else [None, None]
        rotation = torch.eye(3)
        if self.config.rotate:
            if rng is None:
                raise ConfigError("rotation augmentation needs a random generator")
            rotation = rotation_about_axis(float(rng.uniform(0.0, 2.0 * math.pi)), self.config.axis)
            samples = [rotate_sample(s, rotation) for s in samples]
        return AugmentedPair(PairSample(*samples), dists[0], dists[1], remeshes[0], remeshes[1], rotation)


# -- on the data side ----------------------------------------------------------------------------------------
class SampleKey(NamedTuple):
    """Key of an augmented training sample: epoch, place in the epoch (batch index), pair index."""

    epoch: int
    position: int
    index: int


def step_rng(seed: int, epoch: int, position: int) -> np.random.Generator:
    """Generator of one training step's augmentation draws, seeded by ``(seed, epoch, position)``."""
    return np.random.default_rng([int(seed), int(epoch), int(position)])


class AugmentedPairDataset(Dataset):
    """Training pairs augmented inside the dataset (in DataLoader workers), see the module docstring.

    Parameters
    ----------
    pairs : PairDataset
    augmenter : PairAugmenter
        Its ``seed`` seeds the draws.
    geodesics : bool or callable(epoch) -> bool
        Whether the samples of an epoch carry geodesic matrices (e.g. a function of the epochs
        where the geodesic loss is on; it must pickle, for worker processes).

    Items: ``dataset[SampleKey(epoch, position, index)]`` -> :class:`AugmentedPair` of pair ``index`` with the
    draws of ``(seed, epoch, position)``; a plain int ``k`` stands for ``SampleKey(epoch, k, k)`` with the
    dataset's :attr:`epoch` (set by :meth:`set_epoch`; for samplers that do not yield keys, e.g. a plain
    sequential one).
    """

    def __init__(self, pairs: PairDataset, augmenter: PairAugmenter, geodesics: bool | Callable[[int], bool] = True):
        self.pairs = pairs
        self.augmenter = augmenter
        self.geodesics = geodesics
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Epoch whose draws plain int indices use."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.pairs)

    def wants_geodesics(self, epoch: int) -> bool:
        """Whether the samples of ``epoch`` carry geodesic matrices."""
        return bool(self.geodesics(epoch) if callable(self.geodesics) else self.geodesics)

    def __getitem__(self, key: SampleKey | int) -> AugmentedPair:
        epoch, position, index = (key if isinstance(key, tuple) else (self.epoch, int(key), int(key)))
        rng = step_rng(self.augmenter.seed, epoch, position)
        return self.augmenter(self.pairs[int(index)], rng, geodesics=self.wants_geodesics(epoch))

    def names(self, k: int) -> tuple[str, str]:
        """Names ``(x, y)`` of the shapes of pair ``k``."""
        return self.pairs.names(k)
