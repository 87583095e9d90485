"""Thread counts of a run: the ``threads`` option of ``train.py``, ``evaluate.py`` and ``data_prep/prepare.py``.

One number, the threads of each process, sets torch's intra-op threads and the thread pools of the BLAS and
OpenMP libraries (through their environment variables, read when the libraries load, and through
``threadpoolctl`` for libraries already loaded). ``threads=null`` (the default) divides the available cores
that other processes leave free (the cores minus the whole part of the 1-minute load average) among the
processes of the run: ``free // workers`` (at least 1) for ``workers`` worker processes, all free cores without
workers, so the run never starts more busy threads than there are cores; an ``OMP_NUM_THREADS`` set by the user
is kept then (lowered to that share). Spawned workers inherit the environment variables, so each gets the same
share.

Why it matters: torch's own default (one thread per core) on top of OpenBLAS's own pool (one per core again)
oversubscribes a small machine; OpenMP threads then spin waiting for each other and a run can be several times
slower than with fewer threads (docs/benchmarks.md, "Threads").
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from shapecorr.errors import ConfigError

#: Environment variables of the thread pools: OpenMP (torch's intra-op pool, libigl), the BLAS libraries.
THREAD_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "BLIS_NUM_THREADS",
                   "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask; the CPU count where that is unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def free_cores(cores: int | None = None, load: float | None = None) -> int:
    """The cores not busy with other processes: ``cores`` minus the whole part of the 1-minute load average.

    At least 1. ``load`` defaults to :func:`os.getloadavg` (0 where the platform has none).
    """
    cores = available_cores() if cores is None else cores
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):  # not available (Windows)
            load = 0.0
    return max(1, cores - int(load))


def threads_per_process(threads, workers=0, cores: int | None = None,
                        environ: Mapping[str, str] | None = None, load: float | None = None) -> int:
    """The threads each process of a run uses.

    Parameters
    ----------
    threads : int or None
        The ``threads`` option: a positive count, or None (``null``/``auto``) for the default share.
    workers : int or None
        Worker processes that compute side by side (``workers=``); 0 or None: this process alone.
    cores : int, optional
        Available cores (default :func:`available_cores`).
    load : float, optional
        1-minute load average of the machine (default :func:`os.getloadavg`): the default share counts only the
        cores other processes leave free (:func:`free_cores`).
    environ : mapping, optional
        Environment (default ``os.environ``): with ``threads`` None, a positive ``OMP_NUM_THREADS`` set by the
        user is kept, lowered to the share when it is larger.

    Raises
    ------
    ConfigError
        ``threads`` or ``workers`` is not a non-negative integer (``threads`` positive).
    """
    workers = _count(workers, "workers", minimum=0)
    share = max(1, free_cores(cores, load) // max(1, workers))
    if threads is None or (isinstance(threads, str) and threads.strip().lower() in ("auto", "null", "")):
        environ = os.environ if environ is None else environ
        try:
            user = int(environ.get("OMP_NUM_THREADS", ""))
        except ValueError:
            user = 0
        return min(user, share) if user > 0 else share
    return _count(threads, "threads", minimum=1)


def _count(value, name: str, minimum: int) -> int:
    if value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    try:
        number = int(value)
    except ValueError:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}") from None
    if number < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return number


def set_thread_environment(n: int) -> None:
    """Set the thread variables of :data:`THREAD_ENV_VARS` to ``n``.

    Libraries read them when they load and worker processes inherit them, so this takes full effect before torch
    and numpy are imported (the entry scripts call it first).
    """
    for name in THREAD_ENV_VARS:
        os.environ[name] = str(n)


def limit_threads(n: int) -> None:
    """Use ``n`` threads in this process from now on: environment, torch, and the loaded BLAS/OpenMP pools."""
    import torch

    set_thread_environment(n)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional at run time: the environment variables still hold for later loads
        return
    threadpool_limits(limits=n)


def configure_threads(cfg) -> int:
    """Apply the ``threads`` / ``workers`` options of a run config ``cfg``; returns the threads per process.

    ``workers`` is the run's worker-process count: ``workers`` (evaluate.py, prepare.py); train.py has none
    (its data-loader workers run one thread each, as torch sets them).
    """
    n = threads_per_process(cfg.get("threads"), cfg.get("workers") or 0)
    limit_threads(n)
    return n
