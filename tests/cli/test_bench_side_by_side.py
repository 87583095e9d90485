"""The side-by-side summary of ``benchmarks/bench_common.py``: medians over processes, ratios, failed processes left
out (the originals' comparison scripts report through it)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH_COMMON = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_common.py"


@pytest.fixture(scope="module")
def bench_common():
    spec = importlib.util.spec_from_file_location("bench_common_under_test", BENCH_COMMON)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _record(code, cpu, rss, **extra):
    return {"case": "unit", "code": code, "cpu_seconds_median": cpu, "process_max_rss_mb": rss, **extra}


def test_summary_medians_ratio_and_failed_processes(bench_common):
    records = [_record("original", 9.0, 3000.0), _record("ours", 0.5, 500.0, peak_rss_mb=400.0),
               _record("original", 8.0, 3200.0), _record("ours", 0.4, 520.0, peak_rss_mb=420.0),
               _record("original", 10.0, 3100.0), _record("ours", 0.3, 510.0, peak_rss_mb=410.0),
               {"case": "unit", "code": "ours", "error": "killed"},
               _record("original", 1.0, 1.0, case="other")]
    summary = bench_common.side_by_side_summary(records, ["unit"], ["original", "ours"])
    original, ours = summary["unit"]["original"], summary["unit"]["ours"]
    assert original["cpu_seconds_median"] == 9.0 and original["processes"] == 3
    assert original["process_max_rss_mb_median"] == 3100.0 and "peak_rss_mb_median" not in original
    assert ours["cpu_seconds_per_process"] == [0.5, 0.4, 0.3] and ours["peak_rss_mb_median"] == 410.0
    assert ours["ratio_original_over_this"] == pytest.approx(9.0 / 0.4)
    assert "ratio_original_over_this" not in original


def test_run_json_child_reads_the_last_line_and_reports_failures(bench_common, tmp_path):
    ok = [sys.executable, "-c", "print('noise'); print('{\"cpu_seconds_median\": 1.5}')"]
    record = bench_common.run_json_child(ok, {}, 60, tmp_path)
    assert record["cpu_seconds_median"] == 1.5 and "load_average_1min_after" in record
    bad = [sys.executable, "-c", "import sys; sys.exit('error: no original here')"]
    assert bench_common.run_json_child(bad, {}, 60, tmp_path)["error"] == "error: no original here"
