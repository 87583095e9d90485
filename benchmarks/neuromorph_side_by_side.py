"""Benchmark: one NeuroMorph training step, the original code and shapecorr side by side on identical inputs.

    python benchmarks/neuromorph_side_by_side.py --original /tmp/nm_orig --shim /tmp/nm_shim [--rounds 3]
        [--repeats 2] [--cases neuromorph_train_t0 neuromorph_train_t7] [--out benchmarks/results/...json]

``--original``: a checkout of the original NeuroMorph code (github.com/marvin-eisenberger/neuromorph, the
facebookresearch release), outside this repository. ``--shim``: a folder, also outside the repository, holding a
stand-in ``torch_geometric`` package for what the original imports from PyTorch Geometric: ``nn.EdgeConv`` (PyG
semantics: message ``nn([x_i, x_j - x_i])`` for every column of the edge index, duplicates included, max
aggregation), ``nn.knn_graph`` and ``nn.fps`` (imported, not called by a training step on a full mesh).
docs/speed.md §3 describes it. Nothing of the original is part of this project; this script only imports it
from the given folders in a child process.

Protocol:

* Inputs: :func:`speed.neuromorph_inputs` (the golden FAUST_r pair ``tr_reg_080 -> tr_reg_081`` remeshed to ~2000
  vertices per shape, heat-method geodesic matrices), computed once and written to one ``.npz`` that every
  child reads: both codes receive the same vertices, faces and distance matrices.
* Unit: one training step of one pair at the published settings, forward + backward + Adam step. T = 0 with the
  geodesic weight 50, T = 7 with weight 0 (the published schedule). The original's step builds its ``Shape``
  objects (normals, edge lists) from the arrays in the step, as its training loop does for every pair;
  shapecorr's step is ``benchmarks/speed.py``'s case of the same name (``training_step`` + backward + Adam).
* Each measurement is a fresh process, one thread (``OMP_NUM_THREADS=1``, ``torch.set_num_threads(1)``), one
  warm-up step then ``--repeats`` timed steps (process CPU time and wall time, their medians). The processes
  alternate, original then shapecorr, ``--rounds`` times per case; the summary is the median over the
  processes of each code. Peak memory: the process's maximum resident set (``ru_maxrss``, imports included),
  and its peak over the timed span (``VmHWM`` reset after the inputs are loaded).
* ``--no-mmap-variant`` adds a third process per round: shapecorr's step again with glibc told to keep freed
  large blocks (``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``, ``benchmarks/neuromorph_speed.py``'s
  ``--malloc no-mmap``): the same computation, without the page faults of a fresh ``mmap`` per large tensor.
* Before the timing, ``--check-golden`` (default ``$SHAPECORR_NEUROMORPH_GOLDEN``, then the shared copy) runs
  the original with the shim on a golden pair with the golden weights and compares its total loss and soft map
  with the stored outputs of the original: the shim must not change the original's numbers.

Writes ``benchmarks/results/neuromorph_side_by_side.json`` (``--out``) with the command, date, machine and the load
average before and after every process.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_common
import speed

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "neuromorph_side_by_side.json"
DEFAULT_NEUROMORPH_GOLDEN = Path("/work/shared/data/reference/neuromorph_golden")
#: Golden pair used to check that the original runs unchanged with the shim.
CHECK_PAIR = "tr_reg_000__tr_reg_013"
CASES = tuple(speed.NEUROMORPH_SETTINGS)
#: The codes compared: the original, shapecorr, and shapecorr with glibc keeping freed blocks (optional).
CODES = ("original", "shapecorr", "shapecorr_no_mmap")


def _import_original(original: Path, shim: Path):
    """The original's module, energy and Shape classes (imported from ``original``, PyG parts from ``shim``)."""
    sys.path[:0] = [str(shim), str(original)]
    from model.interpolation_net import InterpolationModGeoEC, NetParam
    from utils.arap_interpolation import ArapInterpolationEnergy
    from utils.shape_utils import Shape

    return InterpolationModGeoEC, NetParam, ArapInterpolationEnergy, Shape


def _original_module(original: Path, shim: Path, n_intermediate: int, lambda_geo: float):
    """The original's ``InterpolationModGeoEC`` with T and the geodesic weight set, and its ``Shape`` class."""
    module_cls, param_cls, energy_cls, shape_cls = _import_original(original, shim)
    param = param_cls()
    param.num_timesteps, param.lambd_geo = n_intermediate, lambda_geo
    return module_cls(energy_cls(), param), shape_cls


def run_original_child(case: str, original: Path, shim: Path, inputs: Path, repeats: int) -> dict:
    """Time the original's training step in this process (one thread)."""
    import resource

    import numpy as np

    import torch

    torch.set_num_threads(1)
    setting = speed.NEUROMORPH_SETTINGS[case]
    torch.manual_seed(0)
    module, shape_cls = _original_module(original, shim, setting["n_intermediate"], setting["lambda_geo"])
    module.train()
    optimizer = torch.optim.Adam(module.parameters(), lr=module.param.lr)
    with np.load(inputs) as arrays:
        data = {key: torch.from_numpy(arrays[key]) for key in arrays.files}

    def shape(side):  # per pair, as the original's training loop builds them (batch_to_shape)
        s = shape_cls(data[f"verts_{side}"], data[f"faces_{side}"])
        s.D = data[f"dist_{side}"]
        return s

    def step():
        optimizer.zero_grad()
        loss, _ = module(shape("x"), shape("y"))
        loss.backward()
        optimizer.step()
        return float(loss.detach())

    _, baseline_kb, reset = bench_common.start_memory_span(torch.device("cpu"))
    walls, cpus, value = bench_common.timed(step, repeats)
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    hwm = bench_common.status_kb("VmHWM") if reset else None
    return {"code": "original", "case": case, "seconds": walls, "cpu_seconds": cpus,
            "seconds_median": statistics.median(walls), "cpu_seconds_median": statistics.median(cpus),
            "value": value, "process_max_rss_mb": maxrss / 1024, "peak_rss_mb": (hwm or maxrss) / 1024,
            "baseline_rss_mb": (baseline_kb or 0) / 1024,
            "n_verts": [int(data["verts_x"].shape[0]), int(data["verts_y"].shape[0])]}


def run_original_check(original: Path, shim: Path, golden: Path) -> dict:
    """The original (with the shim) on a golden pair and the golden weights, against its stored outputs."""
    import numpy as np

    import torch

    torch.set_num_threads(1)
    module, shape_cls = _original_module(original, shim, 0, 50.0)
    with np.load(golden / "weights_seed0.npz") as weights:
        module.load_state_dict({key: torch.from_numpy(weights[key]) for key in weights.files}, strict=True)
    inputs, outputs = np.load(golden / f"inputs_{CHECK_PAIR}.npz"), np.load(golden / f"outputs_{CHECK_PAIR}.npz")
    shapes = []
    for side in "xy":
        s = shape_cls(torch.from_numpy(inputs[f"verts_{side}"]), torch.from_numpy(inputs[f"faces_{side}"]))
        s.D = torch.from_numpy(inputs[f"geodesic_{side}"])
        shapes.append(s)
    loss, _ = module(*shapes)
    pi = module.Pi.detach().numpy()
    expected = float(outputs["loss_total"])
    loss = float(loss.detach())
    return {"pair": CHECK_PAIR, "loss_total": loss, "loss_total_golden": expected,
            "loss_total_relative_difference": abs(loss - expected) / abs(expected),
            "pi_max_abs_difference": float(np.abs(pi - outputs["Pi"]).max())}


# ----------------------------------------------------------------------------------------------------------
# Parent: alternating processes
# ----------------------------------------------------------------------------------------------------------
def _run(cmd: list[str], timeout: float, extra_env: dict | None = None) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", **(extra_env or {}))
    load_before = os.getloadavg()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, env=env, timeout=timeout)
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"
        raise SystemExit(f"error: {' '.join(cmd)}: {tail}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["load_average_before_after"] = [list(load_before), list(os.getloadavg())]
    return result


def _summary(results: list[dict]) -> dict:
    out = {}
    for case in {r["case"] for r in results}:
        entry = {}
        for code in CODES:
            runs = [r for r in results if r["case"] == case and r["code"] == code]
            if not runs:
                continue
            entry[code] = {
                "cpu_seconds_per_process": [r["cpu_seconds_median"] for r in runs],
                "cpu_seconds_median": statistics.median(r["cpu_seconds_median"] for r in runs),
                "wall_seconds_median": statistics.median(r["seconds_median"] for r in runs),
                "process_max_rss_mb_median": statistics.median(r["process_max_rss_mb"] for r in runs),
                "span_peak_rss_mb_median": statistics.median(r["peak_rss_mb"] for r in runs),
            }
        per_round = [o["cpu_seconds_median"] / s["cpu_seconds_median"] for o, s in zip(
            [r for r in results if r["case"] == case and r["code"] == "original"],
            [r for r in results if r["case"] == case and r["code"] == "shapecorr"])]
        entry["ratio_cpu_medians"] = entry["original"]["cpu_seconds_median"] / entry["shapecorr"]["cpu_seconds_median"]
        entry["ratio_per_round"] = per_round
        entry["memory_ratio_process_max"] = (entry["original"]["process_max_rss_mb_median"]
                                             / entry["shapecorr"]["process_max_rss_mb_median"])
        if "shapecorr_no_mmap" in entry:
            entry["ratio_cpu_medians_no_mmap"] = (entry["original"]["cpu_seconds_median"]
                                                  / entry["shapecorr_no_mmap"]["cpu_seconds_median"])
        entry["target_ratio"] = speed.TARGET_RATIO[case]
        out[case] = entry
    return dict(sorted(out.items()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--original", type=Path, required=False, help="checkout of the original NeuroMorph code")
    parser.add_argument("--shim", type=Path, required=False, help="folder with the stand-in torch_geometric package")
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--rounds", type=int, default=3, help="processes per code and case (alternating)")
    parser.add_argument("--repeats", type=int, default=2, help="timed steps per process (after one warm-up)")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--check-golden", type=Path, default=None,
                        help="neuromorph_golden folder (default $SHAPECORR_NEUROMORPH_GOLDEN, then the shared copy)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per process")
    parser.add_argument("--no-mmap-variant", action="store_true",
                        help="also time shapecorr with glibc keeping freed large blocks (see above)")
    parser.add_argument("--out", type=Path, default=RESULT)
    parser.add_argument("--original-child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--original-check", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--inputs", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.original is None or args.shim is None:
        parser.error("--original and --shim are required")
    for folder in (args.original, args.shim):
        if str(folder.resolve()).startswith(str(REPO)):
            parser.error(f"{folder}: keep the original code and its shims outside the repository")
    check_golden = args.check_golden or Path(os.environ.get("SHAPECORR_NEUROMORPH_GOLDEN", DEFAULT_NEUROMORPH_GOLDEN))
    if args.original_child:
        print(json.dumps(run_original_child(args.original_child, args.original, args.shim, args.inputs,
                                            args.repeats)))
        return 0
    if args.original_check:
        print(json.dumps(run_original_check(args.original, args.shim, check_golden)))
        return 0
    # imported here, not at the top: the original's child processes run this script and should load no more
    # than they need (their peak memory is measured)
    from neuromorph_speed import GLIBC_NO_MMAP_ENV as no_mmap_env

    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", speed.DEFAULT_GOLDEN))
    me = [sys.executable, str(Path(__file__).resolve()), "--original", str(args.original), "--shim", str(args.shim)]
    check = None
    if (check_golden / f"outputs_{CHECK_PAIR}.npz").is_file():
        check = _run([*me, "--original-check", "--check-golden", str(check_golden)], args.timeout)
        print(f"original with the shim on {CHECK_PAIR}: loss {check['loss_total']:.6f} (golden "
              f"{check['loss_total_golden']:.6f}), Pi max abs difference {check['pi_max_abs_difference']:.2e}",
              flush=True)
    results = []
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        inputs = Path(tmp) / "neuromorph_pair.npz"
        arrays = speed.neuromorph_inputs(golden, inputs)
        for case in args.cases:
            for round_ in range(args.rounds):
                commands = {
                    "original": [*me, "--original-child", case, "--inputs", str(inputs), "--repeats",
                                 str(args.repeats)],
                    "shapecorr": speed.child_command(case, golden, "cpu", 1, args.repeats,
                                                     neuromorph_inputs_path=inputs),
                }
                if args.no_mmap_variant:
                    commands["shapecorr_no_mmap"] = commands["shapecorr"]
                for code, cmd in commands.items():
                    start = time.perf_counter()
                    extra_env = no_mmap_env if code == "shapecorr_no_mmap" else None
                    result = _run(cmd, args.timeout, extra_env)
                    result["extra_env"] = extra_env
                    result.update(code=code, round=round_, process_seconds=time.perf_counter() - start)
                    results.append(result)
                    print(f"{case} round {round_} {code:17s}: cpu {result['cpu_seconds_median']:.2f} s, wall "
                          f"{result['seconds_median']:.2f} s, max RSS {result['process_max_rss_mb']:.0f} MB, load "
                          f"{result['load_average_before_after'][0][0]:.2f}", flush=True)
    summary = _summary(results)
    report = {
        "benchmark": "neuromorph_side_by_side",
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": bench_common.machine_info(),
        "load_average_start_end": [list(load_start), list(os.getloadavg())],
        "inputs": {"pair": speed.PAIR, "remeshed_to": speed.NEUROMORPH_VERTS,
                   "n_verts": [int(arrays["verts_x"].shape[0]), int(arrays["verts_y"].shape[0])],
                   "geodesics": "heat method", "settings": {c: speed.NEUROMORPH_SETTINGS[c] for c in args.cases}},
        "protocol": {"threads": 1, "rounds": args.rounds, "repeats_per_process": args.repeats, "warmup": 1,
                     "order": "original, shapecorr[, shapecorr_no_mmap], alternating",
                     "statistic": "median over processes of each process's median CPU seconds per step"},
        "original_code": "github.com/marvin-eisenberger/neuromorph (InterpolationModGeoEC, ArapInterpolationEnergy), "
                         "torch_geometric replaced by a stand-in (EdgeConv with PyG semantics)",
        "original_check": check,
        "summary": summary,
        "results": results,
    }
    bench_common.write_report(args.out, report)
    for case, entry in summary.items():
        o, s = entry["original"], entry["shapecorr"]
        extra = ""
        if "shapecorr_no_mmap" in entry:
            extra = (f"; no-mmap {entry['shapecorr_no_mmap']['cpu_seconds_median']:.2f} s, "
                     f"{entry['ratio_cpu_medians_no_mmap']:.1f}x")
        print(f"{case}: original {o['cpu_seconds_median']:.2f} s, shapecorr {s['cpu_seconds_median']:.2f} s, "
              f"ratio {entry['ratio_cpu_medians']:.1f}x; max RSS {o['process_max_rss_mb_median']:.0f} / "
              f"{s['process_max_rss_mb_median']:.0f} MB{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
