"""Consistency monitoring inside a filter's scan: a NIS monitor that inflates the robot's
covariance when the measurements keep disagreeing with it, and the counts behind ``DIVERGED``.

Why: a hard Mahalanobis gate has no way back.  After an over-confident stretch (odometry
worse than its noise model, a long gap without sightings) every later sighting of a *known*
landmark looks like an outlier, is gated, and the filter coasts on dead reckoning for the
rest of the log (seen on MRCLAM: 3132 of 4348 sightings gated).  The monitor watches the
normalised innovation of the rows that were offered to the update (before any gate or
robust weighting):

    r_k = Σ_i d²_i / (d_z · n_k)           (the mean NIS per scalar, E[r] = 1 when consistent)
    m_k = (1 − α) m_{k−1} + α r_k           (exponential average over events with rows)

and when ``m_k`` exceeds ``threshold`` it scales the robot block of the covariance by
``f = clip(m_k, 1, max_factor)`` (never a deflation, also for a threshold below 1) — rows
and columns of the robot block by √f, so P stays positive semi-definite and the
robot–landmark correlation is kept (P_rr ← f P_rr, P_rl ← √f P_rl) — and restarts the
average at 1.  The next sightings then pull the robot back instead of being rejected.  Each inflation is counted.

All numbers (α, threshold, max_factor) are traced; the monitor never names a model.
``DIVERGED`` (:mod:`jaxslam.errors`) is raised by the system from the counts of
:func:`outliers` over the run: see :func:`status_bits`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..errors import InputError
from ..linalg import check_float_dtype, check_mask, check_numbers, float_array, is_concrete
from .ekf_slam import SlamModel, SlamState

__all__ = ["MonitorParams", "Monitor", "init", "observe", "inflate_robot", "outliers", "status_bits",
           "DIVERGED_FRACTION"]

#: a run whose outlier fraction among known-landmark rows exceeds this is DIVERGED
DIVERGED_FRACTION = 0.10


class MonitorParams(NamedTuple):
    """alpha: () averaging weight per event with rows (0 < α ≤ 1); threshold: () mean-NIS
    ratio that triggers an inflation; max_factor: () largest inflation of P_rr at once;
    outlier_gate: () d² above which a row counts as an outlier (χ²(d_z) 99 % for d_z = 2:
    9.21), for the gated fractions."""

    alpha: jax.Array
    threshold: jax.Array
    max_factor: jax.Array
    outlier_gate: jax.Array


def _value(value, name: str):
    """A monitor number: one scalar (its shape is static, so checked traced too: a vector
    broadcast the robot rows against it), as a float when it is concrete (an eager call), else
    None (traced: its value not checked).  Each caller checks the range (NaN included) with its
    own message, so :func:`jaxslam.linalg.check_scalar` (eager only) does not serve here."""
    if np.ndim(value) != 0:
        raise InputError(f"{name}: expected a scalar, got shape {np.shape(value)}")
    return float(check_numbers(value, name)) if is_concrete(value) else None


def check_params(params: MonitorParams, name: str = "params"):
    """The monitor's numbers (scalars; their values when concrete, as :class:`MonitorParams`
    documents them): 0 < alpha ≤ 1, threshold > 0, max_factor ≥ 1 (the largest inflation: a
    max_factor below 1 deflated P_rr; finite: an inf d² made an infinite inflation, P NaN),
    outlier_gate ≥ 0; NaN never.  :class:`InputError` naming
    ``name.field`` (alpha = −1 drove the running mean to −48 without a word)."""
    if not isinstance(params, MonitorParams):
        raise InputError(f"{name}: expected a MonitorParams, got {type(params).__name__}")
    rules = (("alpha", lambda v: 0.0 < v <= 1.0, "in (0, 1]"), ("threshold", lambda v: v > 0, "> 0"),
             ("max_factor", lambda v: v >= 1.0, ">= 1 (1: no inflation)"))
    for field, ok, want in rules:
        v = _value(getattr(params, field), f"{name}.{field}")
        if v is not None and not ok(v):
            raise InputError(f"{name}.{field}: must be {want}, got {v}")
    v = _value(params.max_factor, f"{name}.max_factor")
    if v is not None and not np.isfinite(v):  # inf: an inf d² made f = inf and P NaN under jit
        raise InputError(f"{name}.max_factor: must be finite (the largest inflation at once), got {v}")
    _check_gate(params, name)


def _check_gate(params, name: str = "params"):
    """``params.outlier_gate``: a scalar d² ≥ 0 (NaN never: ``d² > nan`` counts no outlier)."""
    v = _value(params.outlier_gate, f"{name}.outlier_gate")
    if v is not None and not v >= 0:
        raise InputError(f"{name}.outlier_gate: must be >= 0, got {v}")


def _rows(d2, valid, name: str = "d2"):
    """``(d2 (K,), valid (K,) bool)`` as arrays, shapes checked (static): :class:`InputError`
    naming the argument (a length mismatch was a broadcast error, a list had no ``.dtype``)."""
    d2 = float_array(d2, name)  # a list is taken, a string named
    valid = jnp.asarray(valid)
    if d2.ndim != 1:
        raise InputError(f"{name}: expected shape (K,), got {tuple(d2.shape)}")
    if valid.shape != d2.shape:
        raise InputError(f"valid: expected shape {tuple(d2.shape)} (one per row of {name}), got {tuple(valid.shape)}")
    check_mask(valid, "valid")
    return d2, valid.astype(bool)


class Monitor(NamedTuple):
    """mean: () the running mean NIS ratio m_k; inflations: () int32 count."""

    mean: jax.Array
    inflations: jax.Array


def init(dtype) -> Monitor:
    """A fresh monitor: running NIS ratio 1, no inflation yet.

    ``dtype``: a floating dtype (the running mean is a ratio; an integer one truncated it)."""
    dt = check_float_dtype(dtype)
    return Monitor(mean=jnp.ones((), dt), inflations=jnp.zeros((), jnp.int32))


def inflate_robot(state: SlamState, model: SlamModel, factor) -> SlamState:
    """P ← D P D with D = diag(√f·I_{n_r}, I): P_rr ×f, P_rl ×√f, P_ll unchanged (PSD kept).

    ``factor`` f: a scalar inflation ≥ 1 (1: unchanged), finite; a concrete one is checked
    (:class:`InputError` naming ``factor``: f < 0 made P all NaN, f = 0 zeroed the robot block,
    0 < f < 1 would deflate it, the opposite of what the monitor is for).  Traced: not checked
    (:func:`observe` passes ``clip(m_k, 1, max_factor)``)."""
    v = _value(factor, "factor")
    if v is not None and not (np.isfinite(v) and v >= 1.0):
        raise InputError(f"factor: expected a finite inflation factor >= 1 (1: unchanged), got {v}")
    nr = model.robot_dim
    g = jnp.sqrt(jnp.asarray(factor, state.P.dtype))
    # only the robot rows and columns change: O(n·n_r)
    rows = state.P[:nr, :] * g
    rows = rows.at[:, :nr].multiply(g)
    P = jax.lax.dynamic_update_slice(state.P, rows, (0, 0))
    P = jax.lax.dynamic_update_slice(P, rows.T, (0, 0))
    return state._replace(P=P)


def observe(mon: Monitor, state: SlamState, model: SlamModel, d2, valid, params: MonitorParams):
    """Fold one event's rows into the monitor and inflate the robot covariance if it trips.

    d2: (K,) marginal NIS of the rows offered to the update; valid: (K,) bool rows that count
    (known landmarks, mapped).  Returns (monitor, state).  Shapes are checked (static) and, when
    concrete, ``params`` (:func:`check_params`) and ``d2`` on the valid rows (not NaN: one NaN
    would make the running mean NaN for the rest of the run; not negative beyond round-off,
    −1e-6: a −inf held it at −inf): :class:`InputError` naming them.
    """
    check_params(params)
    d2, valid = _rows(d2, valid)
    if is_concrete(d2, valid) and np.any(np.isnan(np.asarray(d2)) & np.asarray(valid)):
        raise InputError("d2: NaN on a valid row")
    if is_concrete(d2, valid) and np.any((np.asarray(d2) < -1e-6) & np.asarray(valid)):
        # a d² of −inf held the running mean at −inf (the monitor never tripped again); a
        # round-off −1e-17 of a d² near 0 is not refused
        raise InputError("d2: negative on a valid row (a squared Mahalanobis distance is >= 0)")
    return _observe(mon, state, model, d2, valid, params)


def _observe(mon: Monitor, state: SlamState, model: SlamModel, d2, valid, params: MonitorParams):
    """:func:`observe` without its checks: what a filter's step calls on every event (its
    params checked once at the run's entry; a NaN row there is the run's status to report,
    not an error)."""
    dtype = mon.mean.dtype
    dz = model.meas_dim
    n = jnp.sum(valid)
    r = jnp.sum(jnp.where(valid, d2, 0.0)) / (dz * jnp.maximum(n, 1))
    a = jnp.asarray(params.alpha, dtype)
    mean = jnp.where(n > 0, (1 - a) * mon.mean + a * r, mon.mean)
    trip = (n > 0) & (mean > jnp.asarray(params.threshold, dtype))
    f = jnp.clip(mean, 1.0, jnp.asarray(params.max_factor, dtype))
    state = jax.lax.cond(trip, lambda st: inflate_robot(st, model, f), lambda st: st, state)
    return Monitor(mean=jnp.where(trip, 1.0, mean).astype(dtype),
                   inflations=mon.inflations + trip.astype(jnp.int32)), state


def outliers(d2, valid, params: MonitorParams):
    """() int32: rows that count with d² above ``params.outlier_gate`` (the gated fraction's
    numerator, counted whether or not the monitor acts).

    ``d2`` (K,) (a list is taken) and ``valid`` (K,) are checked for shape; ``params`` is any
    object with an ``outlier_gate`` (a scalar ≥ 0, checked when concrete)."""
    _check_gate(params)
    d2, valid = _rows(d2, valid)
    return _outliers(d2, valid, params)


def _outliers(d2, valid, params):
    """:func:`outliers` without its checks (a filter's per-event call)."""
    return jnp.sum(valid & (d2 > jnp.asarray(params.outlier_gate, d2.dtype))).astype(jnp.int32)


def status_bits(n_outliers, n_rows, fraction=DIVERGED_FRACTION):
    """``errors.DIVERGED`` (int32) where more than ``fraction`` of the ``n_rows`` monitored rows
    were outliers (the run stopped being consistent with its own noise model, whatever the
    monitor did about it), else 0.

    ``fraction``: a scalar in [0, 1]; a concrete one is checked (:class:`InputError` naming it:
    −0.1 flagged DIVERGED with no outlier at all); concrete counts must be >= 0 (NaN neither).
    Compared as the ratio
    ``n_outliers / max(n_rows, 1) > fraction`` (29 of 100 is not more than 0.29)."""
    v = _value(fraction, "fraction")
    if v is not None and not 0.0 <= v <= 1.0:
        raise InputError(f"fraction: expected an outlier fraction in [0, 1], got {v}")
    for name, count in (("n_outliers", n_outliers), ("n_rows", n_rows)):  # counts known now
        if is_concrete(count):
            c = check_numbers(count, name)
            if not np.all(c >= 0):  # n_rows = −3 read as 1 row: 5 "outliers" of it flagged DIVERGED
                raise InputError(f"{name}: expected a count >= 0, got {count!r}")
    # As a ratio: n_outliers > fraction·n_rows rounded 0.29·100 to 28.999999999999996, so 29
    # outliers of 100 were "more than 29 %"; n/N, rounded to the fraction's precision (a float32
    # 0.29 too), and the fraction are then the same number.
    frac = jnp.asarray(fraction)
    ratio = n_outliers / jnp.maximum(n_rows, 1)
    if jnp.issubdtype(frac.dtype, jnp.floating):
        ratio = ratio.astype(frac.dtype)
    div = ratio > frac
    return jnp.where(div, jnp.int32(errors.DIVERGED), jnp.int32(0))
