"""Benchmark: geodesic errors from ground-truth rows vs from the symmetrized all-pairs matrix (FAUST_r).

    python benchmarks/geodesic_rows_parity.py --faust-r /path/to/FAUST_r [--shapes 6] [--cache DIR]

The evaluation reads ``e_r = D[gy[r], p(gx[r])]``, the row of the heat method from the ground-truth point
(R x n, what scales to large scans). The alternative is the cached all-pairs heat-method matrix symmetrized,
``D_sym = (D + D^T) / 2`` (n x n), read as ``D_sym[p(gx[r]), gy[r]]``. The heat method is not exactly
symmetric, so the two differ by its asymmetry. This script measures by how much: ``descriptor_nn`` (WKS, the
baseline of ``benchmarks/results/eval_baselines.json``) on every ordered pair of the first ``--shapes`` FAUST_r
test shapes, scored both ways, plus the memory and time of both geodesic quantities. Writes
``benchmarks/results/geodesic_rows_parity.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "geodesic_rows_parity.json"
FIRST_TEST = 80  # FAUST_r standard split: tr_reg_080..099 are the test shapes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"))
    parser.add_argument("--shapes", type=int, default=6)
    parser.add_argument("--cache", default=None, help="shape cache (default: a temporary folder)")
    args = parser.parse_args()
    if not args.faust_r:
        sys.exit("give --faust-r DIR or set SHAPECORR_FAUST_R")
    sys.path.insert(0, str(REPO))
    from shapecorr.data.datasets import ShapeDataset
    from shapecorr.data.operators import OperatorConfig
    from shapecorr.eval.scoring import score_map
    from shapecorr.matching.baselines import DescriptorNN

    cache = args.cache or tempfile.mkdtemp(prefix="shapecorr_rows_")
    shapes = ShapeDataset(args.faust_r, index_range=[FIRST_TEST, FIRST_TEST + args.shapes],
                          operators=OperatorConfig(request={"eigenbasis": {"k": 200}, "wks": {}}), cache_dir=cache)
    matcher = DescriptorNN(descriptor="wks")
    full, rows, t_full, t_rows = {}, {}, [], []
    for j in range(len(shapes)):
        t0 = time.perf_counter()
        full[j] = shapes.geodesics(j)
        t_full.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        rows[j] = shapes.ground_truth_geodesics(j)
        t_rows.append(time.perf_counter() - t0)
    per_pair = []
    for i in range(len(shapes)):
        for j in range(len(shapes)):
            if i == j:
                continue
            x, y = shapes[i], shapes[j]
            p2p = matcher.match(x, y).p2p
            a = score_map(p2p, x, y, full[j])
            b = score_map(p2p, x, y, rows[j])
            per_pair.append({
                "pair": f"{x.name}__{y.name}",
                "mean_full": float(a["errors"].mean()), "mean_rows": float(b["errors"].mean()),
                "sym_full": float(a["errors_sym"].mean()), "sym_rows": float(b["errors_sym"].mean()),
                "max_abs_point_diff": float(np.abs(a["errors"] - b["errors"]).max()),
            })
    mean_full = float(np.mean([p["mean_full"] for p in per_pair]))
    mean_rows = float(np.mean([p["mean_rows"] for p in per_pair]))
    rel_pairs = [abs(p["mean_rows"] / p["mean_full"] - 1) for p in per_pair]
    out = {
        "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": bench_common.machine_info(),
        "n_pairs": len(per_pair),
        "mean_error_full_matrix": mean_full,
        "mean_error_rows": mean_rows,
        "relative_change_of_mean": mean_rows / mean_full - 1,
        "max_relative_change_per_pair": max(rel_pairs),
        "max_abs_point_error_diff": max(p["max_abs_point_diff"] for p in per_pair),
        "sym_error_full_matrix": float(np.mean([p["sym_full"] for p in per_pair])),
        "sym_error_rows": float(np.mean([p["sym_rows"] for p in per_pair])),
        "full_matrix_mb_per_shape": float(np.mean([full[j].nbytes for j in full]) / 2**20),
        "rows_mb_per_shape": float(np.mean([rows[j].rows.nbytes for j in rows]) / 2**20),
        "rows_per_shape": float(np.mean([rows[j].sources.size for j in rows])),
        "seconds_full_matrix_per_shape": float(np.median(t_full)),
        "seconds_rows_per_shape": float(np.median(t_rows)),
        "per_pair": per_pair,
    }
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps({k: v for k, v in out.items() if k not in ("per_pair", "machine")}, indent=1))


if __name__ == "__main__":
    main()
