"""Benchmark: peak memory of Deep Shells on a FAUST_r pair (~5k vertices), training and test.

    python benchmarks/deep_shells_memory.py --golden $SHAPECORR_DEEP_SHELLS_GOLDEN [--device cuda]

Two cases, each in a fresh Python process (so that one case's allocations and the allocator's caches do not
count for the other):

- ``train_step``: one training step of :class:`~shapecorr.models.deep_shells.DeepShells` with the published
  network and weights (``pretrained``), 2000 samples per shape and the published shell schedule: forward
  (``training_step``) and backward;
- ``query``: one full test query, :meth:`DeepShells.match` (features at full resolution, the OT level, the
  40-level refinement up to k = 499).

Inputs: the golden FAUST_r pair ``tr_reg_080 -> tr_reg_081`` of ``$SHAPECORR_DEEP_SHELLS_GOLDEN`` (meshes,
510 eigenpairs, SHOT of the original; eigenvalues halved to shapecorr's convention), loaded as in
``benchmarks/deep_shells_parity.py``.

Reported per case: ``peak_rss_mb`` (the child's maximum resident set size, from the parent's ``wait4``),
``baseline_rss_mb`` (resident set after imports, model and data loading, just before the measured operation),
``op_peak_rss_mb`` (high-water mark during the operation alone: Linux's ``VmHWM`` after resetting it through
``/proc/self/clear_refs``; else the process maximum) and ``op_rss_above_baseline_mb`` = op peak - baseline; on
CUDA also ``cuda_max_allocated_mb`` (``torch.cuda.max_memory_allocated`` during the operation, statistics reset
after loading), ``cuda_baseline_allocated_mb`` and their difference. Wall and CPU seconds of the operation are
recorded for orientation (one run, not a timing benchmark). Writes ``benchmarks/results/deep_shells_memory.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "deep_shells_memory.json"
PAIR = "tr_reg_080__tr_reg_081"
WEIGHTS = "published_weights_faust_scape_ep20.pth"
CASES = ("train_step", "query")
#: Deep Shells subsample_num: vertices per shape and training step (released checkpoint ``par``).
TRAIN_SAMPLES = 2000
#: Bytes per MiB (all memory numbers are MiB).
MIB = 2 ** 20


def _maxrss_mb(usage: resource.struct_rusage) -> float:
    # ru_maxrss is in kB on Linux, bytes on macOS
    scale = 1 if sys.platform == "darwin" else 1024
    return usage.ru_maxrss * scale / MIB


def load_samples(golden: Path, device):
    """ShapeSamples of the golden pair (SHOT, 510 eigenpairs in shapecorr's eigenvalue convention)."""
    import numpy as np
    import torch

    from shapecorr.data.datasets import PairSample, ShapeSample
    from shapecorr.data.shape import make_shape
    from shapecorr.nn.spectral_conv import ORIGINAL_EIGENVALUE_FACTOR

    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    samples = []
    for side, name in zip("xy", PAIR.split("__")):
        samples.append(ShapeSample(
            # the golden vertices are already normalized (area 0.44, the original convention): keep them
            shape=make_shape(inputs[f"{side}_verts"], inputs[f"{side}_faces"], name, normalization=None),
            operators={
                "eigenbasis": {
                    "evals": torch.from_numpy(inputs[f"{side}_evals"]) / ORIGINAL_EIGENVALUE_FACTOR,
                    "evecs": torch.from_numpy(inputs[f"{side}_evecs"]),
                    "mass": torch.from_numpy(inputs[f"{side}_mass"]),
                },
                "shot": {"shot": torch.from_numpy(inputs[f"{side}_shot"])},
            },
        ))
    return PairSample(*samples).to(device)


def run_case(case: str, golden: Path, device_name: str, threads: int) -> dict:
    """Child process: load, measure one operation, return the numbers (printed as JSON by ``--child``)."""
    import torch

    from shapecorr.losses.shells import level_energy_loss
    from shapecorr.losses.weighted import WeightedLoss
    from shapecorr.models.deep_shells import DeepShells

    torch.set_num_threads(threads)
    device = torch.device(device_name)
    loss = WeightedLoss({"shells": {"fn": level_energy_loss, "weight": 1.0}})  # configs/model/loss/deep_shells.yaml
    model = DeepShells(num_samples=TRAIN_SAMPLES, loss=loss, pretrained=golden / WEIGHTS).to(device)
    pair = load_samples(golden, device)
    model.train(case == "train_step")
    cuda = device.type == "cuda"
    cuda_base, baseline_kb, reset = bench_common.start_memory_span(device)
    wall, cpu = time.perf_counter(), time.process_time()
    if case == "train_step":
        loss = model.training_step(pair, 0)
        loss.backward()
        info = {"loss": float(loss.detach())}
    else:
        result = model.match(pair.x, pair.y)
        info = {"n_matched": int(result.p2p.numel())}
    if cuda:
        torch.cuda.synchronize(device)
    out = {"case": case, "seconds": time.perf_counter() - wall, "cpu_seconds": time.process_time() - cpu, **info,
           "n_verts": [pair.x.shape.n_verts, pair.y.shape.n_verts]}
    hwm = bench_common.status_kb("VmHWM") if reset else None
    op_peak = hwm / 1024 if hwm is not None else _maxrss_mb(resource.getrusage(resource.RUSAGE_SELF))
    out["op_peak_source"] = "VmHWM after clear_refs" if hwm is not None else "ru_maxrss (process maximum)"
    if baseline_kb is not None:
        out["baseline_rss_mb"] = baseline_kb / 1024
        out["op_peak_rss_mb"] = op_peak
        out["op_rss_above_baseline_mb"] = op_peak - baseline_kb / 1024
    if cuda:
        peak = torch.cuda.max_memory_allocated(device)
        out.update(cuda_baseline_allocated_mb=cuda_base / MIB, cuda_max_allocated_mb=peak / MIB,
                   cuda_above_baseline_mb=(peak - cuda_base) / MIB)
    return out


def measure(case: str, golden: Path, device: str, threads: int) -> dict:
    """Run one case in a fresh subprocess; add its maximum RSS as the parent sees it."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", case, "--golden", str(golden), "--device", device,
           "--threads", str(threads)]
    # files, not pipes: the parent waits with wait4 (for the child's rusage) without reading while it runs
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, cwd=REPO)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        raise RuntimeError(f"case {case} failed (exit {proc.returncode}):\n{stderr[-3000:]}")
    result = json.loads(stdout.strip().splitlines()[-1])
    result["peak_rss_mb"] = _maxrss_mb(usage)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--golden", default=os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN"),
                        help="folder of the golden files (default: $SHAPECORR_DEEP_SHELLS_GOLDEN)")
    parser.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--out", default=str(RESULT))
    parser.add_argument("--child", choices=CASES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not args.golden:
        parser.error("pass --golden or set SHAPECORR_DEEP_SHELLS_GOLDEN")
    golden = Path(args.golden)
    if args.child:
        import torch

        threads = args.threads or torch.get_num_threads()
        print(json.dumps(run_case(args.child, golden, args.device, threads)), flush=True)
        return 0
    if not (golden / f"inputs_{PAIR}.npz").is_file() or not (golden / WEIGHTS).is_file():
        parser.error(f"{golden} lacks inputs_{PAIR}.npz or {WEIGHTS}")
    import torch

    threads = args.threads or torch.get_num_threads()
    report = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {**bench_common.machine_info(), "torch_threads": threads,
                    "omp_num_threads": os.environ.get("OMP_NUM_THREADS")},
        "settings": {"pair": PAIR, "device": args.device, "train_samples": TRAIN_SAMPLES, "weights": WEIGHTS,
                     "network": "published SpectralFilterBank 352 -> 120, 200 eigenpairs",
                     "query": "features + OT level k=6 + 40 refinement levels 6..499 (model defaults)",
                     "units": "MiB (2^20 bytes); seconds"},
        "cases": {},
    }
    for case in args.cases:
        result = measure(case, golden, args.device, threads)
        report["cases"][case] = result
        print(case, json.dumps(result, indent=1), flush=True)
    report["machine"]["load_average_after"] = list(os.getloadavg())
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
