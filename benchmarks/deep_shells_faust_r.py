"""Benchmark: Deep Shells on FAUST_r, learning curve and final test numbers.

    python benchmarks/deep_shells_faust_r.py --launch [--run-dir DIR] [--faust-r DIR] [--with-published]
    python benchmarks/deep_shells_faust_r.py --summarize RUN_DIR [--eval-dir DIR] [--ablation-dir DIR]
                                            [--published-dir DIR]

``--launch`` runs, one after the other (each a subprocess, ``OMP_NUM_THREADS=--threads``):

1. ``train.py experiment=deep_shells_faust_r`` with the CPU-budget overrides :data:`CPU_BUDGET_OVERRIDES`
   (two hours of one CPU core: gradients accumulated over 4 pairs instead of the published 53, so that the
   ~6-7k pairs seen give ~1600 optimizer steps instead of ~120; validation on the 20 validation pairs every
   1000 training pairs with the full refinement; a checkpoint every 100 steps), into ``RUN_DIR``;
2. ``evaluate.py model=deep_shells ckpt_path=RUN_DIR/checkpoints/last.ckpt data=faust_r`` on all 380 ordered
   test pairs, into ``RUN_DIR/eval_test``;
3. ``evaluate.py model=deep_shells_ablation data=faust_r`` (raw SHOT into the OT layer, no learning), into
   ``RUN_DIR/eval_ablation``;
4. with ``--with-published``: ``evaluate.py model=deep_shells_published`` (the authors' weights,
   ``$SHAPECORR_DEEP_SHELLS_WEIGHTS``), into ``RUN_DIR/eval_published``;

then summarizes. ``--summarize`` reads the run's TensorBoard events (``val/geodesic_error``, ``train/loss_step``,
``val/pairs_seen`` where logged) and the ``metrics.json`` of the evaluations, writes
``benchmarks/results/deep_shells_faust_r.json`` (command, date, machine, the run's overrides, the learning curve,
the final numbers) and prints Markdown tables.

Pairs seen: Lightning logs at the optimizer step; a point logged at step ``s`` follows about
``(s + 1) x accumulate_grad_batches x devices`` training pairs (exact for validation points of runs that log
``val/pairs_seen``, which DeepShells does since this benchmark exists). Errors are the Princeton protocol's
(geodesic distance / sqrt(area)), printed in percent as in the papers.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import bench_common
from training_runs import markdown_tables, read_metrics, summarize_run

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "deep_shells_faust_r.json"
#: Overrides of the CPU-budget run (besides ``experiment=deep_shells_faust_r`` and the run folder).
CPU_BUDGET_OVERRIDES = (
    "trainer.accumulate_grad_batches=4",
    "trainer.max_time=00:02:00:00",
    "trainer.val_check_interval=1000",
    "trainer.check_val_every_n_epoch=1",
    "checkpoint.every_n_train_steps=100",
    "checkpoint.every_n_epochs=null",
    "test=false",
    "model.val_refine_levels=null",
)
#: Published FAUST_r mean geodesic error of Deep Shells, fraction of sqrt(area) (Eisenberger et al. 2020, 1.7 %; the
#: figure the golden reference README quotes for the released weights on all test pairs).
PUBLISHED_FAUST_R_ERROR = 0.017


def _python() -> str:
    return sys.executable


def launch_commands(run_dir: Path, faust_r: str | None, with_published: bool) -> dict[str, list[str]]:
    """The train / evaluate command lines of ``--launch`` (see the module docstring)."""
    data = [f"data.root={faust_r}"] if faust_r else []
    cmds = {
        "train": [_python(), "train.py", "experiment=deep_shells_faust_r", *CPU_BUDGET_OVERRIDES, *data,
                  f"hydra.run.dir={run_dir}"],
        "eval": [_python(), "evaluate.py", "model=deep_shells", f"ckpt_path={run_dir / 'checkpoints' / 'last.ckpt'}",
                 "data=faust_r", *data, f"output_dir={run_dir / 'eval_test'}",
                 f"hydra.run.dir={run_dir / 'eval_test'}"],
        "ablation": [_python(), "evaluate.py", "model=deep_shells_ablation", "data=faust_r", *data,
                     f"output_dir={run_dir / 'eval_ablation'}", f"hydra.run.dir={run_dir / 'eval_ablation'}"],
    }
    if with_published:
        cmds["published"] = [_python(), "evaluate.py", "model=deep_shells_published", "data=faust_r", *data,
                             f"output_dir={run_dir / 'eval_published'}",
                             f"hydra.run.dir={run_dir / 'eval_published'}"]
    return cmds


def summarize(run_dir: Path, eval_dir: Path | None = None, ablation_dir: Path | None = None,
              published_dir: Path | None = None) -> dict:
    """The summary dict written to the results file (see the module docstring)."""
    final = {name: read_metrics(folder) for name, folder in
             (("trained", eval_dir), ("ablation_no_learning", ablation_dir), ("published_weights", published_dir))}
    return {
        **summarize_run(run_dir),
        "final": {k: v for k, v in final.items() if v is not None},
        "published_mean_geodesic_error": PUBLISHED_FAUST_R_ERROR,
        "units": "errors: geodesic distance / sqrt(area of the target) (x100 = percent)",
    }


def markdown(summary: dict) -> str:
    """Markdown tables: the validation curve and the final test numbers."""
    return markdown_tables(summary, ("published (paper)", summary["published_mean_geodesic_error"]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--launch", action="store_true", help="train, evaluate, then summarize")
    mode.add_argument("--summarize", metavar="RUN_DIR", help="summarize an existing run")
    parser.add_argument("--run-dir", default=str(REPO / "outputs" / "bench" / "deep_shells_faust_r"),
                        help="--launch: the training run's folder")
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="--launch: FAUST_r folder (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--threads", type=int, default=1, help="--launch: OMP_NUM_THREADS of the runs")
    parser.add_argument("--with-published", action="store_true",
                        help="--launch: also evaluate the released weights ($SHAPECORR_DEEP_SHELLS_WEIGHTS)")
    parser.add_argument("--skip", nargs="*", default=[], choices=("train", "eval", "ablation", "published"),
                        help="--launch: steps to skip (e.g. an ablation evaluated elsewhere)")
    parser.add_argument("--eval-dir", help="evaluate.py output folder of the trained model (metrics.json)")
    parser.add_argument("--ablation-dir", help="evaluate.py output folder of model=deep_shells_ablation")
    parser.add_argument("--published-dir", help="evaluate.py output folder of model=deep_shells_published")
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)

    if args.launch:
        run_dir = Path(args.run_dir).absolute()
        cmds = launch_commands(run_dir, args.faust_r, args.with_published)
        for step, cmd in cmds.items():
            if step not in args.skip:
                bench_common.run_command(cmd, args.threads, REPO)
        folders = {"eval": run_dir / "eval_test", "ablation": run_dir / "eval_ablation",
                   "published": run_dir / "eval_published"}
        eval_dir = args.eval_dir or (folders["eval"] if "eval" not in args.skip else None)
        ablation_dir = args.ablation_dir or (folders["ablation"] if "ablation" not in args.skip else None)
        published_dir = args.published_dir or (folders["published"] if "published" in cmds and
                                                "published" not in args.skip else None)
    else:
        run_dir = Path(args.summarize)
        eval_dir, ablation_dir, published_dir = args.eval_dir, args.ablation_dir, args.published_dir
    summary = summarize(run_dir, *(None if d is None else Path(d) for d in (eval_dir, ablation_dir, published_dir)))
    report = bench_common.summary_report("deep_shells_faust_r.py", sys.argv[1:] if argv is None else list(argv),
                                         summary)
    print(markdown(summary))
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
