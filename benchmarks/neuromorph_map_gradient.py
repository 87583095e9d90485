"""Benchmark: which NeuroMorph loss terms can fit the correspondence of a few fixed FAUST_r pairs?

    python benchmarks/neuromorph_map_gradient.py [--faust-r DIR] [--steps 60] [--lr 1e-3] [--threads 1]

A diagnostic behind ``model.map_gradient`` (docs/benchmarks.md, its NeuroMorph section). A fresh network is
trained on the same few training pairs (default 4: two pose-different pairs, both directions) at a fixed
working resolution, without augmentation, one optimizer step per pass over the pairs, and the geodesic error of
its argmax map on those very pairs is recorded every ``--log-every`` steps. Variants:

* ``published``: every loss term trains the soft maps (``map_gradient=all``, weights 1 / 1 / 50);
* ``geodesic``: only the geodesic term trains the soft maps (``map_gradient=geodesic``); registration and ARAP
  still train the interpolator;
* ``geodesic_then_published``: ``geodesic`` for ``--steps`` steps, then ``--switch-steps`` more steps of
  ``published`` from there (does the fitted map survive the registration gradient?);
* ``original_preset``: ``published`` with the original code's choices (``model=neuromorph_original``: channel
  pooling, original residual init, ARAP "average" differentiated through the rotations at face-edge weights),
  on the same heat geodesics, to compare with the original code's run on these pairs (docs/benchmarks.md).

``--variants`` selects a subset.

Errors are at the working resolution: the geodesic distance on y (working-resolution remesh, the training
geodesics) between the image of each reference point and its ground truth, over sqrt(area(y)), in percent.
Results go to ``benchmarks/results/neuromorph_map_gradient.json``.
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
RESULT = REPO / "benchmarks" / "results" / "neuromorph_map_gradient.json"
DEFAULT_PAIRS = ("tr_reg_000:tr_reg_013", "tr_reg_013:tr_reg_000", "tr_reg_021:tr_reg_046", "tr_reg_046:tr_reg_021")
PERCENT = 100.0
VARIANTS = ("published", "geodesic", "geodesic_then_published", "original_preset")


def load_pairs(faust_r: str | None, names: list[tuple[str, str]]):
    """The training pairs ``names`` of FAUST_r (train split) as PairSamples."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from shapecorr.data.datasets import PairDataset

    overrides = ["data=faust_r", *([f"data.root={faust_r}"] if faust_r else [])]
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    dm = instantiate(cfg.data, _convert_="object")
    shapes = dm.shapes("train")
    return PairDataset(shapes, pairs=names)


def pair_errors(model, augmented) -> list[float]:
    """Mean geodesic error (percent of sqrt(area(y))) of the argmax map on each augmented pair."""
    import torch

    from shapecorr.eval.metrics import geodesic_errors, surface_area
    from shapecorr.nn.neuromorph import interpolation_times

    errors = []
    with torch.no_grad():
        for aug in augmented:
            x, y = aug.pair.x, aug.pair.y
            p2p = model.forward_pair(x, y, interpolation_times(0))["pi_x_to_y"].argmax(1)
            sqrt_area = np.sqrt(surface_area(y.verts.double().numpy(), y.faces.numpy()))
            errors.append(PERCENT * float(geodesic_errors(p2p, aug.dist_y, x.corres, y.corres, sqrt_area).mean()))
    return errors


class TermRecorder:
    """Stands in for the model's WeightedLoss and accumulates the mean unweighted value of each term."""

    def __init__(self, loss, n_pairs: int):
        self.inner, self.n_pairs, self.terms = loss, n_pairs, {}

    @property
    def weights(self):
        return self.inner.weights

    def __call__(self, **inputs):
        total, values = self.inner(**inputs)
        for name, value in values.items():
            self.terms[name] = self.terms.get(name, 0.0) + float(value.detach()) / self.n_pairs
        return total, values


def model_loss(model: str = "neuromorph"):
    """The loss of ``model=<model>`` (configs/model/loss/<model>.yaml)."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=[f"model={model}"])
    return instantiate(cfg.model.loss, _convert_="object")


def train(model, optimizer, pairs, augmented, steps: int, log_every: int, first_step: int = 0) -> list[dict]:
    """``steps`` optimizer steps (each on the summed loss of all pairs); a row every ``log_every`` steps with the
    errors before that step and the loss terms of that step."""
    rows, loss = [], model.loss
    for step in range(first_step, first_step + steps + 1):
        last = step == first_step + steps
        if (step - first_step) % log_every == 0 or last:
            errors = pair_errors(model, augmented)
            rows.append({"step": step, "mean_error": float(np.mean(errors)), "errors": errors,
                         "map_gradient": model.map_gradient})
        if last:
            break
        optimizer.zero_grad()
        model.loss = recorder = TermRecorder(loss, len(pairs))
        try:
            for k in range(len(pairs)):
                model.training_step(pairs[k], 0).backward()
        finally:
            model.loss = loss
        optimizer.step()
        if rows[-1]["step"] == step:
            rows[-1]["loss_terms"] = recorder.terms
    return rows


def run(args) -> dict:
    import torch

    from shapecorr.models.neuromorph import DEFAULT_ARAP_EDGE_WEIGHT_SCALE, NeuroMorph
    from shapecorr.nn.edgeconv_backbone import EdgeConvBackbone

    torch.set_num_threads(args.threads)
    names = [tuple(p.split(":")) for p in args.pairs]
    pairs = load_pairs(args.faust_r, names)
    variants = {}
    for variant in args.variants:
        torch.manual_seed(args.seed)
        mode = "all" if variant in ("published", "original_preset") else "geodesic"
        options = dict(loss=model_loss())
        if variant == "original_preset":
            options = dict(backbone=EdgeConvBackbone(pool="channel", residual_init="original"),
                           interpolation_net=dict(hidden_channels=128, n_blocks=5, pool="channel",
                                                  residual_init="original"),
                           arap_edge_weight_scale=1.0, loss=model_loss("neuromorph_original"))
        model = NeuroMorph(query_resolution=args.resolution, augment=dict(remesh=False, rotate=False),
                           map_gradient=mode, seed=args.seed, **options)
        optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)
        augmented = [model.augmenter(pairs[k], None, geodesics=True) for k in range(len(pairs))]
        start = time.perf_counter()
        rows = train(model, optimizer, pairs, augmented, args.steps, args.log_every)
        if variant == "geodesic_then_published":
            model.map_gradient = "all"
            rows += train(model, optimizer, pairs, augmented, args.switch_steps, args.log_every,
                          first_step=args.steps)[1:]
        variants[variant] = {"curve": rows, "final_mean_error": rows[-1]["mean_error"],
                             "seconds": time.perf_counter() - start}
        print(f"{variant}: " + ", ".join(f"step {r['step']}: {r['mean_error']:.1f} %" for r in rows), flush=True)
    return {
        "pairs": [":".join(p) for p in names],
        "settings": {"working_resolution": args.resolution, "steps": args.steps, "switch_steps": args.switch_steps,
                     "lr": args.lr, "seed": args.seed, "threads": args.threads,
                     "loss": "published weights: registration 1, ARAP 1, geodesic 50; T = 0",
                     "arap_edge_weight_scale_default": DEFAULT_ARAP_EDGE_WEIGHT_SCALE,
                     "augmentation": "none (fixed working-resolution remesh, no rotation)"},
        "units": "mean geodesic error of the argmax map on the training pairs, percent of sqrt(area(y))",
        "variants": variants,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"),
                        help="FAUST_r folder (default: $SHAPECORR_FAUST_R)")
    parser.add_argument("--pairs", nargs="+", default=list(DEFAULT_PAIRS), help="training pairs as SOURCE:TARGET")
    parser.add_argument("--resolution", type=int, default=1000, help="working resolution (vertices)")
    parser.add_argument("--steps", type=int, default=60, help="optimizer steps of each variant")
    parser.add_argument("--switch-steps", type=int, default=30,
                        help="geodesic_then_published: steps after the switch to map_gradient=all")
    parser.add_argument("--log-every", type=int, default=10, help="steps between error evaluations")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate")
    parser.add_argument("--seed", type=int, default=0, help="network initialization seed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS, help="variants to run")
    parser.add_argument("--out", default=str(RESULT), help="output JSON")
    args = parser.parse_args(argv)
    if args.faust_r is None:
        parser.error("FAUST_r not given: pass --faust-r or set SHAPECORR_FAUST_R")
    summary = run(args)
    report = bench_common.summary_report("neuromorph_map_gradient.py", sys.argv[1:] if argv is None else list(argv),
                                         summary)
    bench_common.write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
