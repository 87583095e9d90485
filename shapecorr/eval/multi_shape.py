"""Multi-shape matching over a collection, for any matcher: pair queries, the shape graph, composed maps.

G-MSM (Eisenberger et al., "G-MSM: Unsupervised Multi-Shape Matching with Graph-based Affinity Priors", CVPR
2023; docs/gmsm.md §4) queries pairs of a collection, builds a shape graph from the pair costs
(:mod:`shapecorr.matching.shape_graph`) and composes every pair's map along its shortest path. Here this is a
wrapper around any matcher (``evaluate.py model=<any> multishape=graph``, docs/evaluation.md §7):
:class:`MultiShapeMatcher` queries the pairs (sharded over ranks, one resumable file per query), builds the
graph, and then answers ``match(x, y)`` with the composed map, so that the normal per-pair protocol scores it.
G-MSM's training callback builds its graph with the same functions (:func:`query_pairs`,
:func:`build_collection_graph`).

Pair costs (:data:`PAIR_COSTS`, the edge weights before symmetrization):

``matcher``
    The matcher's own cost of its maps, ``MatchResult.extras[PAIR_COST_KEY]`` (G-MSM: the alignment cost of its
    one-level query).
``alignment``
    The Deep Shells alignment cost of the maps (:func:`~shapecorr.matching.gmsm_query.alignment_cost_of_maps`, at
    the last training level), for matchers with Deep Shells' ``config`` and ``spectral_shape`` (Deep Shells,
    G-MSM with its Deep Shells test pipeline).
``cycle``
    Matcher-agnostic: the two-sided round-trip error of the pair's two maps, ``mean_v |X_v - X[q(p(v))]|`` over
    X and the same over Y, in normalized units (``p``: X -> Y; ``q``: the query's Y -> X map, or the reverse
    query's map when the matcher gives only one). It is blind to errors that both maps make consistently (a
    left-right flip composed with its inverse flip is the identity).
``auto``
    ``matcher`` when the matcher reports a cost, else ``alignment`` when it applies, else ``cycle``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr
from tqdm.auto import tqdm

from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import pair_name
from shapecorr.errors import ConfigError
from shapecorr.eval import metrics
from shapecorr.eval.protocol import PRECOMPUTED_SECONDS_KEY
from shapecorr.eval.scoring import score_map
from shapecorr.eval.sharding import shard_pairs
from shapecorr.matching.deep_shells import DeepShellsConfig
from shapecorr.matching.gmsm_query import alignment_cost_of_maps
from shapecorr.matching.result import MatchResult
from shapecorr.matching.shape_graph import (
    GRAPH_VARIANTS,
    ShapeGraph,
    build_shape_graph,
    compose_all,
    costs_from_pairs,
    knn_candidate_pairs,
)

#: Graph variants: those of :func:`build_shape_graph` plus ``knn`` (each shape queried only with its K nearest
#: shapes in a global descriptor space, the graph then ``full`` on those queries).
COLLECTION_VARIANTS = (*GRAPH_VARIANTS, "knn")
#: Pair costs (module docstring).
PAIR_COSTS = ("auto", "matcher", "alignment", "cycle")
#: ``MatchResult.extras`` key of a matcher's own cost of its maps (float, >= 0).
PAIR_COST_KEY = "pair_cost"
#: Eigenvalues (after the constant one) forming the global "shape DNA" descriptor of the knn candidates.
KNN_DESCRIPTOR_EIGS = 20
#: Triplets scored for cycle consistency at most (evenly spaced among all ordered triplets when there are more).
DEFAULT_MAX_TRIPLETS = 200
#: Subfolder of an evaluation's output with one file per pair query (resumable).
QUERIES_DIR = "graph_queries"


@dataclass(frozen=True, eq=False)
class GraphQuery:
    """One ordered pair's query.

    Attributes
    ----------
    map_x_to_y : (n_x,) int64
    map_y_to_x : (n_y,) int64 or None
        When the matcher computes the reverse map too.
    cost : float
        The pair cost (NaN until :func:`fill_cycle_costs` for the ``cycle`` cost).
    seconds : float
        Wall time of the query (0 when not measured).
    cost_kind : str
        Which pair cost ``cost`` is (one of :data:`PAIR_COSTS` but ``auto``; empty when not said).
    """

    map_x_to_y: torch.Tensor
    map_y_to_x: torch.Tensor | None
    cost: float
    seconds: float = 0.0
    cost_kind: str = ""


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
        ``(i, j)`` -> ``(map_i_to_j, map_j_to_i or None)`` of the queries (numpy int64).
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

    def direct_map(self, i: int, j: int) -> np.ndarray | None:
        """The pairwise map i -> j: query ``(i, j)``'s forward map, else query ``(j, i)``'s reverse map, else None."""
        if (i, j) in self.direct:
            return self.direct[(i, j)][0]
        if (j, i) in self.direct:
            return self.direct[(j, i)][1]
        return None

    def map(self, i: int, j: int) -> np.ndarray | None:
        """The composed map i -> j, or the direct one for a pair without a path (None: neither)."""
        return self.composed[(i, j)] if (i, j) in self.composed else self.direct_map(i, j)


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


def collection_candidates(shapes, variant: str, knn_k: int = 5) -> np.ndarray:
    """:func:`candidate_pairs` of a ShapeDataset (the knn descriptors from its shapes' eigenvalues)."""
    descriptors = None
    if check_variant(variant) == "knn":
        descriptors = np.stack([shape_dna(shapes[i].evals) for i in range(len(shapes.names))])
    return candidate_pairs(len(shapes.names), variant, knn_k, descriptors)


def _synchronize(device) -> None:
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def query_pairs(query: Callable, shapes, pairs, progress: bool = False, device=None, desc: str = "graph queries"
                ) -> list[GraphQuery]:
    """``query(x, y) -> GraphQuery`` of every pair ``(i, j)`` of ``shapes`` (a ShapeDataset), in order, timed.

    Returns
    -------
    list of GraphQuery
        Maps on the CPU; ``seconds`` is the wall time of each call.
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
        x, y = sample(i), sample(j)
        t0 = time.perf_counter()
        q = query(x, y)
        _synchronize(device)
        seconds = time.perf_counter() - t0
        inverse = None if q.map_y_to_x is None else q.map_y_to_x.detach().cpu()
        out.append(GraphQuery(q.map_x_to_y.detach().cpu(), inverse, float(q.cost), seconds, q.cost_kind))
    return out


def _spectral(matcher) -> bool:
    return isinstance(getattr(matcher, "config", None), DeepShellsConfig) and hasattr(matcher, "spectral_shape")


def resolve_cost(matcher, cost: str) -> str:
    """The pair cost a matcher gets for the option ``cost`` (``auto``: ``matcher`` is decided per query)."""
    if cost not in PAIR_COSTS:
        raise ConfigError(f"multishape.cost must be one of {PAIR_COSTS}, got {cost!r}")
    if cost == "alignment" and not _spectral(matcher):
        raise ConfigError(f"multishape.cost=alignment needs a Deep Shells-type matcher (config and spectral_shape); "
                          f"{type(matcher).__name__} has none: use cost=cycle")
    return cost


class MatcherQuery:
    """A matcher as a pair query: ``query(x, y) -> GraphQuery`` with the pair cost of option ``cost``.

    Parameters
    ----------
    matcher : Matcher
    cost : one of :data:`PAIR_COSTS`
        ``cycle`` (and ``auto`` without an own or alignment cost) leaves the cost NaN; :func:`fill_cycle_costs`
        computes it once all queries are in.
    """

    def __init__(self, matcher, cost: str = "auto"):
        self.matcher, self.cost = matcher, resolve_cost(matcher, cost)

    def __call__(self, x, y) -> GraphQuery:
        """Match the pair (x, y) and cost its maps (both maps on the matcher's device)."""
        with torch.no_grad():
            result = self.matcher.match(x, y)
        own = result.extras.get(PAIR_COST_KEY)
        if self.cost == "matcher" and own is None:
            raise ConfigError(f"multishape.cost=matcher but {type(self.matcher).__name__} reports no cost of its "
                              "maps: use cost=auto or cost=cycle")
        cost, kind = math.nan, "cycle"
        if own is not None and self.cost in ("auto", "matcher"):
            cost, kind = float(own), "matcher"
        elif self.cost == "alignment" or (self.cost == "auto" and _spectral(self.matcher)):
            m = self.matcher
            inverse = result.p2p_inv
            if inverse is None:
                raise ConfigError(f"the alignment cost needs both maps of a pair; {type(m).__name__} gave only x -> y")
            cost, kind = float(alignment_cost_of_maps(m.spectral_shape(x), m.spectral_shape(y), result.p2p,
                                                      inverse, m.config)), "alignment"
        return GraphQuery(result.p2p, result.p2p_inv, cost, cost_kind=kind)


def round_trip_cost(verts_x, verts_y, map_x_to_y, map_y_to_x) -> float:
    """The ``cycle`` pair cost: mean Euclidean round-trip error over X and over Y, averaged (normalized units).

    Parameters
    ----------
    verts_x : (n_x, 3) float
    verts_y : (n_y, 3) float
    map_x_to_y : (n_x,) int
    map_y_to_x : (n_y,) int

    Returns
    -------
    float
        ``(mean_v |X_v - X[q[p[v]]]| + mean_w |Y_w - Y[p[q[w]]]|) / 2``.
    """
    vx, vy = metrics.as_numpy(verts_x, np.float64), metrics.as_numpy(verts_y, np.float64)
    p, q = metrics.as_numpy(map_x_to_y).astype(np.int64), metrics.as_numpy(map_y_to_x).astype(np.int64)
    back_x = np.linalg.norm(vx - vx[q[p]], axis=1).mean()
    back_y = np.linalg.norm(vy - vy[p[q]], axis=1).mean()
    return float(0.5 * (back_x + back_y))


def fill_cycle_costs(pairs, queries: Sequence[GraphQuery], verts: Callable) -> list[GraphQuery]:
    """Queries with their NaN costs replaced by :func:`round_trip_cost` (others unchanged).

    Parameters
    ----------
    pairs : (P, 2) int
    queries : list of GraphQuery
        In the order of ``pairs``.
    verts : callable
        ``verts(i) -> (n_i, 3)`` vertex positions of shape ``i`` (normalized).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    index = {(int(i), int(j)): k for k, (i, j) in enumerate(pairs.tolist())}
    out = list(queries)
    for k, ((i, j), q) in enumerate(zip(pairs.tolist(), queries)):
        if not math.isnan(q.cost):
            continue
        back = q.map_y_to_x
        if back is None and (j, i) in index:
            back = queries[index[(j, i)]].map_x_to_y
        if back is None:
            raise ConfigError(f"the cycle cost of the pair ({i}, {j}) needs a map back from {j} to {i}: the matcher "
                              "gives one direction and the reverse pair was not queried")
        out[k] = GraphQuery(q.map_x_to_y, q.map_y_to_x, round_trip_cost(verts(i), verts(j), q.map_x_to_y, back),
                            q.seconds, "cycle")
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
        Their results, in the order of ``pairs`` (finite costs).
    variant : one of :data:`COLLECTION_VARIANTS`

    Returns
    -------
    CollectionGraph
    """
    check_variant(variant)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(queries) != pairs.shape[0]:
        raise ConfigError(f"{pairs.shape[0]} pairs but {len(queries)} query results")
    values = np.array([q.cost for q in queries], dtype=np.float64)
    if not np.isfinite(values).all():
        raise ConfigError("a pair cost is NaN or infinite (compute the cycle costs first: fill_cycle_costs)")
    costs = costs_from_pairs(len(names), pairs, values)
    graph = build_shape_graph(costs, "full" if variant == "knn" else variant)
    direct = {(int(i), int(j)): (q.map_x_to_y, q.map_y_to_x) for (i, j), q in zip(pairs.tolist(), queries)}
    composed = compose_all(graph, direct)
    as_np = lambda m: None if m is None else metrics.as_numpy(m).astype(np.int64)  # noqa: E731
    return CollectionGraph(
        names=list(names), pairs=pairs, graph=graph,
        composed={k: as_np(v) for k, v in composed.maps.items()},
        direct={k: (as_np(a), as_np(b)) for k, (a, b) in direct.items()},
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


def cycle_consistency(maps: Callable, triplets, geodesics: Callable, sqrt_areas: Callable) -> dict:
    """Mean / median cycle-consistency error over triplets, at the geodesic sources of the first shape.

    The error of a source vertex ``v`` of X is the geodesic distance from ``v`` to its image under
    X -> Y -> Z -> X, divided by sqrt(area(X)); a triplet's error is the mean over X's sources.

    Parameters
    ----------
    maps : callable
        ``maps(s, t) -> (n_s,)`` int map, or None (the triplet is then skipped).
    triplets : (T, 3) int
    geodesics : callable
        ``geodesics(i)`` -> :class:`~shapecorr.geometry.geodesics.SourceDistances` of shape ``i`` (e.g. the
        rows from its ground-truth points).
    sqrt_areas : callable
        ``sqrt_areas(i) -> float``.

    Returns
    -------
    dict with ``mean``, ``median`` (None without a scored triplet) and ``n_triplets``.
    """
    per_triplet = []
    for x, y, z in np.asarray(triplets, dtype=np.int64).reshape(-1, 3).tolist():
        p_xy, p_yz, p_zx = maps(x, y), maps(y, z), maps(z, x)
        if p_xy is None or p_yz is None or p_zx is None:
            continue
        dist = geodesics(x)
        cycle = metrics.compose_maps(p_xy, p_yz, p_zx)
        err = dist.lookup(dist.sources, cycle[dist.sources]) / sqrt_areas(x)
        per_triplet.append(float(err.mean()))
    if not per_triplet:
        return {"mean": None, "median": None, "n_triplets": 0}
    return {"mean": float(np.mean(per_triplet)), "median": float(np.median(per_triplet)),
            "n_triplets": len(per_triplet)}


# -- resumable queries ------------------------------------------------------------------------------------------

def query_file(out_dir, name_x: str, name_y: str) -> Path:
    """``out_dir/graph_queries/<x>__<y>.npz``."""
    return Path(out_dir) / QUERIES_DIR / f"{pair_name(name_x, name_y)}.npz"


def save_query(path, q: GraphQuery) -> None:
    """Write a query (maps, cost, seconds) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    inverse = np.zeros(0, np.int64) if q.map_y_to_x is None else q.map_y_to_x.numpy()
    with atomic_open(path) as fh:
        np.savez(fh, map_x_to_y=q.map_x_to_y.numpy(), map_y_to_x=inverse, has_inverse=np.array(q.map_y_to_x
                 is not None), cost=np.array(q.cost), seconds=np.array(q.seconds), cost_kind=np.array(q.cost_kind))


def load_query(path) -> GraphQuery:
    """The :class:`GraphQuery` stored at ``path`` by :func:`save_query`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            inverse = torch.from_numpy(z["map_y_to_x"].astype(np.int64)) if bool(z["has_inverse"]) else None
            return GraphQuery(torch.from_numpy(z["map_x_to_y"].astype(np.int64)), inverse, float(z["cost"]),
                              float(z["seconds"]), str(z["cost_kind"]))
    except (OSError, KeyError, ValueError) as err:
        raise ConfigError(f"unreadable graph query file ({err}); delete it to query the pair again", path) from None


def query_pairs_cached(query: Callable, shapes, pairs, out_dir, progress: bool = False, device=None
                       ) -> list[GraphQuery]:
    """:func:`query_pairs` with one ``.npz`` per pair under ``out_dir/graph_queries``.

    Pairs already written are read back, not queried again (an interrupted evaluation resumes).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    todo = [k for k, (i, j) in enumerate(pairs.tolist())
            if not query_file(out_dir, shapes.names[i], shapes.names[j]).is_file()]
    for k, q in zip(todo, query_pairs(query, shapes, pairs[todo], progress=progress, device=device)):
        i, j = pairs[k]
        save_query(query_file(out_dir, shapes.names[i], shapes.names[j]), q)
    return [load_query(query_file(out_dir, shapes.names[i], shapes.names[j])) for i, j in pairs.tolist()]


# -- persistence of a graph --------------------------------------------------------------------------------------

def save_graph(path, graph: CollectionGraph, epoch: int) -> Path:
    """Write names, costs, variant, build epoch and the composed maps to ``path`` (.npz, atomic replace)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = sorted(graph.composed)
    maps = [graph.composed[k].astype(np.int32) for k in keys]
    offsets = np.cumsum([0] + [m.shape[0] for m in maps]).astype(np.int64)
    with atomic_open(path) as fh:
        np.savez(fh, names=np.array(graph.names, dtype=str), costs=graph.graph.costs, pairs=graph.pairs,
                 variant=np.array(graph.variant), epoch=np.array(int(epoch)),
                 map_keys=np.array(keys, dtype=np.int64).reshape(-1, 2), map_offsets=offsets,
                 map_values=np.concatenate(maps) if maps else np.zeros(0, np.int32))
    return path


@dataclass
class StoredGraph:
    """A persisted graph: ``names``, ``costs (n, n)``, ``variant``, ``epoch`` and ``composed[(s, t)] (n_s,)``."""

    names: list
    costs: np.ndarray
    variant: str
    epoch: int
    composed: dict


def load_graph(path) -> StoredGraph:
    """Read a graph written by :func:`save_graph`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            keys, offsets, values = z["map_keys"], z["map_offsets"], z["map_values"]
            composed = {(int(s), int(t)): values[offsets[k]:offsets[k + 1]].astype(np.int64)
                        for k, (s, t) in enumerate(keys.tolist())}
            return StoredGraph(names=[str(n) for n in z["names"]], costs=z["costs"], variant=str(z["variant"]),
                               epoch=int(z["epoch"]), composed=composed)
    except (OSError, KeyError, ValueError) as err:
        raise ConfigError(f"unreadable shape graph file ({err}); delete it to rebuild the graph", path=path) from None


# -- the wrapper ---------------------------------------------------------------------------------------------------

class MultiShapeMatcher:
    """Any matcher's maps composed through the shape graph of the evaluated collection (module docstring).

    Call :meth:`prepare` once per evaluation (all ranks), then ``match(x, y)`` returns the composed map of the
    pair (the direct map for a pair without a path) with ``extras[PRECOMPUTED_SECONDS_KEY]``: the queries' and
    the graph's time spread evenly over the evaluated pairs, so that ``seconds_per_pair`` is the cost of a map.

    Parameters
    ----------
    matcher : Matcher
        Queried on the pairs.
    variant : one of :data:`COLLECTION_VARIANTS`
    knn_k : int
        Neighbours per shape of the ``knn`` variant.
    cost : one of :data:`PAIR_COSTS`
    max_triplets : int
        Ordered triplets scored for cycle consistency at most.
    """

    def __init__(self, matcher, variant: str = "full", knn_k: int = 5, cost: str = "auto",
                 max_triplets: int = DEFAULT_MAX_TRIPLETS):
        if not hasattr(matcher, "match"):
            raise ConfigError(f"{type(matcher).__name__} has no match(x, y) method; it cannot be queried")
        if int(knn_k) < 1 or int(max_triplets) < 0:
            raise ConfigError(f"multishape: need knn_k >= 1 and max_triplets >= 0, got {knn_k}, {max_triplets}")
        self.matcher, self.variant, self.knn_k = matcher, check_variant(str(variant)), int(knn_k)
        self.query = MatcherQuery(matcher, str(cost))
        self.max_triplets = int(max_triplets)
        self.collection: CollectionGraph | None = None
        self.query_seconds = 0.0
        self.graph_seconds = 0.0
        self.seconds_per_map = 0.0
        self.cost_kinds: list[str] = []
        self._index: dict[str, int] = {}

    @property
    def required_operators(self) -> dict:
        """The wrapped matcher's operators."""
        return dict(getattr(self.matcher, "required_operators", {}) or {})

    @property
    def label(self) -> str:
        """Name for plots: the matcher's class and the graph variant."""
        return f"{type(self.matcher).__name__} ({self.variant} graph)"

    def prepare(self, shapes, out_dir, n_evaluated: int, rank: int = 0, world: int = 1, device=None,
                progress: bool = False, barrier: Callable[[], None] | None = None) -> CollectionGraph:
        """Query this rank's share of the candidate pairs, wait for all ranks, then build the graph.

        Parameters
        ----------
        shapes : ShapeDataset
            The collection (every shape of the evaluated split).
        out_dir : path
            Queries go to ``out_dir/graph_queries/<x>__<y>.npz`` (existing ones are read back: resumable).
        n_evaluated : int
            Number of pairs the evaluation scores (spreads the query time over them).
        rank, world : int
            This process and the number of processes (each queries every ``world``-th pair).
        device : torch.device, optional
            Where the samples go for the queries.
        progress : bool
        barrier : callable, optional
            Waits for all ranks (DDP); every rank then reads all queries and builds the same graph.
        """
        candidates = collection_candidates(shapes, self.variant, self.knn_k)
        mine = shard_pairs(list(range(candidates.shape[0])), rank, world)
        query_pairs_cached(self.query, shapes, candidates[mine], out_dir, progress=progress, device=device)
        if barrier is not None:
            barrier()
        t1 = time.perf_counter()
        queries = query_pairs_cached(self.query, shapes, candidates, out_dir)  # all read back from the files
        if self.query.cost == "cycle":  # computed here, whatever cost a query file holds
            queries = [replace(q, cost=math.nan) for q in queries]
        queries = fill_cycle_costs(candidates, queries, lambda i: shapes.load_shape(i).verts)
        self.collection = build_collection_graph(list(shapes.names), candidates, queries, self.variant)
        self._index = {n: i for i, n in enumerate(shapes.names)}
        self.query_seconds = float(sum(q.seconds for q in queries))
        self.cost_kinds = sorted({q.cost_kind for q in queries})
        self.graph_seconds = time.perf_counter() - t1
        self.seconds_per_map = (self.query_seconds + self.graph_seconds) / max(int(n_evaluated), 1)
        return self.collection

    def match(self, x, y) -> MatchResult:
        """The composed map x -> y (``p2p (n_x,)`` int64; the identity for x == y)."""
        if self.collection is None:
            raise ConfigError("MultiShapeMatcher.match before prepare(): the shape graph is not built")
        i, j = self._index.get(x.name), self._index.get(y.name)
        if i is None or j is None:
            raise ConfigError(f"{x.name if i is None else y.name} is not a shape of the graph's collection")
        extras = {PRECOMPUTED_SECONDS_KEY: self.seconds_per_map}
        if i == j:
            return MatchResult(p2p=torch.arange(x.shape.n_verts), extras=extras)
        p2p = self.collection.map(i, j)
        if p2p is None:
            raise ConfigError(f"no map for the pair {pair_name(x.name, y.name)}: it was not queried and has no path")
        return MatchResult(p2p=torch.from_numpy(p2p), extras=extras)

    def report(self, shapes, pairs, geodesics: str = "heat") -> dict:
        """``metrics.json["multi_shape"]``: graph, costs, timing, cycle consistency, and the pairwise maps' scores.

        ``cycle_consistency`` of the composed maps and ``cycle_consistency_pairwise`` of the direct (queried)
        maps over at most ``max_triplets`` ordered triplets; ``pairwise``: mean geodesic error and PCK AUC of
        the direct maps on the evaluated ``pairs`` (what the matcher alone scores on them), and the Spearman rank
        correlation between the pair cost and the direct map's mean error over the queried evaluated pairs (how well
        the cost tells good from bad maps; None when either is constant).
        """
        if self.collection is None:
            raise ConfigError("MultiShapeMatcher.report before prepare()")
        col = self.collection
        rows: dict[int, object] = {}

        def dist(i):
            if i not in rows:
                rows[i] = shapes.ground_truth_geodesics(i, method=geodesics)
            return rows[i]

        areas: dict[int, float] = {}

        def sqrt_area(i: int) -> float:
            if i not in areas:
                shape = shapes.load_shape(i)
                areas[i] = float(np.sqrt(metrics.surface_area(shape.verts.numpy(), shape.faces.numpy())))
            return areas[i]

        triplets = sample_triplets(len(col.names), self.max_triplets)
        errors, costs = [], []
        for i, j in pairs:
            p2p = col.direct_map(i, j)
            if p2p is not None:
                errors.append(score_map(torch.from_numpy(p2p), shapes[i], shapes[j], dist(j))["errors"])
                costs.append(col.graph.costs[i, j])
        pairwise = {"n_pairs": len(errors), "mean_geodesic_error": None, "pck_auc": None, "cost_error_spearman": None}
        if errors:
            t, frac = metrics.pck_curve(np.concatenate(errors))
            means = np.array([e.mean() for e in errors])
            pairwise.update(mean_geodesic_error=float(means.mean()), pck_auc=metrics.pck_auc(t, frac))
            queried = np.isfinite(costs)
            if queried.sum() > 2 and np.ptp(np.asarray(costs)[queried]) > 0 and np.ptp(means[queried]) > 0:
                rho = spearmanr(np.asarray(costs)[queried], means[queried]).statistic
                pairwise["cost_error_spearman"] = float(rho)
        finite = col.graph.costs[np.isfinite(col.graph.costs)]
        return {
            "variant": self.variant, "cost": "+".join(self.cost_kinds), "n_shapes": len(col.names),
            "n_queries": int(col.pairs.shape[0]), "n_edges": int(col.graph.edges.shape[0]),
            "unreachable_pairs": len(col.unreachable),
            "mean_pair_cost": float(finite.mean()) if finite.size else None,
            "query_seconds_total": self.query_seconds,
            "seconds_per_query": self.query_seconds / max(int(col.pairs.shape[0]), 1),
            "graph_seconds": self.graph_seconds,
            "cycle_consistency": cycle_consistency(col.map, triplets, dist, sqrt_area),
            "cycle_consistency_pairwise": cycle_consistency(col.direct_map, triplets, dist, sqrt_area),
            "pairwise": pairwise,
        }


def summary_line(report: dict) -> str:
    """One printed line of a :meth:`MultiShapeMatcher.report`: cycle consistency, graph vs pairwise."""
    cc, pw = report["cycle_consistency"], report["cycle_consistency_pairwise"]
    if cc["mean"] is None:
        return f"{report['variant']} shape graph: no triplet for cycle consistency"
    line = (f"cycle consistency ({report['variant']} graph, {report['cost']} cost): {cc['mean']:.4f} over "
            f"{cc['n_triplets']} triplets")
    if pw["mean"] is not None:
        line += f" (pairwise maps: {pw['mean']:.4f} over {pw['n_triplets']})"
    if report["pairwise"]["mean_geodesic_error"] is not None:
        line += f"; pairwise maps' mean error {report['pairwise']['mean_geodesic_error']:.4f}"
    return line


__all__ = [
    "COLLECTION_VARIANTS",
    "PAIR_COSTS",
    "PAIR_COST_KEY",
    "QUERIES_DIR",
    "CollectionGraph",
    "GraphQuery",
    "MatcherQuery",
    "MultiShapeMatcher",
    "StoredGraph",
    "build_collection_graph",
    "candidate_pairs",
    "check_variant",
    "collection_candidates",
    "cycle_consistency",
    "fill_cycle_costs",
    "load_graph",
    "load_query",
    "query_pairs",
    "query_pairs_cached",
    "resolve_cost",
    "round_trip_cost",
    "sample_triplets",
    "save_graph",
    "save_query",
    "shape_dna",
    "summary_line",
]
