"""Asynchronous sensor streams → one fixed-shape, event-ordered log for ``lax.scan``.

Real logs interleave an input stream (odometry, wheel encoder, IMU) with
measurement streams at other, irregular times.  :func:`merge_events` sorts the
union of input times and distinct measurement times into one event sequence
and pads the measurements of each event to ``K`` rows with a mask, so a whole
log is one ``lax.scan`` with static shapes:

    event k:  predict over dt_k = t_k − t_{k−1} with input u_k, then update with
              the (masked) measurements z_k[:K].

There is no time grid and therefore no resampling error: every measurement is
applied at its own time stamp, and every input interval is integrated up to
the exact measurement time.  The only approximation is the input model, chosen
by ``input_mode``:

* ``"rate"`` (odometry velocities, wheel speed and steering): a sample holds
  from its own time until the next input sample (zero-order hold, as the
  datasets' reference integrators do).  Before the first input sample the
  input is ``u_before`` (zeros: the robot is at rest).
* ``"increment"`` (odometry pose increments, e.g. CMU Plaza's ``DR``): the
  sample is applied once, at its own event; measurement-only events carry a
  zero input.

A measurement time equal to an input time becomes one event that carries
both (the input holds *from* that time on, so the prediction into the event
uses the previous input).  Measurements beyond ``K`` rows at one time are
never dropped silently: they are counted in ``stats["dropped_overflow"]``.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

from ..errors import InputError

__all__ = ["EventLog", "check_times", "merge_events"]


class EventLog(NamedTuple):
    """An event-ordered log with static shapes (NumPy arrays; ``T`` events).

    t: (T,) event time [s]; dt: (T,) t_k − t_{k−1} (0 for the first event);
    u: (T, d_u) input over (t_{k−1}, t_k] ("rate") or applied at t_k ("increment");
    is_input: (T,) bool, an input sample starts at this event;
    z: (T, K, d_z) measurements (NaN where masked); ids: (T, K) int32
    measurement labels (landmark/anchor id, −1 when none);
    mask: (T, K) bool row present;
    stats: host-side counts (``n_events``, ``n_input``, ``n_meas``,
    ``n_meas_events``, ``dropped_overflow``, ``outside_window``, ``K``).
    """

    t: np.ndarray
    dt: np.ndarray
    u: np.ndarray
    is_input: np.ndarray
    z: np.ndarray
    ids: np.ndarray
    mask: np.ndarray
    stats: dict


def _as_2d(a, name):
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise InputError(f"{name}: expected a 1-D or 2-D array, got shape {a.shape}")
    return a


def check_times(t, name: str) -> None:
    """Raise :class:`InputError` naming ``name`` unless the (N,) times ``t`` are finite and
    non-decreasing (equal times are allowed: one event).  The message gives the first bad index
    (and, for a step back, the two times).  Host-side (NumPy)."""
    t = np.asarray(t, dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise InputError(f"{name}: non-finite time at index {int(np.argmin(np.isfinite(t)))}")
    if t.size > 1 and np.any(np.diff(t) < 0):
        i = int(np.argmax(np.diff(t) < 0)) + 1
        raise InputError(f"{name}: time decreases at index {i} ({float(t[i - 1])!r} → {float(t[i])!r})")


def merge_events(input_t, inputs, meas_t, meas, meas_ids=None, K: Optional[int] = None,
                 input_mode: str = "rate", u_before=None, t_start=None, t_end=None) -> EventLog:
    """Merge an input stream and a measurement stream into an :class:`EventLog`.

    Args:
      input_t: (N_u,) input times [s], non-decreasing.
      inputs: (N_u, d_u) input samples.
      meas_t: (N_z,) measurement times [s], non-decreasing; rows with equal
        times form one event.
      meas: (N_z, d_z) measurement rows.
      meas_ids: (N_z,) int labels (−1 when unknown); default −1.
      K: static rows per event; default the largest group.  Extra rows are
        counted in ``stats["dropped_overflow"]``.
      input_mode: ``"rate"`` (zero-order hold) or ``"increment"``.
      u_before: (d_u,) input before the first sample ("rate"); default zeros.
      t_start, t_end: optional time window; events outside are discarded
        (measurements counted in ``stats["outside_window"]``).

    Raises:
      InputError: shapes disagree, times are not finite or decrease, or
        ``input_mode`` is unknown.
    """
    if input_mode not in ("rate", "increment"):
        raise InputError(f"input_mode: expected 'rate' or 'increment', got {input_mode!r}")
    ut = np.asarray(input_t, dtype=np.float64).reshape(-1)
    U = _as_2d(inputs, "inputs")
    zt = np.asarray(meas_t, dtype=np.float64).reshape(-1)
    Z = _as_2d(meas, "meas")
    if U.shape[0] != ut.shape[0]:
        raise InputError(f"inputs: {U.shape[0]} rows but input_t has {ut.shape[0]}")
    if Z.shape[0] != zt.shape[0]:
        raise InputError(f"meas: {Z.shape[0]} rows but meas_t has {zt.shape[0]}")
    if meas_ids is not None and np.issubdtype(np.asarray(meas_ids).dtype, np.floating):
        a = np.asarray(meas_ids)  # 2.5 would be truncated onto id 2
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise InputError("meas_ids: expected whole-number ids (a fractional or non-finite id would be "
                             "truncated onto another landmark)")
    ids = (np.full(zt.shape, -1, np.int32) if meas_ids is None
           else np.asarray(meas_ids).astype(np.int32).reshape(-1))
    if ids.shape != zt.shape:
        raise InputError(f"meas_ids: {ids.shape[0]} rows but meas_t has {zt.shape[0]}")
    check_times(ut, "input_t")
    check_times(zt, "meas_t")
    d_u = U.shape[1]
    outside = 0
    if t_start is not None or t_end is not None:
        lo = -np.inf if t_start is None else float(t_start)
        hi = np.inf if t_end is None else float(t_end)
        if np.isnan(lo) or np.isnan(hi):
            # a NaN bound kept no event: the run then returned zeros flagged degenerate (an empty
            # window stays allowed: a dataset runner reports it in its notes)
            raise InputError(f"t_start, t_end: expected numbers (or None), got {t_start}, {t_end}")
        keep_z = (zt >= lo) & (zt <= hi)
        outside = int(np.sum(~keep_z))
        zt, Z, ids = zt[keep_z], Z[keep_z], ids[keep_z]
        if input_mode == "rate":
            # keep the last sample before the window: it holds into it
            first = max(int(np.searchsorted(ut, lo, side="right")) - 1, 0)
            keep_u = (np.arange(ut.size) >= first) & (ut <= hi)
        else:
            keep_u = (ut >= lo) & (ut <= hi)
        ut, U = ut[keep_u], U[keep_u]
        if input_mode == "rate" and ut.size and ut[0] < lo:
            ut = ut.copy()
            ut[0] = lo
    z_times, z_first, z_count = np.unique(zt, return_index=True, return_counts=True)
    if K is None:
        K = int(z_count.max()) if z_count.size else 1
    K = int(K)
    if K < 1:
        raise InputError(f"K: must be >= 1, got {K}")
    t = np.union1d(ut, z_times)
    T = t.size
    if T == 0:
        raise InputError("merge_events: no events (both streams empty in the window)")
    # Input of each event.
    if input_mode == "rate":
        # the sample holding over (t_{k-1}, t_k]: the last input at or before t_{k-1}
        u = np.empty((T, d_u))
        prev = np.concatenate([[t[0]], t[:-1]])
        j = np.searchsorted(ut, prev, side="right") - 1
        ub = np.zeros(d_u) if u_before is None else np.asarray(u_before, np.float64).reshape(d_u)
        u[:] = ub
        has = j >= 0
        u[has] = U[j[has]]
    else:
        u = np.zeros((T, d_u))
        k_in = np.searchsorted(t, ut)
        np.add.at(u, k_in, U)  # several increments at one time compose additively (rare)
    is_input = np.isin(t, ut)
    # Measurements of each event, padded to K.
    d_z = Z.shape[1]
    z = np.full((T, K, d_z), np.nan)
    lab = np.full((T, K), -1, np.int32)
    mask = np.zeros((T, K), bool)
    k_ev = np.searchsorted(t, z_times)
    dropped = 0
    for k, f, c in zip(k_ev, z_first, z_count):
        n = min(int(c), K)
        dropped += int(c) - n
        z[k, :n] = Z[f:f + n]
        lab[k, :n] = ids[f:f + n]
        mask[k, :n] = True
    dt = np.diff(t, prepend=t[0])
    stats = {
        "n_events": int(T),
        "n_input": int(ut.size),
        "n_meas": int(zt.size),
        "n_meas_events": int(z_times.size),
        "dropped_overflow": int(dropped),
        "outside_window": int(outside),
        "K": K,
    }
    return EventLog(t, dt, u, is_input, z, lab, mask, stats)
