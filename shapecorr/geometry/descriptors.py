"""Spectral point descriptors: heat kernel signature (HKS) and wave kernel signature (WKS).

Both are filtered sums of squared Laplace-Beltrami eigenfunctions (numpy in, numpy out, float64):

- HKS (Sun, Ovsjanikov & Guibas, SGP 2009): ``HKS(x, t) = sum_i exp(-t lambda_i) phi_i(x)^2``;
- WKS (Aubry, Schlickewei & Cremers, ICCV-W 2011):
  ``WKS(x, e) = sum_i exp(-(e - log lambda_i)^2 / (2 sigma^2)) phi_i(x)^2``.

Zero eigenvalues (the constants, one per connected component) are skipped by default (``skip_zero``):
they add the same value ``1/area`` to every vertex and WKS needs ``log lambda``.

Normalization (``normalize``), per column (time or energy):

- ``"none"``: the raw sums (the convention of Smooth Shells' HKS);
- ``"sum"``: divided by the sum of the filter over the used eigenvalues (for HKS the heat trace
  ``sum_i exp(-t lambda_i)``, Sun et al.; for WKS the ``C_e`` of Aubry et al.). Since
  ``sum_x m_x phi_i(x)^2 = 1``, every column then integrates to 1 over the surface;
- ``"mean"``: ``"sum"`` times the total area (needs ``mass``): every column has area-weighted mean 1. This
  is dimensionless and, with the default times / energies (derived from the spectrum), **invariant to a
  uniform scaling** of the shape (eigenvalues scale by ``1/s^2``, squared eigenfunctions by ``1/s^2``).

All variants are invariant to rigid motions (they only depend on the intrinsic eigenpairs). Eigenpairs
must be those of :func:`shapecorr.geometry.laplace_beltrami.eigenbasis` (mass-orthonormal); eigenvalues in the
original Smooth/Deep Shells scale are 2x ours (``ORIGINAL_EIGENVALUE_FACTOR``).

Smooth Shells' HKS (docs/deep_shells.md §2: 200 eigenpairs without the constant, 100 times log-spaced in
[0.002, 0.05] in the doubled eigenvalue scale, raw sums) is::

    hks(ORIGINAL_EIGENVALUE_FACTOR * evals[:200], evecs[:, :200], t_min=0.002, t_max=0.05, n_times=100,
        normalize="none")
"""

from __future__ import annotations

import math

import numpy as np

from shapecorr.errors import ConfigError, NumericalError
from shapecorr.geometry.mesh import as_numpy as _as_numpy

#: HKS default time range (Sun et al. 2009, §5): t_min = 4 ln 10 / lambda_max, t_max = 4 ln 10 / lambda_min
#: (lambda_min the smallest nonzero eigenvalue used): exp(-t lambda) spans 1e-4 .. 1 over the used band.
HKS_TIME_FACTOR = 4.0 * math.log(10.0)
#: Number of HKS times (Smooth Shells uses 100).
HKS_N_TIMES = 100
#: Number of WKS energies (Aubry et al.'s reference implementation: 100).
WKS_N_ENERGIES = 100
#: WKS Gaussian width in units of the energy spacing (Aubry et al.'s reference implementation:
#: "wks_variance = 6", sigma = wks_variance * delta).
WKS_VARIANCE = 6.0
#: Eigenvalues at most this fraction of the largest one count as zero (skipped by ``skip_zero``).
ZERO_EVAL_RTOL = 1e-9
NORMALIZATIONS = ("none", "sum", "mean")


def _inputs(evals, evecs, skip_zero: bool) -> tuple[np.ndarray, np.ndarray]:
    lam = np.asarray(_as_numpy(evals), dtype=np.float64)
    phi = np.asarray(_as_numpy(evecs), dtype=np.float64)
    if lam.ndim != 1 or phi.ndim != 2 or phi.shape[1] != lam.shape[0]:
        raise ConfigError(f"need evals (k,) and evecs (n, k), got {lam.shape} and {phi.shape}")
    if not (np.isfinite(lam).all() and np.isfinite(phi).all()):
        raise NumericalError("eigenpairs contain NaN/Inf")
    if (lam < 0).any():
        raise ConfigError(f"eigenvalues must be >= 0, got min {lam.min():.3g}")
    if skip_zero:
        nonzero = lam > ZERO_EVAL_RTOL * lam.max() if lam.size and lam.max() > 0 else np.zeros(lam.shape, bool)
        lam, phi = lam[nonzero], phi[:, nonzero]
    if lam.size == 0:
        raise ConfigError("no eigenpair left (all eigenvalues are zero or none given)")
    return lam, phi


def _normalize(values: np.ndarray, filt: np.ndarray, normalize: str, mass) -> np.ndarray:
    """Apply the documented normalization; ``filt`` is the (k, T) filter matrix."""
    if normalize == "none":
        return values
    if normalize not in NORMALIZATIONS:
        raise ConfigError(f"normalize must be one of {NORMALIZATIONS}, got {normalize!r}")
    total = filt.sum(axis=0)
    if not (total > 0).all():
        raise NumericalError("a filter is zero on every eigenvalue: choose times/energies inside the spectrum")
    values = values / total[None, :]
    if normalize == "mean":
        if mass is None:
            raise ConfigError("normalize='mean' needs the vertex masses (mass=...)")
        m = np.asarray(_as_numpy(mass), dtype=np.float64)
        if m.shape != (values.shape[0],):
            raise ConfigError(f"mass must have shape ({values.shape[0]},), got {m.shape}")
        values = values * m.sum()
    return values


def _finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.isfinite(values).all():
        raise NumericalError(f"{what} contains NaN/Inf (times/energies outside the range of the spectrum?)")
    return values


def hks_times(evals, n_times: int = HKS_N_TIMES, t_min: float | None = None, t_max: float | None = None,
              skip_zero: bool = True) -> np.ndarray:
    """Log-spaced HKS times; defaults from the spectrum (Sun et al. 2009).

    Parameters
    ----------
    evals : (k,) float
    n_times : int
    t_min, t_max : float, optional
        Defaults ``HKS_TIME_FACTOR / lambda_max`` and ``HKS_TIME_FACTOR / lambda_min`` (nonzero eigenvalues).

    Returns
    -------
    (n_times,) float64, ascending
    """
    lam = np.asarray(_as_numpy(evals), dtype=np.float64)
    if skip_zero:
        lam = lam[lam > ZERO_EVAL_RTOL * lam.max()] if lam.size and lam.max() > 0 else lam[:0]
    if n_times < 1:
        raise ConfigError(f"n_times must be >= 1, got {n_times}")
    if (t_min is None or t_max is None) and (lam.size == 0 or lam.min() <= 0):
        raise ConfigError("default HKS times need at least one positive eigenvalue")
    lo = HKS_TIME_FACTOR / lam.max() if t_min is None else float(t_min)
    hi = HKS_TIME_FACTOR / lam.min() if t_max is None else float(t_max)
    if not 0 < lo <= hi:
        raise ConfigError(f"HKS times need 0 < t_min <= t_max, got {lo}, {hi}")
    return np.geomspace(lo, hi, n_times)


def hks(
    evals,
    evecs,
    times=None,
    n_times: int = HKS_N_TIMES,
    t_min: float | None = None,
    t_max: float | None = None,
    normalize: str = "sum",
    mass=None,
    skip_zero: bool = True,
) -> np.ndarray:
    """Heat kernel signature (Sun et al. 2009).

    Parameters
    ----------
    evals : (k,) float
        Eigenvalues, ascending, ``>= 0`` (their scale sets the meaning of the times).
    evecs : (n, k) float
        Mass-orthonormal eigenfunctions.
    times : (T,) float, optional
        Explicit diffusion times; otherwise ``n_times`` log-spaced in ``[t_min, t_max]``, see :func:`hks_times`.
    normalize : {"none", "sum", "mean"}
        See the module docstring; ``"mean"`` needs ``mass`` and is scale invariant.
    mass : (n,) float, optional
        Lumped vertex areas (only for ``normalize="mean"``).
    skip_zero : bool
        Leave out the zero eigenvalues (constants).

    Returns
    -------
    (n, T) float64
    """
    lam, phi = _inputs(evals, evecs, skip_zero)
    t = hks_times(lam, n_times, t_min, t_max, skip_zero=False) if times is None else np.asarray(times, np.float64)
    if t.ndim != 1 or t.size == 0 or (t <= 0).any():
        raise ConfigError("times must be a non-empty 1-D array of positive values")
    filt = np.exp(-np.outer(lam, t))  # (k, T)
    return _finite(_normalize((phi * phi) @ filt, filt, normalize, mass), "HKS")


def wks_energies(evals, n_energies: int = WKS_N_ENERGIES, variance: float = WKS_VARIANCE,
                 skip_zero: bool = True) -> tuple[np.ndarray, float]:
    """WKS log-energies and Gaussian width from the spectrum.

    The energies are evenly spaced on ``[log lambda_min, log lambda_max]`` (nonzero eigenvalues) and
    ``sigma = variance * spacing`` (Aubry et al.'s reference implementation; its extra ``/1.02`` on the upper
    log-energy is left out because it makes the range depend on the unit of length).

    Returns
    -------
    energies : (n_energies,) float64
    sigma : float
    """
    lam = np.asarray(_as_numpy(evals), dtype=np.float64)
    if skip_zero:
        lam = lam[lam > ZERO_EVAL_RTOL * lam.max()] if lam.size and lam.max() > 0 else lam[:0]
    if n_energies < 2:
        raise ConfigError(f"n_energies must be >= 2, got {n_energies}")
    if not variance > 0:
        raise ConfigError(f"WKS variance must be positive, got {variance}")
    if lam.size < 2 or lam.min() <= 0 or lam.max() <= lam.min():
        raise ConfigError("WKS needs at least two distinct positive eigenvalues")
    log_lam = np.log(lam)
    energies = np.linspace(log_lam.min(), log_lam.max(), n_energies)
    return energies, float(variance * (energies[1] - energies[0]))


def wks(
    evals,
    evecs,
    n_energies: int = WKS_N_ENERGIES,
    variance: float = WKS_VARIANCE,
    energies=None,
    sigma: float | None = None,
    normalize: str = "sum",
    mass=None,
    skip_zero: bool = True,
) -> np.ndarray:
    """Wave kernel signature (Aubry et al. 2011).

    Parameters
    ----------
    evals : (k,) float
        Eigenvalues, ascending, ``>= 0``; zero ones are skipped (``log 0``), so ``skip_zero`` must stay True
        unless all are positive.
    evecs : (n, k) float
        Mass-orthonormal eigenfunctions.
    n_energies, variance
        Default energies and width, see :func:`wks_energies`.
    energies : (E,) float, optional
        Explicit log-energies (then ``sigma`` is required).
    normalize : {"none", "sum", "mean"}
        See the module docstring; ``"sum"`` is Aubry et al.'s ``C_e``; ``"mean"`` needs ``mass`` and is scale
        invariant.
    mass : (n,) float, optional

    Returns
    -------
    (n, E) float64
    """
    lam, phi = _inputs(evals, evecs, skip_zero)
    if (lam <= 0).any():
        raise ConfigError("WKS needs positive eigenvalues (log lambda): keep skip_zero=True")
    if energies is None:
        e, s = wks_energies(lam, n_energies, variance, skip_zero=False)
        s = s if sigma is None else float(sigma)
    else:
        if sigma is None:
            raise ConfigError("explicit WKS energies need an explicit sigma")
        e, s = np.asarray(energies, dtype=np.float64), float(sigma)
    if e.ndim != 1 or e.size == 0 or not s > 0:
        raise ConfigError("energies must be a non-empty 1-D array and sigma positive")
    filt = np.exp(-((e[None, :] - np.log(lam)[:, None]) ** 2) / (2.0 * s * s))  # (k, E)
    return _finite(_normalize((phi * phi) @ filt, filt, normalize, mass), "WKS")
