"""Benchmark: Deep Shells parity with the original implementation, and speed.

    python benchmarks/deep_shells_parity.py --golden $SHAPECORR_DEEP_SHELLS_GOLDEN --faust-r $SHAPECORR_FAUST_R

For each golden pair (inputs, published weights and the original's outputs; see the golden README):

1. features: our spectral filter bank with the published weights vs the original's ``features_*``
   (the golden eigenvalues are in the doubled convention and are halved before use);
2. maps: our test pipeline (feature Sinkhorn, one OT level at k = 6, 40 refinement levels 6..499) with
   ``DeepShellsConfig.original()`` vs the original's maps (fraction of identical vertices), and the mean
   geodesic error of both (Princeton protocol, FAUST_r ``.vts``, heat-method geodesics on the golden target,
   / sqrt(area), in percent); also with shapecorr's default flags;
3. speed: wall time of a query (features + pipeline; median over ``--repeats`` after a warm-up) and of a
   training forward+backward (2000 random samples per shape, published feature net, 8 OT levels) with
   the fast Sinkhorn and with the op-by-op log-domain one (ratio in the same run).

The machine is shared: the load average before and after is recorded; CPU times are recorded as well.
Results go to ``benchmarks/results/deep_shells_parity.json`` with the command, date, machine and versions.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from pathlib import Path

import bench_common

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "deep_shells_parity.json"
PAIRS = ("tr_reg_080__tr_reg_081", "tr_reg_090__tr_reg_095")
#: Errors of the original maps stated in the golden README (percent), for reference in the report.
PUBLISHED_ERRORS = {"tr_reg_080__tr_reg_081": 0.97, "tr_reg_090__tr_reg_095": 0.90}
#: Original query time per pair on the 2-core reference CPU (golden README), seconds.
ORIGINAL_QUERY_SECONDS = (12.8, 15.3)
#: Training samples per shape (Deep Shells subsample_num).
TRAIN_SAMPLES = 2000


def _timed(fn, repeats: int):
    """Median wall and CPU seconds of ``fn()`` over ``repeats`` calls after one warm-up; last result."""
    walls, cpus, result = bench_common.timed(fn, repeats)
    return bench_common.median(walls), bench_common.median(cpus), result


def load_pair(golden: Path, pair: str):
    """Spectral shapes, SHOT, shapecorr-convention eigenvalues and the original's outputs of a golden pair."""
    from shapecorr.geometry.spectral_shape import make_spectral_shape

    inputs = np.load(golden / f"inputs_{pair}.npz")
    output = np.load(golden / f"original_output_{pair}.npz")
    names = pair.split("__")
    shapes, shot, evals = {}, {}, {}
    for side, name in zip("xy", names):
        shapes[side] = make_spectral_shape(torch.from_numpy(inputs[f"{side}_verts"]),
                                           torch.from_numpy(inputs[f"{side}_faces"]),
                                           torch.from_numpy(inputs[f"{side}_evecs"]),
                                           torch.from_numpy(inputs[f"{side}_mass"]), name=name)
        shot[side] = torch.from_numpy(inputs[f"{side}_shot"])
        # golden eigenvalues use the full-cot (doubled) convention; shapecorr's are half of them
        evals[side] = torch.from_numpy(inputs[f"{side}_evals"]) / 2.0
    return shapes, shot, evals, {k: output[k] for k in output.files}


def geodesic_errors_percent(verts_y, faces_y, maps: dict, ref_x, ref_y) -> dict:
    """Mean Princeton geodesic error (percent of sqrt(area_y)) of several maps X -> Y.

    Distances only from the ground-truth vertices that some map misses (heat method, potpourri3d through
    ``shapecorr.geometry.geodesics``).
    """
    from shapecorr.geometry.mesh import triangle_areas
    from shapecorr.geometry.geodesics import geodesic_distances

    need = np.unique(np.concatenate([ref_y[np.asarray(p)[ref_x] != ref_y] for p in maps.values()]))
    dist = geodesic_distances(verts_y, faces_y, need, method="heat") if need.size else np.zeros((0, len(verts_y)))
    row = np.full(len(verts_y), -1, dtype=np.int64)
    row[need] = np.arange(need.size)
    sqrt_area = float(np.sqrt(triangle_areas(verts_y, faces_y).sum()))
    out = {}
    for name, p2p in maps.items():
        pred = np.asarray(p2p)[ref_x]
        err = np.zeros(ref_x.shape[0])
        miss = pred != ref_y
        err[miss] = dist[row[ref_y[miss]], pred[miss]]
        out[name] = float(100.0 * err.mean() / sqrt_area)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--golden", default=os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN"),
                        help="folder of the golden files (default: $SHAPECORR_DEEP_SHELLS_GOLDEN)")
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder with corres/*.vts (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repetitions after a warm-up")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch intra-op threads")
    parser.add_argument("--skip-reference-sinkhorn", action="store_true",
                        help="do not time the training step with the slow op-by-op Sinkhorn")
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)
    if not args.golden:
        parser.error("pass --golden or set SHAPECORR_DEEP_SHELLS_GOLDEN")
    torch.set_num_threads(args.threads)

    from dataclasses import replace

    from shapecorr.data.io import read_vts
    from shapecorr.matching.deep_shells import DeepShellsConfig, deep_shells_layer, deep_shells_query, random_samples
    from shapecorr.nn.spectral_conv import SpectralFilterBank, load_original_deep_shells_weights

    golden = Path(args.golden)
    net = SpectralFilterBank()
    load_original_deep_shells_weights(net, golden / "published_weights_faust_scape_ep20.pth")
    net.eval()
    original_cfg = DeepShellsConfig.original()
    default_cfg = DeepShellsConfig()
    load_before = os.getloadavg()
    report = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {"cpu": bench_common.cpu_model(), "cores": os.cpu_count(), "gpu": None,
                    "torch_threads": args.threads,
                    "load_average_before": list(load_before)},
        "versions": bench_common.package_versions(),
        "settings": {"repeats": args.repeats, "train_samples": TRAIN_SAMPLES, "geodesics": "heat (potpourri3d)",
                     "original_query_seconds": list(ORIGINAL_QUERY_SECONDS)},
        "pairs": {},
    }

    for pair in PAIRS:
        shapes, shot, evals, orig = load_pair(golden, pair)
        x, y = shapes["x"], shapes["y"]
        entry: dict = {}

        def features():
            with torch.no_grad():
                return {s: net(shot[s], shapes[s].evecs, evals[s], shapes[s].mass) for s in "xy"}

        wall, cpu, feats = _timed(features, args.repeats)
        for s in "xy":
            ref = torch.from_numpy(orig[f"features_{s}"])
            entry[f"features_{s}_max_abs_diff"] = float((feats[s] - ref).abs().max())
            entry[f"features_{s}_max_abs"] = float(ref.abs().max())
        entry["features_seconds"] = wall

        def query(cfg):
            def run():
                f = features()
                return deep_shells_query(f["x"], f["y"], x, y, cfg)
            return run

        wall, cpu, match = _timed(query(original_cfg), args.repeats)
        entry["query_seconds"] = wall
        entry["query_cpu_seconds"] = cpu
        ours = match.map_x_to_y.numpy()
        ours_inv = match.map_y_to_x.numpy()
        entry["map_agreement_x_to_y"] = float((ours == orig["map_x_to_y"]).mean())
        entry["map_agreement_y_to_x"] = float((ours_inv == orig["map_y_to_x"]).mean())
        default_match = deep_shells_query(feats["x"], feats["y"], x, y, default_cfg)
        entry["map_agreement_x_to_y_default_flags"] = float(
            (default_match.map_x_to_y.numpy() == orig["map_x_to_y"]).mean())

        if args.faust_r:
            root = Path(args.faust_r) / "corres"
            name_x, name_y = pair.split("__")
            ref_x = read_vts(root / f"{name_x}.vts", x.n_verts)
            ref_y = read_vts(root / f"{name_y}.vts", y.n_verts)
            errors = geodesic_errors_percent(y.verts.numpy().astype(np.float64), y.faces.numpy(),
                                             {"ours": ours, "original": orig["map_x_to_y"],
                                              "ours_default_flags": default_match.map_x_to_y.numpy()},
                                             ref_x, ref_y)
            entry["geodesic_error_percent"] = errors
            entry["geodesic_error_difference_pp"] = errors["ours"] - errors["original"]
            entry["original_error_percent_readme"] = PUBLISHED_ERRORS[pair]

        gen = torch.Generator().manual_seed(0)

        def train_step(cfg):
            def run():
                sx, sy = random_samples(x.n_verts, TRAIN_SAMPLES, gen), random_samples(y.n_verts, TRAIN_SAMPLES, gen)
                net.zero_grad()
                fx = net(shot["x"], x.evecs, evals["x"], x.mass, rows=sx)
                fy = net(shot["y"], y.evecs, evals["y"], y.mass, rows=sy)
                out = deep_shells_layer(fx, fy, x, y, sx, sy, cfg)
                out.loss.backward()
                return out.loss.item()
            return run

        wall, cpu, _ = _timed(train_step(original_cfg), args.repeats)
        entry["train_step_seconds"] = wall
        entry["train_step_cpu_seconds"] = cpu
        if not args.skip_reference_sinkhorn:
            wall_ref, cpu_ref, _ = _timed(train_step(replace(original_cfg, sinkhorn_impl="reference")), args.repeats)
            entry["train_step_seconds_reference_sinkhorn"] = wall_ref
            entry["train_step_cpu_seconds_reference_sinkhorn"] = cpu_ref
            entry["train_step_speedup_vs_reference_sinkhorn"] = wall_ref / wall
        report["pairs"][pair] = entry
        print(pair, json.dumps(entry, indent=1), flush=True)

    report["machine"]["load_average_after"] = list(os.getloadavg())
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
