"""CPU seconds of the original Deep Shells code on the golden pair, for side-by-side runs with ``speed.py``.

    git clone https://github.com/marvin-eisenberger/deep-shells /tmp/deep_shells_original
    python benchmarks/deep_shells_original_query.py --original-src /tmp/deep_shells_original --repeats 3
    python benchmarks/deep_shells_original_query.py --original-src /tmp/deep_shells_original --unit train \
        --samples /tmp/samples.npz --repeats 3

Two units, each on the golden inputs of ``speed.py`` (``--golden``: meshes, the original's 510 eigenpairs, lumped
mass and SHOT) with the released FAUST + SCAPE weights (``models/Faust_Scape/ckpt_ep20.pth`` of the checkout), one
thread, in this process: one warm-up call, then ``--repeats`` timed calls (process CPU seconds).

* ``--unit query`` (``speed.py``'s ``deep_shells_query``): the original's ``test_model`` (feature Sinkhorn, its OT
  level at k = 6, then the 40-level ``AssSmoothShells`` refinement), with autograd on as in the original's own test
  call (``--no-grad`` to switch it off); reports the agreement of the map with the golden original output.
* ``--unit train`` (``speed.py``'s ``deep_shells_train``): one pair of the original's training loop
  (``UnsupervisedShells.train``: the two ``Shape`` objects built from the arrays as ``batch_to_shape`` does, 2000
  samples per shape, ``match_pair`` over the published shells 6..21, ``backward``), the weights loaded as its
  ``load_self`` does (the checkpoint's ``par`` included). The gradients are cleared before every pair; the Adam step,
  which the original's loop takes once per 53 pairs (``batch_size``), is timed once after the pairs
  (``adam_step_cpu_seconds``). ``--samples`` (an ``.npz`` with ``samples_x``, ``samples_y``) fixes the samples of
  every pair (the ones ``speed.py``'s step draws, so that both codes compute the same loss); without it the
  original draws its own (``subsample_random``). Reports the loss of every pair and the norm of the last pair's
  gradient.

Nothing of the original code is copied: it is imported from ``--original-src``. What it imports but is not
installed is supplied as a shim package written to a temporary folder: ``torch_geometric.nn.knn`` / ``knn_graph``
by scipy's ``cKDTree`` (float64, exact; the original uses torch_cluster), and ``torch.solve`` (removed from PyTorch)
by ``torch.linalg.solve``. Prints one JSON line (the medians, every call, the process's peak resident set, the load
average); ``benchmarks/originals_side_by_side.py`` alternates it with ``speed.py --child`` (docs/speed.md §3).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

DEFAULT_GOLDEN = Path("/work/shared/data/reference/deep_shells_golden")
PAIR = "tr_reg_080__tr_reg_081"

_SHIM = '''
import numpy as np
import torch
from scipy.spatial import cKDTree


def knn(x, y, k):
    """For each row of y its k nearest rows of x: (2, len(y) * k), rows (y index, x index)."""
    _, idx = cKDTree(x.detach().double().cpu().numpy()).query(y.detach().double().cpu().numpy(), k=k)
    idx = np.asarray(idx).reshape(len(y), k)
    return torch.from_numpy(np.stack([np.repeat(np.arange(len(y)), k), idx.reshape(-1)])).long()


def knn_graph(x, k, loop=False):
    pts = x.detach().double().cpu().numpy()
    _, idx = cKDTree(pts).query(pts, k=k + 1)
    return torch.from_numpy(np.stack([idx[:, 1:].reshape(-1), np.repeat(np.arange(len(x)), k)])).long()


def fps(x, ratio):
    raise NotImplementedError("farthest-point sampling is not shimmed: the side-by-side runs do not need it")
'''


def write_torch_geometric_shim(folder: Path) -> None:
    """Write a ``torch_geometric`` stand-in (k-d tree ``knn`` / ``knn_graph``) under ``folder`` for the originals."""
    pkg = folder / "torch_geometric"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "io.py").write_text("")
    (pkg / "nn.py").write_text(_SHIM)


def prepare_original(src: Path, prefix: str) -> Path:
    """Make this process ready to import an original checkout ``src``: one thread, the ``torch.solve`` the originals
    call (removed from torch), the ``torch_geometric`` stand-in in a new temporary folder (returned) and ``src`` first
    on ``sys.path``; the working folder becomes ``src`` (the originals resolve their files relative to it)."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)
    torch.solve = lambda b, a: (torch.linalg.solve(a, b), None)
    shim = Path(tempfile.mkdtemp(prefix=prefix))
    write_torch_geometric_shim(shim)
    sys.path[:0] = [str(shim), str(src)]
    os.chdir(src)
    return shim


def golden_shape(shape_cls, inputs, side: str):
    """An original ``Shape`` of side ``x`` or ``y`` of the golden inputs, as the originals' ``batch_to_shape`` builds
    it: vertices, faces, eigenpairs, lumped mass, SHOT, and the coordinates' spectral coefficients (``xi``)."""
    import numpy as np
    import torch

    s = shape_cls(torch.from_numpy(inputs[f"{side}_verts"].astype(np.float32)),
                  torch.from_numpy(inputs[f"{side}_faces"].astype(np.int64)))
    for attr, key in (("evecs", "evecs"), ("evals", "evals"), ("A", "mass"), ("SHOT", "shot")):
        setattr(s, attr, torch.from_numpy(inputs[f"{side}_{key}"].astype(np.float32)))
    s.compute_xi_()
    return s


def timed_calls(fn, repeats: int) -> tuple[list[float], list]:
    """Process CPU seconds of ``repeats`` calls of ``fn`` after one warm-up call, and every call's result."""
    cpus, results = [], []
    for i in range(repeats + 1):  # the first call warms up
        start = time.process_time()
        with contextlib.redirect_stdout(io.StringIO()):
            results.append(fn())
        if i > 0:
            cpus.append(time.process_time() - start)
    return cpus, results


def _query(model, shape_cls, inputs, reference, no_grad: bool, repeats: int) -> dict:
    import torch

    def query():
        shape_x, shape_y = golden_shape(shape_cls, inputs, "x"), golden_shape(shape_cls, inputs, "y")
        with torch.set_grad_enabled(not no_grad):
            return model.test_model(shape_x, shape_y)[0]

    cpus, maps = timed_calls(query, repeats)
    return {"no_grad": no_grad, "cpu_seconds": cpus,
            "map_agreement_with_golden_original": float((maps[-1].cpu().numpy() == reference).mean())}


def _train(model, shape_cls, inputs, samples: Path | None, repeats: int) -> dict:
    import numpy as np
    import torch

    fixed = None
    if samples is not None:
        with np.load(samples) as stored:
            fixed = {side: torch.from_numpy(stored[f"samples_{side}"].astype(np.int64)) for side in "xy"}
    optimizer = torch.optim.Adam(model.feat_mod.parameters(), lr=model.param.lr)
    model.feat_mod.train()
    num = model.param.subsample_num

    def pair():
        optimizer.zero_grad()
        shapes = {side: golden_shape(shape_cls, inputs, side) for side in "xy"}
        for side, shape in shapes.items():
            if fixed is None:
                shape.subsample_random(num)
            else:
                shape.samples = fixed[side]
        loss = model.match_pair(shapes["x"], shapes["y"])
        loss.backward()
        return float(loss.detach())

    cpus, losses = timed_calls(pair, repeats)
    grad_norm = float(torch.sqrt(sum((q.grad.double() ** 2).sum() for q in model.feat_mod.parameters())))
    start = time.process_time()
    optimizer.step()
    return {"gradient_norm": grad_norm, "samples": num, "samples_from": str(samples) if samples else "subsample_random",
            "k_array": list(model.param.k_array), "num_sink": model.param.num_sink, "cpu_seconds": cpus,
            "losses": losses, "adam_step_cpu_seconds": time.process_time() - start}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--original-src", type=Path, required=True, help="checkout of marvin-eisenberger/deep-shells")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--unit", choices=("query", "train"), default="query")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-grad", action="store_true",
                        help="query: run under torch.no_grad() (the original's own test call does not: its features "
                             "and Sinkhorn then record autograd graphs)")
    parser.add_argument("--samples", type=Path, default=None,
                        help="train: .npz with samples_x, samples_y used for every pair (default: the original draws)")
    args = parser.parse_args(argv)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", DEFAULT_GOLDEN))
    src = args.original_src.resolve()
    if not (src / "unsupervised_shells.py").is_file() or not (src / "models/Faust_Scape/ckpt_ep20.pth").is_file():
        print(f"error: {src}: not a checkout of the original Deep Shells code with its released weights",
              file=sys.stderr)
        return 2
    samples = args.samples.resolve() if args.samples else None
    prepare_original(src, "deep_shells_shim_")
    import numpy as np

    with contextlib.redirect_stdout(io.StringIO()):
        from main import load_model_matching
        from param import save_path
        from shape_utils import Shape
        from unsupervised_shells import UnsupervisedShells

        if args.unit == "query":
            model = load_model_matching("Faust_Scape", num_epoch=20)
        else:  # a training run: DeepParam, the checkpoint's weights and parameters, a save path (no plots)
            model = UnsupervisedShells(save_path=save_path("side_by_side_unused"))
            model.load_self(save_path("Faust_Scape"), 20)
    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    if args.unit == "query":
        reference = np.load(golden / f"original_output_{PAIR}.npz")["map_x_to_y"]
        record = _query(model, Shape, inputs, reference, args.no_grad, args.repeats)
        case = "deep_shells_query"
    else:
        record = _train(model, Shape, inputs, samples, args.repeats)
        case = "deep_shells_train"
    print(json.dumps({"case": case, "code": "original", "original_src": str(src), "threads": 1, **record,
                      "cpu_seconds_median": statistics.median(record["cpu_seconds"]),
                      "process_max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "load_average": list(os.getloadavg())}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
