"""Writing evaluation outputs to disk: point-to-point maps and interpolation sequences.

Layout under an output folder (docs/evaluation.md §6)::

    maps/<x>__<y>.txt               one zero-based target index per line, one line per source vertex
    maps/<x>__<y>.npy               the same map as an int64 array
    maps/maps.json                  says the maps are zero-based (``maps_dir=`` reads the folder without flags)
    interp/<x>__<y>/t_XX.ply        frame XX (two digits, zero-based, more digits from 100 frames on) of an
                                    interpolation of x towards y, in the input units of x
    interp/<x>__<y>/times.txt       the time of each frame, line XX for t_XX.ply (shortest round-trip decimals)

A sequence folder is self-describing: :func:`read_times` reads ``times.txt`` back and :func:`frame_paths`
pairs each time with its frame. Times may lie beyond 1 (extrapolation) and need not include 0 or 1.

Every file is written atomically (temporary file in the same folder, then ``os.replace``), so an
interrupted evaluation never leaves a truncated map that a resumed run would take as done; ``times.txt`` is
written after the frames.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import pair_name
from shapecorr.errors import CorrespondenceError, NumericalError

MAPS_DIR = "maps"
#: Folder of the interpolation sequences under an evaluation output folder (``interp/<x>__<y>/``).
INTERP_DIR = "interp"
#: File listing the frame times of a sequence folder, one per line.
TIMES_FILE = "times.txt"
#: Frame files are ``t_XX.ply``: prefix, minimum number of digits of the frame index, extension.
FRAME_PREFIX = "t_"
FRAME_DIGITS = 2
FRAME_EXTENSION = ".ply"


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
    from shapecorr.data.io import write_map, write_maps_marker

    p2p = np.asarray(p2p.detach().cpu().numpy() if hasattr(p2p, "detach") else p2p)
    if p2p.ndim != 1 or not np.issubdtype(p2p.dtype, np.integer):
        raise CorrespondenceError(f"a map must be a 1-D integer array, got {p2p.dtype} of shape {p2p.shape}")
    txt, npy = map_paths(out_dir, name_x, name_y)
    txt.parent.mkdir(parents=True, exist_ok=True)
    write_maps_marker(txt.parent)  # maps_dir=<this folder> then reads them without maps_one_based
    write_map(txt, p2p.astype(np.int64), one_based=False)
    _atomic_save_npy(npy, p2p.astype(np.int64))
    return txt, npy


def frame_name(k: int, n_frames: int) -> str:
    """File name of frame ``k`` of ``n_frames``: ``t_00.ply`` ... (``t_000.ply`` ... from 101 frames on)."""
    digits = max(FRAME_DIGITS, len(str(max(n_frames - 1, 0))))
    return f"{FRAME_PREFIX}{k:0{digits}d}{FRAME_EXTENSION}"


def interp_folder(out_dir: str | os.PathLike, name_x: str, name_y: str) -> Path:
    """Folder ``out_dir/interp/<x>__<y>`` of a pair's interpolation frames."""
    return Path(out_dir) / INTERP_DIR / pair_name(name_x, name_y)


def _as_float64(a, what: str) -> np.ndarray:
    a = np.asarray(a.detach().cpu().numpy() if hasattr(a, "detach") else a, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise NumericalError(f"{what} contains NaN or infinite values; nothing written")
    return a


def write_frames(folder: str | os.PathLike, frames, faces, times, shape=None) -> list[Path]:
    """Write a sequence of meshes as ``folder/t_XX.ply`` plus ``folder/times.txt``.

    Frame files of an earlier sequence in the same folder that the new one does not overwrite are deleted,
    so that the folder always holds exactly the frames listed in ``times.txt``.

    Parameters
    ----------
    folder : path
        Created if needed.
    frames : (T, n, 3) float array or tensor
        Vertex positions per frame (normalized units when ``shape`` is given).
    faces : (f, 3) int
        Triangles shared by every frame.
    times : (T,) float
        Time of each frame (any finite values, e.g. beyond 1 for an extrapolation).
    shape : Shape, optional
        If given, frames are written in its input units (``shape.denormalize``).

    Returns
    -------
    list of the T frame paths, in order.

    Raises
    ------
    CorrespondenceError
        ``frames`` is not ``(T, n, 3)`` or ``times`` is not ``(T,)``.
    NumericalError
        Non-finite positions or times.
    """
    from shapecorr.data.io import write_mesh

    frames = _as_float64(frames, "the interpolation frames")
    times = _as_float64(times, "the frame times")
    faces = np.asarray(faces.detach().cpu().numpy() if hasattr(faces, "detach") else faces, dtype=np.int64)
    if frames.ndim != 3 or frames.shape[2] != 3 or frames.shape[0] == 0:
        raise CorrespondenceError(f"a sequence must be (T, n, 3) with T >= 1, got shape {frames.shape}")
    if times.shape != (frames.shape[0],):
        raise CorrespondenceError(f"{frames.shape[0]} frames need {frames.shape[0]} times, got shape {times.shape}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / frame_name(k, len(frames)) for k in range(len(frames))]
    for stale in set(folder.glob(f"{FRAME_PREFIX}*{FRAME_EXTENSION}")) - set(paths):
        stale.unlink()
    for path, verts in zip(paths, frames):
        write_mesh(path, shape.denormalize(verts) if shape is not None else verts, faces)
    with atomic_open(folder / TIMES_FILE) as fh:
        # repr(): the shortest decimal that reads back to the same float64
        fh.write("".join(f"{float(t)!r}\n" for t in times).encode("ascii"))
    return paths


def write_sequence(
    out_dir: str | os.PathLike, name_x: str, name_y: str, frames, faces, times, shape=None
) -> list[Path]:
    """Write an interpolation of x towards y as ``out_dir/interp/<x>__<y>/t_XX.ply`` + ``times.txt``.

    Parameters
    ----------
    out_dir : path
    name_x, name_y : str
    frames : (T, n, 3) float array or tensor
        Vertex positions of x along the interpolation (normalized units).
    faces : (f, 3) int
        Triangles of x.
    times : (T,) float
        Time of each frame.
    shape : Shape, optional
        If given, frames are written in the input units of x (``shape.denormalize``).

    Returns
    -------
    list of the T written frame paths (see :func:`write_frames`).
    """
    return write_frames(interp_folder(out_dir, name_x, name_y), frames, faces, times, shape=shape)


def read_times(folder: str | os.PathLike) -> np.ndarray:
    """The frame times of a sequence folder (``times.txt``), line k for frame k.

    Returns
    -------
    (T,) float64

    Raises
    ------
    CorrespondenceError
        Missing or malformed ``times.txt``.
    """
    path = Path(folder) / TIMES_FILE
    try:
        lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
        times = np.array([float(line) for line in lines], dtype=np.float64)
    except FileNotFoundError:
        raise CorrespondenceError("no times.txt in this sequence folder", path) from None
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise CorrespondenceError(f"unreadable frame times: {err}", path) from None
    if times.size == 0 or not np.all(np.isfinite(times)):
        raise CorrespondenceError("times.txt must list one finite time per line", path)
    return times


def frame_paths(folder: str | os.PathLike) -> list[tuple[float, Path]]:
    """``(time, frame path)`` of every frame of a sequence folder, in the order of ``times.txt``.

    Raises
    ------
    CorrespondenceError
        ``times.txt`` is missing or malformed, or a frame file it announces is missing.
    """
    folder = Path(folder)
    times = read_times(folder)
    out = [(float(t), folder / frame_name(k, len(times))) for k, t in enumerate(times)]
    missing = [p.name for _, p in out if not p.is_file()]
    if missing:
        raise CorrespondenceError(f"times.txt lists {len(times)} frames but {missing[:3]} are missing", folder)
    return out
