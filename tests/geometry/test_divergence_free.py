"""Tests of shapecorr.geometry.divergence_free: the basis, its derivatives, the box normalization and the flows."""

import numpy as np
import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError
from shapecorr.eval.metrics import mesh_volume
from shapecorr.geometry import divergence_free as df

K = 3  # 81 fields: every property below holds mode by mode, small K keeps the finite differences fast


@pytest.fixture
def points():
    torch.manual_seed(0)
    return 0.05 + 0.9 * torch.rand(40, 3, dtype=torch.float64)


def test_published_size_and_order():
    assert df.n_fields(df.PUBLISHED_N_MODES) == 1536
    x = torch.rand(5, 3, dtype=torch.float64)
    fields = df.basis_fields(x, 2)
    # field f = ((a-1) K^2 + (b-1) K + (c-1)) * 3 + d; mode (a, b, c) = (1, 2, 1), d = 0 at f = 2 * 3 + 0
    a, b, c = 1, 2, 1
    p = np.pi
    grad = torch.stack([
        a * torch.cos(a * p * x[:, 0]) * torch.sin(b * p * x[:, 1]) * torch.sin(c * p * x[:, 2]),
        b * torch.sin(a * p * x[:, 0]) * torch.cos(b * p * x[:, 1]) * torch.sin(c * p * x[:, 2]),
        c * torch.sin(a * p * x[:, 0]) * torch.sin(b * p * x[:, 1]) * torch.cos(c * p * x[:, 2]),
    ], dim=1)
    expected = torch.cross(grad, torch.tensor([[1.0, 0, 0]], dtype=x.dtype).expand(5, 3), dim=1) / np.sqrt(b**2 + c**2)
    torch.testing.assert_close(fields[:, 6], expected)


def test_basis_is_the_scaled_cross_product_exactly(points):
    """Every field equals s_f * (grad psi_abc x e_d), built here with torch.cross, to the last bit."""
    k = torch.arange(1, K + 1, dtype=points.dtype)
    sin, cos = torch.sin(points[:, :, None] * (np.pi * k)), torch.cos(points[:, :, None] * (np.pi * k)) * k
    def outer(fa, fb, fc):
        return fa[:, :, None, None] * fb[:, None, :, None] * fc[:, None, None, :]
    grad = torch.stack((outer(cos[:, 0], sin[:, 1], sin[:, 2]), outer(sin[:, 0], cos[:, 1], sin[:, 2]),
                        outer(sin[:, 0], sin[:, 1], cos[:, 2])), dim=-1).reshape(points.shape[0], K**3, 1, 3)
    eye = torch.eye(3, dtype=points.dtype).expand(points.shape[0], K**3, 3, 3)
    crossed = torch.cross(grad.expand(-1, -1, 3, -1), eye, dim=-1).reshape(points.shape[0], 3 * K**3, 3)
    for convention in df.CONVENTIONS:
        expected = crossed * df.basis_scales(K, convention, dtype=points.dtype)[None, :, None]
        assert torch.equal(df.basis_fields(points, K, convention), expected)
    # differentiable in the points
    pts = points[:6].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: df.basis_fields(p, 2), (pts,))


def test_every_basis_field_is_divergence_free(points):
    eps = 1e-5
    div = torch.zeros(points.shape[0], df.n_fields(K), dtype=points.dtype)
    for axis in range(3):
        step = torch.zeros(3, dtype=points.dtype)
        step[axis] = eps
        plus, minus = df.basis_fields(points + step, K), df.basis_fields(points - step, K)
        div += (plus[..., axis] - minus[..., axis]) / (2 * eps)
    magnitude = df.basis_fields(points, K).norm(dim=-1).mean()
    assert div.abs().max() < 1e-6 * max(1.0, float(magnitude))
    # ... while the fields are far from zero and their Jacobians are not (the test could fail)
    assert magnitude > 0.1


def test_fields_tangent_to_box_faces():
    torch.manual_seed(1)
    fields_normal = []
    for axis in range(3):
        for value in (0.0, 1.0):
            pts = torch.rand(30, 3, dtype=torch.float64)
            pts[:, axis] = value
            fields = df.basis_fields(pts, K)
            fields_normal.append(fields[..., axis].abs().max())
            assert fields[..., [i for i in range(3) if i != axis]].abs().max() > 0.1  # tangential part is not 0
    assert max(fields_normal) < 1e-12


def test_velocity_matches_basis_and_original_convention(points):
    coeffs = torch.randn(df.n_fields(K), dtype=points.dtype)
    for convention in df.CONVENTIONS:
        expected = torch.einsum("nfi,f->ni", df.basis_fields(points, K, convention), coeffs)
        torch.testing.assert_close(df.velocity(points, coeffs, convention, chunk_size=7), expected)
    # the original code's convention differs in sign and in the scale of each direction, not in the span
    pub, orig = df.basis_scales(K), df.basis_scales(K, "original_code")
    assert (orig < 0).all() and not torch.allclose(pub, -orig)


def test_jacobian_matches_finite_differences(points):
    torch.manual_seed(2)
    coeffs = torch.randn(df.n_fields(K), dtype=points.dtype)
    jac = df.velocity_jacobian(points, coeffs, chunk_size=16)
    eps = 1e-6
    for axis in range(3):
        step = torch.zeros(3, dtype=points.dtype)
        step[axis] = eps
        fd = (df.velocity(points + step, coeffs) - df.velocity(points - step, coeffs)) / (2 * eps)
        torch.testing.assert_close(jac[:, :, axis], fd, atol=1e-6, rtol=1e-6)
    assert jac.diagonal(dim1=1, dim2=2).sum(-1).abs().max() < 1e-10  # trace-free
    assert jac.abs().max() > 0.1


def test_box_normalization_round_trip():
    torch.manual_seed(3)
    x = torch.randn(50, 3, dtype=torch.float64) * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64) + 3
    y = torch.randn(60, 3, dtype=torch.float64) - 1
    tx, ty = df.box_normalization(x, y)
    bx, by = tx.to_box(x), ty.to_box(y)
    lo, hi = min(bx.min(), by.min()), max(bx.max(), by.max())
    assert lo >= df.BOX_MARGIN - 1e-12 and hi <= 1 - df.BOX_MARGIN + 1e-12
    assert abs(max(float((bx.amax(0) - bx.amin(0)).max()), float((by.amax(0) - by.amin(0)).max())) - 0.9) < 1e-12
    torch.testing.assert_close(0.5 * (bx.amax(0) + bx.amin(0)), torch.full((3,), 0.5, dtype=x.dtype))
    torch.testing.assert_close(tx.from_box(bx), x)
    assert tx.scale == ty.scale


def _sphere():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    return torch.tensor(mesh.vertices + 0.5, dtype=torch.float64), np.asarray(mesh.faces)


@pytest.mark.parametrize("n_steps", [10, 16])
def test_random_flow_preserves_volume(n_steps):
    verts, faces = _sphere()
    torch.manual_seed(4)
    coeffs = torch.randn(df.n_fields(4), dtype=verts.dtype)
    coeffs *= 0.1 / df.velocity(verts, coeffs).norm(dim=1).mean()  # mean speed 0.1 = half the radius
    moved = df.integrate_flow(verts, coeffs, n_steps)
    displacement = (moved - verts).norm(dim=1)
    assert displacement.mean() > 0.05  # a real deformation, not a rigid motion or nothing
    v0, v1 = mesh_volume(verts.numpy(), faces), mesh_volume(moved.numpy(), faces)
    assert abs(v1 / v0 - 1) < 0.01
    # a generic (not divergence-free) field of the same size does change the volume
    radial = verts + 0.5 * displacement.mean() * (verts - 0.5)
    assert abs(mesh_volume(radial.numpy(), faces) / v0 - 1) > 0.05


def test_flow_rules_and_frames(points):
    torch.manual_seed(5)
    coeffs = 0.3 * torch.randn(df.n_fields(K), dtype=points.dtype)
    path = df.integrate_flow(points, coeffs, 8, return_path=True)
    assert path.shape == (9, *points.shape)
    torch.testing.assert_close(path[0], points)
    torch.testing.assert_close(path[-1], df.integrate_flow(points, coeffs, 8))
    frames = df.flow_frames(points, coeffs, [0.0, 0.5, 1.0, -0.25, 1.5], n_steps=8)
    torch.testing.assert_close(frames[1], path[4])
    torch.testing.assert_close(frames[2], path[8])
    # the backwards flow inverts the forward one up to the midpoint rule's O(h^2) error
    disp = (frames[2] - points).norm(dim=1).mean()
    errors = []
    for n in (16, 64):
        fwd = df.integrate_flow(points, coeffs, n)
        errors.append((df.flow_frames(fwd, coeffs, [-1.0], n_steps=n)[0] - points).norm(dim=1).mean())
    assert errors[1] < 0.02 * disp and errors[1] < errors[0] / 8  # second order: 16x smaller for 4x the steps
    # original rule: its steps advance the time by 1.5 h^2 (endpoint ~ the flow over 1.5 / n_steps)
    orig = df.integrate_flow(points, coeffs, 16, rule="original")
    short = df.integrate_flow(points, coeffs, 64, t_end=1.5 / 16)
    assert (orig - short).norm(dim=1).max() < 0.02 * (short - points).norm(dim=1).max()
    orig_frames = df.flow_frames(points, coeffs, [0.5, 1.0], n_steps=16, rule="original")
    torch.testing.assert_close(orig_frames[1], orig)
    with pytest.raises(ConfigError):
        df.flow_frames(points, coeffs, [0.3], n_steps=16, rule="original")


def test_gradients_reach_coefficients(points):
    coeffs = torch.zeros(df.n_fields(K), dtype=points.dtype, requires_grad=True)
    target = points + 0.01
    loss = (df.integrate_flow(points, coeffs, 4) - target).square().sum()
    loss.backward()
    assert coeffs.grad is not None and coeffs.grad.abs().max() > 0


def test_resize_coefficients(points):
    coeffs = torch.randn(df.n_fields(2), dtype=points.dtype)
    big = df.resize_coefficients(coeffs, 4)
    torch.testing.assert_close(df.velocity(points, big), df.velocity(points, coeffs))
    torch.testing.assert_close(df.resize_coefficients(big, 2), coeffs)


def test_bad_input():
    with pytest.raises(ConfigError):
        df.velocity(torch.rand(4, 2), torch.zeros(81))
    with pytest.raises(ConfigError):
        df.velocity(torch.rand(4, 3), torch.zeros(80))
    with pytest.raises(ConfigError):
        df.integrate_flow(torch.rand(4, 3), torch.zeros(81), rule="euler")
