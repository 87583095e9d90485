"""Per-pair evaluation: run a matcher on one ordered pair, score its map against the ground truth, store it.

The protocol (docs/evaluation.md §1): the map X -> Y is scored at the reference points of the ground truth with
geodesic distances on Y normalized by sqrt(area(Y)) (:mod:`shapecorr.eval.scoring`); interpolating matchers are
run at the requested times and their frame at t = 1 is scored as well (:mod:`shapecorr.eval.matcher_run`).

Per pair, under the output folder::

    maps/<x>__<y>.txt, maps/<x>__<y>.npy     the map (see :mod:`shapecorr.eval.export`)
    interp/<x>__<y>/t_XX.ply, times.txt      interpolation frames, for matchers returning a deformation
    pairs/<x>__<y>.npz                       per-reference-point errors (``errors``, ``errors_sym``)
    pairs/<x>__<y>.json                      the :class:`PairRecord`, written last

A pair is *done* when its record exists (every file is written atomically and the record last), so an
interrupted run resumes with the pairs that are missing.

Records: :mod:`shapecorr.eval.records`; many pairs, in worker processes: :mod:`shapecorr.eval.pair_pool`.
"""

from __future__ import annotations

import os
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from shapecorr.data.datasets import pair_name
from shapecorr.errors import ConfigError
from shapecorr.eval import metrics
from shapecorr.eval.export import write_map_files, write_sequence
from shapecorr.eval.matcher_run import check_interp_times, run_matcher
from shapecorr.eval.records import PairRecord, write_record
from shapecorr.eval.scoring import score_deformation, score_map


#: Number of ShapeSamples (eigenbasis + descriptors) kept in memory per process (~5 MB each at 5k vertices).
DEFAULT_SAMPLE_CACHE = 32
#: Number of per-shape geodesic rows (from the ground-truth points, 4 R n bytes: 70 MB for FAUST_r) kept in memory
#: per process.
DEFAULT_GEODESIC_CACHE = 2
GEODESIC_METHODS = ("heat", "exact")
#: ``MatchResult.extras`` key of a post-processed matcher's map before its refinement (scored as
#: ``PairRecord.initial_mean_error``).
INITIAL_MAP_KEY = "initial_p2p"
#: ``MatchResult.extras`` key: seconds spent on the map before ``match`` (a multi-shape matcher's queries), added
#: to the pair's ``seconds``.
PRECOMPUTED_SECONDS_KEY = "precomputed_seconds"


@dataclass(frozen=True)
class EvalSettings:
    """How pairs are evaluated.

    Attributes
    ----------
    geodesics : {"heat", "exact"}
        Geodesic distances used for the errors (``exact`` for final numbers, docs/evaluation.md §1).
    conformal_clamp : float
        Per-triangle clamp of the conformal distortion.
    write_maps : bool
        Write ``maps/<x>__<y>.txt`` and ``.npy``.
    write_interp : bool
        Write the interpolation frames of matchers returning a deformation as
        ``interp/<x>__<y>/t_XX.ply`` + ``times.txt`` (in x's input units).
    interp_times : tuple of float, optional
        Times at which interpolating matchers are evaluated and their frames written (finite, strictly
        increasing, t > 1 allowed); None: the frames ``match`` returns.
    device : str
        Device the pair is moved to before ``match`` (``cpu``, ``cuda:0``, ...).
    sample_cache, geodesic_cache : int
        In-memory LRU sizes per process.
    """

    geodesics: str = "heat"
    conformal_clamp: float = metrics.CONFORMAL_DISTORTION_CLAMP
    write_maps: bool = True
    write_interp: bool = True
    interp_times: tuple[float, ...] | None = None
    device: str = "cpu"
    sample_cache: int = DEFAULT_SAMPLE_CACHE
    geodesic_cache: int = DEFAULT_GEODESIC_CACHE

    def __post_init__(self):
        if self.geodesics not in GEODESIC_METHODS:
            raise ConfigError(f"geodesics must be one of {GEODESIC_METHODS}, got {self.geodesics!r}")
        if self.sample_cache < 1 or self.geodesic_cache < 1:
            raise ConfigError("sample_cache and geodesic_cache must be >= 1")
        if self.interp_times is not None:
            object.__setattr__(self, "interp_times", check_interp_times(self.interp_times))


class _LRU:
    """A small least-recently-used cache of ``key -> value`` computed by a function."""

    def __init__(self, compute, size: int):
        self.compute, self.size, self.items = compute, size, OrderedDict()

    def __call__(self, key):
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        value = self.compute(key)
        self.items[key] = value
        while len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class PairEvaluator:
    """Evaluates pairs (i, j) of a ShapeDataset with one matcher and writes their outputs to ``out_dir``.

    Parameters
    ----------
    shapes : ShapeDataset
    matcher : Matcher
    out_dir : path
    settings : EvalSettings
    """

    def __init__(self, shapes, matcher, out_dir: str | os.PathLike, settings: EvalSettings = EvalSettings()):
        self.shapes, self.matcher, self.out_dir, self.settings = shapes, matcher, Path(out_dir), settings
        self.device = torch.device(settings.device)
        self.sample = _LRU(lambda i: shapes[i], settings.sample_cache)
        self.geodesics = _LRU(lambda j: shapes.ground_truth_geodesics(j, method=settings.geodesics),
                              settings.geodesic_cache)

    def __call__(self, i: int, j: int) -> PairRecord:
        """Match, score and write pair ``(i, j)`` (maps, sequence, per-pair record); return its record."""
        start = time.perf_counter()
        x, y = self.sample(i), self.sample(j)
        name = pair_name(x.name, y.name)
        t0 = time.perf_counter()
        xd, yd = x.to(self.device), y.to(self.device)
        with torch.no_grad():
            run = run_matcher(self.matcher, xd, yd, self.settings.interp_times)
        _synchronize(self.device)
        seconds = time.perf_counter() - t0 + float(run.result.extras.get(PRECOMPUTED_SECONDS_KEY, 0.0))
        result = run.result.cpu().validate(x.shape.n_verts, y.shape.n_verts, name)
        run = replace(run, result=result)
        scores = score_map(result.p2p, x, y, self.geodesics(j), self.settings.conformal_clamp)
        extra: dict[str, float | None] = {}
        if result.deformation is not None:
            extra = score_deformation(result.deformation, x, y, self.settings.conformal_clamp, times=result.times)
            if self.settings.write_interp:
                frames, times = run.sequence()
                write_sequence(self.out_dir, x.name, y.name, frames, x.shape.faces, times, shape=x.shape)
        if self.settings.write_maps:
            write_map_files(self.out_dir, x.name, y.name, result.p2p)
        errors, errors_sym = scores["errors"], scores["errors_sym"]
        initial = result.extras.get(INITIAL_MAP_KEY)
        if initial is not None:  # a post-processed matcher: score the map it started from as well
            initial_scores = score_map(initial, x, y, self.geodesics(j), self.settings.conformal_clamp)
            extra["initial_mean_error"] = float(initial_scores["errors"].mean())
        record = PairRecord(
            source=x.name,
            target=y.name,
            mean_error=float(errors.mean()),
            median_error=float(np.median(errors)),
            n_points=int(errors.shape[0]),
            n_excluded=int(scores["n_excluded"]),
            seconds=seconds,
            eval_seconds=0.0,
            conformal_distortion=float(scores["conformal_distortion"]),
            mean_error_sym=None if errors_sym is None else float(errors_sym.mean()),
            **extra,
        )
        record.eval_seconds = time.perf_counter() - start - seconds
        write_record(self.out_dir, record, errors, errors_sym)
        return record
