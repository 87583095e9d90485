"""Benchmark: Deep Shells' training pair and G-MSM's query, the original codes and shapecorr side by side.

    python benchmarks/originals_side_by_side.py --deep-shells-src /tmp/deep_shells_original \
        --gmsm-src /tmp/gmsm_original [--cases deep_shells_train gmsm_query] [--rounds 5] [--repeats 3]

``--deep-shells-src`` / ``--gmsm-src``: checkouts of github.com/marvin-eisenberger/deep-shells (with its released
``models/Faust_Scape/ckpt_ep20.pth``) and github.com/marvin-eisenberger/gmsm-matching, outside this repository. Their
processes are ``deep_shells_original_query.py`` and ``gmsm_original_step.py`` (which write the shims they need to a
temporary folder); nothing of the originals is part of this project.

Protocol:

* Cases: ``speed.py``'s cases of the same names, on its golden inputs. ``deep_shells_train``: one training pair
  (2000 samples per shape, the published shells 6..21, forward + backward; the original's ``UnsupervisedShells``
  loop per pair, ``deep_shells_original_query.py --unit train``), both codes on the same samples (the ones
  shapecorr's step draws, written to a temporary ``.npz``) and the same released weights. ``gmsm_query``: G-MSM's
  fast one-level query of the pair (the original's ``test_model_fast``, ``gmsm_original_step.py --unit query``),
  each code with its own seed-0 initial DiffusionNet weights and its own random samples. ``deep_shells_query`` and
  ``gmsm_train`` run the same way (the units of those two scripts).
* Each measurement is a fresh process, one thread (``OMP_NUM_THREADS=1``, ``torch.set_num_threads(1)``), one warm-up
  call, then ``--repeats`` timed calls (process CPU seconds, their median). The processes alternate, original then
  shapecorr (``speed.py --child <case> --device cpu --threads 1``), ``--rounds`` times per case; the summary is
  the median over the processes of each code (``bench_common.side_by_side_summary``). Peak memory: the process's
  maximum resident set (``ru_maxrss``, imports included).
* Checks that the two codes compute the same thing: for ``deep_shells_train`` shapecorr's step with the original's
  settings on every deviation (``DeepShellsConfig.original()``, docs/deep_shells.md §9) on the same samples, in
  this process: its loss and gradient norm against the original's (the timed shapecorr step runs the published
  config, whose deviations change the loss, not the work). For ``gmsm_query`` the pair costs of both (the
  one-level alignment cost of the maps: the original's ``loss_1``), of the same size only: the weights differ.

Writes ``benchmarks/results/originals_side_by_side.json`` (``--out``) with the command, date, machine, the originals'
commits (when they are git checkouts) and the load average before and after every process.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import bench_common
import speed

REPO = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
RESULT = REPO / "benchmarks" / "results" / "originals_side_by_side.json"
#: Case -> (the original's source argument, its measuring script, its unit).
ORIGINALS = {"deep_shells_train": ("deep_shells_src", "deep_shells_original_query.py", "train"),
             "deep_shells_query": ("deep_shells_src", "deep_shells_original_query.py", "query"),
             "gmsm_train": ("gmsm_src", "gmsm_original_step.py", "train"),
             "gmsm_query": ("gmsm_src", "gmsm_original_step.py", "query")}
DEFAULT_CASES = ("deep_shells_train", "gmsm_query")


def write_deep_shells_samples(golden: Path, path: Path) -> dict:
    """The vertex samples shapecorr's ``deep_shells_train`` step draws (``sample_generator(0)``), written to
    ``path`` as ``samples_x``, ``samples_y`` ``(2000,)`` int64; returns them as tensors."""
    import numpy as np

    from shapecorr.matching.deep_shells import random_samples
    from shapecorr.models.deep_shells import DeepShells

    with np.load(golden / f"inputs_{speed.PAIR}.npz") as inputs:
        n = {side: inputs[f"{side}_verts"].shape[0] for side in "xy"}
    gen = DeepShells(num_samples=speed.TRAIN_SAMPLES).sample_generator(0)
    samples = {side: random_samples(n[side], speed.TRAIN_SAMPLES, generator=gen) for side in "xy"}
    np.savez(path, **{f"samples_{side}": s.numpy() for side, s in samples.items()})
    return samples


def deep_shells_check(golden: Path) -> dict:
    """shapecorr's Deep Shells training pair (``training_step`` + backward, the samples of
    :func:`write_deep_shells_samples`) with the original's settings on every deviation
    (``DeepShellsConfig.original()``): loss, gradient norm of the backbone and CPU seconds of three steps (this
    process, one thread)."""
    import torch

    from shapecorr.matching.deep_shells import DeepShellsConfig

    torch.set_num_threads(1)
    model = speed.deep_shells_model(golden, torch.device("cpu"), True,
                                    layer=DeepShellsConfig.original(num_samples=speed.TRAIN_SAMPLES))
    step = speed._learned_unit(model, speed._golden_pair(golden, torch.device("cpu")), True)
    cpus, losses = [], []
    for _ in range(3):
        start = time.process_time()
        losses.append(step())
        cpus.append(time.process_time() - start)
    grads = [p.grad.double() for p in model.parameters() if p.grad is not None]
    return {"settings": "DeepShellsConfig.original()", "loss": losses[-1], "losses": losses,
            "gradient_norm": float(torch.sqrt(sum((g ** 2).sum() for g in grads))), "cpu_seconds": cpus}


def map_errors(map_x_to_y, verts_y, faces_y, corres: Path) -> dict:
    """Euclidean error of a map ``x -> y`` at the FAUST_r reference points (``corres``: folder of the ``.vts``
    files of the golden pair), divided by sqrt(area of Y): mean and median."""
    import numpy as np

    from shapecorr.eval.metrics import surface_area

    ref = [np.loadtxt(corres / f"{name}.vts", dtype=np.int64) - 1 for name in speed.PAIR.split("__")]
    err = np.linalg.norm(verts_y[np.asarray(map_x_to_y)[ref[0]]] - verts_y[ref[1]], axis=1)
    err = err / np.sqrt(surface_area(verts_y, faces_y))
    return {"mean": float(err.mean()), "median": float(np.median(err))}


def gmsm_check(golden: Path, corres: Path | None) -> dict:
    """shapecorr's G-MSM query of the golden pair as ``gmsm_query`` runs it and with dropout on (the original's
    queries keep the network in training mode): pair cost, map errors (:func:`map_errors`) and CPU seconds of three
    queries each (this process, one thread); the error of the golden original Deep Shells map for scale."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    device = torch.device("cpu")
    pair = speed._golden_pair(golden, device, diffusion=True)
    with np.load(golden / f"inputs_{speed.PAIR}.npz") as inputs:
        verts_y, faces_y = inputs["y_verts"].astype(np.float64), inputs["y_faces"]
    out = {}
    if corres is not None:
        with np.load(golden / f"original_output_{speed.PAIR}.npz") as reference:
            out["golden_original_deep_shells_map_errors"] = map_errors(reference["map_x_to_y"], verts_y, faces_y,
                                                                       corres)
    for label, dropout in (("as_timed", False), ("dropout_at_test", True)):
        model = speed.gmsm_model(golden, device, False, dropout_at_test=dropout)
        cpus, costs = [], []
        for _ in range(3):
            start = time.process_time()
            result = model.match(pair.x, pair.y)
            cpus.append(time.process_time() - start)
            costs.append(float(result.extras["pair_cost"]))
        out[label] = {"cpu_seconds": cpus, "pair_costs": costs}
        if corres is not None:
            out[label]["map_errors"] = map_errors(result.p2p.numpy(), verts_y, faces_y, corres)
    return out


def _checks(case: str, records: list[dict], ours: dict | None, maps: Path | None = None,
            corres: Path | None = None, golden: Path | None = None) -> dict:
    originals = [r for r in records if r["case"] == case and r["code"] == "original" and "error" not in r]
    timed = [r for r in records if r["case"] == case and r["code"] == "shapecorr" and "error" not in r]
    if not originals or not timed:
        return {}
    if case == "deep_shells_train":
        loss, grad = originals[0]["losses"][0], originals[0]["gradient_norm"]
        out = {"original_loss": loss, "original_gradient_norm": grad,
               "shapecorr_published_config_loss": timed[0]["value"]}
        if ours:
            out.update(shapecorr_original_settings=ours,
                       loss_relative_difference=abs(ours["loss"] - loss) / abs(loss),
                       gradient_norm_relative_difference=abs(ours["gradient_norm"] - grad) / grad)
        return out
    if case == "gmsm_query":
        out = {"original_pair_costs": [q["losses"][1] for r in originals for q in r["query_outputs"]],
               "original_level_energy_means": [q["losses"][0] for r in originals for q in r["query_outputs"]],
               "shapecorr_pair_costs_timed": [r["value"] for r in timed], "shapecorr": ours}
        if maps is not None and corres is not None and maps.is_file():
            import numpy as np

            with np.load(golden / f"inputs_{speed.PAIR}.npz") as inputs, np.load(maps) as stored:
                out["original_last_map_errors"] = map_errors(stored["map_x_to_y"], inputs["y_verts"].astype(
                    np.float64), inputs["y_faces"], corres)
        return out
    return {}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--deep-shells-src", type=Path, default=None, help="checkout of the original Deep Shells")
    parser.add_argument("--gmsm-src", type=Path, default=None, help="checkout of the original G-MSM code")
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), choices=list(ORIGINALS))
    parser.add_argument("--rounds", type=int, default=5, help="processes per code and case (alternating)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per process (after one warm-up)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per process")
    parser.add_argument("--out", type=Path, default=RESULT)
    args = parser.parse_args(argv)
    sources = {}
    for case in args.cases:
        attr = ORIGINALS[case][0]
        src = getattr(args, attr)
        if src is None:
            parser.error(f"{case} needs --{attr.replace('_', '-')}")
        if str(src.resolve()).startswith(str(REPO)):
            parser.error(f"{src}: keep the original code and its shims outside the repository")
        sources[case] = src.resolve()
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", speed.DEFAULT_GOLDEN))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    faust_r = os.environ.get("SHAPECORR_FAUST_R")
    corres = Path(faust_r) / "corres" if faust_r else None  # the map errors of the G-MSM check need it
    records, load_start = [], os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="originals_sbs_") as tmp:
        samples_path, maps_path = Path(tmp) / "deep_shells_samples.npz", Path(tmp) / "gmsm_original_maps.npz"
        if "deep_shells_train" in args.cases:
            write_deep_shells_samples(golden, samples_path)
        for case in args.cases:
            _, script, unit = ORIGINALS[case]
            original = [sys.executable, str(HERE / script), "--original-src", str(sources[case]), "--golden",
                        str(golden), "--unit", unit, "--repeats", str(args.repeats)]
            if case == "deep_shells_train":
                original += ["--samples", str(samples_path)]
            if case == "gmsm_query":
                original += ["--save-maps", str(maps_path)]
            ours = speed.child_command(case, golden, "cpu", 1, args.repeats)
            for rnd in range(args.rounds):
                for code, cmd in (("original", original), ("shapecorr", ours)):
                    start = time.perf_counter()
                    record = bench_common.run_json_child(cmd, env, args.timeout, REPO)
                    record.update(case=case, code=code, round=rnd, process_seconds=time.perf_counter() - start)
                    records.append(record)
                    shown = record.get("error") or (f"cpu {record['cpu_seconds_median']:.3f} s, max RSS "
                                                    f"{record['process_max_rss_mb']:.0f} MB")
                    print(f"{case} round {rnd} {code:9s}: {shown} (load {record['load_average_1min_before']:.2f})",
                          flush=True)
        ours_checked = {"deep_shells_train": deep_shells_check(golden) if "deep_shells_train" in args.cases else None,
                        "gmsm_query": gmsm_check(golden, corres) if "gmsm_query" in args.cases else None}
        summary = bench_common.side_by_side_summary(records, args.cases, ["original", "shapecorr"])
        for case, entry in summary.items():
            recorded = speed.ORIGINAL_REFERENCE.get(case, {}).get("seconds")
            if "shapecorr" in entry:
                entry["target_ratio"] = speed.TARGET_RATIO.get(case)
                entry["original_recorded_seconds"] = recorded
                if recorded:
                    entry["ratio_recorded_original_over_shapecorr"] = (recorded
                                                                       / entry["shapecorr"]["cpu_seconds_median"])
                if "original" in entry:
                    per_round = [o["cpu_seconds_median"] / s["cpu_seconds_median"] for o, s in zip(
                        *([r for r in records if r["case"] == case and r["code"] == c and "error" not in r]
                          for c in ("original", "shapecorr")))]
                    entry["ratio_per_round"] = per_round
                    entry["memory_ratio_process_max"] = (entry["original"]["process_max_rss_mb_median"]
                                                         / entry["shapecorr"]["process_max_rss_mb_median"])
            entry["checks"] = _checks(case, records, ours_checked.get(case), maps_path, corres, golden)
    report = {
        "benchmark": "originals_side_by_side",
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "machine": bench_common.machine_info(),
        "load_average_start_end": [list(load_start), list(os.getloadavg())],
        "originals": {case: {"path": str(src), "script": ORIGINALS[case][1], "unit": ORIGINALS[case][2]}
                      for case, src in sources.items()},
        "protocol": {"threads": 1, "rounds": args.rounds, "repeats_per_process": args.repeats, "warmup": 1,
                     "order": "original, shapecorr, alternating",
                     "statistic": "median over processes of each process's median CPU seconds per call"},
        "summary": summary,
        "records": records,
    }
    bench_common.write_report(args.out, report)
    for case, entry in summary.items():
        o, s = entry.get("original"), entry.get("shapecorr")
        if o and s:
            print(f"{case}: original {o['cpu_seconds_median']:.3f} s, shapecorr {s['cpu_seconds_median']:.3f} s, "
                  f"{s['ratio_original_over_this']:.1f}x (target {entry['target_ratio']}x); max RSS "
                  f"{o['process_max_rss_mb_median']:.0f} / {s['process_max_rss_mb_median']:.0f} MB")
        print(f"  checks: {json.dumps(entry['checks'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
