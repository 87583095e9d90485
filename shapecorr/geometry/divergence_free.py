"""Divergence-free vector fields on the unit box and the flows they generate (docs/divfree.md §1-§3).

The basis of the divergence-free deformation method (Eisenberger, Lähner, Cremers, "Divergence-Free Shape
Correspondence by Deformation", SGP 2019) and of the Hamiltonian interpolation: curls of sine potentials on
the unit box ``[0, 1]^3``.

* **Potentials**: ``psi_abc(x) = sin(a pi x_0) sin(b pi x_1) sin(c pi x_2)`` for ``a, b, c = 1..K``.
* **Fields**: ``v_{abc,d} = s_{abc,d} / pi * curl(psi_abc e_d) = s_{abc,d} / pi * grad(psi_abc) x e_d`` for the
  three directions ``d = 0, 1, 2``: ``3 K^3`` fields (1536 for the published K = 8). A curl has zero
  divergence, and ``psi`` vanishes on the box faces, so every field is tangent to them: the flow maps the box
  onto itself and preserves volume.
* **Scaling** (as published): ``s_{abc,d} = 1 / sqrt(p^2 + q^2)`` where p, q are the two mode indices other
  than the d-th (e.g. ``b, c`` for d = 0); the ``1 / pi`` drops the common factor of the gradient (the
  original code omits it too). Each field then has a magnitude of order one. ``convention="original_code"``
  reproduces the original code instead, whose fields have the opposite sign (``e_d x grad psi``) and whose
  scale factors are assigned to the wrong directions (d = 0 gets ``1 / sqrt(a^2 + b^2)``, d = 1
  ``1 / sqrt(b^2 + c^2)``, d = 2 ``1 / sqrt(a^2 + c^2)``; measured on that code, docs/divfree.md §2): still
  divergence-free, only the relative weights of the fields differ.
* **Field order**: ``f = ((a-1) K^2 + (b-1) K + (c-1)) * 3 + d``, as in the original code, so coefficient
  vectors are interchangeable (up to the convention).

A field ``v = sum_f coeffs[f] v_f`` is the curl of the vector potential ``Phi_d = sum_abc A_{d,abc} psi_abc /
pi`` with ``A_{d,abc} = s_{abc,d} coeffs[abc,d]``, so velocities and Jacobians are evaluated from the
separable per-coordinate sines and cosines in ``O(n K^3)`` without building the ``(n, 3 K^3, 3)`` basis
tensor (:func:`basis_fields` builds it where it is needed, e.g. for tests or least squares).

Flows (:func:`integrate_flow`, :func:`flow_frames`): the stationary field is integrated from t = 0 to 1 with
``n_steps`` steps of ``h = 1 / n_steps``.

* ``"midpoint"`` (default): the explicit midpoint rule ``x <- x + h v(x + h/2 v(x))``, second order, its
  endpoint converging to the exact time-1 flow as the steps increase.
* ``"original"``: the step as the original code writes it, ``x_mid = x + h^2/2 v(x)``, ``x <- x_mid + h^2
  v(x_mid)``. Its steps advance the time by ``1.5 h^2`` rather than h, so the endpoint is the flow for time
  ``1.5 / n_steps`` (it depends on the number of steps) and the rule is only first-order accurate for that
  time (docs/divfree.md §3 has the measurements).

Pure torch: every function works on CPU or GPU tensors, batched over points (chunked to bound memory),
differentiable with autograd in the points and in the coefficients. Written by hand: no library provides
this basis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from shapecorr.errors import ConfigError, NumericalError

#: Modes per axis K of the published method (original code ``DivFreeParam.k = 8``): 3 K^3 = 1536 fields.
PUBLISHED_N_MODES = 8
#: Time steps of the flow (original code ``DivFreeParam.num_timesteps = 16``).
PUBLISHED_N_STEPS = 16
#: Box margin of the pair normalization: shapes fill [margin, 1 - margin]^3 (original code: v <- 0.9 v + 0.05).
BOX_MARGIN = 0.05
#: Points evaluated at once (bounds memory to ~ chunk * K^2 floats per einsum; the original code replays the
#: flow on full-resolution meshes in chunks of 1000 vertices).
DEFAULT_CHUNK_SIZE = 4096
#: Conventions of the basis (module docstring).
CONVENTIONS = ("published", "original_code")
#: Integration rules of :func:`integrate_flow` (module docstring).
FLOW_RULES = ("midpoint", "original")
#: Frame times are matched to the step grid of the "original" rule within this tolerance (in steps).
STEP_GRID_ATOL = 1e-4


# ----------------------------------------------------------------------------------------------------------
# The basis
# ----------------------------------------------------------------------------------------------------------
def n_fields(n_modes: int) -> int:
    """Number of basis fields ``3 K^3`` for ``K = n_modes`` modes per axis."""
    return 3 * int(n_modes) ** 3


def n_modes_of(n_coeffs: int) -> int:
    """Modes per axis K of a coefficient vector of length ``3 K^3``.

    Raises
    ------
    ConfigError
        ``n_coeffs`` is not of the form ``3 K^3``.
    """
    k = round((n_coeffs / 3) ** (1.0 / 3.0))
    if k < 1 or 3 * k**3 != n_coeffs:
        raise ConfigError(f"a divergence-free coefficient vector has 3 K^3 entries (K modes per axis), got {n_coeffs}")
    return k


def _check_convention(convention: str) -> None:
    if convention not in CONVENTIONS:
        raise ConfigError(f"basis convention must be one of {CONVENTIONS}, got {convention!r}")


def basis_scales(n_modes: int, convention: str = "published", dtype=torch.float32, device=None) -> torch.Tensor:
    """Signed scale ``s_f`` of every field (module docstring), in field order.

    Parameters
    ----------
    n_modes : int
        K >= 1.
    convention : {"published", "original_code"}

    Returns
    -------
    (3 K^3,) float
        ``1 / sqrt(p^2 + q^2)`` (published); the original code's permuted, negated factors otherwise.
    """
    _check_convention(convention)
    if n_modes < 1:
        raise ConfigError(f"n_modes must be >= 1, got {n_modes}")
    k = torch.arange(1, n_modes + 1, dtype=torch.float64, device=device)
    a, b, c = torch.meshgrid(k, k, k, indexing="ij")
    if convention == "published":
        pairs = ((b, c), (a, c), (a, b))  # the two indices other than d
        sign = 1.0
    else:
        pairs = ((a, b), (b, c), (a, c))  # as the original code assigns them
        sign = -1.0
    scales = torch.stack([sign / torch.sqrt(p**2 + q**2) for p, q in pairs], dim=-1)  # (K, K, K, 3)
    return scales.reshape(-1).to(dtype)


def _check_points(points: torch.Tensor) -> None:
    if not isinstance(points, torch.Tensor) or points.ndim != 2 or points.shape[1] != 3:
        shape = tuple(points.shape) if isinstance(points, torch.Tensor) else type(points).__name__
        raise ConfigError(f"points must be an (n, 3) float tensor, got {shape}")
    if not points.dtype.is_floating_point:
        raise ConfigError(f"points must be floating point, got {points.dtype}")
    if not bool(torch.isfinite(points.detach()).all()):
        raise NumericalError("points contain NaN or Inf; cannot evaluate the divergence-free field")


def _check_coeffs(coeffs: torch.Tensor) -> int:
    if not isinstance(coeffs, torch.Tensor) or coeffs.ndim != 1:
        raise ConfigError("coefficients must be a 1-D tensor of length 3 K^3")
    if not bool(torch.isfinite(coeffs.detach()).all()):
        raise NumericalError("divergence-free coefficients contain NaN or Inf")
    return n_modes_of(coeffs.shape[0])


def _factors(points: torch.Tensor, n_modes: int, second: bool = True):
    """Sine/cosine features per coordinate m and mode a, each (n, 3, K).

    ``sin(a pi x_m)``, ``a cos(a pi x_m)`` and (``second``) ``-a^2 sin(a pi x_m)``; None for the last without
    ``second``.
    """
    k = torch.arange(1, n_modes + 1, dtype=points.dtype, device=points.device)
    arg = points.unsqueeze(-1) * (math.pi * k)
    sin = torch.sin(arg)
    return sin, torch.cos(arg) * k, (-sin * k**2 if second else None)


def _potential_coefficients(coeffs: torch.Tensor, n_modes: int, convention: str) -> torch.Tensor:
    """``A (3, K, K, K)``: per direction d the scaled coefficients of the potential ``Phi_d``."""
    scales = basis_scales(n_modes, convention, dtype=coeffs.dtype, device=coeffs.device)
    return (coeffs * scales).reshape(n_modes, n_modes, n_modes, 3).permute(3, 0, 1, 2)


def _prepare(points: torch.Tensor, coeffs: torch.Tensor, convention: str) -> tuple[int, torch.Tensor]:
    """Check the inputs once; K and the potential coefficients ``(3, K, K, K)`` in the dtype of ``points``."""
    _check_convention(convention)
    _check_points(points)
    k = _check_coeffs(coeffs)
    return k, _potential_coefficients(coeffs.to(points.dtype), k, convention)


def _contract(fa: torch.Tensor, fb: torch.Tensor, fc: torch.Tensor, pot: torch.Tensor) -> torch.Tensor:
    """``sum_abc fa[n,a] fb[n,b] fc[n,c] pot[d,a,b,c]`` -> (n, 3), contracting one axis at a time."""
    t = torch.einsum("nc,dabc->ndab", fc, pot)
    t = torch.einsum("nb,ndab->nda", fb, t)
    return torch.einsum("na,nda->nd", fa, t)


def _curl(grad: torch.Tensor) -> torch.Tensor:
    """Curl from ``grad[..., j, d] = d_j Phi_d``: ``v_i = eps_ijd grad[j, d]`` -> (..., 3)."""
    return torch.stack(
        (
            grad[..., 1, 2] - grad[..., 2, 1],
            grad[..., 2, 0] - grad[..., 0, 2],
            grad[..., 0, 1] - grad[..., 1, 0],
        ),
        dim=-1,
    )


def _chunks(n: int, chunk_size: int):
    if chunk_size < 1:
        raise ConfigError(f"chunk_size must be positive, got {chunk_size}")
    for start in range(0, n, chunk_size):
        yield slice(start, min(n, start + chunk_size))


def _velocity_block(points: torch.Tensor, pot: torch.Tensor, n_modes: int) -> torch.Tensor:
    """Velocity at ``points (n, 3)`` from the potential coefficients ``pot (3, K, K, K)``.

    The three gradient components need the products (cos, sin, sin), (sin, cos, sin), (sin, sin, cos); the
    contraction over c is shared between the first two. Written as a few batched matrix products (rather than
    one einsum per component) because the per-call overhead dominates at the sizes of the optimization.
    """
    k = n_modes
    n = points.shape[0]
    sin, dcos, _ = _factors(points, k, second=False)
    fz = torch.stack((sin[:, 2], dcos[:, 2]), dim=1)  # (n, 2, K): (sin z, cos z)
    fy = torch.stack((sin[:, 1], dcos[:, 1]), dim=1)  # (n, 2, K)
    u = fz @ pot.reshape(3 * k * k, k).T  # (n, 2_z, 3_d * K_a * K_b)
    w = u.reshape(n, 2 * 3 * k, k) @ fy.transpose(1, 2)  # (n, 2_z * 3_d * K_a, 2_y)
    w = w.reshape(n, 2, 3, k, 2)  # (n, z, d, a, y)
    # components j = 0, 1, 2: (z, y) = (sin, sin), (sin, cos), (cos, sin); x factor cos, sin, sin
    zy = torch.stack((w[:, 0, :, :, 0], w[:, 0, :, :, 1], w[:, 1, :, :, 0]), dim=1)  # (n, j, d, a)
    fx = torch.stack((dcos[:, 0], sin[:, 0], sin[:, 0]), dim=1)  # (n, j, a)
    grad = (zy * fx[:, :, None, :]).sum(-1)  # (n, j, d) = d_j Phi_d, with the 1/pi of the module docstring
    return _curl(grad)


def velocity(
    points: torch.Tensor,
    coeffs: torch.Tensor,
    convention: str = "published",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """The field ``v(x) = sum_f coeffs[f] v_f(x)`` at many points.

    Parameters
    ----------
    points : (n, 3) float
        Positions in box coordinates (the field is defined everywhere; it is tangent to the faces of [0, 1]^3).
    coeffs : (3 K^3,) float
        Field coefficients in the field order of the module docstring (K is read from the length).
    convention : {"published", "original_code"}
    chunk_size : int
        Points per block.

    Returns
    -------
    (n, 3) float
        Differentiable in ``points`` and ``coeffs``.
    """
    k, pot = _prepare(points, coeffs, convention)
    return _field(points, pot, k, chunk_size)


def _field(points: torch.Tensor, pot: torch.Tensor, k: int, chunk_size: int) -> torch.Tensor:
    """Unchecked velocity from the potential coefficients (the flows check their inputs once)."""
    if points.shape[0] <= chunk_size:
        return _velocity_block(points, pot, k)
    blocks = [_velocity_block(points[s], pot, k) for s in _chunks(points.shape[0], chunk_size)]
    return torch.cat(blocks, dim=0) if blocks else points.new_zeros(0, 3)


def velocity_jacobian(
    points: torch.Tensor,
    coeffs: torch.Tensor,
    convention: str = "published",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """Jacobian of the field, ``J[n, i, l] = d v_i / d x_l`` at many points (analytic second derivatives).

    Parameters
    ----------
    points : (n, 3) float
    coeffs : (3 K^3,) float
    convention : {"published", "original_code"}
    chunk_size : int

    Returns
    -------
    (n, 3, 3) float
        Trace-free (the field is divergence-free), differentiable in ``points`` and ``coeffs``.
    """
    k, pot = _prepare(points, coeffs, convention)
    blocks = []
    for s in _chunks(points.shape[0], chunk_size):
        sin, dcos, d2 = _factors(points[s], k)
        entries = {}  # (j, q) -> (n, d): d_j d_q Phi_d
        for j in range(3):
            for q in range(j, 3):
                fac = []
                for m in range(3):
                    order = (m == j) + (m == q)
                    fac.append(sin[:, m] if order == 0 else dcos[:, m] if order == 1 else d2[:, m])
                # The second derivative carries one more factor pi than the gradient (module docstring).
                entries[(j, q)] = math.pi * _contract(fac[0], fac[1], fac[2], pot)
        hess = torch.stack(
            [torch.stack([entries[(min(j, q), max(j, q))] for q in range(3)], dim=1) for j in range(3)], dim=1
        )  # (n, j, q, d)
        # J[i, q] = eps_ijd d_q d_j Phi_d: the curl taken over (j, d) for each q.
        blocks.append(_curl(hess.permute(0, 2, 1, 3)).transpose(1, 2))  # (n, q, i) -> (n, i, q)
    return torch.cat(blocks, dim=0) if blocks else points.new_zeros(0, 3, 3)


def basis_fields(points: torch.Tensor, n_modes: int = PUBLISHED_N_MODES, convention: str = "published") -> torch.Tensor:
    """Every basis field at every point, ``out[n, f] = v_f(points[n])``.

    Parameters
    ----------
    points : (n, 3) float
    n_modes : int
        K; the result has ``3 K^3`` fields.
    convention : {"published", "original_code"}

    Returns
    -------
    (n, 3 K^3, 3) float
        ``velocity(points, a) == einsum("nfi,f->ni", basis_fields(points), a)``. Memory ``n * 9 K^3`` floats:
        chunk the points for large n. Stored component-major (the transposed view of an ``(n, 3, 3 K^3)``
        tensor), so ``out.transpose(1, 2)`` is contiguous: the rows ``(n, i)`` of a least-squares system.
    """
    _check_convention(convention)
    _check_points(points)
    if n_modes < 1:
        raise ConfigError(f"n_modes must be >= 1, got {n_modes}")
    k = int(n_modes)
    n = points.shape[0]
    sin, dcos, _ = _factors(points, k, second=False)
    sx, sy, sz = sin[:, 0], sin[:, 1], sin[:, 2]
    cx, cy, cz = dcos[:, 0], dcos[:, 1], dcos[:, 2]

    def outer(fa, fb, fc):
        return (fa[:, :, None] * fb[:, None, :]).reshape(n, k * k, 1) * fc[:, None, :]  # (n, K^2, K)

    # d_j psi for j = 0, 1, 2, each (n, K^3) in (a, b, c) order
    grad = (outer(cx, sy, sz).reshape(n, k**3), outer(sx, cy, sz).reshape(n, k**3), outer(sx, sy, cz).reshape(n, k**3))
    scales = basis_scales(k, convention, dtype=points.dtype, device=points.device).reshape(k**3, 3)
    # (grad psi x e_d)_i = eps_ijd g_j: for each component i, +g_{i+1} at d = i + 2, -g_{i+2} at d = i + 1 and
    # 0 at d = i (indices mod 3). Every nonzero entry is one product sign * g_j * s_d, written into its slot.
    out = points.new_empty(n, 3, k**3, 3)  # (n, i, abc, d)
    for i in range(3):
        j1, j2 = (i + 1) % 3, (i + 2) % 3
        out[:, i, :, i] = 0.0
        out[:, i, :, j2] = grad[j1] * scales[:, j2]
        out[:, i, :, j1] = grad[j2] * -scales[:, j1]
    return out.reshape(n, 3, 3 * k**3).transpose(1, 2)


def resize_coefficients(coeffs: torch.Tensor, n_modes: int) -> torch.Tensor:
    """The same field in a basis of ``n_modes`` modes per axis: zero-padded (more modes) or truncated (fewer).

    Parameters
    ----------
    coeffs : (3 K^3,) float
    n_modes : int
        The new K'.

    Returns
    -------
    (3 K'^3,) float
        Coefficients of modes with indices <= min(K, K') are kept, the others are zero (coarse-to-fine: the
        field of a coarse level is exactly the starting field of the next).
    """
    k = _check_coeffs(coeffs)
    if n_modes < 1:
        raise ConfigError(f"n_modes must be >= 1, got {n_modes}")
    m = min(k, int(n_modes))
    out = coeffs.new_zeros(int(n_modes), int(n_modes), int(n_modes), 3)
    out[:m, :m, :m] = coeffs.reshape(k, k, k, 3)[:m, :m, :m]
    return out.reshape(-1)


# ----------------------------------------------------------------------------------------------------------
# Normalization of a pair into the box
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BoxTransform:
    """Similarity ``box = (v - center) * scale + 0.5`` of one shape into the unit box.

    Attributes
    ----------
    center : (3,) float tensor
        Centre of the shape's bounding box (input units).
    scale : float
        Box units per input unit (shared by both shapes of a pair).
    """

    center: torch.Tensor
    scale: float

    def to_box(self, verts: torch.Tensor) -> torch.Tensor:
        """``(..., 3)`` input-unit positions -> box coordinates."""
        return (verts - self.center.to(verts)) * self.scale + 0.5

    def from_box(self, points: torch.Tensor) -> torch.Tensor:
        """``(..., 3)`` box coordinates -> input units (inverse of :meth:`to_box`)."""
        return (points - 0.5) / self.scale + self.center.to(points)


def box_normalization(
    verts_x: torch.Tensor, verts_y: torch.Tensor, margin: float = BOX_MARGIN
) -> tuple[BoxTransform, BoxTransform]:
    """Place a pair in the unit box as the original code does (docs/divfree.md §1).

    Each shape is centred (bounding-box centre to 0.5), both are scaled by the same factor so that the
    largest bounding-box side over both shapes spans ``[margin, 1 - margin]``.

    Parameters
    ----------
    verts_x : (n, 3) float
    verts_y : (m, 3) float
    margin : float
        In [0, 0.5).

    Returns
    -------
    (BoxTransform, BoxTransform)
        For x and for y.
    """
    _check_points(verts_x)
    _check_points(verts_y)
    if not 0.0 <= margin < 0.5:
        raise ConfigError(f"box margin must be in [0, 0.5), got {margin}")
    if verts_x.shape[0] == 0 or verts_y.shape[0] == 0:
        raise ConfigError("box normalization needs non-empty point sets")
    lo_x, hi_x = verts_x.detach().amin(0), verts_x.detach().amax(0)
    lo_y, hi_y = verts_y.detach().amin(0), verts_y.detach().amax(0)
    extent = float(torch.maximum((hi_x - lo_x).max(), (hi_y - lo_y).max()))
    if not extent > 0:
        raise ConfigError("box normalization: both point sets are single points (zero extent)")
    scale = (1.0 - 2.0 * margin) / extent
    return BoxTransform(0.5 * (lo_x + hi_x), scale), BoxTransform(0.5 * (lo_y + hi_y), scale)


# ----------------------------------------------------------------------------------------------------------
# Flows
# ----------------------------------------------------------------------------------------------------------
def _check_rule(rule: str, n_steps: int) -> None:
    if rule not in FLOW_RULES:
        raise ConfigError(f"flow rule must be one of {FLOW_RULES}, got {rule!r}")
    if int(n_steps) < 1:
        raise ConfigError(f"n_steps must be >= 1, got {n_steps}")


def flow_step(points: torch.Tensor, coeffs: torch.Tensor, h: float, rule: str = "midpoint",
              convention: str = "published", chunk_size: int = DEFAULT_CHUNK_SIZE) -> torch.Tensor:
    """One step of the flow (module docstring).

    Parameters
    ----------
    points : (n, 3) float
    coeffs : (3 K^3,) float
    h : float
        Step size (negative: backwards in time, "midpoint" only).
    rule : {"midpoint", "original"}

    Returns
    -------
    (n, 3) float
    """
    _check_rule(rule, 1)
    k, pot = _prepare(points, coeffs, convention)
    return _step(points, pot, k, h, rule, chunk_size)


def _step(points: torch.Tensor, pot: torch.Tensor, k: int, h: float, rule: str, chunk_size: int) -> torch.Tensor:
    if rule == "midpoint":
        mid = points + 0.5 * h * _field(points, pot, k, chunk_size)
        return points + h * _field(mid, pot, k, chunk_size)
    if h < 0:
        raise ConfigError("the 'original' step rule cannot run backwards in time (its steps scale with h^2)")
    mid = points + 0.5 * h * h * _field(points, pot, k, chunk_size)
    return mid + h * h * _field(mid, pot, k, chunk_size)


def integrate_flow(
    points: torch.Tensor,
    coeffs: torch.Tensor,
    n_steps: int = PUBLISHED_N_STEPS,
    rule: str = "midpoint",
    t_end: float = 1.0,
    return_path: bool = False,
    convention: str = "published",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """Flow points along the stationary field from t = 0 to ``t_end``.

    Parameters
    ----------
    points : (n, 3) float
        Starting positions (box coordinates).
    coeffs : (3 K^3,) float
    n_steps : int
        Steps of ``h = t_end / n_steps``.
    rule : {"midpoint", "original"}
        See the module docstring ("original": ``t_end`` must be >= 0, and its steps advance by 1.5 h^2).
    t_end : float
        Negative: the inverse flow ("midpoint").
    return_path : bool
        Return every step (including the start) instead of the endpoint.

    Returns
    -------
    (n, 3) float, or (n_steps + 1, n, 3) with ``return_path``
        Differentiable in ``points`` and ``coeffs``.

    Raises
    ------
    NumericalError
        The flow produced NaN/Inf (coefficients far too large).
    """
    _check_rule(rule, n_steps)
    k, pot = _prepare(points, coeffs, convention)
    h = float(t_end) / int(n_steps)
    path = [points]
    x = points
    for _ in range(int(n_steps)):
        x = _step(x, pot, k, h, rule, chunk_size)
        if return_path:
            path.append(x)
    if not bool(torch.isfinite(x.detach()).all()):
        raise NumericalError("the divergence-free flow diverged (NaN/Inf); the field coefficients are too large")
    return torch.stack(path, dim=0) if return_path else x


def flow_frames(
    points: torch.Tensor,
    coeffs: torch.Tensor,
    times,
    n_steps: int = PUBLISHED_N_STEPS,
    rule: str = "midpoint",
    convention: str = "published",
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """Positions at any times (t = 1: the full flow, t > 1 extrapolates, t < 0 runs backwards).

    The time axis is cut at 0 and at every requested time; each piece of length ``dt`` is integrated with
    ``ceil(|dt| n_steps)`` equal steps, so requested times on the grid ``k / n_steps`` reproduce
    :func:`integrate_flow` exactly ("midpoint"). The "original" rule needs times on that grid (its steps are
    tied to h = 1 / n_steps) and t >= 0.

    Parameters
    ----------
    points : (n, 3) float
    coeffs : (3 K^3,) float
    times : sequence of float or (T,) tensor
        Any order.
    n_steps : int
        Steps per unit time.
    rule : {"midpoint", "original"}

    Returns
    -------
    (T, n, 3) float
        In the order of ``times``.
    """
    _check_rule(rule, n_steps)
    k, pot = _prepare(points, coeffs, convention)
    values = [float(t) for t in (times.reshape(-1).tolist() if isinstance(times, torch.Tensor) else times)]
    if not all(math.isfinite(t) for t in values):
        raise ConfigError(f"frame times must be finite, got {values}")
    n_steps = int(n_steps)
    h = 1.0 / n_steps
    out: dict[float, torch.Tensor] = {}
    for sign in (1.0, -1.0):
        wanted = sorted({abs(t) for t in values if (t > 0 if sign > 0 else t < 0)})
        x, t_now = points, 0.0
        for t in wanted:
            if rule == "original":
                if sign < 0:
                    raise ConfigError("the 'original' step rule cannot produce frames at negative times")
                steps = t * n_steps
                if abs(steps - round(steps)) > STEP_GRID_ATOL:
                    raise ConfigError(
                        f"the 'original' step rule only has frames at multiples of 1/{n_steps}; got t = {t}"
                    )
                for _ in range(round(steps) - round(t_now * n_steps)):
                    x = _step(x, pot, k, h, rule, chunk_size)
            else:
                m = max(1, math.ceil((t - t_now) / h - STEP_GRID_ATOL))
                for _ in range(m):
                    x = _step(x, pot, k, sign * (t - t_now) / m, rule, chunk_size)
            t_now = t
            out[sign * t] = x
    out.setdefault(0.0, points)
    frames = torch.stack([out[0.0] if t == 0 else out[t] for t in values], dim=0)
    if not bool(torch.isfinite(frames.detach()).all()):
        raise NumericalError("the divergence-free flow diverged (NaN/Inf); the field coefficients are too large")
    return frames
