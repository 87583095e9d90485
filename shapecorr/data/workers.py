"""Worker process pools that stop at once on Ctrl-C.

A terminal's Ctrl-C sends SIGINT to every process of the foreground group: the parent and its workers. With a plain
:class:`~concurrent.futures.ProcessPoolExecutor` each worker then prints its own ``KeyboardInterrupt`` traceback,
and leaving the executor's ``with`` block waits for the running jobs (minutes for a large shape), so a second
Ctrl-C lands in that wait and can leave the process hanging. Here:

* workers start with SIGINT ignored (:func:`submit_all` ignores it in the parent while the workers are created:
  an ignored signal stays ignored across ``fork`` and ``exec``), so only the parent sees Ctrl-C;
* :func:`process_pool` terminates the workers when the parent is interrupted (their unfinished jobs are lost; what
  they wrote is atomic, so nothing partial remains) and re-raises the ``KeyboardInterrupt``; a second Ctrl-C during
  that clean-up is ignored, also one that lands before the clean-up could ignore it (the clean-up then starts over);
* every worker exits by itself within :data:`PARENT_CHECK_S` seconds once the process that started it is gone
  (whatever ended it), so no orphaned worker keeps running, holding memory or the terminal's pipes.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

#: Seconds a terminated worker gets to exit before it is killed.
TERMINATE_GRACE_S = 5.0
#: Seconds between a worker's checks that the process that started it is still there.
PARENT_CHECK_S = 1.0


@contextmanager
def sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT (Ctrl-C) in this process for the duration of the block (main thread only; else a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def submit_all(pool: ProcessPoolExecutor, fn: Callable, jobs: Iterable[Sequence[Any]]) -> list[Future]:
    """``[pool.submit(fn, *job) for job in jobs]`` with Ctrl-C ignored while the workers start (they inherit it)."""
    with sigint_ignored():
        return [pool.submit(fn, *job) for job in jobs]


def _exit_when_orphaned(parent_pid: int) -> None:
    """Worker thread: end this process at once when its parent ``parent_pid`` is gone (it was re-parented)."""
    while os.getppid() == parent_pid:
        time.sleep(PARENT_CHECK_S)
    os._exit(1)


def _start_worker(initializer: Callable | None, initargs: tuple) -> None:
    """Worker initializer: watch the parent (:func:`_exit_when_orphaned`), then run the caller's ``initializer``."""
    threading.Thread(target=_exit_when_orphaned, args=(os.getppid(),), name="exit-when-orphaned",
                     daemon=True).start()
    if initializer is not None:
        initializer(*initargs)


def stop_workers(pool: ProcessPoolExecutor, processes: list | None = None) -> None:
    """Cancel the queued jobs of ``pool`` and terminate its worker processes (killed after a grace period).

    ``processes``: the workers to stop (default: the pool's current ones; pass them when the pool may already have
    been shut down, which forgets them).
    """
    if processes is None:
        processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(TERMINATE_GRACE_S)
        if process.is_alive():
            process.kill()
            process.join(TERMINATE_GRACE_S)


@contextmanager
def process_pool(max_workers: int, mp_context=None, initializer: Callable | None = None,
                 initargs: tuple = ()) -> Iterator[ProcessPoolExecutor]:
    """A :class:`~concurrent.futures.ProcessPoolExecutor` that stops its workers at once on Ctrl-C.

    Submit with :func:`submit_all` (workers that ignore Ctrl-C). On ``KeyboardInterrupt`` inside the block the
    workers are terminated (a second Ctrl-C meanwhile is ignored) and the interrupt is re-raised; on another error
    the queued jobs are cancelled and the running ones finish; otherwise the pool is shut down normally.
    """
    pool = ProcessPoolExecutor(max_workers=max_workers, mp_context=mp_context, initializer=_start_worker,
                               initargs=(initializer, initargs))
    try:
        yield pool
    except KeyboardInterrupt:
        _stop_after_interrupt(pool)
        raise
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _stop_after_interrupt(pool: ProcessPoolExecutor) -> None:
    """:func:`stop_workers` with Ctrl-C ignored; a Ctrl-C that lands before it is ignored starts the stop over."""
    processes = None
    while True:
        try:
            with sigint_ignored():
                if processes is None:
                    processes = list((getattr(pool, "_processes", None) or {}).values())
                stop_workers(pool, processes)
            return
        except KeyboardInterrupt:  # a second Ctrl-C arrived before SIGINT was ignored
            continue
