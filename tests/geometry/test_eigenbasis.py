"""Tests of shapecorr.geometry.laplace_beltrami.eigenbasis: orthonormality, sphere spectrum, determinism,
components, removed vertices, the sliced solver, and (opt-in) parity with the original preprocessing."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

from shapecorr.errors import ConfigError
from shapecorr.geometry import laplace_beltrami as lap
from shapecorr.geometry.laplace_beltrami import ORIGINAL_EIGENVALUE_FACTOR, eigenbasis, laplacian


def check_eigenpairs(v, f, evals, evecs, mass, method="cotan", atol=1e-8):
    """L phi = lambda M phi, M-orthonormal, ascending, non-negative."""
    L, m = laplacian(v, f, method)
    np.testing.assert_array_equal(mass, m)
    k = evals.shape[0]
    assert evecs.shape == (v.shape[0], k) and evals.dtype == np.float64 and evecs.dtype == np.float64
    np.testing.assert_allclose(evecs.T @ (mass[:, None] * evecs), np.eye(k), atol=atol)
    assert (np.diff(evals) >= 0).all() and (evals >= 0).all()
    residual = L @ evecs - (mass[:, None] * evecs) * evals[None, :]
    assert np.abs(residual).max() < 1e-7 * max(evals.max(), 1.0) * mass.max()


@pytest.mark.parametrize("subdivisions", [3, 4])  # 642 vertices: dense path; 2562: sparse shift-invert
def test_orthonormal_residuals(subdivisions, smooth_bumpy_sphere):
    v, f = smooth_bumpy_sphere(subdivisions)
    evals, evecs, mass = eigenbasis(v, f, 40)
    check_eigenpairs(v, f, evals, evecs, mass)
    assert evals[0] == 0.0 and evals[1] > 0.1
    np.testing.assert_allclose(evecs[:, 0], 1.0 / np.sqrt(mass.sum()), rtol=1e-12)


def test_unit_sphere_spectrum_and_multiplicities(unit_sphere):
    v, f = unit_sphere(4)
    evals, evecs, mass = eigenbasis(v, f, 25)
    check_eigenpairs(v, f, evals, evecs, mass)
    degrees = np.arange(5)
    exact = degrees * (degrees + 1.0)
    nearest = np.abs(evals[:, None] - exact[None, :]).argmin(axis=1)
    # Multiplicities 1, 3, 5, 7, 9 ...
    np.testing.assert_array_equal(np.bincount(nearest, minlength=5), 2 * degrees + 1)
    # ... and values l (l + 1) within 1% (O(h^2) discretization error, 0.7% at l = 4 on this mesh).
    np.testing.assert_allclose(evals[1:], exact[nearest[1:]], rtol=1e-2)


def test_deterministic(smooth_bumpy_sphere):
    v, f = smooth_bumpy_sphere(4, seed=1)
    a = eigenbasis(v, f, 30)
    b = eigenbasis(v, f, 30)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("subdivisions", [3, 4])
def test_vertex_permutation_permutes_eigenfunctions(subdivisions, smooth_bumpy_sphere):
    """The sign rule is intrinsic: eigenfunctions of a permuted mesh are the permuted eigenfunctions."""
    v, f = smooth_bumpy_sphere(subdivisions, seed=2)
    k = 30
    evals, evecs, _ = eigenbasis(v, f, k)
    perm = np.random.default_rng(3).permutation(len(v))
    inverse = np.argsort(perm)
    evals_p, evecs_p, _ = eigenbasis(v[perm], inverse[f], k)
    np.testing.assert_allclose(evals_p, evals, rtol=1e-9, atol=1e-9)
    gaps = np.diff(evals)
    simple = np.flatnonzero(np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf]) > 1e-3 * evals[-1])
    assert simple.size >= k // 2  # the bumps split most multiple eigenvalues of the sphere
    np.testing.assert_allclose(evecs_p[:, simple], evecs[perm][:, simple], atol=1e-6)


def test_two_disjoint_spheres(unit_sphere):
    v1, f1 = unit_sphere(3)
    v2, f2 = unit_sphere(3)
    v = np.vstack([v1, 0.5 * v2 + [3.0, 0.0, 0.0]])  # second sphere smaller (radius 0.5), given second
    f = np.vstack([f1, f2 + len(v1)])
    n1 = len(v1)
    evals, evecs, mass = eigenbasis(v, f, 13)
    check_eigenpairs(v, f, evals, evecs, mass)
    # One zero eigenvalue per component, eigenvectors = normalized indicators, larger component first.
    assert evals[0] == 0.0 and evals[1] == 0.0 and evals[2] > 1.0
    area1, area2 = mass[:n1].sum(), mass[n1:].sum()
    np.testing.assert_allclose(evecs[:n1, 0], 1 / np.sqrt(area1))
    np.testing.assert_allclose(evecs[n1:, 0], 0.0)
    np.testing.assert_allclose(evecs[n1:, 1], 1 / np.sqrt(area2))
    np.testing.assert_allclose(evecs[:n1, 1], 0.0)
    # Then the union of both spectra: unit sphere l=1 (2, x3), l=2 (6, x5), then small sphere l=1 (8, x3).
    np.testing.assert_allclose(evals[2:5], 2.0, rtol=2e-2)
    np.testing.assert_allclose(evals[5:10], 6.0, rtol=2e-2)
    np.testing.assert_allclose(evals[10:13], 8.0, rtol=2e-2)
    assert np.abs(evecs[n1:, 2:10]).max() < 1e-8  # supported on the unit sphere only
    assert np.abs(evecs[:n1, 10:13]).max() < 1e-8  # supported on the small sphere only


def test_equal_components_ordered_by_first_vertex(unit_sphere):
    v1, f1 = unit_sphere(2)
    v = np.vstack([v1, v1 + [3.0, 0.0, 0.0]])
    f = np.vstack([f1, f1 + len(v1)])
    evals, evecs, _ = eigenbasis(v, f, 4)
    assert (evecs[: len(v1), 0] > 0).all() and np.abs(evecs[len(v1) :, 0]).max() == 0.0


def test_unreferenced_vertex_is_removed_and_gets_a_finite_row(smooth_bumpy_sphere):
    v, f = smooth_bumpy_sphere(3)
    evals, evecs, mass = eigenbasis(v, f, 20)
    v_extra = np.vstack([v, [[4.0, 4.0, 4.0]]])
    evals_x, evecs_x, mass_x = eigenbasis(v_extra, f, 20)
    assert mass_x[-1] == 0.0 and np.isfinite(evecs_x).all()
    np.testing.assert_allclose(evals_x, evals, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(evecs_x[:-1], evecs, atol=1e-8)
    # No kept neighbour: the mean row over the kept vertices (the MATLAB rule).
    np.testing.assert_allclose(evecs_x[-1], evecs.mean(axis=0), atol=1e-8)


def test_small_mass_vertices_get_neighbour_means(smooth_bumpy_sphere):
    v, f = smooth_bumpy_sphere(3)
    _, m = laplacian(v, f)
    threshold = np.sort(m)[3] * (1 + 1e-9)  # removes the 4 smallest-mass vertices
    evals, evecs, mass = eigenbasis(v, f, 15, min_mass=threshold)
    removed = np.flatnonzero(mass < threshold)
    assert removed.size == 4 and np.isfinite(evecs).all()
    kept = np.setdiff1d(np.arange(len(v)), removed)
    G = evecs[kept].T @ (mass[kept, None] * evecs[kept])
    np.testing.assert_allclose(G, np.eye(15), atol=1e-8)
    for r in removed:
        nbrs = np.setdiff1d(np.unique(f[(f == r).any(axis=1)]), np.r_[r, removed])
        np.testing.assert_allclose(evecs[r], evecs[nbrs].mean(axis=0), atol=1e-12)


def test_k_out_of_range_raises(unit_sphere):
    v, f = unit_sphere(1)  # 42 vertices
    with pytest.raises(ConfigError, match="k"):
        eigenbasis(v, f, len(v))
    with pytest.raises(ConfigError):
        eigenbasis(v, f, 0)
    evals, evecs, _ = eigenbasis(v, f, len(v) - 1)  # the largest allowed
    assert evecs.shape == (len(v), len(v) - 1)


@pytest.mark.parametrize("ordering", ["mmd", "colamd"])
def test_sliced_solver_matches_dense_with_multiplicities(unit_sphere, ordering, monkeypatch):
    """Small slices on the sphere (groups of 2l+1 close eigenvalues, split by the icosahedral symmetry into
    exact clusters of up to 5) must neither lose nor repeat any eigenvalue, with either fill-reducing ordering
    of the LDL^T (COLAMD is what meshes above ``LDLT_MMD_MAX_N`` vertices get; its inertia count must hold)."""
    if ordering == "colamd":
        monkeypatch.setattr(lap, "LDLT_MMD_MAX_N", 0)
    used, splu = set(), lap.sla.splu

    def recording_splu(*args, **kwargs):
        used.add(kwargs["permc_spec"])
        return splu(*args, **kwargs)

    monkeypatch.setattr(lap.sla, "splu", recording_splu)
    v, f = unit_sphere(3)
    L, m = laplacian(v, f)
    s = 1.0 / np.sqrt(m)
    A = sp.csc_matrix(sp.diags(s) @ L @ sp.diags(s))
    k = 64
    evals, evecs = lap._sliced_eigsh(A, k, float(A.diagonal().mean()), 10, lap.EIGSH_TOL)
    dense = scipy.linalg.eigh(A.toarray(), eigvals_only=True, subset_by_index=[0, k - 1])
    np.testing.assert_allclose(evals, dense, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(evecs.T @ evecs, np.eye(k), atol=1e-8)
    assert lap._max_residual(A, evals, evecs) < 1e-8 * A.diagonal().mean()
    assert used == {"MMD_AT_PLUS_A" if ordering == "mmd" else "COLAMD"}


def test_robust_method_close_to_cotan_on_good_mesh(smooth_bumpy_sphere):
    v, f = smooth_bumpy_sphere(3)
    evals_c, _, _ = eigenbasis(v, f, 10)
    evals_r, evecs_r, mass_r = eigenbasis(v, f, 10, method="robust")
    check_eigenpairs(v, f, evals_r, evecs_r, mass_r, method="robust")
    np.testing.assert_allclose(evals_r[1:], evals_c[1:], rtol=2e-2)


@pytest.mark.reference
def test_matches_original_preprocessing():
    """Golden eigenpairs of the original MATLAB preprocessing (full-cot scale) on a FAUST_r shape."""
    root = os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN")
    if not root:
        pytest.skip("set SHAPECORR_DEEP_SHELLS_GOLDEN to the deep_shells_golden folder to run this parity test")
    data = np.load(Path(root) / "inputs_tr_reg_080__tr_reg_081.npz")
    k = 200
    evals, evecs, mass = eigenbasis(data["x_verts"], data["x_faces"], k)
    ref_evals = data["x_evals"][:k].astype(np.float64)
    np.testing.assert_allclose(mass, data["x_mass"], rtol=1e-5)
    np.testing.assert_allclose(ORIGINAL_EIGENVALUE_FACTOR * evals[1:], ref_evals[1:], rtol=1e-5)
    # Same eigenfunctions up to sign (the first 100 are well separated on this shape).
    overlap = np.abs((evecs[:, :100] * mass[:, None]).T @ data["x_evecs"][:, :100].astype(np.float64))
    assert overlap.diagonal().min() > 0.999
