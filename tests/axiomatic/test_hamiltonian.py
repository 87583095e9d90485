"""Tests of the Hamiltonian interpolation (shapecorr.axiomatic.hamiltonian) on small closed meshes."""

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from omegaconf import OmegaConf

from shapecorr.axiomatic.hamiltonian import Hamiltonian, HamiltonianConfig, hamiltonian_interpolation
from shapecorr.errors import ConfigError
from shapecorr.eval.metrics import mesh_volume
from shapecorr.geometry import divergence_free as df
from shapecorr.matching.result import MatchResult

#: The published parameters (read by both model=hamiltonian and interpolator=hamiltonian).
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "interpolator" / "hamiltonian.yaml"
# Few modes and iterations so that each fit takes a few seconds on one CPU thread.
FAST = {"n_modes": 3, "iterations": 20, "lr": 0.05}


def _ellipsoid():
    mesh = trimesh.creation.icosphere(subdivisions=2)  # 162 vertices, closed
    verts = torch.tensor(mesh.vertices, dtype=torch.float32) * torch.tensor([1.0, 0.7, 0.5])
    return verts, torch.tensor(mesh.faces, dtype=torch.int64)


def _bent_target(verts):
    """x moved by a smooth divergence-free flow (a volume-preserving non-rigid deformation)."""
    box, _ = df.box_normalization(verts, verts)
    coeffs = 0.1 * torch.randn(df.n_fields(2), generator=torch.Generator().manual_seed(0))
    return box.from_box(df.integrate_flow(box.to_box(verts), coeffs, 16))


def test_translation_reproduced_and_extrapolated():
    verts, faces = _ellipsoid()
    shift = torch.tensor([0.3, -0.2, 0.5])
    fit = hamiltonian_interpolation(verts, faces, verts + shift, {**FAST, "iterations": 3}, times=[0, 0.5, 1, 1.5, 2])
    expected = verts[None] + fit.times[:, None, None] * shift
    assert torch.allclose(fit.frames, expected, atol=1e-5)


def test_identical_shapes_give_identity_sequence():
    verts, faces = _ellipsoid()
    fit = hamiltonian_interpolation(verts, faces, verts.clone(), {**FAST, "iterations": 3}, times=[0, 0.5, 1, 1.25])
    assert torch.allclose(fit.frames, verts[None].expand_as(fit.frames), atol=1e-6)
    assert fit.energies["align"] < 1e-12


def test_volume_preserved_and_target_approached():
    verts, faces = _ellipsoid()
    target = _bent_target(verts)
    times = [0.0, 0.25, 0.5, 0.75, 1.0]
    fit = hamiltonian_interpolation(verts, faces, target, FAST, times=times)
    vol0 = mesh_volume(verts.numpy(), faces.numpy())
    drift = [abs(mesh_volume(f.numpy(), faces.numpy()) / vol0 - 1) for f in fit.frames]
    assert max(drift) < 0.01
    before = (verts - target).norm(dim=1).mean()
    after = (fit.frames[-1] - target).norm(dim=1).mean()
    assert after < 0.7 * before
    assert fit.history[-1][0] < 0.5 * fit.history[0][0]  # the alignment energy decreased


def test_deterministic(single_thread):
    # Bitwise repeatable with one torch thread; with several, parallel reductions may differ in the last bits
    # from run to run (checked below with the default thread count: equal to float32 round-off).
    verts, faces = _ellipsoid()
    target = _bent_target(verts)
    cfg = {**FAST, "iterations": 4}
    a = hamiltonian_interpolation(verts, faces, target, cfg, times=[0.5, 1.0, 1.5])
    b = hamiltonian_interpolation(verts, faces, target, cfg, times=[0.5, 1.0, 1.5])
    assert torch.equal(a.frames, b.frames) and torch.equal(a.xi, b.xi)
    assert a.xi.shape[0] == 24  # 16 steps to t = 1, 8 more to extrapolate to 1.5


def test_partial_target_only_aligns_mapped_vertices():
    verts, faces = _ellipsoid()
    target = _bent_target(verts)
    mask = verts[:, 0] > 0
    wrong = target.clone()
    wrong[~mask] = 10.0  # unknown targets: must not influence the fit
    full = target.clone()
    full[~mask] = target[mask].mean(0)
    cfg = {**FAST, "iterations": 3}
    a = hamiltonian_interpolation(verts, faces, wrong, cfg, times=[1.0], mask=mask)
    b = hamiltonian_interpolation(verts, faces, full, cfg, times=[1.0], mask=mask)
    assert torch.allclose(a.frames, b.frames, atol=1e-5)
    with pytest.raises(ConfigError):
        hamiltonian_interpolation(verts, faces, target, cfg, times=[1.0], mask=torch.zeros_like(mask))


def test_bad_input_raises():
    verts, faces = _ellipsoid()
    with pytest.raises(ConfigError):
        hamiltonian_interpolation(verts, faces, verts[:10], FAST)
    with pytest.raises(ConfigError):
        hamiltonian_interpolation(verts, faces, verts, FAST, times=[-0.5, 1.0])
    with pytest.raises(ConfigError):
        HamiltonianConfig(lr=-1.0)


class _GroundTruth:
    """A matcher returning the identity map (x and y share the connectivity)."""

    def match(self, x, y):
        return MatchResult(p2p=torch.arange(x.verts.shape[0]))


class _Sample:
    def __init__(self, verts, faces):
        self.verts, self.faces = verts, faces


def test_matcher_and_config(compose_config):
    cfg = OmegaConf.load(CONFIG)
    # model=hamiltonian composes the same parameters around its wrapped matcher
    model_cfg = compose_config("evaluate", ["model=hamiltonian"]).model
    assert model_cfg.matcher._target_.endswith("IdentityGT")
    assert {k: model_cfg[k] for k in cfg if k != "_target_"} == {k: cfg[k] for k in cfg if k != "_target_"}
    published = {key: cfg[key] for key in ("lr", "iterations", "n_steps", "lambda_reg", "samples", "knn", "n_modes")}
    assert published == {"lr": 0.02, "iterations": 100, "n_steps": 16, "lambda_reg": 20.0, "samples": 2000, "knn": 5,
                         "n_modes": 8}
    assert HamiltonianConfig() == HamiltonianConfig(**{k: v for k, v in OmegaConf.to_container(cfg).items()
                                                      if k not in ("_target_", "defaults", "interp_times")})
    verts, faces = _ellipsoid()
    target = verts + torch.tensor([0.1, 0.0, 0.0])
    model = Hamiltonian(_GroundTruth(), interp_times=[0.0, 1.0], **{**FAST, "iterations": 2})
    result = model.match(_Sample(verts, faces), _Sample(target, faces))
    assert result.deformation.shape == (2, len(verts), 3)
    assert np.allclose(result.deformation[-1].numpy(), target.numpy(), atol=1e-5)
    with pytest.raises(ConfigError):
        Hamiltonian(_GroundTruth(), not_an_option=1)


def test_replay_reproduces_the_simulated_samples():
    from shapecorr.axiomatic.divfree import knn_graph_edges
    from shapecorr.axiomatic.hamiltonian import _Graph, _replay, _simulate, edge_vectors

    gen = torch.Generator().manual_seed(1)
    x0 = 0.3 + 0.4 * torch.rand(80, 3, generator=gen)
    cfg = HamiltonianConfig(n_modes=3, knn=5)
    edges, counts = knn_graph_edges(x0, cfg.knn)
    graph = _Graph(edges, counts, edge_vectors(x0, edges))
    coeffs = 0.5 * torch.randn(df.n_fields(3), generator=gen)
    aniso = torch.eye(3) + 0.05 * torch.randn(80, 3, 3, generator=gen)
    x_end, energy, xis = _simulate(x0, coeffs, aniso, torch.tensor(np.log(0.3)), graph, 20, cfg)
    path = _replay(x0, coeffs, xis, HamiltonianConfig(n_modes=3, chunk_size=30))
    assert path.shape == (21, 80, 3)
    assert float((x_end - x0).norm(dim=1).mean()) > 1e-3  # it moved
    assert torch.allclose(path[16], x_end, atol=1e-5)
    assert float(energy) > 0


def test_repeatable_to_round_off_with_several_threads():
    verts, faces = _ellipsoid()
    target = _bent_target(verts)
    cfg = {**FAST, "iterations": 4}
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        a = hamiltonian_interpolation(verts, faces, target, cfg, times=[0.5, 1.0])
        b = hamiltonian_interpolation(verts, faces, target, cfg, times=[0.5, 1.0])
    finally:
        torch.set_num_threads(previous)
    torch.testing.assert_close(a.frames, b.frames, rtol=0, atol=1e-5)


def _random_graph(n: int, gen: torch.Generator):
    """``n`` random float64 points in a box and their 3-nearest-neighbour graph (the step's ``_Graph``)."""
    from shapecorr.axiomatic.divfree import knn_graph_edges
    from shapecorr.axiomatic.hamiltonian import _Graph, edge_vectors

    x0 = (0.3 + 0.4 * torch.rand(n, 3, generator=gen)).double()
    edges, counts = knn_graph_edges(x0, 3)
    return x0, _Graph(edges, counts.double(), edge_vectors(x0, edges))


def test_step_solve_gradients_match_finite_differences():
    """The hand-written backward of the per-step solve (rank-two cotangents) against float64 finite differences."""
    from shapecorr.axiomatic.hamiltonian import _StepSolve

    gen = torch.Generator().manual_seed(3)
    n = 12
    x0, graph = _random_graph(n, gen)
    cfg = HamiltonianConfig(n_modes=2)
    mid = (x0 + 0.01 * torch.randn(n, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    frames = (torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    frames.requires_grad_()
    lam = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)
    rhs = torch.randn(n, 3, generator=gen, dtype=torch.float64, requires_grad=True)

    def fn(m, f, la, r):
        return _StepSolve.apply(m, f, la, r, graph, 1.0 / 16, cfg)

    assert torch.autograd.gradcheck(fn, (mid, frames, lam, rhs), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_step_basis_and_field_derivatives_match_the_divergence_free_module():
    """The step's direction-major basis is basis_fields' (bitwise), and its transposed products and potential
    derivatives give Psi^T w, the field and its Jacobian of shapecorr.geometry.divergence_free."""
    from shapecorr.axiomatic import hamiltonian as ham

    gen = torch.Generator().manual_seed(4)
    k, n = 3, 40
    points = 0.1 + 0.8 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    factors = ham._field_factors(points, k)
    for convention in df.CONVENTIONS:
        basis = df.basis_fields(points, k, convention)  # (n, F, 3), fields abc * 3 + e
        psi = ham._direction_major_basis(factors, k, convention)  # (n, 3, F), fields e * K^3 + abc
        assert torch.equal(ham._to_field_order(psi, k), basis.transpose(1, 2))
        scales = ham._direction_major_scales(k, convention, points.dtype, points.device)[0]
        w = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        expected = torch.einsum("nfi,ni->f", basis, w)
        torch.testing.assert_close(ham._to_field_order(ham._basis_transpose(factors, w, scales), k), expected,
                                   rtol=1e-12, atol=1e-12)
        coeffs = torch.randn(2, df.n_fields(k), generator=gen, dtype=torch.float64)
        pot = (ham._to_direction_major(coeffs, k) * scales).reshape(2, 3, k, k, k)
        deriv = ham._potential_derivatives(factors, pot)
        at_grad, at_hess = ham._derivative_index(2, points.device)
        eps_dj = ham._EPS.to(points).permute(0, 2, 1).reshape(3, 9)
        torch.testing.assert_close(deriv.index_select(1, at_grad) @ eps_dj.T,
                                   df.velocity(points, coeffs[0], convention), rtol=1e-12, atol=1e-12)
        # J^T w for both fields from the second derivatives: sum_i w_i d_l v_i = pi sum_jd (w x)_jd d_l d_j Phi_d
        skew = (torch.stack((w, 2 * w), dim=1) @ eps_dj).reshape(n, 1, 18)
        jtw = torch.pi * (skew @ deriv.index_select(1, at_hess).reshape(n, 18, 3)).reshape(n, 3)
        jac = [df.velocity_jacobian(points, c, convention) for c in coeffs]
        expected = (jac[0].transpose(1, 2) @ w[..., None] + jac[1].transpose(1, 2) @ (2 * w)[..., None]).squeeze(-1)
        torch.testing.assert_close(jtw, expected, rtol=1e-10, atol=1e-10)


def test_force_gradients_match_finite_differences():
    """The hand-written backward of the force from the rotations against float64 finite differences."""
    from shapecorr.axiomatic.hamiltonian import _ForceFromRotations

    gen = torch.Generator().manual_seed(5)
    n = 10
    x0, graph = _random_graph(n, gen)
    x = (x0 + 0.05 * torch.randn(n, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    rot = (torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    aniso = (torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))

    def fn(p, r, an):
        return _ForceFromRotations.apply(p, r, an, graph)

    assert torch.autograd.gradcheck(fn, (x, rot.requires_grad_(), aniso.requires_grad_()), eps=1e-6, atol=1e-7,
                                    rtol=1e-5)
