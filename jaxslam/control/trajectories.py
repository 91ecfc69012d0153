"""Reference trajectories as flat outputs y = [x, y, z, ψ] (NED) and their time derivatives.

Paper 000 (Sec. 2.2.1, eq. 4-5) flies a figure-8; paper 001 (Sec. IV-B) a helix about the
z axis; paper 003 (Sec. IV-A/B) a circle and a square.  None of the papers gives every
number, so each container below documents the value jaxslam chose.

Every container is a ``typing.NamedTuple`` of numbers (pytree leaves), so
:func:`flat_output` is jit-able in ``t`` *and* in the container's numeric fields (a change of
radius or period never recompiles).  Dispatch is on the container's Python type (each class
implements ``_position_yaw``).  Derivatives are never written by hand:
:func:`flat_derivatives` nests ``jax.jacfwd`` in ``t``.

Frames and units: positions in metres in the inertial NED frame N (z points down, so an
altitude h is z = −h), yaw ψ in radians about n̂3 (0 = nose north), time t in seconds.

Decisions (papers silent or incomplete):

* **Figure-8** (paper 000 gives no size, period or altitude): a Gerono-type lemniscate
  x = x_c + a_x sin(ωt), y = y_c + a_y sin(2ωt), z = z_c, ω = 2π/period, with a_x = 5 m,
  a_y = 2.5 m, altitude 5 m (z_c = −5), period 25 s (the paper's 50 s flight = two loops).
  Peak speed 1.8 m/s, peak horizontal acceleration 0.67 m/s² (tilt ≈ 3.9°).
  Heading is fixed at ψ0 = 0 by default; ``heading_along_path = 1`` adds the tangent angle
  atan2(ẏ, ẋ) of the (un-blended) lemniscate, which never has zero speed.  That heading is
  wrapped to (−π, π] by atan2 and therefore jumps by 2π where the tangent points south; the
  controller wraps the ψ error, and the derivatives (from jacfwd) are the smooth ones.
* **Take-off blend** (paper 000: "the quadcopter is set at the origin and controlled to
  achieve the trajectory"): every container has ``start`` (3,) and ``ramp_time`` T_r.  The
  position is p(t) = start + s(t/T_r) (p_path(t) − start), where s is the C⁴ smoothstep
  126x⁵ − 420x⁶ + 540x⁷ − 315x⁸ + 70x⁹ (x clipped to [0, 1]); so the reference starts at rest
  at ``start`` and equals the path exactly for t ≥ T_r, and its derivatives up to snap (what
  the flatness feedforward torques need) are continuous.  The yaw is not blended.  T_r = 0
  disables the blend (the figure-8 default is T_r = 8 s from the origin; the others 0).
* **Helix** (paper 001 gives no numbers; 4 poles at (±2, ±2)): radius 1 m about the z axis,
  period 20 s, starting at 0.5 m altitude and climbing 0.03 m/s (1.5 m in 50 s), fixed yaw.
  Paper 001 writes z up; jaxslam is NED, so climbing is z decreasing.
* **Circle** (paper 003 scenario I): [1.5 cos(0.1t), 1.5 sin(0.1t)], yaw rate 0.2 sin(0.1t),
  i.e. ψ = ψ0 + (0.2/0.1)(1 − cos 0.1t).  Paper 003 is planar; altitude chosen 1 m (z = −1).
* **Square** (paper 003 scenario II gives no side or speed; its lab rectangle is
  1.5 m × 1.8 m): a smooth square x = h tanh(k cos θ)/tanh k, y = h tanh(k sin θ)/tanh k,
  θ = 2πt/period, half side h = 1.5 m, sharpness k = 3 (corners at 97 % of h, infinitely
  differentiable; the path slows in the corners as a real square flight does), period 60 s,
  altitude 1 m.  k → ∞ gives the sharp square.  Paper 003's staged roll/pitch motion cannot be
  imposed on a quadcopter through flat outputs (roll and pitch follow from the acceleration);
  only a constant yaw rate is offered.
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import is_concrete

__all__ = [
    "Figure8",
    "Helix",
    "Circle",
    "Square",
    "flat_output",
    "flat_derivatives",
]

Vec3 = Tuple[float, float, float]


def _float_dtype(traj, t):
    """Working dtype: that of t and the container's array fields (Python floats are weak)."""
    dt = jnp.result_type(t, *jax.tree_util.tree_leaves(traj))
    if not jnp.issubdtype(dt, jnp.floating):
        dt = jnp.result_type(float)
    return dt


def _vec(v, dtype):
    """(3,) array from a tuple of (possibly traced) scalars or an array."""
    if isinstance(v, (tuple, list)):
        return jnp.stack([jnp.asarray(c, dtype=dtype) for c in v])
    return jnp.asarray(v, dtype=dtype)


def _smoothstep9(x):
    """C⁴ smoothstep on [0, 1]: s(0)=0, s(1)=1, derivatives 1..4 vanish at both ends."""
    x = jnp.clip(x, 0.0, 1.0)
    return x ** 5 * (126.0 + x * (-420.0 + x * (540.0 + x * (-315.0 + 70.0 * x))))


def _blend(start, ramp_time, t, p):
    """start + s(t/T_r)(p − start); exactly p when T_r ≤ 0 (no blend)."""
    has_ramp = ramp_time > 0
    x = t / jnp.where(has_ramp, ramp_time, 1.0)
    s = jnp.where(has_ramp, _smoothstep9(x), 1.0)
    return start + s * (p - start)


class Figure8(NamedTuple):
    """Figure-8 (Gerono lemniscate) at constant altitude; paper 000's '8' trajectory.

    x = c_x + a_x sin(ωt), y = c_y + a_y sin(2ωt), z = c_z, ω = 2π/period (NED, metres),
    blended from ``start`` over ``ramp_time`` (module docstring).  Values are jaxslam's
    choices (paper 000 gives none).
    """

    center: Vec3 = (0.0, 0.0, -5.0)  # (3,) m, NED centre (crossing point); z = −altitude
    a_x: float = 5.0  # m, half extent along n̂1 (north)
    a_y: float = 2.5  # m, half extent along n̂2 (east)
    period: float = 25.0  # s, one full '8'
    psi0: float = 0.0  # rad, fixed heading (or offset added to the path tangent)
    heading_along_path: float = 0.0  # 0: ψ = ψ0 fixed; 1: ψ = ψ0 + atan2(ẏ, ẋ)
    start: Vec3 = (0.0, 0.0, 0.0)  # (3,) m, NED start point of the take-off blend
    ramp_time: float = 8.0  # s, take-off blend duration (0 disables)

    def _position_yaw(self, t, dtype):
        c = _vec(self.center, dtype)
        w = 2.0 * jnp.pi / jnp.asarray(self.period, dtype)
        ax = jnp.asarray(self.a_x, dtype)
        ay = jnp.asarray(self.a_y, dtype)

        def path(tt):
            return c + jnp.stack([ax * jnp.sin(w * tt), ay * jnp.sin(2.0 * w * tt),
                                  jnp.zeros_like(tt)])

        p, v = jax.jvp(path, (t,), (jnp.ones_like(t),))
        # double where: at zero speed (a_x = a_y = 0) arctan2's derivative is NaN, and
        # 0 × NaN = NaN even with heading_along_path = 0; there the tangent is 0
        moving = (v[0] != 0) | (v[1] != 0)
        tangent = jnp.where(moving, jnp.arctan2(jnp.where(moving, v[1], 0.0),
                                                jnp.where(moving, v[0], 1.0)), 0.0)
        psi = jnp.asarray(self.psi0, dtype) + jnp.asarray(self.heading_along_path, dtype) * tangent
        p = _blend(_vec(self.start, dtype), jnp.asarray(self.ramp_time, dtype), t, p)
        return p, psi


class Helix(NamedTuple):
    """Helix about the n̂3 axis; paper 001 Sec. IV-B (numbers are jaxslam's choices).

    x = c_x + R cos(ωt), y = c_y + R sin(ωt), z = c_z − v_c t (climbing, NED),
    ψ = ψ0 + ψ̇ t, ω = 2π/period.
    """

    center: Vec3 = (0.0, 0.0, -0.5)  # (3,) m, NED axis point at t = 0 (0.5 m altitude)
    radius: float = 1.0  # m
    period: float = 20.0  # s per turn (north → east, i.e. clockwise seen from above)
    climb_rate: float = 0.03  # m/s upward (z decreases)
    psi0: float = 0.0  # rad
    yaw_rate: float = 0.0  # rad/s, constant
    start: Vec3 = (0.0, 0.0, 0.0)  # (3,) m, blend start (unused when ramp_time = 0)
    ramp_time: float = 0.0  # s, 0: no take-off blend

    def _position_yaw(self, t, dtype):
        c = _vec(self.center, dtype)
        w = 2.0 * jnp.pi / jnp.asarray(self.period, dtype)
        R = jnp.asarray(self.radius, dtype)
        p = c + jnp.stack([R * jnp.cos(w * t), R * jnp.sin(w * t),
                           -jnp.asarray(self.climb_rate, dtype) * t])
        psi = jnp.asarray(self.psi0, dtype) + jnp.asarray(self.yaw_rate, dtype) * t
        p = _blend(_vec(self.start, dtype), jnp.asarray(self.ramp_time, dtype), t, p)
        return p, psi


class Circle(NamedTuple):
    """Circle of paper 003 scenario I: [1.5 cos(0.1t), 1.5 sin(0.1t)], ψ̇ = 0.2 sin(0.1t).

    x = c_x + R cos(ωt), y = c_y + R sin(ωt), z = c_z,
    ψ = ψ0 + (a_ψ/ω_ψ)(1 − cos ω_ψ t) so that ψ̇ = a_ψ sin(ω_ψ t).
    """

    center: Vec3 = (0.0, 0.0, -1.0)  # (3,) m, NED (altitude 1 m: jaxslam's choice)
    radius: float = 1.5  # m (paper 003)
    omega: float = 0.1  # rad/s (paper 003)
    yaw_amp: float = 0.2  # rad/s, amplitude of the yaw rate (paper 003)
    yaw_omega: float = 0.1  # rad/s, frequency of the yaw rate (paper 003)
    psi0: float = 0.0  # rad
    start: Vec3 = (0.0, 0.0, 0.0)  # (3,) m
    ramp_time: float = 0.0  # s

    def _position_yaw(self, t, dtype):
        c = _vec(self.center, dtype)
        w = jnp.asarray(self.omega, dtype)
        R = jnp.asarray(self.radius, dtype)
        p = c + jnp.stack([R * jnp.cos(w * t), R * jnp.sin(w * t), jnp.zeros_like(t)])
        wy = jnp.asarray(self.yaw_omega, dtype)
        ay = jnp.asarray(self.yaw_amp, dtype)
        # (1 − cos w t)/w → w t²/2 as w → 0; double where keeps gradients finite.
        small = jnp.abs(wy) < 1e-6
        wy_safe = jnp.where(small, 1.0, wy)
        integ = jnp.where(small, 0.5 * wy * t * t, (1.0 - jnp.cos(wy_safe * t)) / wy_safe)
        psi = jnp.asarray(self.psi0, dtype) + ay * integ
        p = _blend(_vec(self.start, dtype), jnp.asarray(self.ramp_time, dtype), t, p)
        return p, psi


class Square(NamedTuple):
    """Smooth square of paper 003 scenario II (size, speed and rounding are jaxslam's).

    x = c_x + h tanh(k cos θ)/tanh k, y = c_y + h tanh(k sin θ)/tanh k, z = c_z,
    θ = 2πt/period; ψ = ψ0 + ψ̇ t.
    """

    center: Vec3 = (0.0, 0.0, -1.0)  # (3,) m, NED
    half_side: float = 1.5  # m
    period: float = 60.0  # s per lap
    sharpness: float = 3.0  # k (dimensionless); larger = sharper corners
    psi0: float = 0.0  # rad
    yaw_rate: float = 0.0  # rad/s
    start: Vec3 = (0.0, 0.0, 0.0)  # (3,) m
    ramp_time: float = 0.0  # s

    def _position_yaw(self, t, dtype):
        c = _vec(self.center, dtype)
        th = 2.0 * jnp.pi / jnp.asarray(self.period, dtype) * t
        h = jnp.asarray(self.half_side, dtype)
        k = jnp.asarray(self.sharpness, dtype)
        scale = h / jnp.tanh(k)
        p = c + jnp.stack([scale * jnp.tanh(k * jnp.cos(th)), scale * jnp.tanh(k * jnp.sin(th)),
                           jnp.zeros_like(th)])
        psi = jnp.asarray(self.psi0, dtype) + jnp.asarray(self.yaw_rate, dtype) * t
        p = _blend(_vec(self.start, dtype), jnp.asarray(self.ramp_time, dtype), t, p)
        return p, psi


_TRAJECTORIES = (Figure8, Helix, Circle, Square)
_POSITIVE = ("period", "sharpness")  # fields that divide: must be > 0 (radius etc. may be 0)


def _check_fields(traj) -> None:
    """A container's concrete numeric fields: finite, and ``period`` / ``sharpness`` > 0
    (:class:`InputError` naming the field; a zero period made every reference NaN).  Traced
    fields (a tuned radius under ``jit``) are not checked."""
    if not hasattr(traj, "_position_yaw"):
        raise TypeError(f"traj: expected one of {[c.__name__ for c in _TRAJECTORIES]}, "
                        f"got {type(traj).__name__}")
    if not isinstance(traj, _TRAJECTORIES):
        return
    name = type(traj).__name__
    for field, v in zip(traj._fields, traj):
        if not is_concrete(v):
            continue
        a = np.asarray(v, dtype=float)
        if a.shape not in ((), (3,)):
            raise InputError(f"{name}.{field}: expected a number{' or 3 numbers' if field in ('center', 'start') else ''}, "
                             f"got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name}.{field}: must be finite, got {v!r}")
        if field in _POSITIVE and not np.all(a > 0):
            raise InputError(f"{name}.{field}: must be > 0, got {v!r}")


def flat_output(traj, t):
    """Flat output y_d(t) = [x, y, z, ψ] of a trajectory container (paper 000 eq. 4-5).

    ``traj``: a :class:`Figure8`, :class:`Helix`, :class:`Circle` or :class:`Square`
    (or any object with a ``_position_yaw(t, dtype) -> ((3,), ())`` method).
    ``t``: scalar time in s.  Returns (4,): NED position in m and yaw in rad, in the dtype
    of ``t`` and the container's array fields (Python floats follow ``t``).
    Jit-able in ``t`` and in the container's numeric fields.
    """
    _check_fields(traj)
    return _flat_output(traj, t)


def _flat_output(traj, t):
    dtype = _float_dtype(traj, t)
    t = jnp.asarray(t, dtype)
    p, psi = traj._position_yaw(t, dtype)
    return jnp.concatenate([p, psi[None]]).astype(dtype)


def flat_derivatives(traj, t, order: int):
    """Flat output and its time derivatives up to ``order`` by nested forward-mode autodiff.

    Paper 000 eq. 4-5 need y, ẏ, ÿ; the flatness feedforward (body rates and torques) needs
    up to the 4th derivative (snap).  ``order`` is a static Python int ≥ 0.  Each level is
    ``jax.jvp`` (= ``jax.jacfwd`` for scalar t) of the previous level, so the cost grows as
    2^order evaluations of the flat output; jit the caller (eager nesting is slow).
    Returns (order + 1, 4): row k is d^k/dt^k [x, y, z, ψ] (units m/s^k and rad/s^k).
    """
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 0:
        raise InputError(f"order: must be an int >= 0 (static), got {order!r}")
    order = int(order)
    _check_fields(traj)
    dtype = _float_dtype(traj, t)
    t = jnp.asarray(t, dtype)
    # Cast the (t-independent) fields once, so the 2^order nested evaluations do not repeat it.
    traj = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), traj)

    def f(tt):  # fields checked above
        return _flat_output(traj, tt)[None]

    # D_k(t) = [y, y', ..., y^(k)] = [y, jacfwd(D_{k-1})(t)]; the primal of the forward-mode
    # pass already holds y, so each level is one jvp of the previous one.
    def make(k):
        if k == 0:
            return f
        prev = make(k - 1)

        def dk(tt):
            primal, tangent = jax.jvp(prev, (tt,), (jnp.ones_like(tt),))
            return jnp.concatenate([primal[0:1], tangent], axis=0)

        return dk

    return make(order)(t)
