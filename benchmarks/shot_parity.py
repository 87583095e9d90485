"""SHOT parity and speed against the original C++ SHOT of the Deep Shells preprocessing.

For the four FAUST_r shapes of the Deep Shells reference data (``inputs_<x>__<y>.npz``: ``s_verts``,
``s_faces``, ``s_shot``), computes :func:`shapecorr.geometry.shot_descriptor.shot` with its defaults and reports the
per-vertex cosine similarity to the stored SHOT (quantiles, mean), the same for two variants (area-weighted
normals; ``legacy=False``), how the disagreements split between frame-sign ties and the rest, the runtime
(median of ``--repeats`` runs after one warm-up), the peak memory of one call, and the neighbour counts.
Writes ``benchmarks/results/shot_parity.json``.

    python benchmarks/shot_parity.py --golden /path/to/deep_shells_golden
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
import tracemalloc
from datetime import datetime, timezone
from pathlib import Path

import bench_common

import numpy as np
from scipy.spatial import cKDTree

from shapecorr.geometry.shot_descriptor import (
    SHOT_RADIUS_FRACTION,
    SHOT_REFERENCE_AREA,
    shot,
    shot_lrf,
)

GOLDEN_ENV = "SHAPECORR_DEEP_SHELLS_GOLDEN"
PAIRS = ("tr_reg_080__tr_reg_081", "tr_reg_090__tr_reg_095")
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
#: A vertex "agrees" with the reference when its cosine exceeds this.
AGREE_COS = 0.999
VARIANTS = {
    "default (legacy=True, normals='uniform')": {},
    "normals='area'": {"normals": "area"},
    "legacy=False (paper frame weights, no wrap quirks)": {"legacy": False},
}


def _cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return (a * b).sum(1) / np.maximum(norms, np.finfo(np.float64).tiny)


def _distribution(cos: np.ndarray) -> dict:
    out = {f"q{int(round(100 * q)):02d}": float(np.quantile(cos, q)) for q in QUANTILES}
    out.update(
        mean=float(cos.mean()),
        min=float(cos.min()),
        frac_above_0_999=float((cos > AGREE_COS).mean()),
        frac_below_0_99=float((cos < 0.99).mean()),
        n_vertices=int(cos.size),
    )
    return out


def _area(v: np.ndarray, f: np.ndarray) -> float:
    tri = v[f]
    return 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def _frame_ties(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(n,) bool: vertices whose x or z frame axis has exactly as many neighbours on each side, i.e. where
    the majority sign rule is undecided and the reference kept its eigen-solver's arbitrary sign."""
    scale = math.sqrt(SHOT_REFERENCE_AREA / _area(v, f))
    vs = v * scale
    radius = SHOT_RADIUS_FRACTION * math.sqrt(SHOT_REFERENCE_AREA)
    frames, _ = shot_lrf(vs, radius, squared_distance_weights=True)
    pairs = cKDTree(vs).query_pairs(radius, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    count = np.bincount(i, minlength=len(v))
    tie = np.zeros(len(v), dtype=bool)
    for axis in (frames[:, 0], frames[:, 2]):
        proj = np.einsum("ma,ma->m", vs[j] - vs[i], axis[i])
        positive = np.bincount(i, weights=proj >= 0, minlength=len(v))
        tie |= 2 * positive == count
    return tie


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--golden",
        default=os.environ.get(GOLDEN_ENV),
        help=f"folder of the Deep Shells reference data (default: ${GOLDEN_ENV})",
    )
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "shot_parity.json"))
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per shape after one warm-up")
    args = parser.parse_args(argv)
    machine = bench_common.machine_info()  # before the work, so the load average is the other users'
    if not args.golden:
        parser.error(f"give --golden or set {GOLDEN_ENV}")
    golden = Path(args.golden)

    shapes = []
    for pair in PAIRS:
        path = golden / f"inputs_{pair}.npz"
        if not path.is_file():
            parser.error(f"{path} not found")
        data = np.load(path)
        x_name, y_name = pair.split("__")
        for s, name in (("x", x_name), ("y", y_name)):
            shapes.append((name, data[f"{s}_verts"], data[f"{s}_faces"], data[f"{s}_shot"]))

    per_shape, all_cos, all_ties = [], {k: [] for k in VARIANTS}, []
    for name, v, f, ref in shapes:
        entry = {"shape": name, "n_vertices": int(len(v))}
        shot(v, f)  # warm-up
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            ours = shot(v, f)
            times.append(time.perf_counter() - t0)
        entry["time_s_median"] = statistics.median(times)
        entry["time_s_all"] = times
        tracemalloc.start()
        shot(v, f)
        entry["peak_traced_memory_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()

        radius = SHOT_RADIUS_FRACTION * math.sqrt(_area(v.astype(np.float64), f))
        counts = np.array([len(nb) - 1 for nb in cKDTree(v).query_ball_point(v, radius)])
        entry["neighbours_per_vertex"] = {"min": int(counts.min()), "median": float(np.median(counts)),
                                          "max": int(counts.max())}

        for label, kwargs in VARIANTS.items():
            cos = _cosines(ours if not kwargs else shot(v, f, **kwargs), ref)
            all_cos[label].append(cos)
            if not kwargs:
                entry["cosine_default"] = _distribution(cos)
        ties = _frame_ties(v.astype(np.float64), f)
        all_ties.append(ties)
        entry["frame_tie_fraction"] = float(ties.mean())
        per_shape.append(entry)
        stats = entry["cosine_default"]
        print(
            f"{name}: median cos {stats['q50']:.6f}, mean {stats['mean']:.4f}, "
            f"{entry['time_s_median']:.2f} s, peak {entry['peak_traced_memory_mb']:.0f} MB",
            flush=True,
        )

    default_label = next(iter(VARIANTS))
    cos = np.concatenate(all_cos[default_label])
    ties = np.concatenate(all_ties)
    disagree = cos <= AGREE_COS
    result = {
        "benchmark": "shot_parity",
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine,
        "reference": "original C++ SHOT (Deep Shells MATLAB preprocessing), inputs_<x>__<y>.npz s_shot",
        "settings": {
            "radius": "5% of sqrt(area)",
            "n_bins": 10,
            "min_neighbors": 3,
            "descriptor_length": 352,
        },
        "metric": "per-vertex cosine similarity between our SHOT row and the reference row",
        "cosine_all_shapes": {label: _distribution(np.concatenate(c)) for label, c in all_cos.items()},
        "disagreement_analysis": {
            "agree_threshold": AGREE_COS,
            "frac_vertices_with_frame_tie": float(ties.mean()),
            "frac_disagreeing_vertices_that_are_ties": (
                float(ties[disagree].mean()) if disagree.any() else None
            ),
            "cosine_non_tie_vertices": _distribution(cos[~ties]),
            "cosine_tie_vertices": _distribution(cos[ties]),
            "note": (
                "At a tie the reference keeps the arbitrary sign of its eigen-solver (Eigen); we break "
                "ties by the sum of projections, so about half of the tie vertices get the other frame. "
                "In a one-off experiment (not part of this benchmark) with Eigen's own eigenvectors "
                "substituted in the frame step, the same histogram code gave mean cosine 0.9999996 and "
                "no vertex below 0.99."
            ),
        },
        "time_unit": "s",
        "per_shape": per_shape,
        "time_s_median_over_shapes": statistics.median(e["time_s_median"] for e in per_shape),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(out)
    print(json.dumps(result["cosine_all_shapes"], indent=2))
    print(json.dumps({k: v for k, v in result["disagreement_analysis"].items() if k != "note"}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
