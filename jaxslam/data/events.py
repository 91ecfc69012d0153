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

from ..errors import InputError, check_int

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


_TIME_HINT = (" (times are seconds as numbers: convert datetime64 stamps with "
              "(t - t[0]) / np.timedelta64(1, 's'))")


def _numbers(a, name, hint=""):
    """``a`` as float64 when it holds real numbers (integer or floating dtype); a string, bool,
    complex, datetime/timedelta, object or ragged value is an :class:`InputError` naming
    ``name`` (NumPy parsed "1.5", turned a datetime64 into epoch seconds and complex into its
    real part)."""
    try:
        raw = np.asarray(a)
    except ValueError:  # a ragged list
        raw = None
    if raw is None or raw.dtype.kind not in "iuf":
        what = "a ragged sequence" if raw is None else f"dtype {raw.dtype}"
        raise InputError(f"{name}: expected real numbers, got {what}{hint}")
    return raw.astype(np.float64)


def _as_2d(a, name):
    a = _numbers(a, name)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise InputError(f"{name}: expected a 1-D or 2-D array, got shape {a.shape}")
    return a


def _finite(a, name, why, offset: int = 0):
    """InputError at the first non-finite entry of ``a``, its row counted from ``offset`` (the
    caller's row of ``a``'s first)."""
    bad = ~np.isfinite(a)
    if bad.any():
        i = [int(j) for j in np.argwhere(bad)[0]]
        where = f"row {offset + i[0]}, column {i[1]}" if len(i) == 2 else f"index {offset + i[0]}"
        raise InputError(f"{name}: non-finite value {float(a[tuple(i)])!r} at {where} ({why})")


def _bound(v, name):
    """A window bound: None, or one real number (NaN and inf: handled by the caller)."""
    if v is None:
        return None
    a = _numbers(v, name)
    if a.shape != ():
        raise InputError(f"{name}: expected one time [s] (or None), got shape {a.shape}")
    return float(a)


_INT32 = np.iinfo(np.int32)


def _ids(meas_ids, n, name: str = "meas_ids"):
    """``meas_ids`` as (n,) int32: whole numbers that fit int32 (the cast wrapped 2**32 - 1 onto
    -1, "no id"); a bool, complex, string or object array is refused.  The messages call the
    ids ``name`` (the caller's own argument name)."""
    if meas_ids is None:
        return np.full((n,), -1, np.int32)
    try:
        a = np.asarray(meas_ids)
    except ValueError:
        a = None
    if a is None or a.dtype.kind not in "iuf":
        raise InputError(f"{name}: expected integer ids (-1 for none), got "
                         + ("a ragged sequence" if a is None else f"dtype {a.dtype}"))
    a = a.reshape(-1)
    if a.dtype.kind == "f" and (not np.all(np.isfinite(a)) or np.any(a != np.round(a))):
        # 2.5 would be truncated onto id 2
        raise InputError(f"{name}: expected whole-number ids (a fractional or non-finite id would be "
                         "truncated onto another landmark)")
    out = (a < _INT32.min) | (a > _INT32.max)
    if out.any():
        i = int(np.argmax(out))
        raise InputError(f"{name}: id {a[i].item()!r} at index {i} does not fit int32 "
                         f"([{_INT32.min}, {_INT32.max}]: the ids are stored as int32)")
    if a.shape != (n,):
        raise InputError(f"{name}: {a.shape[0]} rows but meas_t has {n}")
    return a.astype(np.int32)


def check_times(t, name: str) -> None:
    """Raise :class:`InputError` naming ``name`` unless the (N,) times ``t`` are real numbers
    (not datetime64, strings or bools), finite and non-decreasing (equal times are allowed:
    one event).  The message gives the first bad index
    (and, for a step back, the two times).  Host-side (NumPy)."""
    t = _numbers(t, name, _TIME_HINT)
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
      inputs: (N_u, d_u) input samples, finite where used (an input drives
        every later prediction: a NaN would poison the rest of the run); with
        a window only the samples in it, and for ``"rate"`` the last one
        before ``t_start`` (held into the window), are used and checked.
      meas_t: (N_z,) measurement times [s], non-decreasing; rows with equal
        times form one event.
      meas: (N_z, d_z) measurement rows.
      meas_ids: (N_z,) int labels (−1 when unknown), whole numbers that fit
        int32; default −1.
      K: static rows per event, an int >= 1; default the largest group.  Extra
        rows are counted in ``stats["dropped_overflow"]``.
      input_mode: ``"rate"`` (zero-order hold) or ``"increment"``.
      u_before: (d_u,) finite input before the first sample ("rate" only);
        default zeros.
      t_start, t_end: optional time window [s], ``t_start <= t_end``;
        events outside are discarded (measurements counted in
        ``stats["outside_window"]``).  None, ``t_start=-inf`` or
        ``t_end=+inf`` leave that end open.

    Times, samples and ids are real numbers: a string, bool, complex,
    ``datetime64``/``timedelta64`` or object array is refused (convert
    datetimes to seconds first).

    Raises:
      InputError: an argument is not real numbers, shapes disagree, times are
        not finite or decrease, an input is not finite, an id is fractional or
        does not fit int32, ``K`` is not an int >= 1, the window is reversed or
        has a NaN bound, ``t_start`` is +inf or ``t_end`` is −inf, or
        ``input_mode`` is unknown.
    """
    if not isinstance(input_mode, str) or input_mode not in ("rate", "increment"):
        raise InputError(f"input_mode: expected 'rate' or 'increment', got {input_mode!r}")
    ut = _numbers(input_t, "input_t", _TIME_HINT).reshape(-1)
    U = _as_2d(inputs, "inputs")
    zt = _numbers(meas_t, "meas_t", _TIME_HINT).reshape(-1)
    Z = _as_2d(meas, "meas")
    if U.shape[0] != ut.shape[0]:
        raise InputError(f"inputs: {U.shape[0]} rows but input_t has {ut.shape[0]}")
    if Z.shape[0] != zt.shape[0]:
        raise InputError(f"meas: {Z.shape[0]} rows but meas_t has {zt.shape[0]}")
    ids = _ids(meas_ids, zt.shape[0])
    check_times(ut, "input_t")
    check_times(zt, "meas_t")
    d_u = U.shape[1]
    ub = np.zeros(d_u)
    if u_before is not None:
        if input_mode != "rate":
            raise InputError("u_before: applies to input_mode='rate' only (an increment is applied at its "
                             "own event; nothing holds before the first one)")
        ub = _numbers(u_before, "u_before")
        if ub.size != d_u:
            raise InputError(f"u_before: expected {d_u} value(s) (one per input column), got shape {ub.shape}")
        ub = ub.reshape(d_u)
        _finite(ub, "u_before", "it drives the predictions before the first input")
    K = None if K is None else check_int(K, "K", 1)  # 1.5 or True was truncated to 1 row
    outside = 0
    if t_start is not None or t_end is not None:
        lo, hi = _bound(t_start, "t_start"), _bound(t_end, "t_end")
        if (lo is not None and np.isnan(lo)) or (hi is not None and np.isnan(hi)):
            # a NaN bound kept no event: the run then returned zeros flagged degenerate (an empty
            # window stays allowed: a dataset runner reports it in its notes)
            raise InputError(f"t_start, t_end: expected numbers (or None), got {t_start}, {t_end}")
        # -inf for t_start and +inf for t_end are open ends, as None (t_start=inf gave one event at
        # t = inf; t_end=-inf kept nothing)
        if lo is not None and np.isinf(lo):
            if lo > 0:
                raise InputError(f"t_start: expected a time [s] (None or -inf for an open start), got {lo!r}")
            lo = None
        if hi is not None and np.isinf(hi):
            if hi < 0:
                raise InputError(f"t_end: expected a time [s] (None or +inf for an open end), got {hi!r}")
            hi = None
        lo = -np.inf if lo is None else lo
        hi = np.inf if hi is None else hi
        if lo > hi:  # a reversed window kept an event at t_start, after t_end
            raise InputError(f"t_start, t_end: t_start {lo!r} is after t_end {hi!r} (a reversed window)")
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
        row0 = int(np.argmax(keep_u)) if keep_u.any() else 0  # index in the caller's rows
    else:
        row0 = 0
    # an input drives every prediction after it: a NaN would make the rest of the run NaN (only the
    # samples in use are checked: those in the window and, for "rate", the one held into it)
    _finite(U, "inputs", "an input drives every later prediction", offset=row0)
    z_times, z_first, z_count = np.unique(zt, return_index=True, return_counts=True)
    if K is None:
        K = int(z_count.max()) if z_count.size else 1
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
