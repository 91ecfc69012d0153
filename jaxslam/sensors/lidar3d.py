"""Body-frame 3D LiDAR: azimuth, elevation, range of point landmarks (paper 000 eq. 30-31, 44-45).

Frames: NED inertial frame N, body frame B (b̂1 along the LiDAR boresight, b̂2 right, b̂3 down),
C_NB of paper 000 eq. 1 (``jaxslam.geometry.euler.dcm_from_euler``, 3-2-1 Euler angles
Λ = (φ, θ, ψ)).  A landmark l (N frame, m) seen from position ρ has body coordinates
c = C_NBᵀ(l − ρ) and measurement y = [α, β, δ]:

* azimuth   α = atan2(c2, c1) ∈ (−π, π]  (positive towards b̂2, to the right),
* elevation β = atan2(c3, √(c1² + c2²)) ∈ [−π/2, π/2]  (positive **below** the body x-y plane,
  because b̂3 points down),
* range     δ = ‖c‖ [m].

Decisions where the paper is silent or wrong (also in docs/papers.md):

* Eq. 31 is inconsistent with eq. 45 (its first row is an elevation and its second uses
  atan(c1/c2)).  jaxslam uses the model that eq. 44-45 invert (errata in the papers README):
  the three rows above, in the order y = [α, β, δ] of Sec. 2.3.3.
* atan2 (not atan) keeps the azimuth right in all four quadrants; the elevation uses atan2 of
  the horizontal range so its derivative stays finite up to ±90°.
* Norms are ``jaxslam.linalg.safe_norm``'s, of the vector scaled by the power of two at or
  below its largest entry (exact; the squares then never overflow or underflow), and the angles use double-``where`` guards: the model is
  smooth wherever δ > 0 and the landmark is not straight above/below the sensor (c1 = c2 = 0,
  where the azimuth is undefined).  At those degenerate points the undefined angle reads 0 with
  zero partials, so values and Jacobians stay finite (the range keeps its true gradient
  wherever δ > 0).
* FOV (Table 4) boundaries are **inclusive**: a landmark exactly at ±45° azimuth, ±30°
  elevation or at 0 m / 100 m is visible.  :func:`in_fov` compares in the measurement's dtype.
* Table 4 σ's are standard deviations of independent Gaussian noise on α, β, δ.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import check_last_dim, real_float
from ..errors import InputError
from ..geometry.euler import _last_axis, dcm_from_euler, rotate_jacobian, unrotate_jacobian
from ..linalg import (check_float_dtype, check_numbers, check_real, check_shape, is_concrete, pow2_factors, safe_norm,
                      wrap_angle)

__all__ = [
    "LidarSpec",
    "PAPER000_LIDAR",
    "check_lidar_spec",
    "spherical_from_cartesian",
    "cartesian_from_spherical",
    "measure",
    "measure_state",
    "measure_state_and_jacobians",
    "inverse_state_and_jacobians",
    "inverse",
    "inverse_state",
    "in_fov",
    "measure_all",
    "innovation",
    "measurement_cov",
    "sample_noise",
]


class LidarSpec(NamedTuple):
    """LiDAR field of view and noise (paper 000 Table 4).  Angles in rad, ranges in m.

    Fields may be Python floats or scalar arrays.
    """

    az_min: Any = -math.pi / 4
    """Azimuth FOV lower bound [rad]; Table 4: −45°."""
    az_max: Any = math.pi / 4
    """Azimuth FOV upper bound [rad]; Table 4: +45°."""
    el_min: Any = -math.pi / 6
    """Elevation FOV lower bound [rad]; Table 4: −30° (above the body x-y plane)."""
    el_max: Any = math.pi / 6
    """Elevation FOV upper bound [rad]; Table 4: +30° (below the body x-y plane)."""
    range_min: Any = 0.0
    """Minimum range [m]; Table 4: 0 m."""
    range_max: Any = 100.0
    """Maximum range [m]; Table 4: 100 m."""
    sigma_az: Any = math.radians(0.33)
    """Azimuth noise std σ_α [rad]; Table 4: 0.33°."""
    sigma_el: Any = math.radians(0.3)
    """Elevation noise std σ_β [rad]; Table 4: 0.3°."""
    sigma_range: Any = 0.1
    """Range noise std σ_δ [m]; Table 4: 0.1 m."""
    rate: Any = 10.0
    """Sampling rate [Hz]; Table 4: 10 Hz."""


PAPER000_LIDAR = LidarSpec()
"""Paper 000 Table 4: FOV ±45° × ±30°, range [0, 100] m, σ = (0.33°, 0.3°, 0.1 m), 10 Hz."""


def check_lidar_spec(spec: LidarSpec, name: str = "spec") -> LidarSpec:
    """Host-side validation (before jit): finite scalars, min ≤ max, σ ≥ 0, rate > 0.

    Raises :class:`~jaxslam.errors.InputError` naming the field.
    """
    if not isinstance(spec, LidarSpec):
        raise InputError(f"{name}: expected a LidarSpec, got {type(spec).__name__}")
    vals = {}
    for f in LidarSpec._fields:
        v = check_numbers(getattr(spec, f), f"{name}.{f}")
        if v.shape != ():
            raise InputError(f"{name}.{f}: expected a scalar, got shape {v.shape}")
        if not np.isfinite(v):
            raise InputError(f"{name}.{f}: must be finite, got {v}")
        vals[f] = float(v)
    for lo, hi in (("az_min", "az_max"), ("el_min", "el_max"), ("range_min", "range_max")):
        if vals[lo] > vals[hi]:
            raise InputError(f"{name}.{lo}: {vals[lo]} exceeds {name}.{hi} = {vals[hi]}")
    for f in ("sigma_az", "sigma_el", "sigma_range"):
        if vals[f] < 0:
            raise InputError(f"{name}.{f}: must be >= 0, got {vals[f]}")
    if vals["rate"] <= 0:
        raise InputError(f"{name}.rate: must be > 0, got {vals['rate']}")
    if vals["el_min"] < -math.pi / 2 or vals["el_max"] > math.pi / 2:
        raise InputError(f"{name}.el_min/el_max: elevation bounds must lie in [-pi/2, pi/2]")
    return spec


# ---------------------------------------------------------------------------
# Spherical <-> Cartesian (shared with range_bearing3d)
# ---------------------------------------------------------------------------

def _scaled_norm(x):
    """``(‖x‖, x·2^−e, (2^−e as two factors, 2^e))`` over the last axis, 2^e the power of two at or below max|xᵢ|
    (:func:`jaxslam.linalg.pow2_factors`).  The sum of squares is taken on the scaled vector,
    whose largest entry lies in [1, 2), so it neither overflows nor underflows for any finite x
    (in float32 a 1e20 m vector read an infinite range, a 1e-25 m one a zero range); scaling by
    a power of two is exact, so ordinary vectors give the bits of the plain form.  Zero (and
    subnormal: XLA flushes them) gives 0 with zero partials, NaN or Inf entries NaN or Inf, as
    :func:`jaxslam.linalg.safe_norm`.  The scale carries no derivative, so every partial is
    formed from x·2^−e and stays finite."""
    d1, d2, up = pow2_factors(jnp.max(jnp.abs(x), axis=-1))
    u = x * d1[..., None] * d2[..., None]
    return safe_norm(u) * up, u, (d1, d2, up)


_FLOOR = 16.0
"""Shortest vector whose angles :func:`spherical_from_cartesian` evaluates, in units of
``finfo.tiny``; a shorter one leaves them undefined (read 0, zero partials): their derivatives
(~1/length) would overflow."""


def spherical_from_cartesian(c):
    """[α, β, δ] of a vector c (paper 000 eq. 31 per errata; paper 001 eq. 13).

    Args: c: (..., 3) Cartesian vector [m] (an integer one is read as JAX's default float).
    Returns: (..., 3) [atan2(c2, c1), atan2(c3, √(c1²+c2²)), ‖c‖].  The norms and angles are
    evaluated on c scaled by a power of two (exact: an ordinary vector gives the plain form's
    bits), so they stay right from 16 times the smallest normal number to the largest finite
    one, also where the squares of c would overflow or underflow (float32 beyond ~1e19 m or
    below ~1e-19 m); below 16 times the smallest normal number the angles read 0.
    """
    c = real_float(c, "c")
    c = _last_axis(c, 3, "c")  # a (2,) vector read its third entry from a clamped index
    floor = _FLOOR * jnp.finfo(c.dtype).tiny
    horiz, uh, (_, _, up_h) = _scaled_norm(c[..., :2])
    rng, ur, (d1, d2, _) = _scaled_norm(c)
    # Double-where guards: where an angle is undefined (c1 = c2 = 0 for α, c = 0 for β) it is
    # evaluated as atan2(0, 1) = 0, so no NaN partials leak into the range's gradient.  The
    # angles are scale-free: atan2 of the scaled vector (ur's scale also applied to the
    # horizontal norm, taken from its own scaled form so that it cannot overflow).
    has_h = horiz >= floor
    has_r = rng >= floor
    az = jnp.arctan2(jnp.where(has_h, uh[..., 1], 0.0), jnp.where(has_h, uh[..., 0], 1.0))
    hr = safe_norm(uh) * (up_h * d1 * d2)  # 2^(e_h − e) ≤ 1: exact, and no overflowed horiz
    el = jnp.arctan2(jnp.where(has_r, ur[..., 2], 0.0), jnp.where(has_r, hr, 1.0))
    return jnp.stack([az, el, rng], axis=-1)


def cartesian_from_spherical(y):
    """ϱ(y) = δ [cos β cos α, cos β sin α, sin β] (paper 000 eq. 45; paper 001 eq. 15).

    Args: y: (..., 3) [α rad, β rad, δ m].  Returns: (..., 3) [m].
    """
    check_real(y, "y")
    y = _last_axis(y, 3, "y")
    az, el, rng = y[..., 0], y[..., 1], y[..., 2]
    ce = jnp.cos(el)
    return jnp.stack([rng * ce * jnp.cos(az), rng * ce * jnp.sin(az), rng * jnp.sin(el)], axis=-1)


# ---------------------------------------------------------------------------
# Measurement model and inverse
# ---------------------------------------------------------------------------

def measure(pos, euler, landmark):
    """LiDAR measurement h_o (paper 000 eq. 30-31, corrected per errata).

    Args:
      pos: (3,) quadcopter position ρ in N (NED) [m].
      euler: (3,) Λ = (φ, θ, ψ) [rad], 3-2-1.
      landmark: (3,) or (L, 3) landmark position(s) l in N [m].

    Returns:
      (3,) or (L, 3) y = [α, β, δ] [rad, rad, m] with c = C_NBᵀ(l − ρ) (module docstring).
    """
    pos = real_float(pos, "pos", (3,))  # lists are converted (``list - list`` was a TypeError)
    euler = real_float(euler, "euler", (3,))
    if np.ndim(landmark) not in (1, 2) or np.shape(landmark)[-1] != 3:
        raise InputError(f"landmark: expected shape (3,) or (L, 3), got {np.shape(landmark)}")
    landmark = real_float(landmark, "landmark")
    C = dcm_from_euler(euler)
    # Row-vector form d @ C equals (C_NBᵀ d)ᵀ for every landmark at once.
    c = (landmark - pos) @ C
    return spherical_from_cartesian(c)


def _state(s, name="s"):
    """``s`` as a real floating (9,) or (12,) array (a list is converted, a complex one refused)."""
    if np.ndim(s) != 1 or np.shape(s)[0] not in (9, 12):
        raise InputError(f"{name}: expected shape (9,) or (12,), got {np.shape(s)}")
    return real_float(s, name)


def _split_state(s, name="s"):
    s = _state(s, name)
    return s[0:3], s[6:9]


def measure_state(s, landmark):
    """h_o(s, l) of paper 000 eq. 30 on the EKF state s = [ρ (3), v_B (3), Λ (3)].

    Args:
      s: (9,) EKF state (eq. 24); a (12,) state (eq. 2) is accepted too.  Only ρ and Λ are
        read, so ∂h/∂v_B = 0 (and ∂h/∂ω = 0).
      landmark: (3,) l in N [m].

    Returns: (3,) [α, β, δ].  Differentiable in s and l (``jax.jacfwd`` gives H of eq. 40).
    """
    pos, euler = _split_state(s)
    check_shape(landmark, (3,), "landmark")
    return measure(pos, euler, landmark)


def measure_state_and_jacobians(s, landmark):
    """h_o(s, l) with H_s = ∂h/∂s (3, 9) and H_l = ∂h/∂l (3, 3) in closed form (paper 000 eq. 40).

    With d = l − ρ, c = C_NBᵀ d, h = ‖c₁,₂‖, r = ‖c‖ and a = C₁(φ)ᵀ e₂ = [0, cφ, −sφ]:

        J = ∂y/∂c = [[−c₂/h², c₁/h², 0], [−c₁c₃/(h r²), −c₂c₃/(h r²), h/r²], cᵀ/r]
        H_l = J Cᵀ,  H_ρ = −H_l,  H_v = 0,  H_Λ = J [c × e₁,  c × a,  Cᵀ [d₂, −d₁, 0]]

    Where an angle is undefined (h = 0, r = 0) its row is zero, as autodiff of the guarded
    :func:`spherical_from_cartesian` gives.  Equal to ``jax.jacfwd`` of :func:`measure_state`
    (tests); the engine's update uses it (``SlamModel.observe_jacobian``) because a gradient
    through the filter differentiates H, and the closed form's derivatives take far fewer
    kernels than autodiff's.  s: (9,) (or (12,)); landmark: (3,).  Returns (y, H_s, H_l).
    """
    s = _state(s)
    pos, euler = _split_state(s)
    landmark = real_float(landmark, "landmark", (3,))
    C = dcm_from_euler(euler)
    d = landmark - pos
    c = d @ C  # Cᵀ d, as measure() forms it
    y = spherical_from_cartesian(c)
    # J from c scaled by a power of two, u = c·2^−e (as spherical_from_cartesian's values: the
    # squares of c overflow or underflow beyond ~1e19 m or below ~1e-19 m in float32); the angle
    # rows scale back by 2^−e (degree −1 in c), the range row is u/‖u‖.  For ordinary c equal to
    # the unscaled form to rounding (~1 ulp: XLA fuses the two differently), not bit for bit.
    _, u, (d1, d2, _) = _scaled_norm(c)
    c1, c2, c3 = u[0], u[1], u[2]
    h2 = c1 * c1 + c2 * c2
    r2 = h2 + c3 * c3
    h2s = jnp.where(h2 > 0, h2, 1.0)
    r2s = jnp.where(r2 > 0, r2, 1.0)
    hs, rs = jnp.sqrt(h2s), jnp.sqrt(r2s)
    t = c3 / (hs * r2s)
    z = jnp.zeros_like(c1)
    J = jnp.stack([jnp.stack([-c2 / h2s, c1 / h2s, z]) * d1 * d2,
                   jnp.stack([-c1 * t, -c2 * t, jnp.where(h2 > 0, hs, 0.0) / r2s]) * d1 * d2,
                   u / rs])
    Hl = jnp.sum(J[:, None, :] * C[None, :, :], axis=-1)  # J Cᵀ
    dc = unrotate_jacobian(euler, d, C)
    Ha = jnp.sum(J[:, :, None] * dc[None, :, :], axis=1)
    Hs = jnp.concatenate([-Hl, jnp.zeros((3, 3), Hl.dtype), Ha] + ([jnp.zeros((3, 3), Hl.dtype)] if s.shape[0] == 12 else []),
                         axis=1)
    return y, Hs, Hl


def inverse(pos, euler, y):
    """Inverse observation model l = g(s, y) = C_NB ϱ(y) + ρ (paper 000 eq. 44-45).

    Args:
      pos: (3,) ρ [m].  euler: (3,) Λ [rad].  y: (3,) or (L, 3) [α, β, δ].

    Returns: (3,) or (L, 3) landmark position(s) in N [m].
    """
    pos = real_float(pos, "pos", (3,))
    euler = real_float(euler, "euler", (3,))
    if np.ndim(y) not in (1, 2) or np.shape(y)[-1] != 3:
        raise InputError(f"y: expected shape (3,) or (L, 3), got {np.shape(y)}")
    y = real_float(y, "y")
    C = dcm_from_euler(euler)
    return cartesian_from_spherical(y) @ C.T + pos


def inverse_state_and_jacobians(s, y):
    """g(s, y) of paper 000 eq. 44 with G_s = ∂g/∂s (3, 9) and G_y = ∂g/∂y (3, 3) in closed form
    (eq. 49): with ϱ = δ [cβ cα, cβ sα, sβ],

        G_ρ = I,  G_v = 0,  G_Λ = ∂(C ϱ)/∂Λ (``geometry.euler.rotate_jacobian``),
        G_y = C [δ cβ [−sα, cα, 0],  δ [−sβ cα, −sβ sα, cβ],  [cβ cα, cβ sα, sβ]]  (columns)

    Equal to ``jax.jacfwd`` of :func:`inverse_state` (tests); the engine's registration uses it
    (``SlamModel.inverse_jacobian``).  s: (9,) (or (12,)); y: (3,).  Returns (l, G_s, G_y).
    """
    s = _state(s)
    pos, euler = _split_state(s)
    y = real_float(y, "y", (3,))
    C = dcm_from_euler(euler)
    rho = cartesian_from_spherical(y)
    l = rho @ C.T + pos
    sa, ca = jnp.sin(y[0]), jnp.cos(y[0])
    sb, cb = jnp.sin(y[1]), jnp.cos(y[1])
    r = y[2]
    z = jnp.zeros_like(sa)
    drho = jnp.stack([jnp.stack([-r * cb * sa, -r * sb * ca, cb * ca]),
                      jnp.stack([r * cb * ca, -r * sb * sa, cb * sa]),
                      jnp.stack([z, r * cb, sb])])
    Gy = jnp.sum(C[:, :, None] * drho[None, :, :], axis=1)
    eye = jnp.eye(3, dtype=Gy.dtype)
    z3 = jnp.zeros((3, 3), Gy.dtype)
    Gs = jnp.concatenate([eye, z3, rotate_jacobian(euler, rho, C)] + ([z3] if s.shape[0] == 12 else []), axis=1)
    return l, Gs, Gy


def inverse_state(s, y):
    """g(s, y_l) of paper 000 eq. 44 on the EKF state s (9,) (or (12,)); y (3,).

    Returns (3,) l in N [m].  ``jax.jacfwd`` w.r.t. s and y gives G_s, G_l of eq. 49.
    """
    pos, euler = _split_state(s)
    check_shape(y, (3,), "y")
    return inverse(pos, euler, y)


# ---------------------------------------------------------------------------
# Field of view, noise
# ---------------------------------------------------------------------------

def in_fov(y, spec: LidarSpec = PAPER000_LIDAR):
    """Visibility mask of measurement(s) y under the FOV of Table 4 (inclusive bounds).

    Args: y: (..., 3) [α, β, δ].  spec: :class:`LidarSpec`.
    Returns: (...,) bool, True where az_min ≤ α ≤ az_max, el_min ≤ β ≤ el_max and
    range_min ≤ δ ≤ range_max (bounds cast to y's dtype, so a measurement equal to a bound
    after rounding counts as visible).
    """
    if np.shape(y)[-1:] != (3,):
        raise InputError(f"y: expected shape (..., 3), got {np.shape(y)}")
    check_real(y, "y")
    if is_concrete(tuple(spec)):
        check_lidar_spec(spec)  # an inverted spec (az_min > az_max) hid every landmark
    y = jnp.asarray(y)
    dt = y.dtype

    def within(v, lo, hi):
        return (v >= jnp.asarray(lo, dt)) & (v <= jnp.asarray(hi, dt))

    return (within(y[..., 0], spec.az_min, spec.az_max)
            & within(y[..., 1], spec.el_min, spec.el_max)
            & within(y[..., 2], spec.range_min, spec.range_max))


def measure_all(pos, euler, landmarks, spec: LidarSpec = PAPER000_LIDAR):
    """Noise-free measurements of every landmark and their visibility (paper 000 Sec. 2.3.3).

    Args:
      pos: (3,) ρ [m].  euler: (3,) Λ [rad].  landmarks: (L, 3) in N [m].
      spec: :class:`LidarSpec` (FOV).

    Returns: (y (L, 3) [α, β, δ], visible (L,) bool).  y is returned for every landmark;
    callers mask with ``visible``.
    """
    check_shape(landmarks, (None, 3), "landmarks")
    y = measure(pos, euler, landmarks)
    return y, in_fov(y, spec)


def innovation(y, y_pred):
    """Measurement residual y − ŷ with the azimuth wrapped to [−π, π) (for EKF updates).

    Args: y, y_pred: (..., 3) [α, β, δ].  Returns (..., 3).  Elevation lies in [−π/2, π/2]
    and range is not periodic, so only α is wrapped.
    """
    y = check_last_dim(real_float(y, "y"), 3, "y")  # lists are converted; a (2,) residual refused
    y_pred = check_last_dim(real_float(y_pred, "y_pred"), 3, "y_pred")
    r = y - y_pred
    return jnp.concatenate([wrap_angle(r[..., :1]), r[..., 1:]], axis=-1)  # no scatter (vmapped)


def measurement_cov(spec: LidarSpec = PAPER000_LIDAR, dtype=None):
    """R_ζ = diag(σ_α², σ_β², σ_δ²) (paper 000 eq. 30, Table 4), shape (3, 3)."""
    dtype = jnp.result_type(float) if dtype is None else check_float_dtype(dtype)  # an int dtype made zeros
    sig = (spec.sigma_az, spec.sigma_el, spec.sigma_range)
    if is_concrete(sig):  # the usual case: built on the host, no program to compile
        check_lidar_spec(spec)  # a negative σ gave the same R as its absolute value, NaN a NaN R
        s = np.asarray(sig, np.float64)
        return jnp.asarray(np.diag(s * s), dtype)
    s = jnp.stack([jnp.asarray(v, dtype) for v in sig])
    return jnp.diag(s * s)


def sample_noise(key, spec: LidarSpec = PAPER000_LIDAR, shape_prefix=(), dtype=None):
    """Gaussian measurement noise ζ ~ N(0, R_ζ) (paper 000 eq. 30, Table 4).

    Args: key: PRNG key.  shape_prefix: static leading shape.  dtype: float dtype (default
    JAX's default float).
    Returns: (*shape_prefix, 3) with stds (σ_α rad, σ_β rad, σ_δ m).
    """
    dtype = jnp.result_type(float) if dtype is None else check_float_dtype(dtype)  # an int dtype made zeros
    if is_concrete(tuple(spec)):
        check_lidar_spec(spec)
    s = jnp.stack([jnp.asarray(spec.sigma_az, dtype), jnp.asarray(spec.sigma_el, dtype),
                   jnp.asarray(spec.sigma_range, dtype)])
    shape = tuple(int(d) for d in shape_prefix) + (3,)
    # Flat draw + reshape: XLA on CPU compiles it several times faster than an (N, 3) draw.
    return jax.random.normal(key, (int(np.prod(shape)),), dtype).reshape(shape) * s
