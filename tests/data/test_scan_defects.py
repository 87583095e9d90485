"""Real-scan defects end to end: one case per item, each on a tiny FAUST-style folder in a tmp dir,
run through ``evaluate.py``'s configs (Hydra compose, in process). Each case asserts the outcome (the run
completes, or stops with exit status 2) and that the message names the file and the exact option."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_dir

from shapecorr.cli import evaluate as evaluate_cli
from shapecorr.data.io import write_mesh, write_vts
from shapecorr.eval import pair_pool

REPO = Path(__file__).resolve().parents[2]
N_REF = 40


def _sphere(subdivisions=3):
    m = trimesh.creation.icosphere(subdivisions=subdivisions)  # 642 vertices
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def _island(v, f):
    """Append a tiny icosahedron (12 vertices) floating beside the mesh."""
    iv, ifc = _sphere(0)
    return np.vstack([v, 0.1 * iv + [3.0, 0.0, 0.0]]), np.vstack([f, ifc + len(v)])


def _sliver(v, f, count=1):
    """Append ``count`` zero-area faces (a new vertex on the midpoint of an edge of face k)."""
    v, f = v.copy(), f.copy()
    for k in range(count):
        a, b = f[k, 0], f[k, 1]
        v = np.vstack([v, 0.5 * (v[a] + v[b])])
        f = np.vstack([f, [a, b, len(v) - 1]])
    return v, f


def _unreferenced(v, f):
    return np.vstack([v, [[0.0, 0.0, 5.0]]]), f


def _duplicate(v, f):
    return v, np.vstack([f, f[:1, ::-1]])


def make_folder(root: Path, defect=None, names=("a", "b", "c"), refs_on_island=False, vts=True):
    """A folder of slightly stretched spheres, the defect applied to shape ``names[1]``."""
    for sub in ("off", "corres", "splits"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    v0, f0 = _sphere()
    rng = np.random.default_rng(0)
    ref = rng.choice(len(v0), N_REF, replace=False)
    paths = {}
    for k, name in enumerate(names):
        v, f = v0 * [1.0 + 0.1 * k, 1.0, 1.0], f0
        r = ref
        if defect is not None and k == 1:
            v, f = defect(v, f)
            if refs_on_island:
                r = np.concatenate([ref[:-2], [len(v) - 1, len(v) - 2]])
        elif refs_on_island and k != 1:
            r = ref
        path = root / "off" / (name if isinstance(name, str) else os.fsdecode(name))
        path = path.with_name(path.name + ".off")
        write_mesh(path, v, f)
        if vts:
            write_vts(root / "corres" / f"{path.stem}.vts", r)
        paths[k] = path
    with open(root / "splits" / "test.txt", "wb") as fh:
        fh.write(b"".join(os.fsencode(p.stem) + b"\n" for p in paths.values()))
    return paths


def _cfg(root: Path, cache: Path, out: Path, *overrides: str):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        return compose("evaluate", overrides=[
            "data=folder", f"data.root={root}", f"paths.cache_dir={cache}", f"output_dir={out}",
            "progress=false", "n_examples=0", "data.operators.n_eig=20",
            "model=descriptor_nn", *overrides])


def _run(tmp_path, *overrides, expect_exit=False, capsys=None):
    out = tmp_path / "out"
    cfg = _cfg(tmp_path / "data", tmp_path / "cache", out, *overrides)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if expect_exit:
            with pytest.raises(SystemExit) as exc:
                evaluate_cli.evaluate(cfg)
            assert exc.value.code == 2
            result = None
        else:
            result = evaluate_cli.evaluate(cfg)
    return result, [str(w.message) for w in caught], out


# (id, defect, extra overrides, expect exit, [strings the message must contain], mesh-file-named)
CASES = [
    ("zero-area-faces-fall-back-to-robust", lambda v, f: _sliver(v, f, 1), [], False,
     ["cotangent Laplacian has infinite weights", "robust", "data.validation.laplacian_fallback"]),
    ("zero-area-faces-refused-without-fallback", lambda v, f: _sliver(v, f, 1),
     ["data.validation.laplacian_fallback=false"], True,
     ["infinite weights", "data.validation.laplacian_fallback=true", "data.operators.laplacian=robust"]),
    ("too-many-zero-area-faces", lambda v, f: _sliver(v, f, 3), [], True,
     ["zero-area" if False else "degenerate", "data.validation.max_degenerate_fraction="]),
    ("too-many-zero-area-faces-accepted-by-option", lambda v, f: _sliver(v, f, 3),
     ["data.validation.max_degenerate_fraction=0.02"], False, ["degenerate"]),
    ("unreferenced-vertex", _unreferenced, [], True,
     ["not used by any face", "data.validation.allow_unreferenced=true"]),
    ("disconnected-refused-by-option", _island, ["data.validation.allow_disconnected=false"], True,
     ["2 connected components", "data.validation.allow_disconnected=true"]),
    ("duplicate-faces-reported", _duplicate, [], False, ["1 duplicate faces"]),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_mesh_defect(case, tmp_path, capsys):
    _, defect, overrides, expect_exit, needles = case
    paths = make_folder(tmp_path / "data", defect)
    result, messages, _ = _run(tmp_path, *overrides, expect_exit=expect_exit)
    text = capsys.readouterr().err if expect_exit else " | ".join(messages)
    for needle in needles:
        assert needle in text, (needle, text)
    assert str(paths[1]) in text  # the message names the file
    if not expect_exit:
        assert result["n_pairs"] == 6 and np.isfinite(result["mean_geodesic_error"])


def test_islands_evaluate_by_default_and_are_counted(tmp_path):
    paths = make_folder(tmp_path / "data", _island, refs_on_island=True)
    result, messages, out = _run(tmp_path)
    assert result["n_pairs"] == 6
    # shape b has 2 reference points on its island: excluded in the 4 pairs with b
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["n_excluded_points"] == 4 * 2 == result["n_excluded_points"]
    island = [m for m in messages if "small islands" in m]
    assert len(island) == 1 and str(paths[1]) in island[0] and "n_excluded_points" in island[0]  # once per file


def _write_maps(tmp_path, p2p) -> Path:
    """The same map file for every ordered pair of shapes a, b, c."""
    maps = tmp_path / "maps"
    maps.mkdir()
    for a in "abc":
        for b in "abc":
            if a != b:
                np.savetxt(maps / f"{a}__{b}.txt", p2p, fmt="%d")
    return maps


@pytest.mark.parametrize("flag, expect_exit, needles", [
    (None, True, ["never uses index 0", "maps_one_based=true", "maps_one_based=false"]),
    ("true", False, []),
    ("false", False, []),
], ids=["not-said-refused", "one-based", "zero-based-said"])
def test_one_based_map_without_the_flag(tmp_path, capsys, flag, expect_exit, needles):
    make_folder(tmp_path / "data")
    n = len(_sphere()[0])
    maps = _write_maps(tmp_path, np.minimum(np.arange(n) + 1, n - 1))  # one-based identity never reaching n
    over = [f"maps_dir={maps}", "~model"] + ([] if flag is None else [f"maps_one_based={flag}"])
    result, _, _ = _run(tmp_path, *over, expect_exit=expect_exit)
    if expect_exit:
        err = capsys.readouterr().err
        assert all(s in err for s in needles), err
        assert str(maps) in err and "__" in err  # names the map file
    else:
        assert result["n_pairs"] == 6
        if flag == "true":
            assert result["mean_geodesic_error"] < 0.05


def test_map_index_out_of_range_names_the_flag(tmp_path, capsys):
    make_folder(tmp_path / "data")
    n = len(_sphere()[0])
    maps = _write_maps(tmp_path, np.arange(n) + 1)  # uses n: only valid one-based
    _run(tmp_path, f"maps_dir={maps}", "~model", "maps_one_based=false", expect_exit=True)
    err = capsys.readouterr().err
    assert "maps_one_based=true" in err and str(maps) in err


def test_missing_vts_names_the_file(tmp_path, capsys):
    make_folder(tmp_path / "data")
    (tmp_path / "data" / "corres" / "b.vts").unlink()
    _run(tmp_path, expect_exit=True)
    err = capsys.readouterr().err
    assert "corres/b.vts is missing" in err and " X " not in err and str(tmp_path / "data") in err


def test_directory_inside_off_is_reported(tmp_path, capsys):
    make_folder(tmp_path / "data", names=("a",))
    (tmp_path / "data" / "off" / "more_scans").mkdir()
    _, messages, _ = _run(tmp_path, expect_exit=True)
    err = capsys.readouterr().err
    assert any("more_scans/" in m and "sub-folders are not searched" in m for m in messages)
    assert "pair list is empty" in err and "1 shape(s)" in err and "sub-folders are not searched" in err


def test_non_utf8_file_name_end_to_end(tmp_path):
    root = tmp_path / "data"
    bad = os.fsdecode(b"caf\xe9")  # latin-1 name: not valid UTF-8
    try:
        make_folder(root, names=("a", bad, "c"))
    except (OSError, UnicodeError) as err:  # pragma: no cover - a file system refusing such names
        pytest.fail(f"the file system refused a non-UTF-8 name: {err}")
    result, _, out = _run(tmp_path, "n_examples=1")
    assert result["n_pairs"] == 6
    raw = (out / "per_pair.csv").read_bytes()
    assert b"caf\xe9" in raw and (out / "pck.png").is_file()


def test_ctrl_c_prints_one_line_with_the_resume_command(tmp_path, capsys, monkeypatch):
    make_folder(tmp_path / "data")
    real = pair_pool.evaluate_pairs

    def interrupted(matcher, shapes, pairs, out_dir, *args, **kwargs):
        real(matcher, shapes, pairs[:2], out_dir, *args, **kwargs)  # two pairs done, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(pair_pool, "evaluate_pairs", interrupted)
    cfg = _cfg(tmp_path / "data", tmp_path / "cache", tmp_path / "out")
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.evaluate(cfg)
    assert exc.value.code == 130
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines[-1].startswith("interrupted: 2 of 6 pairs done; resume with: python evaluate.py")
    assert f"output_dir={tmp_path / 'out'}" in lines[-1] and "Traceback" not in "\n".join(lines)
    monkeypatch.setattr(pair_pool, "evaluate_pairs", real)
    evaluate_cli.evaluate(cfg)
    assert "resuming: 2 of 6 pairs done" in capsys.readouterr().err


def test_operator_errors_name_the_file(tmp_path):
    # An operator that fails on the mesh (here: DiffusionNet's frames at a vertex in no face, accepted by
    # data.validation.allow_unreferenced) must name the shape's file, not only the vertex.
    from shapecorr.data.cache import ShapeCache
    from shapecorr.data.datasets import operators_with_fallback
    from shapecorr.data.operators import OperatorConfig
    from shapecorr.data.shape import Shape
    from shapecorr.errors import NumericalError

    import torch

    mesh = trimesh.creation.icosphere(subdivisions=1)
    verts = np.vstack([mesh.vertices, [[3.0, 0.0, 0.0]]]).astype(np.float32)
    shape = Shape(verts=torch.from_numpy(verts), faces=torch.from_numpy(np.asarray(mesh.faces, np.int64)),
                  name="loose", path=tmp_path / "loose.off")
    config = OperatorConfig(request={"diffusion_gradients": {}})
    with pytest.raises(NumericalError, match="loose.off: no vertex normal"):
        operators_with_fallback(ShapeCache(tmp_path / "cache"), shape, config, True)
