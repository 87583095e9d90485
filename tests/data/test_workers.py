"""Worker pools (shapecorr.data.workers): no worker outlives its parent, a second Ctrl-C cannot skip the stop."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from shapecorr.data import workers

REPO = Path(__file__).resolve().parents[2]
ORPHAN_SCRIPT = '''
import os, signal, sys, time
from pathlib import Path
from shapecorr.data.workers import process_pool, submit_all

def sleep_and_report(path):
    Path(path).write_text(str(os.getpid()))
    time.sleep(120.0)

if __name__ == "__main__":
    pid_file = Path(sys.argv[1])
    with process_pool(1) as pool:
        submit_all(pool, sleep_and_report, [(str(pid_file),)])
        while not pid_file.exists() or not pid_file.read_text():
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGKILL)  # the parent dies without any clean-up
'''


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return fields[0] != "Z"


def _sleep(seconds: float) -> None:
    time.sleep(seconds)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads process states from /proc (Linux only)")
def test_worker_exits_when_its_parent_is_killed(tmp_path):
    pid_file = tmp_path / "worker.pid"
    (tmp_path / "orphan.py").write_text(ORPHAN_SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, str(tmp_path / "orphan.py"), str(pid_file)], env=env, timeout=120,
                          capture_output=True, text=True)
    assert proc.returncode == -9, proc.stderr[-2000:]
    worker = int(pid_file.read_text())
    deadline = time.monotonic() + 10 * workers.PARENT_CHECK_S + 5.0
    while _running(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = _running(worker)
    if alive:
        os.kill(worker, 9)
    assert not alive, "the worker kept running after its parent was killed"


def test_a_ctrl_c_before_the_stop_ignores_it_still_stops_the_workers(monkeypatch):
    real = workers.sigint_ignored
    calls = []

    @contextmanager
    def interrupted_once():
        calls.append(1)
        if len(calls) == 1:  # the second Ctrl-C lands before SIGINT is ignored
            raise KeyboardInterrupt
        with real():
            yield

    monkeypatch.setattr(workers, "sigint_ignored", interrupted_once)
    context = multiprocessing.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    with pytest.raises(KeyboardInterrupt), workers.process_pool(2, context) as pool:
        futures = [pool.submit(_sleep, 60.0) for _ in range(4)]
        while not any(f.running() for f in futures):
            time.sleep(0.05)
        processes = list(pool._processes.values())
        raise KeyboardInterrupt
    assert len(calls) == 2
    assert processes and not any(p.is_alive() for p in processes)
