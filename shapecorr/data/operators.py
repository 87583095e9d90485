"""Per-shape operators: a registry of named computations on a mesh, and their on-disk caching.

Everything a method needs from a mesh beyond its vertices and faces — the Laplace–Beltrami eigenbasis, the
SHOT / WKS / HKS descriptors, all-pairs geodesic distances, sparse differential operators — is an *operator*:
a named computation with parameters, registered once in :data:`REGISTRY` (:func:`register_operator`), computed
once per (mesh content, parameters, operator version) and stored in the :class:`~shapecorr.data.cache.ShapeCache`.

Requests. Models, backbones and matchers declare what they need as an *operator request*
``{operator name: {parameter: value}}`` (their ``required_operators``), e.g.
``{"eigenbasis": {"k": 200}, "shot": {}}``; an empty dict takes the operator's defaults. Two requests for the
same operator are combined by the operator's merge rule (:func:`merge_requests`; the eigenbasis keeps the
larger ``k``, other parameters must agree). A :class:`ShapeSample` then carries
``sample.operators[name] -> {array name: tensor}``.

Data-wide settings and per-dataset parameters (:class:`OperatorConfig`, the data config's ``operators`` node):

* ``laplacian`` (``cotan`` | ``robust``) applies to every operator that has a ``laplacian`` parameter
  (eigenbasis, WKS, HKS);
* ``n_eig``: the eigenpairs every shape gets (``request.eigenbasis.k``; default 200);
* ``request``: further operators computed for every shape whatever the model, e.g. ``{shot: {}, wks: {}}``;
* ``params``: this dataset's parameter defaults per operator, e.g. ``{shot: {radius_factor: 0.25}}`` for tiny
  meshes; a model's request inherits them unless it sets the parameter itself.

Resolution (:meth:`OperatorConfig.resolve`): operator defaults < data-wide settings < dataset ``params`` <
the request's own values; then each operator's ``resolve`` hook (WKS/HKS: ``k`` unset = at most the requested
eigenbasis size, 200 by default).

Reuse. A cached entry with other parameters answers a request when the operator says so (``satisfies``): an
eigenbasis with k' >= k eigenpairs (same Laplacian) is truncated to k (``restrict``) instead of recomputed. The
exact entry is preferred; among larger ones the smallest.

Cache keys are ``(name, mesh content hash, resolved parameters, version)``; the parameters of the built-in
operators are eigenbasis ``{k, laplacian}``, shot ``{radius_factor}``, wks/hks ``{count, k, laplacian}``,
geodesics ``{method}``.

Adding an operator (e.g. DiffusionNet's sparse gradient operators) is one call::

    register_operator(
        "gradients", defaults={"k": 128, "laplacian": "cotan"}, version=1,
        compute=lambda ctx, p: {"grad_x": ..., "grad_y": ...},   # numpy arrays or scipy.sparse matrices
    )

``compute(ctx, params)`` receives an :class:`OperatorContext` (``ctx.verts (n, 3)`` float64, ``ctx.faces (f, 3)``
int64, ``ctx.get(name, **params)`` for operators it builds on, through the cache) and the resolved parameters.

Conventions: eigenvalues are in shapecorr's standard scale (½(cot a + cot b) stiffness; the original Deep
Shells/Smooth Shells scale is 2x, see :mod:`shapecorr.geometry.laplace_beltrami`); descriptors are computed on
the normalized shape (the normalization is part of the cached mesh content, so a different normalization is a
different entry).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shapecorr.data.cache import CacheKey, ShapeCache, as_stored, content_hash
from shapecorr.errors import ConfigError

#: An operator request: operator name -> parameters (missing parameters take the defaults).
OperatorRequest = Mapping[str, Mapping[str, Any]]
#: Laplacian discretizations (``shapecorr.geometry.laplace_beltrami.laplacian``).
LAPLACIANS = ("cotan", "robust")
#: Data-wide settings: applied to every operator that has a parameter of that name.
DATA_SETTINGS = ("laplacian",)
#: Eigenpairs requested for every shape by default (Deep Shells' filters use 200; models raise it as needed).
DEFAULT_N_EIG = 200
#: Eigenpairs used by WKS/HKS by default, at most the requested eigenbasis (Smooth Shells: 200).
DEFAULT_DESCRIPTOR_EIG = 200
#: SHOT support radius as a fraction of sqrt(total area) (Deep Shells' SHOT setting, docs/deep_shells.md).
DEFAULT_SHOT_RADIUS_FACTOR = 0.05
#: WKS energies / HKS times (Aubry et al. 2011 reference implementation; Smooth Shells: 100 HKS times).
DEFAULT_DESCRIPTOR_COUNT = 100


def _unchanged(arrays: dict, params: Mapping[str, Any]) -> dict:
    return arrays


@dataclass(frozen=True)
class Operator:
    """A registered operator (see the module docstring; build with :func:`register_operator`).

    Attributes
    ----------
    name
        Registry and cache name.
    defaults
        Every parameter with its default value (the cache key holds all of them).
    version
        Bump when the computation's result changes: cached entries of another version are recomputed.
    compute
        ``compute(ctx, params) -> {array name: numpy array or scipy.sparse matrix}``.
    merge
        ``merge(a, b) -> params``: one request satisfying two (partial) requests; raises ConfigError if they
        cannot be combined.
    satisfies
        ``satisfies(stored, requested) -> bool``: whether a cached entry with other parameters answers a request
        (after ``restrict``); ``None``: only the exact parameters do.
    restrict
        ``restrict(arrays, requested) -> arrays``: the requested part of a satisfying entry (e.g. truncation).
    preference
        ``preference(stored params)``: among several satisfying entries the smallest value is used.
    resolve
        ``resolve(params, request) -> params``: fills parameters that depend on the rest of the resolved
        request (e.g. WKS's eigenpair count).
    feature
        A per-vertex descriptor ``arrays[name] (n, c)``, also exposed as ``ShapeSample.features[name]``.
    keep_float64
        Store float64 arrays as float64 (default: float32).
    """

    name: str
    defaults: Mapping[str, Any]
    version: int | str
    compute: Callable[[OperatorContext, dict], Mapping[str, Any]]
    merge: Callable[[Mapping[str, Any], Mapping[str, Any]], dict]
    satisfies: Callable[[Mapping[str, Any], Mapping[str, Any]], bool] | None = None
    restrict: Callable[[dict, Mapping[str, Any]], dict] = _unchanged
    preference: Callable[[Mapping[str, Any]], Any] | None = None
    resolve: Callable[[dict, Mapping[str, Mapping[str, Any]]], dict] | None = None
    feature: bool = False
    keep_float64: bool = False

    def check_params(self, params: Mapping[str, Any], where: str = "") -> None:
        """Raise ConfigError for parameters the operator does not have."""
        unknown = sorted(set(params) - set(self.defaults))
        if unknown:
            raise ConfigError(f"{where}operator {self.name!r} has no parameter(s) {unknown}; its parameters: "
                              f"{sorted(self.defaults)}")


#: The operators by name (:func:`register_operator` adds to it).
REGISTRY: dict[str, Operator] = {}


def merge_by(**rules: Callable[[Any, Any], Any]) -> Callable[[Mapping[str, Any], Mapping[str, Any]], dict]:
    """A merge rule for two parameter requests.

    Parameters named in ``rules`` combine with their function (e.g. ``k=max``), every other parameter present in
    both requests must be equal; a parameter in one request only is taken as is.
    """

    def merge(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict:
        out = dict(a)
        for key, value in b.items():
            if key not in out or out[key] == value:
                out[key] = value
            elif key in rules:
                out[key] = rules[key](out[key], value)
            else:
                raise ConfigError(f"two requests for the same operator disagree on {key!r}: {out[key]!r} vs "
                                  f"{value!r}")
        return out

    return merge


def at_least(*names: str) -> Callable[[Mapping[str, Any], Mapping[str, Any]], bool]:
    """A ``satisfies`` rule: stored values of ``names`` at least the requested ones, all others equal."""

    def satisfies(stored: Mapping[str, Any], requested: Mapping[str, Any]) -> bool:
        if set(stored) != set(requested):
            return False
        return all(stored[k] >= requested[k] if k in names else stored[k] == requested[k] for k in requested)

    return satisfies


def register_operator(
    name: str,
    *,
    defaults: Mapping[str, Any],
    version: int | str,
    compute: Callable[[OperatorContext, dict], Mapping[str, Any]],
    merge: Callable[[Mapping[str, Any], Mapping[str, Any]], dict] | None = None,
    satisfies: Callable[[Mapping[str, Any], Mapping[str, Any]], bool] | None = None,
    restrict: Callable[[dict, Mapping[str, Any]], dict] | None = None,
    preference: Callable[[Mapping[str, Any]], Any] | None = None,
    resolve: Callable[[dict, Mapping[str, Mapping[str, Any]]], dict] | None = None,
    feature: bool = False,
    keep_float64: bool = False,
    replace: bool = False,
) -> Operator:
    """Add an operator to :data:`REGISTRY` (see :class:`Operator` for the arguments).

    ``merge`` defaults to :func:`merge_by` with no rule (equal parameters only). ``replace=True`` allows
    re-registering a name (otherwise a ConfigError, so two modules cannot silently claim one name).
    """
    if name in REGISTRY and not replace:
        raise ConfigError(f"operator {name!r} is already registered")
    CacheKey(name, "0" * 64, dict(defaults), version)  # validates the name, the defaults' JSON form, the version
    op = Operator(name=name, defaults=dict(defaults), version=version, compute=compute,
                  merge=merge or merge_by(), satisfies=satisfies, restrict=restrict or _unchanged,
                  preference=preference, resolve=resolve, feature=feature, keep_float64=keep_float64)
    REGISTRY[name] = op
    return op


def get_operator(name: str, where: str = "") -> Operator:
    """The registered operator ``name`` (ConfigError listing the known ones otherwise, prefixed by ``where``)."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise ConfigError(f"{where}unknown operator {name!r}; registered: {sorted(REGISTRY)}") from None


def operator_names() -> tuple[str, ...]:
    """Names of the registered operators (registration order)."""
    return tuple(REGISTRY)


class _Versions(Mapping):
    """Live view ``{operator name: version}`` of the registry."""

    def __getitem__(self, name: str):
        return get_operator(name).version

    def __iter__(self) -> Iterator[str]:
        return iter(REGISTRY)

    def __len__(self) -> int:
        return len(REGISTRY)


#: ``{name: version}`` of the registered operators (bump an operator's ``version`` when its result changes).
OPERATOR_VERSIONS: Mapping[str, int | str] = _Versions()


def plain_container(value: Any) -> Any:
    """OmegaConf containers -> Python containers (no-op on plain values)."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - hydra is a dependency
        return value
    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    return value


def as_request(request: OperatorRequest | None, where: str = "") -> dict[str, dict[str, Any]]:
    """``request`` checked (registered names, known parameters) as a plain ``{name: {param: value}}`` dict."""
    request = plain_container(request) or {}
    if not isinstance(request, Mapping):
        raise ConfigError(f"{where}an operator request must be a mapping {{name: {{param: value}}}}, got {request!r}")
    out = {}
    for name, params in request.items():
        op = get_operator(name, where)
        params = plain_container(params) or {}
        if not isinstance(params, Mapping):
            raise ConfigError(f"{where}parameters of operator {name!r} must be a mapping, got {params!r}")
        op.check_params(params, where)
        out[str(name)] = dict(params)
    return out


def merge_requests(*requests: OperatorRequest | None) -> dict[str, dict[str, Any]]:
    """One request satisfying all of ``requests`` (each operator's merge rule per name).

    Example: ``merge_requests({"eigenbasis": {"k": 200}, "shot": {}}, {"eigenbasis": {"k": 508}})`` is
    ``{"eigenbasis": {"k": 508}, "shot": {}}``.
    """
    out: dict[str, dict[str, Any]] = {}
    for request in requests:
        for name, params in as_request(request).items():
            out[name] = get_operator(name).merge(out[name], params) if name in out else dict(params)
    return out


def _eigenbasis_request(n_eig: Any) -> dict[str, dict]:
    """The request of the ``n_eig`` setting (``{}`` when it is None)."""
    if n_eig is None:
        return {}
    k = int(n_eig)
    if k < 1:
        raise ConfigError(f"n_eig must be >= 1, got {k}")
    return {"eigenbasis": {"k": k}}


#: Keys that are not ``data.operators`` options, with the option that says the same.
_NOT_OPTIONS = {
    "descriptors": "request: {<name>: {}} (e.g. request: {shot: {}, wks: {}})",
    "shot_radius_factor": "params: {shot: {radius_factor: ...}}",
    "n_wks": "params: {wks: {count: ...}}",
    "n_hks": "params: {hks: {count: ...}}",
    "n_descriptor_eig": "params: {wks: {k: ...}, hks: {k: ...}}",
}


def _unknown_options(keys: Any, where: str) -> ConfigError:
    """The error for option names ``keys`` that ``data.operators`` (or ``with_request``) does not take."""
    hints = [f"{k}: use {_NOT_OPTIONS[k]}" for k in keys if k in _NOT_OPTIONS]
    return ConfigError(f"unknown {where} option(s) {sorted(keys)}; allowed: request, params, n_eig, "
                       f"{', '.join(DATA_SETTINGS)}" + ("".join(f"; {h}" for h in hints)))


@dataclass(frozen=True, init=False)
class OperatorConfig:
    """The data side of the operators: what every shape gets, this dataset's parameters, data-wide settings.

    Parameters
    ----------
    request
        Operators computed for every shape (default ``{"eigenbasis": {"k": 200}}``); models add theirs
        (:meth:`with_request`).
    params
        This dataset's parameter defaults per operator (they apply only to operators that are requested).
    laplacian
        ``"cotan"`` (libigl) or ``"robust"`` (robust-laplacian, for non-manifold meshes): every operator built
        on the Laplacian.
    n_eig
        Eigenpairs every shape gets (``request.eigenbasis.k``); replaces the default eigenbasis size.

    Raises
    ------
    ConfigError
        An unknown option (the message names the option that says the same, where there is one).
    """

    request: Mapping[str, Mapping[str, Any]]
    params: Mapping[str, Mapping[str, Any]]
    laplacian: str

    def __init__(self, request: OperatorRequest | None = None, params: OperatorRequest | None = None,
                 laplacian: str = "cotan", n_eig: int | None = None, **unknown: Any):
        if unknown:
            raise _unknown_options(unknown, "data.operators")
        if laplacian not in LAPLACIANS:
            raise ConfigError(f"laplacian must be one of {LAPLACIANS}, got {laplacian!r}")
        base = {"eigenbasis": {"k": DEFAULT_N_EIG}} if request is None and n_eig is None else {}
        merged_params = {name: dict(values) for name, values in as_request(params, "data.operators.params: ").items()}
        object.__setattr__(self, "request", merge_requests(base, as_request(request, "data.operators.request: "),
                                                           _eigenbasis_request(n_eig)))
        object.__setattr__(self, "params", merged_params)
        object.__setattr__(self, "laplacian", str(laplacian))

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | OperatorConfig | None) -> OperatorConfig:
        """From a data config's ``operators`` node (a mapping, possibly OmegaConf), an OperatorConfig or None."""
        if isinstance(options, OperatorConfig):
            return options
        options = dict(plain_container(options) or {})
        return cls(**options)

    def with_request(self, request: OperatorRequest | None = None, **changes: Any) -> OperatorConfig:
        """A copy with ``request`` merged in.

        ``changes`` are further ``{name: params}`` requests, ``params`` (dataset parameter defaults, updated),
        data-wide settings (``laplacian``) or ``n_eig`` (then a lower bound on the eigenbasis size).
        """
        request = dict(as_request(request))
        extra_params = as_request(changes.pop("params", None), "params: ")
        settings = {k: changes.pop(k) for k in DATA_SETTINGS if k in changes}
        n_eig_request = _eigenbasis_request(changes.pop("n_eig", None))
        not_operators = [k for k in changes if k in _NOT_OPTIONS]
        if not_operators:
            raise _unknown_options(not_operators, "with_request")
        params = {name: dict(values) for name, values in self.params.items()}
        for name, values in extra_params.items():
            params.setdefault(name, {}).update(values)
        merged = merge_requests(self.request, request, as_request(changes), n_eig_request)
        return OperatorConfig(request=merged, params=params, laplacian=settings.get("laplacian", self.laplacian))

    def resolve(self, request: OperatorRequest | None = None) -> dict[str, dict[str, Any]]:
        """Full parameters of every operator of ``self.request`` merged with ``request`` (see the module docstring)."""
        merged = merge_requests(self.request, request)
        settings = {"laplacian": self.laplacian}
        resolved = {}
        for name, values in merged.items():
            op = get_operator(name)
            full = dict(op.defaults)
            full.update({k: v for k, v in settings.items() if k in op.defaults})
            full.update(self.params.get(name, {}))
            full.update(values)
            resolved[name] = full
        for name, full in resolved.items():
            op = get_operator(name)
            if op.resolve is not None:
                resolved[name] = op.resolve(full, resolved)
        return resolved

    @property
    def n_eig(self) -> int | None:
        """Requested eigenpairs (``request["eigenbasis"]["k"]``; None without eigenbasis)."""
        eig = self.request.get("eigenbasis")
        return None if eig is None else int(eig.get("k", get_operator("eigenbasis").defaults["k"]))

    @property
    def descriptors(self) -> tuple[str, ...]:
        """Requested descriptor operators (the names in ``request`` registered as descriptors)."""
        return tuple(name for name in self.request if get_operator(name).feature)

    def as_dict(self) -> dict[str, Any]:
        """Plain-dict view (for logging / hyperparameter records)."""
        return {"request": {k: dict(v) for k, v in self.request.items()},
                "params": {k: dict(v) for k, v in self.params.items()}, "laplacian": self.laplacian}


@dataclass
class OperatorContext:
    """What an operator's ``compute`` sees: the mesh and the cache (for the operators it builds on).

    Attributes
    ----------
    verts : (n, 3) float64
    faces : (f, 3) int64
    cache : ShapeCache
    """

    verts: np.ndarray
    faces: np.ndarray
    cache: ShapeCache
    _hash: str | None = field(default=None, repr=False)

    @property
    def content_hash(self) -> str:
        """SHA-256 of the mesh content (:func:`~shapecorr.data.cache.content_hash`), computed once."""
        if self._hash is None:
            self._hash = content_hash(self.verts, self.faces)
        return self._hash

    def get(self, name: str, **params: Any) -> dict[str, Any]:
        """Operator ``name`` with full parameters ``params`` (missing ones take the defaults), through the cache."""
        op = get_operator(name)
        op.check_params(params)
        return compute_operator(self.cache, self.verts, self.faces, name, {**op.defaults, **params}, _ctx=self)


def compute_operator(cache: ShapeCache, verts, faces, name: str, params: Mapping[str, Any],
                     _ctx: OperatorContext | None = None) -> dict[str, Any]:
    """Operator ``name`` of one mesh with fully resolved ``params``, through the cache.

    The exact cache entry, else a cached entry that satisfies the request (restricted), else computed and stored.

    Parameters
    ----------
    cache : ShapeCache
    verts : (n, 3) float array
    faces : (f, 3) int array
    name : str
        A registered operator.
    params : mapping
        All its parameters (:meth:`OperatorConfig.resolve`).

    Returns
    -------
    dict
        Array name -> numpy array (float32 unless the operator keeps float64) or ``scipy.sparse`` CSR/CSC array.
    """
    op = get_operator(name)
    params = dict(params)
    op.check_params(params)
    missing = sorted(set(op.defaults) - set(params))
    if missing:
        raise ConfigError(f"operator {name!r}: parameter(s) {missing} not resolved")
    ctx = _ctx or OperatorContext(np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64), cache)
    key = CacheKey(name, ctx.content_hash, params, op.version, op.keep_float64)
    hit = cache.get(key)
    if hit is not None:
        return hit
    if op.satisfies is not None:
        stored = cache.find(name, key.content_hash, lambda k: k.version == op.version and k.keep_float64 ==
                            op.keep_float64 and op.satisfies(k.params, key.params))
        if op.preference is not None:
            stored.sort(key=lambda k: op.preference(k.params))
        for candidate in stored:
            arrays = cache.get(candidate)
            if arrays is not None:
                return op.restrict(arrays, key.params)
    computed = op.compute(ctx, dict(key.params))
    if cache.writable:
        return cache.put(key, computed)
    return as_stored(key, computed)


def compute_operators(cache: ShapeCache, verts, faces, config: OperatorConfig | None = None,
                      request: OperatorRequest | None = None) -> dict[str, dict[str, Any]]:
    """Every operator of ``config`` (plus ``request``) for one shape, cached.

    Returns
    -------
    dict
        Operator name -> its arrays (see :func:`compute_operator`).
    """
    config = config or OperatorConfig()
    ctx = OperatorContext(np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64), cache)
    return {name: compute_operator(cache, ctx.verts, ctx.faces, name, params, _ctx=ctx)
            for name, params in config.resolve(request).items()}


def geodesics_cached(cache: ShapeCache, verts, faces, method: str = "heat") -> np.ndarray:
    """All-pairs geodesic distance matrix ``(n, n)`` float32 from the cache, computing it on a miss."""
    return compute_operator(cache, verts, faces, "geodesics", {"method": method})["geodesics"]


#: Version of the cached geodesic rows of :func:`geodesics_from_cached` (bump when their computation changes).
#: Not a registered operator: the rows depend on a shape's ground truth (the evaluation's sources), which no
#: model requests.
GEODESICS_FROM_VERSION = 1
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

    hit = cache.get_or_compute("geodesics_from", verts, faces, params, GEODESICS_FROM_VERSION, compute)
    rows = hit["rows"]
    if (rows < 0).any():
        rows = rows.copy()
        rows[rows < 0] = np.inf
    return SourceDistances(hit["sources"].astype(np.int64), rows)


# -- the built-in operators ---------------------------------------------------------------------------------

def _eigenbasis(ctx: OperatorContext, p: dict) -> dict:
    from shapecorr.geometry.laplace_beltrami import eigenbasis

    evals, evecs, mass = eigenbasis(ctx.verts, ctx.faces, int(p["k"]), method=p["laplacian"])
    return {"evals": evals, "evecs": evecs, "mass": mass}


def _truncate_eigenbasis(arrays: dict, p: Mapping[str, Any]) -> dict:
    k = int(p["k"])
    return {"evals": arrays["evals"][:k], "evecs": arrays["evecs"][:, :k], "mass": arrays["mass"]}


def _shot(ctx: OperatorContext, p: dict) -> dict:
    from shapecorr.geometry.shot_descriptor import shot

    return {"shot": shot(ctx.verts, ctx.faces, radius_fraction=p["radius_factor"])}


def _spectral_descriptor(kind: str) -> Callable[[OperatorContext, dict], dict]:
    def compute(ctx: OperatorContext, p: dict) -> dict:
        from shapecorr.geometry import descriptors

        k = int(p["k"])
        eig = ctx.get("eigenbasis", k=k, laplacian=p["laplacian"])
        evals, evecs = eig["evals"][:k].astype(np.float64), eig["evecs"][:, :k].astype(np.float64)
        if kind == "wks":
            return {"wks": descriptors.wks(evals, evecs, n_energies=int(p["count"]))}
        return {"hks": descriptors.hks(evals, evecs, n_times=int(p["count"]))}

    return compute


def _descriptor_eig(params: dict, request: Mapping[str, Mapping[str, Any]]) -> dict:
    """WKS/HKS ``k`` unset: :data:`DEFAULT_DESCRIPTOR_EIG`, at most the requested eigenbasis size."""
    if params.get("k") is None:
        k = DEFAULT_DESCRIPTOR_EIG
        if "eigenbasis" in request:
            k = min(k, int(request["eigenbasis"]["k"]))
        params = {**params, "k": int(k)}
    return params


def _geodesics(ctx: OperatorContext, p: dict) -> dict:
    from shapecorr.geometry.geodesics import geodesic_distances

    return {"geodesics": geodesic_distances(ctx.verts, ctx.faces, method=p["method"])}


register_operator(
    "eigenbasis", defaults={"k": DEFAULT_N_EIG, "laplacian": "cotan"}, version=1, compute=_eigenbasis,
    merge=merge_by(k=max), satisfies=at_least("k"), restrict=_truncate_eigenbasis, preference=lambda p: p["k"],
)
register_operator("shot", defaults={"radius_factor": DEFAULT_SHOT_RADIUS_FACTOR}, version=1, compute=_shot,
                  feature=True)
for _kind in ("wks", "hks"):
    register_operator(_kind, defaults={"count": DEFAULT_DESCRIPTOR_COUNT, "k": None, "laplacian": "cotan"}, version=1,
                      compute=_spectral_descriptor(_kind), resolve=_descriptor_eig, feature=True)
register_operator("geodesics", defaults={"method": "heat"}, version=1, compute=_geodesics)


#: Relative ridge of DiffusionNet's per-vertex gradient fit (``geometry.diffusion_operators.GRADIENT_RIDGE``,
#: docs/gmsm.md §2.1; the value is repeated here so that importing the registry does not import the geometry).
DEFAULT_GRADIENT_RIDGE = 1e-5


def _diffusion_gradients(ctx: OperatorContext, p: dict) -> dict:
    from shapecorr.geometry.diffusion_operators import diffusion_gradients

    return diffusion_gradients(ctx.verts, ctx.faces, ridge=float(p["ridge"]))


# DiffusionNet (docs/gmsm.md §2.1, §7): tangent frames (n, 3, 3) float32, grad_x / grad_y (n, n) sparse CSR.
register_operator("diffusion_gradients", defaults={"ridge": DEFAULT_GRADIENT_RIDGE}, version=1,
                  compute=_diffusion_gradients)


def feature_names() -> tuple[str, ...]:
    """Registered per-vertex descriptors (``ShapeSample.features``)."""
    return tuple(name for name, op in REGISTRY.items() if op.feature)


def required_request(matcher: Any) -> dict[str, dict[str, Any]]:
    """The operator request of a model or matcher: its ``required_operators`` (``{}`` when it has none), checked."""
    request = dict(plain_container(getattr(matcher, "required_operators", None)) or {})
    return as_request(request, f"{type(matcher).__name__}: ")


__all__ = [
    "DATA_SETTINGS",
    "OPERATOR_VERSIONS",
    "REGISTRY",
    "Operator",
    "OperatorConfig",
    "OperatorContext",
    "OperatorRequest",
    "as_request",
    "at_least",
    "compute_operator",
    "compute_operators",
    "feature_names",
    "geodesics_cached",
    "geodesics_from_cached",
    "get_operator",
    "merge_by",
    "merge_requests",
    "operator_names",
    "plain_container",
    "register_operator",
    "required_request",
]
