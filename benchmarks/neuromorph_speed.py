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

With ``--pair FILE`` the shapes and distance matrices are read from an ``.npz`` (``verts_x``, ``faces_x``,
``dist_x``, the same for ``y``; positions used as given), e.g. the pair of ``benchmarks/speed.py``'s NeuroMorph
cases, written by ``python benchmarks/speed.py --cases neuromorph_train_t0 --devices cpu1 --neuromorph-inputs
FILE``.

``--parts`` measures where a ``fast`` training step's time goes instead: every part in isolation, forward and
backward, on the same pair (inputs of a part detached, fixed random upstream gradients of the right shapes):
both feature nets, the two soft maps (one exponential), the interpolator (T + 1 frames), registration + ARAP,
the geodesic distortion (T = 0 only: the published schedule sets its weight to 0 with T > 0), the Adam step;
their sum next to the whole step, the one-thread GEMM rate on the geodesic term's ``n x n`` products, and
``torch.profiler``'s operator table of one whole step (self CPU time, top rows). Results:
``benchmarks/results/neuromorph_profile.json`` by default.

Usage::

    python benchmarks/neuromorph_speed.py [--threads 2 1] [--repeats 5] [--naive-repeats 2] [--faust-root DIR]
        [--variants fast baseline naive fast_bf16] [--baseline-src DIR] [--malloc default no-mmap]
        [--queries 5] [--pair FILE] [--out benchmarks/results/neuromorph_speed.json]
    python benchmarks/neuromorph_speed.py --parts --pair FILE --threads 1 --steps 0 7 --repeats 5
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
#: Result files of the timing runs and of ``--parts``.
DEFAULT_OUT = str(Path(__file__).parent / "results" / "neuromorph_speed.json")
DEFAULT_PROFILE_OUT = str(Path(__file__).parent / "results" / "neuromorph_profile.json")
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


def _load_pair(cache: Path, given: bool = False):
    """``[(verts, faces, dist) of x, ... of y]``; normalized on load unless ``given`` (positions used as stored)."""
    data = np.load(cache)
    shapes = []
    for key in ("x", "y"):
        s = make_shape(data[f"verts_{key}"], data[f"faces_{key}"], key, **({"normalization": None} if given else {}))
        shapes.append((s.verts, s.faces, torch.from_numpy(data[f"dist_{key}"]).float()))
    return shapes


def _medians(samples: dict) -> dict:
    return {k: statistics.median(v) for k, v in samples.items()}


def run_query(args) -> dict:
    """Seconds per query (no gradients) and peak memory of this process."""
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    (vx, fx, _), (vy, fy, _) = _load_pair(Path(args.cache), args.pair is not None)
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
    (vx, fx, dx), (vy, fy, dy) = _load_pair(Path(args.cache), args.pair is not None)
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


#: Parts of a training step measured by ``--parts`` (in the order of the forward pass).
PARTS = ("feature_nets", "soft_maps", "interpolator", "registration_arap", "geodesic", "adam_step")
#: Rows of ``torch.profiler``'s operator table kept by ``--parts``.
PROFILE_ROWS = 15
#: Operator classes of the per-part profile: dense products (compute-bound, their floor is the GEMM rate) and
#: row gathers / scatters (memory-bound); everything else (element-wise, reductions, SVDs, copies) is "other".
GEMM_OPS = {"aten::mm", "aten::addmm", "aten::addmm_", "aten::bmm", "aten::baddbmm", "aten::vdot", "aten::dot"}
GATHER_SCATTER_OPS = {"aten::index_select", "aten::index_add_", "aten::scatter_add_", "aten::scatter_reduce_",
                      "aten::index", "aten::_index_put_impl_", "aten::gather", "aten::scatter_"}


def _op_classes(fn) -> dict:
    """Shares of ``fn()``'s self CPU time (``torch.profiler``) by operator class (gemm, gather_scatter, other) and
    the floating-point operations of its dense products (``gemm_flops``, the profiler's count)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], with_flops=True, record_shapes=True) as prof:
        fn()
    totals = {"gemm": 0.0, "gather_scatter": 0.0, "other": 0.0}
    flops = 0
    for event in prof.key_averages(group_by_input_shape=True):
        kind = "gemm" if event.key in GEMM_OPS else "gather_scatter" if event.key in GATHER_SCATTER_OPS else "other"
        totals[kind] += event.self_cpu_time_total
        if event.key == "aten::addmm_":  # not counted by the profiler: 2 m k n from (self, mat1 (m, k), mat2 (k, n))
            (m, k), n = event.input_shapes[1], event.input_shapes[2][1]
            flops += 2 * m * k * n * event.count
        elif kind == "gemm":
            flops += event.flops
    whole = sum(totals.values()) or 1.0
    return {**{kind: value / whole for kind, value in totals.items()}, "gemm_flops": flops}


def _cpu_median(fn, repeats: int) -> float:
    """Median process-CPU seconds of ``fn()`` over ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        c0 = time.process_time()
        fn()
        times.append(time.process_time() - c0)
    return statistics.median(times)


def run_parts(args) -> dict:
    """CPU seconds of each part of a ``fast`` training step, forward and backward in isolation (``--parts``)."""
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    (vx, fx, dx), (vy, fy, dy) = _load_pair(Path(args.cache), args.pair is not None)
    edges_x, counts_x = undirected_edges(fx, return_counts=True)
    edges_y = undirected_edges(fy)
    weights = counts_x.float() * DEFAULT_ARAP_EDGE_WEIGHT_SCALE
    feat_net, interp = NeuroMorphFeatureNet(), NeuroMorphInterpolator()
    params = list(feat_net.parameters()) + list(interp.parameters())
    optimizer = torch.optim.Adam(params, lr=1e-4)
    times = interpolation_times(args.steps)
    use_geo = args.steps == 0  # published schedule: geodesic weight 50 with T = 0, 0 from T = 1 on
    gen = torch.Generator().manual_seed(0)

    def upstream(t):
        return torch.randn(t.shape, generator=gen, dtype=t.dtype)

    def leaf(t):
        return t.detach().clone().requires_grad_(True)

    def losses(pi, pi_inv, target, frames):
        reg = registration_loss(frames[-1], vy, pi, pi_inv, soft_target=target)
        arap = arap_sequence_loss(torch.cat((vx.unsqueeze(0), frames)), edges_x, weights, mode="both-sides",
                                  detach_rotations=True)
        return reg + arap

    def full_step():
        optimizer.zero_grad(set_to_none=True)
        feat_x, feat_y = feat_net(vx, fx, edges_x), feat_net(vy, fy, edges_y)
        pi, pi_inv = softmax_soft_maps(feat_x, feat_y, sigma=DEFAULT_SIGMA, normalize=False)
        target = pi @ vy
        frames = interp.interpolate(vx, target, edges_x, times)
        loss = losses(pi, pi_inv, target, frames)
        if use_geo:
            loss = loss + 50.0 * geodesic_distortion_loss(pi, dx, dy)
        loss.backward()
        optimizer.step()

    # Fixed inputs and upstream gradients of every part, from one step's values.
    with torch.no_grad():
        feat_x0, feat_y0 = feat_net(vx, fx, edges_x), feat_net(vy, fy, edges_y)
        pi0, pi_inv0 = softmax_soft_maps(feat_x0, feat_y0, sigma=DEFAULT_SIGMA, normalize=False)
        target0 = pi0 @ vy
        frames0 = interp.interpolate(vx, target0, edges_x, times)
    grads = {"feat": (upstream(feat_x0), upstream(feat_y0)), "maps": (upstream(pi0), upstream(pi_inv0)),
             "frames": upstream(frames0)}
    parts = {
        "feature_nets": (lambda: (feat_net(vx, fx, edges_x), feat_net(vy, fy, edges_y)), lambda out: grads["feat"]),
        "soft_maps": (lambda: softmax_soft_maps(leaf(feat_x0), leaf(feat_y0), sigma=DEFAULT_SIGMA, normalize=False),
                      lambda out: grads["maps"]),
        "interpolator": (lambda: (interp.interpolate(vx, leaf(target0), edges_x, times),),
                         lambda out: (grads["frames"],)),
        "registration_arap": (lambda: (losses(leaf(pi0), leaf(pi_inv0), leaf(target0), leaf(frames0)),),
                              lambda out: (torch.ones(()),)),
    }
    if use_geo:
        parts["geodesic"] = (lambda: (50.0 * geodesic_distortion_loss(leaf(pi0), dx, dy),),
                             lambda out: (torch.ones(()),))
    forward_s, backward_s, op_shares = {}, {}, {}
    for name, (forward, upstream_grads) in parts.items():
        forward_s[name] = _cpu_median(forward, args.repeats)
        state = {}

        def prepare(forward=forward, state=state):
            state["out"] = forward()

        def backward(upstream_grads=upstream_grads, state=state):
            out = state.pop("out")
            torch.autograd.backward(out, upstream_grads(out))

        samples = []
        for i in range(args.repeats + 1):  # the first pair warms up
            prepare()
            c0 = time.process_time()
            backward()
            if i:
                samples.append(time.process_time() - c0)
        backward_s[name] = statistics.median(samples)

        def forward_backward(forward=forward, upstream_grads=upstream_grads):
            out = forward()
            torch.autograd.backward(out, upstream_grads(out))

        op_shares[name] = _op_classes(forward_backward)
    for p in params:  # gradients for the optimizer step
        p.grad = torch.randn(p.shape, generator=gen)
    forward_s["adam_step"], backward_s["adam_step"] = _cpu_median(optimizer.step, args.repeats), 0.0
    whole = _cpu_median(full_step, args.repeats)

    # GEMM rate at the geodesic term's sizes: (n_x, n_y) x (n_y, n_y), as Pi D_y.
    pi_mat, dist = pi0.contiguous(), dy.contiguous()
    gemm_s = _cpu_median(lambda: pi_mat @ dist, args.repeats)
    gemm_flops = 2.0 * pi_mat.shape[0] * pi_mat.shape[1] * dist.shape[1]

    from torch.profiler import ProfilerActivity, profile

    full_step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        full_step()
    table = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total_us = sum(e.self_cpu_time_total for e in table)
    ops = [{"op": e.key, "self_cpu_ms": e.self_cpu_time_total / 1e3, "share": e.self_cpu_time_total / total_us,
            "calls": e.count} for e in table[:PROFILE_ROWS]]
    return {
        "T": args.steps,
        "geodesic_term": use_geo,
        "part_cpu_seconds": {name: {"forward": forward_s[name], "backward": backward_s[name],
                                    "total": forward_s[name] + backward_s[name]} for name in forward_s},
        "part_op_class_shares": op_shares,
        # the dense products of each part at the measured GEMM rate: the part's floor with its math unchanged
        "part_gemm_seconds_at_gemm_rate": {name: shares["gemm_flops"] * gemm_s / gemm_flops
                                           for name, shares in op_shares.items()},
        "sum_of_parts_cpu_seconds": sum(forward_s.values()) + sum(backward_s.values()),
        "whole_step_cpu_seconds": whole,
        "gemm_cpu_seconds_pi_dist": gemm_s,
        "gemm_gflops_per_second": gemm_flops / gemm_s / 1e9,
        "profiler_total_self_cpu_ms": total_us / 1e3,
        "profiler_top_ops": ops,
        "load_average": os.getloadavg(),
        "n_verts": [int(vx.shape[0]), int(vy.shape[0])],
        "n_undirected_edges": [int(edges_x.shape[0]), int(edges_y.shape[0])],
    }


def _prepare(args) -> dict:
    """Build the two shapes and their geodesic matrices once; save them for the subprocesses."""
    if args.pair is not None:
        with np.load(args.pair) as data:
            return {"kind": "given pair, positions as stored", "path": str(args.pair),
                    "n_verts": [int(data["verts_x"].shape[0]), int(data["verts_y"].shape[0])]}
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
    if args.pair is not None:
        cmd += ["--pair", args.pair]
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


def main_parts(args) -> None:
    """``--parts``: one subprocess per (threads, T); writes ``--out`` (default neuromorph_profile.json)."""
    source = _prepare(args)
    results = []
    for threads in args.threads:
        for steps in args.steps:
            env = dict(os.environ, OMP_NUM_THREADS=str(threads))
            cmd = [sys.executable, __file__, "--single-parts", "--steps", str(steps), "--threads", str(threads),
                   "--repeats", str(args.repeats), "--cache", args.cache]
            if args.pair is not None:
                cmd += ["--pair", args.pair]
            res = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
                             .stdout.strip().splitlines()[-1])
            res["threads"] = threads
            results.append(res)
            shown = ", ".join(f"{k} {v['total']:.3f}" for k, v in res["part_cpu_seconds"].items())
            print(f"threads={threads} T={steps}: {shown}; sum {res['sum_of_parts_cpu_seconds']:.3f} s, whole step "
                  f"{res['whole_step_cpu_seconds']:.3f} s, GEMM {res['gemm_gflops_per_second']:.0f} GFLOP/s",
                  flush=True)
    out = Path(args.out if args.out != DEFAULT_OUT else DEFAULT_PROFILE_OUT)
    report = {
        "benchmark": "neuromorph_profile",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpu": bench_common.cpu_model(), "logical_cpus": os.cpu_count(),
                    "load_average_end": os.getloadavg()},
        "software": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__},
        "data": source,
        "protocol": {"repeats": args.repeats, "statistic": "median process CPU seconds (one warm-up)",
                     "parts": list(PARTS)},
        "results": results,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


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
    parser.add_argument("--out", default=DEFAULT_OUT)
    parser.add_argument("--cache", default="/tmp/shapecorr_neuromorph_speed.npz")
    parser.add_argument("--single", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--single-query", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--pair", default=None, help="npz of the pair (verts_x, faces_x, dist_x, ... y), used as given")
    parser.add_argument("--parts", action="store_true", help="where a fast step's time goes, per part (see above)")
    parser.add_argument("--single-parts", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--variant", default="fast", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.pair is not None:
        args.cache = args.pair
    if args.single or args.single_query or args.single_parts:
        args.steps, args.threads = args.steps[0], args.threads[0]
        run = run_parts if args.single_parts else run_query if args.single_query else run_single
        print(json.dumps(run(args)))
        return
    if args.parts:
        main_parts(args)
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
