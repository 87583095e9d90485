"""Shape graph: weights, variants, shortest paths, map composition, unreachable pairs, knn candidates."""

import itertools

import networkx as nx
import numpy as np
import pytest
import torch

from shapecorr.errors import ConfigError, CorrespondenceError
from shapecorr.matching.shape_graph import (
    UnreachableShapeError,
    build_shape_graph,
    compose_all,
    compose_along_path,
    costs_from_pairs,
    hop_map,
    knn_candidate_pairs,
    star_hub,
    symmetric_weights,
)


def _random_costs(n, seed=0):
    return np.random.default_rng(seed).random((n, n)) + 0.1


def _connected(n, edges):
    g = nx.Graph()
    g.add_nodes_from(range(n))
    g.add_edges_from(map(tuple, edges.tolist()))
    return g, nx.is_connected(g)


def test_symmetric_weights_take_the_cheaper_direction_and_skip_missing():
    c = np.array([[0.0, 2.0, np.nan], [1.0, 0.0, 3.0], [np.inf, 0.0, 0.0]])
    w = symmetric_weights(c)
    assert np.array_equal(w, w.T)
    assert w[0, 1] == 1.0 and w[1, 2] == 0.0  # a zero cost is a (cheap) edge
    assert np.isinf(w[0, 2]) and np.isinf(np.diag(w)).all()
    with pytest.raises(ConfigError, match=">= 0"):
        symmetric_weights(-c)
    with pytest.raises(ConfigError, match="square"):
        symmetric_weights(np.zeros((2, 3)))


def test_full_graph_shortest_path_routes_around_an_expensive_pair():
    # 0 - 1 - 2 - 3 cheap chain, direct 0 - 3 expensive: the path must go along the chain.
    c = np.full((4, 4), 10.0)
    for a, b in [(0, 1), (1, 2), (2, 3)]:
        c[a, b] = 1.0
        c[b, a] = 3.0
    g = build_shape_graph(c, "full")
    assert g.edges.shape == (6, 2)
    assert g.path(0, 3) == [0, 1, 2, 3] and g.path(3, 0) == [3, 2, 1, 0] and g.path(2, 2) == [2]
    assert g.distances[0, 3] == pytest.approx(3.0) and g.unreachable_pairs().shape == (0, 2)
    c[0, 3] = 2.5  # now the direct edge is shorter than the chain
    assert build_shape_graph(c, "full").path(0, 3) == [0, 3]
    c[1, 2] = 0.0  # a zero-cost edge is an edge (not a missing one): the chain is shorter again
    g = build_shape_graph(c, "full")
    assert g.path(0, 3) == [0, 1, 2, 3] and g.distances[0, 3] == pytest.approx(2.0)


def test_mst_has_n_minus_one_edges_and_the_minimal_weight():
    n = 12
    c = _random_costs(n, 1)
    c[3, 7] = 0.0  # a zero-weight edge must be kept (scipy would drop it without the shift)
    g = build_shape_graph(c, "mst")
    assert g.edges.shape == (n - 1, 2)
    _graph, connected = _connected(n, g.edges)
    assert connected and [3, 7] in g.edges.tolist()
    w = symmetric_weights(c)
    ref = nx.Graph()
    ref.add_weighted_edges_from((i, j, w[i, j]) for i, j in itertools.combinations(range(n), 2))
    ref_weight = sum(d["weight"] for *_, d in nx.minimum_spanning_tree(ref).edges(data=True))
    assert w[g.edges[:, 0], g.edges[:, 1]].sum() == pytest.approx(ref_weight)
    assert np.isfinite(g.distances).all()


def test_star_is_a_star_around_the_lowest_mean_cost_shape():
    n = 7
    c = _random_costs(n, 2)
    c[4, :] *= 0.1  # shape 4 matches everything cheaply
    g = build_shape_graph(c, "star")
    assert g.hub == star_hub(c) == 4
    assert g.edges.shape == (n - 1, 2) and ((g.edges == 4).sum(axis=1) == 1).all()
    assert all(len(g.path(s, t)) <= 3 for s in range(n) for t in range(n))
    assert g.path(1, 2) == [1, 4, 2]


def test_tsp_is_a_deterministic_near_optimal_hamiltonian_path():
    n = 8
    x = np.random.default_rng(3).random((n, 2))
    c = np.linalg.norm(x[:, None] - x[None], axis=2)
    g = build_shape_graph(c, "tsp")
    graph, connected = _connected(n, g.edges)
    assert g.edges.shape == (n - 1, 2) and connected and max(d for _, d in graph.degree) <= 2  # a Hamiltonian path
    assert np.array_equal(build_shape_graph(c, "tsp").edges, g.edges)  # deterministic
    best = min(sum(c[a, b] for a, b in itertools.pairwise(p)) for p in itertools.permutations(range(n)))
    assert c[g.edges[:, 0], g.edges[:, 1]].sum() <= 1.15 * best
    with pytest.raises(ConfigError, match="all pairs"):
        c2 = c.copy()
        c2[0, 1] = c2[1, 0] = np.inf
        build_shape_graph(c2, "tsp")


def test_graph_building_is_deterministic_and_validates_the_variant():
    c = _random_costs(9, 4)
    for variant in ("full", "mst", "star"):
        a, b = build_shape_graph(c, variant), build_shape_graph(c.copy(), variant)
        assert np.array_equal(a.edges, b.edges) and np.array_equal(a.predecessors, b.predecessors)
    with pytest.raises(ConfigError, match="variant"):
        build_shape_graph(c, "vanilla")


def _collection(seed=0, n_shapes=4, n_template=30):
    """Shapes that are vertex permutations (with repeats) of one template: exact maps are known."""
    rng = np.random.default_rng(seed)
    labels = [rng.permutation(n_template)[: n_template - 3 * k] for k in range(n_shapes)]  # shape k: template ids
    labels = [np.concatenate([lab, lab[:2]]) for lab in labels]  # some template points twice

    def true_map(i, j):
        first = {int(t): v for v, t in reversed(list(enumerate(labels[j])))}
        # template ids missing on j map to a fixed vertex; the tests only compare ids present on all shapes
        return torch.tensor([first.get(int(t), 0) for t in labels[i]], dtype=torch.int64)

    return labels, true_map


def test_composition_along_a_path_equals_the_true_map_and_uses_the_cheaper_direction():
    labels, true_map = _collection()
    n = len(labels)
    costs = np.full((n, n), 1.0)
    maps = {(i, j): (true_map(i, j), true_map(j, i)) for i, j in itertools.permutations(range(n), 2)}
    # The direct query 0 -> 3 is wrong and expensive; its reverse query (3, 0) is wrong too.
    wrong = torch.zeros(len(labels[0]), dtype=torch.int64)
    maps[(0, 3)] = (wrong, torch.zeros(len(labels[3]), dtype=torch.int64))
    maps[(3, 0)] = (torch.zeros(len(labels[3]), dtype=torch.int64), torch.zeros(len(labels[0]), dtype=torch.int64))
    costs[0, 3] = costs[3, 0] = 10.0
    g = build_shape_graph(costs, "full")
    path = g.path(0, 3)
    assert len(path) == 3
    composed = compose_along_path(path, g.costs, maps)
    shared = set(map(int, labels[0])) & set(map(int, labels[3])) & set(map(int, labels[path[1]]))
    rows = [v for v, t in enumerate(labels[0]) if int(t) in shared]
    assert torch.equal(labels_of(labels[3], composed[rows]), labels_of(labels[0], torch.tensor(rows)))
    assert not torch.equal(labels_of(labels[3], wrong[rows]), labels_of(labels[0], torch.tensor(rows)))

    # Direction per hop: with c_01 < c_10 the direct map of (0, 1) is used, else the reverse output of (1, 0).
    a, b = torch.arange(len(labels[0])) % len(labels[1]), (torch.arange(len(labels[0])) + 1) % len(labels[1])
    m = {(0, 1): (a, None), (1, 0): (None, b)}
    c = np.array([[0.0, 1.0], [2.0, 0.0]])
    assert torch.equal(hop_map(0, 1, c, m), a)
    assert torch.equal(hop_map(0, 1, np.array([[0.0, 2.0], [1.0, 0.0]]), m), b)
    assert torch.equal(hop_map(0, 1, c, {(0, 1): a}), a)  # only one direction stored
    tie = np.array([[0.0, 1.0], [1.0, 0.0]])  # a tie: query (0, 1) serves both directions
    assert torch.equal(hop_map(0, 1, tie, m), a)
    assert torch.equal(hop_map(1, 0, tie, {(0, 1): (a, b), (1, 0): (a, a)}), b)
    with pytest.raises(CorrespondenceError, match="no map"):
        hop_map(1, 0, c, {(0, 1): a})
    assert torch.equal(compose_along_path([2], c, m, n_source=5), torch.arange(5))


def labels_of(labels, idx):
    return torch.as_tensor(np.asarray(labels)[np.asarray(idx)])


def test_compose_all_with_exact_pairwise_maps_is_exact_and_reports_unreachable_pairs():
    labels, true_map = _collection(seed=1, n_shapes=5)
    n = len(labels)
    maps = {(i, j): (true_map(i, j), true_map(j, i)) for i, j in itertools.permutations(range(n), 2)}
    # two clusters {0, 1, 2} and {3, 4}: queries only inside them
    pairs = [(i, j) for i, j in itertools.permutations(range(n), 2) if (i < 3) == (j < 3)]
    costs = costs_from_pairs(n, pairs, np.linspace(1.0, 2.0, len(pairs)))
    g = build_shape_graph(costs, "full")
    out = compose_all(g, maps)
    assert sorted(out.unreachable) == sorted((i, j) for i, j in itertools.permutations(range(n), 2)
                                             if (i < 3) != (j < 3))
    assert set(out.maps) == set(pairs)
    for (s, t), m in out.maps.items():
        shared = set(map(int, labels[s])) & set(map(int, labels[t]))
        for p in out.paths[(s, t)]:
            shared &= set(map(int, labels[p]))
        rows = [v for v, lab in enumerate(labels[s]) if int(lab) in shared]
        assert torch.equal(labels_of(labels[t], m[rows]), labels_of(labels[s], torch.tensor(rows)))
    with pytest.raises(UnreachableShapeError, match="not connected"):
        g.path(0, 4)
    assert {tuple(p) for p in g.unreachable_pairs().tolist()} == set(out.unreachable)


def test_knn_candidate_pairs_counts_neighbours_and_ties():
    x = np.array([[0.0], [1.0], [3.0], [3.5], [10.0], [10.2]])
    pairs = knn_candidate_pairs(x, 2)
    assert pairs.shape == (12, 2) and len({tuple(p) for p in pairs.tolist()}) == 12
    assert (pairs[:, 0] != pairs[:, 1]).all()
    assert pairs[pairs[:, 0] == 0, 1].tolist() == [1, 2] and pairs[pairs[:, 0] == 4, 1].tolist() == [5, 3]
    ties = knn_candidate_pairs(np.array([[0.0], [1.0], [-1.0]]), 1)
    assert ties[0].tolist() == [0, 1]  # equal distances: the smaller index
    sym = knn_candidate_pairs(x, 2, symmetric=True)
    assert {tuple(p) for p in pairs.tolist()} <= {tuple(p) for p in sym.tolist()}
    assert all((j, i) in {tuple(p) for p in sym.tolist()} for i, j in pairs.tolist())
    rng = np.random.default_rng(0)
    big = knn_candidate_pairs(rng.random((50, 4)), 5)
    assert big.shape == (250, 2) and np.bincount(big[:, 0]).tolist() == [5] * 50
    with pytest.raises(ConfigError):
        knn_candidate_pairs(x, 6)


def test_knn_graph_from_sparse_costs_connects_through_candidates():
    rng = np.random.default_rng(5)
    n, k = 30, 4
    desc = rng.random((n, 3))
    pairs = knn_candidate_pairs(desc, k)
    d = np.linalg.norm(desc[pairs[:, 0]] - desc[pairs[:, 1]], axis=1)
    costs = costs_from_pairs(n, pairs, d)
    assert np.isfinite(costs).sum() == n * k
    g = build_shape_graph(costs, "full")
    assert g.edges.shape[0] <= n * k
    assert {tuple(e) for e in g.edges.tolist()} <= {(min(i, j), max(i, j)) for i, j in pairs.tolist()}
    mst = build_shape_graph(costs, "mst")
    n_comp = nx.number_connected_components(_connected(n, g.edges)[0])
    assert mst.edges.shape[0] == n - n_comp
    with pytest.raises(ConfigError, match="costs"):
        costs_from_pairs(n, pairs, d[:-1])


def test_tree_composed_maps_are_cycle_consistent_where_direct_maps_are_not():
    from shapecorr.eval.metrics import cycle_consistency_errors

    rng = np.random.default_rng(6)
    n, m = 6, 40
    labels = [rng.permutation(m) for _ in range(n)]  # shape k, vertex v <-> template point labels[k][v]
    inverse = [np.argsort(lab) for lab in labels]
    dist = [np.abs(lab[:, None] - lab[None, :]).astype(float) for lab in labels]  # template points on a line
    costs = np.full((n, n), 1.0) + rng.random((n, n))
    maps = {}
    for i, j in itertools.combinations(range(n), 2):
        sigma = inverse[j][labels[i]]  # the true bijection i -> j
        if rng.random() < 0.3:  # a wrong (but bijective) pair of queries, with a high cost
            sigma = sigma[rng.permutation(m)]
            costs[i, j] = costs[j, i] = 10.0
        # both queries return a bijection and its inverse (Deep Shells' two outputs of one query)
        maps[(i, j)] = (torch.from_numpy(sigma), torch.from_numpy(np.argsort(sigma)))
        maps[(j, i)] = (torch.from_numpy(np.argsort(sigma)), torch.from_numpy(sigma))
    triplets = list(itertools.permutations(range(n), 3))
    direct = {k: v[0] for k, v in maps.items()}
    err_direct = max(cycle_consistency_errors(direct[(a, b)], direct[(b, c)], direct[(c, a)], dist[a], 1.0).max()
                     for a, b, c in triplets)
    assert err_direct > 0
    # On a tree, the closed walk a -> b -> c -> a crosses every edge both ways, each time by one query's two
    # mutually inverse maps: exactly cycle consistent (even through a wrong edge).
    for variant in ("mst", "star", "tsp"):
        out = compose_all(build_shape_graph(costs, variant), maps).maps
        for a, b, c in triplets:
            assert cycle_consistency_errors(out[(a, b)], out[(b, c)], out[(c, a)], dist[a], 1.0).max() == 0


def test_compose_all_equals_composing_each_path_on_long_tree_paths():
    rng = np.random.default_rng(8)
    n, sizes = 9, rng.integers(5, 12, 9)
    maps = {(i, j): (torch.from_numpy(rng.integers(0, sizes[j], sizes[i])),
                     torch.from_numpy(rng.integers(0, sizes[i], sizes[j])))
            for i, j in itertools.permutations(range(n), 2)}
    g = build_shape_graph(_random_costs(n, 9), "mst")
    out = compose_all(g, maps)
    assert max(len(p) for p in out.paths.values()) >= 4  # long paths: the shared prefixes matter
    for (s, t), m in out.maps.items():
        assert out.paths[(s, t)] == g.path(s, t)
        assert torch.equal(m, compose_along_path(g.path(s, t), g.costs, maps))
    sub = compose_all(g, maps, pairs=[(0, 5), (5, 0)])
    assert set(sub.maps) == {(0, 5), (5, 0)} and torch.equal(sub.maps[(0, 5)], out.maps[(0, 5)])
    with pytest.raises(ConfigError, match="different shapes"):
        compose_all(g, maps, pairs=[(1, 1)])
    bad = dict(maps)
    bad[(0, 1)] = (torch.full((sizes[0],), 99), bad[(0, 1)][1])  # indices beyond shape 1's vertex count
    with pytest.raises(CorrespondenceError, match="outside"):
        compose_along_path([0, 1, 2], np.zeros((n, n)), bad)
