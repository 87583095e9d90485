"""CPU seconds of the parts of one G-MSM training step (``speed.py``'s ``gmsm_train``), one thread.

    python benchmarks/gmsm_step_parts.py [--steps 4] [--golden DIR]

The step of ``speed.py --child gmsm_train`` (the same model, inputs and samples), cut at the features: DiffusionNet's
forward on both shapes, the matching layer's forward (with the loss) on detached copies of the features, its backward
(which gives the features' gradients), the network's backward with those gradients, the Adam step. The math is that
of the whole step (the same products and sums); the cut adds two tensor copies. The Sinkhorn's share of the layer is
timed around its calls (forward) and around its autograd node (backward). Prints the medians of ``--steps`` steps
after one warm-up step, and the load average (docs/speed.md §4).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import speed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--steps", type=int, default=4)
    args = parser.parse_args(argv)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", speed.DEFAULT_GOLDEN))
    import torch

    from shapecorr.matching import deep_shells as ds
    from shapecorr.models.gmsm import GMSM
    from shapecorr.nn.diffusion_net import DiffusionNetBackbone

    torch.set_num_threads(1)
    clock = time.process_time
    pair = speed._golden_pair(golden, torch.device("cpu"), diffusion=True)
    torch.manual_seed(0)
    model = GMSM(backbone=DiffusionNetBackbone(), num_samples=speed.TRAIN_SAMPLES, loss=speed._published_loss("gmsm"))
    model.train(True)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    sinkhorn = defaultdict(float)
    transport = ds._transport

    def timed_transport(*a, **k):
        start = clock()
        out = transport(*a, **k)
        sinkhorn["forward"] += clock() - start
        out[0].grad_fn.register_prehook(lambda _: sinkhorn.__setitem__("start", clock()))
        out[0].grad_fn.register_hook(lambda *_: sinkhorn.__setitem__(
            "backward", sinkhorn["backward"] + clock() - sinkhorn["start"]))
        return out

    ds._transport = timed_transport
    x, y = pair.x, pair.y
    parts = defaultdict(list)
    for i in range(args.steps + 1):  # the first step warms up
        sinkhorn.clear()
        model.zero_grad(set_to_none=True)
        gen = model.sample_generator(i)
        sx = ds.random_samples(x.shape.n_verts, model.config.num_samples, generator=gen)
        sy = ds.random_samples(y.shape.n_verts, model.config.num_samples, generator=gen)
        t0 = clock()
        fx, fy = model.features(x, sx), model.features(y, sy)
        t1 = clock()
        lx, ly = fx.detach().requires_grad_(), fy.detach().requires_grad_()
        out = ds.deep_shells_layer(lx, ly, model.spectral_shape(x), model.spectral_shape(y), sx, sy, model.config,
                                   return_plans=False)
        total, _ = model.loss(level_energies=out.level_energies)
        t2 = clock()
        total.backward()
        t3 = clock()
        torch.autograd.backward([fx, fy], [lx.grad, ly.grad])
        t4 = clock()
        optimizer.step()
        t5 = clock()
        if i > 0:
            for name, value in (("diffusion_net_forward", t1 - t0), ("layer_forward", t2 - t1),
                                ("layer_forward_sinkhorn", sinkhorn["forward"]), ("layer_backward", t3 - t2),
                                ("layer_backward_sinkhorn", sinkhorn["backward"]), ("diffusion_net_backward", t4 - t3),
                                ("adam", t5 - t4), ("step", t5 - t0)):
                parts[name].append(value)
    ds._transport = transport
    print(json.dumps({"case": "gmsm_train", "threads": 1, "steps": args.steps,
                      "cpu_seconds_median": {k: statistics.median(v) for k, v in parts.items()},
                      "load_average": list(os.getloadavg())}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
