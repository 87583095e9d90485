"""Side by side: ``benchmarks/speed.py`` cases from two source trees, one fresh process each, alternating.

    python benchmarks/speed_interleaved.py --trees /tmp/base_tree . --cases deep_shells_query gmsm_query \
        --rounds 4 --repeats 3 --out benchmarks/results/speed_interleaved.json

Each tree is a checkout of this repository (e.g. ``git archive <commit> | tar -x -C /tmp/base_tree``); its own
``benchmarks/speed.py --child`` runs with ``PYTHONPATH`` set to that tree, one thread (``OMP_NUM_THREADS=1``), in
the order tree 1, tree 2 for every case, ``--rounds`` times. On a shared machine the two codes then see the same
load; compare the CPU seconds of one round, and the medians over the rounds. The load average before each process
is recorded with its result. Output: every process's result (``speed.py``'s child record), per case and tree the
median CPU seconds over the rounds, and the ratio of the first tree's median to each other tree's.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import bench_common

REPO = Path(__file__).resolve().parents[1]
DEFAULT_GOLDEN = Path("/work/shared/data/reference/deep_shells_golden")


def _commit(tree: Path) -> str | None:
    out = subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True)
    return out.stdout.strip() if out.returncode == 0 else None


def run_child(tree: Path, case: str, golden: Path, repeats: int, timeout: float) -> dict:
    """One ``speed.py --child`` process of ``tree`` at one thread; its record plus the load before it."""
    cmd = [sys.executable, str(tree / "benchmarks" / "speed.py"), "--child", case, "--golden", str(golden),
           "--device", "cpu", "--threads", "1", "--repeats", str(repeats)]
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    load = list(os.getloadavg())
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tree, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"case": case, "error": f"timed out after {timeout:.0f} s", "load_average_before": load}
    if proc.returncode != 0:
        lines = proc.stderr.strip().splitlines()
        return {"case": case, "error": lines[-1] if lines else f"exit {proc.returncode}", "load_average_before": load}
    record = json.loads(proc.stdout.strip().splitlines()[-1])
    record["load_average_before"] = load
    return record


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trees", nargs="+", type=Path, required=True,
                        help="source trees; the first is the baseline of the ratios")
    parser.add_argument("--labels", nargs="+", default=None,
                        help="a name per tree for the record (e.g. its commit; default: git's HEAD of the tree)")
    parser.add_argument("--cases", nargs="+", required=True, help="cases of benchmarks/speed.py")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per process (after one warm-up call)")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per process")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "speed_interleaved.json")
    args = parser.parse_args(argv)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", DEFAULT_GOLDEN))
    trees = [t.resolve() for t in args.trees]
    missing = [str(t) for t in trees if not (t / "benchmarks" / "speed.py").is_file()]
    if missing:
        print(f"error: no benchmarks/speed.py in {missing}", file=sys.stderr)
        return 2
    if args.labels is not None and len(args.labels) != len(trees):
        print("error: --labels needs one name per tree", file=sys.stderr)
        return 2
    labels = args.labels or [_commit(t) for t in trees]
    runs = []
    for rnd in range(args.rounds):
        for case in args.cases:
            for i, tree in enumerate(trees):
                record = run_child(tree, case, golden, args.repeats, args.timeout)
                record.update(round=rnd, tree=i)
                runs.append(record)
                shown = record.get("error") or f"cpu {record['cpu_seconds_median']:.3f} s"
                print(f"round {rnd} {case:20s} tree {i} {shown} (load {record['load_average_before'][0]:.1f})",
                      flush=True)
    summary = {}
    for case in args.cases:
        medians = []
        for i in range(len(trees)):
            values = [r["cpu_seconds_median"] for r in runs
                      if r["case"] == case and r["tree"] == i and "error" not in r]
            medians.append(statistics.median(values) if values else None)
        summary[case] = {"cpu_seconds_median_over_rounds": medians,
                         "ratio_to_first_tree": [medians[0] / m if medians[0] and m else None for m in medians]}
        print(f"{case}: " + ", ".join(f"tree {i} {m:.3f} s" for i, m in enumerate(medians) if m is not None))
    report = {
        "benchmark": "speed_interleaved",
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "trees": [{"path": str(t), "label": label} for t, label in zip(trees, labels)],
        "rounds": args.rounds,
        "repeats": args.repeats,
        "machine": bench_common.machine_info(),
        "summary": summary,
        "runs": runs,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
