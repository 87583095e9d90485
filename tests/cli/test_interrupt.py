"""Ctrl-C during ``evaluate.py workers=2``: the run stops promptly, reports the true count and never hangs.

A real process receives SIGINT on its whole process group (what a terminal's Ctrl-C does). The matcher is a
stand-in written to a temporary module: pairs onto shape ``a`` are instant, every other pair sleeps a minute, so a
run that waited for its running pairs (or hung) would exceed the time limit by far.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
NAMES = ["a", "b", "c", "d"]
SLOW_MATCHER = '''
import time
import torch
from shapecorr.matching.result import MatchResult


class SlowMatcher:
    needs_ground_truth = False
    required_operators = {}

    def match(self, x, y):
        if y.name != "a":
            time.sleep(60.0)
        n_x, n_y = x.shape.n_verts, y.shape.n_verts
        return MatchResult(p2p=torch.arange(n_x) % n_y)
'''
#: Seconds from the last Ctrl-C to the end of the process that count as prompt (a pair takes 60 s).
PROMPT_S = 15.0


def _wait_for_records(folder: Path, count: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if len(list(folder.glob("*.json"))) >= count:
            return
        if proc.poll() is not None:
            pytest.fail(f"evaluate.py ended early: {proc.communicate()[1][-2000:]}")
        time.sleep(0.2)
    pytest.fail(f"fewer than {count} records after {timeout} s")


@pytest.mark.slow
@pytest.mark.parametrize("presses, start", [(1, "spawn"), (2, "spawn"), (2, "fork")],
                         ids=["one Ctrl-C", "two Ctrl-C", "two Ctrl-C, fork"])
def test_ctrl_c_with_workers_stops_promptly(tmp_path, bent_sphere_folder, presses, start):
    root = bent_sphere_folder(tmp_path / "data", NAMES)
    (tmp_path / "slow_matcher.py").write_text(SLOW_MATCHER)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO)]), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, str(REPO / "evaluate.py"), "+model._target_=slow_matcher.SlowMatcher", "data=folder",
           f"data.root={root}", f"paths.cache_dir={tmp_path / 'cache'}", f"output_dir={out}", "progress=false",
           "n_examples=0", "data.operators.n_eig=20", "workers=2", f"start_method={start}", "write_maps=false",
           f"hydra.run.dir={tmp_path / 'hydra'}"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        _wait_for_records(out / "pairs", 3, proc)  # the three pairs onto "a"; the workers now sleep in others
        time.sleep(1.0)
        for _ in range(presses):
            os.killpg(proc.pid, signal.SIGINT)
            time.sleep(0.5)
        t0 = time.monotonic()
        _, stderr = proc.communicate(timeout=PROMPT_S + 30)
        elapsed = time.monotonic() - t0
        print(f"stopped {elapsed:.1f} s after the last Ctrl-C")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr[-2000:]
    assert elapsed < PROMPT_S, f"took {elapsed:.1f} s to stop"
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr[-2000:]
    done = len(list((out / "pairs").glob("*.json")))
    assert done == 3
    assert f"interrupted: {done} of {len(NAMES) * (len(NAMES) - 1)} pairs done" in stderr
    time.sleep(2.0)  # no worker outlived the run: nothing more is written
    assert len(list((out / "pairs").glob("*.json"))) == done
