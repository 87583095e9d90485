"""Benchmark: Hamiltonian shape interpolation vs linear blend (vs NeuroMorph) along t, on FAUST_r and synthetic pairs.

    OMP_NUM_THREADS=1 python benchmarks/hamiltonian_interpolation.py --faust-r /path/to/FAUST_r \
        [--neuromorph-weights $SHAPECORR_NEUROMORPH_GOLDEN/weights_seed0.npz | --neuromorph-ckpt CKPT] \
        [--faust-pairs 3] [--synthetic-pairs 3] [--n-modes 4] [--iterations 30] [--samples 500]

For every dataset and method the pairs are evaluated with the project's evaluation (``shapecorr.eval.pair_pool``
and ``shapecorr.eval.reports``, the code behind ``evaluate.py``) at the times ``--times`` (default 0, 0.125, ...,
1, 1.25, 1.5), so the numbers are those ``evaluate.py`` writes:

* datasets: ``--faust-pairs`` evenly spaced ordered pairs of the FAUST_r test shapes (tr_reg_080..099; folder from
  ``--faust-r`` or ``$SHAPECORR_FAUST_R``), and ``--synthetic-pairs`` evenly spaced test pairs of the embedded
  synthetic dataset (``data=synthetic``, ``--synthetic-preset``; generated into the cache on first use);
* maps: the ground truth (``model=identity_gt``: the .vts points, every other vertex like its nearest one);
* methods: ``hamiltonian`` (``model=hamiltonian`` at a REDUCED setting, see below), ``linear_blend``
  (``model=linear_blend`` on the same maps) and, on FAUST_r only and when weights are given, ``neuromorph``
  (``model=neuromorph_original`` with the original's weights loaded by ``load_original_neuromorph_weights``, e.g. the
  initial (untrained) seed-0 weights of the golden folder,
  or a trained checkpoint); NeuroMorph computes its own maps;
* per method and dataset: the per-time means over pairs of the conformal distortion (scale-invariant,
  docs/evaluation.md §3) and of the volume score ``V_t/V_0 + V_0/V_t - 2``, the two-sided and one-sided Chamfer
  distance of X(1) to Y (fractions of sqrt(area(Y))), seconds per pair (the matcher alone, one thread with
  OMP_NUM_THREADS=1).

Outputs: ``benchmarks/results/hamiltonian_interpolation.json`` (settings, curves, summary table, machine), the
curves ``hamiltonian_interpolation_curves.png`` (both datasets, every method), and renders of the first pair of
each dataset at t = 0, 0.5, 1, 1.5 (extrapolation) and the target, one row per method
(``hamiltonian_interpolation_<dataset>.png``; under ``--work-dir`` unless ``--render-dir`` is given).

Reduced setting: the published one (K = 8 modes per axis, i.e. 1536 fields, 2000 samples, 100 Adam iterations,
16 steps) takes about 30 min per FAUST_r pair on one core of this CPU; the defaults here (K = 4, 500 samples,
30 iterations, 16 steps) finish the whole benchmark in minutes. They are recorded in the JSON and the numbers are
NOT those of the published setting.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
RESULT = RESULTS / "hamiltonian_interpolation.json"
DEFAULT_TIMES = (0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0, 1.25, 1.5)
#: Frames of the renders (t = 1.5 is the extrapolation).
RENDER_TIMES = (0.0, 0.5, 1.0, 1.5)
#: Times of the summary table.
TABLE_TIMES = (0.5, 1.0, 1.5)
PUBLISHED = {"n_modes": 8, "samples": 2000, "iterations": 100, "n_steps": 16}


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        return compose("evaluate", overrides=overrides)


def _at(curves: dict, key: str, t: float) -> float | None:
    times = np.asarray(curves["times"])
    k = int(np.abs(times - t).argmin())
    return curves[key][k] if abs(times[k] - t) < 1e-6 else None


def evaluate_method(data_overrides: list[str], model_overrides: list[str], out: Path, max_pairs: int,
                    times: tuple[float, ...], weights: str | None = None) -> dict:
    """Evaluate one method on ``max_pairs`` test pairs of a dataset; returns the aggregated metrics (+ pairs)."""
    import hydra
    import torch

    from shapecorr.cli.matcher_factory import build_matcher
    from shapecorr.data.datasets import PairDataset
    from shapecorr.data.operators import required_request
    from shapecorr.eval import pair_pool, protocol, reports
    from shapecorr.eval.records import load_record

    shutil.rmtree(out, ignore_errors=True)  # fresh: evaluate_pairs would skip the pairs of an earlier run
    cfg = _compose([*data_overrides, *model_overrides, f"output_dir={out}", "progress=false"])
    matcher = build_matcher(cfg, torch.device("cpu"))
    if weights is not None:
        from shapecorr.nn.neuromorph_weights import load_original_neuromorph_weights

        load_original_neuromorph_weights(matcher.feature_net, matcher.interpolator, weights)
        matcher.eval()
    dm = hydra.utils.instantiate(cfg.data, _convert_="object")
    dm.with_operators(required_request(matcher))
    shapes = dm.shapes("test")
    shapes.prepare(num_workers=1, geodesics="heat", progress=False)
    pairs = list(PairDataset(shapes, pairs=dm.pairs("test").pairs, max_pairs=max_pairs).pairs)
    settings = protocol.EvalSettings(geodesics="heat", interp_times=times, write_maps=False)
    records = pair_pool.evaluate_pairs(matcher, shapes, pairs, out, settings, workers=0, progress=False)
    loaded = [load_record(out, r.source, r.target) for r in records]
    metrics = reports.aggregate(records, [e for _, e, _ in loaded], [s for _, _, s in loaded])
    metrics["pairs"] = [[r.source, r.target] for r in records]
    metrics["per_pair_seconds"] = [r.seconds for r in records]
    return metrics


def summarize(metrics: dict) -> dict:
    """The summary row of one method on one dataset."""
    curves = metrics["interp_curves"]
    row = {
        "n_pairs": metrics["n_pairs"],
        "seconds_per_pair": metrics["seconds_per_pair"],
        "mean_chamfer": metrics["mean_chamfer"],
        "mean_chamfer_one_sided": metrics["mean_chamfer_one_sided"],
        "mean_deformation_conformal_distortion_0_to_1": metrics["mean_deformation_conformal_distortion"],
        "mean_geodesic_error_of_map": metrics["mean_geodesic_error"],
    }
    for t in TABLE_TIMES:
        row[f"conformal_distortion_t{t:g}"] = _at(curves, "conformal_distortion", t)
        row[f"volume_score_t{t:g}"] = _at(curves, "volume_score", t)
    return row


def render_first_pair(path: Path, runs: dict[str, Path], pair: tuple[str, str], times: tuple[float, ...],
                      target_mesh) -> Path:
    """One row per method: the frames of ``pair`` at :data:`RENDER_TIMES` (from the written PLYs) and the target."""
    from matplotlib.figure import Figure

    from shapecorr.data.datasets import pair_name
    from shapecorr.data.io import read_mesh
    from shapecorr.viz.render import PANEL_SIZE, coordinate_colors, draw_mesh, save_figure

    index = [int(np.abs(np.asarray(times) - t).argmin()) for t in RENDER_TIMES]
    n_cols = len(RENDER_TIMES) + 1
    scale = 0.6
    fig = Figure(figsize=(scale * PANEL_SIZE[0] * n_cols, scale * PANEL_SIZE[1] * len(runs)), dpi=80)
    for row, (method, out) in enumerate(runs.items()):
        seq = out / "interp" / pair_name(*pair)
        # no validation: the frames of a linear blend onto a non-injective map have collapsed faces
        frames = [read_mesh(seq / f"t_{k:02d}.ply", validate=False) for k in index]
        colors = coordinate_colors(frames[0][0])
        for col, ((v, f), t) in enumerate(zip(frames, RENDER_TIMES)):
            ax = fig.add_subplot(len(runs), n_cols, row * n_cols + col + 1, projection="3d")
            draw_mesh(ax, v, f, colors, title=f"{method} t = {t:g}")
        ax = fig.add_subplot(len(runs), n_cols, row * n_cols + n_cols, projection="3d")
        vy, fy = target_mesh
        draw_mesh(ax, vy, fy, np.full((len(vy), 3), 0.7), title=f"target {pair[1]}")
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.95, wspace=0.0, hspace=0.1)
    return save_figure(fig, path)


def curves_png(path: Path, datasets: dict[str, dict[str, dict]]) -> Path:
    """Conformal distortion and volume score vs t: one row per dataset, one line per method."""
    from matplotlib.figure import Figure

    from shapecorr.viz.interp_curves import PANELS, draw_interp_curves
    from shapecorr.viz.render import save_figure

    fig = Figure(figsize=(9.0, 3.2 * len(datasets)), dpi=90)
    for r, (dataset, methods) in enumerate(datasets.items()):
        axes = [fig.add_subplot(len(datasets), len(PANELS), r * len(PANELS) + c + 1) for c in range(len(PANELS))]
        draw_interp_curves(axes, methods)
        for ax in axes:
            ax.set_title(dataset, fontsize="small")
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default $SHAPECORR_FAUST_R; FAUST_r is skipped without it)")
    parser.add_argument("--faust-pairs", type=int, default=3, help="evenly spaced FAUST_r test pairs")
    parser.add_argument("--synthetic-pairs", type=int, default=3, help="evenly spaced synthetic test pairs (0: none)")
    parser.add_argument("--synthetic-preset", default="default", help="data.synthetic.preset: default | tiny | large")
    parser.add_argument("--neuromorph-weights", default=None,
                        help="the original NeuroMorph's weights (.npz/.pt, load_original_neuromorph_weights)")
    parser.add_argument("--neuromorph-ckpt", default=None, help="a trained model=neuromorph checkpoint instead")
    parser.add_argument("--n-modes", type=int, default=4, help="Hamiltonian modes per axis K (published 8)")
    parser.add_argument("--samples", type=int, default=500, help="Hamiltonian farthest-point samples (published 2000)")
    parser.add_argument("--iterations", type=int, default=30, help="Hamiltonian Adam iterations (published 100)")
    parser.add_argument("--n-steps", type=int, default=16, help="Hamiltonian time steps to t = 1 (published 16)")
    parser.add_argument("--times", type=float, nargs="+", default=list(DEFAULT_TIMES), help="frame times")
    parser.add_argument("--work-dir", default=str(REPO / "outputs" / "bench_hamiltonian"), help="evaluation outputs")
    parser.add_argument("--render-dir", default=None, help="folder of the renders (default: --work-dir)")
    parser.add_argument("--output", default=str(RESULT), help="results JSON")
    parser.add_argument("--curves-png", default=str(RESULTS / "hamiltonian_interpolation_curves.png"))
    args = parser.parse_args(argv)
    times = tuple(sorted(set(args.times) | set(RENDER_TIMES)))
    work = Path(args.work_dir)
    render_dir = Path(args.render_dir or work)
    ham = [f"model.n_modes={args.n_modes}", f"model.samples={args.samples}", f"model.iterations={args.iterations}",
           f"model.n_steps={args.n_steps}"]
    datasets: dict[str, list[str]] = {}
    if args.faust_r:
        datasets["faust_r"] = ["data=faust_r", f"data.root={args.faust_r}", "data.operators.n_eig=30"]
    if args.synthetic_pairs > 0:
        datasets["synthetic"] = ["data=synthetic", f"data.synthetic.preset={args.synthetic_preset}",
                                 "data.operators.n_eig=30"]
    if not datasets:
        parser.error("nothing to run: give --faust-r (or $SHAPECORR_FAUST_R) and/or --synthetic-pairs > 0")
    results, curves, renders = {}, {}, {}
    for dataset, data in datasets.items():
        n = args.faust_pairs if dataset == "faust_r" else args.synthetic_pairs
        methods = {"hamiltonian": (["model=hamiltonian", *ham], None),
                   "linear_blend": (["model=linear_blend", "model@model.matcher=identity_gt"], None)}
        if dataset == "faust_r" and (args.neuromorph_weights or args.neuromorph_ckpt):
            nm = ["model=neuromorph_original", "model.geodesics=heat"]
            if args.neuromorph_ckpt:
                methods["neuromorph"] = ([*nm, f"ckpt_path={args.neuromorph_ckpt}"], None)
            else:
                methods["neuromorph"] = (nm, args.neuromorph_weights)
        results[dataset], curves[dataset], outs = {}, {}, {}
        for method, (overrides, weights) in methods.items():
            out = work / dataset / method
            t0 = time.perf_counter()
            metrics = evaluate_method(data, overrides, out, n, times, weights)
            row = summarize(metrics)
            row["wall_seconds"] = time.perf_counter() - t0
            row["overrides"] = overrides
            row["pairs"] = metrics["pairs"]
            row["per_pair_seconds"] = metrics["per_pair_seconds"]
            results[dataset][method], curves[dataset][method], outs[method] = row, metrics["interp_curves"], out
            print(dataset, method, json.dumps({k: v for k, v in row.items() if k not in ("overrides", "pairs")}),
                  flush=True)
        first = tuple(results[dataset]["hamiltonian"]["pairs"][0])
        target = _target_mesh(data, first[1])
        renders[dataset] = str(render_first_pair(render_dir / f"hamiltonian_interpolation_{dataset}.png", outs,
                                                 first, times, target))
    png = curves_png(Path(args.curves_png), curves)
    summary = {
        "benchmark": "hamiltonian_interpolation",
        "settings": {
            "hamiltonian": {"n_modes": args.n_modes, "fields": 3 * args.n_modes ** 3, "samples": args.samples,
                            "iterations": args.iterations, "n_steps": args.n_steps,
                            "other": "configs/interpolator/hamiltonian.yaml (published lr 0.02, lambda_reg 20, knn 5, "
                                     "lambda_inertia 0.3)"},
            "reduced": True,
            "published": PUBLISHED,
            "times": list(times),
            "maps": "ground truth (model=identity_gt) for hamiltonian and linear_blend; NeuroMorph its own",
            "neuromorph": ({"weights": args.neuromorph_weights, "ckpt": args.neuromorph_ckpt,
                            "preset": "model=neuromorph_original model.geodesics=heat"}
                           if (args.neuromorph_weights or args.neuromorph_ckpt) else None),
            "geodesics": "heat", "threads": os.environ.get("OMP_NUM_THREADS"),
        },
        "notes": [
            "REDUCED Hamiltonian setting (see settings; published K=8, 2000 samples, 100 iterations takes ~30 min "
            "per FAUST_r pair on one core): numbers are not those of the published setting.",
            "conformal distortion: our scale-invariant (K - 1/K)^2, area-weighted, clamp 10 (docs/evaluation.md "
            "§3), not comparable with the papers' numbers; volume score V_t/V_0 + V_0/V_t - 2; Chamfer: X(1) vs "
            "Y's vertices, mean nearest-vertex distance / sqrt(area(Y)) (two-sided: both ways summed).",
            "t > 1 is an extrapolation (linear blend: the straight lines continued; Hamiltonian: the simulation "
            "continued; NeuroMorph: its interpolator evaluated at t).",
            "seconds_per_pair: the matcher alone (map + frames), one thread with OMP_NUM_THREADS=1.",
            "a few pairs only: preliminary numbers.",
        ],
        "results": results,
        "curves": curves,
        "curves_png": str(png),
        "renders": renders,
    }
    result = bench_common.summary_report("hamiltonian_interpolation.py", sys.argv[1:] if argv is None else list(argv),
                                         summary)
    bench_common.write_report(args.output, result)
    return result


def _target_mesh(data_overrides: list[str], name: str):
    """``(verts, faces)`` of shape ``name`` of the dataset, in its input units (as the written frames)."""
    import hydra

    dm = hydra.utils.instantiate(_compose([*data_overrides, "model=identity_gt"]).data, _convert_="object")
    shapes = dm.shapes("test")
    mesh = shapes.load_shape(list(shapes.names).index(name))
    return mesh.verts.numpy(), mesh.faces.numpy()


if __name__ == "__main__":
    main()
