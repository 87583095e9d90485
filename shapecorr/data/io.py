"""Reading and writing meshes and correspondence files.

Meshes
------
* ``.off``: read by a strict parser in this module. trimesh's OFF reader silently accepts header counts
  that disagree with the data (it reads a face line as a vertex, or drops data) and moves triangles
  ahead of polygons when a file mixes them; a wrong count must be an error here because ground-truth
  files index vertices by position. Accepted: ``OFF``/``COFF``/``NOFF``/``CNOFF``/``STOFF`` headers
  (extra per-vertex columns are ignored), counts on the header line or the next one, ``#`` comments,
  blank lines, trailing whitespace, per-face colors after the indices. Rejected: binary OFF, dimensions
  other than 3, fewer or more data lines than the header announces.
* ``.ply``, ``.obj``: read with trimesh, ``process=False`` and ``maintain_order=True`` so that vertices
  are never merged, dropped or reordered. The vertex count is checked against the file (PLY header
  counts, OBJ ``v`` lines). An OBJ split by materials arrives as a trimesh ``Scene`` whose pieces share
  the full vertex list; their faces are concatenated. Pieces with different vertex lists are refused.
* Polygons with more than three corners are fan-triangulated (corner 0 with each pair of consecutive
  corners), in place, by every reader: vertices and their order are unchanged, so ground-truth indices
  stay valid. A fan is exact for convex polygons, which quad-dominant scans are.
* Problems with the file (missing, unreadable, empty, unknown extension, not parseable, no faces) raise
  :class:`~shapecorr.errors.MeshReadError`; a file that parses but holds an invalid mesh (NaN, bad or
  repeated indices, degenerate faces, unreferenced vertices) raises
  :class:`~shapecorr.errors.InvalidMeshError` from :func:`~shapecorr.data.validation.validate_mesh`.
  OBJ face indices beyond the vertex list are rejected by trimesh's parser, so they are a
  ``MeshReadError``.
* Written files: ``.off`` as text with every coordinate in Python's shortest round-trip form (``repr``),
  ``.ply`` as binary little-endian with float64 coordinates (trimesh's exporter rounds to float32).
  Both are exact for float64, byte-identical for identical input, and written atomically.

Correspondences
---------------
========  ===========  ==========================================================================
suffix    index base   content
========  ===========  ==========================================================================
``.vts``  one-based    ground-truth vertex index per reference point (FAUST_r/SCAPE_r ``corres/``);
                       whitespace- or newline-separated; entry r of every file is the same point
``.map``  zero-based   point-to-point map, one target index per source vertex, one per line
``.txt``  zero-based   point-to-point map, one per line (shapecorr's maps/<x>__<y>.txt); SHREC files are
                       one-based: pass ``one_based=True``
========  ===========  ==========================================================================

All readers return zero-based int64 arrays; all writers take zero-based arrays.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from os import PathLike
from pathlib import Path

import numpy as np
import trimesh

from shapecorr.data.cache import atomic_open
from shapecorr.data.shape import Normalization, Shape, make_shape
from shapecorr.data.validation import (
    DEFAULT_DEGENERATE_TOL,
    DEFAULT_MAX_DEGENERATE_FRACTION,
    ValidationOptions,
    validate_mesh,
)
from shapecorr.errors import ConfigError, CorrespondenceError, InvalidMeshError, MeshReadError
from shapecorr.geometry.mesh import as_numpy, check_mesh_arrays

#: Mesh formats :func:`read_mesh` understands.
MESH_READ_EXTENSIONS = (".off", ".ply", ".obj")
#: Mesh formats :func:`write_mesh` writes.
MESH_WRITE_EXTENSIONS = (".off", ".ply")
#: Index base of each correspondence format (see the module docstring).
# `.txt` maps are zero-based, as shapecorr writes maps/<x>__<y>.txt (docs/evaluation.md §6); read SHREC-style one-based
# `.txt` files with one_based=True.
CORRESPONDENCE_ONE_BASED = {".vts": True, ".map": False, ".txt": False}

# OFF header keywords: optional ST (texture), C (color), N (normal) prefixes; the 3-D variants only.
_OFF_KEYWORD = re.compile(r"^(ST)?C?N?OFF$")
_INTEGER = re.compile(r"^[+-]?[0-9]+$")
# What trimesh's loaders raise on malformed input (they do not use a common exception type; a
# None-valued parse result surfaces as AttributeError/TypeError).
_TRIMESH_ERRORS = (ValueError, IndexError, KeyError, TypeError, AttributeError, EOFError, UnicodeDecodeError)
# Bytes read at most to find the end of a PLY header.
_PLY_HEADER_MAX_BYTES = 1 << 16
# Bytes in which the 'OFF' keyword of an OFF file is looked for before the whole file is split into lines.
_OFF_HEADER_PROBE_BYTES = 1 << 16


# --------------------------------------------------------------------------------------------- meshes


def _fan_triangulate(polygon: list[int]) -> list[list[int]]:
    return [[polygon[0], polygon[i], polygon[i + 1]] for i in range(1, len(polygon) - 1)]


def _check_off_keyword(path: Path, data: bytes) -> None:
    """Refuse a file whose first data line is not an OFF header, reading only its first bytes.

    So that a large file that is not OFF (a log, a CSV named ``.off``) is refused before it is split into lines.
    """
    head = data[:_OFF_HEADER_PROBE_BYTES].decode("utf-8", errors="replace")
    for number, line in enumerate(head.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if tokens:
            if not _OFF_KEYWORD.match(tokens[0]):
                raise MeshReadError(f"not an OFF file: line {number} starts with {tokens[0][:40]!r}, expected 'OFF'",
                                    path)
            return


def _read_off(path: Path, data: bytes) -> tuple[np.ndarray, np.ndarray]:
    # Hand-written: see the module docstring for what trimesh's OFF reader gets wrong.
    _check_off_keyword(path, data)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise MeshReadError(f"not a text OFF file (binary OFF is not supported): {err}", path) from err
    lines = []  # (line number, tokens) of the non-blank lines, comments removed
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if tokens:
            lines.append((number, tokens))
    if not lines:
        raise MeshReadError("file is empty (no data lines)", path)

    number, header = lines[0]
    keyword = header[0]
    if not _OFF_KEYWORD.match(keyword):
        raise MeshReadError(f"not an OFF file: line {number} starts with {keyword[:40]!r}, expected 'OFF'", path)
    if "BINARY" in (token.upper() for token in header[1:]):
        raise MeshReadError("binary OFF is not supported; convert it to text OFF or PLY", path)
    if len(header) > 1:
        count_tokens, cursor = header[1:], 1
    elif len(lines) > 1:
        (number, count_tokens), cursor = lines[1], 2
    else:
        raise MeshReadError("file ends after the 'OFF' header line (no vertex/face counts)", path)
    if len(count_tokens) not in (2, 3) or not all(_INTEGER.match(token) for token in count_tokens):
        raise MeshReadError(
            f"line {number}: expected counts 'n_vertices n_faces [n_edges]', got {' '.join(count_tokens)!r}", path
        )
    n_verts, n_faces = int(count_tokens[0]), int(count_tokens[1])
    if n_verts <= 0:
        raise MeshReadError(f"line {number}: header declares {n_verts} vertices", path)
    if n_faces <= 0:
        raise MeshReadError(f"header declares {n_faces} faces: a point cloud, not a mesh", path)

    vertex_lines = lines[cursor : cursor + n_verts]
    if len(vertex_lines) < n_verts:
        raise MeshReadError(
            f"file ends after {len(vertex_lines)} of the {n_verts} vertices the header declares "
            "(truncated, or the header counts are wrong)",
            path,
        )
    cursor += n_verts
    face_lines = lines[cursor : cursor + n_faces]
    if len(face_lines) < n_faces:
        raise MeshReadError(
            f"file ends after {len(face_lines)} of the {n_faces} faces the header declares "
            "(truncated, or the header counts are wrong)",
            path,
        )
    cursor += n_faces
    if cursor < len(lines):
        raise MeshReadError(
            f"line {lines[cursor][0]}: unexpected data after the {n_verts} vertices and {n_faces} faces the "
            "header declares (the header counts are wrong)",
            path,
        )

    for number, tokens in vertex_lines:
        if len(tokens) < 3:
            raise MeshReadError(f"line {number}: a vertex needs 3 coordinates, got {' '.join(tokens)!r}", path)
    try:
        verts = np.array([tokens[:3] for _, tokens in vertex_lines], dtype=np.float64)
    except ValueError:
        for number, tokens in vertex_lines:
            try:
                [float(token) for token in tokens[:3]]
            except ValueError as err:
                raise MeshReadError(f"line {number}: invalid vertex coordinate in {' '.join(tokens)!r}", path) from err
        raise  # unreachable: some line failed above

    if all(len(tokens) >= 4 and tokens[0] == "3" for _, tokens in face_lines):
        try:  # fast path: triangles only
            return verts, np.array([tokens[1:4] for _, tokens in face_lines], dtype=np.int64)
        except ValueError:
            pass  # the loop below names the offending line
    faces: list[list[int]] = []
    for number, tokens in face_lines:
        size = int(tokens[0]) if _INTEGER.match(tokens[0]) else -1
        corners = tokens[1 : 1 + size] if size >= 3 else []
        if size < 3 or len(corners) < size or not all(_INTEGER.match(token) for token in corners):
            raise MeshReadError(
                f"line {number}: expected a face 'k i_1 ... i_k' with k >= 3 integer indices, got {' '.join(tokens)!r}",
                path,
            )
        polygon = [int(token) for token in corners]
        if size == 3:
            faces.append(polygon)
        else:
            faces.extend(_fan_triangulate(polygon))
    return verts, np.array(faces, dtype=np.int64)


def _ply_element_counts(path: Path, data: bytes) -> dict[str, int]:
    end = data.find(b"end_header", 0, _PLY_HEADER_MAX_BYTES)
    if not data.startswith(b"ply") or end < 0:
        raise MeshReadError("not a PLY file (no 'ply' magic line or no 'end_header')", path)
    counts = {}
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        tokens = line.split()
        if len(tokens) == 3 and tokens[0] == "element" and _INTEGER.match(tokens[2]):
            counts[tokens[1]] = int(tokens[2])
    return counts


def _read_with_trimesh(path: Path, data: bytes, extension: str) -> tuple[np.ndarray, np.ndarray]:
    file_type = extension[1:]
    try:
        loaded = trimesh.load(str(path), file_type=file_type, process=False, maintain_order=True, skip_materials=True)
    except _TRIMESH_ERRORS as err:
        raise MeshReadError(f"cannot parse {file_type.upper()} file ({type(err).__name__}: {err})", path) from err

    if isinstance(loaded, trimesh.Scene):
        pieces = list(loaded.geometry.values())
        meshes = [piece for piece in pieces if isinstance(piece, trimesh.Trimesh)]
        if not pieces:
            raise MeshReadError(f"no geometry found in the {file_type.upper()} file (empty or not a mesh)", path)
        if not meshes:
            raise MeshReadError("file has no faces: a point cloud, not a mesh", path)
        if len(meshes) != len(pieces) or any(not np.array_equal(m.vertices, meshes[0].vertices) for m in meshes):
            raise MeshReadError(
                f"file holds {len(pieces)} separate pieces with different vertex lists; merge them into one mesh",
                path,
            )
        verts = np.asarray(meshes[0].vertices)
        faces = np.concatenate([np.asarray(m.faces).reshape(-1, 3) for m in meshes])
    elif isinstance(loaded, trimesh.PointCloud):
        raise MeshReadError("file has no faces: a point cloud, not a mesh", path)
    elif isinstance(loaded, trimesh.Trimesh):
        verts, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
    else:
        raise MeshReadError(f"unsupported content ({type(loaded).__name__}) in {file_type.upper()} file", path)

    if faces.size == 0:
        raise MeshReadError("file has no faces: a point cloud, not a mesh (or its face data is truncated)", path)
    if extension == ".ply":
        counts = _ply_element_counts(path, data)
        declared_verts, declared_faces = counts.get("vertex"), counts.get("face", 0)
        if declared_verts is not None and declared_verts != len(verts):
            raise MeshReadError(f"header declares {declared_verts} vertices but {len(verts)} were read", path)
        if len(faces) < declared_faces:  # each declared polygon gives at least one triangle
            raise MeshReadError(
                f"header declares {declared_faces} faces but only {len(faces)} triangles were read (truncated?)", path
            )
    else:
        declared_verts = len(re.findall(rb"^[ \t]*v[ \t]", data, flags=re.MULTILINE))
        if declared_verts != len(verts):
            raise MeshReadError(
                f"file lists {declared_verts} vertices but the reader returned {len(verts)}; "
                "vertex order cannot be trusted",
                path,
            )
    return verts.astype(np.float64), faces.astype(np.int64)


def read_mesh(
    path: str | PathLike,
    validate: bool = True,
    degenerate_tol: float = DEFAULT_DEGENERATE_TOL,
    max_degenerate_fraction: float = DEFAULT_MAX_DEGENERATE_FRACTION,
    allow_unreferenced: bool = False,
    allow_disconnected: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh from an OFF, PLY or OBJ file, keeping the file's vertex order.

    Parameters
    ----------
    path
        ``.off``, ``.ply`` or ``.obj`` file (case-insensitive suffix).
    validate
        Run :func:`~shapecorr.data.validation.validate_mesh` (raising on invalid content, warning on
        non-manifold or multi-component meshes). ``False`` returns the arrays as parsed.
    degenerate_tol, max_degenerate_fraction, allow_unreferenced, allow_disconnected
        Passed to :func:`~shapecorr.data.validation.validate_mesh` (``data.validation.*`` options).

    Returns
    -------
    verts : (n, 3) float64
    faces : (f, 3) int64
        Zero-based; polygons fan-triangulated.

    Raises
    ------
    MeshReadError
        Missing, unreadable, empty, unparseable or unknown-format file, or a file without faces.
    InvalidMeshError
        The content fails validation.
    """
    path = Path(path)
    if not path.exists():
        raise MeshReadError("file not found", path)
    if path.is_dir():
        raise MeshReadError("is a directory, not a mesh file", path)
    extension = path.suffix.lower()
    if extension not in MESH_READ_EXTENSIONS:
        supported = ", ".join(MESH_READ_EXTENSIONS)
        raise MeshReadError(f"unknown mesh extension {extension or '(none)'!r}; supported: {supported}", path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise MeshReadError(f"cannot read file: {err.strerror or err}", path) from err
    if not data or data.isspace():  # (no strip(): it would copy a large file)
        raise MeshReadError("file is empty", path)

    if extension == ".off":
        verts, faces = _read_off(path, data)
    else:
        verts, faces = _read_with_trimesh(path, data, extension)
    if validate:
        validate_mesh(
            verts,
            faces,
            path=path,
            degenerate_tol=degenerate_tol,
            max_degenerate_fraction=max_degenerate_fraction,
            allow_unreferenced=allow_unreferenced,
            allow_disconnected=allow_disconnected,
        )
    return verts, faces


def load_shape(
    path: str | PathLike,
    normalization: Normalization | None = Normalization(),
    validate: bool = True,
    validation: ValidationOptions | None = None,
) -> Shape:
    """Read a mesh file into a normalized :class:`~shapecorr.data.shape.Shape` named after the file stem.

    Parameters
    ----------
    path
        Mesh file (see :func:`read_mesh`).
    normalization
        How to center and scale (``None``: keep the raw coordinates); the transform is stored on the shape.
    validate
        Validate the mesh (see :func:`read_mesh`).
    validation
        The ``data.validation.*`` relaxations (default :class:`~shapecorr.data.validation.ValidationOptions`).
    """
    path = Path(path)
    opts = ValidationOptions() if validation is None else validation
    verts, faces = read_mesh(
        path,
        validate=validate,
        degenerate_tol=opts.degenerate_tol,
        max_degenerate_fraction=opts.max_degenerate_fraction,
        allow_unreferenced=opts.allow_unreferenced,
        allow_disconnected=opts.allow_disconnected,
    )
    try:
        return make_shape(verts, faces, name=path.stem, path=path, normalization=normalization)
    except InvalidMeshError as err:
        if err.path is not None:
            raise
        raise InvalidMeshError(err.problem, path) from err


def _off_bytes(verts: np.ndarray, faces: np.ndarray) -> bytes:
    lines = ["OFF", f"{len(verts)} {len(faces)} 0"]
    # repr() is the shortest decimal string that reads back to the same float64.
    lines += [" ".join(map(repr, row)) for row in verts.tolist()]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces.tolist()]
    return ("\n".join(lines) + "\n").encode("ascii")


def _ply_bytes(verts: np.ndarray, faces: np.ndarray) -> bytes:
    # Hand-written: trimesh's PLY exporter stores coordinates as float32.
    header = (
        "ply\n"
        "format binary_little_endian 1.0\n"
        f"element vertex {len(verts)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\n"
        "property list uchar int vertex_indices\n"
        "end_header\n"
    )
    packed = np.empty(len(faces), dtype=[("count", "u1"), ("index", "<i4", (3,))])
    packed["count"] = 3
    packed["index"] = faces
    return header.encode("ascii") + np.ascontiguousarray(verts, dtype="<f8").tobytes() + packed.tobytes()


def write_mesh(path: str | PathLike, verts: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh as ``.off`` (text) or ``.ply`` (binary), atomically and losslessly.

    Parameters
    ----------
    path
        Output file; its suffix picks the format.
    verts : (n, 3) float
    faces : (f, 3) int
        Zero-based.

    Raises
    ------
    ConfigError
        The suffix is not ``.off`` or ``.ply``.
    InvalidMeshError
        Wrong shapes, NaN/Inf coordinates or out-of-range indices.
    OSError
        The file cannot be written.
    """
    path = Path(path)
    extension = path.suffix.lower()
    if extension not in MESH_WRITE_EXTENSIONS:
        supported = ", ".join(MESH_WRITE_EXTENSIONS)
        raise ConfigError(f"cannot write mesh format {extension or '(none)'!r}; supported: {supported}", path)
    v, f = check_mesh_arrays(as_numpy(verts), as_numpy(faces), path)
    if f.max() >= np.iinfo(np.int32).max:
        raise InvalidMeshError("too many vertices for 32-bit face indices", path)
    data = _off_bytes(v, f) if extension == ".off" else _ply_bytes(v, f)
    with atomic_open(path) as handle:
        handle.write(data)


# ------------------------------------------------------------------------------------ correspondences


def _read_text(path: Path) -> str:
    if not path.exists():
        raise CorrespondenceError("file not found", path)
    if path.is_dir():
        raise CorrespondenceError("is a directory, not a correspondence file", path)
    try:
        return path.read_bytes().decode("utf-8")
    except OSError as err:
        raise CorrespondenceError(f"cannot read file: {err.strerror or err}", path) from err
    except UnicodeDecodeError as err:
        raise CorrespondenceError(f"not a text file: {err}", path) from err


def _check_indices(idx: np.ndarray, path: Path, what: str) -> np.ndarray:
    a = as_numpy(idx)
    if a.ndim != 1 or a.dtype.kind not in "iu":
        raise CorrespondenceError(f"{what} must be a 1-D integer array, got {a.dtype} with shape {a.shape}", path)
    if len(a) and a.min() < 0:
        raise CorrespondenceError(f"{what} has a negative index {int(a.min())}", path)
    return a.astype(np.int64)


def _write_indices(path: Path, idx: np.ndarray) -> None:
    with atomic_open(path) as handle:
        handle.write("".join(f"{i}\n" for i in idx.tolist()).encode("ascii"))


def read_vts(path: str | PathLike, n_verts: int | None = None) -> np.ndarray:
    """Read a ``.vts`` ground-truth file (one-based vertex indices, whitespace-separated).

    Parameters
    ----------
    path
        The ``.vts`` file.
    n_verts
        Vertex count of the shape it belongs to; indices above it are an error.

    Returns
    -------
    (R,) int64
        Zero-based vertex index of each reference point.

    Raises
    ------
    CorrespondenceError
        Missing/unreadable/empty file, a non-integer token, an index < 1 or > ``n_verts``.
    """
    path = Path(path)
    tokens = _read_text(path).split()
    if not tokens:
        raise CorrespondenceError("file is empty (no indices)", path)
    for position, token in enumerate(tokens, start=1):
        if not _INTEGER.match(token):
            raise CorrespondenceError(f"entry {position}: {token[:40]!r} is not an integer index", path)
    idx = np.array([int(token) for token in tokens], dtype=np.int64)
    low = np.flatnonzero(idx < 1)
    if len(low):
        raise CorrespondenceError(
            f"entry {low[0] + 1}: index {idx[low[0]]} is invalid; .vts indices are one-based (>= 1)", path
        )
    if n_verts is not None:
        high = np.flatnonzero(idx > n_verts)
        if len(high):
            raise CorrespondenceError(
                f"entry {high[0] + 1}: index {idx[high[0]]} exceeds the shape's n = {n_verts} vertices", path
            )
    return idx - 1


def write_vts(path: str | PathLike, idx_zero_based: np.ndarray) -> None:
    """Write zero-based vertex indices as a one-based ``.vts`` file (one per line, atomic)."""
    path = Path(path)
    _write_indices(path, _check_indices(idx_zero_based, path, "vts indices") + 1)


#: The evaluate.py option that says whether map files are one-based (named in every map-index error).
MAPS_ONE_BASED_OPTION = "maps_one_based"


#: File that ``evaluate.py`` writes beside its maps (``maps/``): it says the index base, so ``maps_dir=`` reads the
#: folder without ``maps_one_based``.
MAPS_MARKER = "maps.json"


def write_maps_marker(folder: str | PathLike) -> Path:
    """Write :data:`MAPS_MARKER` in ``folder`` (once): its ``.txt`` / ``.npy`` maps are zero-based."""
    path = Path(folder) / MAPS_MARKER
    if not path.is_file():
        content = {"index_base": 0, "layout": "<x>__<y>.txt (one target vertex per line) and <x>__<y>.npy (int64)",
                   "written_by": "shapecorr evaluate.py"}
        with atomic_open(path) as handle:
            handle.write((json.dumps(content, indent=1) + "\n").encode("ascii"))
    return path


def maps_marker_one_based(folder: str | PathLike) -> bool | None:
    """The index base that ``folder``'s :data:`MAPS_MARKER` declares (True: one-based), or None without a marker.

    Raises
    ------
    CorrespondenceError
        The marker exists but is unreadable or declares another base than 0 or 1.
    """
    path = Path(folder) / MAPS_MARKER
    if not path.is_file():
        return None
    try:
        base = json.loads(path.read_text())["index_base"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise CorrespondenceError(f"unreadable maps marker ({type(err).__name__}: {err}); delete it and set "
                                  f"{MAPS_ONE_BASED_OPTION}=true|false", path) from None
    if base not in (0, 1) or isinstance(base, bool):
        raise CorrespondenceError(f"index_base must be 0 or 1, got {base!r}", path)
    return base == 1


def read_map(
    path: str | PathLike, one_based: bool | None = False, n_source: int | None = None, n_target: int | None = None
) -> np.ndarray:
    """Read a point-to-point map: one target vertex index per line, line i for source vertex i.

    Parameters
    ----------
    path
        The map file (``.map``: zero-based; ``.txt``: zero-based unless one_based=True (SHREC), see
        :func:`read_correspondence`).
    one_based
        The file's indices start at 1 (True) or 0 (False). None: not said; then a file that never uses
        index 0 is refused (it is most likely one-based, and reading it zero-based would shift every vertex
        silently), and so is a file using index ``n_target`` (only valid one-based); the message names
        ``maps_one_based``.
    n_source
        Expected number of lines (source vertices).
    n_target
        Target vertex count; indices must lie in ``[0, n_target)`` after conversion.

    Returns
    -------
    (n_source,) int64
        Zero-based point-to-point map, source -> target.

    Raises
    ------
    CorrespondenceError
        Missing/unreadable/empty file, a line without exactly one integer, wrong length, index out of range,
        an ambiguous base with ``one_based=None``.
    """
    path = Path(path)
    values, numbers = [], []
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != 1 or not _INTEGER.match(tokens[0]):
            raise CorrespondenceError(f"line {number}: expected one integer index, got {line.strip()[:60]!r}", path)
        values.append(int(tokens[0]))
        numbers.append(number)
    if not values:
        raise CorrespondenceError("file is empty (no indices)", path)
    raw = np.array(values, dtype=np.int64)
    if one_based is None:
        smallest, largest = int(raw.min()), int(raw.max())
        if smallest >= 1:
            hint = f"; it uses index {largest} = n" if n_target is not None and largest == n_target else ""
            raise CorrespondenceError(
                f"the map never uses index 0 (indices {smallest}..{largest}{hint}): it looks one-based, and read "
                f"as zero-based every vertex would be off by one. Say which: {MAPS_ONE_BASED_OPTION}=true "
                f"(indices start at 1) or {MAPS_ONE_BASED_OPTION}=false (they start at 0)",
                path,
            )
        one_based = False
    p2p = raw - (1 if one_based else 0)
    if n_source is not None and len(p2p) != n_source:
        raise CorrespondenceError(f"map has {len(p2p)} entries but the source shape has {n_source} vertices", path)
    upper = n_target if n_target is not None else np.iinfo(np.int64).max
    bad = np.flatnonzero((p2p < 0) | (p2p >= upper))
    if len(bad):
        first, base = bad[0], int(one_based)
        valid = f">= {base}"
        if n_target is not None:
            valid = f"{base}..{n_target - 1 + base} for a target with n = {n_target} vertices"
        raise CorrespondenceError(
            f"line {numbers[first]}: index {values[first]} is out of range ({'one' if one_based else 'zero'}-based "
            f"as {MAPS_ONE_BASED_OPTION}={'true' if one_based else 'false'} says; valid: {valid}); if the file is "
            f"{'zero' if one_based else 'one'}-based, set {MAPS_ONE_BASED_OPTION}={'false' if one_based else 'true'}",
            path,
        )
    return p2p


def write_map(path: str | PathLike, p2p: np.ndarray, one_based: bool = False) -> None:
    """Write a zero-based point-to-point map ``(n,)``, one index per line, atomically.

    ``one_based=True`` writes indices + 1 (the SHREC ``.txt`` convention).
    """
    path = Path(path)
    _write_indices(path, _check_indices(p2p, path, "map") + (1 if one_based else 0))


def read_correspondence(
    path: str | PathLike,
    n_source: int | None = None,
    n_target: int | None = None,
    one_based: bool | None = None,
) -> np.ndarray:
    """Read a correspondence file, choosing the reader and index base from its suffix.

    ``.vts`` goes to :func:`read_vts` (``n_target`` is the shape's vertex count and ``n_source`` the
    expected number of reference points); ``.map`` and ``.txt`` go to :func:`read_map`. ``one_based``
    overrides :data:`CORRESPONDENCE_ONE_BASED` (e.g. a one-based SHREC ``.txt``).

    Returns
    -------
    (R,) int64
        Zero-based indices.
    """
    path = Path(path)
    extension = path.suffix.lower()
    if extension not in CORRESPONDENCE_ONE_BASED:
        raise CorrespondenceError(
            f"unknown correspondence extension {extension or '(none)'!r}; "
            f"supported: {', '.join(CORRESPONDENCE_ONE_BASED)}",
            path,
        )
    base_one = CORRESPONDENCE_ONE_BASED[extension] if one_based is None else one_based
    if extension == ".vts" and base_one:
        idx = read_vts(path, n_verts=n_target)
        if n_source is not None and len(idx) != n_source:
            raise CorrespondenceError(f"has {len(idx)} reference points, expected {n_source}", path)
        return idx
    return read_map(path, one_based=base_one, n_source=n_source, n_target=n_target)


def _vts_file(root: str | PathLike, name: str) -> Path:
    """The file a :func:`check_vts_lengths` key stands for: a shape name, or already a ``.vts`` path."""
    candidate = Path(name)
    if candidate.suffix.lower() == ".vts":
        return candidate if candidate.is_absolute() else Path(root) / candidate
    return Path(root) / f"{name}.vts"


def check_vts_lengths(vts_by_name: dict[str, np.ndarray], root: str | PathLike) -> None:
    """Check that all ground-truth files of a dataset list the same number of reference points.

    Parameters
    ----------
    vts_by_name
        Shape name (file ``root / f"{name}.vts"``) or ``.vts`` path -> its indices.
    root
        Folder holding the ``.vts`` files, used in the error message.

    Raises
    ------
    CorrespondenceError
        Naming the first file whose length differs from the most common length, and both lengths.
    """
    lengths = {name: len(idx) for name, idx in vts_by_name.items()}
    if len(set(lengths.values())) <= 1:
        return
    common = Counter(lengths.values()).most_common(1)[0][0]
    reference = next(name for name, length in lengths.items() if length == common)
    offender = next(name for name, length in lengths.items() if length != common)
    raise CorrespondenceError(
        f"has {lengths[offender]} reference points but {_vts_file(root, reference).name} has {common}; all .vts "
        "files of a dataset must list the same reference points",
        _vts_file(root, offender),
    )
