"""Benchmark: the Hamiltonian interpolation's two basis conventions on animations with true in-between frames.

    OMP_NUM_THREADS=1 python benchmarks/hamiltonian_conventions.py [--sequences 3] [--frames 9] \
        [--n-modes 4 --samples 1000 --iterations 40] [--template-verts 4000] [--out FILE]

An **animation** is made with the synthetic skinning generator (``shapecorr.data.synthetic``): one human subject
(template, identity proportions of ``sample_identity``), two key poses A and B of the human body plan, and the
frames ``F(s) = skin((1 - s) A + s B)`` for ``s = 0, 1/(frames-1), ..., 1``: the joint angles move linearly, so
the in-betweens are a plausible true motion and every frame has the template's connectivity (the ground-truth map
is the identity). The Hamiltonian interpolation (:func:`shapecorr.axiomatic.hamiltonian.hamiltonian_interpolation`)
moves ``F(0)`` onto ``F(1)`` with each basis ``convention`` (``published``: the stated scaling and the curl's sign;
``original_code``: the released code's, docs/divfree.md §2), and the linear blend ``(1 - t) F(0) + t F(1)`` is the
reference. Recorded per sequence, method and time: the mean vertex distance to the true in-between ``F(t)``
(fraction of sqrt(area(F(0)))), the volume score ``V_t/V_0 + V_0/V_t - 2`` and the conformal distortion
(``shapecorr.eval.metrics``); per fit the final alignment MSE (box units^2), the ARAP energy and the seconds.

The Hamiltonian runs at the reduced CPU setting of ``configs/interpolator/hamiltonian_cpu.yaml`` unless
``--n-modes / --samples / --iterations`` say otherwise. Results: ``benchmarks/results/hamiltonian_conventions.json``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "hamiltonian_conventions.json"
#: (pose A, pose B) indices into the human key poses of ``shapecorr.data.synthetic.poses.KEY_POSES``.
SEQUENCES = ((0, 1), (0, 2), (1, 5), (3, 9), (6, 10))
CONVENTIONS = ("published", "original_code")


def animation(seq: tuple[int, int], subject: int, n_frames: int, template_verts: int):
    """``(frames (S, n, 3), faces, s (S,), names)`` of one skinned animation between two key poses (y up)."""
    from shapecorr.data.synthetic import poses
    from shapecorr.data.synthetic.config import preset
    from shapecorr.data.synthetic.generator import OUTPUT_ROTATION, _cached_template
    from shapecorr.data.synthetic.skinning import blend_skin, identity_transforms, pose_transforms, sample_identity

    cfg = preset("default")
    template = _cached_template("human", template_verts, cfg.grid_step, cfg.remesh_iterations)
    plan = template.plan
    rng = np.random.default_rng([cfg.seed, 0, subject, 1])
    identity = sample_identity(plan, rng, cfg.length_std, cfg.thickness_std, cfg.build_std)
    id_transforms, heads = identity_transforms(plan, identity)
    rest = blend_skin(template.verts, template.weights, id_transforms)
    name_a, angles_a = poses.key_pose(plan, seq[0])
    name_b, angles_b = poses.key_pose(plan, seq[1])
    s = np.linspace(0.0, 1.0, n_frames)
    posed = [pose_transforms(plan, heads, (1 - t) * angles_a + t * angles_b) for t in s]
    frames = np.stack([blend_skin(rest, template.weights, transforms) for transforms in posed])
    frames = frames @ OUTPUT_ROTATION.T
    return frames, np.asarray(template.faces), s, (name_a, name_b)


def frame_metrics(frames: np.ndarray, truth: np.ndarray, faces: np.ndarray, sqrt_area: float) -> dict:
    from shapecorr.eval import metrics

    rest = truth[0]
    return {
        "distance_to_true": [float(np.linalg.norm(f - g, axis=1).mean() / sqrt_area) for f, g in zip(frames, truth)],
        "volume_score": [float(metrics.volume_change_score(rest, faces, f)) for f in frames],
        "conformal_distortion": [float(metrics.mean_conformal_distortion(rest, faces, f)) for f in frames],
    }


def _mean_inner(values: list[float]) -> float:
    return float(np.mean(values[1:-1]))


def main(argv=None) -> int:
    import torch

    from shapecorr.axiomatic.hamiltonian import hamiltonian_interpolation
    from shapecorr.eval.metrics import surface_area

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequences", type=int, default=3, help=f"animations (at most {len(SEQUENCES)})")
    parser.add_argument("--frames", type=int, default=9, help="frames per animation, both ends included")
    parser.add_argument("--template-verts", type=int, default=4000, help="vertices of the human template")
    parser.add_argument("--n-modes", type=int, default=4)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--n-steps", type=int, default=16)
    parser.add_argument("--out", default=str(RESULT))
    args = parser.parse_args(argv)
    settings = {"n_modes": args.n_modes, "samples": args.samples, "iterations": args.iterations,
                "n_steps": args.n_steps}
    rows = []
    for k, seq in enumerate(SEQUENCES[:args.sequences]):
        truth, faces, s, names = animation(seq, subject=k, n_frames=args.frames, template_verts=args.template_verts)
        sqrt_area = float(np.sqrt(surface_area(truth[0], faces)))
        x, y = truth[0], truth[-1]
        row = {"poses": names, "n_verts": int(x.shape[0]), "times": s.tolist(),
               "linear_blend": frame_metrics(np.stack([(1 - t) * x + t * y for t in s]), truth, faces, sqrt_area)}
        for conv in CONVENTIONS:
            fit = hamiltonian_interpolation(torch.tensor(x, dtype=torch.float32), torch.tensor(faces),
                                            torch.tensor(y, dtype=torch.float32), {**settings, "convention": conv},
                                            times=s.tolist())
            row[conv] = {**frame_metrics(fit.frames.double().numpy(), truth, faces, sqrt_area),
                         "align_mse": fit.energies["align"], "arap": fit.energies["arap"], "seconds": fit.seconds}
            print(f"{names[0]} -> {names[1]} {conv}: align {fit.energies['align']:.3e}, distance to true in-betweens "
                  f"{_mean_inner(row[conv]['distance_to_true']):.4f} (blend "
                  f"{_mean_inner(row['linear_blend']['distance_to_true']):.4f}), {fit.seconds:.1f} s", flush=True)
        rows.append(row)
    table = {}
    for method in ("linear_blend", *CONVENTIONS):
        table[method] = {
            "distance_to_true_inner_mean": float(np.mean([_mean_inner(r[method]["distance_to_true"]) for r in rows])),
            "distance_at_t1": float(np.mean([r[method]["distance_to_true"][-1] for r in rows])),
            "volume_score_max": float(np.mean([max(r[method]["volume_score"]) for r in rows])),
            "conformal_distortion_inner_mean": float(np.mean([_mean_inner(r[method]["conformal_distortion"])
                                                               for r in rows])),
        }
        if method != "linear_blend":
            table[method]["align_mse"] = float(np.mean([r[method]["align_mse"] for r in rows]))
            table[method]["seconds"] = float(np.mean([r[method]["seconds"] for r in rows]))
    summary = {"settings": settings, "sequences": args.sequences, "frames": args.frames,
               "units": "distance: mean vertex distance / sqrt(area(F(0))); volume score V_t/V_0 + V_0/V_t - 2; "
                        "conformal distortion: shapecorr.eval.metrics (scale-invariant, clamp 10); align_mse: box "
                        "units^2. *_inner_mean: over the frames strictly between t = 0 and 1; volume_score_max: the "
                        "largest over t, averaged over sequences.",
               "table": table, "sequences_detail": rows}
    report = bench_common.summary_report("hamiltonian_conventions.py", sys.argv[1:] if argv is None else list(argv),
                                         summary)
    bench_common.write_report(args.out, report)
    for method, vals in table.items():
        print(method, {k: round(v, 6) for k, v in vals.items()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
