"""Tests of shapecorr.geometry.descriptors (HKS, WKS): oracles, integrals, invariances, conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.descriptors import (
    HKS_TIME_FACTOR,
    WKS_VARIANCE,
    hks,
    hks_times,
    wks,
    wks_energies,
)
from shapecorr.geometry.laplace_beltrami import ORIGINAL_EIGENVALUE_FACTOR, eigenbasis

K = 60


def random_rotation(seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.fixture(scope="module")
def basis(smooth_bumpy_sphere):
    v, f = smooth_bumpy_sphere(3, 0, 0.2, n_bumps=5)
    return v, f, eigenbasis(v, f, K)


def test_hks_matches_naive_sum(basis):
    _, _, (evals, evecs, _) = basis
    times = np.array([1e-3, 1e-2, 0.1])
    out = hks(evals, evecs, times=times, normalize="none", skip_zero=False)
    ref = np.zeros((evecs.shape[0], 3))
    for a, t in enumerate(times):
        for i in range(K):
            ref[:, a] += math.exp(-t * evals[i]) * evecs[:, i] ** 2
    np.testing.assert_allclose(out, ref, rtol=1e-12)
    assert out.shape == (evecs.shape[0], 3) and out.dtype == np.float64


def test_wks_matches_naive_sum(basis):
    _, _, (evals, evecs, _) = basis
    energies, sigma = np.array([1.0, 2.0, 3.5]), 0.4
    out = wks(evals, evecs, energies=energies, sigma=sigma, normalize="sum")
    ref = np.zeros((evecs.shape[0], 3))
    for a, e in enumerate(energies):
        weights = [math.exp(-((e - math.log(lam)) ** 2) / (2 * sigma**2)) for lam in evals[1:]]
        for w, i in zip(weights, range(1, K)):
            ref[:, a] += w * evecs[:, i] ** 2
        ref[:, a] /= sum(weights)
    np.testing.assert_allclose(out, ref, rtol=1e-12)


@pytest.mark.parametrize("descriptor", [hks, wks])
def test_normalizations_integrate_as_documented(basis, descriptor):
    """'sum': each column integrates to 1 over the surface; 'mean': area-weighted mean 1."""
    _, _, (evals, evecs, mass) = basis
    d_sum = descriptor(evals, evecs, normalize="sum")
    np.testing.assert_allclose(mass @ d_sum, 1.0, rtol=1e-9)
    d_mean = descriptor(evals, evecs, normalize="mean", mass=mass)
    np.testing.assert_allclose(mass @ d_mean / mass.sum(), 1.0, rtol=1e-9)


def test_raw_hks_integrates_to_heat_trace_and_decreases_in_time(basis):
    _, _, (evals, evecs, mass) = basis
    times = hks_times(evals)
    out = hks(evals, evecs, normalize="none")
    np.testing.assert_allclose(mass @ out, np.exp(-np.outer(times, evals[1:])).sum(axis=1), rtol=1e-9)
    assert (np.diff(out, axis=1) <= 0).all()


@pytest.mark.parametrize("descriptor", [hks, wks])
def test_invariant_to_rigid_motion(basis, descriptor):
    v, f, (evals, evecs, mass) = basis
    moved = v @ random_rotation(4).T + np.array([0.3, -2.0, 5.0])
    evals_m, evecs_m, mass_m = eigenbasis(moved, f, K)
    a = descriptor(evals, evecs, normalize="mean", mass=mass)
    b = descriptor(evals_m, evecs_m, normalize="mean", mass=mass_m)
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("descriptor", [hks, wks])
def test_mean_normalization_is_scale_invariant(basis, descriptor):
    v, f, (evals, evecs, mass) = basis
    evals_s, evecs_s, mass_s = eigenbasis(2.7 * v, f, K)
    a = descriptor(evals, evecs, normalize="mean", mass=mass)
    b = descriptor(evals_s, evecs_s, normalize="mean", mass=mass_s)
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9)
    # ... while "sum" keeps the 1/area unit.
    np.testing.assert_allclose(descriptor(evals_s, evecs_s), descriptor(evals, evecs) / 2.7**2, rtol=1e-6)


def test_smooth_shells_hks_convention(smooth_bumpy_sphere):
    """Smooth Shells: HKS(v, t) = sum_{i=2..200} phi_i(v)^2 exp(-t lambda_i), doubled eigenvalues, 100
    log-spaced times in [0.002, 0.05] (docs/deep_shells.md §2), on a shape of area 0.44."""
    v, f = smooth_bumpy_sphere(3, 1, 0.2, n_bumps=5)
    v = v * math.sqrt(0.44 / trimesh.Trimesh(v, f, process=False).area)
    evals, evecs, _ = eigenbasis(v, f, 200)
    doubled = ORIGINAL_EIGENVALUE_FACTOR * evals
    out = hks(doubled, evecs, t_min=0.002, t_max=0.05, n_times=100, normalize="none")
    times = np.exp(np.linspace(np.log(0.002), np.log(0.05), 100))
    ref = (evecs[:, 1:200] ** 2) @ np.exp(-np.outer(doubled[1:200], times))
    assert out.shape == (len(v), 100)
    np.testing.assert_allclose(out, ref, rtol=1e-10)


def test_default_times_and_energies(basis):
    _, _, (evals, _, _) = basis
    t = hks_times(evals, n_times=10)
    np.testing.assert_allclose([t[0], t[-1]], [HKS_TIME_FACTOR / evals[-1], HKS_TIME_FACTOR / evals[1]])
    assert np.allclose(np.diff(np.log(t)), np.log(t[1] / t[0]))
    e, sigma = wks_energies(evals, n_energies=20)
    np.testing.assert_allclose([e[0], e[-1]], np.log([evals[1], evals[-1]]))
    np.testing.assert_allclose(sigma, WKS_VARIANCE * (e[1] - e[0]))


def test_accepts_torch_tensors(basis):
    _, _, (evals, evecs, _) = basis
    np.testing.assert_array_equal(hks(torch.from_numpy(evals), torch.from_numpy(evecs)), hks(evals, evecs))


def test_invalid_inputs_raise(basis):
    _, _, (evals, evecs, mass) = basis
    with pytest.raises(ConfigError, match="evals"):
        hks(evals[:-1], evecs)
    with pytest.raises(ConfigError, match="mass"):
        wks(evals, evecs, normalize="mean")
    with pytest.raises(ConfigError, match="normalize"):
        hks(evals, evecs, normalize="l2")
    with pytest.raises(ConfigError, match="sigma"):
        wks(evals, evecs, energies=[1.0, 2.0])
    with pytest.raises(ConfigError, match="positive"):
        wks(evals, evecs, skip_zero=False)
    bad = evecs.copy()
    bad[0, 3] = np.nan
    with pytest.raises(NumericalError):
        hks(evals, bad)
    with pytest.raises(ConfigError):
        hks(evals, evecs, times=[-1.0])
