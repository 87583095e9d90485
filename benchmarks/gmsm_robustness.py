"""Benchmark: does the shape graph help where pairwise matching fails? G-MSM on synthetic topological noise.

    python benchmarks/gmsm_robustness.py [--out-dir DIR] [--self-contact 0.5] [--holes 1] [--threads 1]

Generates a variant of the embedded dataset (``data=synthetic_small`` with 6 human subjects x 3 poses, 2 subjects
held out: 12 training and 6 test shapes) whose shapes are corrupted with ``self_contact_fraction`` (body parts
posed into contact and fused: topological merges as in SHREC'16 TOPKIDS) and ``n_holes``; trains
``train.py model=gmsm`` with its quick settings on it (graph built after the first epoch, graph loss in the
second); then evaluates the 30 ordered test pairs twice with the same checkpoint: ``multishape=graph`` (shape graph
over the 6 test shapes, composed maps) and without it (the direct maps), and reports mean / median
geodesic error, PCK AUC and the cycle-consistency error over triplets of both. Writes
``benchmarks/results/gmsm_robustness.json``. A few minutes on one core; a smoke-sized run, not a paper number.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "gmsm_robustness.json"
#: ``seconds_per_pair`` of the graph evaluation is the composition only (its queries are ``eval_seconds_per_pair``
#: and the pairwise evaluation's time); cycle consistency of both is in ``multi_shape`` of the graph evaluation.
KEYS = ("n_pairs", "mean_geodesic_error", "median_geodesic_error", "pck_auc", "seconds_per_pair", "peak_memory_mb")


def data_overrides(root: Path, self_contact: float, holes: int) -> list[str]:
    return ["data=synthetic_small", f"data.root={root}", f"+data.synthetic.self_contact_fraction={self_contact}",
            f"+data.synthetic.n_holes={holes}", "data.synthetic.n_human_subjects=6",
            "+data.synthetic.test_fraction=0.34"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-dir", default=str(REPO / "outputs" / "bench" / "gmsm_robustness"))
    parser.add_argument("--self-contact", type=float, default=0.5, help="data.synthetic.self_contact_fraction")
    parser.add_argument("--holes", type=int, default=1, help="data.synthetic.n_holes")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of the runs")
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)

    out = Path(args.out_dir).absolute()
    data = data_overrides(out / "data", args.self_contact, args.holes)
    ckpt = out / "train" / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        bench_common.run_command([sys.executable, "train.py", "model=gmsm", *data, "test=false",
                                  f"hydra.run.dir={out / 'train'}"], args.threads, REPO)
    results = {}
    for matching in ("graph", "pairwise"):
        folder = out / f"eval_{matching}"
        if not (folder / "metrics.json").is_file():
            graph = ["multishape=graph"] if matching == "graph" else []
            bench_common.run_command([sys.executable, "evaluate.py", "model=gmsm", f"ckpt_path={ckpt}", *graph,
                                      *data, "n_examples=0", f"output_dir={folder}", f"hydra.run.dir={folder}"],
                                     args.threads, REPO)
        metrics = json.loads((folder / "metrics.json").read_text())
        results[matching] = {k: metrics.get(k) for k in KEYS}
        if "multi_shape" in metrics:  # the graph evaluation scores the direct maps' cycle consistency too
            results["multi_shape"] = metrics["multi_shape"]
    shapes = json.loads((out / "data" / "params.json").read_text())["shapes"]
    fused = {split: sum(1 for s in shapes.values() if s["split"] == split and s.get("fused"))
             for split in ("train", "test")}
    summary = {"data_overrides": data, "fused_shapes": fused,
               "train": "train.py model=gmsm (configs/quick/gmsm/quick.yaml)", "results": results,
               "units": "errors: geodesic distance / sqrt(area of the target) (x100 = percent)"}
    print(json.dumps(results, indent=1))
    bench_common.write_report(args.out, bench_common.summary_report("gmsm_robustness.py", sys.argv[1:] if argv is None
                                                                    else list(argv), summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
