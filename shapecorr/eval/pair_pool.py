"""Evaluating many pairs: those already done are skipped, the others run in CPU worker processes or here.

:func:`evaluate_pairs` runs pairs in ``workers`` CPU processes (each holding a copy of the matcher and the
dataset); with ``workers=0`` everything runs in the calling process, which is what a matcher on a GPU needs.
Under DDP every rank evaluates its shard (:func:`shapecorr.eval.sharding.shard_pairs`) into the same folder;
the records are the per-pair results that rank 0 merges afterwards (``shapecorr.cli.evaluate``).
"""

from __future__ import annotations

import multiprocessing
import os
import warnings
from concurrent.futures import FIRST_EXCEPTION, wait
from typing import Sequence

import torch
from tqdm.auto import tqdm

from shapecorr.data.datasets import check_pair_names
from shapecorr.data.validation import MeshWarning
from shapecorr.data.workers import process_pool, submit_all
from shapecorr.errors import ConfigError
from shapecorr.eval.protocol import EvalSettings, PairEvaluator
from shapecorr.eval.records import PairRecord, is_done, load_record


START_METHODS = ("spawn", "forkserver", "fork")


_WORKER: PairEvaluator | None = None


def _init_worker(shapes, matcher, out_dir, settings, threads: int) -> None:
    global _WORKER
    import signal

    # Ctrl-C reaches the whole process group: the parent stops the workers and the run (one line, see
    # shapecorr.cli.evaluate) instead of each worker printing a traceback (already ignored from the start when
    # submitted with shapecorr.data.workers.submit_all).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # the calling process has loaded every mesh of the run and reported its warnings (ShapeDataset.prepare)
    warnings.simplefilter("ignore", MeshWarning)
    torch.set_num_threads(threads)
    _WORKER = PairEvaluator(shapes, matcher, out_dir, settings)


def _run_in_worker(i: int, j: int) -> PairRecord:
    assert _WORKER is not None, "worker not initialized"
    return _WORKER(i, j)


def evaluate_pairs(
    matcher,
    shapes,
    pairs: Sequence[tuple[int, int]],
    out_dir: str | os.PathLike,
    settings: EvalSettings = EvalSettings(),
    workers: int = 0,
    start_method: str = "spawn",
    progress: bool = True,
) -> list[PairRecord]:
    """Evaluate ordered pairs of ``shapes`` (skipping pairs already done) and return all their records.

    Parameters
    ----------
    matcher : Matcher
    shapes : ShapeDataset
    pairs : list of (i, j)
        Indices into ``shapes``; the map goes from i to j.
    out_dir : path
    settings : EvalSettings
    workers : int
        CPU worker processes; 0 runs in this process (required for a matcher on a GPU).
    start_method : {"spawn", "forkserver", "fork"}
        How worker processes start (spawn is safe with threaded libraries; fork starts faster on Linux).
    progress : bool
        Show a progress bar.

    Returns
    -------
    list of PairRecord, in the order of ``pairs``
    """
    if start_method not in START_METHODS:
        raise ConfigError(f"start_method must be one of {START_METHODS}, got {start_method!r}")
    if workers < 0:
        raise ConfigError(f"workers must be >= 0, got {workers}")
    if workers > 0 and torch.device(settings.device).type != "cpu":
        raise ConfigError(f"parallel workers evaluate on the CPU only; use workers=0 with device={settings.device}")
    names = [(shapes.names[i], shapes.names[j]) for i, j in pairs]
    check_pair_names(names, getattr(shapes, "root", None))  # two pairs must never share one record
    todo = [p for p, (a, b) in zip(pairs, names) if not is_done(out_dir, a, b)]
    # Grouping by target lets each process reuse the target's geodesic matrix across consecutive pairs.
    todo.sort(key=lambda p: (p[1], p[0]))
    bar = tqdm(total=len(pairs), initial=len(pairs) - len(todo), desc="evaluating", unit="pair", disable=not progress)
    try:
        if workers == 0 or len(todo) <= 1:
            evaluator = PairEvaluator(shapes, matcher, out_dir, settings)
            for i, j in todo:
                evaluator(i, j)
                bar.update()
        else:
            # each worker gets its share of the CPUs, never more torch threads than this process has (which
            # honours OMP_NUM_THREADS): oversubscribed OpenMP threads spin and slow everything down
            threads = max(1, min(torch.get_num_threads(), (os.cpu_count() or 1) // workers))
            ctx = multiprocessing.get_context(start_method)
            # Ctrl-C: the workers ignore it and are terminated at once (shapecorr.data.workers); the pairs they
            # were running are lost (their files are written atomically), the finished ones are kept
            with process_pool(min(workers, len(todo)), ctx, _init_worker,
                              (shapes, matcher, str(out_dir), settings, threads)) as pool:
                pending = set(submit_all(pool, _run_in_worker, todo))
                while pending:
                    done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                    for future in done:
                        if future.exception() is not None:
                            raise future.exception()
                        bar.update()
    finally:
        bar.close()
    return [load_record(out_dir, a, b)[0] for a, b in names]
