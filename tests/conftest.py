"""Fixtures shared by the whole test suite.

* :func:`compose_config`: compose ``configs/<name>.yaml`` with overrides through Hydra's compose API (the same
  files and override grammar as the command line), without running an app or changing the working directory.
* :func:`single_thread`: torch limited to one thread for a module (the tests use tiny tensors: OpenMP threading
  only adds overhead, and stalls on a busy machine). Use it with
  ``pytestmark = pytest.mark.usefixtures("single_thread")``.
* Mesh builders: :func:`unit_sphere` (icosphere on the unit sphere), :func:`bumpy_sphere` (random radial noise,
  no symmetry left), :func:`smooth_bumpy_sphere` (smooth Gaussian bumps: every Laplacian eigenvalue simple).
  They are factories: ``def test_x(unit_sphere): v, f = unit_sphere(2)``; subdivisions 1 / 2 / 3 / 4 give
  42 / 162 / 642 / 2562 vertices.
* :func:`bent_sphere_folder`: writes a tiny FAUST-style dataset folder (``off/``, ``corres/``, ``splits/``) for
  the ``evaluate.py`` tests.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

REPO = Path(__file__).resolve().parents[1]
CONFIG_DIR = REPO / "configs"

Mesh = tuple[np.ndarray, np.ndarray]


def _compose(config_name: str, overrides: Sequence[str] = ()) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name, overrides=list(overrides))


@pytest.fixture(scope="session")
def compose_config() -> Callable[..., DictConfig]:
    """``compose_config(name, overrides=())``: the composed ``configs/<name>.yaml`` (e.g. ``"train"``)."""
    return _compose


def _evaluate_on_folder(root, cache_dir, out, *overrides: str, n_examples: int = 0) -> DictConfig:
    return _compose("evaluate", [
        "data=folder", f"data.root={root}", f"paths.cache_dir={cache_dir}", f"output_dir={out}", "progress=false",
        f"n_examples={n_examples}",
        "data.operators.n_eig=30",  # small eigenbases: fast cache fill
        *overrides,
    ])


@pytest.fixture(scope="session")
def evaluate_on_folder() -> Callable[..., DictConfig]:
    """``evaluate_on_folder(root, cache_dir, out, *overrides, n_examples=0)``: the evaluate.py config of a
    ``data=folder`` run on ``root`` (cache in ``cache_dir``, outputs in ``out``, no progress bar, 30 eigenpairs),
    plus ``overrides``."""
    return _evaluate_on_folder


@pytest.fixture(scope="module")
def single_thread():
    """torch on one thread for the module that uses it; the previous setting is restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _unit_sphere(subdivisions: int = 2) -> Mesh:
    s = trimesh.creation.icosphere(subdivisions)
    v = np.asarray(s.vertices)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.asarray(s.faces, dtype=np.int64)


def _bumpy_sphere(subdivisions: int = 2, seed: int = 0, amplitude: float = 0.1) -> Mesh:
    s = trimesh.creation.icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    v = np.asarray(s.vertices) * (1.0 + amplitude * rng.uniform(-1, 1, (len(s.vertices), 1)))
    return v, np.asarray(s.faces, dtype=np.int64)


def _smooth_bumpy_sphere(subdivisions: int, seed: int = 0, amplitude: float = 0.15, n_bumps: int = 6) -> Mesh:
    v, f = _unit_sphere(subdivisions)
    rng = np.random.default_rng(seed)
    centers = rng.normal(size=(n_bumps, 3))
    centers /= np.linalg.norm(centers, axis=1, keepdims=True)
    bump = np.exp(-4.0 * ((v[:, None, :] - centers[None]) ** 2).sum(-1)) @ rng.uniform(0.5, 1.0, n_bumps)
    return v * (1.0 + amplitude * bump[:, None]), f


def _asymmetric_blob(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    v = points / np.linalg.norm(points, axis=1, keepdims=True)
    centres = rng.normal(size=(5, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    amplitudes = np.array([0.5, 0.35, 0.3, -0.25, 0.4])
    radius = 1.0 + sum(a * np.exp(-np.sum((v - c) ** 2, 1) / 0.3) for a, c in zip(amplitudes, centres))
    return v * radius[:, None] * np.array([1.4, 1.0, 0.8])


@pytest.fixture(scope="session")
def asymmetric_blob() -> Callable[[np.ndarray, np.random.Generator], np.ndarray]:
    """``asymmetric_blob(points (n, 3), rng) -> (n, 3)``: sphere points pushed out radially by 5 Gaussian bumps
    at random directions (drawn from ``rng``) and stretched by (1.4, 1, 0.8): a bumpy ellipsoid with no
    intrinsic symmetry, star-shaped over the unit sphere."""
    return _asymmetric_blob


def _bent_sphere_folder(root: Path, names: Sequence[str]) -> Path:
    from shapecorr.data.io import write_mesh, write_vts

    for sub in ("off", "corres", "splits"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    base, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(0)
    for k, name in enumerate(names):
        perm = rng.permutation(len(base))
        bent = base * [1.0 + 0.2 * k, 1.0, 1.0 - 0.1 * k]
        bent[:, 2] += 0.3 * np.sin(1.5 * bent[:, 1]) * (k % 2)
        bent = bent * (1.0 + 2.0 * k) + [5.0 * k, -2.0, 1.0]  # different units per shape
        verts = np.empty_like(bent)
        verts[perm] = bent
        write_mesh(root / "off" / f"{name}.off", verts, perm[faces])
        write_vts(root / "corres" / f"{name}.vts", perm)
    for split in ("test", "train"):
        (root / "splits" / f"{split}.txt").write_text("\n".join(names) + "\n")
    return root


@pytest.fixture(scope="session")
def bent_sphere_folder() -> Callable[[Path, Sequence[str]], Path]:
    """``bent_sphere_folder(root, names) -> root``: one bent, vertex-permuted icosphere (162 vertices) per name,
    in different units and positions (so that frames in the wrong units would show), as ``off/<name>.off`` with
    ``.vts`` ground truth on every vertex (``corres/``) and every shape in ``splits/{test,train}.txt``."""
    return _bent_sphere_folder


@pytest.fixture(scope="session")
def unit_sphere() -> Callable[..., Mesh]:
    """``unit_sphere(subdivisions=2) -> (verts (n, 3) float64, faces (f, 3) int64)``, vertices of norm 1."""
    return _unit_sphere


@pytest.fixture(scope="session")
def bumpy_sphere() -> Callable[..., Mesh]:
    """``bumpy_sphere(subdivisions=2, seed=0, amplitude=0.1)``: an icosphere with every vertex moved radially by
    a factor ``1 + amplitude * U(-1, 1)`` (seeded), so no symmetry is left."""
    return _bumpy_sphere


@pytest.fixture(scope="session")
def smooth_bumpy_sphere() -> Callable[..., Mesh]:
    """``smooth_bumpy_sphere(subdivisions, seed=0, amplitude=0.15, n_bumps=6)``: the unit sphere with
    ``n_bumps`` smooth Gaussian bumps at random directions (seeded): asymmetric, every eigenvalue simple."""
    return _smooth_bumpy_sphere
