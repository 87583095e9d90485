"""Benchmark: how many FAUST_r test pairs end in the left/right mirrored solution (divfree, Smooth Shells).

    python benchmarks/mirror_flips.py --faust-r DIR [--max-pairs 80 | --pairs 088-089,098-097,...]
        [--runs divfree divfree_noprealign smooth_shells ...] [--parallel 1] [--threads 1] [--device auto]
        [--run-dir DIR] [--out FILE] [--no-launch]

Each run is ``evaluate.py`` on the same FAUST_r test pairs (shapes 080-099): ``--max-pairs`` evenly spaced of the
380 ordered pairs (evaluate.py's ``max_pairs`` order, 0: all 380), or the pairs named by ``--pairs`` (``xxx-yyy``,
the numbers of ``tr_reg_xxx``). ``--parallel P`` splits the pairs into P interleaved parts run as P evaluate.py
processes at once (each with ``--threads`` threads; on a GPU machine they share the device), into
``RUN_DIR/<run>/part_<k>``; a run stopped early resumes where it stopped. ``--no-launch`` runs nothing and only
summarizes the pairs already evaluated under ``RUN_DIR/<run>/part_*`` (e.g. two runs on different pair sets whose
``part_*`` folders were put side by side); it fails when one of the requested pairs is missing.

Two medians are recorded: over the pairs (of the per-pair mean errors, ``median_geodesic_error``) and over all
points of all pairs pooled (``median_point_error``, what evaluate.py's metrics.json calls
``median_geodesic_error``). A pair counts as **mirrored** when its mean geodesic error against the mirrored
ground truth (``corres/*.sym.vts``) is below its error against the ground truth. Recorded per run: mean /
median errors, the per-pair list (error, error vs mirror, seconds), the mirrored count and pairs, seconds per pair
(the matcher alone), and for interpolating matchers the mean volume change at t = 1. Written to ``--out``
(default ``benchmarks/results/mirror_flips.json``). No ground truth is used by any matcher; it only scores.

========================  =============================================================================
run                       evaluate.py arguments
========================  =============================================================================
divfree                   ``model=divfree`` (config default: Smooth Shells' rigid stage as the pre-alignment, WKS in
                          the product space, the spectral final extraction)
divfree_flow              ``model=divfree model.extraction=flow`` (final maps from the deformed x alone, without the
                          spectral extraction)
divfree_shot              ``model=divfree model.descriptor=shot model.descriptor_weight=[0.2,0.1,0.05]`` (the
                          earlier default product space, SHOT)
divfree_pca               ``model=divfree model.prealign=pca`` (the paper's 4 axis-sign candidates)
divfree_noprealign        ``model=divfree model.prealign=none`` (x as given)
divfree_pca_turns         ``model=divfree model.prealign=pca_turns`` (8 PCA orientations, ICP-refined)
divfree_smooth_shells_rigid ``model=divfree model.prealign=smooth_shells model.prealign_keep_input=false
                          model.prealign_score_descriptors=0`` (the rigid stage's own choice, geometric scores)
smooth_shells             ``model=smooth_shells`` (config default)
smooth_shells_original    ``model=smooth_shells model.rigid_joint=false model.score_descriptors=0``
                          (the original code's greedy rigid candidates and geometric scores)
smooth_shells_scoredesc   ``model=smooth_shells model.score_descriptors=0.3`` (descriptors in the candidate scores)
========================  =============================================================================
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "mirror_flips.json"
TEST_SHAPES = [f"tr_reg_{i:03d}" for i in range(80, 100)]
RUNS = {
    "divfree": ["model=divfree"],
    "divfree_flow": ["model=divfree", "model.extraction=flow"],
    "divfree_shot": ["model=divfree", "model.descriptor=shot", "model.descriptor_weight=[0.2,0.1,0.05]"],
    "divfree_pca": ["model=divfree", "model.prealign=pca"],
    "divfree_noprealign": ["model=divfree", "model.prealign=none"],
    "divfree_pca_turns": ["model=divfree", "model.prealign=pca_turns"],
    "divfree_smooth_shells_rigid": ["model=divfree", "model.prealign=smooth_shells", "model.prealign_keep_input=false",
                                    "model.prealign_score_descriptors=0"],
    "smooth_shells": ["model=smooth_shells"],
    "smooth_shells_original": ["model=smooth_shells", "model.rigid_joint=false", "model.score_descriptors=0"],
    "smooth_shells_scoredesc": ["model=smooth_shells", "model.score_descriptors=0.3"],
}


def test_pairs(max_pairs: int) -> list[tuple[str, str]]:
    """The ordered test pairs in evaluate.py's order, evenly thinned to ``max_pairs`` (0: all 380)."""
    pairs = [(a, b) for a in TEST_SHAPES for b in TEST_SHAPES if a != b]
    if 0 < max_pairs < len(pairs):
        keep = np.linspace(0, len(pairs) - 1, max_pairs).round().astype(int)
        pairs = [pairs[k] for k in keep]
    return pairs


def named_pairs(spec: str) -> list[tuple[str, str]]:
    """``"088-089,098-097"`` -> the FAUST_r pairs ``(tr_reg_088, tr_reg_089), ...``."""
    out = []
    for item in filter(None, (s.strip() for s in spec.split(","))):
        a, _, b = item.partition("-")
        out.append((f"tr_reg_{int(a):03d}", f"tr_reg_{int(b):03d}"))
    return out


def read_pairs(folder: Path) -> list[dict]:
    """Per-pair records ``pairs/*.json`` written by evaluate.py under ``folder`` (all parts).

    Each row also carries ``point_errors``: the pair's per-point errors (``pairs/*.npz``), for the pooled median.
    """
    rows = []
    for js in sorted(folder.glob("part_*/pairs/*.json")):
        rec = json.loads(js.read_text())
        with np.load(js.with_suffix(".npz")) as arrays:
            points = arrays["errors"].astype(np.float64)
        rows.append({"pair": f"{rec['source'][-3:]}-{rec['target'][-3:]}", "error": rec["mean_error"],
                     "error_mirror": rec.get("mean_error_sym"), "seconds": rec["seconds"],
                     "volume_change": rec.get("volume_change"), "point_errors": points})
    return rows


def summarize(rows: list[dict]) -> dict:
    """Mean, medians (over pairs and over all points pooled), mirrored pairs, seconds of the per-pair ``rows``."""
    pooled = np.concatenate([r.pop("point_errors") for r in rows])
    err = np.array([r["error"] for r in rows])
    mirrored = [r["pair"] for r in rows if r["error_mirror"] is not None and r["error_mirror"] < r["error"]]
    secs = np.array([r["seconds"] for r in rows])
    vol = [r["volume_change"] for r in rows if r["volume_change"] is not None]
    out = {"n_pairs": len(rows), "mean_geodesic_error": float(err.mean()), "median_geodesic_error":
           float(np.median(err)), "mean_over_median": float(err.mean() / np.median(err)),
           "median_point_error": float(np.median(pooled)),
           "mean_over_median_point": float(err.mean() / np.median(pooled)),
           "mirrored_count": len(mirrored), "mirrored_pairs": mirrored,
           "seconds_per_pair": float(secs.mean()), "median_seconds_per_pair": float(np.median(secs)),
           "per_pair": rows}
    if vol:
        out["mean_volume_change"] = float(np.mean(vol))
    return out


def launch(run: str, pairs: list[tuple[str, str]], folder: Path, args) -> None:
    """Run evaluate.py on ``pairs`` in ``args.parallel`` interleaved parts at once."""
    procs = []
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}
    for k in range(args.parallel):
        part = pairs[k::args.parallel]
        if not part:
            continue
        out = folder / f"part_{k}"
        out.mkdir(parents=True, exist_ok=True)
        pair_file = out / "pairs.txt"
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in part))
        cmd = [sys.executable, "evaluate.py", *RUNS[run], *args.override, "data=faust_r",
               f"data.root={args.faust_r}", f"pair_file={pair_file}", "pairs=test", f"output_dir={out}",
               f"hydra.run.dir={out}", "progress=false", "n_examples=0", "write_interp=false",
               "geodesics=heat", f"device={args.device}"]
        log = open(out / "evaluate.log", "a")  # noqa: SIM115 (closed after the process ends)
        procs.append((subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT), log, out))
    for proc, log, out in procs:
        rc = proc.wait()
        log.close()
        if rc != 0:
            raise SystemExit(f"run {run}: evaluate.py failed (exit {rc}); see {out / 'evaluate.log'}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--max-pairs", type=int, default=80, help="evenly spaced test pairs (0: all 380)")
    parser.add_argument("--pairs", help="comma-separated pairs xxx-yyy instead of --max-pairs")
    parser.add_argument("--runs", nargs="+", default=["divfree", "smooth_shells"], choices=list(RUNS))
    parser.add_argument("--override", action="append", default=[], help="extra evaluate.py override (all runs)")
    parser.add_argument("--parallel", type=int, default=1, help="evaluate.py processes at once per run")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of each process")
    parser.add_argument("--device", default="auto", help="evaluate.py device (auto: cuda if available)")
    parser.add_argument("--run-dir", default=str(REPO / "outputs" / "bench" / "mirror_flips"))
    parser.add_argument("--out", default=str(RESULT))
    parser.add_argument("--no-launch", action="store_true",
                        help="run nothing; summarize the pairs already under RUN_DIR/<run>/part_*")
    args = parser.parse_args(argv)
    if not args.faust_r:
        parser.error("set --faust-r or SHAPECORR_FAUST_R to the FAUST_r folder")
    if args.parallel < 1:
        parser.error("--parallel must be >= 1")
    pairs = named_pairs(args.pairs) if args.pairs else test_pairs(args.max_pairs)
    run_dir = Path(args.run_dir).absolute()
    results = {}
    for run in args.runs:
        folder = run_dir / run
        start = time.perf_counter()
        if not args.no_launch:
            launch(run, pairs, folder, args)
        wanted = {f"{a[-3:]}-{b[-3:]}" for a, b in pairs}
        rows = [r for r in read_pairs(folder) if r["pair"] in wanted]
        missing = sorted(wanted - {r["pair"] for r in rows})
        if missing:
            raise SystemExit(f"run {run}: {len(missing)} of {len(wanted)} pairs have no record under {folder} "
                             f"(e.g. {missing[0]})")
        results[run] = {**summarize(rows), "wall_seconds": None if args.no_launch else time.perf_counter() - start,
                        "overrides": RUNS[run] + args.override}
        s = results[run]
        print(f"{run}: {s['n_pairs']} pairs, mean {100 * s['mean_geodesic_error']:.2f} median over pairs "
              f"{100 * s['median_geodesic_error']:.2f} over points {100 * s['median_point_error']:.2f} (x100), "
              f"mirrored {s['mirrored_count']} "
              f"{s['mirrored_pairs']}, {s['seconds_per_pair']:.1f} s/pair", flush=True)
    summary = {"pairs": args.pairs or f"{len(pairs)} evenly spaced of the 380 FAUST_r test pairs",
               "parallel": args.parallel, "threads": args.threads, "device": args.device, "runs": results,
               "units": "errors: geodesic distance / sqrt(area of the target), heat geodesics (x100 = percent); "
                        "median_geodesic_error: median over pairs of the per-pair means; median_point_error: "
                        "over all points of all pairs pooled (evaluate.py's median_geodesic_error); "
                        "mirrored: error vs the mirrored ground truth below the error vs the ground truth"}
    report = bench_common.summary_report("mirror_flips.py", sys.argv[1:] if argv is None else list(argv), summary)
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
