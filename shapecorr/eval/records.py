"""Per-pair records on disk: the scalar results of a pair and its per-reference-point errors.

``pairs/<x>__<y>.npz`` holds the errors (``errors``, ``errors_sym``), ``pairs/<x>__<y>.json`` the
:class:`PairRecord`, written last: a pair is *done* when its record exists (every file is written atomically),
so an interrupted run resumes with the pairs that are missing.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import pair_name
from shapecorr.errors import CorrespondenceError


RECORDS_DIR = "pairs"


@dataclass
class PairRecord:
    """Scalar results of one evaluated pair (the row of ``per_pair.csv``).

    Attributes
    ----------
    source, target : str
        Shape names; the map goes from source to target.
    mean_error, median_error : float
        Over the reference points, as fractions of sqrt(area(target)).
    n_points : int
        Number of reference points.
    seconds : float
        Wall time of the matcher alone (``match``, or ``interpolate`` at the interpolation times), including
        moving the pair to the device.
    eval_seconds : float
        Wall time of everything else for this pair (loading, scoring, writing).
    conformal_distortion : float
        Area-weighted conformal distortion of the map (:func:`shapecorr.eval.metrics.map_conformal_distortion`).
    mean_error_sym : float or None
        Mean error against the mirrored ground truth, when the target has one.
    chamfer, chamfer_one_sided, volume_change, deformation_conformal_distortion : float or None
        For matchers returning a deformation (interpolating matchers), from :func:`score_deformation`:
        two-sided / one-sided Chamfer distance between the frame at t = 1 and the target (fractions of
        sqrt(area(target))), relative volume change of that frame (closed meshes only), and the conformal
        distortion of the frames with 0 <= t <= 1 averaged over those frames. None otherwise.
    n_excluded : int
        Reference points excluded because they lie on a small island of the source or target mesh.
    volume_score : float or None
        ``V_1/V_0 + V_0/V_1 - 2`` of the frame at t = 1 (closed meshes only; interpolating matchers).
    curve_times, curve_conformal_distortion, curve_volume_score : list or None
        Interpolating matchers: the time of every computed frame (extrapolated ones and an added t = 1
        included) and that frame's conformal distortion and volume score (None entries: open mesh or
        inverted frame). Kept in ``pairs/<x>__<y>.json``; not columns of ``per_pair.csv``.
    initial_mean_error : float or None
        Post-processed matchers (``postprocess=``, whose result carries ``extras["initial_p2p"]``): the mean
        error of the wrapped matcher's map before the refinement, on the same reference points; None otherwise.
    """

    source: str
    target: str
    mean_error: float
    median_error: float
    n_points: int
    seconds: float
    eval_seconds: float
    conformal_distortion: float
    mean_error_sym: float | None = None
    chamfer: float | None = None
    chamfer_one_sided: float | None = None
    volume_change: float | None = None
    deformation_conformal_distortion: float | None = None
    n_excluded: int = 0
    volume_score: float | None = None
    curve_times: list[float] | None = None
    curve_conformal_distortion: list[float] | None = None
    curve_volume_score: list[float | None] | None = None
    initial_mean_error: float | None = None

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PairRecord":
        """Record from a dict (e.g. a parsed JSON line); keys that are not fields are ignored."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def record_paths(out_dir: str | os.PathLike, source: str, target: str) -> tuple[Path, Path]:
    """``(json, npz)`` paths of a pair's record."""
    folder, stem = Path(out_dir) / RECORDS_DIR, pair_name(source, target)
    return folder / f"{stem}.json", folder / f"{stem}.npz"


def is_done(out_dir: str | os.PathLike, source: str, target: str) -> bool:
    """True when the pair's record and errors exist (it is skipped on re-run)."""
    js, npz = record_paths(out_dir, source, target)
    return js.is_file() and npz.is_file()


def count_done(out_dir: str | os.PathLike, names: Sequence[tuple[str, str]]) -> int:
    """How many of the pairs ``names`` (source, target) already have a record in ``out_dir``."""
    return sum(is_done(out_dir, a, b) for a, b in names)


def write_record(
    out_dir: str | os.PathLike, record: PairRecord, errors: np.ndarray, errors_sym: np.ndarray | None
) -> None:
    """Write a pair's errors then its record (atomic files; the record marks the pair as done)."""
    js, npz = record_paths(out_dir, record.source, record.target)
    js.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"errors": np.asarray(errors, dtype=np.float32)}
    if errors_sym is not None:
        arrays["errors_sym"] = np.asarray(errors_sym, dtype=np.float32)
    with atomic_open(npz) as fh:
        np.savez(fh, **arrays)
    with atomic_open(js) as fh:
        fh.write(json.dumps(asdict(record), indent=1).encode())


def load_record(
    out_dir: str | os.PathLike, source: str, target: str
) -> tuple[PairRecord, np.ndarray, np.ndarray | None]:
    """Read back ``(record, errors, errors_sym)`` of a done pair."""
    js, npz = record_paths(out_dir, source, target)
    try:
        record = PairRecord.from_dict(json.loads(js.read_text()))
        with np.load(npz, allow_pickle=False) as data:
            errors = data["errors"].astype(np.float64)
            errors_sym = data["errors_sym"].astype(np.float64) if "errors_sym" in data.files else None
    except (OSError, ValueError, KeyError, TypeError) as err:
        problem = f"unreadable evaluation record ({err}); delete it to recompute the pair"
        raise CorrespondenceError(problem, js) from None
    return record, errors, errors_sym
