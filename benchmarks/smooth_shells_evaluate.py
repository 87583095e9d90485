"""Benchmark: Smooth Shells through evaluate.py on the FAUST_r test split, alone and as post-processing.

    python benchmarks/smooth_shells_evaluate.py --faust-r DIR [--max-pairs 40] [--runs NAME ...]
        [--pair-file FILE] [--run-dir DIR] [--deep-shells-weights FILE] [--neuromorph-ckpt CKPT] [--threads 1]
        [--workers 0] [--out FILE]

Each run is one ``evaluate.py`` call (a subprocess with ``OMP_NUM_THREADS=--threads``) on the same evenly spaced
``--max-pairs`` of the 380 ordered pairs of shapes 080-099 (``max_pairs``; all 380 with ``--max-pairs 0``), into
``RUN_DIR/<name>``; an interrupted run resumes where it stopped (evaluate.py skips the pairs it has written).
``--pair-file`` replaces the evenly spaced subset by a list of FAUST_r pairs (``x y`` per line; evaluate.py runs
them grouped by target shape, so a run stopped early has covered the first targets only: split a long list into
interleaved parts and run them one after the other to keep every finished part evenly spread).

========================  =================================================================================
name                      evaluate.py arguments
========================  =================================================================================
smooth_shells_norigid     ``model=smooth_shells model.no_rigid=true`` (no rigid stage: wrong for FAUST_r, whose
                          test shapes 088 and 098 are turned ~100 degrees about the vertical axis)
smooth_shells_published   ``model=smooth_shells`` (the published isometric preset, rigid stage on)
smooth_shells_features    ``model=smooth_shells model.score_descriptors=0.3`` (descriptors in the scores)
deep_shells               ``model=deep_shells_published`` (the authors' released weights)
deep_shells_refined       the same with ``postprocess=smooth_shells`` (its maps refined from k = 20)
descriptor_nn             ``model=descriptor_nn`` (WKS nearest neighbours: a rough map)
descriptor_nn_refined     the same with ``postprocess=smooth_shells``
neuromorph                ``model=neuromorph ckpt_path=--neuromorph-ckpt`` (a NeuroMorph checkpoint trained with
                          train.py, e.g. ``experiment=neuromorph_faust_r``)
neuromorph_refined        the same with ``postprocess=smooth_shells``
interclass                ``model=smooth_shells_interclass data=synthetic`` on 4 humanoid <-> quadruped pairs of
                          the embedded data's test split (:data:`INTERCLASS_PAIRS`; semantic ground truth)
interclass_descriptor_nn  ``model=descriptor_nn`` on the same pairs (a reference for that ground truth)
========================  =================================================================================

Recorded per run: the metrics of its ``metrics.json`` (mean / median geodesic error, PCK AUC, seconds per
pair, peak memory; for the ``*_refined`` runs also ``mean_initial_geodesic_error``, the wrapped matcher's map
before the refinement on the same pairs). Writes ``benchmarks/results/smooth_shells_evaluate.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import bench_common
from training_runs import read_metrics

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "smooth_shells_evaluate.json"
#: Published FAUST_r errors (fraction of sqrt(area)): Smooth Shells 2.5 (Deep Shells paper's table), Deep Shells
#: 1.7, NeuroMorph 2.3 -> 1.5 with Smooth Shells post-processing (NeuroMorph paper).
PUBLISHED = {"smooth_shells": 0.025, "deep_shells": 0.017, "neuromorph": 0.023, "neuromorph_refined": 0.015}
EXTRA_KEYS = ("peak_memory_mb", "n_pairs", "median_seconds_per_pair", "mean_geodesic_error_sym",
              "mean_initial_geodesic_error")

RUNS = {
    "smooth_shells_norigid": ["model=smooth_shells", "model.no_rigid=true"],
    "smooth_shells_published": ["model=smooth_shells"],
    "smooth_shells_features": ["model=smooth_shells", "model.score_descriptors=0.3"],
    "deep_shells": ["model=deep_shells_published"],
    "deep_shells_refined": ["model=deep_shells_published", "postprocess=smooth_shells"],
    "descriptor_nn": ["model=descriptor_nn"],
    "descriptor_nn_refined": ["model=descriptor_nn", "postprocess=smooth_shells"],
    "neuromorph": ["model=neuromorph"],
    "neuromorph_refined": ["model=neuromorph", "postprocess=smooth_shells"],
    "interclass": ["model=smooth_shells_interclass"],
    "interclass_descriptor_nn": ["model=descriptor_nn"],
}
#: Humanoid <-> quadruped pairs of the embedded default dataset's test split (subjects 6, 7 and quadruped 3).
INTERCLASS_PAIRS = (("human_s06_p00", "quad_s03_p00"), ("human_s07_p02", "quad_s03_p02"),
                    ("quad_s03_p04", "human_s06_p04"), ("quad_s03_p01", "human_s07_p01"))


def eval_command(name: str, out: Path, faust_r: str, max_pairs: int, weights: str | None,
                 workers: int = 0, neuromorph_ckpt: str | None = None, pair_file: str | None = None) -> list[str]:
    args = list(RUNS[name])
    common = [f"output_dir={out}", f"hydra.run.dir={out}", "progress=false", "n_examples=4", f"workers={workers}"]
    if name.startswith("interclass"):
        pair_file = out.parent / "interclass_pairs.txt"
        pair_file.parent.mkdir(parents=True, exist_ok=True)
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in INTERCLASS_PAIRS))
        return [sys.executable, "evaluate.py", *args, "data=synthetic", f"pair_file={pair_file}", *common]
    if name.startswith("deep_shells"):
        if not weights:
            raise SystemExit(f"run {name}: pass --deep-shells-weights or set SHAPECORR_DEEP_SHELLS_WEIGHTS")
        args.append(f"model.pretrained={weights}")
    if name.startswith("neuromorph"):
        if not neuromorph_ckpt:
            raise SystemExit(f"run {name}: pass --neuromorph-ckpt or set SHAPECORR_NEUROMORPH_CKPT")
        args.extend([f"ckpt_path={neuromorph_ckpt}", "write_interp=false"])
    if pair_file:
        args.append(f"pair_file={Path(pair_file).absolute()}")
    elif max_pairs > 0:
        args.append(f"max_pairs={max_pairs}")
    return [sys.executable, "evaluate.py", *args, "data=faust_r", f"data.root={faust_r}", *common]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--max-pairs", type=int, default=40, help="evenly spaced test pairs (0: all 380)")
    parser.add_argument("--runs", nargs="+", default=list(RUNS), choices=list(RUNS), help="runs, in this order")
    parser.add_argument("--pair-file", help="FAUST_r pairs to evaluate (x y per line) instead of --max-pairs")
    parser.add_argument("--run-dir", default=str(REPO / "outputs" / "bench" / "smooth_shells_evaluate"))
    parser.add_argument("--deep-shells-weights", default=os.environ.get("SHAPECORR_DEEP_SHELLS_WEIGHTS"),
                        help="the authors' released Deep Shells weights (default: $SHAPECORR_DEEP_SHELLS_WEIGHTS)")
    parser.add_argument("--neuromorph-ckpt", default=os.environ.get("SHAPECORR_NEUROMORPH_CKPT"),
                        help="a trained NeuroMorph checkpoint for the neuromorph runs (default: "
                             "$SHAPECORR_NEUROMORPH_CKPT)")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of the runs")
    parser.add_argument("--workers", type=int, default=0,
                        help="evaluate.py worker processes (pairs in parallel, each with --threads threads); an "
                             "interrupted run may resume with another count")
    parser.add_argument("--collect-only", action="store_true", help="only collect the runs already finished")
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)
    if not args.faust_r:
        parser.error("set --faust-r or SHAPECORR_FAUST_R to the FAUST_r folder")
    run_dir = Path(args.run_dir).absolute()
    results = {}
    for name in args.runs:
        folder = run_dir / name
        if not args.collect_only and not (folder / "metrics.json").is_file():
            command = eval_command(name, folder, args.faust_r, args.max_pairs, args.deep_shells_weights,
                                   args.workers, args.neuromorph_ckpt, args.pair_file)
            bench_common.run_command(command, args.threads, REPO)
        if (folder / "metrics.json").is_file():
            results[name] = read_metrics(folder, EXTRA_KEYS)
            print(f"{name}: mean geodesic error {100 * results[name]['mean_geodesic_error']:.2f} (x100), "
                  f"{results[name].get('seconds_per_pair', float('nan')):.1f} s/pair", flush=True)
    summary = {"run_dir": str(run_dir), "max_pairs": args.max_pairs, "pair_file": args.pair_file,
               "threads": args.threads, "runs": results,
               "published": PUBLISHED,
               "units": "errors: geodesic distance / sqrt(area of the target) (x100 = percent)"}
    report = bench_common.summary_report("smooth_shells_evaluate.py", sys.argv[1:] if argv is None else list(argv),
                                         summary)
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
