"""CPU seconds of the original Deep Shells test routine on the golden pair, for side-by-side runs with ``speed.py``.

    git clone https://github.com/marvin-eisenberger/deep-shells /tmp/deep_shells_original
    python benchmarks/deep_shells_original_query.py --original-src /tmp/deep_shells_original --repeats 3

Runs the original's ``test_model`` (feature Sinkhorn, its OT level at k = 6, then the 40-level ``AssSmoothShells``
refinement) with its released FAUST + SCAPE weights (``models/Faust_Scape/ckpt_ep20.pth`` of the checkout) on the
golden inputs of ``speed.py`` (``--golden``: meshes, the original's 510 eigenpairs, lumped mass and SHOT), one
thread, in this process: one warm-up call, then ``--repeats`` timed calls (process CPU seconds), with autograd
on as in the original's own test call (``--no-grad`` to switch it off). Nothing of the
original code is copied: it is imported from ``--original-src``. What it imports but is not installed is supplied
as a shim package written to a temporary folder: ``torch_geometric.nn.knn`` / ``knn_graph`` by scipy's
``cKDTree`` (float64, exact; the original uses torch_cluster), and ``torch.solve`` (removed from PyTorch) by
``torch.linalg.solve``. Prints one JSON line (the medians, every call, the agreement of the map with the golden
original output, the load average); alternate it with ``speed.py --child deep_shells_query`` (docs/speed.md §3).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--original-src", type=Path, required=True, help="checkout of marvin-eisenberger/deep-shells")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-grad", action="store_true",
                        help="run under torch.no_grad() (the original's own test call does not: its features and "
                             "Sinkhorn then record autograd graphs)")
    args = parser.parse_args(argv)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", DEFAULT_GOLDEN))
    src = args.original_src.resolve()
    if not (src / "unsupervised_shells.py").is_file() or not (src / "models/Faust_Scape/ckpt_ep20.pth").is_file():
        print(f"error: {src}: not a checkout of the original Deep Shells code with its released weights",
              file=sys.stderr)
        return 2
    prepare_original(src, "deep_shells_shim_")
    import numpy as np
    import torch

    with contextlib.redirect_stdout(io.StringIO()):
        from main import load_model_matching
        from shape_utils import Shape

        model = load_model_matching("Faust_Scape", num_epoch=20)
    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    reference = np.load(golden / f"original_output_{PAIR}.npz")["map_x_to_y"]

    def shape(side):
        s = Shape(torch.from_numpy(inputs[f"{side}_verts"].astype(np.float32)),
                  torch.from_numpy(inputs[f"{side}_faces"].astype(np.int64)))
        for attr, key in (("evecs", "evecs"), ("evals", "evals"), ("A", "mass"), ("SHOT", "shot")):
            setattr(s, attr, torch.from_numpy(inputs[f"{side}_{key}"].astype(np.float32)))
        s.compute_xi_()
        return s

    cpus = []
    for i in range(args.repeats + 1):  # the first call warms up
        shape_x, shape_y = shape("x"), shape("y")  # test_model changes the shapes' sampling
        start = time.process_time()
        with torch.set_grad_enabled(not args.no_grad), contextlib.redirect_stdout(io.StringIO()):
            map_x_to_y, _ = model.test_model(shape_x, shape_y)
        if i > 0:
            cpus.append(time.process_time() - start)
    print(json.dumps({"case": "deep_shells_query", "code": "original", "original_src": str(src), "threads": 1,
                      "no_grad": args.no_grad,
                      "cpu_seconds": cpus, "cpu_seconds_median": statistics.median(cpus),
                      "map_agreement_with_golden_original": float((map_x_to_y.cpu().numpy() == reference).mean()),
                      "load_average": list(os.getloadavg())}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
