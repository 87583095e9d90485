"""Malformed inputs must raise the exact ShapeCorrError subclass naming the file; odd-but-usable meshes
must warn (MeshWarning) and still load."""

from __future__ import annotations

import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import trimesh

from shapecorr.data.io import check_vts_lengths, read_correspondence, read_map, read_mesh, read_vts
from shapecorr.data.validation import (
    MeshWarning,
    check_mesh_arrays,
    non_manifold_edges,
    validate_mesh,
)
from shapecorr.errors import CorrespondenceError, InvalidMeshError, MeshReadError

# A valid tetrahedron surface; every malformed mesh below is a small edit of it.
TETRA_VERTS = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
TETRA_FACES = "3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n"
TETRA_OFF = "OFF\n4 4 0\n" + TETRA_VERTS + TETRA_FACES


def off(verts: str = TETRA_VERTS, faces: str = TETRA_FACES, counts: str | None = None) -> str:
    n_v, n_f = verts.count("\n"), faces.count("\n")
    return f"OFF\n{counts or f'{n_v} {n_f} 0'}\n{verts}{faces}"


def ply_ascii(verts: str = TETRA_VERTS, faces: str = TETRA_FACES, n_v: int = 4, n_f: int | None = 4) -> str:
    face_header = "" if n_f is None else f"element face {n_f}\nproperty list uchar int vertex_indices\n"
    return (
        "ply\nformat ascii 1.0\n"
        f"element vertex {n_v}\nproperty float x\nproperty float y\nproperty float z\n"
        f"{face_header}end_header\n{verts}{faces}"
    )


def ply_binary_truncated() -> bytes:
    mesh = trimesh.Trimesh(np.eye(4, 3), [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], process=False)
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
    return data[:-7]


def obj(verts: str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n",
        faces: str = "f 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n") -> str:
    return verts + faces


def mesh_reader(path: Path) -> None:
    read_mesh(path)


def vts_reader(n_verts: int | None = 4):
    return lambda path: read_vts(path, n_verts=n_verts)


def map_reader(**kwargs):
    return lambda path: read_map(path, **kwargs)


def lengths_checker(path: Path) -> None:
    # path is a.vts (5 entries); b.vts and c.vts have 4: a.vts is the odd one out.
    vts = {name: read_vts(path.parent / f"{name}.vts") for name in ("b", "a", "c")}
    check_vts_lengths(vts, path.parent)


# (id, file name, content or None for "do not create", reader, exact error class)
CASES = [
    ("missing-file", "missing.off", None, mesh_reader, MeshReadError),
    ("empty-off", "empty.off", "", mesh_reader, MeshReadError),
    ("whitespace-only-off", "blank.off", "  \n\n \t\n", mesh_reader, MeshReadError),
    ("empty-ply", "empty.ply", "", mesh_reader, MeshReadError),
    ("garbage-off", "garbage.off", "hello world\nthis is not a mesh\n", mesh_reader, MeshReadError),
    ("garbage-ply", "garbage.ply", "ply\nnonsense\n", mesh_reader, MeshReadError),
    ("garbage-obj", "garbage.obj", "hello world\nthis is not a mesh\n", mesh_reader, MeshReadError),
    ("binary-garbage-off", "bin.off", b"\xff\xfe\x00\x01OFF", mesh_reader, MeshReadError),
    ("off-too-many-vertices-declared", "counts1.off", off(counts="5 4 0"), mesh_reader, MeshReadError),
    ("off-too-few-faces-declared", "counts2.off", off(counts="4 3 0"), mesh_reader, MeshReadError),
    ("off-too-few-vertices-declared", "counts3.off", off(counts="3 4 0"), mesh_reader, MeshReadError),
    ("off-bad-count-line", "counts4.off", off(counts="four 4 0"), mesh_reader, MeshReadError),
    ("off-truncated", "trunc.off", TETRA_OFF[:-20], mesh_reader, MeshReadError),
    ("off-header-only", "header.off", "OFF\n", mesh_reader, MeshReadError),
    ("off-non-numeric-coordinate", "coord.off", off(verts="0 0 0\n1 x 0\n0 1 0\n0 0 1\n"), mesh_reader, MeshReadError),
    ("off-two-corner-face", "edge.off", off(faces="3 0 2 1\n3 0 1 3\n3 1 2 3\n2 0 3\n"), mesh_reader, MeshReadError),
    ("off-binary", "binary.off", "OFF BINARY\n", mesh_reader, MeshReadError),
    ("off-4d", "four.off", "4OFF\n1 1 0\n0 0 0 0\n3 0 0 0\n", mesh_reader, MeshReadError),
    ("ply-truncated-ascii", "trunc.ply", ply_ascii(faces="3 0 2 1\n"), mesh_reader, MeshReadError),
    ("ply-truncated-binary", "trunc_bin.ply", ply_binary_truncated(), mesh_reader, MeshReadError),
    ("off-nan-coordinate", "nan.off", off(verts="0 0 0\n1 nan 0\n0 1 0\n0 0 1\n"), mesh_reader, InvalidMeshError),
    ("off-inf-coordinate", "inf.off", off(verts="0 0 0\n1 0 0\n0 1 -inf\n0 0 1\n"), mesh_reader, InvalidMeshError),
    ("ply-inf-coordinate", "inf.ply", ply_ascii(verts="inf 0 0\n1 0 0\n0 1 0\n0 0 1\n"), mesh_reader, InvalidMeshError),
    ("obj-nan-coordinate", "nan.obj", obj(verts="v 0 0 0\nv nan 0 0\nv 0 1 0\nv 0 0 1\n"),
     mesh_reader, InvalidMeshError),
    ("off-index-out-of-range", "oob.off", off(faces="3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 4\n"),
     mesh_reader, InvalidMeshError),
    ("ply-index-out-of-range", "oob.ply", ply_ascii(faces="3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 9\n"),
     mesh_reader, InvalidMeshError),
    ("off-negative-index", "neg.off", off(faces="3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 -1 2\n"),
     mesh_reader, InvalidMeshError),
    ("ply-negative-index", "neg.ply", ply_ascii(faces="3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 -1 2\n"),
     mesh_reader, InvalidMeshError),
    ("obj-index-out-of-range", "oob.obj", obj(faces="f 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 9\n"),
     mesh_reader, MeshReadError),
    ("off-repeated-index-face", "rep.off", off(faces="3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 3\n"),
     mesh_reader, InvalidMeshError),
    ("off-zero-area-face", "flat.off",
     off(verts="0 0 0\n1 0 0\n0 1 0\n0 0 1\n2 0 0\n", faces=TETRA_FACES + "3 0 1 4\n"),
     mesh_reader, InvalidMeshError),
    ("off-unreferenced-vertex", "unref.off", off(verts=TETRA_VERTS + "5 5 5\n"), mesh_reader, InvalidMeshError),
    ("off-point-cloud", "cloud.off", "OFF\n4 0 0\n" + TETRA_VERTS, mesh_reader, MeshReadError),
    ("ply-point-cloud", "cloud.ply", ply_ascii(faces="", n_f=None), mesh_reader, MeshReadError),
    ("obj-point-cloud", "cloud.obj", obj(faces=""), mesh_reader, MeshReadError),
    ("unknown-extension", "mesh.stl", TETRA_OFF, mesh_reader, MeshReadError),
    ("no-extension", "mesh", TETRA_OFF, mesh_reader, MeshReadError),
    ("vts-missing", "missing.vts", None, vts_reader(), CorrespondenceError),
    ("vts-index-zero", "zero.vts", "1\n0\n2\n", vts_reader(), CorrespondenceError),
    ("vts-negative", "neg.vts", "1 -3 2\n", vts_reader(), CorrespondenceError),
    ("vts-index-above-n", "big.vts", "1\n5\n2\n", vts_reader(4), CorrespondenceError),
    ("vts-non-integer-token", "float.vts", "1\n2.5\n3\n", vts_reader(), CorrespondenceError),
    ("vts-text-token", "text.vts", "1 2 three\n", vts_reader(), CorrespondenceError),
    ("vts-empty", "empty.vts", "\n \n", vts_reader(), CorrespondenceError),
    ("map-wrong-length", "short.map", "0\n1\n2\n", map_reader(n_source=4, n_target=4), CorrespondenceError),
    ("map-out-of-range", "oob.map", "0\n1\n4\n2\n", map_reader(n_source=4, n_target=4), CorrespondenceError),
    ("map-negative", "neg.map", "0\n-1\n2\n", map_reader(), CorrespondenceError),
    ("map-two-columns", "pairs.map", "0 1\n1 2\n", map_reader(), CorrespondenceError),
    ("map-non-integer", "float.map", "0\n1.0\n", map_reader(), CorrespondenceError),
    ("map-empty", "empty.map", "", map_reader(), CorrespondenceError),
    ("txt-map-one-based-zero", "shrec.txt", "1\n0\n2\n", lambda p: read_correspondence(p, one_based=True),
     CorrespondenceError),
    ("unknown-correspondence-extension", "map.csv", "0\n1\n", lambda p: read_correspondence(p), CorrespondenceError),
    ("vts-different-lengths", "a.vts", "1 2 3 4 5\n", lengths_checker, CorrespondenceError),
]


@pytest.mark.parametrize("name, content, reader, error", [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_malformed_input_raises_exact_error_naming_file(tmp_path, name, content, reader, error):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
    if name == "a.vts":  # the two files a.vts is compared with
        (tmp_path / "b.vts").write_text("1 2 3 4\n")
        (tmp_path / "c.vts").write_text("4 3 2 1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # trimesh may log/warn on garbage; only the raised error matters
        with pytest.raises(Exception) as info:
            reader(path)
    assert type(info.value) is error, f"{type(info.value).__name__}: {info.value}"
    assert name in str(info.value)
    assert info.value.path is not None and Path(info.value.path).name == name


def test_vts_length_error_names_both_lengths(tmp_path):
    vts = {"a": np.arange(5), "b": np.arange(4), "c": np.arange(4)}
    with pytest.raises(CorrespondenceError) as info:
        check_vts_lengths(vts, tmp_path)
    message = str(info.value)
    assert "a.vts" in message and "b.vts" in message and "5" in message and "4" in message
    # Keys may also be the .vts paths themselves.
    with pytest.raises(CorrespondenceError) as info:
        check_vts_lengths({str(tmp_path / "x.vts"): np.arange(2), str(tmp_path / "y.vts"): np.arange(3),
                           str(tmp_path / "z.vts"): np.arange(3)}, tmp_path)
    assert info.value.path == str(tmp_path / "x.vts") and "y.vts has 3" in str(info.value)
    check_vts_lengths({"a": np.arange(3), "b": np.arange(3)}, tmp_path)  # consistent: no error
    check_vts_lengths({}, tmp_path)


def test_directory_is_not_a_mesh(tmp_path):
    folder = tmp_path / "shape.off"
    folder.mkdir()
    with pytest.raises(MeshReadError, match="directory"):
        read_mesh(folder)


# ------------------------------------------------------------------------------ array-level checks


@pytest.mark.parametrize(
    "verts, faces, match",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), dtype=int), "no vertices"),
        (np.eye(3), np.zeros((0, 3), dtype=int), "no faces"),
        (np.zeros((4, 2)), [[0, 1, 2]], r"shape \(n, 3\)"),
        (np.eye(3), [[0, 1, 2, 0]], r"shape \(f, 3\)"),
        (np.eye(3), np.array([[0.0, 1.0, 2.0]]), "integers"),
        (np.array([["a", "b", "c"]] * 3), [[0, 1, 2]], "numeric"),
        (np.eye(3), [[0, 1, 3]], "outside"),
    ],
)
def test_check_mesh_arrays_rejects_structure_errors(verts, faces, match):
    with pytest.raises(InvalidMeshError, match=match) as info:
        check_mesh_arrays(verts, faces, path="x.off")
    assert type(info.value) is InvalidMeshError and "x.off" in str(info.value)


def test_check_mesh_arrays_returns_float64_int64():
    v, f = check_mesh_arrays(np.eye(3, dtype=np.float32), np.array([[0, 1, 2]], dtype=np.int32))
    assert v.dtype == np.float64 and f.dtype == np.int64


def _with_slivers(verts, faces, count):
    """Flatten `count` faces with pairwise disjoint vertices: corner c moves to the midpoint of edge (a, b),
    so exactly those faces get zero area and the connectivity stays manifold."""
    verts = verts.copy()
    used: set[int] = set()
    flattened = 0
    for a, b, c in faces.tolist():
        if flattened == count:
            break
        if used.isdisjoint((a, b, c)):
            verts[c] = (verts[a] + verts[b]) / 2
            used.update((a, b, c))
            flattened += 1
    return verts, faces


def test_clean_meshes_emit_no_warning(unit_sphere):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert validate_mesh(*unit_sphere()) == []
        torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=24, minor_sections=12)
        assert validate_mesh(torus.vertices, torus.faces) == []
        box = trimesh.creation.box()
        assert validate_mesh(box.vertices, box.faces) == []


def test_few_degenerate_faces_warn_many_raise(unit_sphere):
    verts, faces = unit_sphere(3)  # 1280 faces: the default fraction 1e-3 allows one sliver
    v1, f1 = _with_slivers(verts, faces, 1)
    with pytest.warns(MeshWarning, match="1 of 1280 faces are degenerate"):
        messages = validate_mesh(v1, f1, path="sliver.off")
    assert any("degenerate" in m and "sliver.off" in m for m in messages)
    v3, f3 = _with_slivers(verts, faces, 3)
    with pytest.raises(InvalidMeshError, match="3 of 1280 faces are degenerate"):
        validate_mesh(v3, f3)
    with pytest.warns(MeshWarning, match="degenerate"):
        validate_mesh(v3, f3, max_degenerate_fraction=0.01)
    with pytest.raises(InvalidMeshError, match="degenerate"):
        validate_mesh(v1, f1, max_degenerate_fraction=0.0)


def test_degenerate_tolerance_is_relative_to_mean_area(unit_sphere):
    verts, faces = unit_sphere(2)
    # The same mesh at any scale: same verdict (no degenerate face at 1e-12 relative).
    for scale in (1e-6, 1.0, 1e6):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            validate_mesh(verts * scale, faces)
    # A tolerance above the smallest relative area flags faces.
    areas = trimesh.Trimesh(verts, faces, process=False).area_faces
    with pytest.raises(InvalidMeshError, match="degenerate"):
        validate_mesh(verts, faces, degenerate_tol=1.5 * areas.min() / areas.mean())


def test_unreferenced_vertices_allowed_with_warning(unit_sphere):
    verts, faces = unit_sphere(1)
    verts = np.vstack([verts, [[5.0, 5.0, 5.0]]])
    with pytest.raises(InvalidMeshError, match="not used by any face"):
        validate_mesh(verts, faces)
    with pytest.warns(MeshWarning, match="not used by any face"):
        validate_mesh(verts, faces, allow_unreferenced=True)


def test_all_zero_area_mesh_is_rejected():
    verts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    with pytest.raises(InvalidMeshError, match="degenerate"):
        validate_mesh(verts, [[0, 1, 2], [1, 2, 3]])


def _write_off(path: Path, verts: np.ndarray, faces: np.ndarray) -> Path:
    lines = [f"{len(verts)} {len(faces)} 0"] + [" ".join(map(repr, v)) for v in verts.tolist()]
    lines += ["3 " + " ".join(map(str, f)) for f in faces.tolist()]
    path.write_text("OFF\n" + "\n".join(lines) + "\n")
    return path


def test_non_manifold_edge_warns_and_loads(tmp_path):
    # Three triangles sharing the edge (0, 1): a "book" with three pages.
    verts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=float)
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    path = _write_off(tmp_path / "book.off", verts, faces)
    with pytest.warns(MeshWarning, match="1 non-manifold edges") as record:
        v, f = read_mesh(path)
    assert "book.off" in str(record[0].message)
    assert v.shape == (5, 3) and f.shape == (3, 3)


def test_non_manifold_vertex_warns_and_loads(tmp_path):
    # Two tetrahedra touching at vertex 0 only: every edge is manifold, vertex 0 is not.
    tetra = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    faces = np.vstack([tetra, np.where(tetra == 0, 0, tetra + 3)])
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=float)
    path = _write_off(tmp_path / "bowtie.off", verts, faces)
    with pytest.warns(MeshWarning) as record:
        v, f = read_mesh(path)
    messages = [str(r.message) for r in record]
    assert any("1 non-manifold vertices" in m and "vertex 0" in m for m in messages)
    assert not any("non-manifold edges" in m for m in messages)
    assert len(v) == 7 and len(f) == 8


def test_multiple_components_warn_and_load(tmp_path, unit_sphere):
    a, fa = unit_sphere(1)
    b, fb = unit_sphere(0)
    verts = np.vstack([a, b + 3.0])
    faces = np.vstack([fa, fb + len(a)])
    path = _write_off(tmp_path / "two.off", verts, faces)
    with pytest.warns(MeshWarning, match=rf"2 connected components \(vertex counts {len(a)}, {len(b)}\)"):
        v, f = read_mesh(path)
    assert len(v) == len(a) + len(b)


def test_non_manifold_edges_matches_naive_count(unit_sphere):
    rng = np.random.default_rng(0)
    faces = np.array([rng.choice(12, size=3, replace=False) for _ in range(60)])
    counts = Counter(tuple(sorted(e)) for f in faces.tolist() for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])))
    expected = sorted(e for e, c in counts.items() if c > 2)
    assert expected, "the random soup should contain non-manifold edges"
    assert non_manifold_edges(faces).tolist() == [list(e) for e in expected]
    assert non_manifold_edges(unit_sphere(1)[1]).shape == (0, 2)
