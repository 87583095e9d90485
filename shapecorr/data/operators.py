"""Per-shape derived quantities ("shape operators") and their on-disk caching.

Everything a method needs from a mesh beyond its vertices and faces — the Laplace–Beltrami eigenbasis, the
SHOT / WKS / HKS descriptors, all-pairs geodesic distances — is computed here once per (mesh content,
parameters, operator version) and stored in the :class:`~shapecorr.data.cache.ShapeCache`. Each quantity is
a separate cache entry, so changing e.g. the number of WKS energies does not recompute the eigenbasis.

Conventions: eigenvalues are in shapecorr's standard scale (½(cot a + cot b) stiffness; the original Deep
Shells/Smooth Shells scale is 2x, see :mod:`shapecorr.geometry.laplace_beltrami`); descriptors are computed on the
normalized shape (the normalization is part of the cached mesh content, so a different normalization is a
different entry).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from shapecorr.data.cache import ShapeCache
from shapecorr.errors import ConfigError

#: Bump an entry when the code computing that quantity changes its result: old cache entries become stale.
OPERATOR_VERSIONS = {"eigenbasis": 1, "shot": 1, "wks": 1, "hks": 1, "geodesics": 1, "geodesics_from": 1}

KNOWN_DESCRIPTORS = ("shot", "wks", "hks")


@dataclass(frozen=True)
class OperatorConfig:
    """Which per-shape quantities to compute, and their parameters.

    Attributes
    ----------
    n_eig
        Number of Laplace–Beltrami eigenpairs (Deep Shells: 200 for the features, up to 500 for the
        refinement; DiffusionNet/G-MSM: 128).
    laplacian
        ``"cotan"`` (libigl) or ``"robust"`` (robust-laplacian, for non-manifold meshes).
    descriptors
        Subset of ``("shot", "wks", "hks")`` to compute for every shape.
    shot_radius_factor
        SHOT support radius as a fraction of sqrt(total area) (Deep Shells: 0.05).
    n_wks, n_hks
        Number of WKS energies / HKS times (Smooth Shells: 100 HKS times).
    n_descriptor_eig
        Eigenpairs used by WKS/HKS (at most ``n_eig``; Smooth Shells: 200).
    """

    n_eig: int = 200
    laplacian: str = "cotan"
    descriptors: tuple[str, ...] = ()
    shot_radius_factor: float = 0.05
    n_wks: int = 100
    n_hks: int = 100
    n_descriptor_eig: int = 200

    def __post_init__(self):
        object.__setattr__(self, "descriptors", tuple(self.descriptors))
        unknown = set(self.descriptors) - set(KNOWN_DESCRIPTORS)
        if unknown:
            raise ConfigError(f"unknown descriptor(s) {sorted(unknown)}; choose from {KNOWN_DESCRIPTORS}")
        if self.n_eig < 1:
            raise ConfigError(f"n_eig must be >= 1, got {self.n_eig}")
        if self.laplacian not in ("cotan", "robust"):
            raise ConfigError(f"laplacian must be 'cotan' or 'robust', got {self.laplacian!r}")


def _eigen_params(cfg: OperatorConfig, k: int) -> dict:
    return {"k": int(k), "laplacian": cfg.laplacian}


def eigenbasis_cached(cache: ShapeCache, verts, faces, cfg: OperatorConfig, k: int | None = None) -> dict:
    """``{"evals": (k,), "evecs": (n, k), "mass": (n,)}`` from the cache, computing it on a miss."""
    from shapecorr.geometry.laplace_beltrami import eigenbasis

    k = cfg.n_eig if k is None else k

    def compute():
        evals, evecs, mass = eigenbasis(verts, faces, k, method=cfg.laplacian)
        return {"evals": evals, "evecs": evecs, "mass": mass}

    return cache.get_or_compute("eigenbasis", verts, faces, _eigen_params(cfg, k), OPERATOR_VERSIONS["eigenbasis"], compute)


def descriptor_cached(cache: ShapeCache, verts, faces, cfg: OperatorConfig, name: str) -> np.ndarray:
    """One descriptor ``(n, c)`` from the cache, computing it (and the eigenbasis it needs) on a miss."""
    if name == "shot":
        from shapecorr.geometry.shot_descriptor import shot

        params = {"radius_factor": cfg.shot_radius_factor}

        def compute():
            return {"shot": shot(verts, faces, radius_fraction=cfg.shot_radius_factor)}

    elif name in ("wks", "hks"):
        from shapecorr.geometry import descriptors

        k = min(cfg.n_descriptor_eig, cfg.n_eig)
        count = cfg.n_wks if name == "wks" else cfg.n_hks
        params = {"count": count, **_eigen_params(cfg, k)}

        def compute():
            eig = eigenbasis_cached(cache, verts, faces, cfg)
            evals, evecs = eig["evals"][:k].astype(np.float64), eig["evecs"][:, :k].astype(np.float64)
            if name == "wks":
                return {name: descriptors.wks(evals, evecs, n_energies=count)}
            return {name: descriptors.hks(evals, evecs, n_times=count)}

    else:
        raise ConfigError(f"unknown descriptor {name!r}; choose from {KNOWN_DESCRIPTORS}")
    return cache.get_or_compute(name, verts, faces, params, OPERATOR_VERSIONS[name], compute)[name]


def geodesics_cached(cache: ShapeCache, verts, faces, method: str = "heat") -> np.ndarray:
    """All-pairs geodesic distance matrix ``(n, n)`` from the cache, computing it on a miss."""
    from shapecorr.geometry.geodesics import geodesic_distances

    def compute():
        return {"geodesics": geodesic_distances(verts, faces, method=method)}

    return cache.get_or_compute(
        "geodesics", verts, faces, {"method": method}, OPERATOR_VERSIONS["geodesics"], compute
    )["geodesics"]


#: Stored in place of ``inf`` (no path: another connected component) in cached distance rows; the cache
#: refuses non-finite values and a geodesic distance is never negative.
UNREACHABLE = -1.0


def geodesics_from_cached(cache: ShapeCache, verts, faces, sources, method: str = "heat"):
    """Geodesic distances from ``sources (s,) int`` (e.g. a shape's ground-truth points), cached.

    Returns
    -------
    :class:`~shapecorr.geometry.geodesics.SourceDistances`
        Rows ``(u, n)`` float32 for the ``u`` unique sources (``inf`` across connected components).
    """
    import hashlib

    from shapecorr.geometry.geodesics import SourceDistances, geodesic_distances_from

    unique = np.unique(np.asarray(sources, dtype=np.int64))
    params = {"method": method, "n_sources": int(unique.size),
              "sources_sha256": hashlib.sha256(unique.tobytes()).hexdigest()}

    def compute():
        rows = geodesic_distances_from(verts, faces, unique, method=method)
        rows[~np.isfinite(rows)] = UNREACHABLE
        return {"sources": unique, "rows": rows}

    hit = cache.get_or_compute("geodesics_from", verts, faces, params, OPERATOR_VERSIONS["geodesics_from"], compute)
    rows = hit["rows"]
    if (rows < 0).any():
        rows = rows.copy()
        rows[rows < 0] = np.inf
    return SourceDistances(hit["sources"].astype(np.int64), rows)


def compute_operators(cache: ShapeCache, verts, faces, cfg: OperatorConfig) -> dict[str, np.ndarray]:
    """All quantities requested by ``cfg`` for one shape (cached).

    Returns
    -------
    dict with ``evals (k,)``, ``evecs (n, k)``, ``mass (n,)`` and one ``(n, c)`` array per descriptor.
    """
    out = dict(eigenbasis_cached(cache, verts, faces, cfg))
    for name in cfg.descriptors:
        out[name] = descriptor_cached(cache, verts, faces, cfg, name)
    return out


def config_dict(cfg: OperatorConfig) -> dict:
    """Plain-dict view (for logging / hyperparameter records)."""
    return asdict(cfg)


__all__ = [
    "OPERATOR_VERSIONS",
    "OperatorConfig",
    "compute_operators",
    "config_dict",
    "descriptor_cached",
    "eigenbasis_cached",
    "geodesics_cached",
    "geodesics_from_cached",
]
