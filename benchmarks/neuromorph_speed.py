"""Speed and memory of NeuroMorph on CPU (or any device), ~2000 vertices per shape: training steps and queries.

One training step = features of both shapes (forward), softmax soft maps, interpolator for T + 1 time steps,
registration + ARAP (both directions between consecutive frames) + geodesic distortion losses, backward.
One query (``--queries``) = what ``NeuroMorph.match`` does, without gradients: features of both shapes, the
hard maps both ways (chunked argmax), the soft target ``Pi y`` and the interpolator at the five evaluation
times 0, 0.25, 0.5, 0.75, 1. Training is measured for T = 0 and T = 7, each configuration in a fresh
subprocess (so peak memory is per configuration), as the median of ``--repeats`` steps after ``--warmup``
steps, for these variants in the same run:

* ``fast``: the shapecorr implementation (restructured EdgeConv on deduplicated edges, the interpolator's
  time-independent work once for all time steps, custom backwards of the max aggregation, the softmax pair
  and the geodesic loss (block-symmetric ``Pi D Pi^T``), detached ARAP rotations, "both-sides" ARAP, the
  registration loss sharing the interpolator's ``Pi y``);
* ``baseline`` (with ``--baseline-src DIR``): the ``fast`` step run on the shapecorr package found in DIR
  (e.g. ``git worktree add /tmp/before <commit>``; only keyword options it has are used): a before/after
  comparison on the same machine in the same run;
* ``naive``: the same model evaluated the way the original code does it: per-edge EdgeConv MLP on the
  face-listed edges (every interior edge twice per direction) with torch's scatter autograd, the geodesic
  loss through plain autograd, "average" ARAP differentiated through the SVD with ``face counts``
  weights (each face edge once, as the original's ARAP edge list). Its ratio to ``fast`` is measured on the
  same machine in the same run.
* ``fast_bf16``: ``fast`` with both networks under ``torch.autocast(dtype=bfloat16)`` (losses in float32):
  mixed precision, *not* the same numbers; shown because bf16 matrix units make it much faster on CPUs that
  have them.

Shapes: by default two synthetic bumpy spheres decimated with libigl to ~2000 vertices (different
triangulations, like independently remeshed shapes); with ``--faust-root`` (or ``$SHAPECORR_FAUST_R``) two
FAUST_r shapes decimated to ~2000 vertices instead. Geodesic matrices: heat method
(``shapecorr.geometry.geodesics``), only their size matters for the timing.

The machine may be shared: every result records the wall-clock median, the process CPU time (all threads)
per step, per-stage wall and CPU times, and the load average before and after its subprocess, so that
contention is visible; CPU times are the fairer comparison on a loaded machine. Every configuration runs
with torch's thread count(s) from ``--threads`` and, with ``--malloc no-mmap``, with glibc told to keep freed
large blocks (``MALLOC_MMAP_THRESHOLD_``/``MALLOC_TRIM_THRESHOLD_``; in a running process,
``mallopt(M_MMAP_THRESHOLD)``/``mallopt(M_TRIM_THRESHOLD)`` do the same): by default every large CPU tensor is a
fresh ``mmap`` whose pages fault in on first touch, which costs about as much as the arithmetic at T = 7.

Usage::

    python benchmarks/neuromorph_speed.py [--threads 2 1] [--repeats 5] [--naive-repeats 2] [--faust-root DIR]
        [--variants fast baseline naive fast_bf16] [--baseline-src DIR] [--malloc default no-mmap]
        [--queries 5] [--out benchmarks/results/neuromorph_speed.json]
"""

from __future__ import annotations

import argparse
import datetime as dt
import inspect
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import bench_common
import igl
import numpy as np
import torch

from shapecorr.data.shape import make_shape
from shapecorr.geometry.geodesics import geodesic_distances
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.losses.arap import arap_sequence_loss
from shapecorr.losses.geodesic_distortion import geodesic_distortion_loss
from shapecorr.losses.registration import registration_loss
from shapecorr.matching.softmax import DEFAULT_SIGMA, hard_maps, softmax_soft_maps
from shapecorr.models.neuromorph import DEFAULT_ARAP_EDGE_WEIGHT_SCALE
from shapecorr.nn.neuromorph import (
    NeuroMorphFeatureNet,
    NeuroMorphInterpolator,
    interpolation_times,
)

#: Target number of vertices (NeuroMorph trains on 2000-vertex FAUST_r remeshes, docs/neuromorph.md §2).
TARGET_VERTS = 2000
#: Icosphere subdivision level of the synthetic shapes before decimation (2562 vertices).
SYNTH_SUBDIVISIONS = 4
#: Synthetic shapes: number, amplitude (relative to the radius) and sharpness (1 / width^2) of random Gaussian
#: bumps, and a vertex jitter that makes the decimation differ between the two shapes.
SYNTH_BUMPS, SYNTH_BUMP_AMPLITUDE, SYNTH_BUMP_SHARPNESS, SYNTH_JITTER = 12, 0.25, 8.0, 1e-3
#: Published per-pair training time of the original code at 2000 vertices, T = 0 (task brief) and targets.
ORIGINAL_SECONDS_T0 = 5.0
TARGET_SECONDS = {0: 0.5, 7: 1.7}
#: Stages timed inside a step (forward parts, then the whole backward pass).
STAGES = ("feature_nets_fwd", "softmax_fwd", "interpolator_fwd", "registration_arap_fwd", "geodesic_fwd",
          "backward")
#: Frame times of a query (NeuroMorph.match's default interp_times, configs/model/neuromorph.yaml).
QUERY_TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: glibc settings that keep freed large blocks instead of returning them to the OS (no page faults on reuse).
GLIBC_NO_MMAP_ENV = {"MALLOC_MMAP_THRESHOLD_": str(2**34), "MALLOC_TRIM_THRESHOLD_": str(2**34)}


def _decimate(verts: np.ndarray, faces: np.ndarray, n_target: int) -> tuple[np.ndarray, np.ndarray]:
    """libigl edge-collapse decimation to about ``n_target`` vertices (closed genus-0: f = 2n - 4)."""
    v, f, _, _ = igl.decimate(np.asfortranarray(verts, dtype=np.float64),
                              np.asfortranarray(faces, dtype=np.int32), 2 * n_target - 4)
    used = np.unique(f)
    remap = np.full(v.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return v[used], remap[f]


def _synthetic_shape(seed: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(SYNTH_SUBDIVISIONS)
    v = np.asarray(sphere.vertices, dtype=np.float64)
    centers = rng.normal(size=(SYNTH_BUMPS, 3))
    centers /= np.linalg.norm(centers, axis=1, keepdims=True)
    heights = rng.uniform(-1.0, 1.0, SYNTH_BUMPS) * SYNTH_BUMP_AMPLITUDE
    bump = (heights[None] * np.exp(-SYNTH_BUMP_SHARPNESS * np.square(v[:, None] - centers[None]).sum(-1))).sum(1)
    v = v * (1.0 + bump)[:, None] + rng.normal(scale=SYNTH_JITTER, size=v.shape)
    return _decimate(v, np.asarray(sphere.faces), TARGET_VERTS)


def _faust_shape(root: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.load(root / "off" / f"{name}.off", process=False)
    return _decimate(np.asarray(mesh.vertices), np.asarray(mesh.faces), TARGET_VERTS)


def _face_listed_edges(faces: torch.Tensor) -> torch.Tensor:
    """Edges as the original lists them: per face, each triangle edge (duplicates kept)."""
    return faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)


def _naive_geodesic(pi, dist_x, dist_y):
    return (pi @ dist_y @ pi.T - dist_x).square().mean()


def _load_pair(cache: Path):
    data = np.load(cache)
    shapes = []
    for key in ("x", "y"):
        s = make_shape(data[f"verts_{key}"], data[f"faces_{key}"], key)
        shapes.append((s.verts, s.faces, torch.from_numpy(data[f"dist_{key}"]).float()))
    return shapes


def _medians(samples: dict) -> dict:
    return {k: statistics.median(v) for k, v in samples.items()}


def run_query(args) -> dict:
    """Seconds per query (no gradients) and peak memory of this process."""
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    (vx, fx, _), (vy, fy, _) = _load_pair(Path(args.cache))
    edges_x, edges_y = undirected_edges(fx), undirected_edges(fy)
    feat_net, interp = NeuroMorphFeatureNet(), NeuroMorphInterpolator()
    times = torch.tensor(QUERY_TIMES)
    rss_setup = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    @torch.no_grad()
    def query():
        feat_x, feat_y = feat_net(vx, fx, edges_x), feat_net(vy, fy, edges_y)
        p2p, p2p_inv = hard_maps(feat_x, feat_y, normalize=False)
        target = torch.softmax(DEFAULT_SIGMA * (feat_x @ feat_y.T), dim=1) @ vy
        return p2p, p2p_inv, interp.interpolate(vx, target, edges_x, times)

    for _ in range(args.warmup):
        query()
    wall, cpu = [], []
    load_before = os.getloadavg()
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        query()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "variant": args.variant,
        "seconds_per_query_median": statistics.median(wall),
        "seconds_per_query_all": wall,
        "cpu_seconds_per_query_median": statistics.median(cpu),
        "peak_rss_mib": peak / 1024.0,
        "peak_rss_above_setup_mib": (peak - rss_setup) / 1024.0,
        "load_average_before_after": [load_before, os.getloadavg()],
        "n_verts": [int(vx.shape[0]), int(vy.shape[0])],
        "query_times": list(QUERY_TIMES),
    }


def run_single(args) -> dict:
    """One (variant, T) training configuration: returns timings and peak memory of this process."""
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    (vx, fx, dx), (vy, fy, dy) = _load_pair(Path(args.cache))
    naive = args.variant == "naive"
    edges_x, counts_x = undirected_edges(fx, return_counts=True)
    edges_y = undirected_edges(fy)
    conv_edges_x = _face_listed_edges(fx) if naive else edges_x
    conv_edges_y = _face_listed_edges(fy) if naive else edges_y
    # the original: each face edge once (face counts, "average"); ours: the model default (0.5 x counts, both-sides)
    arap_weights = counts_x.float() * (1.0 if naive else DEFAULT_ARAP_EDGE_WEIGHT_SCALE)
    feat_net, interp = NeuroMorphFeatureNet(), NeuroMorphInterpolator()
    params = list(feat_net.parameters()) + list(interp.parameters())
    times = interpolation_times(args.steps)
    rss_setup = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Keyword options of the code under test (the baseline may predate some of them).
    share_target = not naive and "soft_target" in inspect.signature(registration_loss).parameters

    autocast = args.variant == "fast_bf16"

    def step(parts, cpu_parts):
        for p in params:
            p.grad = None
        fast = not naive
        marks, cpu_marks = [time.perf_counter()], [time.process_time()]

        def mark():
            marks.append(time.perf_counter())
            cpu_marks.append(time.process_time())

        with torch.autocast(device_type=vx.device.type, dtype=torch.bfloat16, enabled=autocast):
            feat_x = feat_net(vx, fx, conv_edges_x, fast=fast).float()
            feat_y = feat_net(vy, fy, conv_edges_y, fast=fast).float()
        mark()
        pi, pi_inv = softmax_soft_maps(feat_x, feat_y, sigma=DEFAULT_SIGMA, normalize=False)
        target = pi @ vy
        mark()
        with torch.autocast(device_type=vx.device.type, dtype=torch.bfloat16, enabled=autocast):
            frames = interp.interpolate(vx, target, conv_edges_x, times, fast=fast).float()
        mark()
        extra = {"soft_target": target} if share_target else {}
        reg = registration_loss(frames[-1], vy, pi, pi_inv, **extra)
        arap = arap_sequence_loss(
            torch.cat((vx.unsqueeze(0), frames)), edges_x, arap_weights,
            mode="average" if naive else "both-sides", detach_rotations=not naive,
        )
        mark()
        geo = _naive_geodesic(pi, dx, dy) if naive else geodesic_distortion_loss(pi, dx, dy)
        mark()
        (reg + arap + geo).backward()
        mark()
        for name, t0, t1 in zip(STAGES, marks[:-1], marks[1:]):
            parts.setdefault(name, []).append(t1 - t0)
        for name, t0, t1 in zip(STAGES, cpu_marks[:-1], cpu_marks[1:]):
            cpu_parts.setdefault(name, []).append(t1 - t0)

    for _ in range(args.warmup):
        step({}, {})
    wall, cpu, parts, cpu_parts = [], [], {}, {}
    load_before = os.getloadavg()
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        step(parts, cpu_parts)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "variant": args.variant,
        "T": args.steps,
        "seconds_per_step_median": statistics.median(wall),
        "seconds_per_step_all": wall,
        "cpu_seconds_per_step_median": statistics.median(cpu),
        "cpu_seconds_per_step_all": cpu,
        "stage_seconds_median": _medians(parts),
        "stage_cpu_seconds_median": _medians(cpu_parts),
        "peak_rss_mib": peak / 1024.0,
        "peak_rss_above_setup_mib": (peak - rss_setup) / 1024.0,
        "load_average_before_after": [load_before, os.getloadavg()],
        "n_verts": [int(vx.shape[0]), int(vy.shape[0])],
        "n_undirected_edges": [int(edges_x.shape[0]), int(edges_y.shape[0])],
    }


def _prepare(args) -> dict:
    """Build the two shapes and their geodesic matrices once; save them for the subprocesses."""
    root = args.faust_root or os.environ.get("SHAPECORR_FAUST_R")
    if root:
        source = {"kind": "FAUST_r", "root_from": "--faust-root" if args.faust_root else "$SHAPECORR_FAUST_R",
                  "shapes": ["tr_reg_000", "tr_reg_001"]}
        pair = [_faust_shape(Path(root), name) for name in source["shapes"]]
    else:
        source = {"kind": "synthetic bumpy icospheres decimated with igl.decimate", "seeds": [0, 1]}
        pair = [_synthetic_shape(seed) for seed in (0, 1)]
    arrays = {}
    for key, (v, f) in zip(("x", "y"), pair):
        s = make_shape(v, f, key)
        arrays[f"verts_{key}"], arrays[f"faces_{key}"] = v, f
        arrays[f"dist_{key}"] = geodesic_distances(s.verts.numpy(), s.faces.numpy(), method="heat").astype(np.float32)
    np.savez(args.cache, **arrays)
    source["n_verts"] = [int(arrays["verts_x"].shape[0]), int(arrays["verts_y"].shape[0])]
    return source


def _subprocess(args, variant: str, steps: int, threads: int, repeats: int, malloc: str, mode: str) -> dict:
    cmd = [sys.executable, __file__, mode, "--variant", variant, "--steps", str(steps), "--threads", str(threads),
           "--repeats", str(repeats), "--warmup", str(args.warmup), "--cache", args.cache]
    env = dict(os.environ, **(GLIBC_NO_MMAP_ENV if malloc == "no-mmap" else {}))
    if variant == "baseline":
        env["PYTHONPATH"] = os.pathsep.join(filter(None, (args.baseline_src, env.get("PYTHONPATH"))))
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
    return dict(json.loads(out.strip().splitlines()[-1]), threads=threads, malloc=malloc)


def _summary(args, results, queries) -> dict:
    summary = {}
    for threads in args.threads:
        for steps in args.steps:
            for malloc in args.malloc:
                by = {r["variant"]: r for r in results
                      if r["T"] == steps and r["threads"] == threads and r["malloc"] == malloc}
                entry = {}
                if "fast" in by:
                    entry["fast_seconds"] = by["fast"]["seconds_per_step_median"]
                    entry["fast_cpu_seconds"] = by["fast"]["cpu_seconds_per_step_median"]
                    entry["fast_peak_rss_mib"] = by["fast"]["peak_rss_mib"]
                    if steps in TARGET_SECONDS:
                        entry["target_seconds"] = TARGET_SECONDS[steps]
                        entry["meets_target"] = entry["fast_seconds"] <= TARGET_SECONDS[steps]
                    if steps == 0:
                        entry["speedup_vs_original_5s"] = ORIGINAL_SECONDS_T0 / entry["fast_seconds"]
                for other in ("baseline", "naive", "fast_bf16"):
                    if other in by:
                        entry[f"{other}_seconds"] = by[other]["seconds_per_step_median"]
                        entry[f"{other}_cpu_seconds"] = by[other]["cpu_seconds_per_step_median"]
                        if "fast" in by and other != "fast_bf16":
                            entry[f"speedup_vs_{other}_same_run"] = (
                                by[other]["seconds_per_step_median"] / by["fast"]["seconds_per_step_median"])
                            entry[f"cpu_speedup_vs_{other}_same_run"] = (
                                by[other]["cpu_seconds_per_step_median"] / by["fast"]["cpu_seconds_per_step_median"])
                if entry:
                    summary[f"threads={threads} T={steps} malloc={malloc}"] = entry
        for q in queries:
            if q["threads"] == threads:
                summary[f"threads={threads} query {q['variant']} malloc={q['malloc']}"] = {
                    "seconds_per_query": q["seconds_per_query_median"],
                    "cpu_seconds_per_query": q["cpu_seconds_per_query_median"],
                    "peak_rss_mib": q["peak_rss_mib"],
                }
    return summary


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[2, 1], help="torch thread counts to run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--steps", type=int, nargs="+", default=[0, 7], help="values of T")
    parser.add_argument("--variants", nargs="+", default=["fast", "baseline", "naive", "fast_bf16"],
                        choices=["fast", "baseline", "naive", "fast_bf16"])
    parser.add_argument("--baseline-src", default=None,
                        help="folder holding an older shapecorr package (the 'baseline' variant; skipped without)")
    parser.add_argument("--malloc", nargs="+", default=["default", "no-mmap"], choices=["default", "no-mmap"],
                        help="glibc malloc settings to run: as is, and/or MALLOC_MMAP_THRESHOLD_/"
                             "MALLOC_TRIM_THRESHOLD_ raised (only the 'fast' variant runs with both)")
    parser.add_argument("--naive-repeats", type=int, default=2,
                        help="repeats of the (slow) naive reference; its median gives the speed-up ratio")
    parser.add_argument("--queries", type=int, default=5, help="repeats of the query timing (0: skip)")
    parser.add_argument("--faust-root", default=None)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "neuromorph_speed.json"))
    parser.add_argument("--cache", default="/tmp/shapecorr_neuromorph_speed.npz")
    parser.add_argument("--single", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--single-query", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--variant", default="fast", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.single or args.single_query:
        args.steps, args.threads = args.steps[0], args.threads[0]
        print(json.dumps(run_query(args) if args.single_query else run_single(args)))
        return
    variants = [v for v in args.variants if v != "baseline" or args.baseline_src]

    source = _prepare(args)
    load_before = os.getloadavg()
    results, queries = [], []
    for threads in args.threads:
        for steps in args.steps:
            for variant in variants:
                for malloc in args.malloc:
                    if variant != "fast" and malloc != "default":
                        continue  # the malloc comparison is for the main variant only
                    repeats = args.naive_repeats if variant == "naive" else args.repeats
                    res = _subprocess(args, variant, steps, threads, repeats, malloc, "--single")
                    results.append(res)
                    print(f"threads={threads} T={steps} {variant:9s} malloc={malloc:7s}: "
                          f"{res['seconds_per_step_median']:.3f} s/step (cpu {res['cpu_seconds_per_step_median']:.3f}"
                          f" s), peak RSS {res['peak_rss_mib']:.0f} MiB, "
                          f"load {res['load_average_before_after'][0][0]:.1f}",
                          flush=True)
        if args.queries:
            for variant in [v for v in variants if v in ("fast", "baseline")]:
                res = _subprocess(args, variant, 0, threads, args.queries, "default", "--single-query")
                queries.append(res)
                print(f"threads={threads} query {variant:9s}: {res['seconds_per_query_median']:.3f} s/query (cpu "
                      f"{res['cpu_seconds_per_query_median']:.3f} s), peak RSS {res['peak_rss_mib']:.0f} MiB",
                      flush=True)
    load_after = os.getloadavg()
    summary = _summary(args, results, queries)
    report = {
        "benchmark": "neuromorph_speed",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpu": bench_common.cpu_model(), "logical_cpus": os.cpu_count(), "gpu": None,
                    "torch_threads_runs": args.threads,
                    "glibc_malloc_env_for_no_mmap": GLIBC_NO_MMAP_ENV,
                    "load_average_before": load_before, "load_average_after": load_after},
        "software": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__},
        "data": source,
        "protocol": {"warmup": args.warmup, "repeats": args.repeats, "naive_repeats": args.naive_repeats,
                     "query_repeats": args.queries, "baseline_src": args.baseline_src,
                     "statistic": "median wall-clock seconds per step (and median process CPU seconds, all threads)",
                     "step": "feature net on x and y, softmax, interpolator (T+1 frames), registration + ARAP + "
                             "geodesic losses, backward",
                     "query": "no gradients: feature net on x and y, hard maps both ways, Pi y, interpolator at "
                              f"times {list(QUERY_TIMES)}"},
        "units": {"seconds_per_step_median": "s", "cpu_seconds_per_step_median": "s (process CPU time)",
                  "seconds_per_query_median": "s", "peak_rss_mib": "MiB (process peak resident set size)"},
        "summary": summary,
        "results": results,
        "queries": queries,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
