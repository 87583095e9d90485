"""Batched nearest neighbours and batched SPD solves (shapecorr.matching), as Smooth Shells uses them."""

from __future__ import annotations

import pytest
import torch

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.matching.least_squares import solve_normal_equations
from shapecorr.matching.nearest_neighbors import batched_nearest_neighbors


def test_batched_nearest_neighbours_backends_agree():
    # the brute-force branch is what runs on the GPU; both must be exact, with or without a shared side
    g = torch.Generator().manual_seed(0)
    queries, points = torch.randn(3, 50, 7, generator=g), torch.randn(3, 80, 7, generator=g)
    naive = torch.cdist(queries.double(), points.double()).argmin(-1)
    shared_points = torch.cdist(queries.double(), points[:1].double()).argmin(-1)
    shared_queries = torch.cdist(queries[:1].double(), points.double()).argmin(-1)
    threads = torch.get_num_threads()
    try:
        for n_threads in (1, 3):
            torch.set_num_threads(n_threads)  # the k-d tree branch spreads the batch over the threads
            for backend in ("kdtree", "brute"):
                assert torch.equal(batched_nearest_neighbors(queries, points, backend=backend), naive)
                assert torch.equal(batched_nearest_neighbors(queries, points[:1], backend=backend), shared_points)
                assert torch.equal(batched_nearest_neighbors(queries[:1], points, backend=backend), shared_queries)
    finally:
        torch.set_num_threads(threads)


def test_batched_nearest_neighbours_errors():
    x = torch.zeros(2, 4, 3)
    with pytest.raises(ConfigError):
        batched_nearest_neighbors(x, x, backend="ball")
    with pytest.raises(ConfigError):
        batched_nearest_neighbors(x[0], x)
    # non-finite queries or points (k-d tree: a shared tree and one tree per batch element)
    bad = torch.randn(2, 4, 3)
    bad[1, 2, 0] = float("nan")
    for queries, points in ((bad, x), (x, bad), (bad, x[:1]), (x[:1], bad)):
        with pytest.raises(NumericalError, match="NaN or Inf"):
            batched_nearest_neighbors(queries, points, backend="kdtree")


def test_batched_solve_equals_one_system_at_a_time():
    g = torch.Generator().manual_seed(3)
    a = torch.randn(4, 30, 5, generator=g, dtype=torch.float64)
    gram = a.transpose(1, 2) @ a
    gram[2] *= 1e3  # each system has its own relative ridge
    rhs = torch.randn(4, 5, 2, generator=g, dtype=torch.float64)
    batched = solve_normal_equations(gram, rhs, ridge=1e-3)
    assert batched.shape == (4, 5, 2)
    for i in range(4):
        assert torch.equal(batched[i], solve_normal_equations(gram[i], rhs[i], ridge=1e-3))
    # ridge 1e-3 of the mean diagonal, per system
    for i in range(4):
        shift = 1e-3 * torch.diagonal(gram[i]).mean() * torch.eye(5, dtype=torch.float64)
        torch.testing.assert_close(batched[i], torch.linalg.solve(gram[i] + shift, rhs[i]))


def test_batched_solve_zero_gram_and_errors():
    gram = torch.zeros(2, 3, 3, dtype=torch.float64)
    gram[1] = torch.eye(3)
    rhs = torch.ones(2, 3, 1, dtype=torch.float64)
    rhs[0] = 0.0  # no data at all in system 0
    sol = solve_normal_equations(gram, rhs)  # the all-zero system gets the absolute ridge: solution 0
    assert torch.equal(sol[0], torch.zeros(3, 1, dtype=torch.float64))
    torch.testing.assert_close(sol[1], rhs[1] / (1 + 1e-8))
    with pytest.raises(NumericalError, match="not positive definite"):
        solve_normal_equations(gram, rhs, ridge=0.0)
    bad = gram.clone()
    bad[1, 0, 0] = float("nan")
    with pytest.raises(NumericalError, match="NaN"):
        solve_normal_equations(bad, rhs)
