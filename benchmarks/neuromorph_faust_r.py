"""Benchmark: NeuroMorph on FAUST_r: learning curve, final correspondence numbers and the interpolation quality.

    python benchmarks/neuromorph_faust_r.py --launch [--variant published-loss|geodesic-map] [--run-dir DIR]
                                           [--faust-r DIR] [--threads 1]
    python benchmarks/neuromorph_faust_r.py --interpolation CKPT [--faust-r DIR] [--max-pairs N] [--out-json F]
    python benchmarks/neuromorph_faust_r.py --summarize RUN_DIR [--eval-dir DIR] [--untrained-dir DIR]
                                           [--interp-json F]

``--launch`` runs, one after the other (each a subprocess, ``OMP_NUM_THREADS=--threads``), then summarizes:

1. ``train.py experiment=neuromorph_faust_r`` with the CPU-budget overrides :data:`CPU_BUDGET_OVERRIDES` into
   ``RUN_DIR`` (two hours of one CPU core instead of the published 600 epochs x 6400 pairs, see below);
2. ``evaluate.py model=neuromorph ckpt_path=RUN_DIR/checkpoints/last.ckpt data=faust_r`` on all 380 ordered test
   pairs (``RUN_DIR/eval_test``; the network runs at the 2000-vertex working resolution stored in the checkpoint
   and the maps are carried back to the full meshes by nearest vertex);
3. the same with the untrained network (fresh weights of ``seed=0``) on every 5th pair (``RUN_DIR/eval_untrained``);
4. ``--interpolation`` on the final checkpoint (``RUN_DIR/interpolation.json``).

The CPU-budget run: "epochs" of 640 random training pairs (``limit_train_batches``; a fresh random subset each
epoch), gradients accumulated over 4 pairs (160 optimizer steps per epoch instead of ~40 at the published 16, so
that two hours make a few hundred steps), validation on 40 evenly spaced test pairs after every such epoch, and
the published schedule compressed to the run: T = 0 and lambda_geo = 50 for the first 6 epochs, then T = 1 and
lambda_geo = 0 (published: epochs 0-299 and 300-449 of 600, then T = 3 and 7). Remesh pool: 4 resolutions per
shape instead of 8, which halves the one-off remeshing/geodesics cost inside the budget.

``--variant geodesic-map`` trains with :data:`GEODESIC_MAP_OVERRIDES` instead: ``model.map_gradient=geodesic``
(only the geodesic term trains the soft maps, docs/benchmarks.md "NeuroMorph: why map_gradient exists"), Adam 1e-3,
the geodesic phase for 8 epochs, 1 h 55 min; its results go to ``results/neuromorph_faust_r_geodesic_map.json``.

``--interpolation`` compares, on the test pairs, NeuroMorph's interpolation at t = 0.5 with the linear blend of
the same model's correspondence: at the working resolution (what the network sees) with the soft target
``x + t (Pi y - x)`` and with the hard map ``x + t (y[p2p] - x)``, and at the full resolution (the frames
``evaluate.py`` writes: the displacement lifted barycentrically) against the hard-map blend. Scores: the
area-weighted conformal distortion (clamped at 10, as the evaluation) of each frame against x, and the Chamfer
distance (two-sided and one-sided, fractions of sqrt(area(y))) of X(1) to y.

Errors are the Princeton protocol's (geodesic distance / sqrt(area)), printed in percent as in the papers.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import bench_common
import numpy as np
from training_runs import PERCENT, markdown_tables, read_metrics, summarize_run

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "neuromorph_faust_r.json"
BASELINES = REPO / "benchmarks" / "results" / "eval_baselines.json"
#: Overrides of the CPU-budget run (besides ``experiment=neuromorph_faust_r`` and the run folder).
CPU_BUDGET_OVERRIDES = (
    "trainer.accumulate_grad_batches=4",
    "trainer.limit_train_batches=640",
    "trainer.max_epochs=100",
    "trainer.max_time=00:02:05:00",
    "trainer.check_val_every_n_epoch=1",
    "data.pairs.val.max_pairs=40",
    "checkpoint.every_n_epochs=1",
    "model.augment.variants=4",
    "callbacks.neuromorph_T.milestones=[[0,0],[6,1]]",
    "callbacks.neuromorph_lambda_geo.milestones=[[0,50.0],[6,0.0]]",
    "test=false",
)
#: The "geodesic-map" variant (``--variant geodesic-map``; docs/benchmarks.md, NeuroMorph section): only the
#: geodesic term trains the soft maps, Adam 1e-3, the geodesic phase (T = 0, lambda_geo = 50) for 8 epochs of 640
#: pairs, then T = 1 without it (the interpolator alone trains), 1 h 55 min.
GEODESIC_MAP_OVERRIDES = tuple(
    o for o in CPU_BUDGET_OVERRIDES if not o.startswith(("trainer.max_time", "callbacks."))
) + (
    "trainer.max_time=00:01:55:00",
    "callbacks.neuromorph_T.milestones=[[0,0],[8,1]]",
    "callbacks.neuromorph_lambda_geo.milestones=[[0,50.0],[8,0.0]]",
    "model.map_gradient=geodesic",
    "model.optimizer.lr=1.0e-3",
)
#: ``--variant``: training overrides and default results file.
VARIANTS = {
    "published-loss": (CPU_BUDGET_OVERRIDES, RESULT),
    "geodesic-map": (GEODESIC_MAP_OVERRIDES, REPO / "benchmarks" / "results" / "neuromorph_faust_r_geodesic_map.json"),
}
#: Published FAUST_r mean geodesic error of NeuroMorph without post-processing (Eisenberger et al. 2021), fraction.
PUBLISHED_FAUST_R_ERROR = 0.023
#: Time of the interpolation comparison and the conformal-distortion clamp of the evaluation.
MID_TIME, CLAMP = 0.5, 10.0


def launch_commands(run_dir: Path, faust_r: str | None, overrides=CPU_BUDGET_OVERRIDES) -> dict[str, list[str]]:
    """The train / evaluate command lines of ``--launch`` (see the module docstring); ``overrides`` are the
    training run's (one of :data:`VARIANTS`)."""
    data = [f"data.root={faust_r}"] if faust_r else []
    py = sys.executable
    return {
        "train": [py, "train.py", "experiment=neuromorph_faust_r", *overrides, *data,
                  f"hydra.run.dir={run_dir}"],
        "eval": [py, "evaluate.py", "model=neuromorph", f"ckpt_path={run_dir / 'checkpoints' / 'last.ckpt'}",
                 "data=faust_r", *data, f"output_dir={run_dir / 'eval_test'}", "write_interp=false",
                 f"hydra.run.dir={run_dir / 'eval_test'}"],
        "untrained": [py, "evaluate.py", "model=neuromorph", "model.query_resolution=2000", "data=faust_r", *data,
                      "max_pairs=76", f"output_dir={run_dir / 'eval_untrained'}", "write_interp=false",
                      f"hydra.run.dir={run_dir / 'eval_untrained'}"],
        "interpolation": [py, str(Path(__file__).resolve()), "--interpolation",
                          str(run_dir / "checkpoints" / "last.ckpt"), *(["--faust-r", faust_r] if faust_r else []),
                          "--out-json", str(run_dir / "interpolation.json")],
    }


# -- interpolation quality ---------------------------------------------------------------------------------------
def interpolation_pair(model, x, y) -> dict[str, float]:
    """Scores of one ordered pair (see the module docstring); ``model`` is an eval-mode NeuroMorph.

    Uses the model's working-resolution helpers (``_working``, ``_soft_target``) to reach ``Pi y``, which
    ``match`` does not return.
    """
    import torch

    from shapecorr.eval import metrics
    from shapecorr.geometry.mesh_graph import undirected_edges
    from shapecorr.matching.baselines import LinearBlend
    from shapecorr.matching.softmax import hard_maps

    def distortion(rest, faces, frame) -> float:
        return metrics.mean_conformal_distortion(rest.double().numpy(), faces.numpy(), frame.double().numpy(), CLAMP)

    def chamfers(points, target_verts, target_faces) -> tuple[float, float]:
        scale = np.sqrt(metrics.surface_area(target_verts.double().numpy(), target_faces.numpy()))
        a, b = points.double().numpy(), target_verts.double().numpy()
        return (metrics.chamfer_distance(a, b) / scale, metrics.chamfer_distance(a, b, one_sided=True) / scale)

    times = torch.tensor([MID_TIME, 1.0])
    with torch.no_grad():
        wx, _ = model._working(x)
        wy, _ = model._working(y)
        edges_x = undirected_edges(wx.faces, wx.shape.n_verts)
        feat_x, feat_y = model.features(wx, edges_x), model.features(wy)
        p2p, _ = hard_maps(feat_x, feat_y, normalize=False, chunk_size=model.match_chunk_size)
        pi_y = model._soft_target(feat_x, feat_y, wy.verts)
        frames = model.interpolator.interpolate(wx.verts, pi_y, edges_x, times)
        soft_blend = wx.verts + MID_TIME * (pi_y - wx.verts)
        hard_blend = LinearBlend.blend(wx.verts, wy.verts, p2p, times[:1])[0]
        full = model.interpolate(x, y, times)
        full_blend = LinearBlend.blend(x.verts, y.verts, full.p2p, times[:1])[0]
    chamfer, chamfer_one = chamfers(frames[1], wy.verts, wy.faces)
    full_chamfer, full_chamfer_one = chamfers(full.deformation[1], y.verts, y.faces)
    return {
        "working_n_verts_x": int(wx.shape.n_verts),
        "cd_mid_neuromorph": distortion(wx.verts, wx.faces, frames[0]),
        "cd_mid_blend_soft": distortion(wx.verts, wx.faces, soft_blend),
        "cd_mid_blend_hard": distortion(wx.verts, wx.faces, hard_blend),
        "cd_end_neuromorph": distortion(wx.verts, wx.faces, frames[1]),
        "chamfer_end": chamfer,
        "chamfer_end_one_sided": chamfer_one,
        "full_cd_mid_neuromorph": distortion(x.verts, x.faces, full.deformation[0]),
        "full_cd_mid_blend_hard": distortion(x.verts, x.faces, full_blend),
        "full_chamfer_end": full_chamfer,
        "full_chamfer_end_one_sided": full_chamfer_one,
    }


def interpolation_benchmark(ckpt: str, faust_r: str | None, max_pairs: int | None) -> dict:
    """Mean (and median) of :func:`interpolation_pair` over the FAUST_r test pairs."""
    import torch
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate
    from tqdm import tqdm

    from shapecorr.data.datasets import PairDataset
    from shapecorr.models.recipe import load_model

    overrides = ["data=faust_r", *([f"data.root={faust_r}"] if faust_r else [])]
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("evaluate", overrides=overrides)
    model = load_model(ckpt).eval()
    dm = instantiate(cfg.data, _convert_="object")
    dm.with_operators(**dict(model.required_operators or {}))
    shapes = dm.shapes("test")
    pairs = PairDataset(shapes, pairs=dm.pairs("test").pairs, max_pairs=max_pairs)
    rows, start = [], time.perf_counter()
    for k in tqdm(range(len(pairs)), desc="interpolation", unit="pair"):
        sample = pairs[k]
        rows.append({"pair": "__".join(pairs.names(k)), **interpolation_pair(model, sample.x, sample.y)})
    keys = [k for k in rows[0] if k != "pair"]
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    median = {k: float(np.median([r[k] for r in rows])) for k in keys}
    wins = {name: float(np.mean([r["cd_mid_neuromorph"] < r[name] for r in rows]))
            for name in ("cd_mid_blend_soft", "cd_mid_blend_hard")}
    wins["full_cd_mid_blend_hard"] = float(np.mean([r["full_cd_mid_neuromorph"] < r["full_cd_mid_blend_hard"]
                                                    for r in rows]))
    return {"checkpoint": str(ckpt), "n_pairs": len(rows), "time": MID_TIME, "conformal_clamp": CLAMP,
            "mean": mean, "median": median, "fraction_of_pairs_neuromorph_below": wins,
            "seconds": time.perf_counter() - start, "torch_threads": torch.get_num_threads(), "pairs": rows}


# -- summary -----------------------------------------------------------------------------------------------------
def descriptor_nn_baseline() -> dict | None:
    """The best ``descriptor_nn`` row of ``results/eval_baselines.json`` (all 380 test pairs), if present."""
    if not BASELINES.is_file():
        return None
    runs = json.loads(BASELINES.read_text()).get("runs", {})
    rows = {k: v for k, v in runs.items() if k.startswith("descriptor_nn")}
    if not rows:
        return None
    name, best = min(rows.items(), key=lambda kv: kv[1]["mean_geodesic_error"])
    return {"name": name, **{k: best[k] for k in ("n_pairs", "mean_geodesic_error", "median_geodesic_error",
                                                  "pck_auc") if k in best}}


def summarize(run_dir: Path, eval_dir: Path | None = None, untrained_dir: Path | None = None,
              interp_json: Path | None = None) -> dict:
    """The summary dict written to the results file (see the module docstring)."""
    final = {name: read_metrics(folder) for name, folder in
             (("trained", eval_dir), ("untrained_network", untrained_dir))}
    baseline = descriptor_nn_baseline()
    if baseline is not None:
        final["descriptor_nn (" + baseline.pop("name") + ")"] = baseline
    interp = None
    if interp_json is not None:
        data = json.loads(Path(interp_json).read_text())
        interp = {k: v for k, v in data.items() if k != "pairs"}
    return {
        **summarize_run(run_dir),
        "final": {k: v for k, v in final.items() if v is not None},
        "interpolation": interp,
        "published_mean_geodesic_error": PUBLISHED_FAUST_R_ERROR,
        "units": "errors and Chamfer distances: fractions of sqrt(area of the target) (x100 = percent); "
                 "conformal distortion: area-weighted (K - 1/K)^2 per triangle of x, clamped at 10",
    }


def markdown(summary: dict) -> str:
    """Markdown tables: the validation curve, the final numbers and the interpolation comparison."""
    text = markdown_tables(summary, ("published (paper)", summary["published_mean_geodesic_error"]))
    interp = summary.get("interpolation")
    if interp:
        m = interp["mean"]
        text += "\n\n" + "\n".join([
            f"| t = {interp['time']} ({interp['n_pairs']} pairs) | conformal distortion (mean) | "
            "NeuroMorph lower on |",
            "|---|---:|---:|",
            f"| NeuroMorph X(0.5), working resolution | {m['cd_mid_neuromorph']:.3f} | |",
            f"| linear blend x + t(Pi y - x) | {m['cd_mid_blend_soft']:.3f} | "
            f"{100 * interp['fraction_of_pairs_neuromorph_below']['cd_mid_blend_soft']:.0f} % of pairs |",
            f"| linear blend x + t(y[p2p] - x) | {m['cd_mid_blend_hard']:.3f} | "
            f"{100 * interp['fraction_of_pairs_neuromorph_below']['cd_mid_blend_hard']:.0f} % of pairs |",
            f"| NeuroMorph X(0.5), full resolution | {m['full_cd_mid_neuromorph']:.3f} | |",
            f"| linear blend (hard map), full resolution | {m['full_cd_mid_blend_hard']:.3f} | "
            f"{100 * interp['fraction_of_pairs_neuromorph_below']['full_cd_mid_blend_hard']:.0f} % of pairs |",
            "",
            f"Chamfer X(1) to y (% of sqrt(area)): working resolution {PERCENT * m['chamfer_end']:.2f} "
            f"(one-sided {PERCENT * m['chamfer_end_one_sided']:.2f}), full resolution "
            f"{PERCENT * m['full_chamfer_end']:.2f} (one-sided {PERCENT * m['full_chamfer_end_one_sided']:.2f}).",
        ])
    return text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--launch", action="store_true", help="train, evaluate, compare interpolations, summarize")
    mode.add_argument("--summarize", metavar="RUN_DIR", help="summarize an existing run")
    mode.add_argument("--interpolation", metavar="CKPT", help="interpolation comparison of a NeuroMorph checkpoint")
    parser.add_argument("--run-dir", default=str(REPO / "outputs" / "bench" / "neuromorph_faust_r"),
                        help="--launch: the training run's folder")
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--threads", type=int, default=1, help="--launch: OMP_NUM_THREADS of the runs")
    parser.add_argument("--skip", nargs="*", default=[], choices=("train", "eval", "untrained", "interpolation"),
                        help="--launch: steps to skip")
    parser.add_argument("--max-pairs", type=int, default=None,
                        help="--interpolation: evenly spaced subset of the 380 test pairs")
    parser.add_argument("--out-json", help="--interpolation: output file (default: print only)")
    parser.add_argument("--eval-dir", help="evaluate.py output folder of the trained model (metrics.json)")
    parser.add_argument("--untrained-dir", help="evaluate.py output folder of the untrained network")
    parser.add_argument("--interp-json", help="output of --interpolation")
    parser.add_argument("--variant", choices=sorted(VARIANTS), default="published-loss",
                        help="--launch: training overrides (published-loss: CPU_BUDGET_OVERRIDES; geodesic-map: "
                             "GEODESIC_MAP_OVERRIDES); also picks the default --out")
    parser.add_argument("--out", default=None, help="results file (default: the variant's, in benchmarks/results)")
    args = parser.parse_args(argv)
    overrides, default_out = VARIANTS[args.variant]
    args.out = args.out or str(default_out)

    if args.interpolation:
        result = interpolation_benchmark(args.interpolation, args.faust_r, args.max_pairs)
        if args.out_json:
            Path(args.out_json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out_json).write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps({k: v for k, v in result.items() if k != "pairs"}, indent=2))
        return 0
    if args.launch:
        run_dir = Path(args.run_dir).absolute()
        for step, cmd in launch_commands(run_dir, args.faust_r, overrides).items():
            if step not in args.skip:
                bench_common.run_command(cmd, args.threads, REPO)
        folders = {"eval": run_dir / "eval_test", "untrained": run_dir / "eval_untrained",
                   "interpolation": run_dir / "interpolation.json"}
        eval_dir, untrained_dir, interp_json = (
            getattr(args, attr) or (folders[step] if step not in args.skip else None)
            for attr, step in (("eval_dir", "eval"), ("untrained_dir", "untrained"), ("interp_json", "interpolation")))
    else:
        run_dir = Path(args.summarize)
        eval_dir, untrained_dir, interp_json = args.eval_dir, args.untrained_dir, args.interp_json
    summary = summarize(run_dir, *(None if p is None else Path(p) for p in (eval_dir, untrained_dir, interp_json)))
    report = bench_common.summary_report("neuromorph_faust_r.py", sys.argv[1:] if argv is None else list(argv), summary)
    print(markdown(summary))
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
