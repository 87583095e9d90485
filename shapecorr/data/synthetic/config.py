"""Options of the synthetic dataset generator (:class:`SyntheticConfig`) and named presets.

Lengths given as a *fraction of sqrt(area)* are relative to the square root of the surface area of the
shape they apply to, the unit in which correspondence errors are reported (Princeton protocol).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields, replace

from shapecorr.errors import ConfigError

#: Bumped whenever the generator's output for a given configuration changes; part of the fingerprint,
#: so cached datasets made by an older generator are regenerated.
GENERATOR_VERSION = 2

#: Split rules (see :class:`SyntheticConfig`).
SPLIT_RULES = ("subject", "pose")


@dataclass(frozen=True)
class SyntheticConfig:
    """Every option of the procedural creature dataset. Defaults = the ``default`` preset.

    Attributes
    ----------
    seed
        Master seed; every random choice derives from it (same seed -> byte-identical files).
    n_human_subjects, n_human_poses
        Humanoid subjects (identities) and poses per subject (like FAUST's 10 x 10).
    n_quad_subjects, n_quad_poses
        Quadruped subjects and poses per subject (inter-class pairs); 0 subjects disables the class.
    n_verts_min, n_verts_max
        Every shape is remeshed independently to a vertex count drawn uniformly from this range (the
        remesher reaches the drawn count within ~8%).
    n_ref_points
        R, the number of reference points in every ``corres/<name>.vts`` (FAUST_r has 5000).
    template_verts
        Vertex count of the canonical template meshes (all shapes of a class are remeshings of deformed
        copies of it).
    grid_step
        Marching-cubes grid spacing (metres; creatures are ~1.8 m tall / long) used to mesh the templates.
    remesh_iterations
        Iterations of the isotropic remesher (Botsch & Kobbelt) per shape.
    length_std, thickness_std, build_std
        Identity variation: log-normal spread of bone lengths, of bone cross sections, and of a
        whole-body build factor (0, 0, 0 makes all subjects identical).
    pose_jitter_deg
        Random change (degrees, std) of every joint angle of pose p, shared by all subjects.
    subject_pose_jitter_deg
        Additional per-subject change of every joint angle (degrees, std).
    random_pose_range
        Poses beyond the key-pose library are drawn uniformly within this fraction of the joint limits.
    max_yaw_deg
        Every shape is rotated about the vertical axis by a uniform angle in [-max_yaw_deg, max_yaw_deg].
    contact_margin
        Poses are backed off towards the rest pose until distinct body parts stay this far apart
        (fraction of sqrt(area); at least half a remeshed edge length).
    test_fraction
        Fraction of subjects (``split="subject"``) or poses (``split="pose"``) per class held out for test.
    split
        ``"subject"``: the last subjects of each class are the test set (FAUST: people 9-10 are
        ``tr_reg_080..099``); ``"pose"``: the last poses of every subject are.
    noise_std
        Corruption: Gaussian noise added to every vertex (std, fraction of sqrt(area)); 0 = off.
    n_holes, hole_radius
        Corruption: holes cut into every shape (count, and radius as a fraction of sqrt(area)).
    self_contact_fraction
        Corruption: fraction of shapes posed so that body parts touch and fused where they do
        (topological noise as in SHREC'16 TOPKIDS); 0 = off.
    contact_merge_radius
        Width of the fused zone around each contact (fraction of sqrt(area)).
    output_decimals
        Vertex coordinates are rounded to this many decimals (metres) before writing.
    write_dense
        Also write the dense ground truth ``dense/<name>.npz`` (``template_face`` (n,) int64 and
        ``template_bary`` (n, 3) float64: the point of the class template every vertex corresponds to) and
        the templates themselves (``templates/<class>.off`` with their ``.vts`` / ``.sym.vts``).
    """

    seed: int = 0
    n_human_subjects: int = 8
    n_human_poses: int = 10
    n_quad_subjects: int = 4
    n_quad_poses: int = 5
    n_verts_min: int = 1500
    n_verts_max: int = 2500
    n_ref_points: int = 1000
    template_verts: int = 4000
    grid_step: float = 0.01
    remesh_iterations: int = 6
    length_std: float = 0.10
    thickness_std: float = 0.10
    build_std: float = 0.12
    pose_jitter_deg: float = 8.0
    subject_pose_jitter_deg: float = 4.0
    random_pose_range: float = 0.6
    max_yaw_deg: float = 20.0
    contact_margin: float = 0.03
    test_fraction: float = 0.2
    split: str = "subject"
    noise_std: float = 0.0
    n_holes: int = 0
    hole_radius: float = 0.05
    self_contact_fraction: float = 0.0
    contact_merge_radius: float = 0.03
    output_decimals: int = 6
    write_dense: bool = True

    def __post_init__(self):
        ints_nonneg = ("n_human_subjects", "n_human_poses", "n_quad_subjects", "n_quad_poses", "n_holes")
        for name in ints_nonneg:
            if int(getattr(self, name)) < 0:
                raise ConfigError(f"synthetic.{name} must be >= 0, got {getattr(self, name)}")
        if self.n_human_subjects * self.n_human_poses + self.n_quad_subjects * self.n_quad_poses == 0:
            raise ConfigError("synthetic dataset would be empty: set n_human_subjects/poses or n_quad_subjects/poses")
        if not 4 <= self.n_verts_min <= self.n_verts_max:
            raise ConfigError(f"need 4 <= n_verts_min <= n_verts_max, got {self.n_verts_min}, {self.n_verts_max}")
        if self.n_ref_points < 1:
            raise ConfigError(f"synthetic.n_ref_points must be >= 1, got {self.n_ref_points}")
        if self.n_ref_points > self.template_verts // 2:
            raise ConfigError(f"synthetic.n_ref_points ({self.n_ref_points}) must be at most template_verts / 2 "
                              f"({self.template_verts // 2})")
        for name in ("grid_step",):
            if not getattr(self, name) > 0:
                raise ConfigError(f"synthetic.{name} must be positive, got {getattr(self, name)}")
        for name in ("length_std", "thickness_std", "build_std", "pose_jitter_deg", "subject_pose_jitter_deg",
                     "max_yaw_deg", "contact_margin", "noise_std", "hole_radius", "contact_merge_radius"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"synthetic.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("random_pose_range", "test_fraction", "self_contact_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"synthetic.{name} must be in [0, 1], got {getattr(self, name)}")
        if self.split not in SPLIT_RULES:
            raise ConfigError(f"synthetic.split must be one of {SPLIT_RULES}, got {self.split!r}")
        if self.remesh_iterations < 1:
            raise ConfigError(f"synthetic.remesh_iterations must be >= 1, got {self.remesh_iterations}")
        if not 0 <= self.output_decimals <= 12:
            raise ConfigError(f"synthetic.output_decimals must be in [0, 12], got {self.output_decimals}")

    def to_dict(self) -> dict:
        """Plain dict of every option (JSON-serializable)."""
        return asdict(self)

    def fingerprint(self) -> str:
        """SHA-256 of the options and :data:`GENERATOR_VERSION`; identifies the generated files."""
        payload = json.dumps({"generator_version": GENERATOR_VERSION, "config": self.to_dict()}, sort_keys=True)
        return hashlib.sha256(payload.encode("utf-8")).hexdigest()

    @classmethod
    def from_dict(cls, values: dict) -> "SyntheticConfig":
        """Build from a mapping (e.g. a Hydra node), rejecting unknown keys with a ConfigError."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown synthetic dataset option(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(values))


#: Named presets: overrides of the defaults.
PRESETS: dict[str, dict] = {
    # 8 x 10 humans + 4 x 5 quadrupeds, 1.5k-2.5k vertices: the default dataset (data=synthetic).
    "default": {},
    # A few ~300-vertex shapes for unit and integration tests (seconds to generate).
    "tiny": dict(n_human_subjects=2, n_human_poses=3, n_quad_subjects=2, n_quad_poses=2, n_verts_min=250,
                 n_verts_max=350, n_ref_points=100, template_verts=1200),
    # FAUST_r-like resolution (~5k vertices per shape, 10 x 10 humans).
    "large": dict(n_human_subjects=10, n_human_poses=10, n_verts_min=4500, n_verts_max=5500, n_ref_points=3000,
                  template_verts=8000),
}


def preset(name: str = "default", **overrides) -> SyntheticConfig:
    """A preset configuration with optional overrides, e.g. ``preset("tiny", seed=3)``.

    Raises
    ------
    ConfigError
        Unknown preset, unknown option name (the message lists the valid ones), or an invalid value.
    """
    if name not in PRESETS:
        raise ConfigError(f"unknown synthetic preset {name!r}; choose one of {sorted(PRESETS)}")
    known = {f.name for f in fields(SyntheticConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ConfigError(f"unknown synthetic dataset option(s) {unknown}; known: {sorted(known)}")
    return replace(SyntheticConfig(), **{**PRESETS[name], **overrides})
