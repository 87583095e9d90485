"""Cost of G-MSM's shape graph: graph building for n shapes, full (n (n - 1) queries) vs knn (n K candidate pairs).

    python benchmarks/gmsm_graph_cost.py [--sizes 20 80] [--k 5] [--n-verts 500] [--real-pairs 6]

Two parts (docs/gmsm.md §4.1):

1. *Graph building without queries*: synthetic costs (distances between random points in the plane plus
   noise, so that the knn candidates are meaningful) and random maps of ``--n-verts`` vertices per shape;
   seconds of ``build_collection_graph`` (costs -> graph -> every pair's composed map) for each n, full and knn.
2. *Real queries*: seconds of one G-MSM one-level query (``GMSM.graph_query``, published network and sample
   size) on pairs of the embedded tiny synthetic shapes (~300 vertices), median over ``--real-pairs`` pairs.

The extrapolation to 1000 shapes is ``queries x seconds per query`` (n (n - 1) for full, at most 2 n K for knn,
symmetric candidates) plus the graph building time scaled from the largest measured n (``n^3`` for full:
Floyd-Warshall and n^2 composed maps of n vertices; ``n^2`` for knn: Dijkstra on a sparse graph and n^2 maps).
Writes ``benchmarks/results/gmsm_graph_cost.json``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import machine_info, median, write_report

from shapecorr.eval.multi_shape import (
    GraphQuery,
    build_collection_graph,
    candidate_pairs,
)

RESULTS = Path(__file__).resolve().parent / "results" / "gmsm_graph_cost.json"


def synthetic_collection(n: int, n_verts: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 2))
    costs = np.linalg.norm(points[:, None] - points[None], axis=-1) + 0.05 * rng.random((n, n))
    return points, costs, rng


def time_building(n: int, variant: str, k: int, n_verts: int) -> dict:
    points, costs, rng = synthetic_collection(n, n_verts)
    pairs = candidate_pairs(n, variant, k, descriptors=points)
    queries = [GraphQuery(torch.from_numpy(rng.integers(0, n_verts, n_verts)),
                          torch.from_numpy(rng.integers(0, n_verts, n_verts)), float(costs[i, j]))
               for i, j in pairs.tolist()]
    t0 = time.perf_counter()
    graph = build_collection_graph([f"s{i}" for i in range(n)], pairs, queries, variant)
    seconds = time.perf_counter() - t0
    return {"n": n, "variant": variant, "queries": int(pairs.shape[0]), "build_seconds": seconds,
            "composed_pairs": len(graph.composed), "unreachable_pairs": len(graph.unreachable)}


def time_real_queries(n_pairs: int) -> dict:
    from shapecorr.data.datamodule import ShapePairDataModule
    from shapecorr.models.gmsm import GMSM

    torch.manual_seed(0)
    model = GMSM().eval()  # the published network and 2000 samples
    with tempfile.TemporaryDirectory() as tmp:
        dm = ShapePairDataModule(root=Path(tmp) / "data", synthetic={"preset": "tiny"}, cache_dir=Path(tmp) / "cache")
        dm.with_operators(model.required_operators)
        shapes = dm.shapes("train")
        samples = [shapes[i] for i in range(len(shapes))]
        pairs = [(i, j) for i in range(len(samples)) for j in range(len(samples)) if i != j][:n_pairs]
        model.graph_query(samples[0], samples[1])  # warm-up
        seconds = []
        for i, j in pairs:
            t0 = time.perf_counter()
            model.graph_query(samples[i], samples[j])
            seconds.append(time.perf_counter() - t0)
        n_verts = [int(s.shape.n_verts) for s in samples]
    return {"pairs": len(pairs), "seconds_per_query": median(seconds), "n_verts": n_verts}


def main(argv: list[str]) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 80])
    parser.add_argument("--k", type=int, default=5)
    parser.add_argument("--n-verts", type=int, default=500)
    parser.add_argument("--real-pairs", type=int, default=6)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    building = [time_building(n, v, args.k, args.n_verts) for n in args.sizes for v in ("full", "knn")]
    for row in building:
        print(f"n={row['n']:4d} {row['variant']:4s}: {row['queries']:6d} queries, graph + composed maps "
              f"{row['build_seconds']:.3f} s")
    real = time_real_queries(args.real_pairs)
    print(f"one-level query on {real['n_verts'][0]}-vertex shapes: {real['seconds_per_query']:.3f} s")
    n_big, largest = 1000, max(args.sizes)
    extrapolated = {}
    for variant, power in (("full", 3), ("knn", 2)):
        row = next(r for r in building if r["n"] == largest and r["variant"] == variant)
        queries = n_big * (n_big - 1) if variant == "full" else 2 * n_big * args.k
        extrapolated[variant] = {
            "queries": queries,
            "query_seconds": queries * real["seconds_per_query"],
            "build_seconds": row["build_seconds"] * (n_big / largest) ** power,
        }
        est = extrapolated[variant]
        print(f"n=1000 {variant}: {queries} queries x {real['seconds_per_query']:.3f} s = "
              f"{est['query_seconds'] / 3600:.1f} h, graph ~{est['build_seconds']:.0f} s")
    report = {"command": " ".join(["benchmarks/gmsm_graph_cost.py", *argv]), "machine": machine_info(),
              "k": args.k, "n_verts_synthetic": args.n_verts, "building": building, "real_queries": real,
              "extrapolated_n1000": extrapolated}
    write_report(args.out, report)
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
