"""On-disk cache of quantities derived from a mesh (eigenbasis, descriptors, geodesics, operators).

An entry is identified by a :class:`CacheKey`: the name of the quantity (``"eigenbasis"``), the content hash
of the mesh it was computed from, the parameters of the computation and an operator version that the
computing module bumps whenever its output changes. Entries live in

    <root>/<name>/<content hash>/<key digest>.npz

Storage policy:

* ``.npz`` written with ``allow_pickle=False`` and read with ``allow_pickle=False``: only numeric arrays
  (bool, int, uint, float) and ``scipy.sparse`` matrices/arrays can be stored; nothing is ever unpickled. A
  sparse value ``name`` is stored as CSR (or CSC, when given as CSC) in the members
  ``__sparse__<name>__{data,indices,indptr,shape}`` (names users cannot give: theirs may not start with
  ``__``) and read back as a ``scipy.sparse.csr_array`` / ``csc_array``; the metadata lists it under
  ``sparse``.
* float64 arrays are stored as float32 (the compute precision is float64, the storage precision float32,
  as diffusion-net does) unless the key says ``keep_float64=True``; the flag is part of the key so a
  float32 entry never answers a float64 request. Other dtypes are stored unchanged. A miss returns the
  arrays exactly as they were stored, so a first run and a cached run see identical values.
* NaN/Inf are refused on write (:class:`~shapecorr.errors.NumericalError`) and treated as corruption
  on read.
* Each file carries its full key (canonical JSON, plus dtype and shape of every array) in a ``__meta__``
  uint8 member. An entry whose stored key differs from the requested one (a digest collision, a file
  copied by hand) is stale: it is ignored and rewritten.
* Writes are atomic: a uniquely named temp file in the same directory, flushed and fsync'ed, then
  ``os.replace``. A reader sees the previous entry or the new one, never a partial file; concurrent
  writers of the same entry each write their own temp file and the last rename wins. Temp files left by a
  crashed writer are never read and are removed once older than ``STALE_TEMP_SECONDS``.
* A corrupt entry (truncated or garbage zip, missing metadata or arrays, wrong dtype/shape, NaN) is
  reported with a :class:`CacheWarning`, recomputed and overwritten.
* ``writable=False`` (evaluation on a shared, read-only cache): a miss computes and returns the result
  without writing anything.

Upgrading entries (e.g. an eigenbasis with k' >= k serving a request for k) is left to the caller, who
knows which parameters are monotone (:mod:`shapecorr.data.operators` does it for the registered operators):
:meth:`ShapeCache.find` lists the stored keys of one quantity of one mesh that satisfy a predicate, then
:meth:`ShapeCache.get` loads the chosen one::

    keys = cache.find("eigenbasis", h, lambda key: key.version == V and key.params["k"] >= k)
    if keys:
        best = min(keys, key=lambda key: key.params["k"])
        evecs = cache.get(best)["evecs"][:, :k]
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
import uuid
import warnings
import zipfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import scipy.sparse as sp

from shapecorr.errors import CacheError, NumericalError
from shapecorr.geometry.mesh import as_numpy

#: Environment variable naming the cache root.
CACHE_ENV_VAR = "SHAPECORR_CACHE"
#: Cache root when the environment variable is unset.
DEFAULT_CACHE_ROOT = Path("~/.cache/shapecorr")
#: Version of the entry layout itself (metadata fields, member names); entries of another format are stale.
FORMAT_VERSION = 1
#: Temp files older than this (seconds) belong to a crashed writer and are deleted. Writing an entry takes
#: seconds, so an hour leaves any live writer alone.
STALE_TEMP_SECONDS = 3600.0
#: Suffix of temp files written by :func:`atomic_open`.
TEMP_SUFFIX = ".tmp"

_META = "__meta__"
# Members of a sparse value: __sparse__<name>__<part>.
_SPARSE_PREFIX = "__sparse__"
_SPARSE_PARTS = ("data", "indices", "indptr", "shape")
_SPARSE_FORMATS = {"csr": sp.csr_array, "csc": sp.csc_array}
_ARRAY_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# np.savez takes these as its own keyword arguments, so they cannot name arrays.
_RESERVED_NAMES = frozenset({"file", "allow_pickle"})
_QUANTITY_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_HEX_DIGEST = re.compile(r"^[0-9a-f]{64}$")
# What reading a damaged .npz can raise (zip layer, npy header parser, our own checks, metadata JSON).
_CORRUPTION_ERRORS = (OSError, ValueError, EOFError, KeyError, TypeError, zipfile.BadZipFile)


class CacheWarning(UserWarning):
    """A cache entry was corrupt or stale and is being recomputed."""


class _CorruptEntry(Exception):
    """Raised internally when an entry file is readable but inconsistent."""


def default_cache_root() -> Path:
    """``$SHAPECORR_CACHE`` if set and non-empty, else ``~/.cache/shapecorr``."""
    configured = os.environ.get(CACHE_ENV_VAR, "")
    return Path(configured or DEFAULT_CACHE_ROOT).expanduser()


@contextmanager
def atomic_open(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """Open ``path`` for binary writing such that it appears complete or not at all.

    Writes go to a uniquely named temp file next to ``path``; when the ``with`` block ends without an
    exception, the temp file is flushed, fsync'ed and renamed over ``path`` (``os.replace``, atomic on
    POSIX and Windows within one file system). On an exception the temp file is removed and ``path`` is
    left untouched.

    Raises
    ------
    OSError
        The temp file cannot be created, written or renamed; it names ``path`` when the failure named no file.
    """
    target = Path(path)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}{TEMP_SUFFIX}")
    try:
        with open(tmp, "xb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException as err:
        with suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(err, OSError) and err.filename is None and err.errno is not None:
            # a failed write (e.g. disk full) names no file: name the one being written
            raise OSError(err.errno, err.strerror, str(target)) from err
        raise


def remove_stale_temp_files(directory: str | os.PathLike, max_age_s: float = STALE_TEMP_SECONDS) -> int:
    """Delete temp files left by :func:`atomic_open` in ``directory`` that are older than ``max_age_s``.

    Returns
    -------
    int
        Number of files removed.
    """
    cutoff = time.time() - max_age_s
    removed = 0
    for tmp in Path(directory).glob(f".*{TEMP_SUFFIX}"):
        with suppress(FileNotFoundError):
            if tmp.stat().st_mtime < cutoff:
                tmp.unlink()
                removed += 1
    return removed


@contextmanager
def _open_archive(path: Path) -> Iterator[np.lib.npyio.NpzFile]:
    # Open the file ourselves: np.load(path) leaks its handle when the zip directory is unreadable.
    with open(path, "rb") as handle:
        archive = np.load(handle, allow_pickle=False)
        if not isinstance(archive, np.lib.npyio.NpzFile):
            raise _CorruptEntry("not an .npz archive")
        with archive:
            yield archive


def content_hash(verts: Any, faces: Any) -> str:
    """SHA-256 of a mesh's content.

    Hashes shapes and bytes of ``verts`` as little-endian float64 and ``faces`` as little-endian int64.

    Parameters
    ----------
    verts : (n, 3) float array or tensor
    faces : (f, 3) int array or tensor

    Returns
    -------
    str
        64 lowercase hex digits.
    """
    digest = hashlib.sha256()
    for tag, array, dtype in ((b"verts", verts, "<f8"), (b"faces", faces, "<i8")):
        a = np.ascontiguousarray(as_numpy(array), dtype=dtype)
        digest.update(tag)
        digest.update(np.asarray(a.shape, dtype="<i8").tobytes())
        digest.update(a.tobytes())
    return digest.hexdigest()


@dataclass(frozen=True)
class CacheKey:
    """Identity of a cache entry.

    Attributes
    ----------
    name
        The quantity, e.g. ``"eigenbasis"``; letters, digits, ``_ . -``.
    content_hash
        :func:`content_hash` of the mesh the quantity is computed from.
    params
        Parameters of the computation; must be JSON-serializable (tuples become lists, NaN is refused).
    version
        Operator version, bumped by the computing module whenever its output changes.
    keep_float64
        Store float64 arrays as float64 instead of float32.
    """

    name: str
    content_hash: str
    params: Mapping[str, Any]
    version: int | str
    keep_float64: bool = False
    canonical: str = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not _QUANTITY_NAME.match(self.name):
            raise CacheError(f"cache quantity name must match {_QUANTITY_NAME.pattern}, got {self.name!r}")
        if not isinstance(self.content_hash, str) or not _HEX_DIGEST.match(self.content_hash):
            raise CacheError(f"content_hash must be 64 lowercase hex digits, got {self.content_hash!r}")
        if isinstance(self.version, bool) or not isinstance(self.version, (int, str)):
            raise CacheError(f"cache version must be an int or a str, got {self.version!r}")
        if not isinstance(self.params, Mapping):
            raise CacheError(f"cache params must be a mapping, got {type(self.params).__name__}")
        parts = {
            "name": self.name,
            "content_hash": self.content_hash,
            "params": dict(self.params),
            "version": self.version,
            "keep_float64": bool(self.keep_float64),
        }
        try:
            canonical = json.dumps(parts, sort_keys=True, separators=(",", ":"), allow_nan=False)
        except (TypeError, ValueError) as err:
            raise CacheError(f"cache params of {self.name!r} must be JSON-serializable and finite: {err}") from err
        object.__setattr__(self, "canonical", canonical)
        # Keep the canonical form so later mutation of the caller's dict cannot change the key.
        object.__setattr__(self, "params", json.loads(canonical)["params"])

    @property
    def digest(self) -> str:
        """SHA-256 of :attr:`canonical` (64 hex digits), the entry's file stem."""
        return hashlib.sha256(self.canonical.encode("utf-8")).hexdigest()


def _sparse_member(name: str, part: str) -> str:
    return f"{_SPARSE_PREFIX}{name}__{part}"


def _check_stored(key: CacheKey, name: str, a: np.ndarray) -> np.ndarray:
    """``a`` in its storage dtype (float64 -> float32 unless kept), refused when not numeric or not finite."""
    if a.dtype.kind not in "biuf":
        raise CacheError(
            f"array {name!r} of cache entry {key.name!r} has dtype {a.dtype}; only numeric arrays are stored"
        )
    if a.dtype == np.float64 and not key.keep_float64:
        with np.errstate(over="ignore"):  # overflow to inf is reported just below
            a = a.astype(np.float32)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise NumericalError(
            f"array {name!r} of {key.name!r} contains NaN/Inf ({int((~np.isfinite(a)).sum())} entries"
            f"{'' if key.keep_float64 else ', after conversion to float32'}); refusing to cache it"
        )
    return np.ascontiguousarray(a)


def _prepare_arrays(key: CacheKey, arrays: Mapping[str, Any]) -> dict[str, Any]:
    """Validate ``arrays`` and convert them to their storage dtypes.

    float64 becomes float32 unless kept; sparse values become ``scipy.sparse`` CSR (CSC stays CSC) arrays with
    sorted indices.
    """
    if not isinstance(arrays, Mapping) or not arrays:
        raise CacheError(f"cache entry {key.name!r} must be a non-empty dict of arrays, got {arrays!r:.80}")
    stored = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _ARRAY_NAME.match(name) or name in _RESERVED_NAMES or name.startswith("__"):
            raise CacheError(f"invalid array name {name!r} in cache entry {key.name!r}")
        if sp.issparse(value):
            fmt = "csc" if value.format == "csc" else "csr"
            matrix = _SPARSE_FORMATS[fmt](value)
            matrix.sum_duplicates()
            matrix.sort_indices()
            data = _check_stored(key, name, np.asarray(matrix.data))
            stored[name] = _SPARSE_FORMATS[fmt]((data, matrix.indices.astype(np.int64), matrix.indptr.astype(np.int64)),
                                                shape=matrix.shape)
            continue
        stored[name] = _check_stored(key, name, as_numpy(value))
    return stored


def as_stored(key: CacheKey, arrays: Mapping[str, Any]) -> dict[str, Any]:
    """``arrays`` exactly as :meth:`ShapeCache.put` would store and return them, without writing.

    Read-only caches return this on a miss, so a first run and a cached run see identical values.
    """
    return _prepare_arrays(key, arrays)


def _members(stored: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The ``.npz`` members of prepared values and the formats of the sparse ones."""
    members, sparse = {}, {}
    for name, value in stored.items():
        if sp.issparse(value):
            sparse[name] = value.format
            parts = {"data": value.data, "indices": value.indices, "indptr": value.indptr,
                     "shape": np.asarray(value.shape, dtype=np.int64)}
            members.update({_sparse_member(name, part): np.ascontiguousarray(a) for part, a in parts.items()})
        else:
            members[name] = value
    return members, sparse


def _assemble(arrays: dict[str, np.ndarray], sparse: Mapping[str, str]) -> dict[str, Any]:
    """Rebuild the sparse values of a read entry from their members."""
    out = {name: a for name, a in arrays.items() if not name.startswith(_SPARSE_PREFIX)}
    for name, fmt in sparse.items():
        if fmt not in _SPARSE_FORMATS:
            raise _CorruptEntry(f"sparse value {name!r} has unknown format {fmt!r}")
        parts = {part: arrays.get(_sparse_member(name, part)) for part in _SPARSE_PARTS}
        if any(a is None for a in parts.values()) or parts["shape"].shape != (2,):
            raise _CorruptEntry(f"sparse value {name!r} lacks members")
        shape = tuple(int(s) for s in parts["shape"])
        major = shape[0] if fmt == "csr" else shape[1]
        indptr, indices = parts["indptr"], parts["indices"]
        if (indptr.shape != (major + 1,) or indptr[0] != 0 or indptr[-1] != len(indices)
                or len(indices) != len(parts["data"])
                or np.any(np.diff(indptr) < 0)
                or (len(indices) and (indices.min() < 0 or indices.max() >= shape[1 if fmt == "csr" else 0]))):
            raise _CorruptEntry(f"sparse value {name!r} is inconsistent")
        out[name] = _SPARSE_FORMATS[fmt]((parts["data"], indices, indptr), shape=shape)
    return out


def _read_meta(archive: np.lib.npyio.NpzFile) -> dict:
    if _META not in archive.files:
        raise _CorruptEntry("no metadata member")
    meta = json.loads(archive[_META].tobytes().decode("utf-8"))
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_VERSION:
        raise _CorruptEntry(f"metadata format is not {FORMAT_VERSION}")
    if not isinstance(meta.get("key"), str) or not isinstance(meta.get("arrays"), dict):
        raise _CorruptEntry("metadata lacks the key or the array list")
    return meta


def _key_from_meta(meta: dict) -> CacheKey:
    parts = json.loads(meta["key"])
    return CacheKey(parts["name"], parts["content_hash"], parts["params"], parts["version"], parts["keep_float64"])


class ShapeCache:
    """Directory of cached per-mesh quantities (see the module docstring for the policy).

    Parameters
    ----------
    root
        Cache directory; default :func:`default_cache_root`.
    writable
        ``False``: never write or delete anything; a miss computes and returns without storing.
    """

    def __init__(self, root: str | os.PathLike | None = None, writable: bool = True):
        self.root = Path(root).expanduser() if root is not None else default_cache_root()
        self.writable = writable

    def __repr__(self) -> str:
        return f"ShapeCache(root={str(self.root)!r}, writable={self.writable})"

    def path(self, key: CacheKey) -> Path:
        """File holding the entry of ``key`` (it may not exist)."""
        return self.root / key.name / key.content_hash / f"{key.digest}.npz"

    def get(self, key: CacheKey) -> dict[str, Any] | None:
        """The stored arrays (and ``scipy.sparse`` values) of ``key``, or ``None`` on a miss.

        A corrupt or stale file counts as a miss and emits a :class:`CacheWarning`; it is left in place
        (a following :meth:`put` overwrites it).
        """
        path = self.path(key)
        if not path.is_file():
            return None
        try:
            with _open_archive(path) as archive:
                meta = _read_meta(archive)
                if meta["key"] != key.canonical:
                    warnings.warn(f"{path}: stale cache entry (stored key differs from the requested one); "
                                  "recomputing", CacheWarning, stacklevel=2)
                    return None
                spec = meta["arrays"]
                if set(archive.files) != set(spec) | {_META}:
                    raise _CorruptEntry(f"members {sorted(archive.files)} do not match metadata {sorted(spec)}")
                arrays = {}
                for name, (dtype, shape) in spec.items():
                    a = archive[name]
                    if a.dtype.str != dtype or list(a.shape) != shape:
                        found = f"{a.dtype.str}{list(a.shape)}"
                        raise _CorruptEntry(f"array {name!r} is {found}, metadata says {dtype}{shape}")
                    if a.dtype.kind == "f" and not np.isfinite(a).all():
                        raise _CorruptEntry(f"array {name!r} contains NaN/Inf")
                    arrays[name] = a
                arrays = _assemble(arrays, meta.get("sparse", {}))
        except (_CorruptEntry, *_CORRUPTION_ERRORS) as err:
            warnings.warn(f"{path}: corrupt cache entry ({type(err).__name__}: {err}); recomputing",
                          CacheWarning, stacklevel=2)
            return None
        return arrays

    def put(self, key: CacheKey, arrays: Mapping[str, Any]) -> dict[str, Any]:
        """Store ``arrays`` under ``key`` atomically and return them as stored.

        float64 becomes float32 unless ``key.keep_float64``.

        Raises
        ------
        CacheError
            The cache is read-only, an array is not numeric or badly named, or the file cannot be written.
        NumericalError
            An array contains NaN/Inf.
        """
        if not self.writable:
            raise CacheError("cache is read-only (writable=False); cannot store entries", self.root)
        stored = _prepare_arrays(key, arrays)
        members, sparse = _members(stored)
        meta = {
            "format": FORMAT_VERSION,
            "key": key.canonical,
            "arrays": {name: [a.dtype.str, list(a.shape)] for name, a in members.items()},
        }
        if sparse:
            meta["sparse"] = sparse
        meta_bytes = np.frombuffer(json.dumps(meta, sort_keys=True).encode("utf-8"), dtype=np.uint8)
        path = self.path(key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_open(path) as handle:
                np.savez(handle, allow_pickle=False, **members, **{_META: meta_bytes})
            remove_stale_temp_files(path.parent)
        except OSError as err:
            raise CacheError(f"cannot write cache entry: {err}", path) from err
        return stored

    def get_or_compute(
        self,
        name: str,
        verts: Any,
        faces: Any,
        params: Mapping[str, Any],
        version: int | str,
        compute: Callable[[], Mapping[str, Any]],
        keep_float64: bool = False,
    ) -> dict[str, np.ndarray]:
        """The cached quantity ``name`` of the mesh ``(verts, faces)``, computing and storing it on a miss.

        Parameters
        ----------
        name
            Quantity name, e.g. ``"eigenbasis"``.
        verts : (n, 3) float
        faces : (f, 3) int
            The mesh the quantity is computed from (hashed with :func:`content_hash`).
        params
            JSON-serializable parameters of the computation.
        version
            Operator version of the computing code.
        compute
            Called with no argument on a miss; returns a dict of arrays.
        keep_float64
            Store float64 arrays as float64 (e.g. when a later solve needs the precision).

        Returns
        -------
        dict[str, np.ndarray]
            The arrays as stored, identical on a hit and on a miss.
        """
        key = CacheKey(name, content_hash(verts, faces), params, version, keep_float64)
        hit = self.get(key)
        if hit is not None:
            return hit
        computed = compute()
        if self.writable:
            return self.put(key, computed)
        return _prepare_arrays(key, computed)

    def find(self, name: str, content_hash: str, predicate: Callable[[CacheKey], bool]) -> list[CacheKey]:
        """Stored keys of quantity ``name`` for the mesh ``content_hash`` that satisfy ``predicate``.

        Only the metadata of each file is read; unreadable files are skipped (they are reported when
        :meth:`get` reads them). Keys come sorted by digest, so the result is deterministic.
        """
        probe = CacheKey(name, content_hash, {}, 0)  # validates name and hash before touching the disk
        directory = self.root / probe.name / probe.content_hash
        found = []
        for path in sorted(directory.glob("*.npz")):
            try:
                with _open_archive(path) as archive:
                    key = _key_from_meta(_read_meta(archive))
            except (_CorruptEntry, CacheError, *_CORRUPTION_ERRORS):
                continue
            if key.digest == path.stem and key.name == name and key.content_hash == content_hash and predicate(key):
                found.append(key)
        return found

    def clean_temp(self, max_age_s: float = STALE_TEMP_SECONDS) -> int:
        """Remove temp files of crashed writers older than ``max_age_s`` anywhere under the root.

        Returns
        -------
        int
            Number of files removed (0 in read-only mode, which never deletes).
        """
        if not self.writable or not self.root.is_dir():
            return 0
        directories = {tmp.parent for tmp in self.root.rglob(f".*{TEMP_SUFFIX}")}
        return sum(remove_stale_temp_files(directory, max_age_s) for directory in directories)
