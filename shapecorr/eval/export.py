"""Writing evaluation outputs to disk: point-to-point maps and interpolation sequences.

Layout under an output folder (design.md, "Outputs of evaluate.py")::

    maps/<x>__<y>.txt     one zero-based target index per line, one line per source vertex
    maps/<x>__<y>.npy     the same map as an int64 array
    sequences/<x>__<y>/t_<k>.ply   frame k of an interpolation, in the input units of x

Every file is written atomically (temporary file in the same folder, then ``os.replace``), so an
interrupted evaluation never leaves a truncated map that a resumed run would take as done.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import pair_name
from shapecorr.errors import CorrespondenceError

MAPS_DIR = "maps"
SEQUENCES_DIR = "sequences"
#: Digits of the frame number in sequence file names (t_000.ply ...).
FRAME_DIGITS = 3


def _atomic_save_npy(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as fh:
        np.save(fh, array, allow_pickle=False)


def map_paths(out_dir: str | os.PathLike, name_x: str, name_y: str) -> tuple[Path, Path]:
    """Paths ``(txt, npy)`` of a pair's map under ``out_dir/maps``."""
    folder, stem = Path(out_dir) / MAPS_DIR, pair_name(name_x, name_y)
    return folder / f"{stem}.txt", folder / f"{stem}.npy"


def write_map_files(out_dir: str | os.PathLike, name_x: str, name_y: str, p2p) -> tuple[Path, Path]:
    """Write a map x -> y as ``maps/<x>__<y>.txt`` (zero-based, one index per line) and ``.npy``.

    Parameters
    ----------
    out_dir : path
    name_x, name_y : str
    p2p : (n_x,) int array or tensor

    Returns
    -------
    (txt_path, npy_path)
    """
    from shapecorr.data.io import write_map

    p2p = np.asarray(p2p.detach().cpu().numpy() if hasattr(p2p, "detach") else p2p)
    if p2p.ndim != 1 or not np.issubdtype(p2p.dtype, np.integer):
        raise CorrespondenceError(f"a map must be a 1-D integer array, got {p2p.dtype} of shape {p2p.shape}")
    txt, npy = map_paths(out_dir, name_x, name_y)
    txt.parent.mkdir(parents=True, exist_ok=True)
    write_map(txt, p2p.astype(np.int64), one_based=False)
    _atomic_save_npy(npy, p2p.astype(np.int64))
    return txt, npy


def write_sequence(out_dir: str | os.PathLike, name_x: str, name_y: str, frames, faces, shape=None) -> list[Path]:
    """Write an interpolation sequence as one PLY file per frame.

    Parameters
    ----------
    out_dir : path
    name_x, name_y : str
    frames : (T, n, 3) float array or tensor
        Vertex positions of x along the interpolation (normalized units).
    faces : (f, 3) int
        Triangles of x.
    shape : Shape, optional
        If given, frames are written in the input units of x (``shape.denormalize``).

    Returns
    -------
    list of the T written paths, ``sequences/<x>__<y>/t_000.ply`` ...
    """
    from shapecorr.data.io import write_mesh

    frames = np.asarray(frames.detach().cpu().numpy() if hasattr(frames, "detach") else frames, dtype=np.float64)
    faces = np.asarray(faces.detach().cpu().numpy() if hasattr(faces, "detach") else faces, dtype=np.int64)
    if frames.ndim != 3 or frames.shape[2] != 3:
        raise CorrespondenceError(f"a sequence must be (T, n, 3), got shape {frames.shape}")
    folder = Path(out_dir) / SEQUENCES_DIR / pair_name(name_x, name_y)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, verts in enumerate(frames):
        path = folder / f"t_{k:0{FRAME_DIGITS}d}.ply"
        write_mesh(path, shape.denormalize(verts) if shape is not None else verts, faces)
        paths.append(path)
    return paths
