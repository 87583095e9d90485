"""Cotangent Laplacian, lumped mass and the Laplace-Beltrami eigenbasis of a triangle mesh.

Conventions
-----------
``laplacian`` returns the *stiffness* matrix ``L`` (symmetric positive semidefinite: positive diagonal,
non-positive off-diagonal entries on Delaunay meshes, zero row sums) with the standard finite-element
weights ``L_ij = -1/2 (cot a_ij + cot b_ij)`` (``-igl.cotmatrix``), and the barycentric lumped mass
``m_i = 1/3 * sum of the areas of the faces around i`` (``igl.massmatrix`` BARYCENTRIC). The
Laplace-Beltrami eigenpairs solve the generalized problem ``L phi = lambda M phi``, ``M = diag(m)``; on a
unit sphere ``lambda_l = l (l + 1)``.

Eigenvalue scale of the original code: the MATLAB preprocessing of Smooth Shells / Deep Shells / G-MSM
builds its stiffness with the full ``cot a + cot b`` weight, so every eigenvalue stored in their ``.mat``
files is exactly ``ORIGINAL_EIGENVALUE_FACTOR = 2`` times ours (docs/deep_shells.md §2). Hyperparameters
published in that scale (spectral filter scale 5e4, HKS times [0.002, 0.05]) need
``ORIGINAL_EIGENVALUE_FACTOR * evals`` (or rescaled parameters) to mean the same thing here.

``method="robust"`` uses the intrinsic-Delaunay Laplacian of the tufted cover (Sharp & Crane, "A Laplacian
for Nonmanifold Triangle Meshes", SGP 2020) from ``robust_laplacian``: same sign and scale conventions, but
well defined on non-manifold meshes, with slivers and zero-area faces, where the cotan weights are
infinite or badly negative. Its mass is the lumped mass of the intrinsic triangulation (also ~ area / 3).
"""

from __future__ import annotations

from contextlib import nullcontext

import igl
import numpy as np
import robust_laplacian
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.sparse.csgraph import connected_components

from shapecorr.errors import ConfigError, InvalidMeshError, NumericalError
from shapecorr.geometry.mesh import as_numpy, check_mesh_arrays

try:  # optional: limits BLAS threads during the ARPACK solves (see _single_threaded_blas)
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover - only slower without it
    threadpool_limits = None

#: The original Smooth Shells / Deep Shells / G-MSM stiffness uses cot a + cot b (not 1/2 of it), so their
#: eigenvalues are exactly this factor times ours (docs/deep_shells.md §2).
ORIGINAL_EIGENVALUE_FACTOR = 2.0

#: Vertices whose lumped mass is below this are removed from the eigen solve (MATLAB preprocessing of
#: Smooth Shells / Deep Shells, docs/deep_shells.md §2). Absolute, in squared units of the input.
DEFAULT_MIN_MASS = 1e-14

#: Mollification of the tufted-cover Laplacian (robust_laplacian's default, Sharp & Crane 2020 §4.2).
ROBUST_MOLLIFY_FACTOR = 1e-5

LAPLACIAN_METHODS = ("cotan", "robust")

# --- eigen solver settings (project choices, measured in benchmarks/geometry_speed.py) -------------------
#: Relative shift of the first shift-invert solve: sigma = -EIGSH_SHIFT_REL * mean(diag(A)). Slightly below
#: zero so that L - sigma M is positive definite while the zero eigenvalues stay the nearest ones (the
#: MATLAB code used an absolute shift of 1e-5 on area-0.44 shapes; relative here, so any unit works).
EIGSH_SHIFT_REL = 1e-8
#: ARPACK convergence tolerance (relative accuracy of the Ritz values of the inverted operator).
EIGSH_TOL = 1e-10
#: Eigenpairs computed per shift-invert solve ("spectral slice"). ARPACK's cost grows with the square of the
#: number of requested pairs (one 500-pair run on a 5k-vertex FAUST_r shape: 15 s, 12 s of it in the
#: eigenvector extraction dseupd), so many pairs are computed as several slices at increasing shifts
#: (500 pairs: ~2 s of CPU). 40-60 measured best on FAUST_r (benchmarks/geometry_speed.py).
EIGSH_SLICE_SIZE = 50
#: Lanczos basis size per slice: ncv = max(EIGSH_NCV_FACTOR * m + 1, m + EIGSH_NCV_MIN_EXTRA). scipy's
#: default factor is 2; 1.3-1.45 was ~20% faster on FAUST_r (fewer BLAS-2 orthogonalization steps).
EIGSH_NCV_FACTOR = 1.4
EIGSH_NCV_MIN_EXTRA = 20
#: Fraction of each slice spent re-finding eigenvalues of the previous slice (guarantees no gap).
EIGSH_SLICE_OVERLAP = 0.15
#: Attempts to place a slice so that it reaches back below the boundary (shift halfway closer, 1.5x pairs).
EIGSH_SLICE_RETRIES = 4
#: Searches for eigenvalues missed by Lanczos (exact multiplicities), each orthogonal to those found.
EIGSH_DEFLATION_ROUNDS = 12
#: Extra pairs asked for beyond the needed ones in the last slice (at least this many, or OVERLAP * need).
EIGSH_SLICE_MARGIN = 3
#: Eigenvalues closer than this (relative to the largest one found) belong to one cluster (a multiple
#: eigenvalue); clusters are never split between two slices.
EIGSH_CLUSTER_RTOL = 1e-6
#: Accepted residual ||A psi - lambda psi|| relative to mean(diag(A)) (a spectral-radius scale); a larger
#: residual after the sliced solve triggers the dense fallback.
EIGSH_RESIDUAL_RTOL = 1e-7
#: Largest matrix factorized with SuperLU's minimum-degree ordering of A^T + A (least fill); COLAMD above.
#: Measured on FAUST_r tr_reg_080 refined (one thread): MMD vs COLAMD 0.18 s vs 0.20 s at 21k rows, 4.9 s vs
#: 0.6 s at 49k, 234 s vs 2.0 s at 147k (the ordering itself grows super-linearly); COLAMD fills ~1.6x more.
LDLT_MMD_MAX_N = 30000
#: Largest mesh for the dense fallback (an n x n float64 eigendecomposition: 16 s and 200 MB at n = 5000).
DENSE_FALLBACK_MAX_N = 8000
#: Up to this many vertices the eigenproblem is solved densely (LAPACK), which is faster there and exact.
DENSE_MAX_N = 1000
#: ... and also when more than this fraction of the spectrum is requested.
DENSE_MAX_K_FRACTION = 0.3
#: Eigenvalues at most this (relative to mean(diag(A))) count as zero (the constants of each component).
ZERO_EVAL_RTOL = 1e-9
#: Component areas equal to this many decimals (relative to the largest) are ties, ordered by first vertex.
AREA_TIE_DECIMALS = 9
#: Largest accepted negative eigenvalue (relative to mean(diag(A))) before clipping at zero.
NEGATIVE_EVAL_RTOL = 1e-9
#: Eigenvectors are re-orthonormalized when max |Phi^T M Phi - I| exceeds this.
ORTHONORMALITY_TOL = 1e-9
#: Sign rule: the skewness sum(m phi^3) decides unless it is below this fraction of sum(m |phi|^3).
SIGN_SKEW_RTOL = 1e-6
#: Seed of the ARPACK start vector (a fixed start vector makes the solve deterministic).
EIGSH_SEED = 0


def mesh_arrays(verts, faces) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 vertices and int64 faces from numpy arrays or CPU torch tensors.

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int

    Returns
    -------
    verts : (n, 3) float64
    faces : (f, 3) int64

    Raises
    ------
    InvalidMeshError
        Wrong shapes or dtypes, NaN/Inf coordinates, face indices out of range.
    """
    v, f = check_mesh_arrays(as_numpy(verts), as_numpy(faces))
    return np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(f, dtype=np.int64)


def laplacian(verts, faces, method: str = "cotan") -> tuple[sp.csr_matrix, np.ndarray]:
    """Cotangent stiffness matrix and lumped mass of a triangle mesh.

    Parameters
    ----------
    verts : (n, 3) float
        Vertex positions (numpy array or CPU torch tensor).
    faces : (f, 3) int
        Zero-based triangles.
    method : {"cotan", "robust"}
        ``"cotan"``: ``L = -igl.cotmatrix`` (weights 1/2 (cot a + cot b)) and the barycentric lumped mass;
        needs a mesh without zero-area faces. ``"robust"``: the tufted-cover intrinsic-Delaunay Laplacian of
        ``robust_laplacian.mesh_laplacian`` (non-manifold and degenerate meshes).

    Returns
    -------
    L : (n, n) scipy.sparse.csr_matrix float64
        Symmetric positive semidefinite stiffness, zero row sums.
    mass : (n,) float64
        Lumped vertex areas (zero for a vertex in no face).

    Raises
    ------
    InvalidMeshError
        Invalid arrays, or (cotan) infinite weights from zero-area faces.
    ConfigError
        Unknown method.
    """
    v, f = mesh_arrays(verts, faces)
    n = v.shape[0]
    if method == "cotan":
        L = sp.csr_matrix(-igl.cotmatrix(v, f), dtype=np.float64)
        # igl sizes the mass matrix by the largest referenced index: pad for trailing unreferenced vertices.
        diag = igl.massmatrix(v, f, igl.MASSMATRIX_TYPE_BARYCENTRIC).diagonal()
        mass = np.zeros(n)
        mass[: diag.shape[0]] = diag
        if not np.isfinite(L.data).all():
            coo = L.tocoo()
            bad = np.unique(coo.row[~np.isfinite(coo.data)])
            raise InvalidMeshError(
                f"cotangent Laplacian has infinite weights around {len(bad)} vertices (first {bad[:5].tolist()}): "
                "the mesh has zero-area faces; use method='robust' or clean the mesh"
            )
    elif method == "robust":
        L_r, M_r = robust_laplacian.mesh_laplacian(v, f, mollify_factor=ROBUST_MOLLIFY_FACTOR)
        L = sp.csr_matrix(L_r, dtype=np.float64)
        mass = np.asarray(M_r.diagonal(), dtype=np.float64)
    else:
        raise ConfigError(f"laplacian method must be one of {LAPLACIAN_METHODS}, got {method!r}")
    # Exact symmetry (the libraries assemble both triangles in the same order, this only removes round-off).
    L = sp.csr_matrix(0.5 * (L + L.T))
    if not (np.isfinite(L.data).all() and np.isfinite(mass).all()):
        raise NumericalError(f"{method} Laplacian or mass contains NaN/Inf")
    return L, mass


def eigenbasis(
    verts, faces, k: int, method: str = "cotan", min_mass: float = DEFAULT_MIN_MASS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``k`` lowest Laplace-Beltrami eigenpairs: ``L phi = lambda M phi``.

    Solved in float64 as the standard problem for ``A = M^-1/2 L M^-1/2`` (M is diagonal) with
    shift-invert ARPACK (``scipy.sparse.linalg.eigsh`` with a sparse LDL^T of ``A - sigma I`` as
    ``OPinv``), first around a shift slightly below zero. Many pairs are computed as consecutive
    shift-invert "slices" at increasing shifts (much faster than one ARPACK run, see ``EIGSH_SLICE_SIZE``),
    each verified to be complete by Sylvester's law of inertia (missed copies of multiple eigenvalues are
    searched again by deflation); see :func:`_sliced_eigsh`. Meshes up to ``DENSE_MAX_N`` vertices (or
    ``k > DENSE_MAX_K_FRACTION * n``) are solved densely with LAPACK; if the sliced solve cannot be
    verified or its residuals are too large, the dense solve is the fallback (up to
    ``DENSE_FALLBACK_MAX_N`` vertices, else NumericalError). BLAS runs single-threaded during the solve
    when ``threadpoolctl`` is installed (see :func:`_single_threaded_blas`).

    Parameters
    ----------
    verts : (n, 3) float
    faces : (f, 3) int
    k : int
        Number of eigenpairs, ``1 <= k <= n_kept - 1`` (``n_kept``: vertices with ``mass >= min_mass``).
    method : {"cotan", "robust"}
        Laplacian, see :func:`laplacian`.
    min_mass : float
        Vertices with a smaller lumped mass (unreferenced vertices, vertices of collapsed faces) are removed
        from the solve together with their edges (the diagonal is recomputed so that rows still sum to zero).

    Returns
    -------
    evals : (k,) float64
        Ascending, ``>= 0`` (round-off negatives clipped). The standard 1/2-cot scale: multiply by
        ``ORIGINAL_EIGENVALUE_FACTOR`` for the original Smooth/Deep Shells scale.
    evecs : (n, k) float64
        ``evecs.T @ diag(mass) @ evecs = I`` (re-orthonormalized if the solver drifted). Determinism:

        - *components*: a mesh with ``c`` connected components has ``c`` zero eigenvalues; they are returned
          as exact zeros with the eigenvectors ``1_C / sqrt(area(C))`` (indicator of component C), ordered
          by decreasing component area, ties by smallest vertex index;
        - *signs* of the other eigenvectors: ``sum_i m_i phi_i^3 > 0`` (positive mass-weighted skewness);
          when that sum is below ``SIGN_SKEW_RTOL * sum_i m_i |phi_i|^3`` (an odd function of a symmetric
          shape), the entry of largest magnitude is made positive instead. The rule only uses intrinsic
          quantities, so it commutes with a vertex permutation. Eigenvectors of a multiple eigenvalue are an
          arbitrary (deterministic for a given mesh) basis of their eigenspace;
        - *removed vertices* (``mass < min_mass``) get the mean of the rows of their kept one-ring neighbours,
          or, without any kept neighbour, the mean row over all kept vertices (the MATLAB rule).
    mass : (n,) float64
        Lumped vertex areas of all vertices (removed ones included).

    Raises
    ------
    ConfigError
        ``k < 1`` or ``k > n_kept - 1``.
    InvalidMeshError
        See :func:`laplacian`.
    NumericalError
        The solver did not converge, the operator is not positive semidefinite, or NaN/Inf appeared.
    """
    v, f = mesh_arrays(verts, faces)
    n = v.shape[0]
    L, mass = laplacian(v, f, method)
    keep = mass >= min_mass
    n_kept = int(keep.sum())
    if not (1 <= k <= n_kept - 1):
        raise ConfigError(
            f"eigenbasis needs 1 <= k <= n-1 = {n_kept - 1} (vertices with mass >= {min_mass:g}: {n_kept} of {n}), "
            f"got k={k}"
        )
    kept = np.flatnonzero(keep)
    L_k = sp.csr_matrix(L[kept][:, kept])
    if n_kept < n:
        # Drop the edges to removed vertices: recompute the diagonal so that constants stay in the kernel.
        off = L_k - sp.diags(L_k.diagonal())
        L_k = sp.csr_matrix(off - sp.diags(np.asarray(off.sum(axis=1)).ravel()))
    m_k = mass[kept]
    inv_sqrt = 1.0 / np.sqrt(m_k)
    A = sp.diags(inv_sqrt) @ L_k @ sp.diags(inv_sqrt)
    A = sp.csc_matrix(0.5 * (A + A.T))
    scale = float(np.mean(A.diagonal()))
    if not scale > 0:
        raise InvalidMeshError("Laplacian has no positive diagonal entry (no edge with a nonzero weight)")

    evals, psi = _lowest_eigenpairs(A, k, scale)
    if evals[0] < -NEGATIVE_EVAL_RTOL * scale:
        raise NumericalError(
            f"{method} Laplacian is not positive semidefinite (eigenvalue {evals[0]:.3g}); "
            "try method='robust'"
        )
    evals = np.maximum(evals, 0.0)
    phi = inv_sqrt[:, None] * psi

    n_zero = _set_component_indicators(L_k, m_k, evals, phi, scale)
    phi = _m_orthonormalize(phi, m_k)
    _fix_signs(phi[:, n_zero:], m_k)

    evecs = np.empty((n, k))
    evecs[kept] = phi
    if n_kept < n:
        evecs[~keep] = _removed_rows(f, keep, evecs)
    if not (np.isfinite(evals).all() and np.isfinite(evecs).all()):
        raise NumericalError("eigenbasis produced NaN/Inf values")
    return evals, evecs, mass


def _lowest_eigenpairs(
    A: sp.csc_matrix,
    k: int,
    scale: float | None = None,
    slice_size: int = EIGSH_SLICE_SIZE,
    tol: float = EIGSH_TOL,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` smallest eigenpairs of a symmetric positive semidefinite sparse matrix.

    Parameters
    ----------
    A : (n, n) sparse float64, symmetric PSD
    k : int, ``k <= n - 1``
    scale : float
        A spectral scale (mean diagonal); computed when None.
    slice_size : int
        Pairs per shift-invert solve, see ``EIGSH_SLICE_SIZE``.

    Returns
    -------
    evals : (k,) float64, ascending
    evecs : (n, k) float64, orthonormal columns
    """
    n = A.shape[0]
    if scale is None:
        scale = float(np.mean(A.diagonal()))
    if n <= DENSE_MAX_N or k > DENSE_MAX_K_FRACTION * n:
        with _single_threaded_blas() if n <= DENSE_MAX_N else nullcontext():
            return _dense_eigh(A, k)
    try:
        with _single_threaded_blas():
            evals, evecs = _sliced_eigsh(A, k, scale, slice_size, tol)
        if _max_residual(A, evals, evecs) <= EIGSH_RESIDUAL_RTOL * scale:
            return evals, evecs
        failure = "residual check failed"
    except (_SliceError, sla.ArpackNoConvergence, sla.ArpackError, RuntimeError) as err:
        failure = str(err)
    if n <= DENSE_FALLBACK_MAX_N:
        return _dense_eigh(A, k)
    raise NumericalError(f"sparse eigen solve for {k} eigenpairs failed ({failure}) and the mesh is too large "
                         f"({n} > {DENSE_FALLBACK_MAX_N} vertices) for the dense fallback")


def _single_threaded_blas():
    """Context in which BLAS runs on one thread (when threadpoolctl is installed).

    ARPACK's Lanczos steps are BLAS-2 products with (n, ncv) blocks, too small to gain from threads; OpenBLAS
    threads them anyway, and on this 2-core machine shared with other jobs that made the 500-pair solve of
    a 5k-vertex mesh 2-5x slower in wall time (OPENBLAS_NUM_THREADS=1 vs default, measured while other
    processes were running). The sparse LU solves are single-threaded in any case.
    """
    return threadpool_limits(limits=1, user_api="blas") if threadpool_limits is not None else nullcontext()


def _dense_eigh(A, k: int) -> tuple[np.ndarray, np.ndarray]:
    """LAPACK eigendecomposition of the dense matrix (exact, O(n^3))."""
    return scipy.linalg.eigh(A.toarray(), subset_by_index=[0, k - 1])


class _SliceError(Exception):
    """A spectral slice could not be completed (verified) after the allowed retries."""


def _ldlt(A, x: float):
    """Sparse LU of ``A - x I`` with symmetric (diagonal) pivoting, i.e. an LDL^T factorization.

    Fill-reducing ordering: SuperLU's minimum degree on ``A^T + A`` up to ``LDLT_MMD_MAX_N`` rows (least
    fill), COLAMD above, where the minimum-degree ordering itself takes super-linear time (see the constant).
    """
    n = A.shape[0]
    return sla.splu(
        sp.csc_matrix(A - x * sp.eye(n, format="csc")),
        permc_spec="MMD_AT_PLUS_A" if n <= LDLT_MMD_MAX_N else "COLAMD",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )


def _count_below(A, x: float) -> int:
    """Number of eigenvalues of ``A`` below ``x`` (Sylvester's law of inertia on ``A - x I = L D L^T``)."""
    lu = _ldlt(A, x)
    if not np.array_equal(lu.perm_r, lu.perm_c):
        raise _SliceError("LU used off-diagonal pivots; inertia unavailable")
    return int((lu.U.diagonal() < 0).sum())


class _ShiftInvert:
    """Shift-invert operator ``(A - sigma I)^-1`` from a sparse LDL^T.

    Symmetric fill-reducing ordering; no pivoting is accurate for shifted Laplacians in practice, and the
    residual check guards it. Optionally restricted to the orthogonal complement of known eigenvectors
    (deflation).
    """

    def __init__(self, A, sigma: float):
        self.A, self.sigma, self.n = A, sigma, A.shape[0]
        self.solve = _ldlt(A, sigma).solve

    def nearest(self, m: int, tol: float, v0: np.ndarray, known: np.ndarray | None = None):
        """The ``m`` eigenpairs nearest to sigma (orthogonal to ``known`` columns if given), ascending."""
        if known is None:
            matvec = self.solve
        else:

            def matvec(x):
                x = x - known @ (known.T @ x)
                y = self.solve(x)
                return y - known @ (known.T @ y)

            v0 = v0 - known @ (known.T @ v0)
        op = sla.LinearOperator((self.n, self.n), matvec=matvec, dtype=np.float64)
        m = min(m, self.n - 1 - (0 if known is None else known.shape[1]))
        ncv = min(self.n, max(int(EIGSH_NCV_FACTOR * m) + 1, m + EIGSH_NCV_MIN_EXTRA))
        evals, evecs = sla.eigsh(self.A, k=m, sigma=self.sigma, OPinv=op, tol=tol, ncv=ncv, v0=v0)
        order = np.argsort(evals)
        return evals[order], evecs[:, order]


def _trusted_count(evals: np.ndarray) -> int:
    """Number of leading eigenvalues that precede the last cluster (so the cluster is not split)."""
    gaps = np.flatnonzero(np.diff(evals) > EIGSH_CLUSTER_RTOL * max(abs(evals[-1]), 1e-300))
    return int(gaps[-1]) + 1 if gaps.size else 0


def _sliced_eigsh(A, k: int, scale: float, slice_size: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Lowest ``k`` eigenpairs by consecutive, verified shift-invert slices (spectrum slicing).

    All eigenvalues below a boundary ``b`` (initially -inf) are known. A slice asks ARPACK for the ``m``
    eigenvalues nearest to a shift placed above ``b`` (the first one just below 0; the next ones from the
    density of eigenvalues so far, which is almost constant on a surface by Weyl's law, so that the slice
    reaches back below ``b``). Of the result it keeps the eigenvalues in ``[b, b')``, where ``b'`` is the
    midpoint of the gap before the last cluster (a multiple eigenvalue is never split between slices), and
    checks with Sylvester's law of inertia (an LDL^T of ``A - b' I``) that exactly ``count + kept``
    eigenvalues lie below ``b'``. Single-vector Lanczos finds only one direction of an exactly multiple
    eigenvalue (symmetric meshes: spheres, tori), so missing eigenvalues are searched again orthogonally to
    the found ones (deflation) until the count is right. A slice that does not reach back below ``b`` is
    retried with its shift closer to ``b`` and more pairs.
    """
    n = A.shape[0]
    rng = np.random.default_rng(EIGSH_SEED)
    vals, vecs = [], []
    count, bound, density = 0, -np.inf, None
    while count < k:
        need = k - count
        overlap = int(np.ceil(EIGSH_SLICE_OVERLAP * slice_size)) if count else 0
        # Take the rest in one slice when it is at most 1.5 slices (plus a margin so that the k-th eigenvalue
        # is not in the dropped last cluster), else one full slice.
        wanted = need + overlap + max(EIGSH_SLICE_MARGIN, int(np.ceil(EIGSH_SLICE_OVERLAP * need)))
        m = min(wanted if wanted <= 1.5 * slice_size else slice_size, n - 1)
        offset = None if count == 0 else (0.5 * m - overlap) / density
        for _ in range(EIGSH_SLICE_RETRIES):
            sigma = -EIGSH_SHIFT_REL * scale if count == 0 else bound + offset
            shift_invert = _ShiftInvert(A, sigma)
            evals, evecs = shift_invert.nearest(m, tol, rng.standard_normal(n))
            reaches_back = count == 0 or evals[0] < bound
            if reaches_back and np.count_nonzero(evals[: _trusted_count(evals)] >= bound):
                break
            if not reaches_back:
                offset *= 0.5  # the spectrum just above b is sparser than expected: move the shift closer
            m = min(int(1.5 * m) + 1, n - 1)  # (and when all new eigenvalues were in the last cluster)
        else:
            raise _SliceError(f"no spectral slice reached back below {bound:.4g}")
        for _ in range(EIGSH_DEFLATION_ROUNDS):
            top = _trusted_count(evals)
            new = np.flatnonzero(evals >= bound)
            new = new[new < top]
            new_bound = 0.5 * (evals[top - 1] + evals[top])
            missing = _count_below(A, new_bound) - (count + new.size)
            if missing == 0:
                break
            if missing < 0 or evals.shape[0] >= n - 1:
                raise _SliceError(f"inconsistent eigenvalue count in the slice above {bound:.4g}")
            more_vals, more_vecs = shift_invert.nearest(
                missing + EIGSH_SLICE_MARGIN, tol, rng.standard_normal(n), known=evecs
            )
            order = np.argsort(np.r_[evals, more_vals], kind="stable")
            evals = np.r_[evals, more_vals][order]
            evecs = np.hstack([evecs, more_vecs])[:, order]
        else:
            raise _SliceError(f"eigenvalues above {bound:.4g} still missing after deflation")
        vals.append(evals[new])
        vecs.append(evecs[:, new])
        count += new.size
        density = new.size / max(new_bound - max(bound, 0.0), 1e-300)
        bound = new_bound
    return np.concatenate(vals)[:k], np.concatenate(vecs, axis=1)[:, :k]


def _max_residual(A, evals: np.ndarray, evecs: np.ndarray) -> float:
    """max_j ||A psi_j - lambda_j psi_j||_2."""
    r = A @ evecs - evecs * evals[None, :]
    return float(np.sqrt((r * r).sum(axis=0)).max())


def _set_component_indicators(L_k, m_k: np.ndarray, evals: np.ndarray, phi: np.ndarray, scale: float) -> int:
    """Replace the kernel eigenvectors by normalized component indicators (in place); return their count."""
    off = sp.csr_matrix(L_k - sp.diags(L_k.diagonal()))
    off.eliminate_zeros()
    n_comp, labels = connected_components(off, directed=False)
    n_zero = min(n_comp, evals.shape[0])
    if evals[n_zero - 1] > ZERO_EVAL_RTOL * scale:
        raise NumericalError(
            f"expected {n_comp} zero eigenvalues (one per connected component), got eigenvalue "
            f"{evals[n_zero - 1]:.3g} at index {n_zero - 1}"
        )
    areas = np.bincount(labels, weights=m_k, minlength=n_comp)
    first_vertex = np.full(n_comp, labels.shape[0])
    np.minimum.at(first_vertex, labels, np.arange(labels.shape[0]))
    # Areas equal up to round-off (e.g. translated copies) count as ties.
    area_key = np.round(areas / areas.max(), AREA_TIE_DECIMALS)
    order = np.lexsort((first_vertex, -area_key))[:n_zero]
    for j, comp in enumerate(order):
        phi[:, j] = (labels == comp) / np.sqrt(areas[comp])
    evals[:n_zero] = 0.0
    return n_zero


def _m_orthonormalize(phi: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Return ``phi`` made ``diag(m)``-orthonormal (Cholesky of the Gram matrix) if it drifted."""
    gram = phi.T @ (m[:, None] * phi)
    if np.abs(gram - np.eye(gram.shape[0])).max() <= ORTHONORMALITY_TOL:
        return phi
    try:
        R = scipy.linalg.cholesky(gram, lower=False)
    except np.linalg.LinAlgError as err:
        raise NumericalError("eigenvectors are linearly dependent; the eigen solve failed") from err
    # phi R^-1: a triangular correction that leaves each column's leading part (and its sign) unchanged.
    return scipy.linalg.solve_triangular(R, phi.T, trans="T", lower=False).T


def _fix_signs(phi: np.ndarray, m: np.ndarray) -> None:
    """Flip the columns of ``phi`` in place by the documented sign rule (see :func:`eigenbasis`)."""
    if phi.shape[1] == 0:
        return
    cube = phi * phi * phi
    skew = m @ cube
    magnitude = m @ np.abs(cube)
    largest = phi[np.abs(phi).argmax(axis=0), np.arange(phi.shape[1])]
    sign = np.where(np.abs(skew) > SIGN_SKEW_RTOL * magnitude, np.sign(skew), np.sign(largest))
    sign[sign == 0] = 1.0
    phi *= sign[None, :]


def _removed_rows(faces: np.ndarray, keep: np.ndarray, evecs: np.ndarray) -> np.ndarray:
    """Rows for removed vertices: mean of their kept one-ring neighbours' rows, else the mean kept row."""
    n = keep.shape[0]
    i = faces[:, [0, 0, 1, 1, 2, 2]].ravel()
    j = faces[:, [1, 2, 0, 2, 0, 1]].ravel()
    adj = sp.csr_matrix((np.ones(i.shape[0]), (i, j)), shape=(n, n))
    adj.data[:] = 1.0  # duplicates summed by the constructor: back to a 0/1 pattern
    removed = np.flatnonzero(~keep)
    to_kept = adj[removed][:, np.flatnonzero(keep)]
    counts = np.asarray(to_kept.sum(axis=1)).ravel()
    rows = to_kept @ evecs[keep]
    has = counts > 0
    rows[has] /= counts[has, None]
    rows[~has] = evecs[keep].mean(axis=0)
    return rows
