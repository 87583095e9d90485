"""Generation of a synthetic FAUST/SCAPE-style dataset: shapes, ground truth, splits, README, fingerprint.

Per shape (class c, subject s, pose p):

1. subject proportions (``skinning.sample_identity``) deform the class template into the subject's rest
   pose (same vertex set, so correspondence stays exact);
2. the pose's joint angles (key pose p or a shared random pose, plus jitter) and a yaw rotation pose it
   by linear blend skinning; angles are backed off towards the rest pose while distant body parts come
   closer than the contact margin;
3. the posed surface is remeshed isotropically to a random vertex count, vertices and faces are shuffled;
4. every remeshed vertex is traced to the posed template (dense ground truth), reference points are
   matched to their nearest remeshed vertex in the subject's rest pose (``.vts``, and ``.sym.vts`` for the
   mirrored ground truth);
5. optional corruptions (fused self-contacts, holes, noise), rounding, writing.

Randomness: every random choice uses a ``numpy.random.Generator`` seeded by
``SeedSequence([seed, class, subject, pose, stream])``, so a shape does not depend on the other shapes,
on the order of generation or on the number of worker processes.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import textwrap
import uuid
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from shapecorr.data.io import write_mesh, write_vts
from shapecorr.data.synthetic import corruptions, poses
from shapecorr.data.synthetic.config import GENERATOR_VERSION, SyntheticConfig
from shapecorr.data.synthetic.groundtruth import chart_map, interpolate, nearest_vertices, trace_to_surface
from shapecorr.data.synthetic.meshing import edge_length_for_count, topology_report
from shapecorr.data.synthetic.skeleton import BODY_PLANS
from shapecorr.data.synthetic.skinning import (
    blend_skin, identity_transforms, pose_transforms, rotation_about, sample_identity,
)
from shapecorr.data.synthetic.templates import Template, build_template
from shapecorr.errors import DatasetError, InvalidMeshError
from shapecorr.geometry.mesh import triangle_areas
from shapecorr.geometry.remeshing import remesh
from shapecorr.geometry.sampling import farthest_point_sampling

#: Rotation from the generator's axes (x right, y forward, z up; skeleton.py) to the axes of the written
#: files, those of FAUST: y up, z forward (the way the creature looks), x the creature's left.
OUTPUT_ROTATION = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
#: Creature classes in output order, with the integer used in their random streams.
CLASS_IDS = {"human": 0, "quad": 1}
#: Random streams (last entry of the seed sequence).
_STREAM_IDENTITY, _STREAM_POSE, _STREAM_SHAPE = 1, 2, 3
#: The contact margin is at least this many target edge lengths of the remeshed shape: closer surfaces
#: could be merged by the remesher's projection step.
CONTACT_MARGIN_EDGES = 0.5
#: Contacts between adjacent body parts (the inside of a bent knee or elbow) count only between
#: vertices that were at least this far apart in the rest pose (fraction of sqrt(area)).
ADJACENT_CONTACT_REACH = 0.15
#: A remeshed edge whose endpoints trace back to template points farther apart (in the rest pose) than
#: BRIDGE_EDGE_FACTOR target edge lengths and BRIDGE_MIN_LENGTH x sqrt(area) bridges two body parts: the
#: pose is backed off and remeshed again. Bridges between neighbouring parts shorter than BRIDGE_FOLD_LENGTH
#: x sqrt(area) are accepted: they close the crease of a bent knee, elbow or hip, where linear blend
#: skinning folds the surface into itself, like skin folds touching in a scan.
BRIDGE_EDGE_FACTOR = 4.0
BRIDGE_MIN_LENGTH = 0.1
BRIDGE_FOLD_LENGTH = 0.3
#: Remeshing attempts per shape before giving up with an error.
MAX_REMESH_ATTEMPTS = 6
#: The remesher stops when the count is within this fraction of the drawn target (one run is usually
#: enough: the target is itself random).
REMESH_COUNT_RTOL = 0.08
#: Remesher runs per attempt (each corrects the edge length towards the target count).
REMESH_ROUNDS = 2
#: The fused surface (self-contact corruption) is sampled with this many grid cells per remeshed edge
#: length (but never finer than ``grid_step``).
FUSION_STEPS_PER_EDGE = 3.0
#: Name of the parameter/fingerprint file of a generated folder.
PARAMS_FILE = "params.json"
#: Identifies folders written by this generator (only those are ever replaced).
GENERATOR_NAME = "shapecorr.data.synthetic"
#: Line width of the generated README.txt.
_README_WIDTH = 100


@dataclass(frozen=True)
class ShapeSpec:
    """Identity of one shape of the dataset."""

    cls: str
    subject: int
    pose: int

    @property
    def name(self) -> str:
        """Shape name ``<class>_s<subject>_p<pose>`` (two-digit subject and pose)."""
        return f"{self.cls}_s{self.subject:02d}_p{self.pose:02d}"


@dataclass(frozen=True, eq=False)
class SyntheticShape:
    """One generated shape with its ground truth.

    Attributes
    ----------
    spec : ShapeSpec
    pose_name : str
        Key pose (or ``random_<p>`` / contact pose) it started from.
    verts : (m, 3) float64
        Vertex positions as written (metres, rounded; FAUST axes, see :data:`OUTPUT_ROTATION`).
    faces : (g, 3) int64
    template_face : (m,) int64
    template_bary : (m, 3) float64
        Dense ground truth: the point of the class template each vertex corresponds to.
    vts, vts_sym : (R,) int64
        Zero-based vertex of each reference point, and of its mirror image.
    posed_template : (n, 3) float64
        The class template in this subject and pose (the surface the shape was remeshed from), output axes.
    rest_template : (n, 3) float64
        The class template in this subject's rest pose, output axes.
    backoffs : int
        How many times the pose was scaled back towards the rest pose.
    fused : bool
        Whether touching body parts were fused (self-contact corruption).
    """

    spec: ShapeSpec
    pose_name: str
    verts: np.ndarray
    faces: np.ndarray
    template_face: np.ndarray
    template_bary: np.ndarray
    vts: np.ndarray
    vts_sym: np.ndarray
    posed_template: np.ndarray
    rest_template: np.ndarray
    backoffs: int
    fused: bool


def shape_specs(cfg: SyntheticConfig) -> list[ShapeSpec]:
    """All shapes of a configuration, in name order."""
    counts = {"human": (cfg.n_human_subjects, cfg.n_human_poses), "quad": (cfg.n_quad_subjects, cfg.n_quad_poses)}
    return [ShapeSpec(c, s, p) for c in CLASS_IDS for s in range(counts[c][0]) for p in range(counts[c][1])]


def split_names(cfg: SyntheticConfig, specs: list[ShapeSpec]) -> dict[str, list[str]]:
    """Train/test names by class and split.

    Per class, the last ``round(test_fraction * count)`` subjects (``split="subject"``) or poses
    (``split="pose"``) are test; at least one when ``test_fraction > 0`` and at least one is left for training
    (a class with a single subject/pose is train only).
    """
    out = {"train": [], "test": []}
    for c in CLASS_IDS:
        members = [s for s in specs if s.cls == c]
        if not members:
            continue
        key = (lambda s: s.subject) if cfg.split == "subject" else (lambda s: s.pose)
        count = max(key(s) for s in members) + 1
        n_test = int(round(cfg.test_fraction * count))
        if cfg.test_fraction > 0 and count >= 2:
            n_test = min(max(n_test, 1), count - 1)
        else:
            n_test = 0
        for s in members:
            out["test" if key(s) >= count - n_test else "train"].append(s.name)
    return out


def _rng(cfg: SyntheticConfig, *entropy: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(cfg.seed), *map(int, entropy)]))


@lru_cache(maxsize=8)
def _cached_template(cls: str, n_verts: int, grid_step: float, iterations: int) -> Template:
    return build_template(BODY_PLANS[cls], n_verts, grid_step=grid_step, remesh_iterations=iterations)


def class_templates(cfg: SyntheticConfig) -> dict[str, Template]:
    """Canonical templates of the classes present in the configuration (cached per process)."""
    specs = shape_specs(cfg)
    present = [c for c in CLASS_IDS if any(s.cls == c for s in specs)]
    return {c: _cached_template(c, cfg.template_verts, cfg.grid_step, cfg.remesh_iterations) for c in present}


def reference_points(cfg: SyntheticConfig, templates: dict[str, Template]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Reference template vertices ``(ref, ref_sym)`` of every class.

    The references are the first ``n_ref_points`` farthest-point samples of the first class present
    (human, else quadruped), starting at its vertex 0; other classes get them through the semantic chart
    map. ``ref_sym`` are the template vertices at the mirror images.
    """
    classes = list(templates)
    first = templates[classes[0]]
    ref = farthest_point_sampling(first.verts, cfg.n_ref_points, start=0)
    out = {}
    for c in classes:
        t = templates[c]
        r = ref if c == classes[0] else chart_map(first, t, ref)
        out[c] = (r.astype(np.int64), t.mirror[r].astype(np.int64))
    return out


def generate_shape(
    spec: ShapeSpec, cfg: SyntheticConfig, template: Template, ref: np.ndarray, ref_sym: np.ndarray
) -> SyntheticShape:
    """Generate one shape with its ground truth (see the module docstring for the steps).

    Parameters
    ----------
    spec : ShapeSpec
    cfg : SyntheticConfig
    template : Template
        The class template.
    ref, ref_sym : (R,) int
        Reference template vertices and their mirror images.

    Returns
    -------
    SyntheticShape

    Raises
    ------
    InvalidMeshError
        The remeshed surface is not a single closed manifold surface (genus 0 unless fused), or bridges body
        parts even after backing the pose off :data:`MAX_REMESH_ATTEMPTS` times.
    """
    plan = template.plan
    cid = CLASS_IDS[spec.cls]
    identity = sample_identity(plan, _rng(cfg, cid, spec.subject, _STREAM_IDENTITY), cfg.length_std,
                               cfg.thickness_std, cfg.build_std)
    id_transforms, heads = identity_transforms(plan, identity)
    rest = blend_skin(template.verts, template.weights, id_transforms)
    sqrt_area = float(np.sqrt(triangle_areas(rest, template.faces).sum()))

    rng = _rng(cfg, cid, spec.subject, spec.pose, _STREAM_SHAPE)
    n_target = int(rng.integers(cfg.n_verts_min, cfg.n_verts_max + 1))
    yaw = np.radians(rng.uniform(-cfg.max_yaw_deg, cfg.max_yaw_deg))
    root_rotation = rotation_about(np.array([0.0, 0.0, 1.0]), yaw)
    fused = bool(rng.random() < cfg.self_contact_fraction)
    if fused:
        pose_name, angles = poses.key_pose(plan, int(rng.integers(1 << 30)), poses.CONTACT_POSES)
    else:
        shared = _rng(cfg, cid, spec.pose, _STREAM_POSE)
        pose_name, angles = poses.pose_base(plan, spec.pose, shared, cfg.random_pose_range)
        angles = poses.jitter(plan, angles, shared, cfg.pose_jitter_deg)
    angles = poses.jitter(plan, angles, rng, cfg.subject_pose_jitter_deg)

    edge = edge_length_for_count(sqrt_area**2, n_target)
    margin = max(cfg.contact_margin * sqrt_area, CONTACT_MARGIN_EDGES * edge)

    def pose_fn(a: np.ndarray) -> np.ndarray:
        return blend_skin(rest, template.weights, pose_transforms(plan, heads, a, root_rotation))

    def contact_fn(posed: np.ndarray) -> np.ndarray:
        return poses.find_contacts(posed, rest, template.dominant, template.part_adjacency, margin,
                                   ADJACENT_CONTACT_REACH * sqrt_area)

    backoffs = 0
    for _ in range(MAX_REMESH_ATTEMPTS):
        if not fused:
            angles, steps = poses.back_off_contacts(angles, pose_fn, contact_fn)
            backoffs += steps
        posed = pose_fn(angles)
        surface = (posed, template.faces)
        if fused:
            pairs = contact_fn(posed)
            contacts = 0.5 * (posed[pairs[:, 0]] + posed[pairs[:, 1]])
            step = max(cfg.grid_step, edge / FUSION_STEPS_PER_EDGE)
            surface = corruptions.fuse_contacts(posed, template.faces, contacts, cfg.contact_merge_radius * sqrt_area,
                                                step)
        verts, faces = remesh(surface[0], surface[1], n_target, iterations=cfg.remesh_iterations,
                              rtol=REMESH_COUNT_RTOL, max_rounds=REMESH_ROUNDS)
        face, bary, _ = trace_to_surface(verts, posed, template.faces)
        rest_pos = interpolate(rest, template.faces, face, bary)
        part = template.dominant[template.faces[face, np.argmax(bary, axis=1)]]
        bridge = max(BRIDGE_EDGE_FACTOR * edge, BRIDGE_MIN_LENGTH * sqrt_area)
        if fused or _bridging_edges(faces, rest_pos, part, template.part_adjacency, bridge,
                                    BRIDGE_FOLD_LENGTH * sqrt_area) == 0:
            break
        angles = angles * poses.CONTACT_BACKOFF
        backoffs += 1
    else:
        raise InvalidMeshError(f"{spec.name}: the remeshed surface keeps bridging body parts after "
                               f"{MAX_REMESH_ATTEMPTS} attempts")
    _check_surface(spec.name, verts, faces, fused)

    perm, faces = _shuffle(rng, len(verts), faces)
    verts, face, bary, rest_pos = verts[perm], face[perm], bary[perm], rest_pos[perm]
    vts = nearest_vertices(rest[ref], rest_pos)
    vts_sym = nearest_vertices(rest[ref_sym], rest_pos)

    if cfg.n_holes > 0 and cfg.hole_radius > 0:
        keep, faces = corruptions.cut_holes(verts, faces, rest_pos, rng, cfg.n_holes, cfg.hole_radius * sqrt_area)
        vts = corruptions.reassign_lost(vts, keep, rest_pos)
        vts_sym = corruptions.reassign_lost(vts_sym, keep, rest_pos)
        verts, face, bary = verts[keep], face[keep], bary[keep]
    if cfg.noise_std > 0:
        verts = corruptions.add_noise(verts, rng, cfg.noise_std * sqrt_area)
    verts, posed, rest = (x @ OUTPUT_ROTATION.T for x in (verts, posed, rest))
    verts = np.round(verts, cfg.output_decimals)
    return SyntheticShape(spec, pose_name, verts, faces, face, bary, vts, vts_sym, posed, rest, backoffs, fused)


def _check_surface(name: str, verts: np.ndarray, faces: np.ndarray, fused: bool) -> None:
    """Every shape is one closed manifold surface; genus 0 unless fused (fusion may add handles)."""
    report = topology_report(verts, faces)
    closed = report["watertight"] and report["vertex_manifold"] and report["components"] == 1
    if not (closed and (fused or report["genus"] == 0)):
        kind = "" if fused else "genus-0 "
        raise InvalidMeshError(f"{name}: remeshed surface is not a single closed manifold {kind}surface: {report}")


def _shuffle(rng: np.random.Generator, n_verts: int, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Random vertex order, face order and first corner of every face (orientation kept).

    Returns
    -------
    perm : (n,) int64
        New vertex i is old vertex ``perm[i]``.
    faces : (f, 3) int64
        The faces in the new vertex indices.
    """
    perm = rng.permutation(n_verts)
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(n_verts)
    f = inverse[np.asarray(faces, np.int64)]
    shift = rng.integers(0, 3, size=len(f))
    f = np.take_along_axis(f, (np.arange(3)[None, :] + shift[:, None]) % 3, axis=1)
    return perm.astype(np.int64), f[rng.permutation(len(f))].astype(np.int64)


def _bridging_edges(
    faces: np.ndarray, rest_pos: np.ndarray, part: np.ndarray, adjacency: np.ndarray, max_length: float,
    max_fold: float,
) -> int:
    """Number of mesh edges that bridge body parts.

    An edge bridges when its endpoints are farther apart than ``max_length`` in the rest pose, unless they
    belong to neighbouring parts (``adjacency``) and are less than ``max_fold`` apart (a closed crease).
    """
    f = np.asarray(faces)
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    length = np.linalg.norm(rest_pos[a] - rest_pos[b], axis=1)
    fold = adjacency[part[a], part[b]] & (length <= max_fold)
    return int(np.count_nonzero((length > max_length) & ~fold))


# ----------------------------------------------------------------------------------------- writing


def _write_shape(root: Path, shape: SyntheticShape, write_dense: bool) -> None:
    name = shape.spec.name
    write_mesh(root / "off" / f"{name}.off", shape.verts, shape.faces)
    write_vts(root / "corres" / f"{name}.vts", shape.vts)
    write_vts(root / "corres" / f"{name}.sym.vts", shape.vts_sym)
    if write_dense:
        with open(root / "dense" / f"{name}.npz", "wb") as handle:
            np.savez(handle, template_face=shape.template_face.astype(np.int64),
                     template_bary=shape.template_bary.astype(np.float64))


def _write_templates(root: Path, templates: dict[str, Template], refs: dict, decimals: int) -> None:
    for c, t in templates.items():
        write_mesh(root / "templates" / f"{c}.off", np.round(t.verts @ OUTPUT_ROTATION.T, decimals), t.faces)
        write_vts(root / "templates" / f"{c}.vts", refs[c][0])
        write_vts(root / "templates" / f"{c}.sym.vts", refs[c][1])


_WORKER: dict = {}


def _init_worker(cfg: SyntheticConfig, templates: dict, refs: dict) -> None:
    _WORKER.update(cfg=cfg, templates=templates, refs=refs)


def _work(spec: ShapeSpec) -> SyntheticShape:
    cfg, templates, refs = _WORKER["cfg"], _WORKER["templates"], _WORKER["refs"]
    return generate_shape(spec, cfg, templates[spec.cls], *refs[spec.cls])


def default_workers() -> int:
    """Worker processes used by default: the available CPU cores, at most :data:`MAX_DEFAULT_WORKERS`."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not available on macOS / Windows
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_DEFAULT_WORKERS))


#: Upper bound of the default number of worker processes.
MAX_DEFAULT_WORKERS = 8


def generate_dataset(out: str | os.PathLike, cfg: SyntheticConfig, workers: int | None = None,
                     progress: bool = True) -> Path:
    """Generate the dataset into ``out`` (which must not exist or be empty).

    Writes ``off/<name>.off``, ``corres/<name>.vts`` and ``corres/<name>.sym.vts`` (one-based),
    ``splits/train.txt``, ``splits/test.txt``, ``README.txt``, ``params.json`` (options, fingerprint, per-shape
    metadata) and, with ``cfg.write_dense``, ``dense/<name>.npz`` and ``templates/``.

    Parameters
    ----------
    out : path
    cfg : SyntheticConfig
    workers : int, optional
        Worker processes (default :func:`default_workers`; 0 or 1 generates in this process). The files do
        not depend on it.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    Path of the folder.
    """
    root = Path(out)
    if root.exists() and any(root.iterdir()):
        raise DatasetError("output folder exists and is not empty", root)
    for sub in ("off", "corres", "splits") + (("dense", "templates") if cfg.write_dense else ()):
        (root / sub).mkdir(parents=True, exist_ok=True)
    specs = shape_specs(cfg)
    workers = default_workers() if workers is None else int(workers)
    bar = tqdm(total=len(specs), desc="synthetic dataset", unit="shape", disable=not progress)
    try:
        bar.set_postfix_str("building templates")
        templates = class_templates(cfg)
        refs = reference_points(cfg, templates)
        bar.set_postfix_str("")
        meta = {}
        if workers <= 1:
            _init_worker(cfg, templates, refs)
            results = map(_work, specs)
            executor = contextlib.nullcontext()
        else:
            executor = ProcessPoolExecutor(max_workers=min(workers, len(specs)), initializer=_init_worker,
                                           initargs=(cfg, templates, refs))
            results = executor.map(_work, specs)
        with executor:
            for shape in results:
                _write_shape(root, shape, cfg.write_dense)
                meta[shape.spec.name] = {
                    "class": shape.spec.cls, "subject": shape.spec.subject, "pose": shape.spec.pose,
                    "pose_name": shape.pose_name, "n_verts": int(len(shape.verts)), "n_faces": int(len(shape.faces)),
                    "backoffs": int(shape.backoffs), "fused": shape.fused,
                }
                bar.update(1)
    finally:
        bar.close()
    if cfg.write_dense:
        _write_templates(root, templates, refs, cfg.output_decimals)
    splits = split_names(cfg, specs)
    for split, names in splits.items():
        (root / "splits" / f"{split}.txt").write_text("".join(f"{n}\n" for n in names))
    for name in meta:
        meta[name]["split"] = "test" if name in set(splits["test"]) else "train"
    params = {
        "generator": GENERATOR_NAME,
        "generator_version": GENERATOR_VERSION,
        "fingerprint": cfg.fingerprint(),
        "config": cfg.to_dict(),
        "n_shapes": len(specs),
        "n_ref_points": cfg.n_ref_points,
        "template_verts": {c: t.n_verts for c, t in templates.items()},
        "shapes": meta,
    }
    (root / PARAMS_FILE).write_text(json.dumps(params, indent=1, sort_keys=True) + "\n")
    (root / "README.txt").write_text(readme_text(cfg, splits, templates))
    return root


def readme_text(cfg: SyntheticConfig, splits: dict[str, list[str]], templates: dict[str, Template]) -> str:
    """The README.txt of a generated folder: how it was made and how to read it."""
    counts = ", ".join(f"{c}: {t.n_verts} vertices" for c, t in templates.items())
    unit = "subjects" if cfg.split == "subject" else "poses"

    def para(text: str, indent: str = "  ") -> str:
        return textwrap.fill(" ".join(text.split()), width=_README_WIDTH, initial_indent=indent,
                             subsequent_indent=indent)

    sections = [
        "Synthetic deformable creatures with dense ground truth",
        "======================================================",
        "",
        para(f"Generator {GENERATOR_NAME} version {GENERATOR_VERSION}, fingerprint {cfg.fingerprint()}. Made by "
             f"`python data_prep/make_synthetic.py out=DIR seed={cfg.seed} ...` or "
             "shapecorr.data.synthetic.ensure_synthetic_dataset; the same options and seed give byte-identical "
             "files.", indent=""),
        "",
        "Content",
        para(f"{cfg.n_human_subjects} humanoid subjects x {cfg.n_human_poses} poses and {cfg.n_quad_subjects} "
             f"quadruped subjects x {cfg.n_quad_poses} poses. Each class has one canonical template ({counts}): "
             "the smooth union of capsules and ellipsoids, meshed by marching cubes and remeshed. A subject scales "
             "the template's bones (lengths, thickness, build); a pose rotates its joints within joint limits by "
             "linear blend skinning (key poses such as arms raised or crossed, squats, torso twists, kicks and "
             "other left/right asymmetric poses; pose p starts from the same joint angles for every subject, like "
             "FAUST). Every shape is remeshed on its own to "
             f"{cfg.n_verts_min}-{cfg.n_verts_max} vertices and its vertex and face order is shuffled: no two "
             "shapes share a triangulation. Corruptions: "
             f"noise_std={cfg.noise_std}, n_holes={cfg.n_holes} (radius {cfg.hole_radius}), "
             f"self_contact_fraction={cfg.self_contact_fraction}."),
        "",
        "Layout (FAUST_r / SCAPE_r style)",
        "  off/<name>.off         meshes in metres, y up, z forward; <name> = <class>_s<subject>_p<pose>",
        f"  corres/<name>.vts      {cfg.n_ref_points} one-based vertex indices; line r is the same body point",
        "                         on every shape (template vertex ref[r], nearest vertex in the rest pose)",
        "  corres/<name>.sym.vts  the same for the mirrored body point (left/right symmetric ground truth)",
        f"  splits/<split>.txt     rule '{cfg.split}': per class the last round({cfg.test_fraction} x count) {unit}",
        f"                         are test ({len(splits['train'])} train / {len(splits['test'])} test shapes)",
        "  dense/<name>.npz       template_face (n,), template_bary (n, 3): the template point of every",
        "                         vertex (dense ground truth; written when write_dense is true)",
        "  templates/<class>.off  the canonical templates, with <class>.vts / <class>.sym.vts",
        "  params.json            every option, the fingerprint, per shape: class, subject, pose, pose name,",
        "                         vertex count, split, pose back-offs",
        "",
        "Ground truth",
        para("Every vertex is traced back to the posed template surface (closest point), so the dense ground "
             "truth is exact. A .vts entry is a vertex, hence composing two .vts files is accurate up to the "
             "vertex spacing, about 0.4 mean edge lengths on average: ~1.1% of sqrt(area) at 2k vertices, ~0.75% "
             "at 3k, ~0.6% at 5k. Across classes the correspondence is semantic (homologous bones: "
             "forelimbs = arms, hind limbs = legs; same position along the bone and angle around it), not "
             "isometric; the quadruped tail is never a reference point. A reference point whose vertex was "
             "removed by a hole maps to the nearest surviving vertex; fused zones trace to the closest body part."),
        "",
        "Options",
        *[f"  {k} = {v!r}" for k, v in cfg.to_dict().items()],
    ]
    return "\n".join(sections) + "\n"


# ----------------------------------------------------------------------------------------- cache entry


def _is_current(root: Path, cfg: SyntheticConfig) -> bool:
    """Whether ``root`` holds a complete dataset generated with exactly this configuration."""
    try:
        params = json.loads((root / PARAMS_FILE).read_text())
    except (OSError, ValueError):
        return False
    if params.get("fingerprint") != cfg.fingerprint() or not (root / "README.txt").is_file():
        return False
    names = [s.name for s in shape_specs(cfg)]
    return all((root / "off" / f"{n}.off").is_file() and (root / "corres" / f"{n}.vts").is_file() for n in names)


def _is_generated(root: Path) -> bool:
    try:
        return json.loads((root / PARAMS_FILE).read_text()).get("generator") == GENERATOR_NAME
    except (OSError, ValueError, AttributeError):
        return False


@contextlib.contextmanager
def _folder_lock(root: Path):
    """Exclusive inter-process lock next to ``root`` (POSIX flock; no-op where unavailable)."""
    try:
        import fcntl
    except ImportError:  # Windows: no locking, the atomic rename still prevents partial folders
        yield
        return
    lock_path = root.parent / f".{root.name}.lock"
    with open(lock_path, "a+b") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def ensure_synthetic_dataset(root: str | os.PathLike, cfg: SyntheticConfig, workers: int | None = None,
                             progress: bool = True) -> Path:
    """Return the dataset folder ``root``, generating it first if it is missing or was made with other options.

    Generation happens in a temporary folder next to ``root`` that is renamed into place, so ``root`` is
    never seen half-written; concurrent callers (e.g. DDP ranks) serialize on a lock file and only the first
    one generates. A stale folder (different fingerprint in ``params.json``) is replaced, but only if it was
    written by this generator.

    Parameters
    ----------
    root : path
        The dataset folder.
    cfg : SyntheticConfig
    workers : int, optional
        Worker processes (see :func:`generate_dataset`).
    progress : bool
        Show a progress bar while generating.

    Returns
    -------
    Path
        ``root`` (absolute), holding a complete dataset for ``cfg``.

    Raises
    ------
    DatasetError
        ``root`` exists, is not empty and was not written by this generator.
    """
    root = Path(root).expanduser().absolute()
    if _is_current(root, cfg):
        return root
    root.parent.mkdir(parents=True, exist_ok=True)
    with _folder_lock(root):
        if _is_current(root, cfg):
            return root
        if root.exists() and (not root.is_dir() or (any(root.iterdir()) and not _is_generated(root))):
            raise DatasetError("exists and is not a synthetic dataset written by shapecorr; refusing to replace it "
                               "(choose another folder or delete it)", root)
        tmp = Path(tempfile.mkdtemp(prefix=f".{root.name}.tmp-", dir=root.parent))
        try:
            generate_dataset(tmp, cfg, workers=workers, progress=progress)
            if root.exists():
                old = root.parent / f".{root.name}.old-{uuid.uuid4().hex}"
                os.replace(root, old)
                os.replace(tmp, root)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, root)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    return root
