"""Compare the flow integrators of shapecorr.geometry.divergence_free on a random field (docs/divfree.md §3).

For a random coefficient vector (K = 8, Gaussian, scaled to a given mean speed) and a closed sphere mesh in the
box, each rule is measured at several step counts:

- ``volume``: relative volume change of the sphere after the flow;
- ``reverse``: forward flow with ``a`` then the same rule with ``-a``, mean distance back to the start
  (in units of the mean displacement);
- ``vs_exact``: mean distance of the endpoint from a reference flow (midpoint with 512 steps) over the time the
  rule actually covers (1 for "midpoint", 1.5 / n_steps for "original"), relative to the mean displacement.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/divfree_integrators.py [--speed 0.3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
import trimesh

from shapecorr.eval.metrics import relative_volume_change
from shapecorr.geometry import divergence_free as df

#: Steps of the reference flow (midpoint, error ~ 1/steps^2).
REFERENCE_STEPS = 512


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speed", type=float, default=0.3, help="mean speed of the field on the sphere (box units)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="write the numbers as JSON here")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.25)
    verts = torch.tensor(sphere.vertices + 0.5, dtype=torch.float64)
    faces = np.asarray(sphere.faces)
    coeffs = torch.randn(df.n_fields(df.PUBLISHED_N_MODES), dtype=torch.float64)
    coeffs = coeffs * args.speed / df.velocity(verts, coeffs).norm(dim=1).mean()
    rows = []
    # "midpoint@original_time": the midpoint rule over the (shorter) time the original rule covers, for a
    # comparison at equal displacement.
    for rule in ("midpoint", "original", "midpoint@original_time"):
        for n_steps in (4, 16, 64):
            t_cover = 1.0 if rule == "midpoint" else 1.5 / n_steps
            base = rule.split("@")[0]
            end = df.integrate_flow(verts, coeffs, n_steps, base, t_end=t_cover if base == "midpoint" else 1.0)
            back = df.integrate_flow(end, -coeffs, n_steps, base, t_end=t_cover if base == "midpoint" else 1.0)
            # (the original rule runs backwards only by negating the field: its steps scale with h^2)
            exact = df.integrate_flow(verts, coeffs, REFERENCE_STEPS, "midpoint", t_end=t_cover)
            disp = (exact - verts).norm(dim=1).mean().item()
            rows.append({
                "rule": rule, "n_steps": n_steps, "time_covered": t_cover, "mean_displacement": disp,
                "volume_change": relative_volume_change(verts.numpy(), faces, end.numpy()),
                "reverse_error": (back - verts).norm(dim=1).mean().item() / disp,
                "error_vs_exact": (end - exact).norm(dim=1).mean().item() / disp,
            })
            print(json.dumps(rows[-1]))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"speed": args.speed, "seed": args.seed, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
