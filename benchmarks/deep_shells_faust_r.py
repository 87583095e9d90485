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
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

import bench_common

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
VAL_TAG = "val/geodesic_error"
VAL_PAIRS_TAG = "val/pairs_seen"
TRAIN_TAG = "train/loss_step"
#: Published FAUST_r mean geodesic error of Deep Shells, fraction of sqrt(area) (Eisenberger et al. 2020, 1.7 %; the
#: figure the golden reference README quotes for the released weights on all test pairs).
PUBLISHED_FAUST_R_ERROR = 0.017
#: Keys of an evaluate.py metrics.json copied into the summary.
METRIC_KEYS = ("n_pairs", "mean_geodesic_error", "median_geodesic_error", "pck_auc", "mean_geodesic_error_sym",
               "mean_conformal_distortion", "seconds_per_pair")
#: Percent per fraction of sqrt(area), for the printed tables.
PERCENT = 100.0


def _python() -> str:
    return sys.executable


def _run(cmd: list[str], threads: int) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    print("$", " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, cwd=REPO, env=env, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"command failed with status {proc.returncode}: {' '.join(cmd)}")


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


# -- reading a run ------------------------------------------------------------------------------------------------
def event_dirs(run_dir: Path) -> list[Path]:
    """Folders under ``run_dir`` holding TensorBoard event files (sorted)."""
    return sorted({p.parent for p in run_dir.rglob("events.out.tfevents.*")})


def read_scalars(run_dir: Path) -> dict[str, list[tuple[int, float, float]]]:
    """Every scalar of the run's event files: tag -> [(step, value, wall_time)], sorted by wall time.

    Several event folders (e.g. a resumed run writing a new file) are merged; a step logged more than once keeps
    its last value.
    """
    from tensorboard.backend.event_processing.event_accumulator import (
        SCALARS,
        EventAccumulator,
    )

    folders = event_dirs(run_dir)
    if not folders:
        raise SystemExit(f"{run_dir}: no TensorBoard event files (events.out.tfevents.*) found")
    merged: dict[str, dict[int, tuple[float, float]]] = {}
    for folder in folders:
        acc = EventAccumulator(str(folder), size_guidance={SCALARS: 0})  # 0 = keep every event
        acc.Reload()
        for tag in acc.Tags()[SCALARS]:
            for ev in sorted(acc.Scalars(tag), key=lambda e: e.wall_time):
                merged.setdefault(tag, {})[int(ev.step)] = (float(ev.value), float(ev.wall_time))
    return {tag: sorted(((s, v, w) for s, (v, w) in steps.items()), key=lambda t: t[2])
            for tag, steps in merged.items()}


def run_config(run_dir: Path) -> dict:
    """The run's composed config and command-line overrides (``.hydra/``), unresolved; empty if absent."""
    from omegaconf import OmegaConf

    out: dict = {}
    cfg_file, overrides = run_dir / ".hydra" / "config.yaml", run_dir / ".hydra" / "overrides.yaml"
    if cfg_file.is_file():
        out["config"] = OmegaConf.to_container(OmegaConf.load(cfg_file), resolve=False)
    if overrides.is_file():
        out["overrides"] = OmegaConf.to_container(OmegaConf.load(overrides), resolve=False)
    return out


def _int_or(value, default: int) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        return default


def pairs_per_step(config: dict) -> int:
    """Training pairs per optimizer step: accumulate_grad_batches x devices (1 where unknown)."""
    trainer = (config.get("config") or {}).get("trainer") or {}
    devices = trainer.get("devices", 1)
    return _int_or(trainer.get("accumulate_grad_batches"), 1) * (_int_or(devices, 1) if _int_or(devices, 1) > 0 else 1)


def learning_curve(scalars: dict, per_step: int) -> dict:
    """Validation and training curves against the number of training pairs seen."""
    exact = {s: v for s, v, _ in scalars.get(VAL_PAIRS_TAG, [])}
    start = min((w for series in scalars.values() for _, _, w in series), default=None)
    val = []
    for step, value, wall in scalars.get(VAL_TAG, []):
        val.append({"step": step, "pairs_seen": int(exact.get(step, (step + 1) * per_step)),
                    "pairs_seen_exact": step in exact, "val_geodesic_error": value,
                    "hours": None if start is None else (wall - start) / 3600.0})
    train = [{"step": s, "pairs_seen": (s + 1) * per_step, "loss": v} for s, v, _ in scalars.get(TRAIN_TAG, [])]
    return {"validation": val, "train_loss": train, "pairs_per_optimizer_step": per_step}


def read_metrics(folder: Path | None) -> dict | None:
    """Selected numbers of an evaluate.py ``metrics.json`` (None when no folder is given)."""
    if folder is None:
        return None
    path = Path(folder) / "metrics.json"
    if not path.is_file():
        raise SystemExit(f"{path}: not found (did the evaluation finish?)")
    metrics = json.loads(path.read_text())
    out = {k: metrics[k] for k in METRIC_KEYS if k in metrics}
    out["metrics_file"] = str(path)
    return out


def summarize(run_dir: Path, eval_dir: Path | None = None, ablation_dir: Path | None = None,
              published_dir: Path | None = None) -> dict:
    """The summary dict written to the results file (see the module docstring)."""
    run_dir = Path(run_dir)
    scalars = read_scalars(run_dir)
    config = run_config(run_dir)
    curve = learning_curve(scalars, pairs_per_step(config))
    val = curve["validation"]
    final = {name: read_metrics(folder) for name, folder in
             (("trained", eval_dir), ("ablation_no_learning", ablation_dir), ("published_weights", published_dir))}
    return {
        "run_dir": str(run_dir),
        "overrides": config.get("overrides"),
        "curve": curve,
        "best_validation": min(val, key=lambda p: p["val_geodesic_error"]) if val else None,
        "last_validation": val[-1] if val else None,
        "optimizer_steps_logged": max((s for series in scalars.values() for s, _, _ in series), default=-1) + 1,
        "final": {k: v for k, v in final.items() if v is not None},
        "published_mean_geodesic_error": PUBLISHED_FAUST_R_ERROR,
        "units": "errors: geodesic distance / sqrt(area of the target) (x100 = percent)",
    }


def markdown(summary: dict) -> str:
    """Markdown tables: the validation curve and the final test numbers."""
    lines = ["| pairs seen | optimizer steps | hours | val error (%) |", "|---:|---:|---:|---:|"]
    for p in summary["curve"]["validation"]:
        hours = "" if p["hours"] is None else f"{p['hours']:.2f}"
        lines.append(f"| {p['pairs_seen']} | {p['step'] + 1} | {hours} | {PERCENT * p['val_geodesic_error']:.2f} |")
    lines += ["", "| model | test pairs | mean error (%) | median error (%) | PCK AUC |", "|---|---:|---:|---:|---:|"]
    for name, m in summary["final"].items():
        median, auc = m.get("median_geodesic_error", float("nan")), m.get("pck_auc", float("nan"))
        lines.append(f"| {name} | {m.get('n_pairs', '')} | {PERCENT * m['mean_geodesic_error']:.2f} | "
                     f"{PERCENT * median:.2f} | {auc:.3f} |")
    lines.append(f"| published (paper) | 380 | {PERCENT * summary['published_mean_geodesic_error']:.1f} | | |")
    return "\n".join(lines)


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
                _run(cmd, args.threads)
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
    report = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]) if argv is None else " ".join(
            ["deep_shells_faust_r.py", *argv]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": bench_common.machine_info(),
        **summary,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(markdown(summary))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
