"""Bad, odd and hostile inputs to ``evaluate.py`` / ``train.py``: never a silently wrong number, never a traceback.

Each table row is one case: what it sets up, the options, and either the one-line error it must end with (exit
status 2, the file and the option named) or the correct result it must produce. The folders hold 162-vertex
spheres (``bent_sphere_folder``), so every row runs in seconds. Ctrl-C with workers is in
``tests/cli/test_interrupt.py`` (a real process).
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

from shapecorr.cli.common import OutputDirCheck, check_output_dir
from shapecorr.cli.evaluate import evaluate
from shapecorr.data.datasets import DatasetWarning, ShapeDataset, read_pair_lines
from shapecorr.data.io import read_mesh, write_mesh
from shapecorr.data.operators import OperatorConfig
from shapecorr.data.validation import MeshWarning
from shapecorr.errors import ConfigError, DatasetError, MeshReadError
from shapecorr.eval import protocol

pytestmark = pytest.mark.usefixtures("single_thread")
NAMES = ["a", "b", "c"]
FAST = ("model=descriptor_nn", "data.operators.n_eig=20")


@pytest.fixture(scope="module")
def world(tmp_path_factory, bent_sphere_folder, evaluate_on_folder):
    """``(root, cache, config)``: a 3-shape folder, a shared cache, and ``config(out, *overrides)``."""
    root = bent_sphere_folder(tmp_path_factory.mktemp("three"), NAMES)
    cache = tmp_path_factory.mktemp("cache")

    def config(out, *overrides, data_root=root):
        return evaluate_on_folder(data_root, cache, out, *overrides)

    return root, cache, config


def _error(cfg, capsys) -> str:
    """The ``error: ...`` line of a run that must stop with exit status 2 (and no traceback)."""
    with pytest.raises(SystemExit) as stop:
        evaluate(cfg)
    err = capsys.readouterr().err
    assert stop.value.code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, err
    return lines[0]


def _copy(root: Path, dest: Path) -> Path:
    shutil.copytree(root, dest)
    return dest


# ------------------------------------------------------------------------------------- silent wrong results
def test_resume_with_other_data_settings_is_refused_naming_the_keys(world, tmp_path, capsys):
    root, _, config = world
    out = tmp_path / "out"
    evaluate(config(out, *FAST))
    for record in list((out / "pairs").glob("b__*")):
        record.unlink()
    line = _error(config(out, *FAST, "data.reference_points=10", "data.operators.params.wks.count=20"), capsys)
    assert "run.json differs in" in line and str(out) in line
    assert "reference_points: null -> 10" in line and "operators.wks.count: 100 -> 20" in line
    assert len(list((out / "pairs").glob("*.json"))) == 4  # nothing mixed in


def test_maps_dir_is_wrapped_by_interpolator_and_postprocess(world, tmp_path):
    root, _, config = world
    first = evaluate(config(tmp_path / "first", *FAST))
    maps = tmp_path / "first" / "maps"
    blended = evaluate(config(tmp_path / "blend", f"maps_dir={maps}", "interpolator=linear_blend"))
    assert blended["mean_geodesic_error"] == pytest.approx(first["mean_geodesic_error"])
    assert blended["mean_chamfer"] is not None  # the frames of the interpolator were computed and scored
    refined = evaluate(config(tmp_path / "refined", f"maps_dir={maps}", "postprocess=smooth_shells", "max_pairs=1",
                              "postprocess.k_max=40", "postprocess.k_array_length=4",
                              "data.operators.params.shot.radius_factor=0.25"))
    record = json.loads(next((tmp_path / "refined" / "pairs").glob("*.json")).read_text())
    assert record["initial_mean_error"] is not None  # the precomputed map went through the refinement
    assert record["initial_mean_error"] != record["mean_error"]
    assert refined["run"]["postprocess"]["_target_"].endswith("SmoothShellsPostprocess")


def test_maps_written_by_evaluate_are_read_back_without_flags(world, tmp_path):
    root, _, config = world
    first = evaluate(config(tmp_path / "first", *FAST))
    assert (tmp_path / "first" / "maps" / "maps.json").is_file()
    again = evaluate(config(tmp_path / "again", f"maps_dir={tmp_path / 'first' / 'maps'}"))  # no maps_one_based
    assert again["mean_geodesic_error"] == pytest.approx(first["mean_geodesic_error"])


def test_pair_names_that_collide_through_the_separator_are_refused(bent_sphere_folder, tmp_path, capsys,
                                                                   evaluate_on_folder):
    root = bent_sphere_folder(tmp_path / "d", ["p", "p__q", "r", "q__r"])
    line = _error(evaluate_on_folder(root, tmp_path / "cache", tmp_path / "out", "model=identity_gt"), capsys)
    assert "(p__q, r)" in line and "(p, q__r)" in line and "p__q__r" in line
    assert not (tmp_path / "out" / "pairs").exists()


def test_repeated_pair_file_lines_are_scored_once(world, tmp_path):
    root, _, config = world
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("a b\nb c\na b\n")
    with pytest.warns(DatasetWarning, match=r"line 3 repeats line 1 \(a, b\)"):
        result = evaluate(config(tmp_path / "out", *FAST, f"pair_file={pairs}"))
    assert result["n_pairs"] == 2


# ------------------------------------------------------------------------------------- tracebacks and hangs
@pytest.mark.parametrize("value, shown", [(-1, "-1"), (0, "0")])
def test_max_pairs_below_one_is_an_error(world, tmp_path, capsys, value, shown):
    line = _error(world[2](tmp_path / "out", *FAST, f"max_pairs={value}"), capsys)
    assert f"max_pairs must be a positive number of pairs or null (all pairs), got {shown}" in line


def test_output_dir_that_is_a_file_or_unwritable(world, tmp_path, capsys, monkeypatch):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, expected in ((a_file, "is a file, not a folder; choose another output_dir=DIR"),
                          (a_file / "sub", "cannot write the output folder here")):
        line = _error(world[2](out, *FAST), capsys)
        assert line.startswith(f"error: {out}") and expected in line
    # an unwritable or read-only folder (the tests may run as root, which writes anywhere: simulated)
    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "ro"))

    monkeypatch.setattr("shapecorr.cli.common.tempfile.TemporaryFile", refuse)
    line = _error(world[2](tmp_path / "ro", *FAST), capsys)
    assert line.startswith(f"error: {tmp_path / 'ro'}: cannot write the output folder here (Permission denied)")


def test_disk_full_during_the_run_stops_with_one_line_and_resumes(world, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    real = protocol.write_record
    calls = []

    def full_after_two(out_dir, record, *args):
        calls.append(record)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(Path(out_dir) / "pairs" / "x.npz"))
        return real(out_dir, record, *args)

    monkeypatch.setattr(protocol, "write_record", full_after_two)
    line = _error(world[2](out, *FAST), capsys)
    assert "No space left on device [errno 28]" in line and "the same command and output_dir" in line
    monkeypatch.setattr(protocol, "write_record", real)
    result = evaluate(world[2](out, *FAST))
    assert result["n_pairs"] == 6 and "resuming: 2 of 6 pairs done" in capsys.readouterr().err


def test_storage_fault_in_a_writer_thread_is_one_line(capsys):
    """As TensorBoard's event writer on a full disk during train.py: the thread's fault and the run's, no traceback."""
    import threading

    from shapecorr.cli.common import exit_on_user_error

    @exit_on_user_error
    def run():
        def writer():
            raise OSError(errno.ENOSPC, "No space left on device")

        thread = threading.Thread(target=writer)
        thread.start()
        thread.join()
        raise OSError(errno.ENOSPC, "No space left on device", "/runs/x")

    with pytest.raises(SystemExit) as stop:
        run()
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "Traceback" not in err
    assert err.count("error: ") == 2 and "error: /runs/x: No space left on device [errno 28]" in err


@pytest.mark.parametrize("kind", ["a file", "under a file"])
def test_train_run_folder_checked_before_hydra_creates_it(tmp_path, capsys, kind):
    from omegaconf import OmegaConf

    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    run_dir = a_file if kind == "a file" else a_file / "run"
    with pytest.raises(SystemExit) as stop:
        OutputDirCheck().on_run_start(OmegaConf.create({"hydra": {"run": {"dir": str(run_dir)}}}))
    assert stop.value.code == 2
    assert f"error: {a_file}: is a file, not a folder; choose another hydra.run.dir=DIR" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="paths.output_dir"):
        check_output_dir(run_dir, "paths.output_dir=DIR or hydra.run.dir=DIR")


def test_multi_component_shape_in_multi_shape_matching_fails_before_the_work(world, tmp_path, capsys):
    root = _copy(world[0], tmp_path / "islands")
    v, f = read_mesh(root / "off" / "c.off")
    tet = np.array([[30.0, 0, 0], [31, 0, 0], [30, 1, 0], [30, 0, 1]])
    write_mesh(root / "off" / "c.off", np.vstack([v, tet]),
               np.vstack([f, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]) + len(v)]))
    out = tmp_path / "out"
    with pytest.warns(MeshWarning):
        line = _error(world[2](out, "model=gmsm", "multishape=graph", data_root=root), capsys)
    assert f"{root / 'off' / 'c.off'} (2 components)" in line and "without multishape=" in line
    assert not (out / "graph_queries").exists()


# ------------------------------------------------------------------------------------- partial messages
def test_more_eigenpairs_than_vertices_names_the_shape_and_the_option(world, tmp_path, capsys):
    line = _error(world[2](tmp_path / "out", "model=descriptor_nn", "data.operators.n_eig=200"), capsys)
    assert re.search(r"off/a\.off: a has 162 vertices, too few for the eigenpairs requested", line)
    assert "got k=200" in line and "data.operators.n_eig" in line


def test_data_root_that_is_a_file_or_a_looping_link(world, tmp_path, capsys):
    a_mesh = world[0] / "off" / "a.off"
    line = _error(world[2](tmp_path / "o1", *FAST, data_root=a_mesh), capsys)
    assert "is a file, not a dataset folder" in line and f"data.root={world[0]}" in line
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    line = _error(world[2](tmp_path / "o2", *FAST, data_root=loop), capsys)
    assert "symbolic link that loops or points nowhere" in line


def test_mesh_link_that_loops_is_named(world, tmp_path, capsys):
    root = _copy(world[0], tmp_path / "d")
    (root / "off" / "z.off").symlink_to(root / "off" / "z.off")
    line = _error(world[2](tmp_path / "out", *FAST, data_root=root), capsys)
    assert "z.off is a symbolic link that loops or points nowhere" in line


@pytest.mark.parametrize("content, expected", [
    ("a b\nb nope\n", r"pairs.txt: line 2: no shape named 'nope'"),
    ("a b\n\"b c\n", r"pairs.txt: line 2: No closing quotation"),
    ("a b c\n", r"pairs.txt: line 1: expected two shape names, got 3"),
    ("# only a comment\n", r"pairs.txt: pair list file lists no pair"),
])
def test_pair_file_errors_name_the_file_and_the_line(world, tmp_path, capsys, content, expected):
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(content)
    line = _error(world[2](tmp_path / "out", *FAST, f"pair_file={pairs}"), capsys)
    assert re.search(expected, line), line


@pytest.mark.parametrize("line, names", [
    ("my shape\tb\n", ("my shape", "b")),
    ('"my shape" b\n', ("my shape", "b")),
    ("'my shape',b\n", ("my shape", "b")),
    ("a, b\n", ("a", "b")),
])
def test_shape_names_with_spaces_in_pair_files(tmp_path, line, names):
    path = tmp_path / "pairs.txt"
    path.write_text(line)
    assert read_pair_lines(path) == [(1, *names)]


def test_shape_name_with_spaces_evaluates(bent_sphere_folder, tmp_path, evaluate_on_folder):
    root = bent_sphere_folder(tmp_path / "d", ["my shape", "b"])
    (tmp_path / "pairs.txt").write_text('"my shape" b\nb\t my shape\n')
    result = evaluate(evaluate_on_folder(root, tmp_path / "cache", tmp_path / "out", "model=identity_gt",
                                         f"pair_file={tmp_path / 'pairs.txt'}"))
    assert result["n_pairs"] == 2 and result["mean_geodesic_error"] == 0.0


def test_mesh_warnings_repeat_on_a_warm_cache(world, tmp_path):
    root = _copy(world[0], tmp_path / "d")
    v, f = read_mesh(root / "off" / "a.off")
    write_mesh(root / "off" / "a.off", v, np.vstack([f, f[:1]]))  # one duplicate face
    for attempt in ("cold", "warm"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ShapeDataset(root, operators=OperatorConfig(n_eig=4), cache_dir=tmp_path / "cache").load_shape(0)
        messages = [str(w.message) for w in caught if issubclass(w.category, MeshWarning)]
        assert any(m.startswith(f"{root / 'off' / 'a.off'}: 1 duplicate faces") for m in messages), (attempt, messages)


def test_large_text_file_named_off_is_refused_at_its_header(tmp_path):
    path = tmp_path / "log.off"
    path.write_bytes(b"2026-01-01 12:00:00 INFO a log line, not a mesh 123 456\n" * 400_000)  # 22 MB
    tracemalloc.start()
    try:
        with pytest.raises(MeshReadError, match="not an OFF file: line 1 starts with '2026-01-01'"):
            read_mesh(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1.5 * os.path.getsize(path)  # the file's bytes, not a split of its lines


def test_pair_dataset_rejects_non_integer_max_pairs(world):
    from shapecorr.data.datasets import PairDataset

    shapes = ShapeDataset(world[0], split="test", operators=OperatorConfig(n_eig=4), cache_dir=world[1])
    for bad in (-1, 0, 1.5, True):
        with pytest.raises(ConfigError, match="max_pairs must be a positive number"):
            PairDataset(shapes, max_pairs=bad)
    with pytest.raises(DatasetError, match="line 1: no shape named 'zz'"):
        (world[0] / "bad_pairs.txt").write_text("zz a\n")
        PairDataset(shapes, pair_file="bad_pairs.txt")
    with pytest.warns(DatasetWarning, match="1 repeated pair"):
        assert PairDataset(shapes, pairs=[("a", "b"), ("b", "a"), ("a", "b")]).pairs == [(0, 1), (1, 0)]
