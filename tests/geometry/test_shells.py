"""Tests of the existing shapecorr.geometry.shells (smooth shells) and shapecorr.geometry.normals."""

from __future__ import annotations

import igl
import numpy as np
import pytest
import scipy.linalg
import torch
import trimesh

from shapecorr.errors import ConfigError
from shapecorr.geometry.laplace_beltrami import eigenbasis, laplacian
from shapecorr.geometry.normals import face_normals, vertex_normals
from shapecorr.geometry.shells import (
    SHELL_SMOOTH_WIDTH,
    SHELL_TRUNCATION_EPS,
    sigmoid_shell_weights,
    smooth_shell,
    spectral_coefficients,
)


@pytest.fixture(scope="module")
def full_basis(bumpy_sphere):
    """All n generalized eigenpairs (dense LAPACK), float64 torch."""
    v, f = bumpy_sphere(2)  # 162 vertices
    L, mass = laplacian(v, f)
    evals, evecs = scipy.linalg.eigh(L.toarray(), np.diag(mass))
    evals[0] = 0.0
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    return t(v), t(evals), t(evecs), t(mass), L


def m_norm2(mass, x):
    return float((mass[:, None] * x * x).sum())


def test_hard_shell_with_all_eigenvectors_reproduces_the_shape(full_basis):
    verts, _, evecs, mass, _ = full_basis
    n = verts.shape[0]
    shell = smooth_shell(evecs, mass, verts, k=n, mode="hard")
    torch.testing.assert_close(shell, verts, atol=1e-10, rtol=0)


def test_hard_shell_error_decreases_and_obeys_the_spectral_bound(full_basis):
    """||X - X_k||_M^2 = sum_{i>k} ||xi_i||^2 <= tr(X^T L X) / lambda_{k+1} (Smooth Shells, Theorem 1)."""
    verts, evals, evecs, mass, L = full_basis
    xi = spectral_coefficients(evecs, mass, verts)
    dirichlet = float(np.trace(verts.numpy().T @ (L @ verts.numpy())))
    errors = []
    for k in [1, 2, 4, 10, 20, 50, 100, 150]:
        err = m_norm2(mass, verts - smooth_shell(evecs, mass, verts, k=k, mode="hard"))
        np.testing.assert_allclose(err, float((xi[k:] ** 2).sum()), rtol=1e-8, atol=1e-12)
        assert err <= dirichlet / float(evals[k]) * (1 + 1e-9)
        errors.append(err)
    assert all(a >= b for a, b in zip(errors, errors[1:]))


def test_dirichlet_energy_of_coordinates_is_twice_the_area():
    """For a closed surface tr(X^T L X) = int |grad x|^2 = 2 area (the tangential gradients of x, y, z)."""
    s = trimesh.creation.icosphere(4)
    L, mass = laplacian(s.vertices, s.faces)
    v = np.asarray(s.vertices)
    np.testing.assert_allclose(np.trace(v.T @ (L @ v)), 2 * s.area, rtol=1e-2)


@pytest.mark.parametrize("k", [2, 5, 9, 10, 20, 100])
@pytest.mark.parametrize("inclusive", [True, False])
def test_sigmoid_weights(k, inclusive):
    w = sigmoid_shell_weights(k, inclusive=inclusive, dtype=torch.float64)
    if k >= SHELL_SMOOTH_WIDTH:
        expected = k + SHELL_SMOOTH_WIDTH - (1 if inclusive else 2)
    else:
        expected = 2 * k - (1 if inclusive else 2)
    assert w.shape == (expected,)
    torch.testing.assert_close(w[k - 1], torch.tensor(0.5, dtype=torch.float64))
    assert (torch.diff(w) <= 0).all() and (w > 0).all() and (w <= 1).all()
    # The transition is symmetric about k-1 with half-width `upper`: weight 1 - eps at k-1-upper (strictly
    # decreasing from there) and eps at k-1+upper, the last weight of the MATLAB range.
    upper = SHELL_SMOOTH_WIDTH - 1 if k >= SHELL_SMOOTH_WIDTH else k - 1
    torch.testing.assert_close(w[k - 1 - upper], torch.tensor(1 - SHELL_TRUNCATION_EPS, dtype=torch.float64))
    assert (torch.diff(w[k - 1 - upper :]) < 0).all()
    if inclusive:
        torch.testing.assert_close(w[-1], torch.tensor(SHELL_TRUNCATION_EPS, dtype=torch.float64))


def test_sigmoid_weights_k1_and_invalid():
    torch.testing.assert_close(sigmoid_shell_weights(1), torch.ones(1))
    with pytest.raises(ConfigError):
        sigmoid_shell_weights(0)


def test_sigmoid_shell_approaches_shape_and_keeps_dtype(bumpy_sphere):
    v, f = bumpy_sphere(3)
    evals, evecs, mass = eigenbasis(v, f, 300)
    t = lambda a: torch.from_numpy(a).float()  # noqa: E731
    verts, phi, m = t(v), t(evecs), t(mass)
    errors = []
    for k in [5, 20, 80, 250]:
        shell = smooth_shell(phi, m, verts, k=k)
        assert shell.dtype == torch.float32 and shell.shape == verts.shape
        errors.append(m_norm2(m, verts - shell))
    assert all(a > b for a, b in zip(errors, errors[1:]))
    assert errors[-1] < 1e-3 * m_norm2(m, verts)
    with pytest.raises(ConfigError):
        smooth_shell(phi, m, verts, k=10, mode="box")
    with pytest.raises(ConfigError):
        smooth_shell(phi, m, verts, k=301, mode="hard")


def test_vertex_normals_equal_libigl_area_weighted(bumpy_sphere):
    v, f = bumpy_sphere(3, seed=1)
    ours = vertex_normals(torch.from_numpy(v), torch.from_numpy(f)).numpy()
    ref = igl.per_vertex_normals(v, f, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_AREA)
    np.testing.assert_allclose(ours, ref, atol=1e-10)
    fn = face_normals(torch.from_numpy(v), torch.from_numpy(f)).numpy()
    np.testing.assert_allclose(fn, igl.per_face_normals(v, f, np.array([0.0, 0.0, 1.0])), atol=1e-10)


def test_normals_point_outward_on_a_sphere_and_have_unit_length():
    s = trimesh.creation.icosphere(3)
    v = torch.from_numpy(np.asarray(s.vertices))
    n = vertex_normals(v, torch.from_numpy(np.asarray(s.faces, dtype=np.int64)))
    torch.testing.assert_close(n.norm(dim=1), torch.ones(len(v), dtype=torch.float64))
    assert ((n * v).sum(dim=1) > 0.999).all()


def test_unnormalized_face_normals_have_twice_the_area_as_length(bumpy_sphere):
    v, f = bumpy_sphere(1)
    fn = face_normals(torch.from_numpy(v), torch.from_numpy(f), normalize=False)
    np.testing.assert_allclose(fn.norm(dim=1).numpy(), igl.doublearea(v, f), rtol=1e-12)


def test_normals_differentiable_and_isolated_vertex_is_zero_not_nan(bumpy_sphere):
    v, f = bumpy_sphere(1)
    verts = torch.from_numpy(np.vstack([v, [[3.0, 0.0, 0.0]]])).requires_grad_(True)
    n = vertex_normals(verts, torch.from_numpy(f))
    assert torch.isfinite(n).all() and (n[-1] == 0).all()
    (n[:, 0] * torch.arange(len(n))).sum().backward()
    assert torch.isfinite(verts.grad).all() and verts.grad[:-1].abs().sum() > 0
