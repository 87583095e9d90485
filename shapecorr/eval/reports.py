"""Evaluation reports: ``metrics.json`` and ``per_pair.csv``.

The figure ``pck.png`` is drawn by :func:`shapecorr.viz.pck.write_pck_png`: the evaluation layer does not
import the drawing layer.

Aggregation conventions (documented in ``metrics.json`` itself under ``"conventions"``):

* ``mean_geodesic_error``: mean over pairs of the per-pair mean error (each pair weighs the same, the
  Princeton convention; with the same number of reference points per pair it equals the pooled mean);
* ``median_geodesic_error``, ``pck`` and ``pck_auc``: over all reference points of all pairs, pooled;
* errors are fractions of sqrt(area of the target): multiply by 100 for the numbers papers print;
* ``mean_geodesic_error_sym``: the same map scored against the mirrored ground truth, over the pairs whose
  target has one; reported separately, never mixed into the main numbers;
* ``seconds_per_pair``: mean wall time of the matcher per pair; ``eval_seconds_per_pair``: the evaluation's
  own overhead per pair (loading, scoring, writing);
* ``peak_memory_mb``: the largest resident set size of this process and of its worker processes
  (``resource.getrusage``), and ``peak_cuda_memory_mb`` when a GPU was used;
* ``mean_conformal_distortion``: the conformal distortion of the *map* (every matcher), mean over pairs;
* only for matchers returning a deformation (interpolating matchers), means over the pairs that have
  one (``n_pairs_interpolated``): ``mean_deformation_conformal_distortion`` (the conformal distortion along
  the sequence: per pair the mean over the frames with 0 <= t <= 1, then the mean over pairs; same clamp),
  ``mean_chamfer`` / ``mean_chamfer_one_sided`` (the frame at t = 1 against the target, fractions of
  sqrt(area of the target)), ``mean_volume_change`` and ``mean_volume_score`` (closed meshes only), and
  ``interp_curves``: per frame time, the means over pairs of the conformal distortion and of the volume score
  ``V_t/V_0 + V_0/V_t - 2`` (drawn as ``interp_curves.png`` by :mod:`shapecorr.viz.interp_curves`). These
  keys are absent for matchers without a deformation.
* only for post-processed matchers (``postprocess=``): ``mean_initial_geodesic_error``, the mean over those
  pairs of the wrapped matcher's per-pair mean error before the refinement (same reference points), and
  ``n_pairs_initial``.
"""

from __future__ import annotations

import csv
import io
import json
import os
import resource
import sys
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from shapecorr.data.cache import atomic_open
from shapecorr.errors import CorrespondenceError
from shapecorr.eval import metrics
from shapecorr.eval.matcher_run import TIME_ATOL
from shapecorr.eval.records import PairRecord

#: Per-pair curves over the frames (lists), kept in the per-pair JSON records, not in per_pair.csv.
CURVE_ATTRIBUTES = ("curve_times", "curve_conformal_distortion", "curve_volume_score")
#: Column order of per_pair.csv: the four columns of the issue first, then every scalar a record holds.
PER_PAIR_COLUMNS = ["source", "target", "mean_error", "seconds"] + [
    f.name for f in fields(PairRecord)
    if f.name not in ("source", "target", "mean_error", "seconds") and f.name not in CURVE_ATTRIBUTES
]
#: Per-pair deformation metrics averaged into ``mean_<name>`` when present (interpolating matchers).
DEFORMATION_ATTRIBUTES = ("chamfer", "chamfer_one_sided", "volume_change", "volume_score",
                          "deformation_conformal_distortion")
#: Key of ``metrics.json`` holding the per-time means of the interpolation curves.
CURVES_KEY = "interp_curves"
_KIB_PER_MIB = 1024.0


def peak_memory_mb(include_cuda: bool = True) -> dict[str, float]:
    """Peak memory of this process and of its (finished) child processes, in MiB.

    Returns
    -------
    dict with ``peak_memory_mb`` (max over this process and its children's largest), ``peak_memory_self_mb``,
    ``peak_memory_children_mb`` and, when CUDA was initialized, ``peak_cuda_memory_mb``.
    """
    # ru_maxrss is in KiB on Linux and in bytes on macOS.
    unit = 1.0 / (_KIB_PER_MIB * _KIB_PER_MIB) if sys.platform == "darwin" else 1.0 / _KIB_PER_MIB
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * unit
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * unit
    out = {"peak_memory_mb": max(own, children), "peak_memory_self_mb": own, "peak_memory_children_mb": children}
    if include_cuda:
        import torch

        if torch.cuda.is_available() and torch.cuda.is_initialized():
            out["peak_cuda_memory_mb"] = torch.cuda.max_memory_allocated() / (_KIB_PER_MIB * _KIB_PER_MIB)
    return out


def _mean_of(records: Sequence[PairRecord], attr: str) -> float | None:
    values = [getattr(r, attr) for r in records if getattr(r, attr) is not None]
    return float(np.mean(values)) if values else None


def interpolation_curves(records: Sequence[PairRecord]) -> dict[str, list] | None:
    """Per-time means over pairs of the interpolation curves (``metrics.json["interp_curves"]``).

    Parameters
    ----------
    records : list of PairRecord
        Those without curves (non-interpolating matchers) are skipped.

    Returns
    -------
    dict with ``times (T,)`` (every frame time of any pair, sorted; times closer than
    :data:`~shapecorr.eval.matcher_run.TIME_ATOL` merged), ``conformal_distortion (T,)`` and ``volume_score (T,)``
    (means over the pairs having a value at that time; None where no pair has one) and ``n_pairs (T,)``, or
    None when no record has curves.
    """
    with_curves = [r for r in records if r.curve_times]
    if not with_curves:
        return None
    times: list[float] = []
    for t in sorted(t for r in with_curves for t in r.curve_times):
        if not times or t - times[-1] > TIME_ATOL:
            times.append(float(t))
    grid = np.asarray(times)
    sums = {"conformal_distortion": [[] for _ in times], "volume_score": [[] for _ in times]}
    n_pairs = [0] * len(times)
    for r in with_curves:
        index = np.abs(np.asarray(r.curve_times)[:, None] - grid[None, :]).argmin(axis=1)
        volumes = r.curve_volume_score or [None] * len(r.curve_times)
        for k, d, v in zip(index.tolist(), r.curve_conformal_distortion, volumes):
            n_pairs[k] += 1
            sums["conformal_distortion"][k].append(d)
            if v is not None:
                sums["volume_score"][k].append(v)
    out: dict[str, list] = {"times": times, "n_pairs": n_pairs}
    for key, values in sums.items():
        out[key] = [float(np.mean(v)) if v else None for v in values]
    return out


def aggregate(
    records: Sequence[PairRecord],
    errors: Sequence[np.ndarray],
    errors_sym: Sequence[np.ndarray | None] | None = None,
    thresholds: np.ndarray | None = None,
) -> dict[str, Any]:
    """Dataset-level metrics from per-pair records and per-point errors (see the module docstring).

    Parameters
    ----------
    records : list of PairRecord
    errors : list of (R_k,) float
        Per-reference-point errors of each pair.
    errors_sym : list of (R_k,) float or None, optional
        The same against the mirrored ground truth.
    thresholds : (t,) float, optional
        PCK thresholds (default 0..0.25).

    Returns
    -------
    dict (JSON-serializable)
    """
    if not records:
        raise CorrespondenceError("no evaluated pair to aggregate")
    if len(errors) != len(records):
        raise CorrespondenceError(f"{len(records)} records but {len(errors)} error arrays")
    pooled = np.concatenate([np.asarray(e, dtype=np.float64) for e in errors])
    t, frac = metrics.pck_curve(pooled, thresholds)
    seconds = np.array([r.seconds for r in records])
    out: dict[str, Any] = {
        "n_pairs": len(records),
        "n_points": int(pooled.size),
        "mean_geodesic_error": float(np.mean([r.mean_error for r in records])),
        "median_geodesic_error": float(np.median(pooled)),
        "pck_auc": metrics.pck_auc(t, frac),
        "mean_conformal_distortion": _mean_of(records, "conformal_distortion"),
        "seconds_per_pair": float(seconds.mean()),
        "median_seconds_per_pair": float(np.median(seconds)),
        "eval_seconds_per_pair": float(np.mean([r.eval_seconds for r in records])),
    }
    sym = [(r, e) for r, e in zip(records, errors_sym or [None] * len(records)) if e is not None]
    if sym:
        pooled_sym = np.concatenate([np.asarray(e, dtype=np.float64) for _, e in sym])
        ts, fs = metrics.pck_curve(pooled_sym, thresholds)
        out["mean_geodesic_error_sym"] = float(np.mean([r.mean_error_sym for r, _ in sym]))
        out["pck_auc_sym"] = metrics.pck_auc(ts, fs)
        out["n_pairs_sym"] = len(sym)
        out["pck_sym"] = {"thresholds": ts.tolist(), "fractions": fs.tolist()}
    for attr in DEFORMATION_ATTRIBUTES:
        value = _mean_of(records, attr)
        if value is not None:
            out[f"mean_{attr}"] = value
    initial = [r.initial_mean_error for r in records if r.initial_mean_error is not None]
    if initial:
        out["mean_initial_geodesic_error"] = float(np.mean(initial))
        out["n_pairs_initial"] = len(initial)
    interpolated = sum(r.deformation_conformal_distortion is not None for r in records)
    if interpolated:
        out["n_pairs_interpolated"] = interpolated
    curves = interpolation_curves(records)
    if curves is not None:
        out[CURVES_KEY] = curves
    out["pck"] = {"thresholds": t.tolist(), "fractions": frac.tolist()}
    out["conventions"] = {
        "errors": "geodesic distance on the target / sqrt(area of the target); x100 for paper numbers",
        "mean_geodesic_error": "mean over pairs of the per-pair mean",
        "median_geodesic_error": "median over all reference points of all pairs",
        "pck_auc": "trapezoid area under the pooled PCK curve divided by the threshold range",
        "mean_conformal_distortion": "of the map: area-weighted (K - 1/K)^2 per source triangle with its corners "
        "moved to their images, clamped, mean over pairs",
    }
    if initial:
        out["conventions"]["mean_initial_geodesic_error"] = (
            "post-processing: the wrapped matcher's map before the refinement, mean over pairs of the per-pair mean")
    if interpolated:
        out["conventions"].update(
            {
                "mean_deformation_conformal_distortion": "along the interpolation: the same per-triangle measure "
                "between x and each frame with 0 <= t <= 1, mean over those frames, then over pairs",
                "mean_chamfer": "two-sided Chamfer distance between the frame at t = 1 and the target "
                "(mean nearest-vertex distance both ways, summed) / sqrt(area of the target), mean over pairs",
                "mean_chamfer_one_sided": "the frame-at-t=1 -> target half of mean_chamfer",
                "mean_volume_change": "V_1/V_0 - 1 of the frame at t = 1 (signed; closed meshes), mean over pairs",
                "mean_volume_score": "V_1/V_0 + V_0/V_1 - 2 of the frame at t = 1 (closed meshes), mean over pairs",
                CURVES_KEY: "per frame time (extrapolated frames included): conformal distortion of the frame vs x "
                "and V_t/V_0 + V_0/V_t - 2, means over the pairs with that time (n_pairs); drawn in interp_curves.png",
            }
        )
    return out


def summary(metrics_dict: Mapping[str, Any], out_dir: str | os.PathLike | None = None) -> str:
    """The one-line summary ``evaluate.py`` prints (errors, PCK AUC, time; interpolation metrics if present)."""
    m = metrics_dict
    text = (
        f"{m['n_pairs']} pairs: mean geodesic error {m['mean_geodesic_error']:.4f} "
        f"(x100: {100 * m['mean_geodesic_error']:.2f}), PCK AUC {m['pck_auc']:.3f}, "
        f"{m['seconds_per_pair']:.3f} s/pair"
    )
    if "mean_initial_geodesic_error" in m:
        text += f" (before post-processing {m['mean_initial_geodesic_error']:.4f})"
    if "mean_geodesic_error_sym" in m:
        text += f"; vs mirrored ground truth {m['mean_geodesic_error_sym']:.4f}"
    if "mean_deformation_conformal_distortion" in m:
        text += (
            f"; interpolation: conformal distortion {m['mean_deformation_conformal_distortion']:.4f}, "
            f"Chamfer X(1)-Y {m['mean_chamfer']:.4f} (one-sided {m['mean_chamfer_one_sided']:.4f})"
        )
        if "mean_volume_score" in m:
            text += f", volume score at t = 1 {m['mean_volume_score']:.4f}"
    if out_dir is not None:
        text += f" -> {out_dir}"
    return text


def write_metrics_json(path: str | os.PathLike, metrics_dict: Mapping[str, Any]) -> Path:
    """Write ``metrics.json`` atomically (sorted keys, indented)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as fh:
        fh.write((json.dumps(metrics_dict, indent=2, sort_keys=True) + "\n").encode())
    return path


def write_per_pair_csv(path: str | os.PathLike, records: Sequence[PairRecord]) -> Path:
    """Write ``per_pair.csv``: one row per pair, columns :data:`PER_PAIR_COLUMNS` (empty cell = not applicable)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=PER_PAIR_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for r in records:
        row = asdict(r)
        writer.writerow({k: "" if row[k] is None else row[k] for k in PER_PAIR_COLUMNS})
    with atomic_open(path) as fh:
        # surrogateescape: shape names from non-UTF-8 file names are written back as their original bytes
        fh.write(text.getvalue().encode("utf-8", "surrogateescape"))
    return path


def read_per_pair_csv(path: str | os.PathLike) -> list[PairRecord]:
    """Read ``per_pair.csv`` back into records (empty cells -> None)."""
    path = Path(path)
    types = {f.name: f.type for f in fields(PairRecord)}
    records = []
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            values: dict[str, Any] = {}
            for key, text in row.items():
                if key not in types:
                    continue
                if text == "":
                    values[key] = None
                elif key in ("source", "target"):
                    values[key] = text
                elif key == "n_points":
                    values[key] = int(text)
                else:
                    values[key] = float(text)
            records.append(PairRecord.from_dict(values))
    return records
