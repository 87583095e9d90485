"""Benchmark: the divergence-free matcher (model=divfree) on an evenly spaced subset of the FAUST_r test pairs.

    OMP_NUM_THREADS=1 python benchmarks/divfree_faust_r.py --faust-r /path/to/FAUST_r [--max-pairs 4] \
        [--override model.iterations=[25,25,50] ...] [--variant 'fast=model.samples=[500,1000,1000]']

Runs ``evaluate.py`` in process (same configs as the command line) on the same ``--max-pairs`` evenly spaced
ordered pairs of tr_reg_080..099 with

1. ``model=descriptor_nn model.descriptor=shot`` (the product space's descriptor alone) and WKS (the
   project's descriptor baseline default);
2. ``model=divfree`` (configs/model/divfree.yaml, plus any ``--override``);

and records the mean geodesic error (fraction of sqrt(area); x100 in the paper tables), PCK AUC, seconds per
pair (the matcher alone) and, for divfree, the mean relative volume change of the deformed x at t = 1 and the
Chamfer distance to y. The FAUST_r folder comes from ``--faust-r`` or ``$SHAPECORR_FAUST_R``. Results go to
``benchmarks/results/divfree_faust_r.json`` with the command, date, machine and versions.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "divfree_faust_r.json"
KEEP = ("n_pairs", "mean_geodesic_error", "median_geodesic_error", "pck_auc", "mean_geodesic_error_sym",
        "seconds_per_pair", "median_seconds_per_pair", "mean_volume_change", "mean_chamfer",
        "mean_deformation_conformal_distortion")


def _run(root: str, out: Path, max_pairs: int, *overrides: str) -> dict:
    from hydra import compose, initialize_config_dir

    from shapecorr.cli.evaluate import evaluate

    base = ["data=faust_r", f"data.root={root}", f"output_dir={out}", "pairs=test", "workers=0",
            "geodesics=heat", "n_examples=0", f"max_pairs={max_pairs}", "resume=false", "progress=false"]
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("evaluate", overrides=[*base, *overrides])
    return evaluate(cfg)


def _summary(metrics: dict, wall: float) -> dict:
    res = {k: metrics[k] for k in KEEP if k in metrics}
    res["mean_geodesic_error_x100"] = 100 * metrics["mean_geodesic_error"]
    res["wall_seconds"] = wall
    return res


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default $SHAPECORR_FAUST_R)")
    parser.add_argument("--max-pairs", type=int, default=4, help="evenly spaced subset of the 380 test pairs")
    parser.add_argument("--work-dir", default=str(REPO / "outputs" / "bench_divfree"), help="evaluation outputs")
    parser.add_argument("--override", action="append", default=[], help="extra overrides of the divfree run")
    parser.add_argument("--variant", action="append", default=[],
                        help="another divfree run on the same pairs: NAME=OVERRIDE[;OVERRIDE...], e.g. "
                             "'fast=model.samples=[500,1000,1000]'")
    parser.add_argument("--skip-baselines", action="store_true", help="run divfree only")
    parser.add_argument("--output", default=str(RESULT), help="results JSON")
    args = parser.parse_args(argv)
    if not args.faust_r:
        parser.error("give --faust-r DIR or set SHAPECORR_FAUST_R")
    work = Path(args.work_dir)
    runs = {}
    todo = [] if args.skip_baselines else [
        ("descriptor_nn_shot", ["model=descriptor_nn", "model.descriptor=shot"]),
        ("descriptor_nn_wks", ["model=descriptor_nn", "model.descriptor=wks"]),
    ]
    todo.append(("divfree", ["model=divfree", *args.override]))
    for spec in args.variant:
        name, _, overrides = spec.partition("=")
        todo.append((f"divfree_{name}", ["model=divfree", *[o for o in overrides.split(";") if o]]))
    for name, overrides in todo:
        t0 = time.perf_counter()
        metrics = _run(args.faust_r, work / name, args.max_pairs, *overrides)
        runs[name] = _summary(metrics, time.perf_counter() - t0)
        runs[name]["overrides"] = overrides
        print(name, json.dumps(runs[name]), flush=True)
    result = {
        "benchmark": "divfree_faust_r",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": bench_common.machine_info(),
        "dataset": f"FAUST_r test: tr_reg_080..099, {args.max_pairs} evenly spaced ordered pairs of 380; "
                   "heat geodesics",
        "notes": [
            ("errors: fraction of sqrt(target area); seconds_per_pair: the matcher alone (one thread if "
            "OMP_NUM_THREADS=1); mean_volume_change: relative volume change of the deformed x at t = 1."),
            "a small subset: preliminary numbers, not the full 380-pair protocol.",
        ],
        "runs": runs,
    }
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
