import pytest

from shapecorr.cli.threads import THREAD_ENV_VARS, free_cores, set_thread_environment, threads_per_process
from shapecorr.errors import ConfigError


@pytest.mark.parametrize("threads, workers, cores, load, environ, expected", [
    (None, 0, 2, 0.0, {}, 2),           # idle 2-core machine, one process: both cores
    (None, 0, 2, 1.5, {}, 1),           # one core busy with another job
    (None, 0, 2, 9.0, {}, 1),           # heavily loaded: never below one
    (None, 2, 2, 0.0, {}, 1),           # two workers share the two cores
    (None, 3, 8, 0.0, {}, 2),           # 8 cores among 3 workers
    (None, 0, 8, 0.0, {"OMP_NUM_THREADS": "3"}, 3),   # the user's variable is kept ...
    (None, 4, 8, 0.0, {"OMP_NUM_THREADS": "6"}, 2),   # ... but never above the share
    ("auto", 0, 4, 0.0, {}, 4),
    (3, 0, 2, 0.0, {}, 3),              # an explicit count is taken as given
    ("2", 2, 2, 5.0, {}, 2),
])
def test_threads_per_process(threads, workers, cores, load, environ, expected):
    assert threads_per_process(threads, workers, cores=cores, environ=environ, load=load) == expected


@pytest.mark.parametrize("threads, workers", [(0, 0), (-1, 0), ("many", 0), (True, 0), (1.5, 0), (None, -1)])
def test_bad_counts_are_config_errors(threads, workers):
    with pytest.raises(ConfigError):
        threads_per_process(threads, workers, cores=2, environ={}, load=0.0)


def test_free_cores():
    assert free_cores(4, 0.9) == 4 and free_cores(4, 2.2) == 2 and free_cores(2, 7.0) == 1


def test_set_thread_environment(monkeypatch):
    for name in THREAD_ENV_VARS:
        monkeypatch.delenv(name, raising=False)
    set_thread_environment(3)
    import os

    assert all(os.environ[name] == "3" for name in THREAD_ENV_VARS)
