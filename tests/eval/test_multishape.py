"""``evaluate.py multishape=graph``: the shape graph as a wrapper of any matcher (shapecorr.eval.multi_shape).

On a folder of four bent, vertex-permuted icospheres (162 vertices, ground truth on every vertex): the wrapper over
descriptor_nn matches the plain evaluation's pairwise scores and reports cycle consistency and query time; a
ground-truth matcher with one wrong, expensive pair shows that the graph routes around it; a Deep Shells-type
matcher gets the alignment cost; every variant runs; an interrupted evaluation resumes without querying again.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf, open_dict

from shapecorr.cli.evaluate import evaluate
from shapecorr.errors import ConfigError
from shapecorr.eval import multi_shape
from shapecorr.geometry.spectral_shape import make_spectral_shape
from shapecorr.matching.deep_shells import DeepShellsConfig
from shapecorr.matching.gmsm_query import alignment_cost_of_maps
from shapecorr.matching.result import MatchResult

pytestmark = pytest.mark.usefixtures("single_thread")
NAMES = ["a", "b", "c", "d"]
WRONG = ("a", "c")  # the pair the ground-truth matcher gets wrong (at a high cost of its own)


def _gt_map(x, y) -> torch.Tensor:
    """x -> y from the folder's ground truth (every vertex has a .vts entry)."""
    p2p = torch.empty(x.shape.n_verts, dtype=torch.int64)
    p2p[x.corres.long()] = y.corres.long().to(p2p.device)
    return p2p


class GroundTruthMatcher:
    """Exact maps with cost 0.1, except the pair WRONG (and its reverse): a random map at cost 10."""

    def match(self, x, y) -> MatchResult:
        """Exact or, for WRONG, shuffled maps with their own cost (extras[PAIR_COST_KEY])."""
        if {x.name, y.name} == set(WRONG):
            g = torch.Generator().manual_seed(0)
            return MatchResult(p2p=torch.randint(0, y.shape.n_verts, (x.shape.n_verts,), generator=g),
                               extras={multi_shape.PAIR_COST_KEY: 10.0})
        return MatchResult(p2p=_gt_map(x, y), p2p_inv=_gt_map(y, x), extras={multi_shape.PAIR_COST_KEY: 0.1})


class SpectralGroundTruth:
    """A Deep Shells-type matcher (``config`` + ``spectral_shape``) returning noisy ground-truth maps."""

    config = DeepShellsConfig(k_array=(6, 10))

    @staticmethod
    def spectral_shape(sample):
        """The sample's SpectralShape."""
        return make_spectral_shape(sample.verts, sample.faces, sample.evecs, sample.mass, name=sample.name)

    def match(self, x, y) -> MatchResult:
        """Ground truth with every 7th vertex sent to vertex 0."""
        fwd, bwd = _gt_map(x, y), _gt_map(y, x)
        fwd[::7], bwd[::7] = 0, 0
        return MatchResult(p2p=fwd, p2p_inv=bwd)


@pytest.fixture(scope="module")
def folder(tmp_path_factory, bent_sphere_folder):
    root = tmp_path_factory.mktemp("multishape")
    return bent_sphere_folder(root / "data", NAMES), root / "cache"


def _run(folder, evaluate_on_folder, out, *overrides, model="descriptor_nn", target=None):
    root, cache = folder
    cfg = evaluate_on_folder(root, cache, out, f"model={model}", *overrides)
    if target is not None:  # a matcher of this module
        with open_dict(cfg):
            cfg.model = OmegaConf.create({"_target_": f"{__name__}.{target}"})
    return evaluate(cfg)


def test_wrapper_over_descriptor_nn_reports_cycle_consistency_and_query_time(folder, evaluate_on_folder, tmp_path):
    graph = _run(folder, evaluate_on_folder, tmp_path / "graph", "multishape=graph", "n_examples=0")
    plain = _run(folder, evaluate_on_folder, tmp_path / "plain")
    ms = graph["multi_shape"]
    assert ms["n_shapes"] == 4 and ms["n_queries"] == 12 and ms["unreachable_pairs"] == 0
    assert ms["cost"] == "cycle"  # descriptor_nn has no cost of its own
    for key in ("cycle_consistency", "cycle_consistency_pairwise"):
        assert ms[key]["n_triplets"] == 24 and 0 <= ms[key]["mean"] < 1
    # the direct maps of the queries are the plain evaluation's maps
    assert ms["pairwise"]["n_pairs"] == plain["n_pairs"] == graph["n_pairs"] == 12
    assert ms["pairwise"]["mean_geodesic_error"] == pytest.approx(plain["mean_geodesic_error"], rel=1e-6)
    assert ms["pairwise"]["pck_auc"] == pytest.approx(plain["pck_auc"], rel=1e-6)
    # seconds_per_pair: the queries (and the graph) spread over the evaluated pairs
    assert ms["query_seconds_total"] > 0 and graph["seconds_per_pair"] > 0
    assert graph["seconds_per_pair"] >= (ms["query_seconds_total"] + ms["graph_seconds"]) / 12
    saved = json.loads((tmp_path / "graph" / "metrics.json").read_text())
    assert saved["multi_shape"]["variant"] == "full" and saved["run"]["multishape"]["variant"] == "full"
    assert (tmp_path / "graph" / "shape_graph.png").stat().st_size > 0
    assert multi_shape.load_graph(tmp_path / "graph" / "shape_graph.npz").names == NAMES
    assert len(list((tmp_path / "graph" / multi_shape.QUERIES_DIR).glob("*.npz"))) == 12


def test_graph_routes_around_a_wrong_expensive_pair(folder, evaluate_on_folder, tmp_path):
    result = _run(folder, evaluate_on_folder, tmp_path / "out", "multishape=graph", target="GroundTruthMatcher")
    ms = result["multi_shape"]
    assert ms["cost"] == "matcher"
    per_pair = {(r["source"], r["target"]): float(r["mean_error"])
                for r in _csv_rows(tmp_path / "out" / "per_pair.csv")}
    assert per_pair[WRONG] == pytest.approx(0.0, abs=1e-6) and per_pair[WRONG[::-1]] == pytest.approx(0.0, abs=1e-6)
    assert result["mean_geodesic_error"] == pytest.approx(0.0, abs=1e-6)
    assert ms["pairwise"]["mean_geodesic_error"] > 0.05  # the wrong pairs, matched directly
    assert ms["pairwise"]["cost_error_spearman"] > 0.5  # the expensive pairs are the wrong ones
    assert ms["cycle_consistency"]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert ms["cycle_consistency_pairwise"]["mean"] > 0.05


def _csv_rows(path):
    import csv

    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_deep_shells_type_matcher_gets_the_alignment_cost(folder, evaluate_on_folder, tmp_path):
    result = _run(folder, evaluate_on_folder, tmp_path / "out", "multishape=graph", target="SpectralGroundTruth")
    assert result["multi_shape"]["cost"] == "alignment"
    q = multi_shape.load_query(multi_shape.query_file(tmp_path / "out", "a", "b"))
    assert q.cost_kind == "alignment" and q.seconds > 0
    from hydra.utils import instantiate

    shapes = instantiate(evaluate_on_folder(*folder, tmp_path / "unused").data, _convert_="object").shapes("test")
    x, y = shapes[shapes.names.index("a")], shapes[shapes.names.index("b")]
    m = SpectralGroundTruth()
    r = m.match(x, y)
    expected = alignment_cost_of_maps(m.spectral_shape(x), m.spectral_shape(y), r.p2p, r.p2p_inv, m.config)
    assert q.cost == pytest.approx(float(expected), rel=1e-5)
    cycle = _run(folder, evaluate_on_folder, tmp_path / "cycle", "multishape=graph", "multishape.cost=cycle",
                 target="SpectralGroundTruth")
    assert cycle["multi_shape"]["cost"] == "cycle"
    with pytest.raises(SystemExit):  # a matcher without the Deep Shells operators: one line, exit 2
        _run(folder, evaluate_on_folder, tmp_path / "bad", "multishape=graph", "multishape.cost=alignment")


@pytest.mark.parametrize("variant", ["full", "mst", "star", "tsp", "knn"])
def test_every_variant(folder, evaluate_on_folder, tmp_path, variant):
    result = _run(folder, evaluate_on_folder, tmp_path / variant, "multishape=graph",
                  f"multishape.variant={variant}", "multishape.knn_k=1", target="GroundTruthMatcher")
    ms = result["multi_shape"]
    n_edges = {"full": 6, "mst": 3, "star": 3, "tsp": 3}
    assert ms["variant"] == variant and result["n_pairs"] == 12 and ms["unreachable_pairs"] == 0
    if variant in n_edges:
        assert ms["n_queries"] == 12 and ms["n_edges"] == n_edges[variant]
    else:  # knn with K = 1: each shape and its nearest, both directions
        assert 4 <= ms["n_queries"] < 12
    # every graph avoids the wrong pair's edge (cost 10 against 0.1): all composed maps are exact
    assert result["mean_geodesic_error"] == pytest.approx(0.0, abs=1e-6)
    assert ms["cycle_consistency"]["n_triplets"] == 24


def test_resume_queries_only_missing_pairs(folder, evaluate_on_folder, tmp_path):
    out = tmp_path / "out"
    first = _run(folder, evaluate_on_folder, out, "multishape=graph")
    queries = sorted((out / multi_shape.QUERIES_DIR).glob("*.npz"))
    stamps = {p.name: p.stat().st_mtime_ns for p in queries}
    queries[0].unlink()  # as if interrupted before that query
    for record in (out / "pairs").glob("*"):
        record.unlink()
    again = _run(folder, evaluate_on_folder, out, "multishape=graph")
    after = {p.name: p.stat().st_mtime_ns for p in (out / multi_shape.QUERIES_DIR).glob("*.npz")}
    assert set(after) == set(stamps)
    assert [n for n in stamps if after[n] != stamps[n]] == [queries[0].name]
    assert again["mean_geodesic_error"] == pytest.approx(first["mean_geodesic_error"])
    with pytest.raises(SystemExit):  # another variant in the same folder is another run
        _run(folder, evaluate_on_folder, out, "multishape=graph", "multishape.variant=mst")


def test_cycle_costs_need_a_map_back():
    q = multi_shape.GraphQuery(torch.tensor([0, 1]), None, math.nan)
    with pytest.raises(ConfigError, match="map back"):
        multi_shape.fill_cycle_costs(np.array([[0, 1]]), [q], lambda i: torch.zeros(2, 3))
    verts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    swap = multi_shape.GraphQuery(torch.tensor([1, 0]), torch.tensor([0, 0]), math.nan)
    (filled,) = multi_shape.fill_cycle_costs(np.array([[0, 1]]), [swap], lambda i: verts)
    # X: 0 -> 1 -> 0, 1 -> 0 -> 0 (error 1); Y: 0 -> 0 -> 1 (1), 1 -> 0 -> 1 (0): (0.5 + 0.5) / 2
    assert filled.cost == pytest.approx(0.5) and filled.cost_kind == "cycle"
