"""Benchmark: seconds and peak memory of every method's unit of work on one fixed pair, CPU (1 and 2 threads) and CUDA.

    python benchmarks/speed.py [--golden DIR] [--cases all|NAME ...] [--devices cpu1 cpu2 cuda] [--repeats 3]
    python benchmarks/speed.py --devices cuda --repeats 3          # the CUDA column alone (skipped without CUDA)
    python benchmarks/speed.py --cases neuromorph_train_t0 neuromorph_train_t7 --devices cpu1

Inputs: the golden FAUST_r pair ``tr_reg_080 -> tr_reg_081`` (``--golden`` or ``$SHAPECORR_DEEP_SHELLS_GOLDEN``,
default ``/work/shared/data/reference/deep_shells_golden``): meshes (5000 / 5001 vertices), 510 eigenpairs and SHOT
of the original Deep Shells, and the original's map ``x -> y`` (the Hamiltonian targets ``y[map]``). Nothing is
read from ``$SHAPECORR_FAUST_R`` and no shape cache is filled, so the numbers do not depend on this project's
operator code; DiffusionNet's gradient operators (G-MSM) are computed once per process, outside the timing.

Cases (the units of the speed table of docs/speed.md):

* ``deep_shells_train``: one Deep Shells training step (published network and weights, 2000 samples per shape,
  the published shell schedule): ``training_step`` + backward;
* ``deep_shells_query``: one Deep Shells test query (full-resolution features, 40 refinement levels);
* ``gmsm_train``: one G-MSM training step (DiffusionNet of the G-MSM code: width 128, 4 blocks, k_eig 128, 2000
  samples) + backward + Adam step;
* ``gmsm_query``: G-MSM's fast one-level query of the pair;
* ``hamiltonian_published``: one Adam iteration of Hamiltonian interpolation at the published setting (K = 8,
  i.e. 1536 fields, 2000 samples, 16 steps): simulation + backward;
* ``hamiltonian_small``: the same at K = 4, 1000 samples;
* ``smooth_shells_query``: one Smooth Shells query of the FAUST_r pair ``tr_reg_080 -> tr_reg_081`` (read from
  ``$SHAPECORR_FAUST_R`` through the data pipeline of ``evaluate.py data=faust_r``) with the default
  ``model=smooth_shells`` (the published isometric preset: rigid stage, 100 random-search proposals, 51 layers).
  The eigenbasis and SHOT come from the project's shape cache (filled before the timing if missing); the
  original has no figure on this CPU (its paper reports 116 s per query on a GPU machine).
* ``divfree_query``: one divergence-free query of the same FAUST_r pair, read the same way, with the default
  ``model=divfree`` (configs/model/divfree.yaml: Smooth Shells pre-alignment, 3 levels of 500 / 1000 / 2000
  samples, K = 2 / 4 / 8, 50 / 50 / 100 Adam iterations, full-resolution maps and the 5 default frames); the
  original has no figure on this CPU (its paper reports ~370 s per pair).
* ``neuromorph_train_t0`` / ``neuromorph_train_t7``: one NeuroMorph training step (``configs/model/neuromorph.yaml``,
  published settings, seed-0 weights) on the golden pair remeshed to ~2000 vertices per shape
  (:func:`neuromorph_inputs`), with T = 0 (geodesic weight 50) and T = 7 intermediate time steps (geodesic weight 0,
  as the published schedule has it from T = 1 on): ``training_step`` + backward + Adam step. The remeshes
  (``shapecorr.geometry.remeshing``) and their heat-method geodesic matrices are computed once per process before
  the timing (or read from ``--neuromorph-inputs``, the file ``benchmarks/neuromorph_side_by_side.py`` shares with
  the original code); only their sizes matter for the timing.

Every (case, device) runs in a fresh Python process: ``--warmup`` untimed calls (default 1), then ``--repeats``
timed calls (wall and process-CPU seconds; the median is reported). Peak memory: the child's resident set
high-water mark from the moment its inputs are loaded (Linux ``VmHWM`` after resetting it through
``/proc/self/clear_refs``; else the process maximum ``ru_maxrss``), on CUDA ``torch.cuda.max_memory_allocated``
over the same span. Results: ``benchmarks/results/speed.json`` (``--out``), with the originals' figures for the
ratios: as the speed issue recorded them (``ORIGINAL_REFERENCE``) and as re-run side by side with shapecorr
(``ORIGINAL_SIDE_BY_SIDE``; docs/speed.md §3).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_common

REPO = Path(__file__).resolve().parents[1]
RESULT = REPO / "benchmarks" / "results" / "speed.json"
DEFAULT_GOLDEN = Path("/work/shared/data/reference/deep_shells_golden")
PAIR = "tr_reg_080__tr_reg_081"
WEIGHTS = "published_weights_faust_scape_ep20.pth"
#: Deep Shells / G-MSM subsample_num: vertices per shape and training step.
TRAIN_SAMPLES = 2000
#: Hamiltonian settings of the two cases: modes per axis K and farthest-point samples.
HAMILTONIAN_SETTINGS = {"hamiltonian_published": {"n_modes": 8, "samples": 2000},
                        "hamiltonian_small": {"n_modes": 4, "samples": 1000}}
#: NeuroMorph cases: intermediate time steps T and the geodesic weight the published schedule uses with that T
#: (NeuroMorph code, SettingsFaust: lambda_geo 50 while T = 0, then 0; configs/model/neuromorph.yaml).
NEUROMORPH_SETTINGS = {"neuromorph_train_t0": {"n_intermediate": 0, "lambda_geo": 50.0},
                       "neuromorph_train_t7": {"n_intermediate": 7, "lambda_geo": 0.0}}
#: NeuroMorph's working resolution (vertices per shape; the original trains on 2000-vertex FAUST_r remeshes).
NEUROMORPH_VERTS = 2000
CASES = ("deep_shells_train", "deep_shells_query", "gmsm_train", "gmsm_query", "hamiltonian_published",
         "hamiltonian_small", "smooth_shells_query", "divfree_query", *NEUROMORPH_SETTINGS)
#: Cases that run one query of a FAUST_r pair through the data pipeline, and the ``model=`` each uses.
FAUST_R_QUERIES = {"smooth_shells_query": "smooth_shells", "divfree_query": "divfree"}
#: The FAUST_r pair of the FAUST_r query cases (the same pair as the golden inputs).
FAUST_R_PAIR = ("tr_reg_080", "tr_reg_081")
DEVICES = ("cpu1", "cpu2", "cuda")
#: The originals' CPU seconds per unit as the speed issue recorded them (one thread, medians of CPU time, on a 2-core
#: Xeon of this kind; the originals run with a k-d tree in place of torch_cluster's knn), kept as recorded.
#: :data:`ORIGINAL_SIDE_BY_SIDE` has the originals re-run next to shapecorr. docs/speed.md.
ORIGINAL_REFERENCE = {
    "deep_shells_train": {"seconds": 9.36, "peak_memory_mb": None},
    "deep_shells_query": {"seconds": 15.35, "peak_memory_mb": None},
    "gmsm_train": {"seconds": 5.55, "peak_memory_mb": 3900.0},
    "gmsm_query": {"seconds": 2.98, "peak_memory_mb": None},
    "hamiltonian_published": {"seconds": 62.1, "peak_memory_mb": 3470.0},
    "hamiltonian_small": {"seconds": 1.42, "peak_memory_mb": None},
    "neuromorph_train_t0": {"seconds": 5.0, "peak_memory_mb": None},
    "neuromorph_train_t7": {"seconds": 16.6, "peak_memory_mb": None},
}
#: The originals re-run side by side with shapecorr on the same inputs (one thread each, alternating fresh
#: processes, medians over the processes of CPU seconds per unit; docs/speed.md §3): the original's and shapecorr's
#: seconds in that session, and its file in benchmarks/results/. The ratio of a session is the figure to compare:
#: the load of the shared machine moves both codes' seconds from session to session.
ORIGINAL_SIDE_BY_SIDE = {
    "deep_shells_train": {"original_seconds": 8.37, "shapecorr_seconds": 0.339,
                          "result": "originals_side_by_side.json"},
    "deep_shells_query": {"original_seconds": 6.79, "shapecorr_seconds": 1.934,
                          "result": "originals_side_by_side_4cases.json"},
    "gmsm_train": {"original_seconds": 9.06, "shapecorr_seconds": 0.884,
                   "result": "originals_side_by_side_4cases.json"},
    "gmsm_query": {"original_seconds": 4.85, "shapecorr_seconds": 0.287, "result": "originals_side_by_side.json"},
    "hamiltonian_small": {"original_seconds": 1.145, "shapecorr_seconds": 0.211,
                          "result": "hamiltonian_side_by_side.json"},
    "neuromorph_train_t0": {"original_seconds": 6.18, "shapecorr_seconds": 1.07,
                            "result": "neuromorph_side_by_side.json"},
    "neuromorph_train_t7": {"original_seconds": 19.31, "shapecorr_seconds": 2.53,
                            "result": "neuromorph_side_by_side.json"},
}
#: Figures of an original without a measurement on this CPU: recorded as notes, not as ratios.
ORIGINAL_NOTES = {
    "smooth_shells_query": "the Smooth Shells paper (CVPR 2020, §6) reports 116 s per query on a GPU machine; "
                           "target of the speed issue: <= 30 s CPU at one thread",
    "divfree_query": "the divergence-free paper (SGP 2019) reports ~370 s per pair; target of the speed issue: "
                     "<= 60 s CPU per pair at one thread with the config defaults",
}
#: Per-unit targets of the speed issue: the original's seconds divided by shapecorr's.
TARGET_RATIO = {"deep_shells_train": 10.0, "deep_shells_query": 6.0, "gmsm_train": 8.0, "gmsm_query": 8.0,
                "hamiltonian_published": 5.0, "hamiltonian_small": 5.0, "neuromorph_train_t0": 10.0,
                "neuromorph_train_t7": 10.0}
MIB = 2 ** 20


# ----------------------------------------------------------------------------------------------------------
# Child process: inputs, one case, measurements
# ----------------------------------------------------------------------------------------------------------
def _golden_pair(golden: Path, device, diffusion: bool = False):
    """PairSample of the golden pair: eigenbasis (shapecorr's eigenvalue convention), SHOT, optionally DiffusionNet's
    gradient operators."""
    import numpy as np
    import torch

    from shapecorr.data.datasets import PairSample, ShapeSample
    from shapecorr.data.shape import make_shape
    from shapecorr.nn.spectral_conv import ORIGINAL_EIGENVALUE_FACTOR

    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    samples = []
    for side, name in zip("xy", PAIR.split("__")):
        # the golden vertices are already normalized (area 0.44, the original convention): keep them
        shape = make_shape(inputs[f"{side}_verts"], inputs[f"{side}_faces"], name, normalization=None)
        operators = {
            "eigenbasis": {"evals": torch.from_numpy(inputs[f"{side}_evals"]) / ORIGINAL_EIGENVALUE_FACTOR,
                           "evecs": torch.from_numpy(inputs[f"{side}_evecs"]),
                           "mass": torch.from_numpy(inputs[f"{side}_mass"])},
            "shot": {"shot": torch.from_numpy(inputs[f"{side}_shot"])},
        }
        if diffusion:
            from shapecorr.geometry.diffusion_operators import diffusion_gradients

            operators["diffusion_gradients"] = diffusion_gradients(shape.verts.numpy().astype(np.float64),
                                                                   shape.faces.numpy())
        samples.append(ShapeSample(shape=shape, operators=operators))
    return PairSample(*samples).to(device)


def _learned_unit(model, pair, train: bool, optimizer=None):
    """A training step (``training_step`` + backward, + the optimizer's step if given; returns the loss) or a query
    of ``pair`` (returns the pair cost the matcher reports, G-MSM's alignment cost, else the map's size)."""
    if not train:
        from shapecorr.eval.multi_shape import PAIR_COST_KEY

        def query():
            result = model.match(pair.x, pair.y)
            cost = result.extras.get(PAIR_COST_KEY)
            return float(cost) if cost is not None else int(result.p2p.numel())
        return query

    def step():
        model.zero_grad(set_to_none=True)
        loss = model.training_step(pair, 0)
        loss.backward()
        if optimizer is not None:
            optimizer.step()
        return float(loss.detach())
    return step


def _published_loss(model: str):
    """The loss of ``configs/model/<model>.yaml`` (its composed ``model.loss`` node), built."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        return instantiate(compose("train", overrides=[f"model={model}"]).model.loss, _convert_="object")


def deep_shells_model(golden: Path, device, train: bool, layer=None):
    """The Deep Shells model of the two Deep Shells cases: published weights and loss, :data:`TRAIN_SAMPLES`
    samples, the published layer settings (or ``layer``, a ``DeepShellsConfig``)."""
    from shapecorr.models.deep_shells import DeepShells

    extra = {} if layer is None else {"layer": layer}
    return DeepShells(num_samples=TRAIN_SAMPLES, pretrained=golden / WEIGHTS, loss=_published_loss("deep_shells"),
                      **extra).to(device).train(train)


def _deep_shells(golden: Path, device, train: bool):
    return _learned_unit(deep_shells_model(golden, device, train), _golden_pair(golden, device), train)


def gmsm_model(golden: Path, device, train: bool, **options):
    """The G-MSM model of the two G-MSM cases: seed-0 DiffusionNet of the G-MSM code, :data:`TRAIN_SAMPLES` samples,
    the published loss; ``options`` go to ``GMSM`` (e.g. ``dropout_at_test``)."""
    import torch

    from shapecorr.models.gmsm import GMSM
    from shapecorr.nn.diffusion_net import DiffusionNetBackbone

    torch.manual_seed(0)
    model = GMSM(backbone=DiffusionNetBackbone(), num_samples=TRAIN_SAMPLES, loss=_published_loss("gmsm"), **options)
    return model.to(device).train(train)


def _gmsm(golden: Path, device, train: bool):
    import torch

    model = gmsm_model(golden, device, train)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4) if train else None
    return _learned_unit(model, _golden_pair(golden, device, diffusion=True), train, optimizer)


def _hamiltonian(golden: Path, device, setting: dict):
    """One Adam iteration (simulation on the samples + backward) of :func:`hamiltonian_interpolation`'s loop."""
    import numpy as np
    import torch

    from shapecorr.axiomatic import hamiltonian as ham
    from shapecorr.axiomatic.divfree import knn_graph_edges
    from shapecorr.geometry import divergence_free as df
    from shapecorr.geometry.sampling import farthest_point_sampling
    from shapecorr.losses.arap import edge_vectors

    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    mapping = np.load(golden / f"original_output_{PAIR}.npz")["map_x_to_y"].astype(np.int64)
    vx = torch.from_numpy(inputs["x_verts"]).float().to(device)
    target = torch.from_numpy(inputs["y_verts"][mapping]).float().to(device)
    cfg = ham.HamiltonianConfig(**setting)
    box_x, box_y = df.box_normalization(vx, target, cfg.margin)
    bx, by = box_x.to_box(vx), box_y.to_box(target)
    samples = torch.from_numpy(farthest_point_sampling(bx.cpu(), cfg.samples, start=0)).to(device)
    x0 = bx[samples]
    edges, counts = knn_graph_edges(x0, cfg.knn)
    graph = ham._Graph(edges, counts, edge_vectors(x0, edges))
    coeffs = torch.zeros(df.n_fields(cfg.n_modes), device=device, requires_grad=True)
    aniso = torch.eye(3, device=device).repeat(cfg.samples, 1, 1).requires_grad_(True)
    log_lam = torch.tensor(math.log(cfg.lambda_inertia), device=device).requires_grad_(True)
    optimizer = torch.optim.Adam([coeffs, aniso, log_lam], lr=cfg.lr)
    goal = by[samples]

    def op():
        optimizer.zero_grad(set_to_none=True)
        x_end, e_arap, _ = ham._simulate(x0, coeffs, aniso, log_lam, graph, cfg.n_steps, cfg)
        loss = torch.nn.functional.mse_loss(x_end, goal) + cfg.lambda_reg * e_arap
        loss.backward()
        optimizer.step()
        return float(loss.detach())
    return op


def _faust_r_query(model: str, device):
    """One query of the FAUST_r pair with ``model=<model>`` as ``evaluate.py data=faust_r`` builds it."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from shapecorr.cli.matcher_factory import build_matcher
    from shapecorr.data.operators import required_request

    if not os.environ.get("SHAPECORR_FAUST_R"):
        raise SystemExit(f"error: the {model} query needs $SHAPECORR_FAUST_R (the FAUST_r folder)")
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"model={model}", "data=faust_r"])
    matcher = build_matcher(cfg, device)
    dm = instantiate(cfg.data, _convert_="object")
    dm.with_operators(required_request(matcher))
    shapes = dm.shapes("test")
    x, y = (shapes[shapes.index(name)].to(device) for name in FAUST_R_PAIR)
    return lambda: int(matcher.match(x, y).p2p.sum())


def neuromorph_inputs(golden: Path, path: Path | None = None) -> dict:
    """The NeuroMorph pair: the golden meshes remeshed to ~:data:`NEUROMORPH_VERTS` vertices, with geodesics.

    Parameters
    ----------
    golden : Path
        The deep_shells_golden folder (its pair :data:`PAIR`, vertices already normalized to area 0.44).
    path : Path, optional
        An ``.npz`` of these arrays: read when it exists, else written after computing them.

    Returns
    -------
    dict of numpy arrays
        ``verts_x (n_x, 3)`` float32, ``faces_x (f_x, 3)`` int64, ``dist_x (n_x, n_x)`` float32 (heat-method
        geodesics, symmetric, zero diagonal), the same for ``y``.
    """
    import numpy as np

    if path is not None and Path(path).is_file():
        with np.load(path) as stored:
            return {key: stored[key] for key in stored.files}
    from shapecorr.geometry.geodesics import geodesic_distances
    from shapecorr.geometry.remeshing import remesh

    inputs = np.load(golden / f"inputs_{PAIR}.npz")
    arrays = {}
    for side in "xy":
        verts, faces = remesh(inputs[f"{side}_verts"].astype(np.float64), inputs[f"{side}_faces"], NEUROMORPH_VERTS)
        arrays[f"verts_{side}"] = verts.astype(np.float32)
        arrays[f"faces_{side}"] = faces.astype(np.int64)
        arrays[f"dist_{side}"] = geodesic_distances(verts, faces, method="heat").astype(np.float32)
    if path is not None:
        np.savez(path, **arrays)
    return arrays


def _neuromorph(golden: Path, device, setting: dict, inputs_path: Path | None):
    """One NeuroMorph training step (``training_step`` + backward + Adam) on the pair of :func:`neuromorph_inputs`."""
    import torch
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from shapecorr.data.augmentation import AugmentedPair
    from shapecorr.data.datasets import PairSample, ShapeSample
    from shapecorr.data.shape import make_shape

    arrays = neuromorph_inputs(golden, inputs_path)
    # the vertices are already normalized (area 0.44): kept as they are, the same positions the original receives
    samples = [ShapeSample(shape=make_shape(arrays[f"verts_{s}"], arrays[f"faces_{s}"], s, normalization=None),
                           operators={}) for s in "xy"]
    batch = AugmentedPair(pair=PairSample(*samples).to(device), dist_x=torch.from_numpy(arrays["dist_x"]),
                          dist_y=torch.from_numpy(arrays["dist_y"]), remeshed_x=None, remeshed_y=None,
                          rotation=torch.eye(3))
    torch.manual_seed(0)
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=["model=neuromorph", f"model.n_intermediate={setting['n_intermediate']}"])
    model = instantiate(cfg.model, _convert_="object").to(device).train(True)
    model.loss.set_weight(model.geo_term, setting["lambda_geo"])
    optimizer = model.configure_optimizers()  # the published Adam 1e-4 (configs/model/optimizer/adam.yaml)
    return _learned_unit(model, batch, True, optimizer)


def build_case(case: str, golden: Path, device, neuromorph_inputs_path: Path | None = None):
    """The measured operation of ``case`` (a zero-argument callable), inputs loaded."""
    if case in ("deep_shells_train", "deep_shells_query"):
        return _deep_shells(golden, device, train=case.endswith("train"))
    if case in ("gmsm_train", "gmsm_query"):
        return _gmsm(golden, device, train=case.endswith("train"))
    if case in HAMILTONIAN_SETTINGS:
        return _hamiltonian(golden, device, HAMILTONIAN_SETTINGS[case])
    if case in FAUST_R_QUERIES:
        return _faust_r_query(FAUST_R_QUERIES[case], device)
    if case in NEUROMORPH_SETTINGS:
        return _neuromorph(golden, device, NEUROMORPH_SETTINGS[case], neuromorph_inputs_path)
    raise SystemExit(f"error: unknown case {case!r}; one of {CASES}")


def run_child(case: str, golden: Path, device_name: str, threads: int, repeats: int, warmup: int = 1,
              neuromorph_inputs_path: Path | None = None) -> dict:
    import resource

    import torch

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    device = torch.device(device_name)
    cuda = device.type == "cuda"
    op = build_case(case, golden, device, neuromorph_inputs_path)
    cuda_base, baseline_kb, reset = bench_common.start_memory_span(device)
    walls, cpus, value = [], [], None
    for i in range(repeats + warmup):  # the first calls warm up (allocator, lazy initialization, kernels)
        wall, cpu = time.perf_counter(), time.process_time()
        value = op()
        if cuda:
            torch.cuda.synchronize(device)
        if i >= warmup:
            walls.append(time.perf_counter() - wall)
            cpus.append(time.process_time() - cpu)
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux: the process maximum
    hwm = bench_common.status_kb("VmHWM") if reset else None
    if hwm is None:
        hwm = maxrss
    out = {"case": case, "device": device_name, "threads": threads, "seconds": walls, "cpu_seconds": cpus,
           "seconds_median": statistics.median(walls), "cpu_seconds_median": statistics.median(cpus),
           "value": value, "peak_rss_mb": hwm / 1024, "baseline_rss_mb": (baseline_kb or 0) / 1024,
           "process_max_rss_mb": maxrss / 1024,
           "peak_source": "VmHWM after clear_refs" if reset else "ru_maxrss (process maximum)"}
    if cuda:
        peak = torch.cuda.max_memory_allocated(device)
        out.update(cuda_max_allocated_mb=peak / MIB, cuda_baseline_allocated_mb=cuda_base / MIB,
                   device_name=torch.cuda.get_device_name(device))
    return out


# ----------------------------------------------------------------------------------------------------------
# Parent: one fresh process per (case, device)
# ----------------------------------------------------------------------------------------------------------
def child_command(case: str, golden: Path, device_name: str, threads: int, repeats: int, warmup: int = 1,
                  neuromorph_inputs_path: Path | None = None) -> list[str]:
    """Command line of one measuring child process (also run by ``benchmarks/neuromorph_side_by_side.py``)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", case, "--golden", str(golden),
           "--device", device_name, "--threads", str(threads), "--repeats", str(repeats), "--warmup", str(warmup)]
    if neuromorph_inputs_path is not None:
        cmd += ["--neuromorph-inputs", str(neuromorph_inputs_path)]
    return cmd


def measure(case: str, golden: Path, device: str, repeats: int, timeout: float, warmup: int = 1,
            neuromorph_inputs_path: Path | None = None) -> dict:
    device_name, threads = ("cuda", 1) if device == "cuda" else ("cpu", int(device[3:]))
    cmd = child_command(case, golden, device_name, threads, repeats, warmup, neuromorph_inputs_path)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        try:
            proc = subprocess.run(cmd, stdout=out, stderr=err, text=True, cwd=REPO, env=env, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"case": case, "device": device, "error": f"timed out after {timeout:.0f} s"}
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        return {"case": case, "device": device, "error": stderr.strip().splitlines()[-1] if stderr.strip() else
                f"exit {proc.returncode}"}
    result = json.loads(stdout.strip().splitlines()[-1])
    # each result keeps its own provenance: the file merges results of several runs
    result.update(device=device, date_utc=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  command=" ".join([Path(sys.executable).name, *sys.argv]), load_average_1min_before=load_before,
                  load_average_1min_after=os.getloadavg()[0])
    return result


def _table(results: list[dict]) -> str:
    lines = ["| case | device | CPU s (median) | wall s (median) | peak RSS MB | CUDA peak MB | original s recorded | "
             "ratio | side by side: original / shapecorr s | ratio |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['device']} | error: {r['error']} | | | | | | | |")
            continue
        ref = ORIGINAL_REFERENCE.get(r["case"], {}).get("seconds")
        ratio = f"{ref / r['cpu_seconds_median']:.1f}x" if ref and r["device"] == "cpu1" else ""
        sbs = ORIGINAL_SIDE_BY_SIDE.get(r["case"])
        sbs_cells = (f"{sbs['original_seconds']} / {sbs['shapecorr_seconds']} | "
                     f"{sbs['original_seconds'] / sbs['shapecorr_seconds']:.1f}x") if sbs else " | "
        cuda = f"{r['cuda_max_allocated_mb']:.0f}" if "cuda_max_allocated_mb" in r else ""
        lines.append(f"| {r['case']} | {r['device']} | {r['cpu_seconds_median']:.2f} | {r['seconds_median']:.2f} | "
                     f"{r['peak_rss_mb']:.0f} | {cuda} | {ref if ref else ''} | {ratio} | {sbs_cells} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--golden", type=Path, default=None,
                        help="deep_shells_golden folder (default $SHAPECORR_DEEP_SHELLS_GOLDEN, then the shared copy)")
    parser.add_argument("--cases", nargs="+", default=["all"], help=f"any of {CASES} (default all)")
    parser.add_argument("--devices", nargs="+", default=list(DEVICES), help="cpu1, cpu2, cuda (default all three)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1, help="untimed calls before the timed ones (default 1)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per (case, device) process")
    parser.add_argument("--out", type=Path, default=RESULT)
    parser.add_argument("--neuromorph-inputs", type=Path, default=None,
                        help="npz of the NeuroMorph pair (read if present, else computed and written there)")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--device", default="cpu", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    golden = args.golden or Path(os.environ.get("SHAPECORR_DEEP_SHELLS_GOLDEN", DEFAULT_GOLDEN))
    if not (golden / f"inputs_{PAIR}.npz").is_file():
        print(f"error: {golden}: no inputs_{PAIR}.npz (set --golden or $SHAPECORR_DEEP_SHELLS_GOLDEN)", file=sys.stderr)
        return 2
    if args.child:
        print(json.dumps(run_child(args.child, golden, args.device, args.threads, args.repeats, args.warmup,
                                   args.neuromorph_inputs)))
        return 0
    cases = list(CASES) if args.cases == ["all"] else args.cases
    unknown = sorted(set(cases) - set(CASES)) + sorted(set(args.devices) - set(DEVICES))
    if unknown:
        print(f"error: unknown cases/devices {unknown}; cases {CASES}, devices {DEVICES}", file=sys.stderr)
        return 2
    import torch

    devices = [d for d in args.devices if d != "cuda" or torch.cuda.is_available()]
    if len(devices) < len(args.devices):
        print("cuda: not available, skipped", file=sys.stderr)
    results = []
    for case in cases:
        for device in devices:
            result = measure(case, golden, device, args.repeats, args.timeout, args.warmup, args.neuromorph_inputs)
            results.append(result)
            shown = result.get("error") or (f"cpu {result['cpu_seconds_median']:.2f} s, wall "
                                            f"{result['seconds_median']:.2f} s, peak {result['peak_rss_mb']:.0f} MB")
            print(f"{case:24s} {device:5s} {shown}", flush=True)
    previous = json.loads(args.out.read_text()) if args.out.is_file() else {}
    merged = {(r["case"], r["device"]): r for r in previous.get("results", [])}
    merged.update({(r["case"], r["device"]): r for r in results})
    report = {
        "benchmark": "speed",
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "inputs": {"golden": PAIR, "train_samples": TRAIN_SAMPLES, "hamiltonian": HAMILTONIAN_SETTINGS,
                   "faust_r_pair": list(FAUST_R_PAIR), "faust_r": os.environ.get("SHAPECORR_FAUST_R"),
                   "neuromorph": {"verts": NEUROMORPH_VERTS, **NEUROMORPH_SETTINGS}},
        "repeats": args.repeats,
        "machine": bench_common.machine_info(),
        "original_reference": ORIGINAL_REFERENCE,
        "original_side_by_side": ORIGINAL_SIDE_BY_SIDE,
        "original_notes": ORIGINAL_NOTES,
        "target_ratio": TARGET_RATIO,
        "results": sorted(merged.values(), key=lambda r: (CASES.index(r["case"]), r["device"])),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(_table(report["results"]))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
