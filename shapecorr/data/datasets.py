"""Datasets over a FAUST/SCAPE-style folder.

Folder layout (the de-facto layout of FAUST_r / SCAPE_r and of ``data_prep/make_synthetic.py``)::

    ROOT/
      off/ or shapes/        meshes: <name>.off | .ply | .obj
      corres/<name>.vts      optional: one-based vertex indices of R reference points (same r = same point)
      corres/<name>.sym.vts  optional: the same for the left/right mirrored ground truth
      splits/<split>.txt     optional: shape names (one per line) of a split, e.g. train.txt / test.txt;
                             without a splits/ folder every shape belongs to every split

:class:`ShapeDataset` yields one :class:`ShapeSample` per shape: the normalized :class:`Shape`, the per-shape
operators requested (``sample.operators[name]``, :mod:`shapecorr.data.operators`) and ground truth.
:class:`PairDataset` yields ordered pairs.
Derived quantities come from the on-disk :class:`~shapecorr.data.cache.ShapeCache`; missing entries are
computed by :meth:`ShapeDataset.prepare` (in parallel worker processes, with a progress bar) — the data
module calls it before training starts, and ``data_prep/prepare.py`` calls it ahead of time.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shlex
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from shapecorr.data.cache import CacheKey, ShapeCache, default_cache_root
from shapecorr.data.io import check_vts_lengths, load_shape, read_vts
from shapecorr.data.operators import (
    REGISTRY,
    OperatorConfig,
    compute_operators,
    geodesics_cached,
    geodesics_from_cached,
)
from shapecorr.data.shape import Normalization, Shape
from shapecorr.data.validation import CLI_PREFIX, ValidationOptions
from shapecorr.data.workers import process_pool, submit_all
from shapecorr.errors import ConfigError, DatasetError, InvalidMeshError, ShapeCorrError

MESH_DIRS = ("off", "shapes")
MESH_EXTENSIONS = (".off", ".ply", ".obj")
#: Version of the cached, validated and normalized meshes (bump when reading/validation/normalization changes).
MESH_CACHE_VERSION = 2
#: Folder of the split files ``<split>.txt`` under a dataset root.
SPLITS_DIR = "splits"

log = logging.getLogger(__name__)
#: Roots already announced as having no splits/ folder (the message is logged once per root and process).
_ROOTS_WITHOUT_SPLITS: set[str] = set()


def _tensor(value) -> torch.Tensor:
    """A cached array as a tensor; tensors pass through.

    Floats become float32, integers int64, ``scipy.sparse`` a coalesced sparse COO float32 tensor.
    """
    if isinstance(value, torch.Tensor):
        return value
    if sp.issparse(value):
        coo = sp.coo_array(value)
        indices = torch.from_numpy(np.vstack([coo.row, coo.col]).astype(np.int64))
        values = torch.from_numpy(np.ascontiguousarray(coo.data, dtype=np.float32))
        return torch.sparse_coo_tensor(indices, values, coo.shape, check_invariants=True).coalesce()
    a = np.asarray(value)
    dtype = np.float32 if a.dtype.kind == "f" else np.int64 if a.dtype.kind in "iu" else a.dtype
    return torch.from_numpy(np.ascontiguousarray(a, dtype=dtype))


@dataclass(frozen=True, eq=False, init=False)
class ShapeSample:
    """One shape with the per-shape operators a model declared and its ground truth.

    Attributes
    ----------
    shape : Shape
        Normalized mesh (``verts (n, 3)`` float32, ``faces (f, 3)`` int64).
    operators : dict[str, dict[str, Tensor]]
        Per operator name (:mod:`shapecorr.data.operators`) its tensors, e.g. ``operators["eigenbasis"] =
        {"evals": (k,), "evecs": (n, k), "mass": (n,)}``, ``operators["shot"] = {"shot": (n, 352)}``; floats are
        float32, sparse operators sparse COO tensors.
    corres : (R,) int64 or None
        Zero-based vertex indices of the R reference points (``corres/<name>.vts``).
    corres_sym : (R,) int64 or None
        The same for the mirrored ground truth (``corres/<name>.sym.vts``).

    Convenience views: ``evals (k,)``, ``evecs (n, k)``, ``mass (n,)`` (the eigenbasis operator; standard ½-cot
    eigenvalue scale, mass-orthonormal eigenfunctions, lumped vertex areas) and ``features[name] (n, c)`` (the
    descriptor operators: shot, wks, hks).
    """

    shape: Shape
    operators: Mapping[str, Mapping[str, torch.Tensor]]
    corres: torch.Tensor | None
    corres_sym: torch.Tensor | None

    def __init__(
        self,
        shape: Shape,
        operators: Mapping[str, Mapping[str, Any]] | None = None,
        corres: torch.Tensor | None = None,
        corres_sym: torch.Tensor | None = None,
    ):
        ops = {name: {k: _tensor(v) for k, v in arrays.items()} for name, arrays in (operators or {}).items()}
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "operators", ops)
        object.__setattr__(self, "corres", corres)
        object.__setattr__(self, "corres_sym", corres_sym)

    @property
    def name(self) -> str:
        """Name of the shape."""
        return self.shape.name

    @property
    def verts(self) -> torch.Tensor:
        """Vertices ``(n, 3)`` float32 of the shape."""
        return self.shape.verts

    @property
    def faces(self) -> torch.Tensor:
        """Faces ``(f, 3)`` int64 of the shape."""
        return self.shape.faces

    def _eigen(self, part: str) -> torch.Tensor:
        eig = self.operators.get("eigenbasis", {})
        if part not in eig:
            raise ConfigError(f"{self.name}: the sample carries no eigenbasis ({part}); the model or matcher must "
                              "declare it in required_operators, e.g. {'eigenbasis': {'k': 200}}")
        return eig[part]

    @property
    def evals(self) -> torch.Tensor:
        """``(k,)`` Laplace–Beltrami eigenvalues, ascending (``operators["eigenbasis"]["evals"]``)."""
        return self._eigen("evals")

    @property
    def evecs(self) -> torch.Tensor:
        """``(n, k)`` mass-orthonormal eigenfunctions (``operators["eigenbasis"]["evecs"]``)."""
        return self._eigen("evecs")

    @property
    def mass(self) -> torch.Tensor:
        """``(n,)`` lumped vertex areas (``operators["eigenbasis"]["mass"]``)."""
        return self._eigen("mass")

    @property
    def features(self) -> dict[str, torch.Tensor]:
        """Per-vertex descriptors ``(n, c)`` by name.

        Every operator ``name`` with an array ``name`` that is not registered as a non-descriptor (e.g.
        ``geodesics``).
        """
        out = {}
        for name, arrays in self.operators.items():
            op = REGISTRY.get(name)
            if name in arrays and (op is None or op.feature):
                out[name] = arrays[name]
        return out

    def to(self, device: torch.device | str) -> ShapeSample:
        """Copy with every tensor on ``device``."""
        def move(t):
            return None if t is None else t.to(device)
        return ShapeSample(
            shape=self.shape.to(device),
            operators={name: {k: v.to(device) for k, v in arrays.items()} for name, arrays in self.operators.items()},
            corres=move(self.corres),
            corres_sym=move(self.corres_sym),
        )

    def __repr__(self) -> str:
        return f"ShapeSample({self.name!r}, n={self.shape.n_verts}, operators={list(self.operators)})"


@dataclass(frozen=True, eq=False)
class PairSample:
    """An ordered pair (x, y); maps go from x to y."""

    x: ShapeSample
    y: ShapeSample

    @property
    def name(self) -> str:
        """Name of the pair, ``<x>__<y>``."""
        return pair_name(self.x.name, self.y.name)

    def to(self, device: torch.device | str) -> PairSample:
        """Copy of the pair with both samples on ``device``."""
        return PairSample(self.x.to(device), self.y.to(device))


#: Joins the two shape names of a pair's output files (:func:`pair_name`).
PAIR_SEPARATOR = "__"


def pair_name(name_x: str, name_y: str) -> str:
    """File-name stem of a pair's outputs: ``<x>__<y>`` (unambiguous within a run: :func:`check_pair_names`)."""
    return f"{name_x}{PAIR_SEPARATOR}{name_y}"


def find_mesh_files(root: Path) -> dict[str, Path]:
    """Mesh files of a dataset folder by shape name (sorted).

    Raises
    ------
    DatasetError
        The folder does not exist, has no ``off/`` or ``shapes/`` sub-folder, has none of the known mesh
        extensions, or two files share a name.
    """
    root = Path(root)
    if not root.is_dir():
        if root.is_symlink() and not root.exists():
            raise DatasetError("dataset folder is a symbolic link that loops or points nowhere "
                               f"({_link_target(root)})", root)
        if root.exists():
            folder = root.parent.parent if root.parent.name in MESH_DIRS else root.parent
            raise DatasetError(f"is a file, not a dataset folder: data.root must be the folder that holds "
                               f"{'/ or '.join(MESH_DIRS)}/ (here perhaps data.root={folder})", root)
        raise DatasetError("dataset folder does not exist", root)
    mesh_dir = next((root / d for d in MESH_DIRS if (root / d).is_dir()), None)
    if mesh_dir is None:
        raise DatasetError(f"no mesh sub-folder: expected one of {'/, '.join(MESH_DIRS)}/", root)
    files: dict[str, Path] = {}
    skipped: list[str] = []
    for path in sorted(mesh_dir.iterdir()):
        if path.suffix.lower() in MESH_EXTENSIONS and path.is_symlink() and not path.exists():
            raise DatasetError(f"{path.name} is a symbolic link that loops or points nowhere ({_link_target(path)}); "
                               "fix the link or remove it", mesh_dir)
        if path.suffix.lower() in MESH_EXTENSIONS and path.is_file():
            if path.stem in files:
                raise DatasetError(f"two mesh files named {path.stem!r}: {files[path.stem].name} and {path.name}",
                                   mesh_dir)
            files[path.stem] = path
        elif path.is_dir():
            skipped.append(f"{path.name}/ (a directory; sub-folders are not searched)")
        elif path.is_symlink() and not path.exists():
            skipped.append(f"{path.name} (a symbolic link that loops or points nowhere)")
        elif path.suffix.lower() in MESH_EXTENSIONS:
            skipped.append(f"{path.name} (not a regular file)")
        elif not path.name.startswith("."):
            skipped.append(f"{path.name} (not {'/'.join(MESH_EXTENSIONS)})")
    if skipped:
        warnings.warn(f"{mesh_dir}: skipped {len(skipped)} entr{'y' if len(skipped) == 1 else 'ies'}: "
                      f"{', '.join(skipped[:5])}{', ...' if len(skipped) > 5 else ''}", DatasetWarning, stacklevel=2)
    if not files:
        extra = f"; skipped: {', '.join(skipped[:5])}" if skipped else ""
        raise DatasetError(f"no mesh files ({', '.join(MESH_EXTENSIONS)}) found{extra}", mesh_dir)
    return files


def _link_target(path: Path) -> str:
    """``-> <target>`` of a symbolic link, for messages."""
    try:
        return f"-> {os.readlink(path)}"
    except OSError as err:
        return f"unreadable link: {err.strerror}"


class DatasetWarning(UserWarning):
    """Entries of a dataset folder were skipped (directories or files that are not meshes)."""


def select_names(
    all_names: Sequence[str],
    root: Path,
    split: str | None = None,
    names: Iterable[str] | None = None,
    index_range: Sequence[int] | None = None,
    split_file: str | os.PathLike | None = None,
) -> list[str]:
    """Names of the shapes in a split.

    Precedence: explicit ``names`` > ``split_file`` > ``index_range`` ``[start, stop)`` into the sorted names
    > ``ROOT/splits/<split>.txt`` > all shapes (``split=None``). A folder without a ``splits/`` directory has no
    splits: every shape belongs to every split (logged once per folder). With a ``splits/`` directory, a requested
    split without its file is an error, so a typo never silently trains on everything.
    """
    all_set = set(all_names)
    if names is not None:
        chosen, source = list(names), "the configured names"
    elif split_file is None and split is not None and index_range is None and not (Path(root) / SPLITS_DIR).is_dir():
        key = str(Path(root).resolve())
        if key not in _ROOTS_WITHOUT_SPLITS:
            _ROOTS_WITHOUT_SPLITS.add(key)
            log.info("%s has no %s/ folder: every shape (%d) belongs to every split (train, val, test)",
                     root, SPLITS_DIR, len(all_names))
        return list(all_names)
    elif split_file is not None or (split is not None and index_range is None):
        path = Path(split_file) if split_file is not None else Path(root) / SPLITS_DIR / f"{split}.txt"
        if not path.is_file():
            if split_file is None:
                raise DatasetError(
                    f"no split file for split {split!r} (expected splits/{split}.txt, or give an index range in "
                    "the data config; a folder without splits/ puts every shape in every split)", root)
            raise DatasetError("split file does not exist", path)
        chosen = [line.strip() for line in path.read_text(errors="surrogateescape").splitlines()
                  if line.strip() and not line.startswith("#")]
        source = str(path)
    elif index_range is not None:
        start, stop = int(index_range[0]), int(index_range[1])
        if not 0 <= start < stop <= len(all_names):
            raise DatasetError(f"index range [{start}, {stop}) is outside the {len(all_names)} shapes", root)
        return list(all_names[start:stop])
    else:
        return list(all_names)
    missing = [n for n in chosen if n not in all_set]
    if missing:
        raise DatasetError(f"{len(missing)} shape(s) listed in {source} are not in the dataset: {missing[:5]}", root)
    if not chosen:
        raise DatasetError(f"{source} selects no shape", root)
    return chosen


def file_sha256(path: Path) -> str | None:
    """SHA-256 (64 hex digits) of a file's bytes, read in blocks; None when it cannot be read."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(_HASH_BLOCK_BYTES), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


#: Block size of :func:`file_sha256` (hashing a 5k-vertex OFF file, ~0.3 MB, takes ~1 ms).
_HASH_BLOCK_BYTES = 1 << 20


def _without_prefix(message: str, prefix: str) -> str:
    return message[len(prefix):] if message.startswith(prefix) else message


def load_mesh_cached(
    cache: ShapeCache, path: Path, normalization: Normalization, validation: ValidationOptions | None = None
) -> Shape:
    """:func:`~shapecorr.data.io.load_shape` through the cache.

    Parsing and validating a 5k-vertex mesh file costs ~0.1-0.25 s, ten times more than reading its cached
    operators; so the validated, normalized mesh is cached too, keyed by the SHA-256 of the file's bytes (any edit
    is a miss, whatever its size and modification time), the normalization and the validation options. The mesh
    warnings of the file (:class:`~shapecorr.data.validation.MeshWarning`: components, non-manifold, duplicate or
    degenerate faces) are kept in the entry and emitted again on every load, naming the file.
    """
    from shapecorr.data.validation import MeshWarning

    validation = ValidationOptions() if validation is None else validation
    digest = file_sha256(path)
    if digest is None:  # unreadable or missing: load_shape names the problem
        return load_shape(path, normalization=normalization, validation=validation)
    params = {"file_sha256": digest, "normalization": asdict(normalization), "validation": asdict(validation)}
    key = CacheKey("mesh", digest, params, MESH_CACHE_VERSION, keep_float64=True)
    prefix = f"{path}: "
    hit = cache.get(key)
    if hit is not None:
        for message in json.loads(hit["warnings"].tobytes().decode("utf-8")):
            warnings.warn(prefix + message, MeshWarning, stacklevel=2)
        return Shape(
            verts=torch.from_numpy(hit["verts"].astype(np.float32)),
            faces=torch.from_numpy(hit["faces"].astype(np.int64)),
            name=path.stem,
            path=path,
            scale=float(hit["scale"][0]),
            offset=hit["offset"].astype(np.float64),
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        shape = load_shape(path, normalization=normalization, validation=validation)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
    messages = [_without_prefix(str(w.message), prefix) for w in caught if issubclass(w.category, MeshWarning)]
    if cache.writable:
        cache.put(key, {"verts": shape.verts.numpy(), "faces": shape.faces.numpy(),
                        "scale": np.array([shape.scale]), "offset": np.asarray(shape.offset, np.float64),
                        "warnings": np.frombuffer(json.dumps(messages).encode("utf-8"), dtype=np.uint8)})
    return shape


def sample_with_operators(
    shape: Shape, operators: OperatorConfig, cache: ShapeCache, corres=None, corres_sym=None, fallback: bool = True
) -> ShapeSample:
    """``shape`` with the operators of ``operators`` (from ``cache``, computed on a miss) as a :class:`ShapeSample`.

    Parameters
    ----------
    shape : Shape
    operators : OperatorConfig
        What to provide (the data config's operators merged with the model's ``required_operators``).
    cache : ShapeCache
    corres, corres_sym : (n_ref,) int64 tensor, optional
        Ground-truth reference indices (and their symmetric flip), when known.
    fallback : bool
        Robust Laplacian where the cotangent one has infinite weights (:func:`operators_with_fallback`).
    """
    ops = operators_with_fallback(cache, shape, operators, fallback)
    return ShapeSample(shape=shape, operators=ops, corres=corres, corres_sym=corres_sym)


def operators_with_fallback(cache: ShapeCache, shape: Shape, operators: OperatorConfig,
                            fallback: bool = True) -> dict[str, dict]:
    """:func:`compute_operators`, with the robust Laplacian as an optional fallback.

    The robust Laplacian is used for this shape where the cotangent one has infinite weights (zero-area faces)
    when ``fallback`` (``data.validation.laplacian_fallback``), with a warning naming the file; otherwise the
    error names the file and both options.
    """
    from shapecorr.data.validation import MeshWarning

    verts, faces = shape.verts.numpy(), shape.faces.numpy()
    where = shape.path or shape.name
    try:
        return _compute_naming_the_file(cache, verts, faces, operators, where)
    except InvalidMeshError as err:
        if operators.laplacian != "cotan" or "infinite weights" not in str(err):
            raise
        if not fallback:
            raise InvalidMeshError(
                f"{err.problem}; set {CLI_PREFIX}laplacian_fallback=true (robust Laplacian for such shapes) or "
                "data.operators.laplacian=robust (for every shape)", where) from None
        warnings.warn(f"{where}: cotangent Laplacian has infinite weights (zero-area faces); using the robust "
                      f"Laplacian for this shape ({CLI_PREFIX}laplacian_fallback=false refuses such shapes)",
                      MeshWarning, stacklevel=2)
        return _compute_naming_the_file(cache, verts, faces, operators.with_request(laplacian="robust"), where)


def _compute_naming_the_file(cache: ShapeCache, verts, faces, operators: OperatorConfig, where) -> dict:
    """:func:`compute_operators`; an error about the mesh that names no file gets ``where`` (the shape's file)."""
    try:
        return compute_operators(cache, verts, faces, operators)
    except ShapeCorrError as err:
        if err.path is not None:
            raise
        problem = err.problem
        if problem.startswith(EIGENBASIS_RANGE_ERROR):  # more eigenpairs requested than the mesh has
            problem = (f"{Path(str(where)).stem} has {len(verts)} vertices, too few for the eigenpairs requested "
                       f"({problem}): lower data.operators.n_eig, or the model's own eigenbasis size when it asks "
                       "for more (its model.* options), or leave this shape out")
        raise type(err)(problem, where) from None


#: Start of the error of :func:`shapecorr.geometry.laplace_beltrami.eigenbasis` for more eigenpairs than vertices.
EIGENBASIS_RANGE_ERROR = "eigenbasis needs 1 <= k <= n-1"
#: What ``ShapeDataset.prepare(geodesics=...)`` caches: rows from the ground-truth points (what the
#: evaluation needs, ``R x n``) or the all-pairs matrix (``n x n``).
GEODESIC_SOURCES = ("ground_truth", "all")


def _prepare_one(args) -> str:
    """Worker: load one mesh and fill its cache entries (runs in a separate process)."""
    from shapecorr.data.validation import MeshWarning

    path, normalization, operators, cache_root, geodesics, sources, validation = args
    cache = ShapeCache(cache_root)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)  # the calling process has loaded (and reported) every mesh
        shape = load_mesh_cached(cache, Path(path), normalization, validation)
    verts, faces = shape.verts.numpy(), shape.faces.numpy()
    operators_with_fallback(cache, shape, operators, validation.laplacian_fallback)
    if geodesics and sources is None:
        geodesics_cached(cache, verts, faces, method=geodesics)
    elif geodesics:
        geodesics_from_cached(cache, verts, faces, sources, method=geodesics)
    return shape.name


def reference_subset(n_points: int, max_points: int) -> np.ndarray:
    """Indices ``(min(n_points, max_points),) int64`` of evenly spaced ground-truth entries, first and last kept.

    A function of the two counts only, so every ``.vts`` file of a folder (one length) keeps the same template
    points and stays a valid ground truth.
    """
    if max_points >= n_points:
        return np.arange(n_points, dtype=np.int64)
    return np.unique(np.round(np.linspace(0, n_points - 1, max_points)).astype(np.int64))


class ShapeDataset(Dataset):
    """The shapes of a FAUST/SCAPE-style folder (see module docstring).

    Parameters
    ----------
    root
        Dataset folder.
    split, names, index_range, split_file
        Which shapes; see :func:`select_names`.
    normalization
        Applied on load (default: area-weighted centroid at the origin, sqrt(area) = 2/3).
    operators
        The per-shape operators to provide (:class:`~shapecorr.data.operators.OperatorConfig`; a mapping is read
        with :meth:`~shapecorr.data.operators.OperatorConfig.from_options`).
    cache_dir
        Root of the shape cache (default ``$SHAPECORR_CACHE`` or ``~/.cache/shapecorr``).
    require_corres
        Raise if a shape has no ``corres/<name>.vts``.
    validation
        Mesh-check relaxations (``data.validation.*``, :class:`~shapecorr.data.validation.ValidationOptions`).
    reference_points
        Keep at most this many ground-truth points: the same evenly spaced entries of every ``.vts`` and
        ``.sym.vts`` (all have one length, entry r being one template point; see :func:`reference_subset`).
        For large scans, whose evaluation costs one geodesic row of ``n`` floats per point. None: all.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str | None = None,
        names: Iterable[str] | None = None,
        index_range: Sequence[int] | None = None,
        split_file: str | os.PathLike | None = None,
        normalization: Normalization = Normalization(),
        operators: OperatorConfig = OperatorConfig(),
        cache_dir: str | os.PathLike | None = None,
        require_corres: bool = False,
        validation: ValidationOptions | None = None,
        reference_points: int | None = None,
    ):
        self.root = Path(root)
        self.validation = ValidationOptions() if validation is None else validation
        if reference_points is not None and (isinstance(reference_points, bool)
                                             or not isinstance(reference_points, (int, np.integer))
                                             or reference_points < 1):
            raise ConfigError(f"data.reference_points must be a positive number of points or null (all), "
                              f"got {reference_points!r}")
        self.reference_points = None if reference_points is None else int(reference_points)
        self.split = split
        files = find_mesh_files(self.root)
        self.names = select_names(list(files), self.root, split, names, index_range, split_file)
        self._folder_names = set(files)
        self.paths = [files[n] for n in self.names]
        self.normalization = normalization
        self.operators = OperatorConfig.from_options(operators)
        self.cache = ShapeCache(default_cache_root() if cache_dir is None else cache_dir)
        self._index = {n: i for i, n in enumerate(self.names)}
        self._loaded: dict[int, Shape] = {}  # meshes are small next to their operators: keep them all
        self._corres_paths = {n: self._corres_path(n, ".vts") for n in self.names}
        self._sym_paths = {n: self._corres_path(n, ".sym.vts") for n in self.names}
        if require_corres:
            missing = [n for n, p in self._corres_paths.items() if p is None]
            if missing:
                raise DatasetError(f"no ground truth corres/<name>.vts for {len(missing)} shape(s), e.g. {missing[0]}",
                                   self.root)
        self._check_corres_lengths()

    def _corres_path(self, name: str, suffix: str) -> Path | None:
        path = self.root / "corres" / f"{name}{suffix}"
        return path if path.is_file() else None

    def _check_corres_lengths(self) -> None:
        present = {str(p): read_vts(p) for p in self._corres_paths.values() if p is not None}
        if present:
            check_vts_lengths(present, self.root)

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Position of a shape by name."""
        try:
            return self._index[name]
        except KeyError:
            if name in self._folder_names:
                raise DatasetError(
                    f"shape {name!r} is in the folder but not in split {self.split!r} ({len(self.names)} shapes): "
                    "pairs must name shapes of the split they are taken from (choose it with pairs=<split>, or list "
                    f"the shape in {SPLITS_DIR}/<split>.txt)", self.root) from None
            raise DatasetError(f"no shape named {name!r} in this split ({len(self.names)} shapes)", self.root) from None

    def load_shape(self, i: int) -> Shape:
        """The normalized mesh of shape ``i`` (no operators); kept in memory once loaded."""
        shape = self._loaded.get(i)
        if shape is None:
            shape = self._loaded[i] = load_mesh_cached(self.cache, self.paths[i], self.normalization, self.validation)
        return shape

    def __getitem__(self, i: int) -> ShapeSample:
        shape = self.load_shape(i)
        return sample_with_operators(shape, self.operators, self.cache,
                                     corres=self._read_corres(self._corres_paths[shape.name], shape),
                                     corres_sym=self._read_corres(self._sym_paths[shape.name], shape),
                                     fallback=self.validation.laplacian_fallback)

    def _read_corres(self, path: Path | None, shape: Shape) -> torch.Tensor | None:
        if path is None:
            return None
        corres = read_vts(path, n_verts=shape.n_verts)
        if self.reference_points is not None:
            corres = corres[reference_subset(len(corres), self.reference_points)]
        return torch.from_numpy(corres)

    def geodesics(self, i: int, method: str = "heat") -> np.ndarray:
        """All-pairs geodesic distances ``(n, n)`` float32 of shape ``i`` (normalized units), cached.

        Only for connected meshes (see :meth:`check_connected`); errors name the shape's file.
        """
        shape = self.load_shape(i)
        try:
            return geodesics_cached(self.cache, shape.verts.numpy(), shape.faces.numpy(), method=method)
        except ShapeCorrError as err:
            if err.path is not None:
                raise
            raise type(err)(f"all-pairs geodesic distances: {err.problem}", self.paths[i]) from None

    def check_connected(self, purpose: str, fix: str) -> None:
        """Raise :class:`~shapecorr.errors.DatasetError` naming every shape with several connected components.

        For computations that cannot handle them (``purpose``; ``fix`` says what to do instead), before any work.
        """
        from shapecorr.geometry.geodesics import vertex_components

        found = []
        for i in range(len(self)):
            shape = self.load_shape(i)
            n_components, _ = vertex_components(shape.n_verts, shape.faces.numpy())
            if n_components > 1:
                found.append(f"{self.paths[i]} ({n_components} components)")
        if found:
            raise DatasetError(f"{len(found)} shape(s) with several connected components, which {purpose} cannot "
                               f"handle: {', '.join(found[:3])}{', ...' if len(found) > 3 else ''}; {fix}", self.root)

    def geodesic_sources(self, i: int) -> np.ndarray:
        """Sorted unique vertices of shape ``i`` that the evaluation needs geodesic rows from.

        Its ground-truth points (``.vts`` and ``.sym.vts``), or every vertex when it has none (identity ground
        truth).
        """
        shape = self.load_shape(i)
        refs = [self._read_corres(p, shape) for p in (self._corres_paths[shape.name], self._sym_paths[shape.name])]
        refs = [r.numpy() for r in refs if r is not None]
        if not refs:
            return np.arange(shape.n_verts, dtype=np.int64)
        return np.unique(np.concatenate(refs)).astype(np.int64)

    def ground_truth_geodesics(self, i: int, method: str = "heat"):
        """Geodesic rows from the ground-truth points of shape ``i`` (:meth:`geodesic_sources`), cached.

        Returns
        -------
        :class:`~shapecorr.geometry.geodesics.SourceDistances`, rows ``(u, n)`` float32 (normalized units).
        """
        shape = self.load_shape(i)
        return geodesics_from_cached(self.cache, shape.verts.numpy(), shape.faces.numpy(),
                                     self.geodesic_sources(i), method=method)

    def prepare(self, num_workers: int | None = None, geodesics: str | None = None, progress: bool = True,
                geodesic_sources: str = "ground_truth") -> None:
        """Compute every missing cache entry (the operators of ``self.operators``, optionally geodesics).

        Runs in ``num_workers`` processes (default: the CPU count, at most the number of shapes, and at most
        as many as fit in the available memory by :func:`shapecorr.geometry.memory.prepare_bytes`) with a
        progress bar; entries already cached are only read. Safe to interrupt: each entry is written atomically.
        ``geodesic_sources``: ``"ground_truth"`` caches the rows from each shape's ground-truth points
        (:meth:`ground_truth_geodesics`, what the evaluation reads), ``"all"`` the all-pairs matrix.
        """
        from shapecorr.geometry.memory import prepare_bytes, workers_for_memory

        if geodesic_sources not in GEODESIC_SOURCES:
            raise DatasetError(f"geodesic_sources must be one of {GEODESIC_SOURCES}, got {geodesic_sources!r}")
        sources = [None] * len(self.paths)
        if geodesics and geodesic_sources == "ground_truth":
            sources = [self.geodesic_sources(i) for i in range(len(self.paths))]
        jobs = [(p, self.normalization, self.operators, self.cache.root, geodesics, s, self.validation)
                for p, s in zip(self.paths, sources)]
        estimates = []
        for i in range(len(self.paths)):
            n = self.load_shape(i).n_verts
            n_src = (n if sources[i] is None else len(sources[i])) if geodesics else 0
            estimates.append(prepare_bytes(n, self.operators.n_eig, n_src))
        biggest = self.names[int(np.argmax(estimates))] if estimates else ""
        workers = workers_for_memory(
            estimates, num_workers, f"preparing shape {biggest!r} of {self.root}",
            "free memory, lower the eigenpairs (data.operators.n_eig), use fewer ground-truth points "
            "(data.reference_points=N), or evaluate it at a working resolution (e.g. remesh it first)")
        desc = f"preparing {self.root.name}" + (f" [{self.split}]" if self.split else "")
        if workers <= 1:
            for job in tqdm(jobs, desc=desc, unit="shape", disable=not progress):
                _prepare_one(job)
            return
        # Ctrl-C: the workers are stopped at once (shapecorr.data.workers); finished cache entries are kept
        with process_pool(workers) as pool:
            for future in tqdm(submit_all(pool, _prepare_one, [(job,) for job in jobs]), total=len(jobs), desc=desc,
                               unit="shape", disable=not progress):
                future.result()

    def __repr__(self) -> str:
        return f"ShapeDataset(root={str(self.root)!r}, split={self.split!r}, n_shapes={len(self)})"


def _pair_fields(line: str) -> list[str]:
    """The names on a pair-file line.

    Tab-separated fields when the line has a tab, else shell-like words split at spaces or commas, with ``"..."`` /
    ``'...'`` quoting a name that contains them (no backslash escapes).
    """
    if "\t" in line:
        return [part.strip() for part in line.split("\t") if part.strip()]
    lexer = shlex.shlex(line, posix=True)
    lexer.whitespace, lexer.whitespace_split, lexer.commenters, lexer.escape = " ,", True, "", ""
    return list(lexer)


def read_pair_lines(path: str | os.PathLike) -> list[tuple[int, str, str]]:
    """``(line number, x, y)`` of every pair of a pair list file, each pair once.

    One pair per line: two shape names separated by a tab (names may then contain spaces), or by spaces or commas
    (a name with spaces or commas in double or single quotes). Blank lines and lines starting with ``#`` are
    skipped. A pair listed again is dropped with one :class:`DatasetWarning` naming the lines (it would otherwise
    be scored twice).

    Raises
    ------
    DatasetError
        Missing file, a line without exactly two names (or with an unclosed quote), no pair at all; the message
        names the file and the line.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError("pair list file does not exist" if not path.exists() else "is not a pair list file", path)
    pairs: list[tuple[int, str, str]] = []
    first_line: dict[tuple[str, str], int] = {}
    repeats: list[str] = []
    for lineno, line in enumerate(path.read_text(errors="surrogateescape").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            parts = _pair_fields(line)
        except ValueError as err:  # an unclosed quote
            raise DatasetError(f"line {lineno}: {err} in {line[:80]!r}", path) from None
        if len(parts) != 2:
            raise DatasetError(f"line {lineno}: expected two shape names, got {len(parts)} in {line[:80]!r} (separate "
                               "them by a tab, or quote a name with spaces: \"my shape\" other)", path)
        key = (parts[0], parts[1])
        if key in first_line:
            repeats.append(f"line {lineno} repeats line {first_line[key]} ({key[0]}, {key[1]})")
            continue
        first_line[key] = lineno
        pairs.append((lineno, *key))
    if repeats:
        warnings.warn(f"{path}: {len(repeats)} repeated pair(s) dropped, each pair is evaluated once: "
                      f"{'; '.join(repeats[:5])}{'; ...' if len(repeats) > 5 else ''}", DatasetWarning, stacklevel=2)
    if not pairs:
        raise DatasetError("pair list file lists no pair", path)
    return pairs


def read_pair_file(path: str | os.PathLike) -> list[tuple[str, str]]:
    """Pairs of shape names of a pair list file (e.g. FAUST_r test_pairs.txt), each once (:func:`read_pair_lines`)."""
    return [(x, y) for _, x, y in read_pair_lines(path)]


def ambiguous_pair_names(pairs: Iterable[tuple[str, str]]) -> tuple[tuple[str, str], tuple[str, str]] | None:
    """Two different pairs of ``pairs`` (name tuples) whose output files would share a name, or None.

    Records and maps of a pair are named :func:`pair_name` ``<x>__<y>``: with shapes ``p``, ``p__q``, ``r`` and
    ``q__r`` the pairs (p__q, r) and (p, q__r) are both ``p__q__r``.
    """
    seen: dict[str, tuple[str, str]] = {}
    for x, y in pairs:
        other = seen.setdefault(pair_name(x, y), (x, y))
        if other != (x, y):
            return other, (x, y)
    return None


def check_pair_names(pairs: Iterable[tuple[str, str]], where: str | os.PathLike | None = None) -> None:
    """Raise :class:`~shapecorr.errors.DatasetError` when two of ``pairs`` would share their output files."""
    clash = ambiguous_pair_names(pairs)
    if clash is not None:
        (a, b), (c, d) = clash
        raise DatasetError(
            f"the pairs ({a}, {b}) and ({c}, {d}) would share their output files {pair_name(a, b)}.* (shape names "
            f"are joined by '{PAIR_SEPARATOR}'): rename the shapes so that no name holds '{PAIR_SEPARATOR}', or "
            "evaluate only one of these pairs", where)


def check_max_pairs(max_pairs: Any) -> int | None:
    """``max_pairs`` as an int >= 1, or None (all pairs); anything else raises ConfigError."""
    if max_pairs is None:
        return None
    if isinstance(max_pairs, bool) or not isinstance(max_pairs, (int, np.integer)) or max_pairs < 1:
        raise ConfigError(f"max_pairs must be a positive number of pairs or null (all pairs), got {max_pairs!r} "
                          "(evaluate.py max_pairs=N, or data.pairs.<split>.max_pairs in the data config)")
    return int(max_pairs)


class PairDataset(Dataset):
    """Ordered pairs of shapes of a :class:`ShapeDataset`.

    Parameters
    ----------
    shapes
        The shapes.
    pairs
        Explicit pairs as (i, j) indices or (name_x, name_y) names; default: all ordered pairs.
    include_self
        With the default pairs, include (i, i) (Deep Shells and NeuroMorph train on self-pairs too).
    pair_file
        A pair list file (see :func:`read_pair_file`) instead of ``pairs``; a relative path that does not exist
        from the working directory is looked up in the dataset folder (e.g. ``test_pairs.txt`` of FAUST_r).
    max_pairs
        Keep an evenly spaced subset of at most this many pairs (deterministic), e.g. for validation.
    """

    def __init__(
        self,
        shapes: ShapeDataset,
        pairs: Sequence[tuple[int | str, int | str]] | None = None,
        include_self: bool = False,
        pair_file: str | os.PathLike | None = None,
        max_pairs: int | None = None,
    ):
        self.shapes = shapes
        max_pairs = check_max_pairs(max_pairs)
        if pair_file is not None:
            in_root = Path(shapes.root) / pair_file
            if not Path(pair_file).is_absolute() and not Path(pair_file).exists() and in_root.is_file():
                pair_file = in_root
            self.pairs = [self._pair_of_line(pair_file, lineno, a, b) for lineno, a, b in read_pair_lines(pair_file)]
        elif pairs is None:
            n = len(shapes)
            self.pairs = [(i, j) for i in range(n) for j in range(n) if include_self or i != j]
        else:
            listed = [(self._as_index(a), self._as_index(b)) for a, b in pairs]
            self.pairs = list(dict.fromkeys(listed))  # each pair once, in the order listed
            if len(self.pairs) < len(listed):
                warnings.warn(f"{shapes.root}: {len(listed) - len(self.pairs)} repeated pair(s) of the pair list "
                              "dropped, each pair is evaluated once", DatasetWarning, stacklevel=2)
        check_pair_names(((shapes.names[i], shapes.names[j]) for i, j in self.pairs), pair_file or shapes.root)
        if max_pairs is not None and len(self.pairs) > max_pairs:
            keep = np.linspace(0, len(self.pairs) - 1, max_pairs).round().astype(int)
            self.pairs = [self.pairs[k] for k in keep]
        if not self.pairs:
            raise DatasetError(
                f"the pair list is empty: the split has {len(shapes)} shape(s) ({', '.join(shapes.names[:3])}) and "
                "self-pairs are off; a pair needs two shapes (meshes directly inside off/ or shapes/; sub-folders "
                "are not searched)", shapes.root)

    def _pair_of_line(self, path, lineno: int, a: str, b: str) -> tuple[int, int]:
        try:
            return self._as_index(a), self._as_index(b)
        except DatasetError as err:
            raise DatasetError(f"line {lineno}: {err.problem} (dataset folder {err.path})", path) from None

    def _as_index(self, item: int | str) -> int:
        if isinstance(item, str):
            return self.shapes.index(item)
        if not 0 <= int(item) < len(self.shapes):
            raise DatasetError(f"pair index {item} is outside the {len(self.shapes)} shapes", self.shapes.root)
        return int(item)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, k: int) -> PairSample:
        i, j = self.pairs[k]
        return PairSample(self.shapes[i], self.shapes[j])

    def names(self, k: int) -> tuple[str, str]:
        """Names ``(x, y)`` of the shapes of pair ``k``."""
        i, j = self.pairs[k]
        return self.shapes.names[i], self.shapes.names[j]
