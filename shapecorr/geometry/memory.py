"""Memory estimates of per-shape precomputation, checked before large allocations.

The estimates are deliberately simple upper bounds (bytes per vertex and per stored value) so that a run
stops with a message naming the option to change instead of being killed by the kernel's OOM killer, and so
that parallel preparation can pick a number of worker processes that fits in the available memory.
"""

from __future__ import annotations

import os

from shapecorr.errors import ConfigError

#: Working memory of one eigenbasis solve per vertex and eigenpair: the float64 eigenvectors plus ARPACK's
#: Lanczos basis (about 2k vectors of length n) and the factorization; 3 x 8 bytes per entry, rounded up.
EIGEN_BYTES_PER_ENTRY = 24
#: Working memory per vertex of loading and validating a mesh and computing descriptors (SHOT neighbourhoods,
#: normals, ...): a project estimate (a few dozen float64 values per vertex for the mesh, its sparse Laplacian
#: and adjacency), generous on purpose.
BASE_BYTES_PER_VERTEX = 4096
#: Fraction of the available memory a preparation plans to use (the rest is left to the OS and this process).
MEMORY_HEADROOM = 0.8
GIB = 1024**3
#: Bytes per stored distance of :func:`shapecorr.geometry.geodesics.geodesic_distances_from` (float32 rows).
DISTANCE_BYTES = 4
#: Rough working memory of one heat-method solver per vertex (two sparse Cholesky factors of the intrinsic
#: Delaunay cover plus the mesh data structures of potpourri3d): 2.3 kB/vertex measured (peak RSS) on a 5k-vertex
#: FAUST_r shape; rounded up.
HEAT_SOLVER_BYTES_PER_VERTEX = 4096


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` (Linux), or None where it cannot be read."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def source_distance_bytes(n_sources: int, n_verts: int) -> int:
    """Estimated peak bytes of :func:`shapecorr.geometry.geodesics.geodesic_distances_from`.

    The float32 rows plus the working memory of one heat solver.
    """
    return int(n_sources) * int(n_verts) * DISTANCE_BYTES + int(n_verts) * HEAT_SOLVER_BYTES_PER_VERTEX


def prepare_bytes(n_verts: int, n_eig: int = 0, n_geodesic_sources: int = 0) -> int:
    """Estimated peak bytes of preparing one shape of ``n_verts`` vertices.

    Parameters
    ----------
    n_verts : int
    n_eig : int
        Eigenpairs computed (0: none).
    n_geodesic_sources : int
        Sources of the cached geodesic rows (0: no geodesics; ``n_verts`` for a full matrix).
    """
    total = n_verts * BASE_BYTES_PER_VERTEX + n_verts * n_eig * EIGEN_BYTES_PER_ENTRY
    if n_geodesic_sources:
        total += source_distance_bytes(n_geodesic_sources, n_verts)
    return int(total)


def workers_for_memory(estimates: list[int], requested: int | None, what: str, option: str,
                       available: int | None = None) -> int:
    """Number of worker processes for jobs with the given peak-byte ``estimates``.

    ``requested`` (None: the CPU count) is lowered so that that many of the largest jobs fit in
    :data:`MEMORY_HEADROOM` of the available memory; a single job that does not fit raises.

    Raises
    ------
    ConfigError
        The largest job alone needs more than the available memory; the message names ``option``.
    """
    cpus = os.cpu_count() or 1
    workers = max(1, min(cpus if requested is None else int(requested), max(len(estimates), 1)))
    available = available_memory_bytes() if available is None else available
    if available is None or not estimates:
        return workers
    budget = MEMORY_HEADROOM * available
    largest = max(estimates)
    if largest > budget:
        raise ConfigError(
            f"{what} needs about {largest / GIB:.1f} GiB but only {available / GIB:.1f} GiB of memory is "
            f"available; {option}"
        )
    return max(1, min(workers, int(budget // max(largest, 1))))


def check_fits(n_bytes: int, what: str, option: str, available: int | None = None) -> None:
    """Raise :class:`ConfigError` naming ``option`` when ``n_bytes`` exceed the headroom of the available memory."""
    available = available_memory_bytes() if available is None else available
    if available is not None and n_bytes > MEMORY_HEADROOM * available:
        raise ConfigError(
            f"{what} needs about {n_bytes / GIB:.1f} GiB but only {available / GIB:.1f} GiB of memory is "
            f"available; {option}"
        )
