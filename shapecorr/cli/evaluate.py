"""``evaluate.py``: evaluate any matcher, or transfer a pose with an interpolating one.

The matcher may be learned, axiomatic, a baseline, or maps computed elsewhere.

    python evaluate.py model=descriptor_nn data=faust_r data.root=DIR pairs=test output_dir=OUT
    python evaluate.py model=<learned> ckpt_path=CKPT data=... output_dir=OUT [interp_times=[0,0.5,1,1.5]]
    python evaluate.py maps_dir=DIR [maps_one_based=true maps_extension=map] data=... output_dir=OUT
    python evaluate.py model=<interpolating> [ckpt_path=CKPT] task=pose_transfer source=A.off target=B.off \
        [output_dir=OUT] [interp_times=[...]]

Options: ``configs/evaluate.yaml``. Steps of ``task=match`` (the default):

1. Build the matcher (``hydra.utils.instantiate(cfg.model)``; with ``ckpt_path`` the checkpoint's recipe with the
   command line's ``model.*`` overrides on top, and its weights, :func:`shapecorr.models.recipe.load_model`; or
   :class:`~shapecorr.matching.baselines.PrecomputedMaps` for ``maps_dir``) and the data module;
   the matcher's ``required_operators`` (an operator request, e.g. ``{"wks": {}}``;
   :mod:`shapecorr.data.operators`) are added to the data's operators.
2. Fill the shape cache of the split, with the geodesic rows from every target's ground-truth points (rank 0,
   parallel, workers chosen from the estimated memory, progress bar).
3. Evaluate this rank's shard of the pairs (:mod:`shapecorr.eval.pair_pool`): per-pair records, maps. With
   ``multishape=graph`` the model is first queried on the split's candidate pairs (sharded, resumable) and the
   pairs get the maps composed through the shape graph (:class:`~shapecorr.eval.multi_shape.MultiShapeMatcher`,
   docs/evaluation.md §7); ``metrics.json["multi_shape"]`` then reports cycle consistency.
4. Rank 0 merges the records of all pairs into ``metrics.json``, ``per_pair.csv``, ``pck.png`` and renders
   ``examples/<x>__<y>.png``.

Interpolating matchers (those with an ``interpolate(x, y, times)`` method, e.g. NeuroMorph or
``model=linear_blend``, or any matcher with ``interpolator=linear_blend | hamiltonian``: see
:func:`.with_interpolator`) are called at ``interp_times`` (default ``[0, 0.25, 0.5, 0.75, 1]``; values > 1
extrapolate; ``null`` = the matcher's own default frames). Each pair's frames are written (``write_interp``)
as ``OUT/interp/<x>__<y>/t_XX.ply`` (XX = index into ``interp_times``, in x's input units) with
``times.txt`` (line XX = time of t_XX). The metrics compare the frame at t = 1 with y (Chamfer distance,
fractions of sqrt(area(y))) and average the conformal distortion along the sequence over the frames with
0 <= t <= 1; when 1 is not among ``interp_times`` it is evaluated as well for the metrics but not written.
``metrics.json`` then holds ``mean_deformation_conformal_distortion``, ``mean_chamfer``,
``mean_chamfer_one_sided``, ``mean_volume_change``, ``mean_volume_score`` and ``interp_curves`` (per frame
time: mean conformal distortion and volume score ``V_t/V_0 + V_0/V_t - 2`` over pairs, drawn as
``OUT/interp_curves.png``); these are absent for other matchers (``mean_conformal_distortion`` is the
distortion of the map, for every matcher). ``per_pair.csv`` holds the per-pair values, ``pairs/<x>__<y>.json``
also the per-pair curves, and the printed summary the first two.

``task=pose_transfer`` (:mod:`shapecorr.cli.pose_transfer`) runs an interpolating matcher on two mesh files,
``source=A`` and ``target=B`` (.off/.ply/.obj, normalized like the data config's shapes, operators cached),
and writes ``OUT/pose_transfer/<A>__<B>/``: ``deformed.ply`` (the frame at t = 1 in A's input units: A's
identity in B's pose), the frames ``t_XX.ply`` + ``times.txt`` at ``interp_times`` (``write_interp``) and the
map A -> B ``map.txt`` (zero-based, one line per vertex of A; ``write_maps``); it prints the paths.

Ctrl-C stops the run with one line: how many pairs are done and the command that resumes it (the same
options plus ``output_dir=OUT``, since the default output folder is new for every run); a resumed run prints
``resuming: N of M pairs done``.

Resumption: ``OUT/run.json`` records what is evaluated and every setting that changes a number (matcher,
checkpoint or maps folder, post-processing, interpolator, split, geodesics, conformal clamp, the interpolation
times of interpolating matchers, and :func:`~shapecorr.eval.fingerprint.data_settings`: data folder, normalization,
resolved operators, reference points, mesh validation); a re-run with the same ``output_dir`` skips the pairs
already done and refuses, naming the differing keys, to mix results of a different run. DDP: launch with
``torchrun --nproc_per_node=N evaluate.py ...``; every rank evaluates every N-th pair into the same folder
(a shared file system), then rank 0 writes the reports.
"""

from __future__ import annotations

import datetime
import json
import platform
import shutil
import signal
import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from shapecorr.cli.common import EXIT_INTERRUPTED, check_output_dir, exit_on_user_error, user_config_error
from shapecorr.cli.matcher_factory import (
    build_matcher,
    interp_times_option,
    interpolator_config,
    multishape_of,
    resolve_device,
)
from shapecorr.cli.pose_transfer import run_pose_transfer
from shapecorr.cli.threads import configure_threads
from shapecorr.data.cache import atomic_open
from shapecorr.data.datasets import PairDataset, check_pair_names, pair_name
from shapecorr.data.operators import required_request
from shapecorr.errors import ConfigError
from shapecorr.eval import matcher_run, multi_shape, pair_pool, protocol, reports
from shapecorr.eval.fingerprint import data_settings, fingerprint_changes
from shapecorr.eval.records import RECORDS_DIR, count_done, load_record
from shapecorr.eval.sharding import distributed_context, shard_pairs
from shapecorr.eval.export import INTERP_DIR, map_paths
from shapecorr.viz.interp_curves import INTERP_CURVES_PNG, write_interp_curves_png
from shapecorr.viz.pck import write_pck_png
from shapecorr.viz.render import render_correspondence
from shapecorr.viz.shape_graph import write_shape_graph_png

RUN_FILE = "run.json"
EXAMPLES_DIR = "examples"
#: Values of the ``task`` option: evaluate pairs of a dataset, or transfer a pose between two mesh files.
TASKS = ("match", "pose_transfer")


def _matcher_name(matcher) -> str:
    return f"{type(matcher).__module__}.{type(matcher).__qualname__}"


def _init_distributed(device: torch.device) -> tuple[int, int]:
    rank, world = distributed_context()
    if world > 1:
        import torch.distributed as dist

        if not dist.is_available():
            raise ConfigError(f"WORLD_SIZE={world} but torch.distributed is not available")
        if not dist.is_initialized():
            if device.type == "cuda":
                torch.cuda.set_device(device)
            dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        rank, world = dist.get_rank(), dist.get_world_size()
    return rank, world


def _barrier() -> None:
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.barrier()


def _check_run_file(out_dir: Path, fingerprint: dict[str, Any], resume: bool) -> None:
    """Start a fresh output folder or make sure a resumed one holds the same run."""
    run_file = out_dir / RUN_FILE
    if run_file.is_file() and resume:
        try:
            previous = json.loads(run_file.read_text())
        except (OSError, ValueError):
            previous = None
        changes = fingerprint_changes(previous, fingerprint)
        if changes:
            shown = "; ".join(changes[:4]) + (f"; and {len(changes) - 4} more" if len(changes) > 4 else "")
            raise ConfigError(
                f"holds results of a different evaluation ({RUN_FILE} differs in {shown}); use another output_dir, "
                "or resume=false to start over",
                out_dir,
            )
        return
    if not resume:
        for sub in (RECORDS_DIR, EXAMPLES_DIR, INTERP_DIR):
            shutil.rmtree(out_dir / sub, ignore_errors=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_open(run_file) as fh:
        fh.write((json.dumps(fingerprint, indent=1, sort_keys=True) + "\n").encode())


def _peak_memory() -> dict[str, float]:
    mem = reports.peak_memory_mb()
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        gathered: list[Any] = [None] * dist.get_world_size()
        dist.all_gather_object(gathered, mem)
        mem = {k: max(m.get(k, 0.0) for m in gathered) for k in set().union(*gathered)}
    return mem


def printable(name: str) -> str:
    """A shape name for text output: names from non-UTF-8 file names (surrogate escapes) with U+FFFD."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def render_examples(out_dir: Path, shapes, pairs, records, n_examples: int, view) -> list[Path]:
    """Texture-transfer renders of ``n_examples`` evenly spaced pairs (existing images are kept)."""
    if n_examples <= 0 or not pairs:
        return []
    keep = sorted(set(np.linspace(0, len(pairs) - 1, min(n_examples, len(pairs))).round().astype(int).tolist()))
    written = []
    for k in keep:
        (i, j), record = pairs[k], records[k]
        path = out_dir / EXAMPLES_DIR / f"{pair_name(record.source, record.target)}.png"
        npy = map_paths(out_dir, record.source, record.target)[1]
        if path.is_file() or not npy.is_file():
            continue
        x, y = shapes.load_shape(i), shapes.load_shape(j)
        p2p = np.load(npy, allow_pickle=False)
        src, tgt = printable(record.source), printable(record.target)
        title = f"{src} -> {tgt}: mean error {record.mean_error:.4f}"
        render_correspondence(path, x.verts, x.faces, y.verts, y.faces, p2p, title=title, view=view,
                              names=(f"{src} (colors via map)", tgt))
        written.append(path)
    return written


def interrupted_message(out_dir: Path, done: int, total: int, argv: list[str] | None = None) -> str:
    """The one line printed when an evaluation is interrupted: how far it got and the command that resumes it."""
    args = list(sys.argv if argv is None else argv)
    args = [a for a in args[1:] if not a.startswith("output_dir=")]
    command = " ".join(["python evaluate.py", *args, f"output_dir={out_dir}"])
    return f"interrupted: {done} of {total} pairs done; resume with: {command}"


def task_option(cfg: DictConfig) -> str:
    """``cfg.task``, checked against :data:`TASKS`."""
    task = str(cfg.get("task") or "match")
    if task not in TASKS:
        raise ConfigError(f"task must be one of {TASKS}, got {task!r}")
    return task


@exit_on_user_error
def evaluate(cfg: DictConfig) -> dict[str, Any] | None:
    """Run the evaluation described by ``cfg`` (configs/evaluate.yaml); returns metrics on rank 0, else None.

    With ``task=pose_transfer`` runs :func:`shapecorr.cli.pose_transfer.run_pose_transfer` instead and returns
    its summary (the written paths).
    """
    try:
        configure_threads(cfg)
        if task_option(cfg) == "pose_transfer":
            return run_pose_transfer(cfg)
        out_dir = check_output_dir(Path(str(cfg.output_dir)), "output_dir=DIR")  # before any work
        device = resolve_device(str(cfg.device))
        rank, world = _init_distributed(device)
        matcher = build_matcher(cfg, device)
        dm = hydra.utils.instantiate(cfg.data, _convert_="object")
        view = tuple(OmegaConf.to_container(cfg.view, resolve=True))
        settings = protocol.EvalSettings(
            geodesics=str(cfg.geodesics),
            conformal_clamp=float(cfg.conformal_clamp),
            write_maps=bool(cfg.write_maps),
            write_interp=bool(cfg.write_interp),
            interp_times=interp_times_option(cfg),
            device=str(device),
        )
    except OmegaConfBaseException as err:
        raise user_config_error(err) from err
    except hydra.errors.InstantiationException as err:
        raise ConfigError(f"cannot build the data module: {err}") from None
    dm.with_operators(required_request(matcher))
    split = str(cfg.pairs)
    shapes = dm.shapes(split)
    base = PairDataset(shapes, pair_file=cfg.pair_file) if cfg.get("pair_file") else dm.pairs(split)
    pair_ds = PairDataset(shapes, pairs=base.pairs, max_pairs=cfg.get("max_pairs"))
    pairs = list(pair_ds.pairs)

    fingerprint = {
        "matcher": "maps_dir" if cfg.get("maps_dir") else _matcher_name(matcher),
        "model": OmegaConf.to_container(cfg.model, resolve=True) if cfg.get("model") is not None else None,
        **({"interpolator": OmegaConf.to_container(interpolator_config(cfg), resolve=True)}
           if interpolator_config(cfg) is not None else {}),  # only when set: older run.json files still match
        "ckpt_path": str(cfg.ckpt_path) if cfg.get("ckpt_path") else None,
        "maps_dir": str(cfg.maps_dir) if cfg.get("maps_dir") else None,
        "split": split,
        "geodesics": settings.geodesics,
        "conformal_clamp": settings.conformal_clamp,
        **data_settings(shapes),  # every data setting that changes a number (operators, reference points)
    }
    if cfg.get("postprocess") is not None:
        fingerprint["postprocess"] = OmegaConf.to_container(cfg.postprocess, resolve=True)
    if matcher_run.interpolates(matcher):
        fingerprint["interp_times"] = None if settings.interp_times is None else list(settings.interp_times)
    if cfg.get("multishape") is not None:
        fingerprint["multishape"] = OmegaConf.to_container(cfg.multishape, resolve=True)
        # refused before any query: every ordered pair is queried, composed and scored on whole meshes
        check_pair_names(((a, b) for a in shapes.names for b in shapes.names if a != b), shapes.root)
        shapes.check_connected("multi-shape matching (multishape=graph: maps composed over all ordered pairs)",
                               "evaluate them without multishape=, or remove the small pieces from the meshes")
    if rank == 0:
        _check_run_file(out_dir, fingerprint, bool(cfg.resume))
        # Fill the cache of every shape of the split once, in parallel, before any pair is evaluated.
        # data.prepare_workers (null: all CPUs), lowered to what the estimated memory allows
        shapes.prepare(num_workers=getattr(dm, "prepare_workers", None), geodesics=settings.geodesics,
                       progress=bool(cfg.progress))
    _barrier()

    graph = multishape_of(matcher)
    mine = shard_pairs(pairs, rank, world)
    names = [(shapes.names[i], shapes.names[j]) for i, j in pairs]
    done = count_done(out_dir, names)
    if rank == 0 and done and bool(cfg.resume):
        print(f"resuming: {done} of {len(pairs)} pairs done in {out_dir}", file=sys.stderr)
    try:
        if graph is not None:  # query the split's pairs (sharded, resumable), then build the shape graph
            graph.prepare(shapes, out_dir, len(pairs), rank, world, device=device,
                          progress=bool(cfg.progress) and rank == 0, barrier=_barrier)
        pair_pool.evaluate_pairs(
            matcher,
            shapes,
            mine,
            out_dir,
            settings,
            workers=int(cfg.workers),
            start_method=str(cfg.start_method),
            progress=bool(cfg.progress) and rank == 0,
        )
    except KeyboardInterrupt:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the workers are stopped; a second Ctrl-C must not cut the exit
        print(interrupted_message(out_dir, count_done(out_dir, names), len(pairs)), file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    _barrier()
    memory = _peak_memory()
    if rank != 0:
        return None

    loaded = [load_record(out_dir, shapes.names[i], shapes.names[j]) for i, j in pairs]
    records = [r for r, _, _ in loaded]
    result = reports.aggregate(records, [e for _, e, _ in loaded], [s for _, _, s in loaded])
    result.update(memory)
    result["n_excluded_points"] = int(sum(r.n_excluded for r in records))
    result["run"] = {
        **fingerprint,
        "device": str(device),
        "workers": int(cfg.workers),
        "world_size": world,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "command": " ".join(sys.argv),
        "machine": platform.processor() or platform.machine(),
        "torch": torch.__version__,
    }
    if graph is not None:
        result["multi_shape"] = graph.report(shapes, pairs, settings.geodesics)
        multi_shape.save_graph(out_dir / "shape_graph.npz", graph.collection, epoch=-1)
        write_shape_graph_png(out_dir / "shape_graph.png", graph.collection.graph, list(shapes.names))
    reports.write_metrics_json(out_dir / "metrics.json", result)
    reports.write_per_pair_csv(out_dir / "per_pair.csv", records)
    label = graph.label if graph is not None else fingerprint["matcher"].rsplit(".", 1)[-1]
    write_pck_png(out_dir / "pck.png", result, label=label)
    if reports.CURVES_KEY in result:
        write_interp_curves_png(out_dir / INTERP_CURVES_PNG, result, label=label)
    render_examples(out_dir, shapes, pairs, records, int(cfg.n_examples), view)
    summary = reports.summary(result, out_dir)
    print(summary)
    if graph is not None:
        print(multi_shape.summary_line(result["multi_shape"]), flush=True)
    return result
