"""CPU seconds of the original G-MSM code on the golden pair (training step or query), side by side with ``speed.py``.

    git clone https://github.com/marvin-eisenberger/gmsm-matching /tmp/gmsm_original
    python benchmarks/gmsm_original_step.py --original-src /tmp/gmsm_original --repeats 3
    python benchmarks/gmsm_original_step.py --original-src /tmp/gmsm_original --unit query --repeats 3

Both units run the original's ``GraphMultiShapeMatching`` (its DiffusionNet feature module, width 128, 4 blocks,
k_eig 128; its ``DeepParam``: 2000 random samples per shape, shells 6..21, 3 Sinkhorn rounds) with its seed-0 initial
weights on the golden inputs of ``speed.py`` (``--golden``: meshes, the original Deep Shells' 510 eigenpairs, lumped
mass and SHOT), one thread, in this process: one warm-up call, then ``--repeats`` timed calls (process CPU
seconds). The DiffusionNet operators are computed once before the timing by the original's own
``diffusion_net.geometry.get_operators`` (as its dataset does at load).

* ``--unit train`` (``speed.py``'s ``gmsm_train``): ``subsample_random`` on both shapes, ``match_pair`` (features and
  the hierarchical matching), ``backward`` and an Adam step; reports the losses.
* ``--unit query`` (``speed.py``'s ``gmsm_query``): ``test_model_fast``, the one-level query its validation and
  shape-graph construction run for every pair (``get_all_matches``: under ``torch.no_grad``, the feature module in
  training mode as ``load_self`` leaves it, so dropout is on): 2000 random samples, ``match_pair``, then one
  ``AssSmoothShells`` level at k = 21 at full resolution (k-d tree nearest neighbours through the shim). The two
  ``Shape`` objects are built from the arrays in every call, as its ``batch_to_shape`` does per pair. Reports the
  two losses it returns (the sampled level energy mean, the one-level alignment) and the maps' sizes;
  ``--save-maps`` writes the last call's maps to an ``.npz``.

Nothing of the original code is copied: it is imported from ``--original-src``. What it imports but is not installed
is supplied by packages written to a temporary folder: ``torch_geometric.nn`` (``knn`` / ``knn_graph`` by scipy's
``cKDTree``, as in ``deep_shells_original_query.py``), and ``sklearn.neighbors`` and ``python_tsp`` stand-ins that
raise when called (imported at module level, never called by these units); ``torch.solve`` (removed from PyTorch)
is ``torch.linalg.solve``. Prints one JSON line (the medians, every call, the process's peak resident set, the load
average); ``benchmarks/originals_side_by_side.py`` alternates it with ``speed.py --child`` (docs/speed.md §3).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import random
import resource
import statistics
import sys
from pathlib import Path

from deep_shells_original_query import DEFAULT_GOLDEN, PAIR, golden_shape, prepare_original, timed_calls

_RAISING_STUB = '''
def {name}(*args, **kwargs):
    raise NotImplementedError("stand-in of the side-by-side benchmark: not used by a G-MSM training step or query")
'''
#: Modules the original imports at module level that a training step never calls: module -> function names.
_STUBS = {"sklearn/neighbors.py": ("KDTree", "NearestNeighbors"),
          "python_tsp/exact.py": ("solve_tsp_dynamic_programming",),
          "python_tsp/heuristics.py": ("solve_tsp_simulated_annealing",)}


def _write_stubs(folder: Path) -> None:
    for rel, names in _STUBS.items():
        path = folder / rel
        path.parent.mkdir(exist_ok=True)
        (path.parent / "__init__.py").touch()
        path.write_text("".join(_RAISING_STUB.format(name=name) for name in names))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--original-src", type=Path, required=True, help="checkout of marvin-eisenberger/gmsm-matching")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--unit", choices=("train", "query"), default="train")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--save-maps", type=Path, default=None,
                        help="query: write the last call's maps (map_x_to_y, map_y_to_x) to this .npz")
    args = parser.parse_args(argv)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", DEFAULT_GOLDEN))
    src = args.original_src.resolve()
    if not (src / "model.py").is_file() or not (src / "diffusion_net" / "layers.py").is_file():
        print(f"error: {src}: not a checkout of the original G-MSM code", file=sys.stderr)
        return 2
    save_maps = args.save_maps.resolve() if args.save_maps else None  # before the working folder changes
    shim = prepare_original(src, "gmsm_shim_")
    _write_stubs(shim)
    import numpy as np
    import torch

    with contextlib.redirect_stdout(io.StringIO()):
        import diffusion_net
        from model import GraphMultiShapeMatching
        from utils.shape_utils import Shape
    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    operators = {}

    def shape(side):
        s = golden_shape(Shape, inputs, side)
        if side not in operators:
            operators[side] = list(diffusion_net.geometry.get_operators(s.vert, s.triv))
        s.diffusion_net_ops = operators[side]
        return s

    random.seed(0)  # the original draws its samples with Python's random module
    torch.manual_seed(0)
    with contextlib.redirect_stdout(io.StringIO()):
        shape_x, shape_y = shape("x"), shape("y")
        model = GraphMultiShapeMatching(None, None)
    model.feat_mod.train()
    num = model.param.subsample_num

    def step():
        shape_x.subsample_random(num)
        shape_y.subsample_random(num)
        loss = model.match_pair(shape_x, shape_y)
        loss.backward()
        model.optimizer.step()
        model.optimizer.zero_grad()
        return float(loss.detach())

    maps = {}

    def query():
        with torch.no_grad():
            maps["map_x_to_y"], maps["map_y_to_x"], losses = model.test_model_fast(shape("x"), shape("y"))
        return {"losses": losses, "map_sizes": [int(m.numel()) for m in maps.values()]}

    cpus, values = timed_calls(step if args.unit == "train" else query, args.repeats)
    if save_maps is not None and maps:
        np.savez(save_maps, **{key: m.cpu().numpy() for key, m in maps.items()})
    record = {"losses": values} if args.unit == "train" else {"query_outputs": values}
    print(json.dumps({"case": f"gmsm_{args.unit}", "code": "original", "original_src": str(src), "threads": 1,
                      "samples": num, "cpu_seconds": cpus, "cpu_seconds_median": statistics.median(cpus), **record,
                      "process_max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "load_average": list(os.getloadavg())}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
