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
``f = min(m_k, max_factor)`` — rows and columns of the robot block by √f, so P stays
positive semi-definite and the robot–landmark correlation is kept (P_rr ← f P_rr,
P_rl ← √f P_rl) — and restarts the average at 1.  The next sightings then pull the robot back
instead of being rejected.  Each inflation is counted.

All numbers (α, threshold, max_factor) are traced; the monitor never names a model.
``DIVERGED`` (:mod:`jaxslam.errors`) is raised by the system from the counts of
:func:`outliers` over the run: see :func:`status_bits`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import errors
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


class Monitor(NamedTuple):
    """mean: () the running mean NIS ratio m_k; inflations: () int32 count."""

    mean: jax.Array
    inflations: jax.Array


def init(dtype) -> Monitor:
    """A fresh monitor: running NIS ratio 1, no inflation yet."""
    return Monitor(mean=jnp.ones((), dtype), inflations=jnp.zeros((), jnp.int32))


def inflate_robot(state: SlamState, model: SlamModel, factor) -> SlamState:
    """P ← D P D with D = diag(√f·I_{n_r}, I): P_rr ×f, P_rl ×√f, P_ll unchanged (PSD kept)."""
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
    (known landmarks, mapped).  Returns (monitor, state).
    """
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
    numerator, counted whether or not the monitor acts)."""
    return jnp.sum(valid & (d2 > jnp.asarray(params.outlier_gate, d2.dtype))).astype(jnp.int32)


def status_bits(n_outliers, n_rows, fraction=DIVERGED_FRACTION):
    """``errors.DIVERGED`` (int32) where more than ``fraction`` of the ``n_rows`` monitored rows
    were outliers (the run stopped being consistent with its own noise model, whatever the
    monitor did about it), else 0."""
    div = n_outliers > jnp.asarray(fraction) * jnp.maximum(n_rows, 1)
    return jnp.where(div, jnp.int32(errors.DIVERGED), jnp.int32(0))
