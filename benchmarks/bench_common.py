"""Helpers shared by the benchmark scripts: machine description, package versions, timing.

Imported by the scripts in this folder as ``from bench_common import ...`` (a script's own folder is first on
``sys.path`` when it is run as ``python benchmarks/<name>.py``).
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from importlib import metadata
from pathlib import Path

#: Distributions whose versions every result records (a script may add its own).
DEFAULT_PACKAGES = ("numpy", "scipy", "torch", "libigl", "potpourri3d", "robust-laplacian", "gpytoolbox",
                    "trimesh", "threadpoolctl", "pytorch-lightning", "hydra-core", "shapecorr")


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def package_versions(packages=DEFAULT_PACKAGES) -> dict[str, str | None]:
    """Installed versions of ``packages`` (None for a missing one), plus Python's."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for dist in packages:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def gpu_name() -> str | None:
    """Name of CUDA device 0, or None."""
    try:
        import torch

        return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    except Exception:  # noqa: BLE001 - a broken CUDA setup simply means "no GPU" here
        return None


def machine_info(packages=DEFAULT_PACKAGES) -> dict:
    """CPU, cores, platform, GPU, current load average (timings on a shared machine are inflated when it
    exceeds the core count) and package versions."""
    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "gpu": gpu_name(),
        "load_average_1_5_15min": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "versions": package_versions(packages),
    }


def timed(fn, repeats: int, warmup=None):
    """Run ``warmup`` (default ``fn``) once, then ``fn`` ``repeats`` times.

    Returns
    -------
    walls, cpus : list[float]
        Wall-clock and process-CPU seconds of every timed run.
    result
        What the last call of ``fn`` returned.
    """
    result = (warmup or fn)()
    walls, cpus = [], []
    for _ in range(repeats):
        wall0, cpu0 = time.perf_counter(), time.process_time()
        result = fn()
        walls.append(time.perf_counter() - wall0)
        cpus.append(time.process_time() - cpu0)
    return walls, cpus, result


#: Linux /proc/<pid>/clear_refs value that resets the peak resident set size (VmHWM), Documentation/filesystems/proc.
CLEAR_PEAK_RSS = "5"


def status_kb(field: str) -> int | None:
    """A ``kB`` field of /proc/self/status (VmRSS, VmHWM), or None off Linux."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


def reset_peak_rss() -> bool:
    """Reset this process's peak resident set (``VmHWM``) to its current size; False where that is unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text(CLEAR_PEAK_RSS)
    except OSError:
        return False
    return status_kb("VmHWM") is not None


def start_memory_span(device) -> tuple[int | None, int | None, bool]:
    """Start measuring peak memory: CUDA statistics reset (on a CUDA ``device``), the peak resident set reset.

    Returns ``cuda_base`` (bytes allocated now on CUDA, else None), ``baseline_kb`` (resident set now) and whether
    the peak resident set could be reset (then ``status_kb("VmHWM")`` later is the peak of the span).
    """
    cuda_base = None
    if device.type == "cuda":
        import torch

        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        cuda_base = torch.cuda.memory_allocated(device)
    return cuda_base, status_kb("VmRSS"), reset_peak_rss()


def median(values) -> float:
    return float(statistics.median(values))


def write_report(path, report: dict) -> Path:
    """Write ``report`` as indented JSON to ``path`` (parent folders created) and say so; returns the path."""
    import json

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {path}")
    return path


def summary_report(script: str, argv: list[str], summary: dict) -> dict:
    """A training benchmark's report: ``command`` (``script`` and its arguments), ``date``, ``machine``, then
    the keys of ``summary``."""
    import datetime

    return {"command": " ".join([script, *argv]), "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "machine": machine_info(), **summary}


def run_command(cmd: list[str], threads: int, cwd) -> None:
    """Run ``cmd`` in ``cwd`` with ``OMP_NUM_THREADS=threads``, echoing it; exit with a message if it fails."""
    import subprocess
    import sys

    print("$", " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, cwd=cwd, env={**os.environ, "OMP_NUM_THREADS": str(threads)}, check=False)
    if proc.returncode != 0:
        sys.exit(f"command failed with status {proc.returncode}: {' '.join(cmd)}")


def run_json_child(cmd: list[str], env: dict, timeout: float, cwd) -> dict:
    """Run one measuring process and return the JSON record of its last output line, with the 1-minute load
    average before and after it; ``{"error": <last stderr line>}`` when it fails."""
    import json
    import subprocess

    load_before = os.getloadavg()[0]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout, cwd=cwd)
    if proc.returncode != 0:
        lines = proc.stderr.strip().splitlines()
        return {"error": lines[-1] if lines else f"exit {proc.returncode}", "load_average_1min_before": load_before}
    record = json.loads(proc.stdout.strip().splitlines()[-1])
    record.update(load_average_1min_before=load_before, load_average_1min_after=os.getloadavg()[0])
    return record


def side_by_side_summary(records: list[dict], cases, codes) -> dict:
    """Per case and code: the median over the processes of each process's median CPU seconds, the medians of the
    peak resident sets, the number of processes, and for every code but ``"original"`` the ratio of the original's
    median to its own (``ratio_original_over_this``)."""
    summary = {}
    for case in cases:
        per_code = {}
        for code in codes:
            ok = [r for r in records if r["case"] == case and r["code"] == code and "error" not in r]
            if ok:
                per_code[code] = {"cpu_seconds_per_process": [r["cpu_seconds_median"] for r in ok],
                                  "cpu_seconds_median": statistics.median(r["cpu_seconds_median"] for r in ok),
                                  "process_max_rss_mb_median": statistics.median(r["process_max_rss_mb"] for r in ok),
                                  "processes": len(ok)}
                if all("peak_rss_mb" in r for r in ok):
                    per_code[code]["peak_rss_mb_median"] = statistics.median(r["peak_rss_mb"] for r in ok)
        if "original" in per_code:
            for code, entry in per_code.items():
                if code != "original":
                    entry["ratio_original_over_this"] = (per_code["original"]["cpu_seconds_median"]
                                                         / entry["cpu_seconds_median"])
        summary[case] = per_code
    return summary
