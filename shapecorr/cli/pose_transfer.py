r"""``evaluate.py task=pose_transfer``: put shape A into the pose of shape B with an interpolating matcher.

    python evaluate.py model=neuromorph ckpt_path=CKPT task=pose_transfer source=A.off target=B.off \
        [output_dir=OUT] [interp_times=[0,0.25,0.5,0.75,1]]

The two meshes (.off/.ply/.obj) go through the data pipeline of every other shape: read and validated
(:func:`shapecorr.data.io.load_shape`, through the mesh cache), normalized with the data config's
``normalization``, and given the operators of the data config plus the matcher's ``required_operators``,
computed on the first run and read from the shape cache (``paths.cache_dir``) afterwards. The matcher's
``interpolate(A, B, times)`` (docs/evaluation.md §4) then deforms A towards B; A's vertices at t = 1 are A's
identity (its connectivity and vertex order) in B's pose. Written to ``OUT/pose_transfer/<A>__<B>/``::

    deformed.ply        the frame at t = 1 in A's input units (evaluated even when 1 is not in interp_times)
    t_XX.ply            the frames at interp_times (write_interp; null = the matcher's default frames),
    times.txt           in A's input units, and their times, line XX for t_XX.ply
    map.txt             the map A -> B, one zero-based vertex index of B per vertex of A (write_maps)

Errors (printed without a traceback, exit status 2): a missing ``source``/``target`` option (ConfigError), a
matcher without ``interpolate`` (ConfigError), a file that cannot be read (MeshReadError naming it) or holds
an invalid mesh (InvalidMeshError).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from shapecorr.cli.matcher_factory import build_matcher, interp_times_option, resolve_device
from shapecorr.data.cache import ShapeCache, default_cache_root
from shapecorr.data.datamodule import ShapePairDataModule
from shapecorr.data.datasets import (
    ShapeSample,
    load_mesh_cached,
    pair_name,
    sample_with_operators,
)
from shapecorr.data.io import write_map, write_mesh
from shapecorr.data.operators import OperatorConfig, required_request
from shapecorr.data.shape import Normalization
from shapecorr.errors import ConfigError, MeshReadError
from shapecorr.eval import matcher_run
from shapecorr.eval.export import TIMES_FILE, write_frames

#: Folder of the pose-transfer outputs under ``output_dir``.
POSE_TRANSFER_DIR = "pose_transfer"
#: The deformed source at t = 1, in the source's input units.
DEFORMED_FILE = "deformed.ply"
#: The map source -> target, zero-based.
MAP_FILE = "map.txt"


def require_interpolating(matcher, what: str | None = None) -> None:
    """Raise ConfigError unless ``matcher`` has an ``interpolate`` method (``what`` names it in the message)."""
    if not matcher_run.interpolates(matcher):
        raise ConfigError(
            "task=pose_transfer needs an interpolating matcher (with an interpolate(x, y, times) method); "
            f"{what or type(matcher).__name__} has none (e.g. model=neuromorph ckpt_path=CKPT, or model=linear_blend "
            "around any matcher)"
        )


def load_sample(
    path: str | os.PathLike, normalization: Normalization, operators: OperatorConfig, cache: ShapeCache
) -> ShapeSample:
    """A mesh file as a :class:`ShapeSample` (no ground truth), operators from the shape cache.

    Parameters
    ----------
    path : path
        ``.off``, ``.ply`` or ``.obj`` file.
    normalization : Normalization
    operators : OperatorConfig
        The operators to provide (computed on a cache miss).
    cache : ShapeCache

    Raises
    ------
    MeshReadError
        Missing or unreadable file, unknown format.
    InvalidMeshError
        The file holds an invalid mesh.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshReadError("file not found" if not path.exists() else "is not a file", path)
    return sample_with_operators(load_mesh_cached(cache, path, normalization), operators, cache)


def transfer_pose(
    matcher,
    x: ShapeSample,
    y: ShapeSample,
    out_dir: str | os.PathLike,
    interp_times=None,
    write_interp: bool = True,
    write_maps: bool = True,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """Deform x into the pose of y with an interpolating matcher and write the results.

    Parameters
    ----------
    matcher : Matcher with ``interpolate``
    x, y : ShapeSample
        Source (identity) and target (pose), normalized.
    out_dir : path
        Outputs go to ``out_dir/pose_transfer/<x>__<y>/`` (see the module docstring).
    interp_times : sequence of float, optional
        Times of the frames to write; None: the matcher's default frames (those of ``match``).
    write_interp, write_maps : bool
        Write the frames + ``times.txt`` / the map.
    device : torch.device or str
        Where the matcher runs.

    Returns
    -------
    dict with the written paths (``folder``, ``deformed``, ``frames``, ``times``, ``map``; absent ones None),
    the ``times`` of the frames and the matcher's ``seconds``.

    Raises
    ------
    ConfigError
        The matcher does not interpolate.
    """
    require_interpolating(matcher)
    start = time.perf_counter()
    with torch.no_grad():
        run = matcher_run.run_matcher(matcher, x.to(device), y.to(device), interp_times)
    seconds = time.perf_counter() - start
    result = run.result.cpu().validate(x.shape.n_verts, y.shape.n_verts, pair_name(x.name, y.name))
    run = matcher_run.MatcherRun(result, run.export, run.export_times)
    if result.deformation is None:
        raise ConfigError(f"{type(matcher).__name__} returned no deformation for {pair_name(x.name, y.name)}")
    unit = matcher_run.unit_time_index(result.times)
    if unit is None:  # run_matcher adds t = 1 for interpolating matchers; guard against a matcher ignoring it
        raise ConfigError(f"{type(matcher).__name__} returned no frame at t = 1 (times {result.times.tolist()})")
    folder = Path(out_dir) / POSE_TRANSFER_DIR / pair_name(x.name, y.name)
    folder.mkdir(parents=True, exist_ok=True)
    faces = x.shape.faces.numpy()
    deformed = folder / DEFORMED_FILE
    write_mesh(deformed, x.shape.denormalize(result.deformation[unit]), faces)
    frames_written, times_file, map_file = [], None, None
    frames, times = run.sequence()
    if write_interp:
        frames_written = write_frames(folder, frames, faces, times, shape=x.shape)
        times_file = folder / TIMES_FILE
    if write_maps:
        map_file = folder / MAP_FILE
        write_map(map_file, result.p2p.numpy(), one_based=False)
    return {
        "folder": folder,
        "deformed": deformed,
        "frames": frames_written,
        "times_file": times_file,
        "map": map_file,
        "times": [float(t) for t in times],
        "seconds": seconds,
    }


def _required_option(cfg: DictConfig, key: str, what: str) -> Path:
    value = cfg.get(key)
    if value is None or str(value).strip() == "":
        raise ConfigError(f"task=pose_transfer needs {key}=<mesh file> ({what}); e.g. source=A.off target=B.off")
    return Path(os.path.expanduser(str(value)))


def run_pose_transfer(cfg: DictConfig) -> dict[str, Any]:
    """``evaluate.py task=pose_transfer`` (see the module docstring); prints and returns the written paths."""
    source = _required_option(cfg, "source", "the shape whose identity is kept")
    target = _required_option(cfg, "target", "the shape whose pose is taken")
    interp_times = interp_times_option(cfg)
    out_dir = Path(str(cfg.output_dir))
    device = resolve_device(str(cfg.device))
    matcher = build_matcher(cfg, device)
    require_interpolating(matcher, "maps_dir" if cfg.get("maps_dir") else None)
    data = cfg.get("data") or {}
    # Only the data config's normalization, operators and cache folder are used (with_operators merges the
    # matcher's needs as for an evaluation); the module's root is never read.
    dm = ShapePairDataModule(
        root=source.parent,
        normalization=data.get("normalization"),
        operators=data.get("operators"),
        cache_dir=data.get("cache_dir"),
    )
    dm.with_operators(required_request(matcher))
    cache = ShapeCache(default_cache_root() if dm.cache_dir is None else dm.cache_dir)
    x = load_sample(source, dm.normalization, dm.operators, cache)
    y = load_sample(target, dm.normalization, dm.operators, cache)
    out = transfer_pose(matcher, x, y, out_dir, interp_times, bool(cfg.write_interp), bool(cfg.write_maps), device)
    print(f"pose transfer {source} -> pose of {target} ({out['seconds']:.3f} s):")
    print(f"  deformed source: {out['deformed']}")
    if out["frames"]:
        print(f"  {len(out['frames'])} frames at t = {out['times']}: {out['frames'][0].parent}/t_*.ply")
        print(f"  frame times: {out['times_file']}")
    if out["map"] is not None:
        print(f"  map {source.stem} -> {target.stem} (zero-based): {out['map']}")
    return out
