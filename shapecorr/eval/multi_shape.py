"""Multi-shape matching over a collection: pairwise queries, the shape graph, composed maps, cycle consistency.

G-MSM (Eisenberger et al., "G-MSM: Unsupervised Multi-Shape Matching with Graph-based Affinity Priors", CVPR
2023; docs/gmsm.md §4, §5) queries pairs of a collection with a matcher that returns both maps and an alignment
cost, builds a shape graph from the costs (:mod:`shapecorr.matching.shape_graph`) and composes every pair's map
along its shortest path. Used by the G-MSM graph callback (training shapes) and by ``evaluate.py model=gmsm``
(the split's shapes).

A *graph matcher* has ``graph_query(x, y) -> GraphQuery`` (both maps and the cost of one ordered pair); this
module only relies on that method.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm.auto import tqdm

from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import pair_name
from shapecorr.errors import ConfigError
from shapecorr.eval import metrics
from shapecorr.matching.result import MatchResult
from shapecorr.matching.shape_graph import (
    GRAPH_VARIANTS,
    ShapeGraph,
    build_shape_graph,
    compose_all,
    costs_from_pairs,
    knn_candidate_pairs,
)

#: Graph variants of the G-MSM options: those of :func:`build_shape_graph` plus ``knn`` (each shape queried only
#: with its K nearest shapes in a global descriptor space, the graph then ``full`` on those queries).
COLLECTION_VARIANTS = (*GRAPH_VARIANTS, "knn")
#: Eigenvalues (after the constant one) forming the global "shape DNA" descriptor of the knn candidates.
KNN_DESCRIPTOR_EIGS = 20
#: Triplets scored for cycle consistency at most (evenly spaced among all ordered triplets when there are more).
DEFAULT_MAX_TRIPLETS = 200


@dataclass(frozen=True, eq=False)
class GraphQuery:
    """One ordered pair's query: ``map_x_to_y (n_x,)``, ``map_y_to_x (n_y,)`` int64 and its cost (float)."""

    map_x_to_y: torch.Tensor
    map_y_to_x: torch.Tensor
    cost: float


@dataclass
class CollectionGraph:
    """The shape graph of a collection and the maps composed along it.

    Attributes
    ----------
    names : list of str
        Shape names (graph vertex i is ``names[i]``).
    pairs : (P, 2) int64
        The queried ordered pairs.
    graph : ShapeGraph
    composed : dict
        ``(s, t)`` -> ``(n_s,)`` int64 numpy map, for every reachable ordered pair ``s != t``.
    direct : dict
        ``(i, j)`` -> ``(map_i_to_j, map_j_to_i)`` of the queries (numpy int64).
    unreachable : list of (int, int)
    variant : str
    """

    names: list
    pairs: np.ndarray
    graph: ShapeGraph
    composed: dict = field(default_factory=dict)
    direct: dict = field(default_factory=dict)
    unreachable: list = field(default_factory=list)
    variant: str = "full"


def check_variant(variant: str) -> str:
    """``variant`` itself when it is a collection graph variant (ConfigError naming the choices otherwise)."""
    if variant not in COLLECTION_VARIANTS:
        raise ConfigError(f"graph variant must be one of {COLLECTION_VARIANTS}, got {variant!r}")
    return variant


def shape_dna(evals, count: int = KNN_DESCRIPTOR_EIGS) -> np.ndarray:
    """Global descriptor of a shape: its eigenvalues 1..count (the constant eigenfunction's 0 dropped).

    Parameters
    ----------
    evals : (k,) float
        Laplace-Beltrami eigenvalues of the (area-normalized) shape, ascending.

    Returns
    -------
    (count,) float64 (fewer when ``k <= count``)
    """
    e = np.asarray(evals.detach().cpu() if hasattr(evals, "detach") else evals, dtype=np.float64)
    return e[1: count + 1]


def candidate_pairs(n: int, variant: str, knn_k: int = 5, descriptors=None) -> np.ndarray:
    """Ordered pairs to query for a collection of ``n`` shapes.

    All ``i != j`` (``(n (n - 1), 2)``), or for ``knn`` each shape with its ``knn_k`` nearest shapes in
    ``descriptors (n, d)``, both directions of each candidate edge.

    Returns
    -------
    (P, 2) int64
    """
    check_variant(variant)
    if variant != "knn":
        return np.array([(i, j) for i in range(n) for j in range(n) if i != j], dtype=np.int64).reshape(-1, 2)
    if descriptors is None:
        raise ConfigError("the knn graph variant needs one global descriptor per shape")
    return knn_candidate_pairs(descriptors, min(int(knn_k), n - 1), symmetric=True)


def query_pairs(matcher, shapes, pairs, progress: bool = False, device=None, desc: str = "graph queries"
                ) -> list[GraphQuery]:
    """``matcher.graph_query(x, y)`` of every pair ``(i, j)`` of ``shapes`` (a ShapeDataset), in order.

    Returns
    -------
    list of GraphQuery (maps on the CPU)
    """
    out = []
    cache: dict[int, object] = {}

    def sample(i):
        if i not in cache:
            if len(cache) > 8:
                cache.pop(next(iter(cache)))
            s = shapes[i]
            cache[i] = s.to(device) if device is not None else s
        return cache[i]

    for i, j in tqdm([tuple(p) for p in np.asarray(pairs).reshape(-1, 2).tolist()], desc=desc, unit="pair",
                     disable=not progress):
        q = matcher.graph_query(sample(i), sample(j))
        out.append(GraphQuery(q.map_x_to_y.detach().cpu(), q.map_y_to_x.detach().cpu(), float(q.cost)))
    return out


def build_collection_graph(names: Sequence[str], pairs, queries: Sequence[GraphQuery], variant: str = "full"
                           ) -> CollectionGraph:
    """Shape graph from the queries' costs and every reachable pair's composed map.

    Parameters
    ----------
    names : list of str
        The ``n`` shapes.
    pairs : (P, 2) int
        Queried ordered pairs.
    queries : list of GraphQuery
        Their results, in the order of ``pairs``.
    variant : one of :data:`COLLECTION_VARIANTS`

    Returns
    -------
    CollectionGraph
    """
    check_variant(variant)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(queries) != pairs.shape[0]:
        raise ConfigError(f"{pairs.shape[0]} pairs but {len(queries)} query results")
    n = len(names)
    costs = costs_from_pairs(n, pairs, np.array([q.cost for q in queries], dtype=np.float64))
    graph = build_shape_graph(costs, "full" if variant == "knn" else variant)
    direct = {(int(i), int(j)): (q.map_x_to_y, q.map_y_to_x) for (i, j), q in zip(pairs.tolist(), queries)}
    composed = compose_all(graph, direct)
    return CollectionGraph(
        names=list(names), pairs=pairs, graph=graph,
        composed={k: v.cpu().numpy().astype(np.int64) for k, v in composed.maps.items()},
        direct={k: (a.numpy().astype(np.int64), b.numpy().astype(np.int64)) for k, (a, b) in direct.items()},
        unreachable=list(composed.unreachable), variant=variant,
    )


def sample_triplets(n: int, max_triplets: int = DEFAULT_MAX_TRIPLETS) -> np.ndarray:
    """Ordered triplets ``(x, y, z)`` of distinct shapes, all or ``max_triplets`` evenly spaced ones.

    Returns
    -------
    (T, 3) int64
    """
    total = n * (n - 1) * (n - 2)
    if total == 0:
        return np.zeros((0, 3), dtype=np.int64)
    count = min(total, int(max_triplets))
    picks = np.unique(np.linspace(0, total - 1, count).round().astype(np.int64))
    out = []
    for p in picks.tolist():
        x, rest = divmod(p, (n - 1) * (n - 2))
        a, b = divmod(rest, n - 2)
        y = a + (a >= x)
        others = [v for v in range(n) if v not in (x, y)]
        out.append((x, y, others[b]))
    return np.array(out, dtype=np.int64)


def cycle_consistency(maps: dict, triplets, geodesics, sqrt_areas) -> dict:
    """Mean / median cycle-consistency error over triplets (fractions of sqrt(area) of the first shape).

    Parameters
    ----------
    maps : dict
        ``(s, t)`` -> ``(n_s,)`` int map (pairs missing from it skip their triplet).
    triplets : (T, 3) int
    geodesics : callable
        ``geodesics(i) -> (n_i, n_i)`` distances on shape ``i``.
    sqrt_areas : callable
        ``sqrt_areas(i) -> float``.

    Returns
    -------
    dict with ``mean``, ``median`` (None without a scored triplet) and ``n_triplets``.
    """
    per_triplet = []
    for x, y, z in np.asarray(triplets, dtype=np.int64).reshape(-1, 3).tolist():
        if (x, y) not in maps or (y, z) not in maps or (z, x) not in maps:
            continue
        err = metrics.cycle_consistency_errors(maps[(x, y)], maps[(y, z)], maps[(z, x)], geodesics(x), sqrt_areas(x))
        per_triplet.append(float(err.mean()))
    if not per_triplet:
        return {"mean": None, "median": None, "n_triplets": 0}
    return {"mean": float(np.mean(per_triplet)), "median": float(np.median(per_triplet)),
            "n_triplets": len(per_triplet)}


#: Subfolder of an evaluation's output with one file per graph query (resumable).
QUERIES_DIR = "graph_queries"


def query_file(out_dir, name_x: str, name_y: str):
    from pathlib import Path

    return Path(out_dir) / QUERIES_DIR / f"{pair_name(name_x, name_y)}.npz"


def query_pairs_cached(matcher, shapes, pairs, out_dir, progress: bool = False, device=None) -> list[GraphQuery]:
    """:func:`query_pairs` with one ``.npz`` per pair under ``out_dir/graph_queries``.

    Pairs already written are read back, not queried again (an interrupted evaluation resumes).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    todo = [k for k, (i, j) in enumerate(pairs.tolist())
            if not query_file(out_dir, shapes.names[i], shapes.names[j]).is_file()]
    for k, q in zip(todo, query_pairs(matcher, shapes, pairs[todo], progress=progress, device=device)):
        i, j = pairs[k]
        path = query_file(out_dir, shapes.names[i], shapes.names[j])
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(path) as fh:
            np.savez(fh, map_x_to_y=q.map_x_to_y.numpy(), map_y_to_x=q.map_y_to_x.numpy(), cost=np.array(q.cost))
    return [load_query(query_file(out_dir, shapes.names[i], shapes.names[j])) for i, j in pairs.tolist()]


def load_query(path) -> GraphQuery:
    """The :class:`GraphQuery` stored at ``path`` by :func:`query_pairs_cached`."""
    with np.load(path, allow_pickle=False) as z:
        return GraphQuery(torch.from_numpy(z["map_x_to_y"].astype(np.int64)),
                          torch.from_numpy(z["map_y_to_x"].astype(np.int64)), float(z["cost"]))


class ComposedMatcher:
    """A matcher returning the stored maps of a :class:`CollectionGraph` by shape names.

    The maps composed along the graph (``use="graph"``) or the direct query maps (``use="pairwise"``); a pair
    without a path gets its direct map.
    """

    def __init__(self, collection: CollectionGraph, use: str = "graph"):
        if use not in ("graph", "pairwise"):
            raise ConfigError(f"use must be 'graph' or 'pairwise', got {use!r}")
        self.collection, self.use = collection, use
        self.index = {n: i for i, n in enumerate(collection.names)}

    def maps(self) -> dict:
        """``(s, t)`` -> map, as this matcher answers."""
        direct = {k: v[0] for k, v in self.collection.direct.items()}
        return direct if self.use == "pairwise" else {**direct, **self.collection.composed}

    def match(self, x, y) -> MatchResult:
        """The stored point-to-point map x -> y (``p2p (n_x,)`` int64; the identity for x == y)."""
        i, j = self.index[x.name], self.index[y.name]
        if i == j:
            return MatchResult(p2p=torch.arange(x.shape.n_verts))
        if self.use == "graph" and (i, j) in self.collection.composed:
            return MatchResult(p2p=torch.from_numpy(self.collection.composed[(i, j)]))
        if (i, j) in self.collection.direct:
            return MatchResult(p2p=torch.from_numpy(self.collection.direct[(i, j)][0]))
        if (j, i) in self.collection.direct:  # only the reverse query was made (knn): its Y -> X map
            return MatchResult(p2p=torch.from_numpy(self.collection.direct[(j, i)][1]))
        raise ConfigError(f"no map for the pair {pair_name(x.name, y.name)}: it was not queried and has no path")


__all__ = [
    "COLLECTION_VARIANTS",
    "QUERIES_DIR",
    "CollectionGraph",
    "ComposedMatcher",
    "GraphQuery",
    "build_collection_graph",
    "candidate_pairs",
    "check_variant",
    "cycle_consistency",
    "load_query",
    "query_pairs",
    "query_pairs_cached",
    "sample_triplets",
    "shape_dna",
]
