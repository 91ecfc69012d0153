"""UTIL TWR range-only tag tracking and SLAM (3D, constant velocity, common range bias).

A *system* module on the generic EKF-SLAM engine (:mod:`jaxslam.filters.ekf_slam`): it fixes the
state, the motion and range models and the start-ups; the engine does prediction, update
(factored Joseph form), gating and bookkeeping, with every Jacobian from ``jax.jacfwd``.  One
run is one jitted ``lax.scan`` of :func:`step`; nothing raises inside ``jit`` — failures are
the engine's ``status`` bits.  Units: m, s, rad.  The range model (R1) is
:func:`jaxslam.systems.biased_range.range_observe`: z = ‖p − l‖ + b + v.

UTIL TWR, constant velocity in 3D.  Robot
s = [p (3), v (3), b] (7), no input::

    p ← p + v Δt,  v ← v,  b ← b                                              (CV)
    Q_d = q_a [[Δt³/3 I, Δt²/2 I], [Δt²/2 I, Δt I]] ⊕ q_b Δt                  (WNA)

p is the **UWB tag position** (not the Vicon body origin; the evaluation
compares it with p_body + R(q) t_uv).  Noise (``PARAMS``): σ_r = 0.2 m
(data README: 0.18 m overall about the median, per anchor 0.06–0.29 m, heavy
line-of-sight tails that the gate removes); q_a = 0.5 m²/s³; q_b = 1e-5 m²/s
(a nearly constant bias); gate χ²(1) = 9 (3σ, ``Params.gate``).  σ_r and q_a were picked from a
3 × 3 grid (σ_r 0.1/0.15/0.25, q_a 0.5/2/8, gate 4/9) **on this flight itself**
(the only TWR log; in-sample): airborne RMSE 0.22–0.29 m over the whole grid,
so the choice matters little.  Measured limit: a robust per-window least
squares over 16 consecutive ranges (0.2 s) with the *true* motion inside the
window and the true bias gives 0.205 m RMSE (0.18 m of it vertical), so the
ranges themselves do not support the issue's 0.15 m target with a CV model
(the ToF height update below does).  ``jaxslam dataset util-uwb`` runs instead the noise
learned from the flight's first half by innovation likelihood (Student-t ranges, ν = 5, no
gate; :data:`jaxslam.data.presets.UTIL_FITTED`, ``jaxslam tune util-uwb``): 0.213 m range-only,
figures and protocol in docs/datasets.md.  ``PARAMS`` and the table below stay the hand-set
filter's.

*Optional ToF height update* (the Crazyflie's downward laser, ``tof.csv``, ~23 Hz;
``util_events(..., tof_t=, tof=)`` merges its rows into the log with id
:data:`HEIGHT_ID`; :func:`run` fuses them with the engine's ``update_robot``
whenever the log holds such rows, else the run is exactly the range-only filter)::

    h = p_z − t_uv,z + c_tof + v_h,   v_h ~ N(0, σ_h²)                          (H1)

t_uv,z = 0.0908 m the tag's body-frame z offset (p is the tag, the laser sits
below the body origin).  *Tilt is ignored* twice: (i) the tag offset's vertical
projection R(q)t_uv·e_z is taken as t_uv,z — on this flight the airborne tilt is
6.9° median, 13° p95, 20° max (not "a few degrees"), and the projection differs
from 0.0908 m by 1.5 mm median, 5 mm p95, 9.5 mm max (at 3° it would be < 1 mm);
(ii) the laser measures along the body −z axis, i.e. a slant range ≈ height /
cos(tilt): tof·cos(tilt) − z_body has std 0.007 m against 0.014 m for tof − z_body
(motion capture, TWR flight), so the tilt is the larger part of v_h; the filter
has no attitude, so it stays in v_h (time-correlated, not white).  c_tof =
−0.014 m and σ_h = 0.02 m come from the **other** flight (TDOA2, out of sample):
there tof − z_body airborne has median −0.014 m, std 0.019 m (TWR flight:
−0.020 m, 0.014 m).  Height rows are gated one by one on their χ²(1) NIS with
the same ``gate`` (S = P_zz + σ_h², H = e_z) and counted apart (``n_height_used``,
``n_height_gated``); K = 2 slots arise only where a laser and a range row share
a time (never on this flight: K = 1).

* *known anchors*: the surveyed anchors are held in the map with zero
  covariance (the engine never moves them).  The initial tag position is a
  least-squares fix (:func:`jaxslam.filters.trilateration.trilaterate`) from
  the ranges of the first ``n_fix`` rows (the drone stands still on the
  ground), v = 0, b = 0, with P0 = diag(0.3², ·, ·, 0.1², ·, ·, 0.5²).
* *unknown anchors* (SLAM, anchors as engine landmarks): paper 003's
  straight-line start-up needs a flight from one anchor to another, which this
  flight does not contain.  Instead (:func:`startup`, **stated**: the
  motion-capture tag positions are used during a start-up window [0, t_w]
  only) anchors and bias are fitted jointly by robust Gauss–Newton
  least squares to the window's ranges, r_i = ‖p_i − a_{k(i)}‖ + b, with p_i
  the motion-capture tag position at the range's time (linear trilateration
  per anchor as the starting point, then a 4·MAD residual cut); their joint
  covariance σ̂² (JᵀJ)⁻¹ (anchors × anchors and anchors × bias) is written
  into the map.  The filter starts at t_w from the motion-capture position and
  velocity (σ 0.02 m, 0.1 m/s) and uses no motion capture afterwards.  The
  window fixes the map frame, so anchor errors are reported both raw and after
  a rigid (Umeyama) alignment.

Measured on the TWR flight (``scripts/study_range_only.py util``, float64; airborne
9.6–59.0 s, errors at the range events against p_body + R(q)t_uv):

==========================  ===========  ==========  ============  ============================
run                         RMSE 3D [m]  vertical    horizontal    counts
==========================  ===========  ==========  ============  ============================
known anchors, ranges       0.222        0.190       0.115         5469 used, 40 gated
known anchors, + ToF        0.115        0.016       0.114         + 1551 heights used, 0 gated
unknown (t > 30 s), ranges  0.185        0.143       0.117         3001 used, 15 gated
unknown (t > 30 s), + ToF   0.119        0.013       0.118         + 848 heights used, 0 gated
==========================  ===========  ==========  ============  ============================

(bias: −0.242 ± 0.010 → −0.252 ± 0.008 m known; −0.68 ± 0.22 m unknown, where it is
tied to the start-up's anchors).  The laser removes nearly all of the vertical error;
the horizontal 0.11–0.12 m is the ranges' own.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import call_compiled
from ..data.events import EventLog, _ids, check_times, merge_events
from ..data.util_uwb import TAG_OFFSET
from ..errors import InputError
from ..filters import consistency as cons
from ..filters import ekf_slam as es
from ..filters import trilateration as tri
from ..linalg import check_flag, check_int, check_scalar, is_concrete, symmetrize
from .biased_range import (Result, _cast_params, _result, check_ids_vector, check_log, check_params, check_positions,
                           check_unique_ids, range_observe, resolve_outlier_gate, update_ranges)

__all__ = [
    "Config", "Params", "PARAMS", "Log", "Event", "State", "StepOut", "Result", "Startup",
    "init", "step", "run", "log_from_events", "util_events", "startup", "range_observe",
    "height_observe", "cv_motion", "cv_process_noise", "MODEL", "HEIGHT_ID", "TAG_Z", "NR",
]

NR = 7  # robot block [p (3), v (3), b]
HEIGHT_ID = -2  # id of a ToF height row in a UTIL event log (anchor ids are ≥ 0)
TAG_Z = float(TAG_OFFSET[2])  # UWB tag offset along the body z axis [m]


def height_observe(s, params):
    """(H1): ToF height h = p_z − t_uv,z + c_tof of the tag state s (7,); returns (1,).

    ``params``: :class:`Params` (uses ``tof_offset`` = c_tof [m]).  Tilt ignored.
    """
    return jnp.reshape(s[2] - TAG_Z + params.tof_offset, (1,))


def cv_motion(s, u, dt):
    """(CV): constant-velocity step of s = [p, v, b] (7,) over ``dt`` [s]; ``u`` unused."""
    dt = jnp.asarray(dt, s.dtype)
    return jnp.concatenate([s[0:3] + s[3:6] * dt, s[3:6], s[6:7]])


def cv_process_noise(dt, q_acc, q_bias, dtype=None):
    """(WNA) Q_d (7, 7): white-noise acceleration q_acc [m²/s³] per axis, bias walk q_bias [m²/s]."""
    dtype = dtype or jnp.result_type(q_acc)
    dt = jnp.asarray(dt, dtype)
    qa = jnp.asarray(q_acc, dtype)
    I3 = jnp.eye(3, dtype=dtype)
    top = jnp.concatenate([dt**3 / 3 * I3, dt**2 / 2 * I3], axis=1)
    bot = jnp.concatenate([dt**2 / 2 * I3, dt * I3], axis=1)
    Q6 = qa * jnp.concatenate([top, bot], axis=0)
    Q = jnp.zeros((NR, NR), dtype).at[:6, :6].set(Q6)
    return Q.at[6, 6].set(jnp.asarray(q_bias, dtype) * dt)


MODEL = es.SlamModel(robot_dim=NR, lm_dim=3, meas_dim=1, motion=cv_motion, observe=range_observe)


class Params(NamedTuple):
    """UTIL filter noise and gate (floats or traced scalars; module docstring for sources).

    sigma_r [m]; q_acc [m²/s³]; q_bias [m²/s]; p0_pos, p0_vel [m, m/s], p0_bias [m]:
    initial standard deviations (known-anchor mode).  sigma_h [m], tof_offset [m]: the
    optional ToF height update (H1) — used only when the log holds height rows.
    gate: χ²(1) threshold per range and per height row (default 9.0; None: off — None ↔ a
    number changes the pytree, a switch that traces once more; another number does not).
    nu: Student-t degrees of freedom ν of the ranges (None: Gaussian).  With ν each range's
    R is scaled by its EM weight (``robust=nu`` of :func:`jaxslam.filters.ekf_slam.update`):
    a heavy-tailed, never cut-off likelihood for non-line-of-sight ranges; ``Result.nll``
    is then the rows' Student-t terms.
    anchor_offset: (N,) per-anchor range offsets o_i [m] in ``log.anchor_ids`` order (None:
    zero): the ranges of anchor i are modelled as ‖p − a_i‖ + b + o_i + v (antenna delay and
    the mean non-line-of-sight excess of that anchor).  Only differences between anchors
    are identifiable beside the common bias b.
    outlier_gate: marginal d² above which a range counts as an outlier (``Result.n_outliers``;
    more than ``consistency.DIVERGED_FRACTION`` of them over the run sets ``DIVERGED``, whatever
    the update did with them — gated or down-weighted).  None (default): the 99 % quantile of
    the range model's own d² — χ²(1) (6.63) for Gaussian ranges, F(1, ν) for Student-t ranges
    (16.26 at ν = 5; :func:`jaxslam.stats.student_t_d2_ppf_np`, so ``nu`` must then be a number,
    not traced).
    """

    sigma_r: float = 0.2
    q_acc: float = 0.5
    q_bias: float = 1e-5
    p0_pos: float = 0.3
    p0_vel: float = 0.1
    p0_bias: float = 0.5
    sigma_h: float = 0.02
    tof_offset: float = -0.014
    gate: Optional[float] = 9.0
    nu: Optional[float] = None
    anchor_offset: Any = None
    outlier_gate: Optional[float] = None


PARAMS = Params()


class Config(NamedTuple):
    """Static choices (hashable; a change recompiles): sizes and switches (the gate is
    :attr:`Params.gate`, traced).

    n_fix: range rows of the initial fix (known anchors; the first ``n_fix`` range rows, the
    drone at rest; static: it sizes the fix's arrays).
    capacity: anchor slots (None: the number of anchors).  height: the log holds ToF height
    rows to fuse (H1); None: read it from the log (which must then be concrete, not traced).
    smooth: also return the RTS-smoothed tag states (``Result.smoothed``; the anchors held
    static).
    """

    n_fix: int = 16
    capacity: Optional[int] = None
    height: Optional[bool] = None
    smooth: bool = False


class Startup(NamedTuple):
    """Start-up of the unknown-anchor run (:func:`startup`).

    anchors: (N, 3) fitted anchors [m]; bias: () [m]; cov: (3N+1, 3N+1) joint covariance of
    [anchors (row-major), bias]; n_used: () ranges used; n_rejected: () ranges cut as
    outliers; rms: () residual RMS [m]; p0, v0: (3,) tag position / velocity at t_w from
    motion capture; t0: () t_w [s].  status: () int32 :mod:`jaxslam.errors` bits of the fit —
    ``DEGENERATE`` when an anchor kept fewer than 3 ranges in the window (its 3 coordinates are
    not fixed: it came back at (0, 0, 0) or anywhere, with a ~1e10 variance), ``NON_FINITE`` when
    a fitted value is NaN/Inf; :func:`run` ORs it into its status (None, as a hand-made start-up
    may leave it: no bits).
    """

    anchors: jax.Array
    bias: jax.Array
    cov: jax.Array
    n_used: jax.Array
    n_rejected: jax.Array
    rms: jax.Array
    p0: jax.Array
    v0: jax.Array
    t0: jax.Array
    status: Any = None


class Log(NamedTuple):
    """One flight's inputs (T events, K rows per event; a batch adds a leading axis).

    t: (T,) event times [s]; dt: (T,) s since the previous event; z: (T, K, 1) ranges [m] (or
    ToF heights [m] on rows with id :data:`HEIGHT_ID`); ids: (T, K) anchor id of each row;
    mask: (T, K) row present.  anchor_ids: (N,) the anchors' ids.  Exactly one of:
    anchors (N, 3) known positions [m] (localisation), or startup: a :class:`Startup` (SLAM,
    anchors as states; its window must precede the log).  The dtype of ``z`` is the
    computation dtype.  :func:`log_from_events` builds it from :func:`util_events`.
    """

    t: jax.Array
    dt: jax.Array
    z: jax.Array
    ids: jax.Array
    mask: jax.Array
    anchor_ids: jax.Array
    anchors: Any = None
    startup: Any = None


class Event(NamedTuple):
    """One event of a :class:`Log` (the slice :func:`step` takes)."""

    dt: jax.Array  # ()
    z: jax.Array  # (K, 1)
    ids: jax.Array  # (K,)
    mask: jax.Array  # (K,)


#: The state between events: the engine's posterior (tag, bias, anchors).
State = es.SlamState


class StepOut(NamedTuple):
    """What :func:`step` reports for its event (stacked into :class:`Result`)."""

    pos: jax.Array  # (3,)
    pos_var: jax.Array  # (3,)
    heading: jax.Array  # () zero (no heading)
    bias: jax.Array
    bias_var: jax.Array
    nis: jax.Array
    dof: jax.Array
    used: jax.Array
    gated: jax.Array
    height_used: jax.Array
    height_gated: jax.Array
    nll: jax.Array  # () innovation NLL of the event's ranges (filters.ekf_slam.update_nll)
    nll_dof: jax.Array  # () ranges in it
    outliers: jax.Array  # () int32 ranges of mapped anchors with d² > OUTLIER_GATE
    monitored: jax.Array  # () int32 ranges of mapped anchors offered to the update
    smoother: Any = None


def util_events(t, anchor_id, ranges, t_start=None, t_end=None, tof_t=None,
                tof=None) -> EventLog:
    """TWR rows (t [s], anchor id, range [m]) → an :class:`EventLog`, no input.

    ``anchor_id``: whole numbers that fit int32, never :data:`HEIGHT_ID` (reserved);
    ``t`` (and ``tof_t``): finite, non-decreasing (:class:`InputError` naming the argument otherwise).

    Optional ToF rows (``tof_t`` [s], ``tof`` [m], e.g. ``UtilData.tof_t/tof``) are merged
    in as rows with id :data:`HEIGHT_ID` (z = the laser height); :func:`run` then adds
    the height update (H1) (:func:`run`).  Rows are sorted by time (stable, ranges first at equal
    times).  Without ToF rows K = 1: a second range at the time of another (none on the UTIL
    flight; a line repeated by a logging fault) is dropped and counted
    (``EventLog.stats["dropped_overflow"]``, the dataset runner's ``dropped_beyond_K``); with
    them, K is the largest number of rows sharing a time.
    Without ToF rows the log is exactly the range-only one.
    """
    t = np.asarray(t, np.float64).reshape(-1)
    if t.size == 0:
        raise InputError("util_events: no ranges")
    z = np.asarray(ranges, np.float64).reshape(-1, 1)
    if anchor_id is None:  # (np.size(None) is 1: with one range it was read as id -1, "no id")
        raise InputError("anchor_id: expected the anchor id of each range, got None")
    if not (np.size(anchor_id) == t.size == z.shape[0]):
        raise InputError(f"util_events: t, anchor_id and ranges need one entry per range, got "
                         f"{t.size}, {np.size(anchor_id)} and {z.shape[0]}")
    # whole numbers that fit int32 (a bare cast made 1.5 → 1, 2**32 − 1 → −1, NaN → int32 min)
    ids = _ids(anchor_id, t.size, name="anchor_id")
    if np.any(ids == HEIGHT_ID):  # with or without ToF rows: run would fuse the row as a height
        raise InputError(f"util_events: anchor id {HEIGHT_ID} is reserved for height rows")
    if (tof_t is None) != (tof is None):
        raise InputError("util_events: give both tof_t and tof, or neither")
    if tof_t is None:
        check_times(t, "t")  # merge_events would name its own argument, meas_t
        return merge_events(t[:1], np.zeros((1, 1)), t, z, meas_ids=ids, K=1,
                            input_mode="rate", t_start=t_start, t_end=t_end)
    ht = np.asarray(tof_t, np.float64).reshape(-1)
    hz = np.asarray(tof, np.float64).reshape(-1, 1)
    if ht.shape[0] != hz.shape[0]:
        raise InputError(f"util_events: tof has {hz.shape[0]} rows but tof_t {ht.shape[0]}")
    for a, name in ((t, "t"), (ht, "tof_t")):  # merge_events named the merged array's meas_t and index
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name}: non-finite time at index {int(np.argmin(np.isfinite(a)))}")
    if t.size > 1 and np.any(np.diff(t) < 0):
        raise InputError("util_events: range times decrease")
    if ht.size > 1 and np.any(np.diff(ht) < 0):
        raise InputError("util_events: tof times decrease")
    ta = np.concatenate([t, ht])
    o = np.argsort(ta, kind="stable")
    za = np.concatenate([z, hz])[o]
    ia = np.concatenate([ids, np.full(ht.shape, HEIGHT_ID, np.int32)])[o]
    return merge_events(t[:1], np.zeros((1, 1)), ta[o], za, meas_ids=ia, K=None,
                        input_mode="rate", t_start=t_start, t_end=t_end)


def log_from_events(events: EventLog, anchor_ids, anchors=None, startup: Optional[Startup] = None,
                    dtype=None) -> Log:
    """The :class:`Log` of a :func:`util_events` log with the anchors (known) or a start-up (SLAM).

    dtype: float32/float64 of the run (default: JAX's default float, x64 setting).
    """
    if not isinstance(events, EventLog):
        raise InputError("events: expected a jaxslam.data.events.EventLog")
    if events.z.shape[-1] != 1:
        raise InputError(f"events.z: expected one range per row (d_z = 1), got {events.z.shape[-1]}")
    dtype = dtype or jnp.result_type(float)
    return Log(t=jnp.asarray(events.t, dtype), dt=jnp.asarray(events.dt, dtype), z=jnp.asarray(events.z, dtype),
               ids=jnp.asarray(events.ids, jnp.int32), mask=jnp.asarray(events.mask, bool),
               anchor_ids=jnp.asarray(anchor_ids, jnp.int32),
               anchors=None if anchors is None else jnp.asarray(anchors, dtype),
               startup=None if startup is None else Startup(*[None if a is None else jnp.asarray(a) for a in startup]))


def _gn_joint(P, Z, idx, w, A0, b0, iters, prior_w):
    """Gauss–Newton on r_i = z_i − ‖p_i − a_{idx_i}‖ − b over θ = [A (N,d), b], weights w,
    plus one prior row prior_w · b (b ~ N(0, (σ_r / prior_w)²))."""
    N, d = A0.shape

    def resid(theta):
        A = theta[:-1].reshape(N, d)
        diff = P - A[idx]
        r = (Z - jnp.sqrt(jnp.sum(diff * diff, axis=1)) - theta[-1]) * w
        return jnp.concatenate([r, jnp.reshape(prior_w * theta[-1], (1,))])

    theta = jnp.concatenate([A0.reshape(-1), jnp.reshape(b0, (1,))])

    def body(th, _):
        r = resid(th)
        J = jax.jacfwd(resid)(th)
        H = J.T @ J + 1e-9 * jnp.eye(th.shape[0], dtype=th.dtype)
        step = jnp.linalg.solve(H, J.T @ r)
        step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
        return th - step, None

    theta, _ = jax.lax.scan(body, theta, None, length=iters)
    return theta, resid


def startup(t, anchor_id, ranges, tag_pos, anchor_ids, t_window, v0=None,
                 sigma_r=0.15, bias_prior_sigma=0.3, iters: int = 8) -> Startup:
    """Joint robust least squares of anchors and bias over the start-up window [0, t_w].

    t: (M,) range times [s]; anchor_id: (M,) int; ranges: (M,) [m]; tag_pos: (M, 3) the
    motion-capture tag position at each range time [m] (used only where t ≤ t_w);
    anchor_ids: (N,) ids to fit; t_window: t_w [s]; v0: optional (3,) motion-capture
    velocity at t_w (default zeros).  sigma_r: range σ [m] weighting the bias prior
    b ~ N(0, bias_prior_sigma²) [m].  Without that prior the bias trades off against the
    radial anchor distances (the start-up window's path spans ~1.5 m, anchors are 3–5 m
    away): measured on this flight, the unregularised fit put the bias at −3.2 m and every
    anchor 3 m off.  The prior 0 ± 0.3 m states only that a TWR bias is decimetres (the
    sign and size are left to the data).  Pure and jit-safe (dtype follows ``ranges``).

    Checked first (:class:`InputError` naming the argument): shapes (M,), (M, 3), (N,), (3,);
    ``iters`` an int >= 1; ``sigma_r``, ``bias_prior_sigma`` positive and ``t_window`` finite
    when concrete; with concrete values, at least one range of every anchor in the window (an
    anchor without one came back at (0, 0, 0) with a 2e10 variance, unflagged; under ``jit``, where
    the values are not known, it still does, and ``Startup.status`` carries ``DEGENERATE``).  Called eagerly it is compiled once per shape and ``iters``
    (:func:`jaxslam.compilation.call_compiled`; op by op every call re-compiled its two scans).
    """
    iters = check_int(iters, "iters", 1, what="an int (Gauss–Newton iterations)")
    M = int(np.size(t))
    if np.ndim(t) != 1:
        raise InputError(f"t: expected shape (M,) (one time per range), got {np.shape(t)}")
    for a, name in ((anchor_id, "anchor_id"), (ranges, "ranges")):
        if np.shape(a) != (M,):
            raise InputError(f"{name}: expected shape ({M},) (one per range, as t), got {np.shape(a)}")
    if np.shape(tag_pos) != (M, 3):
        raise InputError(f"tag_pos: expected shape ({M}, 3) (one tag position per range), got {np.shape(tag_pos)}")
    if np.ndim(anchor_ids) != 1 or np.shape(anchor_ids)[0] == 0:
        raise InputError(f"anchor_ids: expected shape (N,), N >= 1, got {np.shape(anchor_ids)}")
    if v0 is not None and np.shape(v0) != (3,):
        raise InputError(f"v0: expected shape (3,), got {np.shape(v0)}")
    for a, name in ((sigma_r, "sigma_r"), (bias_prior_sigma, "bias_prior_sigma")):
        if is_concrete(a):
            check_scalar(a, name, lower=0, strict=True)
    if is_concrete(t_window):
        check_scalar(t_window, "t_window")
    if is_concrete(t, anchor_id, ranges, tag_pos, anchor_ids, t_window):
        tn = np.asarray(t, np.float64)
        win = ((tn <= float(t_window)) & np.isfinite(np.asarray(ranges, np.float64))
               & np.all(np.isfinite(np.asarray(tag_pos, np.float64)), axis=1))
        seen = np.isin(np.asarray(anchor_ids), np.asarray(anchor_id)[win])
        if not np.any(win):
            raise InputError(f"t_window: no finite range (with a finite tag_pos) at t <= {float(t_window)!r}: "
                             "the start-up window is empty")
        if not np.all(seen):
            raise InputError(f"anchor_ids: anchor {np.asarray(anchor_ids)[np.argmin(seen)].item()!r} has no range in "
                             f"the start-up window t <= {float(t_window)!r} (it cannot be fitted)")
    return call_compiled(("util_range.startup", iters),
                         lambda opts, *a: _startup(*a, *opts, iters),
                         (t, anchor_id, ranges, tag_pos, anchor_ids), (t_window, v0, sigma_r, bias_prior_sigma),
                         after=1)


def _startup(t, anchor_id, ranges, tag_pos, anchor_ids, t_window, v0, sigma_r, bias_prior_sigma,
             iters: int) -> Startup:
    """:func:`startup` of checked arguments."""
    ranges = jnp.asarray(ranges)
    dtype = ranges.dtype if jnp.issubdtype(ranges.dtype, jnp.floating) else jnp.result_type(float)
    t = jnp.asarray(t, dtype)
    Z = ranges.astype(dtype)
    Pm = jnp.asarray(tag_pos, dtype)
    aid = jnp.asarray(anchor_id, jnp.int32)
    ids = jnp.asarray(anchor_ids, jnp.int32)
    N = ids.shape[0]
    win = (t <= t_window) & jnp.isfinite(Z) & jnp.all(jnp.isfinite(Pm), axis=1)
    eq = aid[:, None] == ids[None, :]
    idx = jnp.argmax(eq, axis=1)
    win = win & jnp.any(eq, axis=1)
    # starting point: linear trilateration of each anchor (paper 003 eq. 26), bias 0
    tr = jax.vmap(lambda k: tri.trilaterate(Pm, Z, mask=win & (idx == k)))(jnp.arange(N))
    w = win.astype(dtype)
    pw = jnp.asarray(sigma_r, dtype) / jnp.asarray(bias_prior_sigma, dtype)
    theta, resid = _gn_joint(Pm, Z, idx, w, tr.position, jnp.zeros((), dtype), iters, pw)
    r = resid(theta)[:-1]
    mad = jnp.nanmedian(jnp.abs(jnp.where(win, r, jnp.nan) - jnp.nanmedian(jnp.where(win, r, jnp.nan))))
    cut = jnp.maximum(4.0 * 1.4826 * mad, 0.05)
    keep = win & (jnp.abs(r - jnp.nanmedian(jnp.where(win, r, jnp.nan))) <= cut)
    w2 = keep.astype(dtype)
    theta, resid = _gn_joint(Pm, Z, idx, w2, theta[:-1].reshape(N, 3), theta[-1], iters, pw)
    J = jax.jacfwd(resid)(theta)
    r = resid(theta)[:-1]
    n = jnp.sum(w2)
    # covariance with the stated σ_r (the post-cut residual RMS underrates correlated errors)
    s2 = jnp.maximum(jnp.sum(r * r) / jnp.maximum(n - theta.shape[0], 1.0),
                     jnp.asarray(sigma_r, dtype) ** 2)
    eye = jnp.eye(theta.shape[0], dtype=dtype)
    cov = s2 * jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(J.T @ J + 1e-12 * eye), True), eye)
    # motion-capture position at t_w: the last window sample's tag position
    last = jnp.argmax(jnp.where(win, t, -jnp.inf))
    # an anchor with < 3 kept ranges is not fixed (3 unknowns): DEGENERATE, carried into the run
    n_per = jnp.sum(keep[:, None] & (idx[:, None] == jnp.arange(N)[None, :]), axis=0)
    finite = jnp.all(jnp.isfinite(theta)) & jnp.all(jnp.isfinite(cov)) & jnp.all(jnp.isfinite(Pm[last]))
    status = (jnp.where(jnp.any(n_per < 3), errors.DEGENERATE, 0)
              | jnp.where(finite, 0, errors.NON_FINITE)).astype(jnp.int32)
    return Startup(anchors=theta[:-1].reshape(N, 3), bias=theta[-1], cov=symmetrize(cov),
                       n_used=jnp.sum(keep).astype(jnp.int32),
                       n_rejected=jnp.sum(win & ~keep).astype(jnp.int32),
                       rms=jnp.sqrt(jnp.sum(r * r) / jnp.maximum(n, 1.0)), p0=Pm[last],
                       v0=jnp.zeros(3, dtype) if v0 is None else jnp.asarray(v0, dtype),
                       t0=jnp.asarray(t_window, dtype), status=status)


def _height_update(st, z_k, id_k, m_k, params, gate):
    """(H1) for each of the event's K rows that is a height row (static loop over K).

    Gated like a range: NIS ν²/S > gate, S = P_zz + σ_h² (H = e_z, so H P Hᵀ = P_zz).
    Returns (state, nis, dof, used (), gated ()) summed over the rows.  A non-finite height
    row is neither used nor gated: it sets ``MASKED_INPUT`` (as a non-finite range does).
    """
    model = MODEL
    R = jnp.reshape(params.sigma_h**2, (1, 1))
    nis = jnp.zeros((), st.x.dtype)
    dof = jnp.zeros((), jnp.int32)
    used = jnp.zeros((), jnp.int32)
    gated = jnp.zeros((), jnp.int32)
    for k in range(z_k.shape[0]):  # static, K ≤ 2 on UTIL
        hk = m_k[k] & (id_k[k] == HEIGHT_ID) & jnp.isfinite(z_k[k, 0])
        nu = z_k[k, 0] - height_observe(st.x[:NR], params)[0]
        nis_k = nu * nu / (st.P[2, 2] + params.sigma_h**2)
        g = (hk & (nis_k > gate)) if gate is not None else jnp.zeros((), bool)
        st, info = es.update_robot(st, model, height_observe, z_k[k], hk & ~g, R, params=params)
        nis = nis + info.nis
        dof = dof + info.dof.astype(jnp.int32)
        used = used + jnp.sum(info.used).astype(jnp.int32)
        gated = gated + g.astype(jnp.int32)
        bad = m_k[k] & (id_k[k] == HEIGHT_ID) & ~jnp.isfinite(z_k[k, 0])
        st = st._replace(status=st.status | jnp.where(bad, jnp.int32(errors.MASKED_INPUT), jnp.int32(0)))
    return st, nis, dof, used, gated


def _fix_rows(log: Log, n_fix: int):
    """The first ``n_fix`` range rows (height rows skipped) of the log: (z0, ids0, present)."""
    rr = (log.mask & (log.ids != HEIGHT_ID)).reshape(-1)
    idx = jnp.nonzero(rr, size=n_fix, fill_value=0)[0]
    present = jnp.arange(n_fix) < jnp.sum(rr)
    return log.z[..., 0].reshape(-1)[idx], jnp.where(present, log.ids.reshape(-1)[idx], -1), present


def init(log: Log, config: Config, params: Params, *, key=None) -> State:
    """The state before the first event.  Known anchors: the tag fixed by trilateration of the
    first ``config.n_fix`` range rows (the drone at rest), v = 0, b = 0, covariance from
    ``params.p0_*``, the anchors in the map with zero covariance.  SLAM: the start-up's tag
    position and velocity (σ 0.02 m, 0.1 m/s), its anchors and bias with their joint covariance
    — the state at ``startup.t0``, which :func:`run` predicts to the first event (its Δt is
    ``t[0] − t0``)."""
    del key
    dtype = log.z.dtype
    N = log.anchor_ids.shape[0]
    cap = int(config.capacity or N)
    if log.anchors is not None:
        z0, ids0, present = _fix_rows(log, int(config.n_fix))
        eq = ids0[:, None] == log.anchor_ids[None, :]
        pts = log.anchors[jnp.argmax(eq, axis=1)]
        if params.anchor_offset is not None:  # the fix sees the ranges as the update does
            z0 = z0 - jnp.where(jnp.any(eq, axis=1), params.anchor_offset[jnp.argmax(eq, axis=1)], 0.0)
        fix = tri.trilaterate(pts, z0, mask=jnp.any(eq, axis=1) & present)
        s0 = jnp.concatenate([fix.position, jnp.zeros(4, dtype)])
        p0 = jnp.asarray([params.p0_pos] * 3 + [params.p0_vel] * 3 + [params.p0_bias], dtype)
        st = es.preload(es.init(s0, jnp.diag(p0 * p0), cap, 3), MODEL, log.anchors, ids=log.anchor_ids)
        return st._replace(status=st.status | jnp.where(fix.ok, 0, errors.DEGENERATE).astype(jnp.int32))
    su = log.startup
    s0 = jnp.concatenate([su.p0, su.v0, jnp.reshape(su.bias, (1,))]).astype(dtype)
    st = es.init(s0, jnp.zeros((NR, NR), dtype), cap, 3)
    P = st.P
    P = P.at[0:3, 0:3].set(jnp.eye(3, dtype=dtype) * 0.02**2)
    P = P.at[3:6, 3:6].set(jnp.eye(3, dtype=dtype) * 0.1**2)
    m = 3 * N
    # joint [anchors, bias] covariance: bias ↔ robot index 6, anchors ↔ map slots 0..N−1
    sel = jnp.concatenate([jnp.arange(NR, NR + m), jnp.asarray([6])])
    P = P.at[sel[:, None], sel[None, :]].set(su.cov.astype(dtype))
    x = st.x.at[NR:NR + m].set(su.anchors.reshape(-1).astype(dtype))
    status = st.status if su.status is None else st.status | jnp.asarray(su.status).astype(st.status.dtype)
    return st._replace(x=x, P=symmetrize(P), active=st.active.at[:N].set(True),
                       ids=st.ids.at[:N].set(log.anchor_ids), status=status)


def step(state: State, event: Event, config: Config, params: Params, *, key=None):
    """One event: constant-velocity prediction over ``event.dt``, the ranges' update (each gated
    on its χ²(1) NIS), then the height rows (H1) when ``config.height``.  ``(state, StepOut)``."""
    del key
    st = state
    gate = params.gate
    height = bool(config.height)
    Q = cv_process_noise(event.dt, params.q_acc, params.q_bias, st.x.dtype)
    st = es.predict(st, MODEL, None, Q, event.dt)
    m_r = (event.mask & (event.ids != HEIGHT_ID)) if height else event.mask
    slots, mapped = es.associate_known(st, event.ids, m_r)
    z = event.z
    if params.anchor_offset is not None:  # anchor i sits in map slot i (init)
        off = jnp.take(params.anchor_offset, slots, mode="clip")
        z = z - jnp.where(mapped, off, 0.0)[:, None]
    st, info, nll, nll_dof, n_out = update_ranges(st, MODEL, z, slots, mapped, params)
    nis, dof = info.nis, info.dof
    zi = jnp.zeros((), jnp.int32)
    h_used = h_gated = zi
    if height:
        st, h_nis, h_dof, h_used, h_gated = _height_update(st, event.z, event.ids, event.mask, params, gate)
        nis, dof = nis + h_nis, dof + h_dof.astype(jnp.asarray(dof).dtype)
    Pd = jnp.diagonal(st.P)
    out = StepOut(pos=st.x[0:3], pos_var=Pd[0:3], heading=jnp.zeros((), st.x.dtype), bias=st.x[6],
                  bias_var=Pd[6], nis=nis, dof=dof, used=jnp.sum(info.used).astype(jnp.int32),
                  gated=jnp.sum(info.gated).astype(jnp.int32), height_used=h_used, height_gated=h_gated,
                  nll=nll, nll_dof=nll_dof, outliers=n_out, monitored=jnp.sum(mapped).astype(jnp.int32),
                  smoother=(es.smoother_terms(st, MODEL), Q) if config.smooth else None)
    return st, out


def run(log: Log, config: Config = Config(), params: Params = PARAMS, *, key=None) -> Result:
    """Range-only CV tracking (``log.anchors``) or SLAM (``log.startup``) over a UTIL TWR log, as
    one jitted ``lax.scan`` of :func:`step`.  Returns :class:`Result` (heading zeros).  ``key`` is
    not used (accepted as every system's ``run`` accepts it).  ``config.height`` None is read
    from the log (height rows present).  SLAM: the start-up state holds at ``startup.t0`` and the
    first event's Δt is ``t[0] − t0`` (``log.dt[0]`` is replaced: the state is predicted across the
    gap); the log must not start before t0.  A start-up of another number of anchors than
    ``log.anchor_ids``, non-finite start-up values or t[0] < t0 (when concrete) raise
    :class:`InputError`; ``startup.status`` (a fit's ``DEGENERATE`` / ``NON_FINITE``) is OR-ed
    into ``Result.status``.
    """
    del key
    if (log.anchors is None) == (log.startup is None):
        raise InputError("log: give exactly one of anchors (known) or startup (SLAM)")
    N = check_ids_vector(log.anchor_ids, "log.anchor_ids")
    cap = N if config.capacity is None else check_int(config.capacity, "config.capacity")
    if cap < N:
        raise InputError(f"config.capacity: {cap} < number of anchors {N}")
    check_log(log)  # t, dt, z, ids, mask: one length T >= 1; dt >= 0, whole ids
    if log.anchors is not None and np.shape(log.anchors) != (N, 3):
        raise InputError(f"log.anchors: expected shape ({N}, 3), got {np.shape(log.anchors)}")
    check_unique_ids(log.anchor_ids, "log.anchor_ids")
    check_positions(log.anchors, "log.anchors")
    if log.startup is not None:
        _check_startup(log, N)
    check_params(params, positive=("sigma_r", "p0_pos", "p0_vel", "p0_bias", "sigma_h"),
                 nonneg=("q_acc", "q_bias"), finite=("tof_offset",))
    if log.anchors is not None:
        check_int(config.n_fix, "config.n_fix", what="an int (range rows of the start fix)")
    if params.anchor_offset is not None and np.shape(params.anchor_offset) != (N,):
        raise InputError(f"params.anchor_offset: expected shape ({N},) (one offset per anchor), "
                         f"got {np.shape(params.anchor_offset)}")
    check_positions(params.anchor_offset, "params.anchor_offset")  # a NaN offset lost that anchor's ranges
    params = resolve_outlier_gate(params)
    if config.height is not None:
        check_flag(config.height, "config.height")
    check_flag(config.smooth, "config.smooth")
    if config.height is None:
        if not is_concrete(log.ids, log.mask):
            raise InputError("config.height: give True or False when the log is traced")
        config = config._replace(height=bool(np.any(np.asarray(log.mask) & (np.asarray(log.ids) == HEIGHT_ID))))
    dtype = jnp.asarray(log.z).dtype
    return _run(log, config._replace(capacity=cap, smooth=bool(config.smooth)), _cast_params(params, dtype))


def _check_startup(log: Log, N: int) -> None:
    """``log.startup``: shapes for N anchors; finite values and t0 <= t[0] when concrete."""
    su = log.startup
    if not isinstance(su, Startup):
        raise InputError("log.startup: expected a util_range.Startup")
    want = {"anchors": (N, 3), "bias": (), "cov": (3 * N + 1, 3 * N + 1), "p0": (3,), "v0": (3,), "t0": ()}
    if su.status is not None:
        want["status"] = ()
    for f, shp in want.items():
        if np.shape(getattr(su, f)) != shp:
            raise InputError(f"log.startup.{f}: expected shape {shp} (the start-up of the log's {N} anchors), "
                             f"got {np.shape(getattr(su, f))}")
        check_positions(getattr(su, f), f"log.startup.{f}")
    if is_concrete(log.t, su.t0):
        tt = np.asarray(log.t)
        t0 = np.asarray(su.t0).astype(tt.dtype)
        if tt[0] < t0:
            raise InputError(f"log.startup.t0: the start-up state holds at t0 = {float(t0)!r} s, after the "
                             f"log's first event t[0] = {float(tt[0])!r} s (the window must precede the log)")


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params) -> Result:
    st0 = init(log, config, params)
    dt = log.dt
    if log.startup is not None:  # the start-up state holds at t0: predict it across the gap to t[0]
        dt = dt.at[0].set(log.t[0] - jnp.asarray(log.startup.t0).astype(dt.dtype))
        log = log._replace(dt=dt)
    events = Event(dt=log.dt, z=log.z, ids=log.ids, mask=log.mask)
    st, outs = jax.lax.scan(lambda s, ev: step(s, ev, config, params), st0, events)
    rs = sst = None
    if config.smooth:
        terms, Qs = outs.smoother
        rs, sst = es.smooth_robot(MODEL, terms, None, Qs, st, params=log.dt)
    fields = (outs.pos, outs.pos_var, outs.heading, outs.bias, outs.bias_var, outs.nis, outs.dof, outs.used,
              outs.gated, outs.height_used, outs.height_gated)
    st = st._replace(status=st.status | cons.status_bits(jnp.sum(outs.outliers), jnp.sum(outs.monitored)))
    # range rows whose id is no anchor of the log: never used, counted (not silently lost)
    n_unm = jnp.sum(log.mask & (log.ids != HEIGHT_ID) & ~jnp.isin(log.ids, log.anchor_ids)).astype(jnp.int32)
    return _result(log.t, fields, st, MODEL, log.anchor_ids.shape[0], n_unm, rs, sst, outs.nll, outs.nll_dof,
                   outs.outliers, outs.monitored)
