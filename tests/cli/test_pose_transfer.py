"""``evaluate.py task=pose_transfer`` end to end, with LinearBlend around the ground-truth matcher.

Two tiny meshes share their connectivity (an icosphere with 162 vertices; B is a bent copy) but have different
sizes and positions, so the identity is the true map, the deformed source at t = 1 is exactly B's pose in A's
input units, and a frame written in the wrong units would show. Configs are composed with Hydra's compose API
(the same ``configs/`` as the command line) and run through ``evaluate()``, the function ``evaluate.py`` calls.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from shapecorr.cli.evaluate import evaluate
from shapecorr.data.io import load_shape, read_map, read_mesh, write_mesh
from shapecorr.eval.export import read_times

BLEND = ["model=linear_blend", "model@model.matcher=identity_gt"]


@pytest.fixture(scope="module")
def meshes(tmp_path_factory, compose_config):
    """``(A.off, B.ply, cache_dir, compose_config)``."""
    folder = tmp_path_factory.mktemp("pose_meshes")
    mesh = trimesh.creation.icosphere(subdivisions=2)
    base, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    a = base * [1.2, 1.0, 0.9] * 5.0 + [10.0, -3.0, 2.0]
    b = base.copy()
    b[:, 2] += 0.4 * np.sin(2.0 * b[:, 1])  # a smooth bend: B is a different pose
    b = b * 2.0 + [-1.0, 4.0, 0.0]
    write_mesh(folder / "A.off", a, faces)
    write_mesh(folder / "B.ply", b, faces)
    return folder / "A.off", folder / "B.ply", tmp_path_factory.mktemp("pose_cache"), compose_config


def _cfg(meshes, out: Path, *overrides: str):
    source, target, cache, compose_config = meshes
    return compose_config(
        "evaluate",
        overrides=[
            "task=pose_transfer",
            f"source={source}",
            f"target={target}",
            f"output_dir={out}",
            f"paths.cache_dir={cache}",
            "data.operators.n_eig=20",  # a small eigenbasis: fast first run
            *overrides,
        ],
    )


def _expected_deformed(meshes) -> np.ndarray:
    """B's normalized vertices in A's input units (identity map, blend at t = 1)."""
    source, target = meshes[:2]
    a, b = load_shape(source), load_shape(target)
    return a.denormalize(b.verts)


def test_pose_transfer_end_to_end(meshes, tmp_path, capsys):
    out = evaluate(_cfg(meshes, tmp_path, *BLEND, "interp_times=[0,0.5,1,1.5]"))
    folder = tmp_path / "pose_transfer" / "A__B"
    assert out["folder"] == folder
    raw_a, faces = read_mesh(meshes[0])
    deformed, deformed_faces = read_mesh(folder / "deformed.ply")
    np.testing.assert_array_equal(deformed_faces, faces)  # A's identity: its connectivity
    np.testing.assert_allclose(deformed, _expected_deformed(meshes), atol=1e-5)
    assert np.abs(deformed - raw_a).max() > 1.0  # ... in B's pose
    assert sorted(p.name for p in folder.glob("t_*.ply")) == ["t_00.ply", "t_01.ply", "t_02.ply", "t_03.ply"]
    assert read_times(folder).tolist() == [0.0, 0.5, 1.0, 1.5]
    np.testing.assert_allclose(read_mesh(folder / "t_00.ply")[0], raw_a, atol=1e-5)  # t = 0: A, input units
    np.testing.assert_allclose(read_mesh(folder / "t_02.ply")[0], deformed, atol=1e-9)
    np.testing.assert_allclose(read_mesh(folder / "t_03.ply")[0], raw_a + 1.5 * (deformed - raw_a), atol=1e-5)
    n = len(raw_a)
    assert read_map(folder / "map.txt", one_based=False, n_source=n, n_target=n).tolist() == list(range(n))
    printed = capsys.readouterr().out
    for path in (folder / "deformed.ply", folder / "map.txt", folder / "times.txt"):
        assert str(path) in printed


def test_unit_time_is_added_but_not_written(meshes, tmp_path):
    evaluate(_cfg(meshes, tmp_path, *BLEND, "interp_times=[0,0.5]", "write_maps=false"))
    folder = tmp_path / "pose_transfer" / "A__B"
    assert sorted(p.name for p in folder.iterdir()) == ["deformed.ply", "t_00.ply", "t_01.ply", "times.txt"]
    assert read_times(folder).tolist() == [0.0, 0.5]
    np.testing.assert_allclose(read_mesh(folder / "deformed.ply")[0], _expected_deformed(meshes), atol=1e-5)


def test_default_frames(meshes, tmp_path):
    evaluate(_cfg(meshes, tmp_path / "a", *BLEND))
    assert read_times(tmp_path / "a" / "pose_transfer" / "A__B").tolist() == [0.0, 0.25, 0.5, 0.75, 1.0]  # config
    evaluate(_cfg(meshes, tmp_path / "b", *BLEND, "interp_times=null", "model.interp_times=[0.0,0.2,1.0]"))
    assert read_times(tmp_path / "b" / "pose_transfer" / "A__B").tolist() == [0.0, 0.2, 1.0]  # the matcher's


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["source=null", *BLEND], "needs source=<mesh file>"),
        (["target=null", *BLEND], "needs target=<mesh file>"),
        (["model=descriptor_nn"], "needs an interpolating matcher"),
        (["task=transfer", *BLEND], "task must be one of"),
        (["interp_times=[1,0]", *BLEND], "strictly increasing"),
        (["interp_times=0.5", *BLEND], "interp_times must be a list"),
    ],
)
def test_config_errors(meshes, tmp_path, capsys, overrides, message):
    with pytest.raises(SystemExit) as exc:
        evaluate(_cfg(meshes, tmp_path, *overrides))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and "Traceback" not in err
    assert not (tmp_path / "pose_transfer").exists()


def test_maps_dir_cannot_transfer_a_pose(meshes, tmp_path, capsys):
    with pytest.raises(SystemExit):
        evaluate(_cfg(meshes, tmp_path, f"maps_dir={tmp_path}"))
    assert "maps_dir has none" in capsys.readouterr().err


def test_unreadable_meshes_name_the_file(meshes, tmp_path, capsys):
    garbage = tmp_path / "broken.off"
    garbage.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # one vertex line and the face missing
    for source, problem in ((garbage, str(garbage)), (tmp_path / "nope.obj", "file not found")):
        with pytest.raises(SystemExit) as exc:
            evaluate(_cfg(meshes, tmp_path, *BLEND, f"source={source}"))
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {source}:") and problem in err and "Traceback" not in err
