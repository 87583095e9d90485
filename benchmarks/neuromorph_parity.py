"""Benchmark: NeuroMorph parity with the original code on identical inputs, the ARAP scale, geodesic preprocessing.

    python benchmarks/neuromorph_parity.py --golden $SHAPECORR_NEUROMORPH_GOLDEN [--faust-r $SHAPECORR_FAUST_R]

1. Parity (both golden pairs; see the golden folder's README): ``model=neuromorph_original`` with the original's
   seed-0 weights (``load_original_neuromorph_weights``) on the original's inputs, fed as they are: features,
   soft maps Pi / Pi_inv, interpolation frames X(t) for T = 0 and T = 7, every loss term (T = 0, and the T = 7
   ARAP and total), the gradient norms of both networks and the two fc_pos gradients. For each quantity: max
   absolute difference and relative difference (max abs difference / max abs of the original's array; for the
   scalars |ours - theirs| / |theirs|; for the gradients also the relative Frobenius difference). The same
   computation in float64 is recorded as well: it tells how far the original's float32 numbers are from the
   exact function (the float32 floor).
2. ARAP scale: our default ARAP term (both-sides, detached rotations, ``arap_edge_weight_scale`` 0.5) and the
   former default (scale 1) on the same frames, against the original's value.
3. Geodesic preprocessing cost (with ``--faust-r``): the ``geodesics=original`` option computes exact geodesics
   of the 2000-vertex working remesh of a FAUST_r shape once; timed on ``--exact-sources`` sources and
   extrapolated to all pairs (seconds per shape), next to the heat method on all pairs of the same remesh and
   the sub-matrix extraction for a 1000-vertex remesh.
4. Truncated soft maps in the geodesic term (the speed option considered for the 0.5 s / 1.7 s step targets):
   the accuracy cost of keeping the k largest entries per row of Pi (value error, gradient cosine) and the time
   of the full geodesic term at 2000 vertices (the most a truncation could save).

Results go to ``benchmarks/results/neuromorph_parity.json`` with the command, date, machine and versions.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import bench_common
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "neuromorph_parity.json"
PAIRS = ("tr_reg_000__tr_reg_013", "tr_reg_021__tr_reg_046")
#: FAUST_r shape used for the geodesic timing and the working resolution of the original (2000 vertices).
TIMING_SHAPE = "tr_reg_000"
WORKING_RESOLUTION = 2000
LOWER_RESOLUTION = 1000


def build_model(tmp: str):
    """``model=neuromorph_original`` from the Hydra configs."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=["model=neuromorph_original", f"paths.cache_dir={tmp}",
                                          f"paths.output_dir={tmp}"])
    return instantiate(cfg.model, _convert_="object")


def run_pair(model, inp, out, dtype) -> dict:
    """Our quantities on one golden pair (numpy, float64), under the names of the golden outputs."""
    import torch

    from shapecorr.geometry.mesh_graph import undirected_edges
    from shapecorr.losses.arap import arap_sequence_loss
    from shapecorr.matching.softmax import softmax_soft_maps

    t = {k: torch.from_numpy(inp[k]).to(dtype) if inp[k].dtype == np.float32 else torch.from_numpy(inp[k])
         for k in inp.files}
    feat_net, interp = model.feature_net.to(dtype), model.interpolator.to(dtype)
    feat_net.zero_grad()
    interp.zero_grad()
    edges_x, counts_x = undirected_edges(t["faces_x"], return_counts=True)
    edges_y = undirected_edges(t["faces_y"])
    feat_x = feat_net.forward_arrays(t["verts_x"], t["faces_x"], edges_x)
    feat_y = feat_net.forward_arrays(t["verts_y"], t["faces_y"], edges_y)
    pi, pi_inv = softmax_soft_maps(feat_x, feat_y, model.sigma, normalize=False)
    target = pi @ t["verts_y"]
    weights = model.arap_edge_weight_scale * counts_x.to(dtype)
    res = {"feat_x": feat_x, "feat_y": feat_y, "Pi": pi, "Pi_inv": pi_inv}
    loss_inputs = dict(verts_y=t["verts_y"], pi_x_to_y=pi, pi_y_to_x=pi_inv, soft_target=target, edges=edges_x,
                       edge_weights=weights, dist_x=t["geodesic_x"], dist_y=t["geodesic_y"])
    totals = {}
    for n_steps in (0, 7):
        times = torch.from_numpy(out[f"times_T{n_steps}"]).to(dtype)
        frames = interp.interpolate(t["verts_x"], target, edges_x, times)
        res[f"X_T{n_steps}"] = frames.permute(1, 2, 0)
        total, values = model.loss(verts_x_deformed=frames[-1], frames=torch.cat((t["verts_x"][None], frames)),
                                   **loss_inputs)
        prefix = "" if n_steps == 0 else "T7_"
        res[f"{prefix}loss_total"] = total
        res[f"{prefix}loss_arap"] = values["arap"]
        if n_steps == 0:
            res["loss_registration"] = values["registration"]
            res["loss_geodesic_unweighted"] = values["geo"]
            res["loss_geodesic_weighted"] = model.loss.weights["geo"] * values["geo"]
            # our default ARAP term (both-sides, detached rotations) at the new and the former edge scale
            seq = torch.cat((t["verts_x"][None], frames)).detach()
            res["default_arap_scale_0.5"] = arap_sequence_loss(seq, edges_x, 0.5 * counts_x.to(dtype))
            res["default_arap_scale_1.0"] = arap_sequence_loss(seq, edges_x, 1.0 * counts_x.to(dtype))
        totals[n_steps] = total
    totals[0].backward()

    def norm(params):
        return torch.sqrt(sum(p.grad.double().square().sum() for p in params))

    res["grad_norm_feat_net"] = norm(feat_net.parameters())
    res["grad_norm_interpolator"] = norm(interp.parameters())
    res["grad_norm_all"] = norm([*feat_net.parameters(), *interp.parameters()])
    res["grad_feat_module_fc_pos_weight"] = feat_net.net.fc_pos.weight.grad
    res["grad_rn_ec_fc_pos_weight"] = interp.net.fc_pos.weight.grad
    model.feature_net.float()
    model.interpolator.float()
    return {k: np.asarray(v.detach().double().numpy()) for k, v in res.items()}


def differences(ours: dict, out) -> dict:
    """Max abs / relative difference (and relative Frobenius for arrays) of every golden quantity."""
    table = {}
    for key, value in ours.items():
        if key not in out.files:
            continue
        theirs = np.asarray(out[key], dtype=np.float64)
        diff = np.abs(value - theirs)
        scale = float(np.abs(theirs).max())
        row = {"max_abs": float(diff.max()), "relative": float(diff.max() / scale) if scale else float(diff.max())}
        if theirs.ndim:
            row["relative_frobenius"] = float(np.linalg.norm(value - theirs) / np.linalg.norm(theirs))
        else:
            row.update(ours=float(value), original=float(theirs))
        table[key] = row
    return table


def geodesic_cost(faust_r: Path, exact_sources: int) -> dict:
    """Seconds per shape of the original geodesic preprocessing at 2000 vertices (see the module docstring)."""
    from scipy.spatial import cKDTree

    from shapecorr.data.augmentation import remesh_with_correspondence
    from shapecorr.data.io import load_shape
    from shapecorr.geometry.geodesics import geodesic_distances

    shape = load_shape(faust_r / "off" / f"{TIMING_SHAPE}.off")
    verts, faces = shape.verts.numpy(), shape.faces.numpy()
    work = remesh_with_correspondence(verts, faces, WORKING_RESOLUTION)
    low = remesh_with_correspondence(verts, faces, LOWER_RESOLUTION)
    n = work.n_verts
    sources = np.linspace(0, n - 1, exact_sources).astype(np.int64)
    start, start_cpu = time.perf_counter(), time.process_time()
    geodesic_distances(work.verts, work.faces, sources=sources, method="exact")
    exact_per_source = (time.perf_counter() - start) / sources.size
    exact_cpu_per_source = (time.process_time() - start_cpu) / sources.size
    start = time.perf_counter()
    heat = geodesic_distances(work.verts, work.faces, method="heat")
    heat_seconds = time.perf_counter() - start
    start = time.perf_counter()
    _, nearest = cKDTree(work.verts.astype(np.float64)).query(low.verts.astype(np.float64), k=1)
    sub = heat.astype(np.float32)[np.ix_(nearest, nearest)]
    sub_seconds = time.perf_counter() - start
    return {"shape": TIMING_SHAPE, "working_vertices": n, "lower_vertices": low.n_verts,
            "exact_sources_timed": int(sources.size), "exact_seconds_per_source": exact_per_source,
            "exact_all_pairs_seconds_per_shape_extrapolated": exact_per_source * n,
            "exact_all_pairs_cpu_seconds_per_shape_extrapolated": exact_cpu_per_source * n,
            "load_average_after": list(os.getloadavg()),
            "heat_all_pairs_seconds_per_shape": heat_seconds,
            "submatrix_seconds_per_lower_resolution_remesh": sub_seconds, "submatrix_shape": list(sub.shape),
            "note": "geodesics=original computes the exact matrix once per shape (cached); every lower-resolution "
                    "remesh then costs only the sub-matrix. Per-remesh heat matrices cost the heat time per remesh."}


def truncated_soft_map(pi, k: int):
    """Pi with only its k largest entries per row kept, rows renormalized (differentiable in the kept entries)."""
    import torch

    idx = pi.topk(k, dim=1).indices
    kept = torch.zeros_like(pi).scatter(1, idx, pi.gather(1, idx))
    return kept / kept.sum(1, keepdim=True)


def geo_topk_accuracy(golden: Path, ks=(16, 64, 256), sigmas=(100.0, 400.0, 1600.0)) -> dict:
    """Accuracy cost of a top-k truncated soft map in the geodesic term, on the golden pairs.

    Soft maps from the original's features (the untrained network) at the published sigma 100, and sharper maps
    (sigma 400, 1600) standing in for a trained network's; per k: the mass the k largest entries keep, the
    relative error of the loss value and the cosine between the truncated and the full gradient dE/dPi.
    """
    import torch

    from shapecorr.losses.geodesic_distortion import geodesic_distortion_loss

    rows = {}
    for pair in PAIRS:
        inp, out = np.load(golden / f"inputs_{pair}.npz"), np.load(golden / f"outputs_{pair}.npz")
        sim = torch.from_numpy(out["feat_x"]).double() @ torch.from_numpy(out["feat_y"]).double().T
        dx, dy = (torch.from_numpy(inp[f"geodesic_{s}"]).double() for s in "xy")
        sim.requires_grad_(True)
        for sigma in sigmas:
            # gradients w.r.t. the similarities (the softmax input): a row-constant part of dE/dPi is meaningless
            pi = torch.softmax(sigma * sim, dim=1)
            full = geodesic_distortion_loss(pi, dx, dy)
            (g_full,) = torch.autograd.grad(full, sim, retain_graph=True)
            for k in ks:
                pik = truncated_soft_map(pi, k)
                trunc = geodesic_distortion_loss(pik, dx, dy)
                (g_k,) = torch.autograd.grad(trunc, sim, retain_graph=True)
                cos = float((g_k * g_full).sum() / (g_k.norm() * g_full.norm()))
                mass = float(pi.detach().topk(k, dim=1).values.sum(1).mean())
                full_v, trunc_v = float(full.detach()), float(trunc.detach())
                rows[f"{pair} sigma={sigma:g} k={k}"] = {
                    "kept_mass_mean": mass, "loss_full": full_v, "loss_topk": trunc_v,
                    "loss_relative_error": abs(trunc_v - full_v) / full_v, "gradient_cosine": cos}
    return rows


def geo_term_seconds(n: int = WORKING_RESOLUTION, repeats: int = 3) -> dict:
    """Wall seconds of the full geodesic term, forward + backward, at n x n (the part a truncation could save)."""
    import torch

    from shapecorr.losses.geodesic_distortion import geodesic_distortion_loss

    gen = torch.Generator().manual_seed(0)
    pts = torch.randn(n, 3, generator=gen)
    dist = torch.cdist(pts, pts)
    dist = 0.5 * (dist + dist.T)  # symmetric, as geodesic matrices (the loss's fast path)
    logits = torch.randn(n, n, generator=gen)
    times, cpu = [], []
    for _ in range(repeats + 1):
        pi = torch.softmax(logits, dim=1).requires_grad_(True)
        start, start_cpu = time.perf_counter(), time.process_time()
        geodesic_distortion_loss(pi, dist, dist).backward()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return {"n": n, "threads": torch.get_num_threads(), "seconds_fwd_bwd_median": float(np.median(times[1:])),
            "cpu_seconds_fwd_bwd_median": float(np.median(cpu[1:])),
            "load_average_after": list(os.getloadavg())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--golden", default=os.environ.get("SHAPECORR_NEUROMORPH_GOLDEN"),
                        help="folder of the golden files (default: $SHAPECORR_NEUROMORPH_GOLDEN)")
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder for the geodesic timing (default: $SHAPECORR_FAUST_R; skipped if unset)")
    parser.add_argument("--exact-sources", type=int, default=40, help="sources timed for the exact geodesics")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)
    if not args.golden:
        parser.error("pass --golden or set SHAPECORR_NEUROMORPH_GOLDEN")
    import tempfile

    import torch

    from shapecorr.nn.neuromorph_weights import load_original_neuromorph_weights

    torch.set_num_threads(args.threads)
    golden = Path(args.golden)
    with tempfile.TemporaryDirectory() as tmp:
        model = build_model(tmp)
    load_original_neuromorph_weights(model.feature_net, model.interpolator, golden / "weights_seed0.npz")
    model.eval()
    parity = {}
    for pair in PAIRS:
        inp, out = np.load(golden / f"inputs_{pair}.npz"), np.load(golden / f"outputs_{pair}.npz")
        row = {}
        for name, dtype in (("float32", torch.float32), ("float64", torch.float64)):
            ours = run_pair(model, inp, out, dtype)
            row[name] = differences(ours, out)
            if name == "float32":
                row["arap_default_vs_original"] = {
                    "original": float(out["loss_arap"]),
                    "default_both_sides_scale_0.5": float(ours["default_arap_scale_0.5"]),
                    "former_default_scale_1.0": float(ours["default_arap_scale_1.0"]),
                    "ratio_default_to_original": float(ours["default_arap_scale_0.5"] / out["loss_arap"]),
                }
        parity[pair] = row
        worst = max(v["relative"] for k, v in row["float32"].items() if not k.startswith("grad_"))
        print(f"{pair}: worst relative difference (values) {worst:.2e}; grad norms "
              f"{row['float32']['grad_norm_feat_net']['relative']:.1e} / "
              f"{row['float32']['grad_norm_interpolator']['relative']:.1e}", flush=True)
    summary = {"settings": {"preset": "model=neuromorph_original", "weights": "weights_seed0.npz (original, seed 0)",
                            "threads": args.threads, "pairs": list(PAIRS),
                            "relative": "max abs difference / max abs of the original's array (scalars: relative "
                                        "difference); relative_frobenius for arrays"},
               "parity": parity}
    summary["geo_topk_accuracy"] = geo_topk_accuracy(golden)
    summary["geo_term_cost"] = geo_term_seconds()
    for key, row in summary["geo_topk_accuracy"].items():
        print(f"{key}: mass {row['kept_mass_mean']:.3f} loss err {row['loss_relative_error']:.3f} "
              f"grad cos {row['gradient_cosine']:.3f}", flush=True)
    print(summary["geo_term_cost"], flush=True)
    if args.faust_r:
        summary["geodesic_preprocessing"] = geodesic_cost(Path(args.faust_r), args.exact_sources)
        print(summary["geodesic_preprocessing"], flush=True)
    bench_common.write_report(args.out, bench_common.summary_report(
        "neuromorph_parity.py", sys.argv[1:] if argv is None else list(argv), summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
