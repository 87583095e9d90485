"""Benchmark: any matcher through the shape graph (``multishape=graph``) on FAUST_r test shapes, vs pairwise.

    python benchmarks/multishape_faust_r.py --faust-r DIR --model deep_shells_published [--every 2] \
        [--variants full mst star tsp] [--costs auto cycle] [--device cuda] [--run-dir DIR] [--out JSON]

1. The test split is the FAUST_r test shapes (``tr_reg_080`` .. ``tr_reg_099``), every ``--every``-th, or
   ``--shapes``: ``data=folder data.root=FAUST_R ~data.splits.test +data.splits.test={names:[...]}`` (the FAUST_r
   folder as any folder; its shape cache is shared with ``data=faust_r`` runs).
2. ``evaluate.py model=MODEL multishape=graph data=folder ...`` (first variant and cost) queries
   all n (n - 1) ordered pairs once (``RUN_DIR/<variant>_<cost>/graph_queries``, resumable) and scores the composed
   maps of all ordered pairs; ``metrics.json["multi_shape"]["pairwise"]`` scores the direct maps of the same
   queries, i.e. ``evaluate.py model=MODEL`` without the graph, on the same pairs.
3. Every other variant / cost is one more ``evaluate.py`` run whose ``graph_queries`` folder links to the first
   run's (no new queries: only the graph, the composed maps and their scores).

Each run is a subprocess with ``OMP_NUM_THREADS=--threads``; extra ``evaluate.py`` options follow ``--``. Writes
``--out`` (default ``benchmarks/results/multishape_<model>_faust_r<n>.json``) with, per run: mean geodesic error,
PCK AUC, cycle consistency of the composed and of the pairwise maps, pairwise mean error / AUC, the rank
correlation of pair cost and pairwise error, seconds per query and per pair, graph seconds. Re-running the same
command resumes (queries and pairs already written are not computed again; the reports are).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from bench_common import machine_info, write_report

REPO = Path(__file__).resolve().parents[1]
TEST_SHAPES = [f"tr_reg_{i:03d}" for i in range(80, 100)]


def run_evaluate(args, names: list[str], out: Path, variant: str, cost: str, first: bool) -> dict:
    split = "{names:[" + ",".join(names) + "]}"
    command = [sys.executable, "evaluate.py", f"model={args.model}", "multishape=graph",
               f"multishape.variant={variant}", f"multishape.cost={cost}", "data=folder",
               f"data.root={args.faust_r}", "~data.splits.test", f"+data.splits.test={split}", f"output_dir={out}",
               f"device={args.device}", "progress=true",
               f"n_examples={4 if first else 0}", f"write_maps={'true' if first else 'false'}", *args.extra]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "PYTHONPATH": str(REPO)}
    print(" ".join(command[1:]), flush=True)
    t0 = time.perf_counter()
    subprocess.run(command, cwd=REPO, env=env, check=True)
    wall = time.perf_counter() - t0
    metrics = json.loads((out / "metrics.json").read_text())
    ms = metrics["multi_shape"]
    return {
        "variant": variant, "cost_option": cost, "cost": ms["cost"], "output_dir": str(out), "wall_seconds": wall,
        "n_shapes": ms["n_shapes"], "n_pairs": metrics["n_pairs"], "n_queries": ms["n_queries"],
        "mean_geodesic_error": metrics["mean_geodesic_error"], "pck_auc": metrics["pck_auc"],
        "mean_geodesic_error_sym": metrics.get("mean_geodesic_error_sym"),
        "cycle_consistency": ms["cycle_consistency"]["mean"],
        "cycle_consistency_pairwise": ms["cycle_consistency_pairwise"]["mean"],
        "n_triplets": ms["cycle_consistency"]["n_triplets"],
        "pairwise_mean_geodesic_error": ms["pairwise"]["mean_geodesic_error"],
        "pairwise_pck_auc": ms["pairwise"]["pck_auc"],
        "cost_error_spearman": ms["pairwise"].get("cost_error_spearman"),
        "seconds_per_query": ms["seconds_per_query"], "seconds_per_pair": metrics["seconds_per_pair"],
        "graph_seconds": ms["graph_seconds"], "unreachable_pairs": ms["unreachable_pairs"],
    }


def main(argv: list[str]) -> dict:
    own, extra = (argv[: argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faust-r", type=Path, default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default $SHAPECORR_FAUST_R)")
    parser.add_argument("--model", default="deep_shells_published")
    parser.add_argument("--every", type=int, default=1, help="every k-th test shape (1: all 20)")
    parser.add_argument("--shapes", nargs="+", help="explicit shape names instead of --every")
    parser.add_argument("--variants", nargs="+", default=["full", "mst", "star", "tsp"])
    parser.add_argument("--costs", nargs="+", default=["auto", "cycle"])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--run-dir", type=Path, default=None, help="default /tmp/multishape_<model>_<n>")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(own)
    args.extra = extra
    if args.faust_r is None:
        raise SystemExit("error: give --faust-r DIR or set SHAPECORR_FAUST_R")
    names = args.shapes or TEST_SHAPES[:: max(args.every, 1)]
    run_dir = args.run_dir or Path(f"/tmp/multishape_{args.model}_{len(names)}")
    runs, first_dir = [], None
    for cost in args.costs:
        for variant in args.variants:
            out = run_dir / f"{variant}_{cost}"
            if first_dir is None:
                first_dir = out
            elif not (out / "graph_queries").exists():
                out.mkdir(parents=True, exist_ok=True)
                (out / "graph_queries").symlink_to((first_dir / "graph_queries").resolve())
            runs.append(run_evaluate(args, names, out, variant, cost, first=out == first_dir))
            r = runs[-1]
            print(f"{variant:5s} {r['cost']:9s}: error {r['mean_geodesic_error']:.4f} (pairwise "
                  f"{r['pairwise_mean_geodesic_error']:.4f}), AUC {r['pck_auc']:.3f} (pairwise "
                  f"{r['pairwise_pck_auc']:.3f}), cycle {r['cycle_consistency']:.4f} (pairwise "
                  f"{r['cycle_consistency_pairwise']:.4f}), {r['seconds_per_query']:.2f} s/query", flush=True)
    out_json = args.out or REPO / "benchmarks" / "results" / f"multishape_{args.model}_faust_r{len(names)}.json"
    report = {"command": " ".join(["benchmarks/multishape_faust_r.py", *argv]), "machine": machine_info(),
              "model": args.model, "shapes": names, "threads": args.threads, "runs": runs,
              "units": "errors and cycle consistency: geodesic distance / sqrt(area) (x100 for paper numbers)"}
    write_report(out_json, report)
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
