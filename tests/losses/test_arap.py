"""ARAP: rotations (rigid recovery, proper rotations, optimality), energy zero for rigid motions and positive
otherwise, both directions, NeuroMorph weighting, gradcheck with detached and differentiated rotations, the
envelope property, degenerate neighbourhoods (finite values and gradients), errors."""

import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.mesh_graph import undirected_edges
from shapecorr.losses.arap import (
    arap_covariances,
    arap_energy,
    arap_rotations,
    arap_sequence_loss,
    polar_rotations,
    rotations_from_covariances,
)

DTYPE = torch.float64


def _mesh(subdivisions=None):
    m = trimesh.creation.icosahedron() if subdivisions is None else trimesh.creation.icosphere(subdivisions)
    faces = torch.from_numpy(m.faces)
    return torch.from_numpy(m.vertices).to(DTYPE), faces, undirected_edges(faces)


def _rotation(seed):
    gen = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=DTYPE))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.linalg.det(q) > 0 else -q


def _nonrigid(verts, seed, amount=0.2):
    gen = torch.Generator().manual_seed(seed)
    bend = verts.clone()
    bend[:, 0] = bend[:, 0] * (1.0 + amount * bend[:, 2])  # a smooth, non-rigid deformation
    return bend + 0.02 * torch.randn(verts.shape, generator=gen, dtype=DTYPE)


def test_rotations_recover_a_rigid_motion():
    verts, _, edges = _mesh(1)
    rot = _rotation(0)
    moved = verts @ rot.T + torch.tensor([0.3, -1.0, 2.0], dtype=DTYPE)
    r = arap_rotations(verts, moved, edges)
    torch.testing.assert_close(r, rot.expand_as(r), rtol=0, atol=1e-10)


def test_rotations_are_proper_and_optimal_even_for_a_reflection():
    verts, _, edges = _mesh(1)
    mirrored = verts * torch.tensor([-1.0, 1.0, 1.0], dtype=DTYPE)  # det(best orthogonal fit) = -1
    cov = arap_covariances(verts, _nonrigid(mirrored, 1), edges)
    r = rotations_from_covariances(cov)
    torch.testing.assert_close(r @ r.mT, torch.eye(3, dtype=DTYPE).expand_as(r), rtol=0, atol=1e-10)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(r.shape[0], dtype=DTYPE), rtol=0, atol=1e-10)
    # Optimality over SO(3): tr(R^T S) >= tr(Q^T S) for random rotations Q.
    score = (r * cov).sum((-2, -1))
    for seed in range(20):
        q = _rotation(100 + seed)
        assert bool((score >= (q * cov).sum((-2, -1)) - 1e-12).all())


@pytest.mark.parametrize("mode", ["both-sides", "average"])
def test_energy_zero_for_rigid_positive_for_nonrigid(mode):
    verts, _, edges = _mesh(1)
    moved = verts @ _rotation(2).T + torch.tensor([1.0, 2.0, 3.0], dtype=DTYPE)
    assert float(arap_energy(verts, moved, edges, mode=mode)) == pytest.approx(0.0, abs=1e-20)
    assert float(arap_energy(moved, verts, edges, mode=mode)) == pytest.approx(0.0, abs=1e-20)
    assert float(arap_energy(verts, _nonrigid(verts, 3), edges, mode=mode)) > 1e-4


def test_energy_matches_an_explicit_loop():
    verts, _, edges = _mesh()
    deformed = _nonrigid(verts, 4)
    r = arap_rotations(verts, deformed, edges)
    both, avg = 0.0, 0.0
    for a, b in edges.tolist():
        e0, et = verts[b] - verts[a], deformed[b] - deformed[a]
        both += float((et - r[a] @ e0).square().sum() + (et - r[b] @ e0).square().sum())
        avg += float((et - 0.5 * (r[a] + r[b]) @ e0).square().sum())
    assert float(arap_energy(verts, deformed, edges)) == pytest.approx(both, rel=1e-12)
    assert float(arap_energy(verts, deformed, edges, mode="average")) == pytest.approx(avg, rel=1e-12)


def _original_arap(verts_new, verts_old, faces):
    """The original's ARAP term as described by its code: per face (f0,f1), (f0,f2), (f1,f2) listed once,
    d = V_a - V_b, S_v = sum of d d0^T over the rows containing v, R_v its rotation, R_e = (R_a + R_b) / 2."""
    rows = torch.cat((faces[:, [0, 1]], faces[:, [0, 2]], faces[:, [1, 2]]))
    d = verts_new[rows[:, 0]] - verts_new[rows[:, 1]]
    d0 = verts_old[rows[:, 0]] - verts_old[rows[:, 1]]
    cov = torch.zeros(verts_new.shape[0], 3, 3, dtype=DTYPE)
    outer = d[:, :, None] * d0[:, None, :]
    cov.index_add_(0, rows[:, 0], outer).index_add_(0, rows[:, 1], outer)
    u, _, vh = torch.linalg.svd(cov)
    fix = torch.ones(verts_new.shape[0], 3, dtype=DTYPE)
    fix[:, 2] = torch.sign(torch.linalg.det(u @ vh))
    rot = u @ (fix[:, :, None] * vh)
    r_e = 0.5 * (rot[rows[:, 0]] + rot[rows[:, 1]])
    return float((d - (r_e @ d0[:, :, None]).squeeze(-1)).square().sum())


def test_neuromorph_face_listed_edges_equal_face_count_weights():
    verts, faces, _ = _mesh()
    edges_w, counts = undirected_edges(faces, return_counts=True)
    deformed = _nonrigid(verts, 5)
    expected = _original_arap(deformed, verts, faces)
    ours = arap_energy(verts, deformed, edges_w, edge_weights=counts.to(DTYPE), mode="average")
    assert float(ours) == pytest.approx(expected, rel=1e-12)
    # counting both directions of every edge (2 x counts) doubles it
    doubled = arap_energy(verts, deformed, edges_w, edge_weights=2.0 * counts.to(DTYPE), mode="average")
    assert float(doubled) == pytest.approx(2.0 * expected, rel=1e-12)
    # both-sides at 0.5 x counts: the original's number of residuals, hence the same order (not a factor 2)
    both = float(arap_energy(verts, deformed, edges_w, edge_weights=0.5 * counts.to(DTYPE)))
    assert 0.8 * expected < both < 1.25 * expected


@pytest.mark.parametrize("mode", ["both-sides", "average"])
def test_sequence_loss_is_symmetric_and_sums_both_directions(mode):
    verts, _, edges = _mesh()
    frames = torch.stack([verts, _nonrigid(verts, 6, 0.1), _nonrigid(verts, 7, 0.3), _nonrigid(verts, 8, 0.5)])
    loss = arap_sequence_loss(frames, edges, mode=mode, displacement_weight=1e-3)
    assert float(loss) == pytest.approx(float(arap_sequence_loss(frames.flip(0), edges, mode=mode,
                                                                 displacement_weight=1e-3)), rel=1e-12)
    manual = sum(
        float(arap_energy(frames[k], frames[k + 1], edges, mode=mode))
        + float(arap_energy(frames[k + 1], frames[k], edges, mode=mode))
        + 2e-3 * float((frames[k + 1] - frames[k]).square().sum())
        for k in range(3)
    )
    assert float(loss) == pytest.approx(manual, rel=1e-12)
    # With optimal per-vertex rotations the classic energy is symmetric in its two poses
    # (min_R ||e_t - R e_0|| = min_R ||e_0 - R^T e_t||); the "average" variant is not.
    forward = float(arap_energy(frames[0], frames[3], edges, mode=mode))
    backward = float(arap_energy(frames[3], frames[0], edges, mode=mode))
    if mode == "both-sides":
        assert forward == pytest.approx(backward, rel=1e-12)
    else:
        assert abs(forward - backward) > 1e-6 * max(forward, backward)


@pytest.mark.parametrize(
    "mode, detach", [("both-sides", True), ("both-sides", False), ("average", False)]
)
def test_gradcheck(mode, detach):
    verts, _, edges = _mesh()
    v0 = verts.clone().requires_grad_()
    vt = _nonrigid(verts, 9).requires_grad_()
    def fn(a, b):
        return arap_energy(a, b, edges, mode=mode, detach_rotations=detach)

    assert torch.autograd.gradcheck(fn, (v0, vt), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=True)


def test_envelope_detached_equals_differentiated_for_both_sides_only():
    verts, _, edges = _mesh(1)
    vt = _nonrigid(verts, 10)
    grads = {}
    for mode in ("both-sides", "average"):
        for detach in (True, False):
            v = vt.clone().requires_grad_()
            (grads[mode, detach],) = torch.autograd.grad(arap_energy(verts, v, edges, mode=mode,
                                                                     detach_rotations=detach), v)
    torch.testing.assert_close(grads["both-sides", True], grads["both-sides", False], rtol=1e-8, atol=1e-10)
    gap = (grads["average", True] - grads["average", False]).norm() / grads["average", False].norm()
    assert gap > 1e-3  # the "average" energy is not minimized by the per-vertex rotations


def test_polar_backward_matches_svd_autograd_for_regular_matrices():
    gen = torch.Generator().manual_seed(11)
    cov = torch.randn(50, 3, 3, generator=gen, dtype=DTYPE)
    weight = torch.randn(50, 3, 3, generator=gen, dtype=DTYPE)
    s1 = cov.clone().requires_grad_()
    (g_ours,) = torch.autograd.grad((rotations_from_covariances(s1, differentiable=True) * weight).sum(), s1)
    s2 = cov.clone().requires_grad_()
    u, _, vh = torch.linalg.svd(s2)
    d = torch.sign(torch.linalg.det(u @ vh)).detach()
    fix = torch.ones(50, 3, dtype=DTYPE)
    fix[:, 2] = d
    r = u @ torch.diag_embed(fix) @ vh
    (g_ref,) = torch.autograd.grad((r * weight).sum(), s2)
    torch.testing.assert_close(g_ours, g_ref, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("mode", ["both-sides", "average"])
@pytest.mark.parametrize("detach", [True, False])
@pytest.mark.parametrize("case", ["identical", "collinear", "collinear_one_ring"])
def test_degenerate_neighbourhoods_give_finite_values_and_gradients(mode, detach, case):
    verts, _, edges = _mesh(1)
    deformed = verts.clone()
    if case == "identical":
        deformed = torch.zeros_like(verts)  # every covariance is zero
    elif case == "collinear":
        deformed[:, 1:] = 0.0  # every one-ring collinear: rank-1 covariances
    else:
        ring = torch.cat((edges[edges[:, 0] == 0, 1], edges[edges[:, 1] == 0, 0]))
        deformed[ring] = deformed[0] + torch.linspace(-0.1, 0.1, len(ring), dtype=DTYPE)[:, None] * torch.tensor(
            [1.0, 0.0, 0.0], dtype=DTYPE
        )
        deformed[0] = deformed[ring].mean(0)  # vertex 0 and its whole one-ring on one line
    for dtype in (torch.float64, torch.float32):
        v0 = verts.to(dtype).requires_grad_()
        vt = deformed.to(dtype).requires_grad_()
        energy = arap_energy(v0, vt, edges, mode=mode, detach_rotations=detach)
        g0, gt = torch.autograd.grad(energy, (v0, vt))
        assert bool(torch.isfinite(energy)) and float(energy.detach()) > 0
        assert bool(torch.isfinite(g0).all()) and bool(torch.isfinite(gt).all())


def test_batched_equals_looped():
    verts, _, edges = _mesh(1)
    rest = torch.stack([verts, _nonrigid(verts, 12)])
    deformed = torch.stack([_nonrigid(verts, 13), verts])
    batched = arap_energy(rest, deformed, edges, mode="average")
    assert batched.shape == (2,)
    for k in range(2):
        assert float(batched[k]) == pytest.approx(float(arap_energy(rest[k], deformed[k], edges, mode="average")))


def test_errors():
    verts, _, edges = _mesh()
    with pytest.raises(ConfigError, match="mode"):
        arap_energy(verts, verts, edges, mode="source")
    with pytest.raises(ConfigError, match="equal shapes"):
        arap_energy(verts, verts[:5], edges)
    with pytest.raises(ConfigError, match="edge_weights"):
        arap_energy(verts, verts, edges, edge_weights=torch.ones(3, dtype=DTYPE))
    with pytest.raises(ConfigError, match="non-negative"):
        arap_energy(verts, verts, edges, edge_weights=-torch.ones(edges.shape[0], dtype=DTYPE))
    with pytest.raises(ConfigError, match="outside"):
        arap_energy(verts, verts, edges + 100)
    bad = verts.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(NumericalError, match="verts_t"):
        arap_energy(verts, bad, edges)
    with pytest.raises(NumericalError):
        rotations_from_covariances(torch.full((2, 3, 3), float("inf")))
    with pytest.raises(ConfigError, match="S >= 2"):
        arap_sequence_loss(verts[None], edges)


def test_polar_rotations_equal_the_svd_rotations():
    """The Newton polar iteration gives the SVD's float32 rotations, reflections and degenerate matrices included."""
    gen = torch.Generator().manual_seed(3)
    e0 = torch.randn(4000, 5, 3, generator=gen, dtype=DTYPE) * torch.tensor([1.0, 1.0, 0.05], dtype=DTYPE)
    turn = torch.linalg.matrix_exp(0.2 * torch.randn(4000, 3, 3, generator=gen, dtype=DTYPE))
    et = e0 @ turn.mT + 0.05 * torch.randn(4000, 5, 3, generator=gen, dtype=DTYPE)
    cov = (et.unsqueeze(-1) * e0.unsqueeze(-2)).sum(1).to(torch.float32).reshape(2, 2000, 3, 3)
    cov[0, 0] = 0.0  # zero
    cov[0, 1] = torch.diag(torch.tensor([1.0, 1.0, 0.0]))  # singular
    cov[0, 2] = torch.diag(torch.tensor([1.0, 1.0, -1.0]))  # reflection
    reflections = int((torch.linalg.det(cov.double()) < 0).sum())
    assert reflections > 1
    fast, reference = polar_rotations(cov), rotations_from_covariances(cov)
    assert fast.shape == cov.shape and fast.dtype == torch.float32
    assert torch.equal(fast, reference)
    assert torch.allclose(torch.linalg.det(fast.double()), torch.ones(2, 2000, dtype=DTYPE), atol=1e-6)
    with pytest.raises(NumericalError):
        polar_rotations(torch.full((2, 3, 3), float("nan")))
