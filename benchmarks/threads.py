"""Seconds per pair of every method at 1 and 2 threads, interleaved in one process, and the default's choice.

    nice -n 10 python benchmarks/threads.py --faust-r /path/to/FAUST_r --weights /path/to/ckpt_ep20.pth \
        [--rounds 3] [--methods descriptor_nn,deep_shells_published,...] [--out benchmarks/results/threads.json]

For each method: the matcher of ``evaluate.py model=<method>`` (reduced settings for the slow axiomatic methods,
below) on a few FAUST_r test pairs (evenly spaced, ``pairs``), its shapes loaded once from the shape cache. Each
round times the matcher alone (``run_matcher``, as evaluate.py times ``seconds``) on every pair once per thread
count, the thread counts in alternating order (1, 2, then 2, 1, ...), switched in the process with
:func:`shapecorr.cli.threads.limit_threads` (torch, BLAS and OpenMP pools); a change of the machine's load then
affects both alike. The result per setting is the median over rounds of the mean seconds per pair. ``default``
is the count ``threads=null`` picks on this machine (:func:`shapecorr.cli.threads.threads_per_process`),
recorded with the load average it saw.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

from bench_common import machine_info

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: method -> (evaluate.py options, pairs): reduced settings where the published ones take minutes per pair.
METHODS = {
    "descriptor_nn": (["model=descriptor_nn"], 4),
    "deep_shells_published": (["model=deep_shells_published"], 2),
    "neuromorph": (["model=neuromorph", "model.query_resolution=2000"], 2),
    "gmsm": (["model=gmsm"], 2),
    "smooth_shells": (["model=smooth_shells"], 1),
    "divfree": (["model=divfree", "model.samples=[250,500,500]", "model.iterations=[20,20,40]"], 1),
    "hamiltonian": (["model=hamiltonian", "model.n_modes=3", "model.iterations=3"], 1),
}
THREADS = (1, 2)


def build(method: str, faust_r: str):
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from shapecorr.cli.matcher_factory import build_matcher
    from shapecorr.data.datasets import PairDataset
    from shapecorr.data.operators import required_request

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("evaluate", overrides=[*METHODS[method][0], "data=faust_r", f"data.root={faust_r}",
                                             "paths.output_dir=/tmp/unused"])
    import torch

    matcher = build_matcher(cfg, torch.device("cpu"))
    dm = instantiate(cfg.data, _convert_="object")
    dm.with_operators(required_request(matcher))
    shapes = dm.shapes("test")
    shapes.prepare(geodesics=None, progress=False)
    pairs = PairDataset(shapes, pairs=dm.pairs("test").pairs, max_pairs=METHODS[method][1]).pairs
    samples = {i: shapes[i] for pair in pairs for i in pair}
    return matcher, [(samples[i], samples[j]) for i, j in pairs]


def time_pairs(matcher, pairs) -> float:
    import torch

    from shapecorr.eval.matcher_run import run_matcher

    start = time.perf_counter()
    with torch.no_grad():
        for x, y in pairs:
            run_matcher(matcher, x, y, None)
    return (time.perf_counter() - start) / len(pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"))
    parser.add_argument("--weights", default=os.environ.get("SHAPECORR_DEEP_SHELLS_WEIGHTS"))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--out", default=str(REPO / "benchmarks/results/threads.json"))
    args = parser.parse_args()
    if not args.faust_r:
        sys.exit("give --faust-r DIR or set SHAPECORR_FAUST_R")
    if args.weights:
        os.environ["SHAPECORR_DEEP_SHELLS_WEIGHTS"] = args.weights
    from shapecorr.cli.threads import limit_threads, threads_per_process

    load_before = os.getloadavg()
    default = threads_per_process(None, 0, environ={})
    table = {}
    start = time.time()
    for method in args.methods.split(","):
        matcher, pairs = build(method, args.faust_r)
        limit_threads(1)
        time_pairs(matcher, pairs[:1])  # warm-up: lazy imports, first-call allocations
        rounds: dict[int, list[float]] = {n: [] for n in THREADS}
        for r in range(args.rounds):
            for n in (THREADS if r % 2 == 0 else THREADS[::-1]):
                limit_threads(n)
                seconds = time_pairs(matcher, pairs)
                rounds[n].append(seconds)
                print(f"{method:22s} round {r} threads={n}: {seconds:7.2f} s/pair  load {os.getloadavg()[0]:.1f}",
                      flush=True)
        med = {n: statistics.median(v) for n, v in rounds.items()}
        best = min(med.values())
        table[method] = {"options": METHODS[method][0], "pairs": len(pairs),
                         "seconds_per_pair": {f"threads={n}": med[n] for n in THREADS},
                         "rounds": {f"threads={n}": rounds[n] for n in THREADS},
                         "best": f"threads={min(med, key=med.get)}",
                         "default_over_best": med[default] / best}
    result = {
        "command": " ".join([sys.executable, *sys.argv]),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": machine_info(),
        "load_average_at_start": load_before,
        "default_threads": default,
        "wall_seconds": time.time() - start,
        "notes": ("FAUST_r test pairs (evenly spaced); seconds_per_pair: the matcher alone, median over rounds of "
                  "the mean over the pairs; thread counts interleaved in one process (order alternating by round) "
                  "on a machine shared with other jobs; default_over_best: the default's time / the best one."),
        "methods": table,
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    for method, row in table.items():
        cells = "  ".join(f"{s} {v:7.2f}" for s, v in row["seconds_per_pair"].items())
        print(f"{method:22s} {cells}  default (threads={default}) / best {row['default_over_best']:.2f}")


if __name__ == "__main__":
    main()
