"""Exact nearest neighbours between two embeddings: both directions of one pair, or one direction of a batch.

Used by the axiomatic shell refinements (Deep Shells test time, G-MSM queries, Smooth Shells): for every
point of X its nearest point of Y in the product-space embedding and vice versa
(:func:`bidirectional_nearest_neighbors`). Smooth Shells' random search and rigid surrogate runs solve many
small independent problems at once (:func:`batched_nearest_neighbors`).

Backends:

- ``"kdtree"``: scipy's ``cKDTree`` in float64 (exact), one tree per side; with ``workers`` other than 1
  the two directions (tree builds included) run in two threads, each querying with half of the workers.
  scipy rejects non-finite points itself (one pass over each side), which is this backend's finiteness
  check: it raises :class:`~shapecorr.errors.NumericalError` without a second pass in torch.
  The embeddings of the shell refinements are intrinsically 2-D surfaces, so the trees prune well even in
  hundreds of dimensions: faster than blocked brute force on CPUs up to the 505-D top level (measured).
- ``"brute"``: blocked exact search with torch on the tensors' device (CPU or GPU): distance blocks from one
  matrix product each, both directions from the same blocks (row argmin per block, running column minimum).
  Never holds more than ``block_size * m`` distances.
- ``"auto"``: ``"brute"`` on CUDA tensors, ``"kdtree"`` otherwise.

Ties are broken arbitrarily (by the backend); the squared-distance expansion of ``"brute"`` is evaluated in
float64 unless ``exact=False``, so both backends return the same neighbours up to exact ties.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy
import torch
from scipy.spatial import cKDTree

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.finiteness import all_finite

#: Rows of X per distance block of the brute-force search (block of ``block_size x m`` entries).
DEFAULT_BLOCK_SIZE = 2048
#: Threads used by the kd-tree queries (-1: all cores).
DEFAULT_WORKERS = -1
#: k-d tree of :func:`bidirectional_nearest_neighbors`: points per leaf and median (True) or sliding-midpoint
#: (False) splits. Measured on the 41 levels of a Deep Shells query (5k vertices, 12 to 505 dimensions, one
#: thread, builds and queries of both directions, medians of 3): 1.36 s with 8 / sliding midpoint, 1.50 s with
#: scipy's defaults (16 / median), 1.37-1.69 s for the other settings of 4-24 points per leaf. Exact either way.
KDTREE_LEAFSIZE = 8
KDTREE_BALANCED = False
#: Points per leaf up to ``KDTREE_LOW_DIM`` dimensions (:func:`kdtree_leafsize`). Replaying the 40 levels of a
#: Deep Shells refinement of two 148k-vertex shapes (one thread): 160 s of search with 8 points per leaf everywhere,
#: 145 s with 32 up to 64 dimensions, 147 s with 64 or 128 there; at 5k vertices no difference (docs/speed.md §6).
KDTREE_LOW_DIM_LEAFSIZE = 32
KDTREE_LOW_DIM = 64

#: Distances per block of the batched brute-force search (memory ~ rows x batch x points).
BATCH_BLOCK_ENTRIES = 1 << 24

#: Search backends of :func:`bidirectional_nearest_neighbors` (module docstring).
NN_BACKENDS = ("auto", "kdtree", "brute")


#: Message of the error raised for non-finite embeddings.
NOT_FINITE = "nearest neighbours: the embedding contains NaN or Inf"
#: scipy >= 1.11 refuses non-finite tree points and queries itself (a ValueError, raised here as NumericalError), so
#: the k-d tree backend skips its own pass over the embeddings; older versions return garbage indices instead.
SCIPY_CHECKS_FINITE = tuple(int(part) for part in scipy.__version__.split(".")[:2]) >= (1, 11)


def _check_shapes(emb_x: torch.Tensor, emb_y: torch.Tensor) -> None:
    if emb_x.dim() != 2 or emb_y.dim() != 2 or emb_x.shape[1] != emb_y.shape[1]:
        raise ConfigError(f"nearest neighbours: need (n, d) and (m, d), got {tuple(emb_x.shape)}, {tuple(emb_y.shape)}")
    if emb_x.shape[0] == 0 or emb_y.shape[0] == 0:
        raise ConfigError("nearest neighbours: empty point set")


def _check_finite(*embs: torch.Tensor) -> None:
    if not all_finite(*embs):
        raise NumericalError(NOT_FINITE)


def _tree(points: np.ndarray, **options) -> cKDTree:
    """``cKDTree(points, **options)``; scipy refuses non-finite points (and queries), raised as ``NumericalError``."""
    try:
        return cKDTree(points, **options)
    except ValueError as err:
        if "finite" in str(err):
            raise NumericalError(NOT_FINITE) from None
        raise


def _query(tree: cKDTree, queries: np.ndarray, workers: int = 1) -> np.ndarray:
    """Index of the nearest tree point of every query (int64); non-finite queries raise ``NumericalError``."""
    try:
        return np.asarray(tree.query(queries, k=1, workers=workers)[1], dtype=np.int64)
    except ValueError as err:
        if "finite" in str(err):
            raise NumericalError(NOT_FINITE) from None
        raise


def _nearest(points: np.ndarray, queries: np.ndarray, workers: int) -> np.ndarray:
    tree = _tree(points, leafsize=kdtree_leafsize(points.shape[1]), balanced_tree=KDTREE_BALANCED)
    return _query(tree, queries, workers)


def resolved_backend(backend: str, device: torch.device) -> str:
    """The search backend ``"auto"`` stands for on ``device`` (``"brute"`` on CUDA, else ``"kdtree"``)."""
    if backend != "auto":
        return backend
    return "brute" if torch.device(device).type == "cuda" else "kdtree"


def kdtree_leafsize(dim: int) -> int:
    """Points per leaf of the k-d trees of :func:`bidirectional_nearest_neighbors` in ``dim`` dimensions."""
    return KDTREE_LOW_DIM_LEAFSIZE if dim <= KDTREE_LOW_DIM else KDTREE_LEAFSIZE


def spatial_order(points: torch.Tensor) -> torch.Tensor:
    """A cache-friendly order of points: nearby points get nearby positions (the order of a k-d tree's leaves).

    Queries of a k-d tree run faster in this order when the tree does not fit the CPU caches: consecutive
    queries visit the same nodes and points. At 148k points and 505 dimensions (a 600 MB tree) the queries took
    5.3 s in the spatial order of the vertex positions and 6.5 s in the vertex order of a remeshed scan; each
    query's result does not depend on the order (exact search).

    Parameters
    ----------
    points : (n, d) float

    Returns
    -------
    (n,) int64
        A permutation of ``range(n)``, on the points' device.
    """
    tree = cKDTree(points.detach().to("cpu", torch.float64).numpy(), leafsize=KDTREE_LEAFSIZE)
    return torch.from_numpy(np.asarray(tree.indices, dtype=np.int64)).to(points.device)


def _kdtree(emb_x: torch.Tensor, emb_y: torch.Tensor, workers: int) -> tuple[torch.Tensor, torch.Tensor]:
    x = emb_x.detach().to("cpu", torch.float64).numpy()
    y = emb_y.detach().to("cpu", torch.float64).numpy()
    threads = _available_cores() if workers == -1 else max(1, int(workers))
    # non-finite points or queries: scipy's own check, raised by _tree / _query as NumericalError
    if threads >= 2:
        # scipy releases the GIL while building and querying, so the two directions (tree build included,
        # which `workers` does not parallelize) run concurrently, each with half of the query threads.
        with ThreadPoolExecutor(max_workers=2) as pool:
            job = pool.submit(_nearest, x, y, threads - threads // 2)  # for each point of Y, one of X
            nn_y = _nearest(y, x, threads // 2)  # for each point of X, the nearest of Y
            nn_x = job.result()
    else:
        nn_y, nn_x = _nearest(y, x, 1), _nearest(x, y, 1)
    device = emb_x.device
    return torch.from_numpy(nn_y).to(device), torch.from_numpy(nn_x).to(device)


def _available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _brute(emb_x: torch.Tensor, emb_y: torch.Tensor, block_size: int, exact: bool):
    dtype = torch.float64 if exact else emb_x.dtype
    x = emb_x.detach().to(dtype)
    y = emb_y.detach().to(dtype)
    n, m = x.shape[0], y.shape[0]
    yy = (y * y).sum(1)
    nn_y = torch.empty(n, dtype=torch.int64, device=x.device)
    col_best = torch.full((m,), float("inf"), dtype=dtype, device=x.device)
    nn_x = torch.zeros(m, dtype=torch.int64, device=x.device)
    for start in range(0, n, block_size):
        xb = x[start:start + block_size]
        # |x|^2 is constant per row, so rows only need |y|^2 - 2 x.y; columns need the full distance.
        d = torch.addmm(yy[None, :], xb, y.transpose(0, 1), alpha=-2.0)
        nn_y[start:start + xb.shape[0]] = d.argmin(1)
        d.add_((xb * xb).sum(1)[:, None])
        block_min, block_arg = d.min(0)
        better = block_min < col_best
        col_best = torch.where(better, block_min, col_best)
        nn_x = torch.where(better, block_arg + start, nn_x)
    return nn_y, nn_x


def bidirectional_nearest_neighbors(
    emb_x: torch.Tensor,
    emb_y: torch.Tensor,
    backend: str = "auto",
    block_size: int = DEFAULT_BLOCK_SIZE,
    exact: bool = True,
    workers: int = DEFAULT_WORKERS,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest neighbours X -> Y and Y -> X (Euclidean).

    Parameters
    ----------
    emb_x : (n, d) float
    emb_y : (m, d) float
    backend : {"auto", "kdtree", "brute"}
        See the module docstring.
    block_size : int
        Rows per block for ``"brute"``.
    exact : bool
        ``"brute"`` only: evaluate distances in float64 (True) or in the input dtype.
    workers : int
        ``"kdtree"`` only: query threads (-1: all).

    Returns
    -------
    nn_y_of_x : (n,) int64
        For each point of X, the index of its nearest point of Y (a point-to-point map X -> Y).
    nn_x_of_y : (m,) int64
        For each point of Y, the index of its nearest point of X.

    Raises
    ------
    ConfigError
        On an unknown backend, mismatched widths or an empty point set.
    NumericalError
        If either embedding contains NaN or Inf.
    """
    if backend not in NN_BACKENDS:
        raise ConfigError(f"nearest-neighbour backend must be one of {NN_BACKENDS}, got {backend!r}")
    _check_shapes(emb_x, emb_y)
    backend = resolved_backend(backend, emb_x.device)
    if backend == "kdtree":
        if not SCIPY_CHECKS_FINITE:
            _check_finite(emb_x, emb_y)
        return _kdtree(emb_x, emb_y, workers)
    _check_finite(emb_x, emb_y)
    return _brute(emb_x, emb_y, int(block_size), exact)


def batched_nearest_neighbors(queries: torch.Tensor, points: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """Exact Euclidean nearest neighbours of a batch of independent problems (one direction).

    A batch dimension of 1 on either side is shared by every batch element.

    Backends: ``"kdtree"``: scipy k-d trees in float64 (exact), faster on the CPU for low-dimensional embeddings
    (measured: brute force ~20x slower for 1000 x 5000 points in 26 dimensions, batched float32 brute force
    ~1.7x slower for 1000 x 1000); a shared point set is one tree for the whole batch, and the batch elements
    are spread over torch's intra-op thread count (scipy releases the GIL). ``"brute"``: one distance block per
    chunk of queries for the whole batch, in the input dtype, on the tensors' device. ``"auto"``: ``"kdtree"``
    on the CPU, ``"brute"`` elsewhere.

    Parameters
    ----------
    queries : (B or 1, q, d) float
    points : (B or 1, p, d) float
    backend : {"auto", "kdtree", "brute"}

    Returns
    -------
    (B, q) int64
        For each query, the index of its nearest point (on the device of ``queries``).
    """
    if backend not in NN_BACKENDS:
        raise ConfigError(f"nearest-neighbour backend must be one of {NN_BACKENDS}, got {backend!r}")
    if queries.dim() != 3 or points.dim() != 3 or queries.shape[2] != points.shape[2]:
        raise ConfigError(f"batched nearest neighbours: need (B, q, d) and (B, p, d), got {tuple(queries.shape)}, "
                          f"{tuple(points.shape)}")
    b = max(queries.shape[0], points.shape[0])
    q, p = queries.shape[1], points.shape[1]
    if backend == "auto":
        backend = "kdtree" if queries.device.type == "cpu" else "brute"
    if backend == "kdtree":
        pts = points.detach().to(torch.float64).cpu().numpy()
        qrs = queries.detach().to(torch.float64).cpu().numpy()
        shared = _tree(pts[0]) if pts.shape[0] == 1 else None
        out = np.empty((b, q), dtype=np.int64)

        def one(i: int) -> None:
            tree = shared if shared is not None else _tree(pts[i])
            out[i] = _query(tree, qrs[0] if qrs.shape[0] == 1 else qrs[i])

        threads = min(torch.get_num_threads(), b)
        if threads < 2:
            for i in range(b):
                one(i)
        else:
            with ThreadPoolExecutor(max_workers=threads) as pool:
                list(pool.map(one, range(b)))
        return torch.from_numpy(out).to(queries.device)
    queries, points = queries.expand(b, -1, -1), points.expand(b, -1, -1)
    chunk = max(1, BATCH_BLOCK_ENTRIES // max(1, b * p))
    out = torch.empty(b, q, dtype=torch.int64, device=queries.device)
    pp = points.square().sum(-1)[:, None, :]
    for start in range(0, q, chunk):
        qb = queries[:, start:start + chunk]
        d = torch.baddbmm(pp, qb, points.transpose(1, 2), alpha=-2.0)
        out[:, start:start + chunk] = d.argmin(-1)
    return out
