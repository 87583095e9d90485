"""Reading a finished (or running) ``train.py`` run for the benchmark summaries: TensorBoard scalars, the run's
Hydra config, the learning curve against training pairs seen, and ``evaluate.py`` metrics files.

Shared by ``deep_shells_faust_r.py`` and ``neuromorph_faust_r.py``.

Pairs seen: Lightning logs at the optimizer step; a point logged at step ``s`` follows about
``(s + 1) x accumulate_grad_batches x devices`` training pairs (exact for validation points of runs that log
``val/pairs_seen``, which every CorrespondenceModule does while fitting).
"""

from __future__ import annotations

import json
from pathlib import Path

VAL_TAG = "val/geodesic_error"
VAL_PAIRS_TAG = "val/pairs_seen"
TRAIN_TAG = "train/loss_step"
#: Keys of an evaluate.py metrics.json copied into the summaries.
METRIC_KEYS = ("n_pairs", "mean_geodesic_error", "median_geodesic_error", "pck_auc", "mean_geodesic_error_sym",
               "mean_conformal_distortion", "seconds_per_pair", "mean_chamfer", "mean_deformation_conformal_distortion")
#: Percent per fraction of sqrt(area), for the printed tables.
PERCENT = 100.0


def event_dirs(run_dir: Path) -> list[Path]:
    """Folders under ``run_dir`` holding TensorBoard event files (sorted)."""
    return sorted({p.parent for p in Path(run_dir).rglob("events.out.tfevents.*")})


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
    cfg_file, overrides = Path(run_dir) / ".hydra" / "config.yaml", Path(run_dir) / ".hydra" / "overrides.yaml"
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
    devices = _int_or(trainer.get("devices", 1), 1)
    return _int_or(trainer.get("accumulate_grad_batches"), 1) * (devices if devices > 0 else 1)


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


def read_metrics(folder: Path | None, extra_keys: tuple[str, ...] = ()) -> dict | None:
    """Selected numbers of an evaluate.py ``metrics.json`` (None when no folder is given).

    ``extra_keys``: more keys, looked up at the top level and in its ``multi_shape`` section (cycle consistency).
    """
    if folder is None:
        return None
    path = Path(folder) / "metrics.json"
    if not path.is_file():
        raise SystemExit(f"{path}: not found (did the evaluation finish?)")
    metrics = json.loads(path.read_text())
    flat = {**metrics.get("multi_shape", {}), **metrics}
    out = {k: flat[k] for k in (*METRIC_KEYS, *extra_keys) if k in flat}
    out["metrics_file"] = str(path)
    return out


def summarize_run(run_dir: Path) -> dict:
    """Overrides, learning curve, best/last validation point and optimizer steps of a run folder."""
    run_dir = Path(run_dir)
    scalars = read_scalars(run_dir)
    config = run_config(run_dir)
    curve = learning_curve(scalars, pairs_per_step(config))
    val = curve["validation"]
    return {
        "run_dir": str(run_dir),
        "overrides": config.get("overrides"),
        "curve": curve,
        "best_validation": min(val, key=lambda p: p["val_geodesic_error"]) if val else None,
        "last_validation": val[-1] if val else None,
        "optimizer_steps_logged": max((s for series in scalars.values() for s, _, _ in series), default=-1) + 1,
    }


def markdown_tables(summary: dict, published: tuple[str, float] | None = None) -> str:
    """Markdown tables: the validation curve and the final test numbers (``summary["final"]``)."""
    lines = ["| pairs seen | optimizer steps | hours | val error (%) |", "|---:|---:|---:|---:|"]
    for p in summary["curve"]["validation"]:
        hours = "" if p["hours"] is None else f"{p['hours']:.2f}"
        lines.append(f"| {p['pairs_seen']} | {p['step'] + 1} | {hours} | {PERCENT * p['val_geodesic_error']:.2f} |")
    lines += ["", "| model | test pairs | mean error (%) | median error (%) | PCK AUC |", "|---|---:|---:|---:|---:|"]
    for name, m in summary["final"].items():
        median, auc = m.get("median_geodesic_error", float("nan")), m.get("pck_auc", float("nan"))
        lines.append(f"| {name} | {m.get('n_pairs', '')} | {PERCENT * m['mean_geodesic_error']:.2f} | "
                     f"{PERCENT * median:.2f} | {auc:.3f} |")
    if published is not None:
        lines.append(f"| {published[0]} | 380 | {PERCENT * published[1]:.1f} | | |")
    return "\n".join(lines)
