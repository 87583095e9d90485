"""Deforming a template: per-subject proportions (identity) and linear blend skinning (pose).

Both steps are linear blend skinning with per-bone 3x4 transforms ``T_b`` and the template's weights ``w``:
``v' = sum_b w_b(v) T_b v``.

* **Identity.** A subject scales each bone in its own frame: ``s_len`` along the bone axis, ``s_lat`` and
  ``s_ref`` across it. The bone's affine map is ``A_b(x) = h'_b + F_b S_b F_b^T (x - h_b)`` with ``h_b`` its
  rest joint, ``F_b`` its frame, and ``h'_b = A_parent(h_b)`` the joint carried along by the scaled parent.
  Joints therefore stay attached, and every subject keeps the template's vertex set, so the dense
  correspondence between subjects is exact.
* **Pose.** Joint rotations ``R_b`` (from three angles, see ``skeleton.py``) compose down the tree:
  ``G_b = G_parent T(h_b) R_b T(-h_b)``, and the root transform adds a global rotation and translation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shapecorr.data.synthetic.skeleton import BodyPlan, plan_frames
from shapecorr.errors import ConfigError, NumericalError

#: Subject scale factors are clipped to [1 / MAX_SCALE_FACTOR, MAX_SCALE_FACTOR].
MAX_SCALE_FACTOR = 1.45


@dataclass(frozen=True, eq=False)
class Identity:
    """Proportions of one subject.

    Attributes
    ----------
    scales : (B, 3) float64
        Per bone, the scale factors along ``(lat, ref, axis)`` of its frame.
    """

    scales: np.ndarray


def rotation_about(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about unit axes (Rodrigues' formula).

    Parameters
    ----------
    axis : (..., 3) float
        Unit axes.
    angle : (...) float
        Angles in radians.

    Returns
    -------
    (..., 3, 3) float64
    """
    u = np.asarray(axis, np.float64)
    a = np.asarray(angle, np.float64)[..., None, None]
    k = np.zeros(u.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2] = -u[..., 2], u[..., 1]
    k[..., 1, 0], k[..., 1, 2] = u[..., 2], -u[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -u[..., 1], u[..., 0]
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def local_rotations(angles_deg: np.ndarray, sides: np.ndarray) -> np.ndarray:
    """Joint rotations in bone-frame coordinates from (flex, abd, twist) angles.

    ``R_local = R_lat(-flex) R_ref(side * abd) R_axis(side * twist)``, frame axes ``(lat, ref, axis) = (x, y, z)``:
    a positive flex turns the bone axis towards ``ref``, a positive abd towards ``lat``.

    Parameters
    ----------
    angles_deg : (B, 3) float
    sides : (B,) float
        +1 or -1 (mirror sign of abd and twist).

    Returns
    -------
    (B, 3, 3) float64
    """
    ang = np.radians(np.asarray(angles_deg, np.float64))
    eye = np.eye(3)
    r_flex = rotation_about(np.broadcast_to(eye[0], ang.shape), -ang[:, 0])
    r_abd = rotation_about(np.broadcast_to(eye[1], ang.shape), sides * ang[:, 1])
    r_twist = rotation_about(np.broadcast_to(eye[2], ang.shape), sides * ang[:, 2])
    return r_flex @ r_abd @ r_twist


def _affine(linear: np.ndarray, centre_from: np.ndarray, centre_to: np.ndarray) -> np.ndarray:
    """4x4 matrices of ``x -> centre_to + linear (x - centre_from)`` (batched)."""
    out = np.zeros(linear.shape[:-2] + (4, 4))
    out[..., :3, :3] = linear
    out[..., :3, 3] = centre_to - np.einsum("...ij,...j->...i", linear, centre_from)
    out[..., 3, 3] = 1.0
    return out


def identity_transforms(plan: BodyPlan, identity: Identity) -> tuple[np.ndarray, np.ndarray]:
    """Per-bone affine maps from the canonical template to a subject's rest pose.

    Parameters
    ----------
    plan : BodyPlan
    identity : Identity

    Returns
    -------
    transforms : (B, 4, 4) float64
    heads : (B, 3) float64
        The subject's joint positions.
    """
    scales = np.asarray(identity.scales, np.float64)
    if scales.shape != (len(plan.bones), 3) or np.any(scales <= 0):
        raise ConfigError(f"identity scales must be positive with shape ({len(plan.bones)}, 3), got {scales.shape}")
    frames = plan_frames(plan)
    heads = plan.heads
    parents = plan.parents
    linear = np.einsum("bij,bj,bkj->bik", frames, scales, frames)
    transforms = np.zeros((len(plan.bones), 4, 4))
    new_heads = np.zeros_like(heads)
    for b, p in enumerate(parents):
        new_heads[b] = heads[b] if p < 0 else transforms[p, :3, :3] @ heads[b] + transforms[p, :3, 3]
        transforms[b] = _affine(linear[b], heads[b], new_heads[b])
    return transforms, new_heads


def pose_transforms(
    plan: BodyPlan, heads: np.ndarray, angles_deg: np.ndarray, root_rotation: np.ndarray | None = None
) -> np.ndarray:
    """Forward kinematics: rigid transform of every bone for joint angles.

    Parameters
    ----------
    plan : BodyPlan
    heads : (B, 3) float
        Rest joint positions (of the subject being posed).
    angles_deg : (B, 3) float
        (flex, abd, twist) of every joint.
    root_rotation : (3, 3) float, optional
        Extra global rotation about the root joint.

    Returns
    -------
    (B, 4, 4) float64 transforms mapping rest positions to posed positions.
    """
    angles = np.asarray(angles_deg, np.float64)
    if angles.shape != (len(plan.bones), 3):
        raise ConfigError(f"pose angles must have shape ({len(plan.bones)}, 3), got {angles.shape}")
    frames = plan_frames(plan)
    local = local_rotations(angles, plan.sides)
    world = frames @ local @ np.swapaxes(frames, 1, 2)
    h = np.asarray(heads, np.float64)
    joint = _affine(world, h, h)
    out = np.zeros_like(joint)
    for b, p in enumerate(plan.parents):
        if p < 0:
            root = np.eye(4)
            if root_rotation is not None:
                root = _affine(np.asarray(root_rotation, np.float64), h[b], h[b])
            out[b] = root @ joint[b]
        else:
            out[b] = out[p] @ joint[b]
    return out


def blend_skin(verts: np.ndarray, weights: np.ndarray, transforms: np.ndarray) -> np.ndarray:
    """Linear blend skinning ``v' = sum_b w_b T_b v``.

    Parameters
    ----------
    verts : (n, 3) float
    weights : (n, B) float, rows summing to one
    transforms : (B, 4, 4) float

    Returns
    -------
    (n, 3) float64
    """
    v = np.asarray(verts, np.float64)
    t = np.asarray(transforms, np.float64)
    blended = (np.asarray(weights, np.float64) @ t[:, :3, :].reshape(len(t), 12)).reshape(-1, 3, 4)
    out = np.einsum("nij,nj->ni", blended[:, :, :3], v) + blended[:, :, 3]
    if not np.isfinite(out).all():
        raise NumericalError("skinning produced NaN/Inf vertex positions")
    return out


def sample_identity(
    plan: BodyPlan, rng: np.random.Generator, length_std: float, thickness_std: float, build_std: float
) -> Identity:
    """Random, left/right symmetric subject proportions.

    Every bone pair (``x_l``/``x_r`` share one draw) gets a length factor ``exp(N(0, length_std))`` and two
    cross-section factors ``exp(N(0, thickness_std))``; a whole-body build factor ``exp(N(0, build_std))``
    multiplies all cross sections (slim vs heavy subjects). Factors are clipped to
    ``[1/MAX_SCALE_FACTOR, MAX_SCALE_FACTOR]``.

    Parameters
    ----------
    plan : BodyPlan
    rng : numpy Generator
    length_std, thickness_std, build_std : float
        Log-normal spreads (0 gives the canonical template).

    Returns
    -------
    Identity
    """
    for name, value in (("length_std", length_std), ("thickness_std", thickness_std), ("build_std", build_std)):
        if not value >= 0:
            raise ConfigError(f"{name} must be >= 0, got {value}")
    base_names = sorted({_base(n) for n in plan.bone_names})
    draws = {name: rng.normal(size=3) for name in base_names}
    build = float(np.exp(rng.normal() * build_std))
    scales = np.empty((len(plan.bones), 3))
    for b, name in enumerate(plan.bone_names):
        z = draws[_base(name)]
        scales[b, :2] = build * np.exp(z[:2] * thickness_std)
        scales[b, 2] = np.exp(z[2] * length_std)
    return Identity(np.clip(scales, 1.0 / MAX_SCALE_FACTOR, MAX_SCALE_FACTOR))


def _base(name: str) -> str:
    return name[:-2] if name.endswith(("_l", "_r")) else name
