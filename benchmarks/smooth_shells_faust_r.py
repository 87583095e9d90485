"""Benchmark (preliminary): Smooth Shells on a few FAUST_r test pairs, one thread.

    SHAPECORR_FAUST_R=/path/to/FAUST_r python benchmarks/smooth_shells_faust_r.py [--pairs 3] [--threads 1]
        [--num-mcmc 100] [--no-rigid] [--device cpu] [--out benchmarks/results/smooth_shells_faust_r.json]

For each of the first ``--pairs`` test pairs (``test_pairs.txt``): the shapes are normalized as the data
pipeline does (area-weighted centroid, area (2/3)^2), their 509 eigenpairs and SHOT come from the project's
shape cache (computed on a miss, not timed), then :func:`shapecorr.axiomatic.smooth_shells.smooth_shells`
with the published isometric settings is timed. Reported: seconds per pair (wall, process CPU), the peak
resident memory of the process before and after the matching, and the mean geodesic error (Princeton
protocol: heat-method geodesics from the ground-truth vertices, divided by sqrt(area of Y)).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import bench_common
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "benchmarks" / "results" / "smooth_shells_faust_r.json"
#: Published FAUST_r mean geodesic error of Smooth Shells alone (fraction of sqrt(area)): 2.5, the comparison
#: table of the Deep Shells paper (Eisenberger et al., NeurIPS 2020).
PUBLISHED_ERROR = 0.025
#: Seconds per pair reported by the Smooth Shells paper (CVPR 2020, §6, GPU): 116 s.
PUBLISHED_SECONDS = 116.0


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _load(root: Path, name: str, cache, config, device):
    from shapecorr.axiomatic.smooth_shells import shells_shape
    from shapecorr.data.io import load_shape, read_vts
    from shapecorr.data.operators import OperatorConfig, compute_operators

    shape = load_shape(root / "off" / f"{name}.off")
    v, f = shape.verts.numpy().astype(np.float64), shape.faces.numpy()
    ops = compute_operators(cache, v, f, OperatorConfig(request={"eigenbasis": {"k": config.num_eigs}, "shot": {}}))
    eig, shot = ops["eigenbasis"], ops["shot"]["shot"]
    s = shells_shape(shape.verts, shape.faces, torch.from_numpy(eig["evals"]).float(),
                     torch.from_numpy(eig["evecs"]).float(), torch.from_numpy(eig["mass"]).float(),
                     shot=torch.from_numpy(shot).float(), name=name)
    corres = read_vts(root / "corres" / f"{name}.vts", n_verts=v.shape[0])
    return _to(s, device), corres, v, f


def _to(s, device):
    from dataclasses import replace

    return replace(s, spectral=s.spectral.to(device), evals=s.evals.to(device),
                   shot=None if s.shot is None else s.shot.to(device))


def _geodesic_error(p2p, corres_x, corres_y, verts_y, faces_y) -> float:
    from shapecorr.eval.metrics import surface_area
    from shapecorr.geometry.geodesics import geodesic_distances

    sources, inverse = np.unique(corres_y, return_inverse=True)
    dist = geodesic_distances(verts_y, faces_y, sources=sources)  # (s, n_y)
    err = dist[inverse, p2p[corres_x]] / np.sqrt(surface_area(verts_y, faces_y))
    return float(err.mean())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"))
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--num-mcmc", type=int, default=100)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-rigid", action="store_true", help="skip the rigid stage (FAUST_r is pre-aligned)")
    parser.add_argument("--out", default=str(DEFAULT_OUT))
    args = parser.parse_args(argv)
    if not args.faust_r:
        print("error: set SHAPECORR_FAUST_R or --faust-r to the FAUST_r folder", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    from shapecorr.axiomatic.smooth_shells import SmoothShellsConfig, smooth_shells
    from shapecorr.data.cache import ShapeCache

    root = Path(args.faust_r)
    pairs = [line.split() for line in (root / "test_pairs.txt").read_text().splitlines() if line.strip()]
    pairs = pairs[: args.pairs]
    config = SmoothShellsConfig(num_mcmc=args.num_mcmc, no_rigid=args.no_rigid)
    cache = ShapeCache()
    device = torch.device(args.device)
    records = []
    for name_x, name_y in pairs:
        x, cx, _, _ = _load(root, name_x, cache, config, device)
        y, cy, vy, fy = _load(root, name_y, cache, config, device)
        before = _peak_mb()
        wall0, cpu0 = time.perf_counter(), time.process_time()
        res = smooth_shells(x, y, config)
        if device.type == "cuda":
            torch.cuda.synchronize()
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        err = _geodesic_error(res.map_x_to_y.cpu().numpy(), cx, cy, vy, fy)
        rec = {"pair": [name_x, name_y], "n_x": x.spectral.n_verts, "n_y": y.spectral.n_verts,
               "seconds": wall, "cpu_seconds": cpu, "peak_rss_before_mb": before, "peak_rss_after_mb": _peak_mb(),
               "mean_geodesic_error": err}
        records.append(rec)
        print(json.dumps(rec), flush=True)
    out = {
        "what": "Smooth Shells (published isometric settings) on the first FAUST_r test pairs; preliminary",
        "command": " ".join([sys.executable] + sys.argv),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": bench_common.machine_info(),
        "threads": args.threads,
        "device": str(device),
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(config).items()},
        "published_error": PUBLISHED_ERROR,
        "published_seconds_per_pair": PUBLISHED_SECONDS,
        "pairs": records,
        "mean_seconds": float(np.mean([r["seconds"] for r in records])),
        "mean_geodesic_error": float(np.mean([r["mean_geodesic_error"] for r in records])),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"mean {out['mean_seconds']:.1f} s/pair, mean error {100 * out['mean_geodesic_error']:.2f} (x100)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
