"""Poses of the synthetic creatures.

A library of key poses, random poses within joint limits, and the detection of self-contact (surfaces of
distant body parts touching).

A pose is a ``(B, 3)`` array of joint angles (flex, abd, twist) in degrees, see ``skeleton.py``. Key poses
name only the joints they move; a name without side (``upper_arm``) sets both sides, ``upper_arm_l`` /
``upper_arm_r`` set one side (asymmetric poses). Like FAUST, where every person performs the same
poses, pose ``p`` of every subject starts from the same base angles (key pose ``p``, or a random pose
shared by all subjects for ``p`` beyond the library), plus a shared and a per-subject random jitter.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from shapecorr.data.synthetic.skeleton import BodyPlan
from shapecorr.errors import ConfigError

#: Key poses of the humanoid, (flex, abd, twist) in degrees per joint. Order matters: pose p of every
#: subject uses entry p, so the first entries are the most different from each other.
HUMAN_KEY_POSES: tuple[tuple[str, dict[str, tuple[float, float, float]]], ...] = (
    ("neutral", {}),
    ("arms_up", {"upper_arm": (10, -105, 0), "forearm": (25, 0, 0), "neck": (-15, 0, 0)}),
    ("squat", {"thigh": (75, -15, 0), "shin": (-100, 0, 0), "foot": (20, 0, 0), "spine": (10, 0, 0),
               "upper_arm": (75, 0, 0), "forearm": (15, 0, 0)}),
    ("twist_t_pose", {"spine": (0, 0, 30), "chest": (0, 0, 30), "neck": (0, 0, 35), "upper_arm": (0, -45, 0)}),
    ("step_reach", {"thigh_r": (60, 0, 0), "shin_r": (-75, 0, 0), "thigh_l": (-20, 0, 0), "upper_arm_l": (120, -25, 0),
                    "upper_arm_r": (-30, 0, 0), "forearm_r": (45, 0, 0), "chest": (0, 0, -20)}),
    ("arms_crossed", {"upper_arm": (55, 20, 20), "forearm": (105, 0, 0), "head": (15, 0, 0)}),
    ("side_bend", {"spine": (0, 25, 0), "chest": (0, 15, 0), "upper_arm_l": (0, -125, 0), "upper_arm_r": (15, -15, 0),
                   "forearm_r": (30, 0, 0), "head": (0, 12, 0), "thigh_l": (0, -15, 0)}),
    ("kick", {"thigh_l": (70, 0, 0), "shin_l": (-20, 0, 0), "thigh_r": (-10, 0, 0), "upper_arm": (20, -30, 0),
              "spine": (-12, 0, 0), "forearm": (40, 0, 0)}),
    ("lunge_twist", {"thigh_r": (70, 0, 0), "shin_r": (-90, 0, 0), "thigh_l": (-25, 0, 0), "shin_l": (-40, 0, 0),
                     "chest": (0, 0, 25), "spine": (0, 0, 15), "upper_arm_r": (-20, -20, 0),
                     "upper_arm_l": (80, -10, 0), "forearm_l": (60, 0, 0)}),
    ("one_leg_balance", {"thigh_l": (25, -35, 0), "shin_l": (-85, 0, 0), "upper_arm": (0, -45, 0),
                         "forearm_r": (90, 0, 0), "neck": (0, 0, -40)}),
    ("bow", {"spine": (38, 0, 0), "chest": (22, 0, 0), "neck": (20, 0, 0), "upper_arm": (-40, 0, 0),
             "forearm": (10, 0, 0)}),
    ("wave", {"upper_arm_l": (0, -120, 30), "forearm_l": (100, 0, 0), "upper_arm_r": (20, 0, 0), "neck": (0, 0, -25),
              "thigh_r": (10, 0, 0)}),
)

#: Key poses of the quadruped (same conventions; for the trunk, ref points down, so flex > 0 bends ventrally).
QUAD_KEY_POSES: tuple[tuple[str, dict[str, tuple[float, float, float]]], ...] = (
    ("stand", {}),
    ("gallop", {"upper_arm": (70, 0, 0), "forearm": (-10, 0, 0), "hand": (-30, 0, 0), "thigh": (-40, -10, 0),
                "shin": (30, 0, 0), "foot": (40, 0, 0), "spine": (-20, 0, 0), "chest": (-15, 0, 0),
                "neck": (-40, 0, 0), "head": (-20, 0, 0), "tail_base": (-40, 0, 0), "tail_tip": (-35, 0, 0)}),
    ("curl_look_back", {"neck": (0, 40, 0), "head": (0, 25, 0), "spine": (0, 25, 0), "chest": (0, 20, 0),
                        "tail_base": (0, 50, 0), "tail_tip": (0, 50, 0)}),
    ("play_bow", {"upper_arm": (70, 0, 0), "forearm": (-10, 0, 0), "spine": (18, 0, 0), "neck": (30, 0, 0),
                  "tail_base": (-45, 0, 0), "tail_tip": (-30, 0, 0)}),
    ("stretch", {"upper_arm": (60, 0, 0), "thigh": (-40, 0, 0), "spine": (-15, 0, 0), "neck": (-20, 0, 0),
                 "tail_base": (0, -40, 0), "tail_tip": (0, -30, 0)}),
    ("walk", {"upper_arm_r": (35, 0, 0), "forearm_r": (50, 0, 0), "upper_arm_l": (-25, 0, 0), "thigh_r": (-30, 0, 0),
              "thigh_l": (25, 0, 0), "shin_l": (-35, 0, 0), "head": (10, 0, 0), "tail_base": (0, 30, 0)}),
    ("paw_raise", {"upper_arm_r": (60, 0, 0), "forearm_r": (80, 0, 0), "hand_r": (50, 0, 0), "head": (0, 0, 25),
                   "neck": (-25, 15, 0), "tail_base": (-30, -20, 0)}),
    ("crouch", {"thigh": (30, 0, 0), "shin": (-55, 0, 0), "upper_arm": (-30, 0, 0), "forearm": (60, 0, 0),
                "neck": (-35, 0, 0), "tail_base": (40, 0, 0)}),
    ("scratch", {"thigh_l": (35, -25, 0), "shin_l": (-60, 0, 0), "neck": (0, -40, 0), "head": (0, -25, 0),
                 "spine": (0, -15, 0)}),
    ("alert", {"neck": (-40, 0, 0), "head": (-20, 0, 0), "tail_base": (-50, 0, 0), "tail_tip": (-40, 0, 0),
               "upper_arm": (-25, 0, 0), "forearm": (20, 0, 0)}),
)

#: Key pose libraries by body plan name.
KEY_POSES = {"human": HUMAN_KEY_POSES, "quad": QUAD_KEY_POSES}

#: Poses in which body parts touch, used only by the self-contact corruption (they are never backed off).
CONTACT_POSES: dict[str, tuple[tuple[str, dict[str, tuple[float, float, float]]], ...]] = {
    "human": (
        ("deep_squat", {"thigh": (105, -10, 0), "shin": (-135, 0, 0), "spine": (35, 0, 0), "upper_arm": (60, 10, 0)}),
        ("arms_crossed_tight", {"upper_arm": (50, 35, 20), "forearm": (130, 0, 0), "head": (20, 0, 0)}),
        ("hands_on_thighs", {"upper_arm": (15, 40, 0), "forearm": (20, 0, 0), "spine": (20, 0, 0)}),
        ("knee_to_chest", {"thigh_r": (110, 10, 0), "shin_r": (-130, 0, 0), "spine": (30, 0, 0),
                           "upper_arm_r": (60, 20, 0), "forearm_r": (90, 0, 0)}),
    ),
    "quad": (
        ("sit", {"thigh": (70, 0, 0), "shin": (-90, 0, 0), "upper_arm": (-20, 0, 0), "neck": (-30, 0, 0)}),
        ("curl", {"neck": (10, 40, 0), "head": (0, 25, 0), "spine": (0, 25, 0), "chest": (0, 20, 0),
                  "tail_base": (0, 50, 0), "tail_tip": (0, 50, 0), "thigh": (40, 0, 0)}),
        ("paw_to_chest", {"upper_arm_r": (60, 10, 0), "forearm_r": (120, 0, 0), "hand_r": (60, 0, 0),
                          "neck": (30, 0, 0)}),
    ),
}

#: Pose jitter never exceeds this fraction of a joint angle's range of motion (std).
JITTER_MAX_RANGE_FRACTION = 0.12
#: Contact resolution: joint angles are scaled by this factor towards the (contact-free) rest pose until
#: no self-contact remains.
CONTACT_BACKOFF = 0.85
#: At most this many back-off steps; the rest pose is used if contact persists.
MAX_CONTACT_BACKOFFS = 12


def key_pose(plan: BodyPlan, index: int, library: dict | None = None) -> tuple[str, np.ndarray]:
    """Name and ``(B, 3)`` angles of key pose ``index`` of a body plan (clipped to the joint limits).

    ``library`` defaults to :data:`KEY_POSES`; :data:`CONTACT_POSES` holds the self-contact poses.
    """
    poses = (KEY_POSES if library is None else library).get(plan.name)
    if poses is None:
        raise ConfigError(f"no key poses for body plan {plan.name!r}")
    name, spec = poses[index % len(poses)]
    angles = np.zeros((len(plan.bones), 3))
    names = plan.bone_names
    for joint, value in spec.items():
        targets = [joint] if joint in names else [n for n in names if n in (f"{joint}_l", f"{joint}_r")]
        if not targets:
            raise ConfigError(f"key pose {name!r} of {plan.name!r} names an unknown joint {joint!r}")
        for target in targets:
            angles[names.index(target)] = value
    return name, clip_to_limits(plan, angles)


def clip_to_limits(plan: BodyPlan, angles: np.ndarray) -> np.ndarray:
    """Clip ``(B, 3)`` joint angles to the body plan's limits."""
    lim = plan.limits
    return np.clip(np.asarray(angles, np.float64), lim[..., 0], lim[..., 1])


def random_pose(plan: BodyPlan, rng: np.random.Generator, range_fraction: float) -> np.ndarray:
    """Angles drawn uniformly within the joint limits shrunk towards zero by ``range_fraction``.

    Parameters
    ----------
    plan : BodyPlan
    rng : numpy Generator
    range_fraction : float in [0, 1]

    Returns
    -------
    (B, 3) float64
    """
    if not 0.0 <= range_fraction <= 1.0:
        raise ConfigError(f"random pose range fraction must be in [0, 1], got {range_fraction}")
    lim = plan.limits * range_fraction
    return lim[..., 0] + rng.random(lim.shape[:2]) * (lim[..., 1] - lim[..., 0])


def pose_base(
    plan: BodyPlan, pose_index: int, shared_rng: np.random.Generator, range_fraction: float
) -> tuple[str, np.ndarray]:
    """Base angles of pose ``pose_index``: the key pose of that index, else a random pose (shared rng)."""
    library = KEY_POSES[plan.name]
    if pose_index < len(library):
        return key_pose(plan, pose_index)
    return f"random_{pose_index}", random_pose(plan, shared_rng, range_fraction)


def jitter(plan: BodyPlan, angles: np.ndarray, rng: np.random.Generator, std_deg: float) -> np.ndarray:
    """Add Gaussian noise to every angle, then clip to the limits.

    The standard deviation is ``std_deg``, but at most :data:`JITTER_MAX_RANGE_FRACTION` of the joint's range
    of motion for that angle (a knee's 16-degree sideways play is not jittered by as much as its flexion).
    """
    lim = plan.limits
    std = np.minimum(std_deg, JITTER_MAX_RANGE_FRACTION * (lim[..., 1] - lim[..., 0]))
    return clip_to_limits(plan, angles + rng.normal(size=angles.shape) * std)


def find_contacts(
    posed: np.ndarray,
    rest: np.ndarray,
    part: np.ndarray,
    adjacency: np.ndarray,
    margin: float,
    adjacent_reach: float,
) -> np.ndarray:
    """Pairs of template vertices that come into contact in a pose although they are far apart on the body.

    A pair counts when its posed distance is below ``margin`` and either its body parts do not touch on the
    rest surface (and it was farther than ``2 * margin`` in the rest pose), or the parts touch but the
    vertices were farther than ``adjacent_reach`` apart in the rest pose (an arm lying on the chest, not
    the inside of a bent elbow or hip).

    Parameters
    ----------
    posed, rest : (n, 3) float
        Template vertices in the pose and in the rest pose.
    part : (n,) int
        Body part (dominant bone) of every vertex.
    adjacency : (B, B) bool
        Parts that touch on the rest surface (``Template.part_adjacency``).
    margin, adjacent_reach : float

    Returns
    -------
    (k, 2) int64 contact pairs.
    """
    pairs = cKDTree(np.asarray(posed, np.float64)).query_pairs(margin, output_type="ndarray")
    if len(pairs) == 0:
        return pairs.reshape(0, 2).astype(np.int64)
    rest_dist = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1)
    adjacent = adjacency[part[pairs[:, 0]], part[pairs[:, 1]]]
    keep = np.where(adjacent, rest_dist > adjacent_reach, rest_dist > 2.0 * margin)
    return pairs[keep].astype(np.int64)


def back_off_contacts(
    angles: np.ndarray, pose_fn: Callable[[np.ndarray], np.ndarray], contact_fn: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, int]:
    """Scale joint angles towards the rest pose until the posed surface has no self-contact.

    Parameters
    ----------
    angles : (B, 3) float
    pose_fn : callable
        ``angles -> posed template vertices``.
    contact_fn : callable
        ``posed vertices -> (k, 2) contact pairs``.

    Returns
    -------
    angles : (B, 3) float64, contact-free (the rest pose if no scaled pose was)
    steps : int
        Number of back-off steps taken (``MAX_CONTACT_BACKOFFS + 1`` when the rest pose was used).
    """
    a = np.asarray(angles, np.float64)
    for step in range(MAX_CONTACT_BACKOFFS + 1):
        if len(contact_fn(pose_fn(a))) == 0:
            return a, step
        a = a * CONTACT_BACKOFF
    return np.zeros_like(a), MAX_CONTACT_BACKOFFS + 1
