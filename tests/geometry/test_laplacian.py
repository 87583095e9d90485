"""Tests of shapecorr.geometry.laplace_beltrami.laplacian: convention, oracles, properties, errors."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
import trimesh

from shapecorr.errors import ConfigError, InvalidMeshError
from shapecorr.geometry.laplace_beltrami import ORIGINAL_EIGENVALUE_FACTOR, laplacian


def naive_cotan(verts, faces):
    """Oracle: loop over corners, add 1/2 cot(corner) to the opposite edge (dense)."""
    n = len(verts)
    L = np.zeros((n, n))
    mass = np.zeros(n)
    for tri in faces:
        p = verts[tri]
        area = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        mass[tri] += area / 3.0
        for c in range(3):
            i, j, k = tri[c], tri[(c + 1) % 3], tri[(c + 2) % 3]
            a, b = verts[j] - verts[i], verts[k] - verts[i]
            cot = a @ b / np.linalg.norm(np.cross(a, b))
            L[j, k] -= 0.5 * cot
            L[k, j] -= 0.5 * cot
            L[j, j] += 0.5 * cot
            L[k, k] += 0.5 * cot
    return L, mass


def matlab_stiffness(verts, faces):
    """Oracle of the original MATLAB construction (docs/deep_shells.md §2): edge lengths, Heron area, weight
    (a^2 + b^2 - c^2) / (4 area) per corner, *full* cot a + cot b; returned as a PSD stiffness."""
    n = len(verts)
    W = np.zeros((n, n))
    for tri in faces:
        lengths = [np.linalg.norm(verts[tri[(c + 1) % 3]] - verts[tri[(c + 2) % 3]]) for c in range(3)]
        s = 0.5 * sum(lengths)
        area = np.sqrt(max(s * (s - lengths[0]) * (s - lengths[1]) * (s - lengths[2]), 1e-10**2))
        for c in range(3):
            j, k = tri[(c + 1) % 3], tri[(c + 2) % 3]
            a, b, opp = lengths[(c + 1) % 3], lengths[(c + 2) % 3], lengths[c]
            w = (a * a + b * b - opp * opp) / (4.0 * area)
            W[j, k] += w
            W[k, j] += w
    return np.diag(W.sum(axis=1)) - W


@pytest.fixture(scope="module")
def bumpy(bumpy_sphere):
    return bumpy_sphere(2)


def test_cotan_matches_naive_oracle(bumpy):
    v, f = bumpy
    L, mass = laplacian(v, f)
    L_ref, mass_ref = naive_cotan(v, f)
    assert L.shape == (len(v), len(v)) and L.dtype == np.float64 and L.format == "csr"
    np.testing.assert_allclose(L.toarray(), L_ref, atol=1e-12)
    np.testing.assert_allclose(mass, mass_ref, rtol=1e-12)


@pytest.mark.parametrize("method", ["cotan", "robust"])
@pytest.mark.parametrize("mesh", ["bumpy", "torus"])
def test_symmetric_psd_zero_row_sums(method, mesh, bumpy):
    if mesh == "bumpy":
        v, f = bumpy
    else:
        t = trimesh.creation.torus(1.0, 0.3, 24, 12)
        v, f = np.asarray(t.vertices), np.asarray(t.faces)
    L, mass = laplacian(v, f, method=method)
    dense = L.toarray()
    scale = np.abs(dense).max()
    assert np.array_equal(dense, dense.T)
    assert (dense.diagonal() > 0).all()
    np.testing.assert_allclose(dense.sum(axis=1), 0.0, atol=1e-12 * scale)
    evals = scipy.linalg.eigvalsh(dense)
    assert evals.min() > -1e-10 * scale
    # Exactly one zero eigenvalue for a connected mesh (the constants).
    assert (evals < 1e-8 * scale).sum() == 1
    assert (mass > 0).all()
    area = trimesh.Trimesh(v, f, process=False).area
    np.testing.assert_allclose(mass.sum(), area, rtol=1e-9 if method == "cotan" else 1e-3)


def test_original_scale_is_twice_ours(bumpy):
    """The MATLAB full-cot stiffness has exactly ORIGINAL_EIGENVALUE_FACTOR times our eigenvalues."""
    v, f = bumpy
    L, mass = laplacian(v, f)
    ours = scipy.linalg.eigh(L.toarray(), np.diag(mass), eigvals_only=True)
    original = scipy.linalg.eigh(matlab_stiffness(v, f), np.diag(mass), eigvals_only=True)
    assert ORIGINAL_EIGENVALUE_FACTOR == 2.0
    np.testing.assert_allclose(original[1:], ORIGINAL_EIGENVALUE_FACTOR * ours[1:], rtol=1e-9)


def test_unreferenced_vertex_gets_zero_mass_and_empty_row(bumpy):
    v, f = bumpy
    L, mass = laplacian(np.vstack([v, [[5.0, 5.0, 5.0]]]), f)
    assert mass.shape == (len(v) + 1,) and mass[-1] == 0.0
    assert L.shape == (len(v) + 1, len(v) + 1) and L[len(v)].nnz == 0


def test_torch_input_same_as_numpy(bumpy):
    v, f = bumpy
    L_np, m_np = laplacian(v, f)
    L_t, m_t = laplacian(torch.tensor(v, dtype=torch.float64, requires_grad=True), torch.from_numpy(f))
    assert (L_np != L_t).nnz == 0
    np.testing.assert_array_equal(m_np, m_t)


def test_robust_handles_nonmanifold_and_zero_area_faces():
    # Three triangles on one edge (non-manifold) plus a flat (zero-area) triangle.
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1], [2, 0, 0]], dtype=float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [0, 1, 5]])
    with pytest.raises(InvalidMeshError, match="zero-area"):
        laplacian(v, f, method="cotan")
    L, mass = laplacian(v, f, method="robust")
    dense = L.toarray()
    assert np.isfinite(dense).all() and np.isfinite(mass).all()
    assert np.array_equal(dense, dense.T)
    np.testing.assert_allclose(dense.sum(axis=1), 0.0, atol=1e-12 * np.abs(dense).max())
    assert scipy.linalg.eigvalsh(dense).min() > -1e-10 * np.abs(dense).max()


def test_invalid_input_raises(bumpy_sphere):
    v, f = bumpy_sphere(1)
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InvalidMeshError, match="NaN"):
        laplacian(bad, f)
    with pytest.raises(InvalidMeshError, match="outside"):
        laplacian(v, np.vstack([f, [[0, 1, len(v)]]]))
    with pytest.raises(InvalidMeshError, match="shape"):
        laplacian(v[:, :2], f)
    with pytest.raises(ConfigError, match="method"):
        laplacian(v, f, method="uniform")
