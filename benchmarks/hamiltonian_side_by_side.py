"""Benchmark: one Hamiltonian-interpolation iteration, the original code and shapecorr side by side on identical inputs.

    git clone https://github.com/marvin-eisenberger/hamiltonian-interpolation /tmp/ham_orig
    python benchmarks/hamiltonian_side_by_side.py --original /tmp/ham_orig [--trees /tmp/base_tree .] \
        [--cases hamiltonian_small hamiltonian_published] [--rounds 3] [--repeats 3]

``--original``: a checkout of the original code (github.com/marvin-eisenberger/hamiltonian-interpolation), outside
this repository. What it imports but is not installed is supplied by a shim package written to a temporary folder
(docs/speed.md §3): ``torch_geometric.nn.knn`` / ``knn_graph`` by scipy's ``cKDTree`` (the original uses
torch_cluster; only the graph of the samples is built, before the timing) and ``torch.solve`` (removed from
PyTorch) by ``torch.linalg.solve``. Nothing of the original is part of this project; this script imports it from
the given folder in a child process.

Protocol:

* Inputs: those of ``benchmarks/speed.py``'s Hamiltonian cases: the golden pair ``tr_reg_080 -> tr_reg_081``, the
  targets ``y[map]`` of the original Deep Shells map, both placed in the unit box (``box_normalization``), the
  farthest-point samples of x (start vertex 0) and their targets. The samples and targets are computed once by
  this script and written to one ``.npz`` that the original's process reads (its ``Shape`` objects hold exactly
  these points; the kNN graph of 5 neighbours is built by its own ``knn_graph`` through the shim).
* Unit: one iteration of the original's optimization, ``E, _ = module.forward(); E.backward()`` plus an Adam step
  on its parameters (``HamiltonianModule`` with ``DivFreeParam``, ``k`` and ``num_vert`` of the case); shapecorr's
  unit is ``benchmarks/speed.py --child <case>`` (simulation + backward + Adam step).
* Each measurement is a fresh process, one thread (``OMP_NUM_THREADS=1``, ``torch.set_num_threads(1)``), one
  warm-up iteration, then ``--repeats`` timed iterations (process CPU seconds, their median). The processes
  alternate (original, then each of ``--trees``) ``--rounds`` times per case; the summary is the median over the
  processes of each code. Peak memory: ``VmHWM`` reset after the inputs are loaded (the timed span) and the
  process maximum ``ru_maxrss``.

Writes ``benchmarks/results/hamiltonian_side_by_side.json`` (``--out``) with the command, date, machine, the
commits of the trees and the load average before and after every process.
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
from pathlib import Path

import bench_common
import speed
from deep_shells_original_query import write_torch_geometric_shim

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "hamiltonian_side_by_side.json"
CASES = tuple(speed.HAMILTONIAN_SETTINGS)


def write_inputs(golden: Path, path: Path) -> None:
    """Samples of x and their targets in box coordinates for every case (``speed.py``'s Hamiltonian inputs)."""
    import numpy as np
    import torch

    from shapecorr.geometry import divergence_free as df
    from shapecorr.geometry.sampling import farthest_point_sampling

    inputs = np.load(golden / f"inputs_{speed.PAIR}.npz")
    mapping = np.load(golden / f"original_output_{speed.PAIR}.npz")["map_x_to_y"].astype(np.int64)
    vx = torch.from_numpy(inputs["x_verts"]).float()
    target = torch.from_numpy(inputs["y_verts"][mapping]).float()
    box_x, box_y = df.box_normalization(vx, target)
    bx, by = box_x.to_box(vx), box_y.to_box(target)
    arrays = {}
    for case, setting in speed.HAMILTONIAN_SETTINGS.items():
        samples = torch.from_numpy(farthest_point_sampling(bx, setting["samples"], start=0))
        arrays[f"{case}_x"] = bx[samples].numpy()
        arrays[f"{case}_y"] = by[samples].numpy()
    np.savez(path, **arrays)


def original_child(case: str, original: Path, inputs: Path, repeats: int) -> dict:
    """One original iteration per repeat in this process (one thread); its record."""
    import contextlib
    import io
    import resource
    import time

    import numpy as np
    import torch

    torch.set_num_threads(1)
    torch.solve = lambda b, a: (torch.linalg.solve(a, b), None)
    shim = Path(tempfile.mkdtemp(prefix="hamiltonian_shim_"))
    write_torch_geometric_shim(shim)
    sys.path[:0] = [str(shim), str(original / "tools"), str(original / "interpolation")]
    with contextlib.redirect_stdout(io.StringIO()):
        from div_free_interpolation import DivFreeParam, HamiltonianModule
        from shape_utils import Shape

        data = np.load(inputs)
        shape_x = Shape(torch.from_numpy(data[f"{case}_x"]).float())
        shape_y = Shape(torch.from_numpy(data[f"{case}_y"]).float())
        param = DivFreeParam()
        param.k = speed.HAMILTONIAN_SETTINGS[case]["n_modes"]
        param.num_vert = shape_x.vert.shape[0]
        param.log = False
        shape_x._neigh_knn(param.num_knn)  # the graph of the samples, as subsample_fps builds it
        module = HamiltonianModule(shape_x, shape_y, param)
    optimizer = torch.optim.Adam(module.parameters(), lr=param.lr)
    _, baseline_kb, reset = bench_common.start_memory_span(torch.device("cpu"))
    cpus, value = [], None
    for i in range(repeats + 1):  # the first iteration warms up
        start = time.process_time()
        optimizer.zero_grad()
        energy, _ = module.forward()
        energy.backward()
        optimizer.step()
        value = float(energy.detach())
        if i > 0:
            cpus.append(time.process_time() - start)
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    hwm = bench_common.status_kb("VmHWM") if reset else None
    return {"case": case, "code": "original", "threads": 1, "cpu_seconds": cpus,
            "cpu_seconds_median": statistics.median(cpus), "value": value,
            "peak_rss_mb": (hwm or maxrss) / 1024, "baseline_rss_mb": (baseline_kb or 0) / 1024,
            "process_max_rss_mb": maxrss / 1024}


def _commit(tree: Path) -> str | None:
    out = subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--original", type=Path, required=True, help="checkout of the original code")
    parser.add_argument("--trees", type=Path, nargs="+", default=[REPO],
                        help="checkouts of this repository whose speed.py children run (default this one)")
    parser.add_argument("--labels", nargs="+", default=None,
                        help="a name per tree for the record (e.g. its commit; default: the tree's git HEAD or path)")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--out", type=Path, default=RESULT)
    parser.add_argument("--original-child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--inputs", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    original = args.original.resolve()
    if args.original_child:
        print(json.dumps(original_child(args.original_child, original, args.inputs, args.repeats)))
        return 0
    if not (original / "interpolation" / "div_free_interpolation.py").is_file():
        print(f"error: {original}: not a checkout of the original Hamiltonian interpolation code", file=sys.stderr)
        return 2
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", speed.DEFAULT_GOLDEN))
    trees = [t.resolve() for t in args.trees]
    if args.labels is not None and len(args.labels) != len(trees):
        print("error: --labels needs one name per tree", file=sys.stderr)
        return 2
    labels = args.labels or [_commit(t) or str(t) for t in trees]
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    records = []
    with tempfile.TemporaryDirectory(prefix="hamiltonian_sbs_") as tmp:
        inputs = Path(tmp) / "inputs.npz"
        write_inputs(golden, inputs)
        for case in args.cases:
            for rnd in range(args.rounds):
                cmd = [sys.executable, str(Path(__file__).resolve()), "--original", str(original),
                       "--original-child", case, "--inputs", str(inputs), "--repeats", str(args.repeats)]
                runs = [("original", cmd, env)]
                for tree, label in zip(trees, labels):
                    cmd = [sys.executable, str(tree / "benchmarks" / "speed.py"), "--child", case, "--golden",
                           str(golden), "--device", "cpu", "--threads", "1", "--repeats", str(args.repeats)]
                    runs.append((label, cmd, dict(env, PYTHONPATH=str(tree))))
                for code, cmd, child_env in runs:
                    record = bench_common.run_json_child(cmd, child_env, args.timeout, REPO)
                    record.update(case=case, code=code, round=rnd)
                    records.append(record)
                    shown = record.get("error") or (f"cpu {record['cpu_seconds_median']:.3f} s, peak "
                                                    f"{record['peak_rss_mb']:.0f} MB, value {record['value']:.6g}")
                    print(f"{case} round {rnd} {code}: {shown} "
                          f"(load {record['load_average_1min_before']:.2f})", flush=True)
    summary = bench_common.side_by_side_summary(records, args.cases, ["original", *labels])
    report = {"benchmark": "hamiltonian_side_by_side",
              "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "command": " ".join([Path(sys.executable).name, *sys.argv]), "original": str(original),
              "original_commit": _commit(original),
              "trees": {label: {"path": str(t), "commit": _commit(t)} for t, label in zip(trees, labels)},
              "rounds": args.rounds, "repeats": args.repeats, "machine": bench_common.machine_info(),
              "summary": summary, "records": records}
    bench_common.write_report(args.out, report)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
