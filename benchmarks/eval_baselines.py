"""Benchmark: the evaluation pipeline and its baselines on the FAUST_r test pairs.

    python benchmarks/eval_baselines.py --faust-r /path/to/FAUST_r [--workers 0] [--geodesics heat]

Runs ``evaluate.py`` (in process, same configs) on all 380 ordered pairs of tr_reg_080..099 with

1. ``model=identity_gt``: the self-check (maps through the ground truth); its error is the floor of the data;
2. ``model=descriptor_nn`` with WKS, for each row normalization;

and records, per run, the mean/median geodesic error (fraction of sqrt(area); x100 in the paper tables),
PCK AUC, the symmetric-map error, the matcher's seconds per pair and the evaluation overhead per pair (loading,
scoring, writing; geodesics already cached). A first run fills the shape cache (eigenbases, WKS, 20 heat
geodesic matrices of ~5k x 5k) and takes several minutes; its duration is recorded separately. Results go to
``benchmarks/results/eval_baselines.json`` with the command, date, machine and versions.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time
from pathlib import Path

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "eval_baselines.json"
#: Row normalizations of DescriptorNN measured (see configs/model/descriptor_nn.yaml for the default).
NORMALIZATIONS = ("standardize", "l2", "none")


def _run(root: str, cache: str | None, out: Path, workers: int, geodesics: str, *overrides: str) -> dict:
    from hydra import compose, initialize_config_dir

    from shapecorr.cli.evaluate import evaluate

    base = ["data=faust_r", f"data.root={root}", f"output_dir={out}", "pairs=test", f"workers={workers}",
            f"geodesics={geodesics}", "n_examples=4"]
    if cache:
        base.append(f"paths.cache_dir={cache}")
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("evaluate", overrides=[*base, *overrides])
    return evaluate(cfg)


def _summary(metrics: dict, out: Path, wall: float) -> dict:
    import csv

    with open(out / "per_pair.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    eval_s = [float(r["eval_seconds"]) for r in rows]
    keep = ("n_pairs", "mean_geodesic_error", "median_geodesic_error", "pck_auc", "mean_geodesic_error_sym",
            "pck_auc_sym", "mean_conformal_distortion", "seconds_per_pair", "median_seconds_per_pair",
            "eval_seconds_per_pair", "peak_memory_mb")
    res = {k: metrics[k] for k in keep if k in metrics}
    res["mean_geodesic_error_x100"] = 100 * metrics["mean_geodesic_error"]
    res["median_eval_seconds_per_pair"] = statistics.median(eval_s)
    res["wall_seconds"] = wall
    res["units"] = {"errors": "fraction of sqrt(target area)", "seconds": "s", "peak_memory_mb": "MiB"}
    return res


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"), help="FAUST_r folder (default $SHAPECORR_FAUST_R)"
    )
    parser.add_argument("--cache-dir", default=None, help="shape cache (default: paths.cache_dir of the configs)")
    parser.add_argument("--work-dir", default=str(REPO / "outputs" / "bench_eval_baselines"), help="evaluation outputs")
    parser.add_argument("--workers", type=int, default=0, help="CPU worker processes of evaluate.py")
    parser.add_argument("--geodesics", default="heat", choices=("heat", "exact"))
    parser.add_argument("--output", default=str(RESULT), help="results JSON")
    args = parser.parse_args(argv)
    if not args.faust_r:
        parser.error("give --faust-r DIR or set SHAPECORR_FAUST_R")
    work = Path(args.work_dir)
    runs = {}
    # 1. identity_gt: a one-pair run fills the cache of all 20 shapes (timed on its own), then all pairs.
    t0 = time.perf_counter()
    _run(args.faust_r, args.cache_dir, work / "cache_fill", args.workers, args.geodesics,
         "model=identity_gt", "resume=false", "max_pairs=1", "n_examples=0")
    cache_fill = time.perf_counter() - t0
    t0 = time.perf_counter()
    metrics = _run(args.faust_r, args.cache_dir, work / "identity_gt", args.workers, args.geodesics,
                   "model=identity_gt", "resume=false")
    runs["identity_gt"] = _summary(metrics, work / "identity_gt", time.perf_counter() - t0)
    runs["identity_gt"]["cache_fill_wall_seconds"] = cache_fill
    # 2. descriptor_nn with WKS, each normalization (the descriptors are cached by the first of these runs).
    for norm in NORMALIZATIONS:
        name = f"descriptor_nn_wks_{norm}"
        t0 = time.perf_counter()
        metrics = _run(args.faust_r, args.cache_dir, work / name, args.workers, args.geodesics,
                       "model=descriptor_nn", "model.descriptor=wks", f"model.normalize={norm}", "resume=false")
        runs[name] = _summary(metrics, work / name, time.perf_counter() - t0)
    result = {
        "benchmark": "eval_baselines",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": bench_common.machine_info(),
        "dataset": "FAUST_r test: tr_reg_080..099, all 380 ordered pairs; geodesics: " + args.geodesics,
        "notes": [
            "identity_gt maps through the .vts ground truth; FAUST_r .vts files are not injective (5000 template "
            "points on ~3500 vertices per shape), so its error is the floor any vertex-to-vertex map has on this data.",
            "seconds_per_pair: the matcher alone; eval_seconds_per_pair: loading, scoring and writing per pair, "
            "geodesics cached.",
        ],
        "runs": runs,
    }
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(runs, indent=2))
    return result


if __name__ == "__main__":
    main()
