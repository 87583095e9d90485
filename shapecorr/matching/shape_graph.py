"""Shape graph of a collection and point-to-point maps composed along its shortest paths (G-MSM).

G-MSM (Eisenberger et al., "G-MSM: Unsupervised Multi-Shape Matching with Graph-based Affinity Priors", CVPR
2023, §4) matches every ordered pair of shapes ``(i, j)`` of a collection, keeps the alignment cost
``c_ij`` of each query, and builds an undirected graph on the shapes whose edge weights are the symmetrized
costs ``w_ij = min(c_ij, c_ji)``. The map between two shapes is then the composition of the pairwise maps along
the shortest path between them, which routes around pairs that direct matching gets wrong. See docs/gmsm.md.

Conventions
-----------
- ``costs (n, n)``: ``costs[i, j]`` is the cost of the query that matched shape ``i`` (as X) to shape ``j``
  (as Y). Entries that were not queried are ``inf`` (or NaN); the diagonal is ignored. A cost of 0 is a
  valid edge of weight 0 (the original code treated zeros as missing edges).
- ``maps``: a mapping from a query ``(i, j)`` to its point-to-point maps, either the pair
  ``(map_i_to_j (n_i,), map_j_to_i (n_j,))`` (both outputs of one query, e.g. Deep Shells' ``assign_x`` and
  ``assign_y``) or the single ``map_i_to_j``. Maps are int64 tensors (or integer arrays) of target vertex
  indices.
- A *hop* from ``i`` to ``j`` uses the direct map ``i -> j`` of query ``(i, j)`` when ``c_ij < c_ji``, and
  otherwise the reverse map of query ``(j, i)`` (its Y -> X output, which also maps ``i`` to ``j``): the more
  reliable of the two queries decides, as in the original (exact ties: the query ``(min, max)``, so that both
  directions of an edge always use one query). When only one of them is available it is used.

Graph variants (:data:`GRAPH_VARIANTS`)
---------------------------------------
``"full"``: every queried pair is an edge (the complete graph for all-pairs costs). ``"mst"``: its minimum
spanning tree (forest). ``"star"``: edges only between a hub and the other shapes, the hub being the shape
with the lowest mean cost ``mean_{j != i} c_ij`` of its queries. ``"tsp"``: a Hamiltonian path of low total
weight: the travelling-salesman cycle through the shapes and a dummy node joined to all of them at cost 0 (as
in the original), with the dummy removed. The cycle is networkx's simulated annealing started from its greedy
tour, with a fixed seed (deterministic, unlike the original's) and the temperature scaled to the mean edge
weight. Measured against the brute-force optimum on 12 random 8-shape instances (points on a line, in the
plane, random symmetric costs): optimal in 9, at most 13% above it in the others (Christofides' algorithm,
which needs metric costs, was 13-160% above); 4x the annealing effort found all 12 optima at 4x the time.

Shortest paths with predecessors are computed for every pair on the chosen edges by ``scipy.sparse.csgraph``
(Floyd-Warshall on dense graphs, Dijkstra on sparse ones); pairs in different components are reported, not composed.

Candidate graphs for large collections
--------------------------------------
All-pairs costs need ``n^2`` queries. :func:`knn_candidate_pairs` picks, from a cheap global descriptor per
shape (e.g. a few low Laplace-Beltrami eigenvalues, "shape DNA"), each shape's ``K`` nearest shapes, so only
``n K`` queries are needed; :func:`costs_from_pairs` turns their costs into a sparse cost matrix that
:func:`build_shape_graph` accepts like a full one.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import networkx as nx
import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import dijkstra, floyd_warshall, minimum_spanning_tree
from scipy.spatial import cKDTree

from shapecorr.errors import ConfigError, CorrespondenceError, ShapeCorrError

GRAPH_VARIANTS = ("full", "mst", "star", "tsp")
#: Simulated annealing of the tsp variant (networkx.approximation.simulated_annealing_tsp; project choice, see
#: the module docstring): outer iterations without improvement before stopping, moves per temperature, cooling
#: rate, initial temperature as a multiple of the mean edge weight, and the default seed.
TSP_ANNEAL_ITERATIONS = 50
TSP_ANNEAL_INNER = 200
TSP_ANNEAL_ALPHA = 0.05
TSP_ANNEAL_TEMPERATURE = 1.0
TSP_SEED = 0
#: Graphs with more than this fraction of all pairs as edges use Floyd-Warshall (O(n^3), about 5x faster than
#: all-source Dijkstra on a complete graph: 0.10 vs 0.45 s at n = 300, 3.3 s at n = 1000), sparser ones Dijkstra.
DENSE_GRAPH_FRACTION = 0.25
#: scipy.sparse.csgraph marks "no predecessor" with this value.
_SCIPY_NO_PREDECESSOR = -9999

MapLike = torch.Tensor | np.ndarray
#: One query's maps: ``(map_i_to_j, map_j_to_i)`` or ``map_i_to_j`` alone.
QueryMaps = MapLike | Sequence[MapLike]


class UnreachableShapeError(ShapeCorrError):
    """Two shapes lie in different components of the shape graph (no path, no composed map)."""


def _as_costs(costs) -> np.ndarray:
    c = np.array(costs.detach().cpu() if hasattr(costs, "detach") else costs, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] != c.shape[1] or c.shape[0] == 0:
        raise ConfigError(f"costs must be a non-empty square (n, n) matrix, got shape {c.shape}")
    c[np.isnan(c)] = np.inf
    off = ~np.eye(c.shape[0], dtype=bool)
    if (c[off] < 0).any():
        raise ConfigError("alignment costs must be >= 0 (shortest paths need non-negative edge weights)")
    c[~off] = np.inf
    return c


def symmetric_weights(costs) -> np.ndarray:
    """Undirected edge weights ``w_ij = min(c_ij, c_ji)`` of a cost matrix.

    Parameters
    ----------
    costs : (n, n) float
        ``costs[i, j]``: cost of the query ``i -> j``; ``inf`` / NaN where not queried; diagonal ignored.

    Returns
    -------
    (n, n) float64
        Symmetric; ``inf`` where neither direction was queried and on the diagonal.

    Raises
    ------
    ConfigError
        Not a square matrix, or negative costs.
    """
    c = _as_costs(costs)
    return np.minimum(c, c.T)


def _edges_of(weights: np.ndarray) -> np.ndarray:
    """Pairs ``(i, j)``, ``i < j``, with a finite weight, sorted: ``(E, 2)`` int64."""
    i, j = np.triu_indices(weights.shape[0], k=1)
    keep = np.isfinite(weights[i, j])
    return np.stack((i[keep], j[keep]), axis=1).astype(np.int64)


def _graph_matrix(n: int, edges: np.ndarray, weights: np.ndarray) -> sp.csr_matrix:
    """Sparse symmetric adjacency; explicit zeros are zero-weight edges for scipy.sparse.csgraph."""
    w = weights[edges[:, 0], edges[:, 1]]
    return sp.csr_matrix(
        (np.r_[w, w], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)
    )


def _mst_edges(n: int, edges: np.ndarray, weights: np.ndarray) -> np.ndarray:
    if edges.shape[0] == 0:
        return edges
    w = weights[edges[:, 0], edges[:, 1]]
    # scipy's minimum_spanning_tree ignores zero entries; adding one constant to every edge weight does not change
    # which spanning forest is minimal (every spanning forest has n - #components edges), so shift zeros away.
    offset = (w.max() if w.max() > 0 else 1.0) if (w == 0).any() else 0.0
    tree = minimum_spanning_tree(sp.csr_matrix((w + offset, (edges[:, 0], edges[:, 1])), shape=(n, n))).tocoo()
    out = np.stack((np.minimum(tree.row, tree.col), np.maximum(tree.row, tree.col)), axis=1).astype(np.int64)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def star_hub(costs) -> int:
    """Hub of the star graph: the shape whose queries have the lowest mean cost ``mean_{j != i} c_ij``.

    Parameters
    ----------
    costs : (n, n) float
        Directed costs (``inf`` where not queried, ignored in the mean).

    Returns
    -------
    int
        Ties: the smallest index.
    """
    c = _as_costs(costs)
    finite = np.isfinite(c)
    counts = finite.sum(axis=1)
    means = np.where(counts > 0, np.where(finite, c, 0.0).sum(axis=1) / np.maximum(counts, 1), np.inf)
    return int(np.argmin(means))


def _tsp_edges(weights: np.ndarray, seed: int) -> np.ndarray:
    n = weights.shape[0]
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    off = ~np.eye(n, dtype=bool)
    if not np.isfinite(weights[off]).all():
        raise ConfigError(
            "the tsp shape graph needs the costs of all pairs (some are missing, e.g. a knn candidate set); "
            "use variant 'full', 'mst' or 'star'"
        )
    g = nx.Graph()
    g.add_nodes_from(range(n + 1))
    i, j = np.nonzero(np.triu(off, k=1))
    g.add_weighted_edges_from(zip(i.tolist(), j.tolist(), weights[i, j].tolist()))
    dummy = n  # zero-cost node: the best cycle through it is the best Hamiltonian path through the shapes
    g.add_weighted_edges_from((dummy, k, 0.0) for k in range(n))
    cycle = nx.approximation.simulated_annealing_tsp(
        g, "greedy", weight="weight", source=dummy, temp=TSP_ANNEAL_TEMPERATURE * float(weights[off].mean()),
        max_iterations=TSP_ANNEAL_ITERATIONS, N_inner=TSP_ANNEAL_INNER, alpha=TSP_ANNEAL_ALPHA, seed=seed,
    )[:-1]
    at = cycle.index(dummy)
    path = cycle[at + 1 :] + cycle[:at]
    out = np.array([(min(a, b), max(a, b)) for a, b in itertools.pairwise(path)], dtype=np.int64)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


@dataclass(frozen=True)
class ShapeGraph:
    """A shape graph with all-pairs shortest paths (build it with :func:`build_shape_graph`).

    Attributes
    ----------
    costs : (n, n) float64
        Directed query costs (``inf`` where not queried and on the diagonal).
    weights : (n, n) float64
        Symmetrized costs of the graph's edges, ``inf`` for pairs that are not an edge of this variant.
    edges : (E, 2) int64
        The undirected edges ``(i, j)``, ``i < j``, sorted.
    variant : str
        One of :data:`GRAPH_VARIANTS`.
    hub : int or None
        The hub of a ``"star"`` graph.
    distances : (n, n) float64
        Shortest-path lengths (``inf`` between components).
    predecessors : (n, n) int64
        ``predecessors[s, t]``: the vertex before ``t`` on the shortest path from ``s`` (-1 for ``t = s`` and
        unreachable ``t``).
    """

    costs: np.ndarray
    weights: np.ndarray
    edges: np.ndarray
    variant: str
    hub: int | None
    distances: np.ndarray
    predecessors: np.ndarray

    @property
    def n(self) -> int:
        """Number of shapes."""
        return self.costs.shape[0]

    def reachable(self, s: int, t: int) -> bool:
        """Whether a path joins shapes ``s`` and ``t``."""
        return bool(np.isfinite(self.distances[s, t]))

    def unreachable_pairs(self) -> np.ndarray:
        """Ordered pairs ``(s, t)``, ``s != t``, without a path: ``(P, 2)`` int64, sorted."""
        s, t = np.nonzero(~np.isfinite(self.distances))
        return np.stack((s, t), axis=1).astype(np.int64)

    def path(self, s: int, t: int) -> list[int]:
        """Shapes on the shortest path ``[s, ..., t]`` (``[s]`` for ``s = t``).

        Raises
        ------
        UnreachableShapeError
            ``s`` and ``t`` are in different components.
        """
        if not (0 <= s < self.n and 0 <= t < self.n):
            raise ConfigError(f"shape indices must be in [0, {self.n}), got {s}, {t}")
        if not self.reachable(s, t):
            raise UnreachableShapeError(
                f"shapes {s} and {t} are not connected in the {self.variant} shape graph (missing queries: add "
                "candidate pairs, e.g. a larger K of the knn candidate graph)"
            )
        out = [t]
        while out[-1] != s:
            out.append(int(self.predecessors[s, out[-1]]))
        return out[::-1]


def build_shape_graph(costs, variant: str = "full", tsp_seed: int = TSP_SEED) -> ShapeGraph:
    """Shape graph of a collection from the pairwise query costs, with all shortest paths.

    Parameters
    ----------
    costs : (n, n) float
        ``costs[i, j]``: cost of the query ``i -> j`` (see the module docstring); ``inf`` / NaN where not queried.
    variant : {"full", "mst", "star", "tsp"}
        Which edges the graph keeps (module docstring).
    tsp_seed : int
        Seed of the simulated annealing of ``"tsp"`` (the result is a deterministic function of costs and seed).

    Returns
    -------
    ShapeGraph

    Raises
    ------
    ConfigError
        Unknown variant, invalid costs, or ``"tsp"`` with missing costs.
    """
    if variant not in GRAPH_VARIANTS:
        raise ConfigError(f"shape graph variant must be one of {GRAPH_VARIANTS}, got {variant!r}")
    c = _as_costs(costs)
    n = c.shape[0]
    w_all = np.minimum(c, c.T)
    candidates = _edges_of(w_all)
    hub = None
    if variant == "full":
        edges = candidates
    elif variant == "mst":
        edges = _mst_edges(n, candidates, w_all)
    elif variant == "star":
        hub = star_hub(c)
        edges = candidates[(candidates[:, 0] == hub) | (candidates[:, 1] == hub)]
    else:
        edges = _tsp_edges(w_all, tsp_seed)
    weights = np.full((n, n), np.inf)
    weights[edges[:, 0], edges[:, 1]] = w_all[edges[:, 0], edges[:, 1]]
    weights[edges[:, 1], edges[:, 0]] = w_all[edges[:, 0], edges[:, 1]]
    shortest = floyd_warshall if edges.shape[0] > DENSE_GRAPH_FRACTION * n * (n - 1) / 2 else dijkstra
    dist, pred = shortest(_graph_matrix(n, edges, w_all), directed=False, return_predecessors=True)
    pred = pred.astype(np.int64)
    pred[pred == _SCIPY_NO_PREDECESSOR] = -1
    return ShapeGraph(c, weights, edges, variant, hub, dist, pred)


def _as_map(m) -> torch.Tensor:
    t = torch.as_tensor(m)
    if t.ndim != 1 or t.dtype.is_floating_point or t.dtype == torch.bool:
        raise CorrespondenceError(f"point-to-point maps must be 1-D integer arrays, "
                                  f"got {t.dtype} of shape {tuple(t.shape)}")
    return t.long()


def _query_maps(maps: Mapping, i: int, j: int) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(map i -> j, map j -> i) of the stored query ``(i, j)`` (None where absent)."""
    if (i, j) not in maps:
        return None, None
    m = maps[(i, j)]
    if isinstance(m, (tuple, list)):
        fwd, bwd = (list(m) + [None, None])[:2]
        return (None if fwd is None else _as_map(fwd)), (None if bwd is None else _as_map(bwd))
    return _as_map(m), None


def hop_map(i: int, j: int, costs, maps: Mapping[tuple[int, int], QueryMaps]) -> torch.Tensor:
    """Point-to-point map from shape ``i`` to shape ``j`` for one hop of a path.

    The direct map of query ``(i, j)`` when ``c_ij < c_ji``, else the reverse (Y -> X) map of query ``(j, i)``;
    on an exact tie the query ``(min(i, j), max(i, j))``, so that the hops ``i -> j`` and ``j -> i`` always use
    the same query. When only one of them is stored, that one.

    Parameters
    ----------
    i, j : int
    costs : (n, n) float
        Directed query costs.
    maps : mapping
        Query ``(a, b)`` -> ``(map_a_to_b, map_b_to_a)`` or ``map_a_to_b`` (module docstring).

    Returns
    -------
    (n_i,) int64 tensor
        For each vertex of shape ``i``, its vertex on shape ``j``.

    Raises
    ------
    CorrespondenceError
        Neither query provides a map from ``i`` to ``j``.
    """
    c = costs
    direct, _ = _query_maps(maps, i, j)
    _, reverse = _query_maps(maps, j, i)
    c_ij = float(c[i][j]) if direct is not None else np.inf
    c_ji = float(c[j][i]) if reverse is not None else np.inf
    # exact ties: the query (min, max) serves both directions, so that both hops use the same query
    if direct is not None and (reverse is None or c_ij < c_ji or (c_ij == c_ji and i < j)):
        return direct
    if reverse is not None:
        return reverse
    raise CorrespondenceError(
        f"no map from shape {i} to shape {j}: neither query ({i}, {j}) nor the reverse output of ({j}, {i}) is stored"
    )


def compose_along_path(path: Sequence[int], costs, maps: Mapping[tuple[int, int], QueryMaps],
                       n_source: int | None = None) -> torch.Tensor:
    """Point-to-point map from ``path[0]`` to ``path[-1]``: the hop maps (:func:`hop_map`) chained in order.

    Parameters
    ----------
    path : sequence of int
        Shapes ``[s, ..., t]`` (e.g. :meth:`ShapeGraph.path`).
    costs : (n, n) float
        Directed query costs (choose each hop's direction).
    maps : mapping
        Stored query maps (module docstring).
    n_source : int, optional
        Vertices of ``s``; only needed for a path of one shape (the identity map).

    Returns
    -------
    (n_s,) int64 tensor
        ``out[v] = p_{m-1}[... p_0[v]]``: for each vertex of ``s`` its vertex on ``t``.
    """
    path = [int(p) for p in path]
    if not path:
        raise ConfigError("a path needs at least one shape")
    if len(path) == 1:
        if n_source is None:
            raise ConfigError("the identity map of a one-shape path needs n_source (its vertex count)")
        return torch.arange(int(n_source), dtype=torch.int64)
    out = hop_map(path[0], path[1], costs, maps)
    for a, b in itertools.pairwise(path[1:]):
        out = _chain(out, hop_map(a, b, costs, maps), a)
    return out


def _chain(first: torch.Tensor, then: torch.Tensor, via: int) -> torch.Tensor:
    """``then[first]``: a map into shape ``via`` followed by a map out of it (indices checked)."""
    then = then.to(first.device)
    if first.numel() and (int(first.max()) >= then.shape[0] or int(first.min()) < 0):
        raise CorrespondenceError(
            f"the map into shape {via} has indices outside [0, {then.shape[0]}) (its maps do not fit its vertex count)"
        )
    return then[first]


@dataclass
class ComposedMaps:
    """Maps composed along a shape graph (:func:`compose_all`).

    Attributes
    ----------
    maps : dict
        ``(s, t)`` -> ``(n_s,)`` int64 tensor, the map from ``s`` to ``t`` along the shortest path.
    paths : dict
        ``(s, t)`` -> the path ``[s, ..., t]`` used.
    unreachable : list of (int, int)
        Requested pairs without a path (not composed).
    """

    maps: dict = field(default_factory=dict)
    paths: dict = field(default_factory=dict)
    unreachable: list = field(default_factory=list)


def compose_all(graph: ShapeGraph, maps: Mapping[tuple[int, int], QueryMaps],
                pairs: Sequence[tuple[int, int]] | np.ndarray | None = None) -> ComposedMaps:
    """Compose the maps of many pairs along the graph's shortest paths; unreachable pairs are reported.

    Parameters
    ----------
    graph : ShapeGraph
    maps : mapping
        Stored query maps (module docstring).
    pairs : (P, 2) int, optional
        Ordered pairs ``(s, t)``, ``s != t``; default all ordered pairs.

    Returns
    -------
    ComposedMaps
    """
    if pairs is None:
        pairs = [(s, t) for s in range(graph.n) for t in range(graph.n) if s != t]
    out = ComposedMaps()
    by_source: dict[int, list[int]] = {}
    for s, t in np.asarray(pairs, dtype=np.int64).reshape(-1, 2).tolist():
        if s == t:
            raise ConfigError(f"compose_all needs pairs of different shapes, got ({s}, {t})")
        if not graph.reachable(s, t):
            out.unreachable.append((s, t))
        else:
            by_source.setdefault(s, []).append(t)
    for s, targets in by_source.items():
        # The shortest paths from s form a tree (the predecessors): compose each vertex's map once, from its
        # predecessor's, so a source costs one hop per reached shape instead of one per hop of every path. The
        # result is the same chain of hop maps as compose_along_path(graph.path(s, t)).
        composed: dict[int, torch.Tensor] = {}
        for t in targets:
            chain = [t]
            while chain[-1] != s and chain[-1] not in composed:
                chain.append(int(graph.predecessors[s, chain[-1]]))
            for prev, v in zip(chain[:0:-1], chain[-2::-1]):
                hop = hop_map(prev, v, graph.costs, maps)
                composed[v] = hop if prev == s else _chain(composed[prev], hop, prev)
            out.maps[(s, t)] = composed[t]
            out.paths[(s, t)] = graph.path(s, t)
    return out


def knn_candidate_pairs(descriptors, k: int, symmetric: bool = False) -> np.ndarray:
    """Query pairs of a knn candidate graph: each shape with its ``k`` nearest shapes in a global descriptor space.

    Parameters
    ----------
    descriptors : (n, d) float
        One cheap global descriptor per shape (Euclidean distances are used).
    k : int
        Neighbours per shape, ``1 <= k <= n - 1``.
    symmetric : bool
        Also include ``(j, i)`` for every pair ``(i, j)`` (both directions of each candidate edge queried).

    Returns
    -------
    (n k, 2) int64, or (P, 2) with ``n k <= P <= 2 n k`` when symmetric
        Ordered pairs ``(i, j)``: rows grouped by ``i`` ascending, neighbours by increasing distance (ties: the
        smaller index first); unique.

    Raises
    ------
    ConfigError
        Invalid descriptors or ``k``.
    """
    x = np.asarray(descriptors.detach().cpu() if hasattr(descriptors, "detach") else descriptors, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or not np.isfinite(x).all():
        raise ConfigError(f"descriptors must be a finite (n, d) array with n >= 2, got shape {x.shape}")
    n = x.shape[0]
    if not 1 <= k <= n - 1:
        raise ConfigError(f"knn candidate graph needs 1 <= k <= n - 1 = {n - 1}, got k={k}")
    dist, idx = cKDTree(x).query(x, k=min(k + 1, n))
    dist, idx = np.atleast_2d(dist), np.atleast_2d(idx)
    rows = []
    for i in range(n):
        keep = idx[i] != i
        d_i, j_i = dist[i][keep], idx[i][keep]
        order = np.lexsort((j_i, d_i))[:k]  # by distance, then index (a deterministic tie rule)
        rows.append(np.stack((np.full(order.size, i), j_i[order]), axis=1))
    pairs = np.concatenate(rows).astype(np.int64)
    if symmetric:
        both = np.concatenate((pairs, pairs[:, ::-1]))
        _, first = np.unique(both, axis=0, return_index=True)
        pairs = both[np.sort(first)]
    return pairs


def costs_from_pairs(n: int, pairs, values) -> np.ndarray:
    """Directed cost matrix of a sparse set of queries (``inf`` where not queried).

    Parameters
    ----------
    n : int
        Number of shapes.
    pairs : (P, 2) int
        Queried ordered pairs ``(i, j)``.
    values : (P,) float
        Their costs ``>= 0``; a pair given twice keeps the lower cost.

    Returns
    -------
    (n, n) float64
    """
    p = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    v = np.asarray(values.detach().cpu() if hasattr(values, "detach") else values, dtype=np.float64).reshape(-1)
    if v.shape[0] != p.shape[0]:
        raise ConfigError(f"{p.shape[0]} pairs but {v.shape[0]} costs")
    if p.size and (p.min() < 0 or p.max() >= n):
        raise ConfigError(f"pair indices must be in [0, {n})")
    out = np.full((n, n), np.inf)
    np.minimum.at(out, (p[:, 0], p[:, 1]), v)
    return out


__all__ = [
    "GRAPH_VARIANTS",
    "ComposedMaps",
    "ShapeGraph",
    "UnreachableShapeError",
    "build_shape_graph",
    "compose_all",
    "compose_along_path",
    "costs_from_pairs",
    "hop_map",
    "knn_candidate_pairs",
    "star_hub",
    "symmetric_weights",
]
