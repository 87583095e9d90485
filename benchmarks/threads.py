"""Seconds per pair of every method with threads=1, threads=2 and the default (threads=null), interleaved.

    nice -n 10 python benchmarks/threads.py --faust-r /path/to/FAUST_r --weights /path/to/ckpt_ep20.pth \
        [--rounds 2] [--methods descriptor_nn,deep_shells_published,...] [--out benchmarks/results/threads.json]

Each run is ``evaluate.py model=<method> data=faust_r`` on a few FAUST_r test pairs (``max_pairs``), with reduced
settings for the slow axiomatic methods (below); the time is the matcher's own (``seconds_per_pair`` of
metrics.json, the median over rounds). The settings of one method run one after the other inside a round, and the
rounds repeat the whole list, so a change in the machine's load affects every setting alike (on a shared machine
report ratios). The shape cache is filled by a first, untimed run of each method.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench_common import machine_info

REPO = Path(__file__).resolve().parents[1]

#: method -> (evaluate.py options, pairs): reduced settings where the published ones take minutes per pair.
METHODS = {
    "descriptor_nn": (["model=descriptor_nn"], 4),
    "deep_shells_published": (["model=deep_shells_published"], 2),
    "neuromorph": (["model=neuromorph"], 2),
    "gmsm": (["model=gmsm", "matching=pairwise"], 2),
    "smooth_shells": (["model=smooth_shells"], 1),
    "divfree": (["model=divfree", "model.samples=[250,500,500]", "model.iterations=[20,20,40]"], 1),
    "hamiltonian": (["model=hamiltonian", "model.n_modes=3", "model.iterations=10"], 1),
}
#: setting name -> evaluate.py options (``default`` passes none: threads=null).
SETTINGS = {"threads=1": ["threads=1"], "threads=2": ["threads=2"], "default": []}


def run(method: str, options: list[str], pairs: int, faust_r: str, weights: str, out: Path) -> float:
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env.update(SHAPECORR_FAUST_R=faust_r, SHAPECORR_DEEP_SHELLS_WEIGHTS=weights, PYTHONPATH=str(REPO))
    cmd = [sys.executable, "evaluate.py", *METHODS[method][0], *options, "data=faust_r", f"max_pairs={pairs}",
           "n_examples=0", "progress=false", "resume=false", f"output_dir={out}"]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{proc.stderr[-3000:]}")
    return float(json.loads((out / "metrics.json").read_text())["seconds_per_pair"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--faust-r", default=os.environ.get("SHAPECORR_FAUST_R"), required=False)
    parser.add_argument("--weights", default=os.environ.get("SHAPECORR_DEEP_SHELLS_WEIGHTS"))
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--work", default="/tmp/shapecorr_threads")
    parser.add_argument("--out", default=str(REPO / "benchmarks/results/threads.json"))
    args = parser.parse_args()
    if not args.faust_r:
        sys.exit("give --faust-r DIR or set SHAPECORR_FAUST_R")
    methods = args.methods.split(",")
    work = Path(args.work)
    for method in methods:  # fill the cache (untimed)
        run(method, ["threads=2"], METHODS[method][1], args.faust_r, args.weights or "", work / f"{method}_warm")
    times: dict[str, dict[str, list[float]]] = {m: {s: [] for s in SETTINGS} for m in methods}
    start = time.time()
    for r in range(args.rounds):
        for method in methods:
            order = list(SETTINGS) if r % 2 == 0 else list(SETTINGS)[::-1]
            for setting in order:
                seconds = run(method, SETTINGS[setting], METHODS[method][1], args.faust_r, args.weights or "",
                              work / f"{method}_{setting}_{r}")
                times[method][setting].append(seconds)
                print(f"round {r} {method:24s} {setting:10s} {seconds:8.2f} s/pair", flush=True)
    table = {}
    for method in methods:
        med = {s: statistics.median(v) for s, v in times[method].items()}
        best = min(med[s] for s in ("threads=1", "threads=2"))
        table[method] = {"options": METHODS[method][0], "pairs": METHODS[method][1], "seconds_per_pair": med,
                         "all_rounds": times[method], "default_over_best": med["default"] / best}
    result = {
        "command": " ".join([sys.executable, *sys.argv]),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": machine_info(),
        "wall_seconds": time.time() - start,
        "notes": ("FAUST_r test pairs (max_pairs evenly spaced), cache warm; seconds_per_pair: the matcher's own time, "
                  "median over rounds; settings interleaved within each round (order reversed every other round) "
                  "on a machine shared with other jobs; default_over_best: default / best of threads=1, 2."),
        "methods": table,
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    for method, row in table.items():
        cells = "  ".join(f"{s} {v:7.2f}" for s, v in row["seconds_per_pair"].items())
        print(f"{method:24s} {cells}  default/best {row['default_over_best']:.2f}")


if __name__ == "__main__":
    main()
