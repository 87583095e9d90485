"""Body plans of the synthetic creatures: bones and implicit primitives.

Bones form a kinematic tree with joint limits; the implicit primitives (round cones, ellipsoids) have the
creature's surface as their smooth union.

Coordinates are in metres of the rest pose. Axes: ``+z`` up, ``+y`` forward (the way the creature looks),
``+x`` the creature's right (right-handed); every body plan is mirror-symmetric about the plane ``x = 0``.
The tables below describe the right-side bones (``_r``, at ``x > 0``); their left mirror images (``_l``) are
generated. (Files are written in the FAUST convention instead: ``y`` up, ``z`` forward, see ``generator.py``.)

Each bone carries a right-handed *bone frame* ``F = [lat, ref, axis]`` (columns): ``axis`` runs from the
bone's head (its joint) to its tail, ``ref`` is a semantic reference direction orthogonal to it (anterior for
a human, cranial for a quadruped's legs, ventral for a quadruped's trunk, dorsal for feet) and
``lat = ref x axis``. The reference directions are chosen so that a human bone and the quadruped bone of the
same name have the same meaning (a quadruped's forelimb is an arm: humerus, radius/ulna, paw), which gives a
semantic cross-class correspondence through bone-local coordinates (see ``groundtruth.py``).

Joint rotations are three angles in degrees, applied in the bone frame as
``R_local = R_lat(-flex) @ R_ref(side * abd) @ R_axis(side * twist)``: ``flex`` turns the bone towards ``ref``,
``abd`` towards ``lat``, ``twist`` about its own axis, and ``side`` (+1 right, -1 left, +1 centre) makes
equal angles on the left and right bones produce mirror-image poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shapecorr.errors import ConfigError

@dataclass(frozen=True)
class Bone:
    """One bone of a kinematic tree.

    Attributes
    ----------
    name
        Unique name; bones of the same name in two body plans correspond semantically.
    parent
        Name of the parent bone, ``None`` for the root.
    head, tail
        ``(3,)`` rest positions of the joint (rotation centre) and of the bone's end.
    ref
        ``(3,)`` semantic reference direction (made orthogonal to the bone axis).
    limits
        ``((flex_lo, flex_hi), (abd_lo, abd_hi), (twist_lo, twist_hi))`` joint limits in degrees.
    side
        +1 right (as described in the tables), -1 left (mirror image), 0 on the symmetry plane.
    """

    name: str
    parent: str | None
    head: tuple[float, float, float]
    tail: tuple[float, float, float]
    ref: tuple[float, float, float]
    limits: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]
    side: int = 0


@dataclass(frozen=True)
class Primitive:
    """An implicit solid attached to a bone (it moves with that bone).

    ``kind == "cone"``: a round cone from ``a`` (radius ``ra``) to ``b`` (radius ``rb``), the radius varying
    linearly along the segment. ``kind == "ellipsoid"``: centre ``a`` with semi-axes ``radii`` along the bone
    frame ``(lat, ref, axis)``.
    """

    bone: str
    kind: str
    a: tuple[float, float, float]
    b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ra: float = 0.0
    rb: float = 0.0
    radii: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class BodyPlan:
    """A creature class: its bones (parents before children) and primitives.

    Attributes
    ----------
    name
        Class name used in shape names (``human``, ``quad``).
    bones, primitives
        See :class:`Bone`, :class:`Primitive`.
    blend
        Radius (m) of the smooth union of the primitives (the fillets between body parts).
    """

    name: str
    bones: tuple[Bone, ...]
    primitives: tuple[Primitive, ...]
    blend: float

    def __post_init__(self):
        seen: set[str] = set()
        for bone in self.bones:
            if bone.parent is not None and bone.parent not in seen:
                raise ConfigError(
                    f"body plan {self.name!r}: bone {bone.name!r} listed before its parent {bone.parent!r}"
                )
            seen.add(bone.name)
        for prim in self.primitives:
            if prim.bone not in seen:
                raise ConfigError(f"body plan {self.name!r}: primitive attached to unknown bone {prim.bone!r}")
            if prim.kind not in ("cone", "ellipsoid"):
                raise ConfigError(f"body plan {self.name!r}: unknown primitive kind {prim.kind!r}")

    @property
    def bone_names(self) -> tuple[str, ...]:
        """Names of the bones, in order."""
        return tuple(b.name for b in self.bones)

    def index(self, name: str) -> int:
        """Index of a bone by name."""
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise ConfigError(f"body plan {self.name!r} has no bone {name!r}") from None

    @property
    def parents(self) -> np.ndarray:
        """``(B,)`` int64 parent index of every bone, -1 for the root."""
        return np.array([-1 if b.parent is None else self.index(b.parent) for b in self.bones], dtype=np.int64)

    @property
    def heads(self) -> np.ndarray:
        """``(B, 3)`` float64 joint positions."""
        return np.array([b.head for b in self.bones], dtype=np.float64)

    @property
    def tails(self) -> np.ndarray:
        """``(B, 3)`` float64 bone end positions."""
        return np.array([b.tail for b in self.bones], dtype=np.float64)

    @property
    def sides(self) -> np.ndarray:
        """``(B,)`` float64: -1 for left bones, +1 otherwise (the sign applied to abd and twist)."""
        return np.array([-1.0 if b.side < 0 else 1.0 for b in self.bones])

    @property
    def limits(self) -> np.ndarray:
        """``(B, 3, 2)`` float64 joint limits in degrees."""
        return np.array([b.limits for b in self.bones], dtype=np.float64)


def bone_frames(heads: np.ndarray, tails: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """Right-handed orthonormal bone frames ``[lat, ref, axis]``.

    Parameters
    ----------
    heads, tails, refs : (B, 3) float

    Returns
    -------
    (B, 3, 3) float64, columns ``lat, ref, axis`` with ``lat = ref x axis``.
    """
    axis = np.asarray(tails, np.float64) - np.asarray(heads, np.float64)
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    if np.any(length <= 0):
        raise ConfigError("a bone has zero length")
    axis = axis / length
    ref = np.asarray(refs, np.float64)
    ref = ref - (ref * axis).sum(1, keepdims=True) * axis
    ref_norm = np.linalg.norm(ref, axis=1, keepdims=True)
    if np.any(ref_norm <= 1e-9 * np.maximum(1.0, length)):
        raise ConfigError("a bone's reference direction is parallel to its axis")
    ref = ref / ref_norm
    lat = np.cross(ref, axis)
    return np.stack([lat, ref, axis], axis=2)


def plan_frames(plan: BodyPlan) -> np.ndarray:
    """``(B, 3, 3)`` rest bone frames of a body plan (see :func:`bone_frames`)."""
    return bone_frames(plan.heads, plan.tails, np.array([b.ref for b in plan.bones], dtype=np.float64))


def _mirror(p: tuple[float, float, float]) -> tuple[float, float, float]:
    return (-p[0], p[1], p[2])


def _sided_bones(specs) -> list[Bone]:
    """Expand ``(name, parent, head, tail, ref, limits, sided)`` rows into bones, mirroring sided rows.

    A sided row describes the right bone (``x > 0``); its parent, if also sided, is the right parent. The
    left copy has mirrored positions and reference direction, and the same anatomical limits.
    """
    sided = {s[0] for s in specs if s[6]}
    right, left, centre = [], [], []
    for name, parent, head, tail, ref, limits, is_sided in specs:
        if not is_sided:
            centre.append(Bone(name, parent, head, tail, ref, limits, side=0))
            continue
        par_r = f"{parent}_r" if parent in sided else parent
        par_l = f"{parent}_l" if parent in sided else parent
        right.append(Bone(f"{name}_r", par_r, head, tail, ref, limits, side=1))
        left.append(Bone(f"{name}_l", par_l, _mirror(head), _mirror(tail), _mirror(ref), limits, side=-1))
    return centre + right + left


def _sided_primitives(specs, sided_bones: set[str]) -> list[Primitive]:
    """Expand primitives of right bones into right + mirrored left copies."""
    out = []
    for prim in specs:
        if prim.bone in sided_bones:
            out.append(Primitive(f"{prim.bone}_r", prim.kind, prim.a, prim.b, prim.ra, prim.rb, prim.radii))
            out.append(Primitive(f"{prim.bone}_l", prim.kind, _mirror(prim.a), _mirror(prim.b), prim.ra, prim.rb,
                                 prim.radii))
        else:
            out.append(prim)
    return out


def _point(a) -> tuple[float, float, float]:
    return tuple(float(x) for x in a)


def _along(head, tail, t):
    h, e = np.asarray(head, float), np.asarray(tail, float)
    return tuple(float(x) for x in h + t * (e - h))


def _human() -> BodyPlan:
    # Proportions of an adult of ~1.8 m in an A-pose (arms 40 degrees below horizontal), legs slightly apart.
    # Joint limits follow typical ranges of motion (degrees); see the module docstring for the angle signs.
    fwd, up = (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    arm_dir = np.array([np.cos(np.radians(40.0)), 0.0, -np.sin(np.radians(40.0))])
    shoulder = np.array([0.19, 0.0, 1.40])
    elbow = shoulder + 0.29 * arm_dir
    wrist = elbow + 0.26 * arm_dir
    hand_end = wrist + 0.17 * arm_dir
    hip, knee, ankle = (0.095, 0.0, 0.90), (0.14, 0.0, 0.49), (0.16, -0.01, 0.09)
    toe = (0.17, 0.17, 0.03)
    specs = [
        ("pelvis", None, (0.0, 0.0, 0.90), (0.0, 0.0, 1.05), fwd, ((-8, 8), (-8, 8), (-12, 12)), False),
        ("spine", "pelvis", (0.0, 0.0, 1.05), (0.0, 0.0, 1.25), fwd, ((-20, 40), (-25, 25), (-35, 35)), False),
        ("chest", "spine", (0.0, 0.0, 1.25), (0.0, 0.0, 1.46), fwd, ((-15, 25), (-20, 20), (-35, 35)), False),
        ("neck", "chest", (0.0, 0.0, 1.46), (0.0, 0.0, 1.57), fwd, ((-30, 40), (-25, 25), (-45, 45)), False),
        ("head", "neck", (0.0, 0.0, 1.57), (0.0, 0.0, 1.80), fwd, ((-20, 30), (-15, 15), (-30, 30)), False),
        ("upper_arm", "chest", _point(shoulder), _point(elbow), fwd, ((-50, 150), (-110, 40), (-60, 60)), True),
        ("forearm", "upper_arm", _point(elbow), _point(wrist), fwd, ((0, 135), (-5, 5), (-30, 30)), True),
        ("hand", "forearm", _point(wrist), _point(hand_end), fwd, ((-60, 60), (-25, 25), (-20, 20)), True),
        ("thigh", "pelvis", hip, knee, fwd, ((-30, 110), (-45, 10), (-30, 30)), True),
        ("shin", "thigh", knee, ankle, fwd, ((-135, 0), (-3, 3), (-10, 10)), True),
        ("foot", "shin", ankle, toe, up, ((-40, 25), (-15, 15), (-15, 15)), True),
    ]
    bones = _sided_bones(specs)
    sided = {s[0] for s in specs if s[6]}
    prims = [
        Primitive("pelvis", "ellipsoid", (0.0, -0.005, 0.96), radii=(0.165, 0.11, 0.12)),
        Primitive("spine", "ellipsoid", (0.0, 0.0, 1.14), radii=(0.145, 0.10, 0.13)),
        Primitive("chest", "ellipsoid", (0.0, 0.01, 1.33), radii=(0.175, 0.11, 0.15)),
        Primitive("neck", "cone", (0.0, 0.0, 1.44), (0.0, 0.0, 1.60), 0.055, 0.05),
        Primitive("head", "ellipsoid", (0.0, 0.012, 1.68), radii=(0.078, 0.095, 0.115)),
        Primitive("upper_arm", "cone", _point(shoulder), _point(elbow), 0.052, 0.040),
        Primitive("forearm", "cone", _point(elbow), _point(wrist), 0.040, 0.030),
        Primitive("hand", "ellipsoid", _along(wrist, hand_end, 0.45), radii=(0.048, 0.022, 0.085)),
        Primitive("thigh", "cone", hip, knee, 0.082, 0.052),
        Primitive("shin", "cone", knee, ankle, 0.050, 0.034),
        Primitive("foot", "ellipsoid", (0.165, 0.055, 0.045), radii=(0.045, 0.035, 0.125)),
    ]
    return BodyPlan("human", tuple(bones), tuple(_sided_primitives(prims, sided)), blend=0.025)


def _quadruped() -> BodyPlan:
    # A dog-like creature ~1.6 m from snout to tail tip. Forelimbs are named like human arms and hind limbs
    # like human legs (homologous bones), so the two classes share bone names for the cross-class chart.
    fwd, up, down = (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0)
    specs = [
        ("pelvis", None, (0.0, -0.42, 0.60), (0.0, -0.20, 0.61), down, ((-8, 8), (-8, 8), (-12, 12)), False),
        ("spine", "pelvis", (0.0, -0.20, 0.61), (0.0, 0.10, 0.62), down, ((-20, 20), (-25, 25), (-25, 25)), False),
        ("chest", "spine", (0.0, 0.10, 0.62), (0.0, 0.36, 0.64), down, ((-15, 15), (-20, 20), (-20, 20)), False),
        ("neck", "chest", (0.0, 0.36, 0.66), (0.0, 0.52, 0.86), down, ((-40, 45), (-40, 40), (-30, 30)), False),
        ("head", "neck", (0.0, 0.52, 0.86), (0.0, 0.80, 0.82), down, ((-30, 30), (-25, 25), (-25, 25)), False),
        ("tail_base", "pelvis", (0.0, -0.50, 0.62), (0.0, -0.70, 0.58), down, ((-40, 50), (-50, 50), (-10, 10)), False),
        ("tail_tip", "tail_base", (0.0, -0.70, 0.58), (0.0, -0.88, 0.46), down, ((-40, 50), (-50, 50), (-10, 10)),
         False),
        ("upper_arm", "chest", (0.135, 0.30, 0.56), (0.145, 0.27, 0.33), fwd, ((-50, 70), (-30, 5), (-15, 15)), True),
        ("forearm", "upper_arm", (0.145, 0.27, 0.33), (0.145, 0.30, 0.09), fwd, ((-10, 120), (-8, 8), (-10, 10)), True),
        ("hand", "forearm", (0.145, 0.30, 0.09), (0.145, 0.39, 0.03), up, ((-40, 60), (-10, 10), (-10, 10)), True),
        ("thigh", "pelvis", (0.135, -0.36, 0.56), (0.145, -0.27, 0.34), fwd, ((-40, 70), (-30, 5), (-15, 15)), True),
        ("shin", "thigh", (0.145, -0.27, 0.34), (0.145, -0.38, 0.14), fwd, ((-90, 30), (-8, 8), (-10, 10)), True),
        ("foot", "shin", (0.145, -0.38, 0.14), (0.145, -0.31, 0.03), fwd, ((-40, 50), (-10, 10), (-10, 10)), True),
    ]
    bones = _sided_bones(specs)
    sided = {s[0] for s in specs if s[6]}
    prims = [
        Primitive("pelvis", "ellipsoid", (0.0, -0.33, 0.59), radii=(0.14, 0.14, 0.17)),
        Primitive("spine", "ellipsoid", (0.0, -0.06, 0.63), radii=(0.115, 0.125, 0.24)),
        Primitive("chest", "ellipsoid", (0.0, 0.22, 0.60), radii=(0.14, 0.18, 0.20)),
        Primitive("neck", "cone", (0.0, 0.34, 0.64), (0.0, 0.54, 0.88), 0.085, 0.065),
        Primitive("head", "ellipsoid", (0.0, 0.58, 0.88), radii=(0.085, 0.09, 0.11)),
        Primitive("head", "cone", (0.0, 0.64, 0.865), (0.0, 0.80, 0.83), 0.055, 0.035),
        Primitive("tail_base", "cone", (0.0, -0.46, 0.63), (0.0, -0.70, 0.58), 0.045, 0.032),
        Primitive("tail_tip", "cone", (0.0, -0.70, 0.58), (0.0, -0.88, 0.46), 0.032, 0.02),
        Primitive("upper_arm", "cone", (0.135, 0.30, 0.56), (0.145, 0.27, 0.33), 0.065, 0.045),
        Primitive("forearm", "cone", (0.145, 0.27, 0.33), (0.145, 0.30, 0.09), 0.042, 0.032),
        Primitive("hand", "ellipsoid", (0.145, 0.33, 0.045), radii=(0.045, 0.03, 0.065)),
        Primitive("thigh", "cone", (0.135, -0.36, 0.56), (0.145, -0.27, 0.34), 0.080, 0.050),
        Primitive("shin", "cone", (0.145, -0.27, 0.34), (0.145, -0.38, 0.14), 0.046, 0.034),
        Primitive("foot", "cone", (0.145, -0.38, 0.14), (0.145, -0.32, 0.045), 0.034, 0.03),
        Primitive("foot", "ellipsoid", (0.145, -0.30, 0.04), radii=(0.045, 0.03, 0.06)),
    ]
    return BodyPlan("quad", tuple(bones), tuple(_sided_primitives(prims, sided)), blend=0.025)


#: The humanoid body plan (torso, head, arms with elbows and hands, legs with knees and feet).
HUMAN = _human()
#: The quadruped body plan (four legs, neck, head with a snout, two-bone tail).
QUADRUPED = _quadruped()
#: Body plans by class name.
BODY_PLANS = {HUMAN.name: HUMAN, QUADRUPED.name: QUADRUPED}
