"""Planar paths and attitude-rate profiles of paper 003's simulations (Sec. IV-A, B, C).

Paper 003 simulates a drone that flies "almost as a hovercraft": a planar
position path and, independently of it, an attitude (roll α, pitch β, yaw θ)
driven by prescribed angular rates ("situations where the drone's orientation
was independent of its speed were considered").  A planar truth state is

    s = [x, y, v_x, v_y, α, β, θ, w_α, w_β, w_θ]      (m, m/s, rad, rad/s)

Paths (all jit-able in ``t`` and in their numeric fields; velocities come from
``jax.jvp`` in time, never by hand):

* :class:`CirclePath` — scenario I: wraps :class:`jaxslam.control.trajectories.Circle`
  (x, y of its flat output and its yaw ψ = θ, whose rate is 0.2 sin(0.1 t)); roll
  and pitch are 0.  The NED z of the 3D container is dropped.
* :class:`PolylinePath` — straight segments between timed waypoints (constant
  speed per segment, the velocity jumps at a waypoint: scenario II's square and
  III's rough path violate the constant-velocity model on purpose), plus an
  optional lateral sinusoid inside a time window (III's "twists").
* :class:`RateProfile` — piecewise-constant angular rates on time intervals plus
  a sinusoid per axis; the angles are the exact integrals from t = 0 (so the
  attitude at t = 0 is zero: the filter's attitude reference is the attitude at
  the start of the EKF, paper 003 Sec. III-D-1).

Decisions: the papers give no square size, speed, or rough-path geometry; the
scenario module states the values it uses.  Paper 003 counts time in filter
iterations; jaxslam uses seconds, and the scenarios use Δt = 1 s so that "60
iterations" is 60 s.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import real_numbers
from ..errors import InputError
from ..linalg import is_concrete
from .trajectories import Circle, flat_output

__all__ = ["CirclePath", "PolylinePath", "RateProfile", "planar_state", "planar_states"]


def _concrete_fields(obj):
    """Host NumPy float64 copies of a container's fields, or None when any field is traced
    (under ``jit`` the values are unknown: nothing is checked then)."""
    if not is_concrete(tuple(obj)):
        return None
    return {name: real_numbers(v, f"{type(obj).__name__}.{name}") for name, v in zip(obj._fields, obj)}


def _check_polyline(path) -> None:
    """:class:`InputError` naming the field of a :class:`PolylinePath` with concrete fields:
    times (K,) K >= 1 finite and strictly increasing (``jnp.interp`` read unsorted times
    silently wrong), points (K, 2) finite, wiggle fields finite and wiggle_period > 0 (0 gave
    NaN positions inside the window even with wiggle_amp = 0)."""
    v = _concrete_fields(path)
    if v is None:
        return
    times, points = v["times"], v["points"]
    if times.ndim != 1 or times.shape[0] < 1:
        raise InputError(f"PolylinePath.times: expected shape (K,) with K >= 1, got {times.shape}")
    if points.shape != (times.shape[0], 2):
        raise InputError(f"PolylinePath.points: expected shape ({times.shape[0]}, 2), got {points.shape}")
    for name, a in v.items():
        if not np.all(np.isfinite(a)):
            raise InputError(f"PolylinePath.{name}: contains NaN or Inf")
        if name.startswith("wiggle") and a.shape != ():
            raise InputError(f"PolylinePath.{name}: expected a scalar, got shape {a.shape}")
    if np.any(np.diff(times) <= 0):
        raise InputError(f"PolylinePath.times: must be strictly increasing, got {times.tolist()}")
    if v["wiggle_period"] <= 0:
        raise InputError(f"PolylinePath.wiggle_period: must be > 0, got {float(v['wiggle_period'])}")


def _check_rates(prof) -> None:
    """:class:`InputError` naming the field of a :class:`RateProfile` with concrete fields:
    t0, t1 (S,), r (S, 3), sin_amp, sin_omega (3,), all finite, and t1 >= t0 (t1 < t0 gave
    angles that are not the integral of the rates: a negative duration)."""
    v = _concrete_fields(prof)
    if v is None:
        return
    t0 = v["t0"]
    if t0.ndim != 1:
        raise InputError(f"RateProfile.t0: expected shape (S,), got {t0.shape}")
    want = {"t1": t0.shape, "r": (t0.shape[0], 3), "sin_amp": (3,), "sin_omega": (3,)}
    for name, shape in want.items():
        if v[name].shape != shape:
            raise InputError(f"RateProfile.{name}: expected shape {shape}, got {v[name].shape}")
    for name, a in v.items():
        if not np.all(np.isfinite(a)):
            raise InputError(f"RateProfile.{name}: contains NaN or Inf")
    if np.any(v["t1"] < t0):
        raise InputError(f"RateProfile.t1: must be >= t0, got t0={t0.tolist()}, t1={v['t1'].tolist()}")


def _dt(t, *trees):
    dt = jnp.result_type(t, *[leaf for tr in trees for leaf in jax.tree_util.tree_leaves(tr)])
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


class CirclePath(NamedTuple):
    """Scenario I of paper 003: [c_x + R cos(ωt), c_y + R sin(ωt)] with yaw rate a sin(ω_ψ t)."""

    circle: Circle = Circle()

    def position(self, t):
        """(2,) position [m] at time t [s]."""
        return flat_output(self.circle, t)[:2]

    def rates(self, t):
        """(3,) angular rates [rad/s]: roll and pitch 0, yaw a sin(ω_ψ t) (paper 003 Sec. IV-A)."""
        t = jnp.asarray(t, _dt(t, self))  # an integer t failed inside jax.jvp
        psi_dot = jax.jvp(lambda tt: flat_output(self.circle, tt)[3], (t,), (jnp.ones_like(t),))[1]
        z = jnp.zeros_like(psi_dot)
        return jnp.stack([z, z, psi_dot])

    def angles(self, t):
        """(3,) roll, pitch, yaw [rad]; yaw relative to its value at t = 0."""
        psi = flat_output(self.circle, t)[3] - flat_output(self.circle, jnp.zeros_like(t))[3]
        z = jnp.zeros_like(psi)
        return jnp.stack([z, z, psi])


class PolylinePath(NamedTuple):
    """Straight segments through timed waypoints, plus an optional windowed lateral sinusoid.

    times: (K,) s, increasing; points: (K, 2) m.  Before times[0] / after
    times[-1] the path holds the end point.  The wiggle adds
    amp · sin(2π (t − t0)/period) · n̂ for t0 ≤ t ≤ t1, with n̂ the unit normal of
    the segment at t (left of travel); ``wiggle_amp = 0`` disables it.
    """

    times: jax.Array
    points: jax.Array
    wiggle_amp: float = 0.0  # m
    wiggle_period: float = 10.0  # s
    wiggle_t0: float = 0.0  # s
    wiggle_t1: float = 0.0  # s

    def _base(self, t):
        ts = jnp.asarray(self.times, jnp.result_type(t))
        pts = jnp.asarray(self.points, jnp.result_type(t))
        return jnp.stack([jnp.interp(t, ts, pts[:, 0]), jnp.interp(t, ts, pts[:, 1])])

    def position(self, t):
        """(2,) position [m] at time t [s] (an integer t is promoted to a float).

        Concrete fields are checked first (:class:`InputError` naming the field: times (K,)
        strictly increasing, points (K, 2), finite values, wiggle_period > 0).
        """
        _check_polyline(self)
        t = jnp.asarray(t, _dt(t))  # an integer t failed inside jax.jvp; a float t keeps its dtype
        p, v = jax.jvp(self._base, (t,), (jnp.ones_like(t),))
        speed = jnp.sqrt(jnp.sum(v * v))
        n = jnp.where(speed > 0, jnp.stack([-v[1], v[0]]) / jnp.where(speed > 0, speed, 1.0), 0.0)
        n = jax.lax.stop_gradient(n)  # the normal is constant on a segment
        t0 = jnp.asarray(self.wiggle_t0, p.dtype)
        t1 = jnp.asarray(self.wiggle_t1, p.dtype)
        inside = (t >= t0) & (t <= t1)
        w = jnp.asarray(self.wiggle_amp, p.dtype) * jnp.sin(
            2.0 * jnp.pi * (t - t0) / jnp.asarray(self.wiggle_period, p.dtype))
        return p + jnp.where(inside, w, 0.0) * n


class RateProfile(NamedTuple):
    """Angular rates: Σ_s r_s 1[t0_s ≤ t < t1_s] + a sin(ω t) per axis (roll, pitch, yaw).

    t0, t1: (S,) s; r: (S, 3) rad/s; sin_amp, sin_omega: (3,) rad/s and rad/s
    (ω = 0 disables that axis' sinusoid).
    """

    t0: jax.Array
    t1: jax.Array
    r: jax.Array
    sin_amp: jax.Array
    sin_omega: jax.Array

    def rates(self, t):
        """(3,) rates [rad/s] at time t [s].  Concrete fields are checked (:class:`InputError`
        naming the field: shapes, finite values, t1 >= t0)."""
        _check_rates(self)
        dt = _dt(t)
        t0, t1 = jnp.asarray(self.t0, dt), jnp.asarray(self.t1, dt)
        on = ((t >= t0) & (t < t1)).astype(dt)
        w = jnp.asarray(self.sin_omega, dt)
        return on @ jnp.asarray(self.r, dt) + jnp.asarray(self.sin_amp, dt) * jnp.sin(w * t)

    def angles(self, t):
        """(3,) angles [rad] = ∫_0^t rates (exact).  Fields checked as in :meth:`rates`."""
        _check_rates(self)
        dt = _dt(t)
        t0, t1 = jnp.asarray(self.t0, dt), jnp.asarray(self.t1, dt)
        dur = jnp.clip(t - t0, 0.0, t1 - t0)
        w = jnp.asarray(self.sin_omega, dt)
        small = jnp.abs(w) < 1e-9
        ws = jnp.where(small, 1.0, w)
        integ = jnp.where(small, 0.0, (1.0 - jnp.cos(ws * t)) / ws)
        return dur @ jnp.asarray(self.r, dt) + jnp.asarray(self.sin_amp, dt) * integ


def planar_state(path, attitude, t):
    """Truth s(t) = [x, y, v_x, v_y, α, β, θ, w_α, w_β, w_θ] (10,) at time t [s].

    ``path`` has ``position(t)``; ``attitude`` has ``angles(t)`` and ``rates(t)``
    (a :class:`CirclePath` serves as both).  Velocity by forward-mode autodiff.
    """
    dtype = _dt(t, path, attitude)
    t = jnp.asarray(t, dtype)
    p, v = jax.jvp(path.position, (t,), (jnp.ones_like(t),))
    return jnp.concatenate([p, v, attitude.angles(t), attitude.rates(t)]).astype(dtype)


def planar_states(path, attitude, ts):
    """:func:`planar_state` at every time of ts (T,) -> (T, 10) (vmapped)."""
    return jax.vmap(lambda t: planar_state(path, attitude, t))(ts)
