"""Benchmark: evaluate.py on large scans: a ~50k-vertex and a ~150k-vertex pair.

    python benchmarks/large_scans.py --faust-r /path/to/FAUST_r [--targets 50000 150000] [--n-ref 200]
        [--models descriptor_nn deep_shells] [--deep-shells-weights FILE] [--out FILE]

Two FAUST_r shapes (tr_reg_080, tr_reg_081) are refined with ``trimesh.remesh.subdivide_to_size`` to about
``--targets`` vertices (the original vertices stay first, so the ``.vts`` ground truth stays valid). They are
evaluated on ``--n-ref`` of their 5000 ground-truth points (``data.reference_points``: evenly spaced entries; all
5000 would cost 5000 heat solves and 2.8 GB of geodesic rows per 150k shape). For each size and each of
``--models`` (``descriptor_nn``; ``deep_shells``: the authors' released weights), ``evaluate.py`` runs on the pair
(both directions) in a fresh process with a fresh cache, with ``--n-eig`` eigenpairs (WKS on min(200, n_eig) of
them); recorded: wall time, peak RSS of that process tree (``wait4``), the size of every cache entry, the mean
error, seconds per pair. Writes ``benchmarks/results/large_scans.json`` (``--out``), keeping the runs of other
sizes and models in it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "large_scans.json"
SHAPES = ("tr_reg_080", "tr_reg_081")


def refine(verts, faces, target: int):
    """Midpoint-subdivide edges longer than a length chosen so that the mesh gets about ``target`` vertices."""
    import trimesh

    mean_edge = trimesh.Trimesh(verts, faces, process=False).edges_unique_length.mean()
    factor = np.sqrt(len(verts) / target)
    for _ in range(4):  # the count moves in steps (each split face adds up to 3 vertices): a few corrections
        v, f = trimesh.remesh.subdivide_to_size(verts, faces, max_edge=mean_edge * factor)
        if abs(len(v) / target - 1) < 0.25:
            break
        factor *= np.sqrt(len(v) / target)
    assert np.array_equal(v[: len(verts)], verts), "subdivision must keep the original vertices first"
    return v, f


def make_folder(root: Path, faust_r: Path, target: int) -> list[int]:
    from shapecorr.data.io import read_mesh, read_vts, write_mesh, write_vts

    for sub in ("off", "corres", "splits"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    counts = []
    for name in SHAPES:
        v, f = read_mesh(faust_r / "off" / f"{name}.off")
        v2, f2 = refine(v, f, target)
        write_mesh(root / "off" / f"{name}.off", v2, f2)
        write_vts(root / "corres" / f"{name}.vts", read_vts(faust_r / "corres" / f"{name}.vts"))
        counts.append(len(v2))
    for split in ("train", "test"):
        (root / "splits" / f"{split}.txt").write_text("\n".join(SHAPES) + "\n")
    return counts


def run_prepare(root: Path, cache: Path, out: Path, n_eig: int, n_ref: int) -> dict:
    """``data_prep/prepare.py geodesics=heat`` alone: mesh checks, eigenbasis and the ground-truth geodesic rows
    (what evaluation adds to a matcher), for sizes where the matcher itself does not fit the time budget."""
    cmd = [sys.executable, str(REPO / "data_prep" / "prepare.py"), "data=folder", f"data.root={root}",
           f"paths.cache_dir={cache}", "geodesics=heat", f"data.operators.n_eig={n_eig}",
           f"data.reference_points={n_ref}", "workers=2",
           "hydra.run.dir=" + str(out / "hydra")]
    return _measure(cmd, cache, out)


#: evaluate.py arguments of each ``--models`` entry (Deep Shells: the authors' released weights, which raise
#: the eigenpairs to the 500 of its refinement whatever ``--n-eig`` says).
MODELS = {
    "descriptor_nn": ["model=descriptor_nn"],
    "deep_shells": ["model=deep_shells_published"],
}


def run_evaluate(root: Path, cache: Path, out: Path, n_eig: int, n_ref: int, model: str = "descriptor_nn",
                 weights: str | None = None) -> dict:
    args = list(MODELS[model])
    if model == "deep_shells":
        args.append(f"model.pretrained={weights}")
    cmd = [sys.executable, str(REPO / "evaluate.py"), *args, "data=folder", f"data.root={root}",
           f"paths.cache_dir={cache}", f"output_dir={out}", "n_examples=0", "progress=false", "workers=0",
           f"data.operators.n_eig={n_eig}", f"data.reference_points={n_ref}",
           "hydra.run.dir=" + str(out / "hydra")]
    return _measure(cmd, cache, out)


def _measure(cmd: list[str], cache: Path, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = proc.stdout.read().decode(errors="replace")
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    entries = {}
    for f in cache.rglob("*.npz"):
        entries.setdefault(f.parent.name, []).append(f.stat().st_size / 2**20)
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    return {
        "seconds_per_pair": metrics.get("seconds_per_pair"),
        "command": " ".join(cmd[1:]),
        "exit_status": os.waitstatus_to_exitcode(status),
        "wall_seconds": wall,
        "peak_rss_mb": usage.ru_maxrss / 1024,  # this process tree (wait4 of the evaluate.py process)
        "cache_mb_by_entry": {k: [round(x, 1) for x in v] for k, v in sorted(entries.items())},
        "mean_geodesic_error": metrics.get("mean_geodesic_error"),
        "output_tail": output[-1500:],
    }


def _run_key(run: dict) -> tuple:
    """What a result replaces: the earlier run of the same size, mode and model."""
    return run["target_vertices"], run.get("mode", "evaluate"), run.get("model", "descriptor_nn")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"))
    parser.add_argument("--targets", type=int, nargs="+", default=[50000, 150000])
    parser.add_argument("--n-ref", type=int, default=200, help="ground-truth points evaluated (data.reference_points)")
    parser.add_argument("--prepare-only", action="store_true",
                        help="run data_prep/prepare.py geodesics=heat instead of evaluate.py (no matcher)")
    parser.add_argument("--n-eig", type=int, default=50,
                        help="eigenpairs (WKS uses min(200, n_eig)); 200 takes minutes per shape at 50k vertices")
    parser.add_argument("--models", nargs="+", default=["descriptor_nn"], choices=list(MODELS),
                        help="evaluate.py runs per size, each in a fresh process with a fresh cache")
    parser.add_argument("--deep-shells-weights", default=os.environ.get("SHAPECORR_DEEP_SHELLS_WEIGHTS"),
                        help="the authors' released Deep Shells weights (default: $SHAPECORR_DEEP_SHELLS_WEIGHTS)")
    parser.add_argument("--out", default=str(RESULT), help="result file (runs of other sizes/models are kept)")
    args = parser.parse_args()
    if not args.faust_r:
        sys.exit("give --faust-r DIR or set SHAPECORR_FAUST_R")
    if "deep_shells" in args.models and not args.prepare_only and not args.deep_shells_weights:
        sys.exit("--models deep_shells needs --deep-shells-weights FILE or $SHAPECORR_DEEP_SHELLS_WEIGHTS")
    sys.path.insert(0, str(REPO))
    runs = []
    for target in args.targets:
        with tempfile.TemporaryDirectory(prefix="shapecorr_large_") as tmp:
            tmp = Path(tmp)
            counts = make_folder(tmp / "data", Path(args.faust_r), target)  # once per size, shared by the runs
            for model in ["prepare"] if args.prepare_only else args.models:
                cache, out = tmp / model / "cache", tmp / model / "out"  # a fresh cache per run
                if args.prepare_only:
                    result = run_prepare(tmp / "data", cache, out, args.n_eig, args.n_ref)
                else:
                    result = run_evaluate(tmp / "data", cache, out, args.n_eig, args.n_ref, model,
                                          args.deep_shells_weights)
                result.update({"mode": "prepare" if args.prepare_only else "evaluate", "model": model,
                               "target_vertices": target, "n_verts": counts, "n_ref": args.n_ref,
                               "n_eig": args.n_eig, "rows_mb_at_5000_refs": [4 * 5000 * n / 2**20 for n in counts]})
                runs.append(result)
                print(json.dumps({k: v for k, v in result.items() if k != "output_tail"}, indent=1), flush=True)
    out = {
        "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": bench_common.machine_info(),
        "runs": runs,
    }
    result_file = Path(args.out)
    result_file.parent.mkdir(parents=True, exist_ok=True)
    if result_file.is_file():  # keep the runs of other sizes measured separately
        previous = json.loads(result_file.read_text()).get("runs", [])
        done = {_run_key(r) for r in runs}
        out["runs"] = [r for r in previous if _run_key(r) not in done] + runs
    result_file.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
