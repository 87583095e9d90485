"""Benchmark: G-MSM on FAUST_r within a CPU budget, against its own pairwise maps and its burn-in checkpoint.

    python benchmarks/gmsm_faust_r.py --launch [--run-dir DIR] [--faust-r DIR] [--max-time HH:MM:SS]
                                      [--burn-in-epoch E]
    python benchmarks/gmsm_faust_r.py --summarize RUN_DIR [--burn-in-epoch E]
    python benchmarks/gmsm_faust_r.py --pairwise-baseline SOURCE_RUN_DIR --run-dir DIR [--max-time ...]

``--launch`` runs, one after the other (each a subprocess, ``OMP_NUM_THREADS=--threads``):

1. ``train.py experiment=gmsm_faust_r_cpu`` (epochs of 400 training pairs, knn graph with K = 5 built after
   ``--burn-in-epoch`` epochs and every 2 after; the published network, layer and loss) for ``--max-time``, with a
   checkpoint every epoch, into ``RUN_DIR``;
2. ``evaluate.py model=gmsm ckpt_path=RUN_DIR/checkpoints/last.ckpt multishape=graph data=faust_r``: the 380
   ordered test pairs as multi-shape matching (the full graph over the 20 test shapes, composed maps, cycle
   consistency), into ``RUN_DIR/eval_graph``;
3. the same without ``multishape=graph`` (the direct maps of the same network), into ``RUN_DIR/eval_pairwise``;
4. pairwise (no ``multishape=``) on the checkpoint of the epoch at whose end the graph is first built (pairwise
   DiffusionNet + Deep Shells training only, the same run up to that point), into ``RUN_DIR/eval_burn_in``.

The ``pairwise`` baseline of the issue (``model.graph.enabled=false``, the same schedule) is the run up to the
burn-in checkpoint (identical training, same seed); a separately trained pairwise run of the full budget is
``train.py experiment=gmsm_faust_r_cpu model.graph.enabled=false``. ``--pairwise-baseline SOURCE_RUN_DIR`` gives that
run for the cost of its second half only: it resumes SOURCE's burn-in checkpoint (identical pairwise training up to
there) with ``model.graph.enabled=false`` and the same ``--max-time`` (Lightning's timer state is in the checkpoint,
so it stops at the same total budget), into ``--run-dir``, then evaluates its last checkpoint pairwise
(``RUN_DIR/eval_pairwise``). Seconds per training pair come from the
TensorBoard wall times of the training loss; the peak memory of the evaluations from their metrics.json.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import bench_common
from shapecorr.models.gmsm import GRAPH_FILE
from training_runs import markdown_tables, read_metrics, read_scalars, summarize_run

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "gmsm_faust_r.json"
#: Published FAUST_r mean geodesic error of G-MSM (Eisenberger et al., CVPR 2023), fraction of sqrt(area).
PUBLISHED_FAUST_R_ERROR = 0.015
#: Our Deep Shells CPU-budget run (benchmarks/results/deep_shells_faust_r.json, 2 h of one core).
DEEP_SHELLS_CPU_BUDGET_ERROR = 0.0208
EXTRA_KEYS = ("cycle_consistency", "cycle_consistency_pairwise", "peak_memory_mb", "unreachable_pairs", "variant")


def checkpoint_of_epoch(run_dir: Path, epoch: int) -> Path:
    """The periodic checkpoint saved at the end of ``epoch`` (0-based), ``checkpoints/epochEEE-stepSSSSSS.ckpt``."""
    found = sorted((run_dir / "checkpoints").glob(f"epoch{epoch:03d}-*.ckpt"))
    if not found:
        raise SystemExit(f"{run_dir / 'checkpoints'}: no checkpoint of epoch {epoch}")
    return found[-1]


def train_command(run_dir: Path, data: list[str], max_time: str, burn_in_epoch: int) -> list[str]:
    return [sys.executable, "train.py", "experiment=gmsm_faust_r_cpu", f"trainer.max_time={max_time}",
            f"model.graph.burn_in={burn_in_epoch}", "model.graph.update_every=2", "trainer.check_val_every_n_epoch=2",
            "checkpoint.every_n_epochs=1", *data, f"hydra.run.dir={run_dir}"]


def pairwise_baseline_command(run_dir: Path, data: list[str], max_time: str, burn_in_ckpt: Path) -> list[str]:
    """The G-MSM schedule with the graph off, resumed from the burn-in checkpoint of a G-MSM run."""
    return [sys.executable, "train.py", "experiment=gmsm_faust_r_cpu", f"trainer.max_time={max_time}",
            "model.graph.enabled=false", "trainer.check_val_every_n_epoch=2", "checkpoint.every_n_epochs=1", *data,
            f"ckpt_path={burn_in_ckpt}", f"hydra.run.dir={run_dir}"]


def eval_command(run_dir: Path, data: list[str], name: str, ckpt: Path, matching: str) -> list[str]:
    out = run_dir / name
    graph = ["multishape=graph"] if matching == "graph" else []
    return [sys.executable, "evaluate.py", "model=gmsm", f"ckpt_path={ckpt}", *graph, "data=faust_r",
            *data, f"output_dir={out}", f"hydra.run.dir={out}"]


def seconds_per_training_pair(run_dir: Path, pairs_per_step: int) -> float | None:
    """Median wall seconds per training pair between consecutive logged training-loss points."""
    series = read_scalars(run_dir).get("train/loss_step", [])
    rates = []
    for (s0, _, w0), (s1, _, w1) in zip(series, series[1:]):
        if s1 > s0 and w1 > w0:
            rates.append((w1 - w0) / ((s1 - s0) * pairs_per_step))
    return bench_common.median(rates) if rates else None


def summarize(run_dir: Path) -> dict:
    finals = {}
    for name in ("eval_graph", "eval_pairwise", "eval_burn_in"):
        folder = run_dir / name
        if (folder / "metrics.json").is_file():
            finals[name] = read_metrics(folder, EXTRA_KEYS)
    summary = summarize_run(run_dir)
    summary["final"] = finals
    summary["seconds_per_training_pair"] = seconds_per_training_pair(run_dir, 4)
    summary["published_mean_geodesic_error"] = PUBLISHED_FAUST_R_ERROR
    summary["deep_shells_cpu_budget_error"] = DEEP_SHELLS_CPU_BUDGET_ERROR
    summary["units"] = "errors: geodesic distance / sqrt(area of the target) (x100 = percent)"
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--launch", action="store_true", help="train, evaluate, then summarize")
    mode.add_argument("--summarize", metavar="RUN_DIR", help="summarize an existing run (and run missing evals)")
    mode.add_argument("--pairwise-baseline", metavar="SOURCE_RUN_DIR",
                      help="resume SOURCE's burn-in checkpoint with the graph off into --run-dir, evaluate pairwise")
    parser.add_argument("--run-dir", default=str(REPO / "outputs" / "bench" / "gmsm_faust_r"))
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of the runs")
    parser.add_argument("--max-time", default="00:02:00:00", help="--launch: training budget (DD:HH:MM:SS)")
    parser.add_argument("--burn-in-epoch", type=int, default=6, help="epoch of the first graph build")
    parser.add_argument("--skip", nargs="*", default=[], help="steps to skip (train, eval_graph, ...)")
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)

    run_dir = Path(args.summarize if args.summarize else args.run_dir).absolute()
    data = [f"data.root={args.faust_r}"] if args.faust_r else []
    if args.launch and "train" not in args.skip:
        bench_common.run_command(train_command(run_dir, data, args.max_time, args.burn_in_epoch), args.threads, REPO)
    if args.pairwise_baseline and "train" not in args.skip:
        source = checkpoint_of_epoch(Path(args.pairwise_baseline).absolute(), args.burn_in_epoch)
        bench_common.run_command(pairwise_baseline_command(run_dir, data, args.max_time, source), args.threads, REPO)
    last = run_dir / "checkpoints" / "last.ckpt"
    evals = {"eval_graph": (lambda: last, "graph"), "eval_pairwise": (lambda: last, "pairwise"),
             "eval_burn_in": (lambda: checkpoint_of_epoch(run_dir, args.burn_in_epoch), "pairwise")}
    if args.pairwise_baseline or not (run_dir / "checkpoints" / GRAPH_FILE).is_file():
        evals = {"eval_pairwise": evals["eval_pairwise"]}  # a run without a graph: only its direct maps
    for name, (ckpt, matching) in evals.items():
        if name not in args.skip and not (run_dir / name / "metrics.json").is_file():
            bench_common.run_command(eval_command(run_dir, data, name, ckpt(), matching), args.threads, REPO)
    summary = summarize(run_dir)
    report = bench_common.summary_report("gmsm_faust_r.py", sys.argv[1:] if argv is None else list(argv), summary)
    print(markdown_tables(summary, ("published G-MSM (paper)", PUBLISHED_FAUST_R_ERROR)))
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
