"""Mesh and correspondence I/O: exact round trips, vertex order as in the file, parser variants,
normalization on load."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from shapecorr.data.io import (
    check_vts_lengths,
    load_shape,
    read_correspondence,
    read_map,
    read_mesh,
    read_vts,
    write_map,
    write_mesh,
    write_vts,
)
from shapecorr.data.shape import Normalization, triangle_areas
from shapecorr.errors import ConfigError, InvalidMeshError

SEED = 0


def _bumpy_sphere(subdivisions: int = 2, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere with random radial noise and an odd offset/scale, so coordinates have full mantissas."""
    mesh = trimesh.creation.icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    verts = np.asarray(mesh.vertices) * (1 + 0.1 * rng.random((len(mesh.vertices), 1)))
    return verts * 123.456789 + np.array([1e-3, -7.5, 1e4]), np.asarray(mesh.faces, dtype=np.int64)


def _permuted(verts, faces, seed=SEED):
    """The same mesh with its vertices in a random order (faces reindexed)."""
    perm = np.random.default_rng(seed).permutation(len(verts))
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    return verts[perm], inverse[faces]


# -------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("suffix", [".off", ".ply", ".OFF"])
def test_write_read_round_trip_is_exact_and_keeps_order(tmp_path, suffix):
    verts, faces = _permuted(*_bumpy_sphere())
    path = tmp_path / f"mesh{suffix}"
    write_mesh(path, verts, faces)
    v, f = read_mesh(path)
    assert v.dtype == np.float64 and f.dtype == np.int64
    np.testing.assert_array_equal(v, verts)  # exact in float64, hence in float32
    np.testing.assert_array_equal(f, faces)


@pytest.mark.parametrize("suffix", [".off", ".ply"])
def test_float32_input_round_trips_exactly(tmp_path, suffix):
    verts, faces = _bumpy_sphere(1)
    verts32 = verts.astype(np.float32)
    write_mesh(tmp_path / f"m{suffix}", verts32, faces.astype(np.int32))
    v, f = read_mesh(tmp_path / f"m{suffix}")
    np.testing.assert_array_equal(v.astype(np.float32), verts32)
    np.testing.assert_array_equal(f, faces)


def test_extreme_magnitudes_round_trip(tmp_path):
    verts, faces = _bumpy_sphere(1)
    verts[0] = [1e-300, -5e-324, 1.7976931348623157e308]
    verts[1] = [0.1, 1 / 3, -0.0]
    for suffix in (".off", ".ply"):
        write_mesh(tmp_path / f"m{suffix}", verts, faces)
        v, _ = read_mesh(tmp_path / f"m{suffix}", validate=False)
        np.testing.assert_array_equal(v, verts)


@pytest.mark.parametrize("suffix", [".off", ".ply"])
def test_written_bytes_are_deterministic(tmp_path, suffix):
    verts, faces = _bumpy_sphere(1)
    write_mesh(tmp_path / f"a{suffix}", verts, faces)
    write_mesh(tmp_path / f"b{suffix}", verts.copy(), faces.copy())
    assert (tmp_path / f"a{suffix}").read_bytes() == (tmp_path / f"b{suffix}").read_bytes()
    write_mesh(tmp_path / f"a{suffix}", verts, faces)  # overwrite in place: same bytes, no temp left over
    assert (tmp_path / f"a{suffix}").read_bytes() == (tmp_path / f"b{suffix}").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"a{suffix}", f"b{suffix}"]


def test_written_files_are_read_identically_by_trimesh(tmp_path):
    verts, faces = _bumpy_sphere(1)
    for suffix in (".off", ".ply"):
        write_mesh(tmp_path / f"m{suffix}", verts, faces)
        mesh = trimesh.load(tmp_path / f"m{suffix}", process=False)
        np.testing.assert_array_equal(mesh.vertices, verts)
        np.testing.assert_array_equal(mesh.faces, faces)


def test_write_mesh_rejects_bad_input_and_writes_nothing(tmp_path):
    verts, faces = _bumpy_sphere(0)
    with pytest.raises(ConfigError, match="obj"):
        write_mesh(tmp_path / "m.obj", verts, faces)
    bad = verts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InvalidMeshError, match="NaN"):
        write_mesh(tmp_path / "m.off", bad, faces)
    with pytest.raises(InvalidMeshError, match="outside"):
        write_mesh(tmp_path / "m.ply", verts, faces + 1)
    assert list(tmp_path.iterdir()) == []


def test_write_mesh_accepts_torch_tensors(tmp_path):
    torch = pytest.importorskip("torch")
    verts, faces = _bumpy_sphere(0)
    write_mesh(tmp_path / "t.off", torch.from_numpy(verts), torch.from_numpy(faces))
    np.testing.assert_array_equal(read_mesh(tmp_path / "t.off")[0], verts)


# ------------------------------------------------------------------------- vertex order and merging


def _split_cube() -> tuple[np.ndarray, np.ndarray]:
    """A cube whose faces do not share vertices: 36 vertices with only 8 distinct positions. Valid for
    validation (every vertex referenced, no zero-area face), so any merge by a reader shows up."""
    box = trimesh.creation.box()
    faces = np.arange(3 * len(box.faces)).reshape(-1, 3)
    return np.asarray(box.vertices)[box.faces.ravel()], faces


def _obj_text(verts, faces) -> str:
    return "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in verts.tolist()) + "".join(
        f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces.tolist()
    )


def test_duplicate_positions_are_not_merged(tmp_path):
    verts, faces = _split_cube()
    (tmp_path / "cube.obj").write_text(_obj_text(verts, faces))
    write_mesh(tmp_path / "cube.off", verts, faces)
    write_mesh(tmp_path / "cube.ply", verts, faces)
    for name in ("cube.obj", "cube.off", "cube.ply"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # 12 components: expected for a split cube
            v, f = read_mesh(tmp_path / name)
        assert len(v) == 36, name
        np.testing.assert_array_equal(v, verts)
        np.testing.assert_array_equal(f, faces)


def test_obj_and_ascii_ply_keep_file_vertex_order(tmp_path):
    # Faces reference vertices in the reverse of file order: a reader that reorders by first use would
    # change the vertex array.
    verts, faces = _bumpy_sphere(1)
    faces = faces[::-1, ::-1].copy()
    verts, faces = _permuted(verts, faces, seed=1)
    (tmp_path / "m.obj").write_text(_obj_text(verts, faces))
    header = (
        f"ply\nformat ascii 1.0\nelement vertex {len(verts)}\nproperty double x\nproperty double y\n"
        f"property double z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in verts.tolist()) + "".join(
        f"3 {a} {b} {c}\n" for a, b, c in faces.tolist()
    )
    (tmp_path / "m.ply").write_text(header + body)
    for name in ("m.obj", "m.ply"):
        v, f = read_mesh(tmp_path / name)
        np.testing.assert_array_equal(v, verts)
        np.testing.assert_array_equal(f, faces)


def test_obj_with_texture_normals_and_materials(tmp_path):
    # Two materials make trimesh return a Scene; its pieces share the vertex list and are merged.
    text = (
        "mtllib missing.mtl\n"
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
        "vt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n"
        "usemtl red\nf 1/1/1 3/3/1 2/2/1\nf 1/1/1 2/2/1 4/3/1\n"
        "usemtl blue\nf 2/2/1 3/3/1 4/1/1\nf 1/1/1 4/3/1 3/2/1\n"
    )
    (tmp_path / "tet.obj").write_text(text)
    v, f = read_mesh(tmp_path / "tet.obj")
    np.testing.assert_array_equal(v, np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float))
    expected = {(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)}
    assert {tuple(face) for face in f.tolist()} == expected and len(f) == 4


# ---------------------------------------------------------------------------------- OFF variants

TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
OFF_VARIANTS = {
    "plain": "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n",
    "comments-blank-lines": "# made by hand\nOFF\n# counts follow\n4 4 0\n\n0 0 0 # origin\n1 0 0\n0 1 0\n0 0 1\n"
    "3 0 2 1\n3 0 1 3\n\n3 1 2 3\n3 0 3 2\n# end\n",
    "counts-on-header-line": "OFF 4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n",
    "no-edge-count": "OFF\n4 4\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n",
    "trailing-whitespace-crlf": "OFF  \r\n4 4 0 \r\n0 0 0  \r\n1 0 0\t\r\n0 1 0\r\n0 0 1\r\n3 0 2 1 \r\n"
    "3 0 1 3\r\n3 1 2 3\r\n3 0 3 2  \r\n\r\n\r\n",
    "coff-vertex-colors": "COFF\n4 4 0\n0 0 0 255 0 0 255\n1 0 0 0 255 0 255\n0 1 0 0 0 255 255\n"
    "0 0 1 9 9 9 255\n3 0 2 1\n3 0 1 3\n3 1 2 3\n3 0 3 2\n",
    "noff-normals": "NOFF\n4 4 0\n0 0 0 0 0 1\n1 0 0 0 0 1\n0 1 0 0 0 1\n0 0 1 0 0 1\n3 0 2 1\n3 0 1 3\n"
    "3 1 2 3\n3 0 3 2\n",
    "face-colors": "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1 255 0 0\n3 0 1 3 0 255 0\n3 1 2 3 1 1 1\n"
    "3 0 3 2 0.5 0.5 0.5\n",
    "scientific-notation": "OFF\n4 4 0\n0e0 0.0 -0\n1E0 0 0\n0 1.000 0\n0 0 10e-1\n3 0 2 1\n3 0 1 3\n"
    "3 1 2 3\n3 0 3 2\n",
}


@pytest.mark.parametrize("variant", sorted(OFF_VARIANTS))
def test_off_parser_variants(tmp_path, variant):
    path = tmp_path / f"{variant}.off"
    path.write_bytes(OFF_VARIANTS[variant].encode())
    v, f = read_mesh(path)
    np.testing.assert_array_equal(v, TETRA)
    np.testing.assert_array_equal(f, TETRA_FACES)


@pytest.mark.parametrize("variant", ["plain", "comments-blank-lines", "counts-on-header-line", "coff-vertex-colors"])
def test_off_parser_agrees_with_trimesh_where_trimesh_is_right(tmp_path, variant):
    path = tmp_path / f"{variant}.off"
    path.write_bytes(OFF_VARIANTS[variant].encode())
    ours = read_mesh(path)
    theirs = trimesh.load(path, process=False, maintain_order=True)
    np.testing.assert_array_equal(ours[0], theirs.vertices)
    np.testing.assert_array_equal(ours[1], theirs.faces)


def test_polygons_are_fan_triangulated_in_place(tmp_path):
    # A unit square split as quad (0 1 2 3) + pentagon (1 4 5 6 2) + triangle; face order is kept.
    text = (
        "OFF\n7 3 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 0 0\n2.5 0.5 0\n2 1 0\n"
        "4 0 1 2 3\n3 1 4 2\n5 1 4 5 6 2\n"
    )
    (tmp_path / "poly.off").write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the stacked faces make non-manifold edges; not the point here
        v, f = read_mesh(tmp_path / "poly.off")
    expected = [[0, 1, 2], [0, 2, 3], [1, 4, 2], [1, 4, 5], [1, 5, 6], [1, 6, 2]]
    assert f.tolist() == expected
    assert len(v) == 7
    # Fan triangulation of a convex polygon preserves its area.
    areas = triangle_areas(v, f)
    assert areas[:2].sum() == pytest.approx(1.0)


def test_ply_and_obj_quads_are_triangulated(tmp_path):
    quad_ply = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    (tmp_path / "q.ply").write_text(quad_ply)
    (tmp_path / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    for name in ("q.ply", "q.obj"):
        v, f = read_mesh(tmp_path / name)
        assert f.shape == (2, 3) and triangle_areas(v, f).sum() == pytest.approx(1.0)


# -------------------------------------------------------------------------------- correspondences


def test_vts_round_trip_and_one_based_on_disk(tmp_path):
    idx = np.random.default_rng(SEED).integers(0, 500, size=137)
    write_vts(tmp_path / "a.vts", idx)
    on_disk = [int(line) for line in (tmp_path / "a.vts").read_text().split()]
    assert on_disk == (idx + 1).tolist()
    back = read_vts(tmp_path / "a.vts", n_verts=500)
    assert back.dtype == np.int64
    np.testing.assert_array_equal(back, idx)


def test_vts_accepts_any_whitespace(tmp_path):
    (tmp_path / "w.vts").write_text("  3 1\t2\r\n\n5  \n")
    np.testing.assert_array_equal(read_vts(tmp_path / "w.vts", n_verts=5), [2, 0, 1, 4])


def test_vts_at_upper_bound_is_valid(tmp_path):
    (tmp_path / "b.vts").write_text("1\n10\n")
    np.testing.assert_array_equal(read_vts(tmp_path / "b.vts", n_verts=10), [0, 9])


@pytest.mark.parametrize("one_based", [False, True])
def test_map_round_trip(tmp_path, one_based):
    p2p = np.random.default_rng(SEED).integers(0, 300, size=250)
    write_map(tmp_path / "x__y.map", p2p, one_based=one_based)
    lines = (tmp_path / "x__y.map").read_text().splitlines()
    assert len(lines) == 250 and int(lines[0]) == p2p[0] + one_based
    back = read_map(tmp_path / "x__y.map", one_based=one_based, n_source=250, n_target=300)
    np.testing.assert_array_equal(back, p2p)


def test_read_correspondence_dispatches_by_suffix(tmp_path):
    (tmp_path / "a.vts").write_text("1 2 3\n")
    (tmp_path / "a.map").write_text("1\n2\n3\n")
    (tmp_path / "a.txt").write_text("1\n2\n3\n")
    np.testing.assert_array_equal(read_correspondence(tmp_path / "a.vts", n_target=3), [0, 1, 2])
    np.testing.assert_array_equal(read_correspondence(tmp_path / "a.map", n_target=4), [1, 2, 3])
    np.testing.assert_array_equal(read_correspondence(tmp_path / "a.txt", one_based=True, n_target=3), [0, 1, 2])
    np.testing.assert_array_equal(read_correspondence(tmp_path / "a.txt"), [1, 2, 3])


def test_check_vts_lengths_on_files_written_by_write_vts(tmp_path):
    from shapecorr.errors import CorrespondenceError

    rng = np.random.default_rng(SEED)
    written = {name: rng.integers(0, 100, size=40) for name in ("s0", "s1", "s2")}
    for name, idx in written.items():
        write_vts(tmp_path / f"{name}.vts", idx)
    read = {name: read_vts(tmp_path / f"{name}.vts") for name in written}
    for name, idx in written.items():
        np.testing.assert_array_equal(read[name], idx)  # zero-based in, zero-based out (one-based on disk)
    assert check_vts_lengths(read, tmp_path) is None  # equal lengths pass
    write_vts(tmp_path / "s3.vts", rng.integers(0, 100, size=39))
    read["s3"] = read_vts(tmp_path / "s3.vts")
    with pytest.raises(CorrespondenceError, match="has 39 reference points but s0.vts has 40") as err:
        check_vts_lengths(read, tmp_path)
    assert str(err.value).startswith(str(tmp_path / "s3.vts"))  # the message names the odd file first


def test_write_map_rejects_non_integer_or_negative(tmp_path):
    from shapecorr.errors import CorrespondenceError

    with pytest.raises(CorrespondenceError, match="integer"):
        write_map(tmp_path / "f.map", np.array([0.0, 1.0]))
    with pytest.raises(CorrespondenceError, match="negative"):
        write_vts(tmp_path / "n.vts", np.array([0, -2]))
    assert not any(tmp_path.iterdir())


# ---------------------------------------------------------------------------------- load_shape


def test_load_shape_normalizes_and_denormalize_inverts(tmp_path):
    verts, faces = _bumpy_sphere(2)
    write_mesh(tmp_path / "bumpy_07.off", verts, faces)
    shape = load_shape(tmp_path / "bumpy_07.off")
    assert shape.name == "bumpy_07" and shape.path == tmp_path / "bumpy_07.off"
    assert shape.verts.dtype.is_floating_point and shape.verts.shape == (len(verts), 3)
    v = shape.verts.numpy().astype(np.float64)
    areas = triangle_areas(v, faces)
    assert areas.sum() == pytest.approx(Normalization().target_area, rel=1e-5)
    centroid = (areas[:, None] * v[faces].mean(axis=1)).sum(axis=0) / areas.sum()
    np.testing.assert_allclose(centroid, 0.0, atol=1e-6)
    # float32 storage: relative error ~1e-7 of the coordinate magnitude (about 1e4 here).
    np.testing.assert_allclose(shape.denormalize(shape.verts), verts, rtol=0, atol=1e-7 * np.abs(verts).max() * 4)


def test_load_shape_mean_center_and_custom_area(tmp_path):
    verts, faces = _bumpy_sphere(1)
    write_mesh(tmp_path / "m.ply", verts, faces)
    shape = load_shape(tmp_path / "m.ply", normalization=Normalization(target_area=0.44, center="mean"))
    v = shape.verts.numpy().astype(np.float64)
    assert triangle_areas(v, faces).sum() == pytest.approx(0.44, rel=1e-5)
    np.testing.assert_allclose(v.mean(axis=0), 0.0, atol=1e-6)


def test_load_shape_without_normalization_keeps_raw_coordinates(tmp_path):
    verts, faces = _bumpy_sphere(1)
    verts = verts / 1e4  # keep float32 rounding small
    write_mesh(tmp_path / "raw.off", verts, faces)
    shape = load_shape(tmp_path / "raw.off", normalization=None)
    assert shape.scale == 1.0
    np.testing.assert_array_equal(shape.verts.numpy(), verts.astype(np.float32))


# ------------------------------------------------------------------------ reference data (opt-in)


@pytest.mark.reference
def test_faust_r_files_read_in_file_order():
    root = os.environ.get("SHAPECORR_FAUST_R")
    if not root:
        pytest.skip("set SHAPECORR_FAUST_R to the FAUST_r folder (off/, corres/) to run this test")
    root = Path(root)
    names = ["tr_reg_000", "tr_reg_081"]
    vts = {}
    for name in names:
        v, f = read_mesh(root / "off" / f"{name}.off")
        reference = trimesh.load(root / "off" / f"{name}.off", process=False, maintain_order=True)
        np.testing.assert_array_equal(v, reference.vertices)
        np.testing.assert_array_equal(f, reference.faces)
        vts[name] = read_vts(root / "corres" / f"{name}.vts", n_verts=len(v))
        assert vts[name].min() >= 0 and vts[name].max() < len(v)
    check_vts_lengths(vts, root / "corres")
