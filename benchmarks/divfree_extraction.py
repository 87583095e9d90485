"""Benchmark: the divergence-free matcher's final extraction, ``flow`` against ``spectral``, on FAUST_r test pairs.

    OMP_NUM_THREADS=1 python benchmarks/divfree_extraction.py --faust-r DIR [--max-pairs 40 | --pairs 096-098,...]
        [--kw '{"samples": [500, 1000, 1000]}'] [--store DIR] [--out FILE]

Each pair is fitted once (``DivFreeMatcher.fit``, the config defaults updated by ``--kw``; the fit does not depend
on the extraction) and its two final readings are scored against the ground truth (which only scores): the flow's
product-space maps (``extraction: flow``) and the spectral extraction (``extraction: spectral``, the default,
docs/divfree.md §5), run from the same fit. ``--max-pairs`` takes the pairs of ``mirror_flips.py``. The fitted
state of each pair (deformed x, box coordinates, both flow maps, per-point errors) is stored under ``--store``,
so an interrupted run resumes and other extraction settings can be scored without refitting. Recorded per pair:
both errors, the errors against the mirrored ground truth, the per-pair medians over points, fit and extraction
seconds; per reading: mean, median over pairs, median over all points pooled, mean / pooled median, mirrored
pairs. Written to ``--out`` (default ``benchmarks/results/divfree_extraction.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

import bench_common
from mirror_flips import TEST_SHAPES, named_pairs, test_pairs

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "divfree_extraction.json"


def load_dataset(root: str, matcher):
    """FAUST_r test shapes with the operators ``matcher`` requests (the data config's normalization and params)."""
    from shapecorr.data.datasets import ShapeDataset
    from shapecorr.data.operators import OperatorConfig
    from shapecorr.data.shape import Normalization

    request = {name: dict(params) for name, params in matcher.required_operators.items()}
    request.setdefault("eigenbasis", {"k": 200})
    ops = OperatorConfig(request=request, laplacian="cotan",
                         params={"shot": {"radius_factor": 0.05}, "wks": {"count": 100, "k": None},
                                 "hks": {"count": 100, "k": None}})  # configs/data/folder.yaml
    return ShapeDataset(root, names=TEST_SHAPES, normalization=Normalization(target_area=4 / 9, center="area"),
                        operators=ops)


def fit_pair(flow_matcher, x, y, path: Path) -> dict:
    """Fit once (``extraction: flow``); store the deformed x, the box coordinates and the flow's two maps."""
    start = time.perf_counter()
    with torch.enable_grad():
        fit = flow_matcher.fit(x, y)
    with torch.no_grad():
        moved, p2p, p2p_inv = flow_matcher._maps(fit, x, y)
    arrays = {"moved": moved.numpy(), "bx": fit["box_verts"][0].numpy(), "by": fit["box_verts"][1].numpy(),
              "p2p": p2p.numpy(), "p2p_inv": p2p_inv.numpy(), "fit_seconds": time.perf_counter() - start,
              "energy_align": fit["energies"].get("align", np.nan)}
    np.savez(path, **arrays)
    return arrays


def score_pair(matcher, x, y, state, dist) -> dict:
    """Errors of the flow reading and of the spectral extraction from the stored fit."""
    from shapecorr.eval.scoring import score_map
    from shapecorr.geometry.normals import vertex_normals

    moved, bx, by = (torch.from_numpy(np.asarray(state[k])) for k in ("moved", "bx", "by"))
    p2p, p2p_inv = (torch.from_numpy(np.asarray(state[k])).long() for k in ("p2p", "p2p_inv"))
    level = matcher.levels[-1]
    dx, dy = matcher._descriptor(x), matcher._descriptor(y)
    emb_x = matcher._embed(moved, vertex_normals(moved, x.faces), dx, level)
    emb_y = matcher._embed(by, vertex_normals(by, y.faces), dy, level)
    start = time.perf_counter()
    spec, _ = matcher._spectral_maps(bx, by, emb_x, emb_y, p2p, p2p_inv, x, y)
    seconds = time.perf_counter() - start
    flow, spectral = score_map(p2p, x, y, dist), score_map(spec, x, y, dist)
    return {"error_flow": float(flow["errors"].mean()), "error_mirror_flow": float(flow["errors_sym"].mean()),
            "median_point_flow": float(np.median(flow["errors"])), "error": float(spectral["errors"].mean()),
            "error_mirror": float(spectral["errors_sym"].mean()), "median_point": float(np.median(spectral["errors"])),
            "fit_seconds": float(state["fit_seconds"]), "extraction_seconds": seconds,
            "energy_align": float(state["energy_align"]),
            "_points": (flow["errors"], spectral["errors"])}


def summarize(rows: list[dict], key: str, mirror_key: str, pooled: np.ndarray) -> dict:
    err = np.array([r[key] for r in rows])
    median_points = float(np.median(pooled))
    return {"mean_geodesic_error": float(err.mean()), "median_geodesic_error": float(np.median(err)),
            "median_point_error": median_points, "mean_over_median_point": float(err.mean() / median_points),
            "mirrored_pairs": [r["pair"] for r in rows if r[mirror_key] < r[key]]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"))
    parser.add_argument("--max-pairs", type=int, default=40)
    parser.add_argument("--pairs", help="comma-separated pairs xxx-yyy instead of --max-pairs")
    parser.add_argument("--kw", default='{"samples": [500, 1000, 1000]}', help="DivFreeMatcher keyword arguments")
    parser.add_argument("--store", default=str(REPO / "outputs" / "bench" / "divfree_extraction"))
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)
    if not args.faust_r:
        parser.error("set --faust-r or SHAPECORR_FAUST_R to the FAUST_r folder")
    from shapecorr.axiomatic.divfree import DivFreeMatcher

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    matcher = DivFreeMatcher(**{**json.loads(args.kw), "extraction": "spectral"})
    flow_matcher = DivFreeMatcher(**{**json.loads(args.kw), "extraction": "flow"})
    data = load_dataset(args.faust_r, matcher)
    store = Path(args.store)
    store.mkdir(parents=True, exist_ok=True)
    pairs = named_pairs(args.pairs) if args.pairs else test_pairs(args.max_pairs)
    rows = []
    for a, b in pairs:
        name = f"{a[-3:]}-{b[-3:]}"
        x, y = data[data.index(a)], data[data.index(b)]
        path = store / f"{name}.npz"
        if path.is_file():
            with np.load(path) as stored:
                state = dict(stored)
        else:
            state = fit_pair(flow_matcher, x, y, path)
        rows.append({"pair": name, **score_pair(matcher, x, y, state, data.ground_truth_geodesics(data.index(b)))})
        r = rows[-1]
        print(f"{name}: flow {100 * r['error_flow']:.2f} spectral {100 * r['error']:.2f} (x100), fit "
              f"{r['fit_seconds']:.0f} s, extraction {r['extraction_seconds']:.1f} s", flush=True)
    pooled_flow = np.concatenate([r["_points"][0] for r in rows])
    pooled_spec = np.concatenate([r.pop("_points")[1] for r in rows])
    summary = {"pairs": args.pairs or f"{len(pairs)} evenly spaced of the 380 FAUST_r test pairs",
               "matcher": json.loads(args.kw), "n_pairs": len(rows),
               "flow": summarize(rows, "error_flow", "error_mirror_flow", pooled_flow),
               "spectral": summarize(rows, "error", "error_mirror", pooled_spec), "per_pair": rows,
               "units": "errors: geodesic distance / sqrt(area of the target), heat geodesics (x100 = percent); "
                        "median_point_error: over all points of all pairs pooled"}
    for key in ("flow", "spectral"):
        s = summary[key]
        print(f"{key}: mean {100 * s['mean_geodesic_error']:.2f} median over pairs "
              f"{100 * s['median_geodesic_error']:.2f} over points {100 * s['median_point_error']:.2f}, "
              f"{s['mean_over_median_point']:.2f}x, mirrored {len(s['mirrored_pairs'])}")
    report = bench_common.summary_report("divfree_extraction.py", sys.argv[1:] if argv is None else list(argv), summary)
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
