"""Benchmark: where one Hamiltonian-interpolation iteration spends its CPU time, part by part (docs/speed.md §4).

    python benchmarks/hamiltonian_profile.py [--case hamiltonian_small] [--repeats 20] [--out FILE.json]

The inputs and the iteration are those of ``benchmarks/speed.py``'s case (golden pair, box-normalized farthest-point
samples, targets of the original Deep Shells map), one thread. Timed, in this process, process CPU seconds
(medians of ``--repeats``):

* the iteration split into the simulation (forward, building the autograd graph), the backward and the Adam
  step (the parameters are moved by a few iterations first, so that the step is not at the zero field);
* the parts of one time step, at the state of the middle step of the simulation, each alone: the rotations and the
  force (forward, and forward + backward), the per-coordinate factors and the direction-major basis, the sparse
  operator ``G``, the product ``G Psi``, the system product ``Psi^T G Psi``, the Cholesky factorization and the
  solve with ``v = Psi xi``, the step's forward (``_StepSolve``) and its backward, the ARAP energy term.

Prints a table and writes JSON (``--out``, default none) with the command, date, machine and load average.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import statistics
import sys
import time
import warnings
from pathlib import Path

import bench_common
import speed


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        times.append(time.process_time() - start)
    return 1000 * statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", default="hamiltonian_small", choices=tuple(speed.HAMILTONIAN_SETTINGS))
    parser.add_argument("--golden", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    import numpy as np
    import torch

    from shapecorr.axiomatic import hamiltonian as ham
    from shapecorr.axiomatic.divfree import knn_graph_edges
    from shapecorr.geometry import divergence_free as df
    from shapecorr.geometry.sampling import farthest_point_sampling
    from shapecorr.losses.arap import edge_vectors

    warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
    torch.set_num_threads(1)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", speed.DEFAULT_GOLDEN))
    inputs = np.load(golden / f"inputs_{speed.PAIR}.npz")
    mapping = np.load(golden / f"original_output_{speed.PAIR}.npz")["map_x_to_y"].astype(np.int64)
    vx = torch.from_numpy(inputs["x_verts"]).float()
    target = torch.from_numpy(inputs["y_verts"][mapping]).float()
    cfg = ham.HamiltonianConfig(**speed.HAMILTONIAN_SETTINGS[args.case])
    box_x, box_y = df.box_normalization(vx, target, cfg.margin)
    bx, by = box_x.to_box(vx), box_y.to_box(target)
    samples = torch.from_numpy(farthest_point_sampling(bx, cfg.samples, start=0))
    x0, goal = bx[samples], by[samples]
    edges, counts = knn_graph_edges(x0, cfg.knn)
    graph = ham._Graph(edges, counts, edge_vectors(x0, edges))
    coeffs = torch.zeros(df.n_fields(cfg.n_modes), requires_grad=True)
    aniso = torch.eye(3).repeat(cfg.samples, 1, 1).requires_grad_(True)
    log_lam = torch.tensor(math.log(cfg.lambda_inertia)).requires_grad_(True)
    optimizer = torch.optim.Adam([coeffs, aniso, log_lam], lr=cfg.lr)
    h, n = 1.0 / cfg.n_steps, cfg.samples
    state = {}

    def forward():
        optimizer.zero_grad(set_to_none=True)
        x_end, e_arap, _ = ham._simulate(x0, coeffs, aniso, log_lam, graph, cfg.n_steps, cfg)
        state["loss"] = torch.nn.functional.mse_loss(x_end, goal) + cfg.lambda_reg * e_arap

    for _ in range(3):  # move away from the zero field
        forward()
        state["loss"].backward()
        optimizer.step()
    parts = {}
    parts["iteration: simulation forward (16 steps)"] = _median_ms(forward, args.repeats)

    def backward():
        forward()
        start = time.process_time()
        state["loss"].backward()
        state["bwd"] = time.process_time() - start

    backward()
    bwd = []
    for _ in range(args.repeats):
        backward()
        bwd.append(state["bwd"])
    parts["iteration: backward"] = 1000 * statistics.median(bwd)
    parts["iteration: Adam step"] = _median_ms(optimizer.step, args.repeats)

    # the state of the middle step
    with torch.no_grad():
        lam = torch.exp(log_lam) * h
        v = h * df.velocity(x0, coeffs, cfg.convention)
        v_prev, x = v, x0
        for _ in range(cfg.n_steps // 2):
            v_pred = 2.0 * v - v_prev
            v_prev = v
            force, _, frames = ham._force(x, x + h * v_pred, x0, graph, aniso)
            _, v = ham._solve_step(x + 0.5 * h * v_pred, v_pred, force, frames, graph, lam, h, cfg)
            x = x + h * v
        v_pred = 2.0 * v - v_prev
    mid = x + 0.5 * h * v_pred
    xg, pred, an = x.clone().requires_grad_(), (x + h * v_pred).requires_grad_(), aniso.detach().requires_grad_()
    with torch.no_grad():
        parts["step: rotations + force, forward"] = _median_ms(lambda: ham._force(x, x + h * v_pred, x0, graph,
                                                                                  aniso), args.repeats)

    def force_fwd_bwd():
        f, rest_rotated, fr = ham._force(xg, pred, x0, graph, an)
        torch.autograd.backward([f, rest_rotated, fr], [torch.ones_like(f), torch.ones_like(rest_rotated),
                                                       torch.ones_like(fr)])
    parts["step: rotations + force, forward + backward"] = _median_ms(force_fwd_bwd, args.repeats)
    with torch.no_grad():
        force, rest_rotated, frames = ham._force(x, x + h * v_pred, x0, graph, aniso)
        k = cfg.n_modes
        factors = ham._field_factors(mid, k)
        parts["step: factors + direction-major basis"] = _median_ms(
            lambda: ham._direction_major_basis(ham._field_factors(mid, k), k, cfg.convention), args.repeats)
        psi = ham._direction_major_basis(factors, k, cfg.convention)
        parts["step: sparse operator G"] = _median_ms(lambda: ham._dynamics_operator(frames, lam, h, graph),
                                                      args.repeats)
        operator = ham._dynamics_operator(frames, lam, h, graph)
        flat = psi.reshape(3 * n, -1)
        buffer = psi.new_empty(flat.shape)
        parts["step: G Psi"] = _median_ms(lambda: torch.addmm(buffer, operator, flat, beta=0, out=buffer),
                                          args.repeats)
        product = buffer.reshape(n, 3, -1)
        parts["step: system product Psi^T G Psi"] = _median_ms(lambda: ham._system_product(psi, product, k),
                                                               args.repeats)
        system = ham._system_product(psi, product, k).double()
        system.diagonal().add_(cfg.ridge)
        rhs = lam * v_pred + 0.5 * h * force

        def solve():
            factor, _ = torch.linalg.cholesky_ex(system)
            xi = torch.cholesky_solve((flat.T @ rhs.reshape(-1)).double().unsqueeze(-1), factor).squeeze(-1)
            return flat @ xi.float()
        parts["step: Cholesky + solve + v"] = _median_ms(solve, args.repeats)
        parts["step: whole step forward (_StepSolve)"] = _median_ms(
            lambda: ham._solve_step(mid, v_pred, force, frames, graph, lam, h, cfg), args.repeats)
    inputs_g = [t.clone().requires_grad_() for t in (mid, frames, lam.detach(), rhs)]
    grad_xi, grad_v = torch.randn(df.n_fields(k)), torch.randn(n, 3)

    def step_fwd_bwd():
        xi, vel = ham._StepSolve.apply(*inputs_g[:3], inputs_g[3], graph, h, cfg)
        torch.autograd.backward([xi, vel], [grad_xi, grad_v])
    parts["step: whole step forward + backward"] = _median_ms(step_fwd_bwd, args.repeats)

    def energy():
        residual = edge_vectors(xg, graph.edges) - rest_rotated
        (graph.weights * residual.square().sum(-1)).sum().backward()
    parts["step: ARAP energy term, forward + backward"] = _median_ms(energy, args.repeats)

    load = list(os.getloadavg())
    width = max(map(len, parts))
    for name, ms in parts.items():
        print(f"{name:{width}s} {ms:9.3f} ms")
    print(f"load average {load}")
    if args.out:
        bench_common.write_report(args.out, {
            "benchmark": "hamiltonian_profile", "case": args.case,
            "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "command": " ".join([Path(sys.executable).name, *sys.argv]), "repeats": args.repeats,
            "machine": bench_common.machine_info(), "load_average": load, "cpu_ms_median": parts})
    return 0


if __name__ == "__main__":
    sys.exit(main())
