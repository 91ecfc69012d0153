"""CMU Plaza range-only SLAM: 2D odometry increments, beacons, a common range bias.

A *system* module on the generic EKF-SLAM engine (:mod:`jaxslam.filters.ekf_slam`); one run is
one jitted ``lax.scan`` of :func:`step`; nothing raises inside ``jit``.  Units: m, s, rad.  The
range model (R1) is :func:`jaxslam.systems.biased_range.range_observe`: z = ‖p − l‖ + b + v.

Plaza, 2D odometry + beacons (:func:`run`; SLAM by default, localisation with
``log.beacons`` the surveyed TL positions).  Robot s = [x, y, θ, b]
(4); input u = (d, dθ), the DR increment, applied at its own event
(``merge_events(..., input_mode="increment")``)::

    (x, y, θ) ← (x, y, θ) ∘ Pose2(d, 0, dθ) = (x + d cos θ, y + d sin θ, θ + dθ)   (ODO)
    Q_d = G_u diag(σ_d², σ_θ²) G_uᵀ ⊕ q_b Δt,   G_u = ∂(ODO)/∂u (jacfwd)
    σ_d = α_d |d| + σ_d0 √Δt,   σ_θ = α_θ |dθ| + β_θ |d| + σ_θ0 √Δt

Odometry noise (``PARAMS``, chosen; then checked on both logs):
α_d = 0.05, α_θ = 0.05, β_θ = 0.002 rad/m, floors σ_d0 = 0.01 m/√s,
σ_θ0 = 0.003 rad/√s.  Range noise σ_r = 1.2 m (the README's MAD 0.8–1.2 m of
the range error is the *core* spread; gtsam uses σ = 100 with a Tukey kernel),
gate χ²(1) = 6.63 (99 %) against the ~6.8 m outliers, bias prior
b₀ = 0 ± 5 m, q_b = 1e-4 m²/s.  Start pose: GT₀ (the caller adds π to Plaza 2's
heading, data README).

*Bias observability on Plaza* (measured): a robust batch fit of the four beacons and
the bias with the **GPS ground-truth poses** (Huber, scipy) gives b = +0.2 m (Plaza 1)
and +1.8 m (Plaza 2), with every beacon 2.7–3.1 m (Plaza 1) off its surveyed TL
position: the README's +2.8 m "bias" (median of measured − true distance to TL)
is, on this geometry, indistinguishable from the beacons sitting ~3 m further
out, so no filter can be expected to recover +2.8 m; the filter's b and
beacon errors are reported as they come.  SLAM (measured): b = −0.54 ± 0.30 m /
+0.89 ± 0.11 m, ATE(rigid) 0.88 / 1.87 m, raw RMS 1.26 / 4.66 m (Plaza 1 / 2).

*Localisation with surveyed beacons* (``log.beacons = node_xy``): the
TL positions are held in the map with zero covariance (as UTIL's known anchors),
so the bias is observable.  Measured (same noise parameters): b = +2.36 ± 0.10 m
(Plaza 1; mean over the second half of the log +2.54 m) and +2.60 ± 0.08 m
(Plaza 2; +2.64 m), against the README's median measured − true +2.84 / +2.80 m
(the gated-core mean is +2.80 / +2.88 m): the final b lies 4.8 σ_b / 2.5 σ_b
below that median, so σ_b is optimistic (range errors are correlated in time,
and per node the median offset runs 2.75–3.04 m on Plaza 1 but 1.9–3.7 m on
Plaza 2, which one common b cannot absorb).  Position: raw RMS 1.21
/ 0.95 m, ATE(rigid) 1.19 / 0.89 m; ranges used 3527 / 1758, gated 2 / 58.

*Delayed beacon initialisation* (paper 003's idea, issue 6's buffer): while a
beacon is unmapped, each of its ranges is stored with the current position
estimate and that position's variance in a per-beacon ring buffer (W rows).
Once ≥ ``params.min_points`` rows are stored and the buffered positions spread
≥ ``params.min_spread`` m in their weakest direction (:func:`trilateration.point_spread`),
the beacon is trilaterated from the ranges minus the current bias estimate,
refitted once without the rows whose residual exceeds max(3·1.4826·MAD, 1 m)
(the outliers) (:func:`jaxslam.filters.delayed_init.from_buffer`, robust, eq. D1),
and added with P_ll = Σ_LS(σ_r²) + mean position variance · I + G_b σ_b² G_bᵀ and the
cross-covariance P_lx = G_b P_b,: with the whole state, G_b = ∂l/∂b by
``jax.jvp`` through the (fixed-mask) trilateration, with the fit itself in the same pass
(every beacon's fit in one ``vmap``, the registrations in one ``lax.scan`` over the beacons) —
so the filter knows the beacon moves with the bias.  Cross-covariances with the buffered poses
are not formed (as paper 003's start-up).
"
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..data.events import EventLog, merge_events
from ..dynamics import planar
from .. import errors
from ..errors import InputError
from ..filters import consistency as cons
from ..filters import ekf_slam as es
from ..filters import delayed_init
from ..linalg import check_int, check_scalar, check_whole_ids, is_concrete, symmetrize, wrap_angle
from .biased_range import (Result, _cast_params, _result, check_ids_vector, check_log, check_params, check_positions,
                           check_unique_ids, range_observe, resolve_outlier_gate, update_ranges)

__all__ = [
    "Config", "Params", "PARAMS", "Log", "Event", "State", "StepOut", "Result", "init", "step", "run",
    "log_from_events", "plaza_events", "range_observe", "odo_motion", "odo_process_noise", "MODEL", "NR",
]

NR = 4  # robot block [x, y, θ, b]


def odo_motion(s, u, params=None):
    """(ODO): s = [x, y, θ, b] ∘ Pose2(d, 0, dθ) with u = (d, dθ) (``planar.odometry_increment``); b unchanged."""
    return jnp.concatenate([planar.odometry_increment(s[:3], u), s[3:]])


def odo_process_noise(s, u, dt, params: "Params"):
    """Q_d (4, 4) of (ODO): G_u diag(σ_d², σ_θ²) G_uᵀ (G_u by jacfwd) plus the bias walk."""
    dtype = s.dtype
    u = jnp.asarray(u, dtype)
    dt = jnp.asarray(dt, dtype)
    ad, ath, bth = params.alpha_d, params.alpha_th, params.beta_th
    sq = jnp.sqrt(jnp.maximum(dt, 0.0))
    sd = ad * jnp.abs(u[0]) + params.sigma_d0 * sq
    sth = ath * jnp.abs(u[1]) + bth * jnp.abs(u[0]) + params.sigma_th0 * sq
    G = jax.jacfwd(odo_motion, argnums=1)(s, u)
    Q = G @ jnp.diag(jnp.stack([sd * sd, sth * sth])) @ G.T
    return Q.at[3, 3].add(params.q_bias * dt)


MODEL = es.SlamModel(robot_dim=NR, lm_dim=2, meas_dim=1, motion=odo_motion, observe=range_observe)


class Params(NamedTuple):
    """Plaza filter noise and thresholds (module docstring for values and sources); every field is
    traced, so a new value never recompiles.

    sigma_r [m]; alpha_d, alpha_th [-], beta_th [rad/m], sigma_d0 [m/√s], sigma_th0 [rad/√s]:
    odometry noise (ODO); q_bias [m²/s]; bias0, sigma_bias0 [m]: bias prior; p0_pos [m],
    p0_th [rad]: initial pose standard deviations.
    gate: χ²(1) threshold per range (default 6.63, 99 %; None: off — None ↔ a number changes the
    pytree, a switch that traces once more; another number does not).
    min_points: buffered rows a beacon needs before its delayed initialisation (default 20; a
    count, only compared).  min_spread: weakest-direction spread of those rows' positions [m]
    (default 5.0).  Both unused with surveyed beacons.
    nu: Student-t degrees of freedom of the ranges (None: Gaussian; as ``util_range.Params.nu``).
    outlier_gate: marginal d² above which a range of a mapped beacon counts as an outlier (None:
    the range model's own 99 % quantile, :func:`biased_range.resolve_outlier_gate`); more than
    10 % of them sets ``DIVERGED``.
    """

    sigma_r: float = 1.2
    alpha_d: float = 0.05
    alpha_th: float = 0.05
    beta_th: float = 0.002
    sigma_d0: float = 0.01
    sigma_th0: float = 0.003
    q_bias: float = 1e-4
    bias0: float = 0.0
    sigma_bias0: float = 5.0
    p0_pos: float = 0.1
    p0_th: float = 0.02
    gate: Optional[float] = 6.63
    min_points: float = 20.0
    min_spread: float = 5.0
    nu: Optional[float] = None
    outlier_gate: Optional[float] = None


PARAMS = Params()


class Config(NamedTuple):
    """Static choices (hashable; a change recompiles): sizes and switches.

    window: delayed-initialisation ring-buffer rows per beacon (a shape; unused with surveyed
    beacons; the gate and the initialisation thresholds are :class:`Params` fields).
    capacity: beacon slots (None: the number of beacons).
    smooth: also return the RTS-smoothed robot states [x, y, θ, b] (``Result.smoothed``;
    beacons held static, a beacon counts from its initialisation on).  delayed: run the delayed
    initialisation in :func:`step` (None: when the log has no surveyed beacons; with them every
    beacon is mapped from the start and the step skips it statically).
    """

    window: int = 60
    capacity: Optional[int] = None
    smooth: bool = False
    delayed: Optional[bool] = None


class Log(NamedTuple):
    """One run's inputs (T events, K rows per event).

    t: (T,) [s]; dt: (T,) [s]; u: (T, 2) DR increments (d [m], dθ [rad]) at their own events
    (zero elsewhere); z: (T, K, 1) ranges [m]; ids: (T, K) beacon id per row; mask: (T, K) row
    present; pose0: (3,) start pose (x, y, θ) [m, rad] (Plaza 2: GT₀ heading + π, the caller's
    job); beacon_ids: (N,) the beacons' ids (ranges to other ids are ignored); beacons: None →
    the beacons are unknown and mapped by delayed initialisation (SLAM); (N, 2) surveyed
    positions, row i for ``beacon_ids[i]`` → localisation (held with zero covariance, so only
    the pose and the bias are estimated).  ``z``'s dtype is the computation dtype.
    """

    t: jax.Array
    dt: jax.Array
    u: jax.Array
    z: jax.Array
    ids: jax.Array
    mask: jax.Array
    pose0: jax.Array
    beacon_ids: jax.Array
    beacons: Any = None


class Event(NamedTuple):
    """One event of a :class:`Log` (the slice :func:`step` takes)."""

    dt: jax.Array
    u: jax.Array
    z: jax.Array
    ids: jax.Array
    mask: jax.Array


class _Buf(NamedTuple):
    pos: jax.Array  # (N, W, 2)
    pos_var: jax.Array  # (N, W)
    rng: jax.Array  # (N, W)
    count: jax.Array  # (N,) int32 rows written


class State(NamedTuple):
    """The state between events: the engine's posterior, the per-beacon ring buffers of the
    delayed initialisation, the beacons registered and the ranges of unmapped beacons so far, and
    the log's beacon ids (constant)."""

    slam: es.SlamState
    buf: _Buf
    n_registered: jax.Array
    n_unmapped: jax.Array
    beacon_ids: jax.Array


class StepOut(NamedTuple):
    """What :func:`step` reports for its event (stacked into :class:`Result`)."""

    pos: jax.Array  # (2,)
    pos_var: jax.Array  # (2,)
    heading: jax.Array
    bias: jax.Array
    bias_var: jax.Array
    nis: jax.Array
    dof: jax.Array
    used: jax.Array
    gated: jax.Array
    nll: jax.Array  # () innovation NLL of the event's ranges (filters.ekf_slam.update_nll)
    nll_dof: jax.Array  # () ranges in it
    outliers: jax.Array  # () int32 ranges of mapped beacons with d² > params.outlier_gate
    monitored: jax.Array  # () int32 ranges of mapped beacons offered to the update
    smoother: Any = None


def plaza_events(dr_t, dr, td_t, td_node, td_range, K: Optional[int] = None, t_end=None) -> EventLog:
    """DR increments (t, (d, dθ)) and TD ranges (t, node, range) → an increment-mode EventLog
    (``t_end``: the events up to that time [s], inclusive).

    Range rows are sorted by time first (stable): Plaza 1's TD file is not in time order
    (row 1988 jumps back from 5103.6 s to 5039.3 s).

    Shapes: ``dr`` (len(dr_t), 2); ``td_node`` and ``td_range`` one entry per ``td_t`` ((M,) or
    (M, 1)); ``td_node`` whole numbers.  Anything else is an :class:`InputError` naming the
    argument (a transposed ``dr`` or a two-column ``td_range`` was reshaped into wrong pairs, a
    fractional or NaN node id cast onto another id).
    """
    n_dr = int(np.size(dr_t))
    if np.shape(dr) != (n_dr, 2):
        raise InputError(f"dr: expected shape ({n_dr}, 2) (one (d, dθ) increment per dr_t), got {np.shape(dr)}")
    td_t = np.asarray(td_t, np.float64).reshape(-1)
    M = td_t.shape[0]
    for a, name in ((td_node, "td_node"), (td_range, "td_range")):
        if np.shape(a) not in ((M,), (M, 1)):
            raise InputError(f"{name}: expected shape ({M},) (one entry per td_t), got {np.shape(a)}")
    check_whole_ids(td_node, "td_node")  # 10.7 was cast to 10, NaN to -2147483648
    o = np.argsort(td_t, kind="stable")
    return merge_events(np.asarray(dr_t, np.float64), np.asarray(dr, np.float64).reshape(-1, 2),
                        td_t[o], np.asarray(td_range, np.float64).reshape(-1, 1)[o],
                        meas_ids=np.asarray(td_node).astype(np.int32).reshape(-1)[o], K=K,
                        input_mode="increment", t_end=t_end)


def log_from_events(events: EventLog, pose0, beacon_ids, beacons=None, dtype=None) -> Log:
    """The :class:`Log` of a :func:`plaza_events` log, the start pose, the beacons' ids and (for
    localisation) their surveyed positions.  dtype: of the run (default: JAX's default float).
    ``beacon_ids`` must be whole numbers (:class:`InputError` naming it: a cast truncated 12.9 to 12)."""
    if not isinstance(events, EventLog):
        raise InputError("events: expected a jaxslam.data.events.EventLog")
    check_whole_ids(beacon_ids, "beacon_ids")
    if events.z.shape[-1] != 1:
        raise InputError(f"events.z: expected one range per row (d_z = 1), got {events.z.shape[-1]}")
    dtype = dtype or jnp.result_type(float)
    return Log(t=jnp.asarray(events.t, dtype), dt=jnp.asarray(events.dt, dtype), u=jnp.asarray(events.u, dtype),
               z=jnp.asarray(events.z, dtype), ids=jnp.asarray(events.ids, jnp.int32),
               mask=jnp.asarray(events.mask, bool), pose0=jnp.asarray(pose0, dtype),
               beacon_ids=jnp.asarray(beacon_ids, jnp.int32),
               beacons=None if beacons is None else jnp.asarray(beacons, dtype))


def _heading_difference(a, b):
    """Robot-state difference with the heading (index 2) wrapped (Plaza)."""
    d = a - b
    return d.at[2].set(wrap_angle(d[2]))


def init(log: Log, config: Config, params: Params, *, key=None) -> State:
    """The state before the first event: the robot at ``log.pose0`` with the bias prior
    (``params.bias0`` ± ``sigma_bias0``), the surveyed beacons in the map (localisation) or
    none (SLAM), empty buffers."""
    del key
    dtype = log.z.dtype
    N = log.beacon_ids.shape[0]
    cap = int(config.capacity or N)
    p = params
    s0 = jnp.concatenate([log.pose0, jnp.reshape(p.bias0, (1,))]).astype(dtype)
    P0 = jnp.diag(jnp.stack([p.p0_pos**2, p.p0_pos**2, p.p0_th**2, p.sigma_bias0**2]))
    st = es.init(s0, P0, cap, 2)
    if log.beacons is not None:  # surveyed beacons: in the map from the start, zero covariance
        st = es.preload(st, MODEL, log.beacons, ids=log.beacon_ids)
    W = int(config.window)
    buf = _Buf(pos=jnp.zeros((N, W, 2), dtype), pos_var=jnp.zeros((N, W), dtype),
               rng=jnp.zeros((N, W), dtype), count=jnp.zeros((N,), jnp.int32))
    zero = jnp.zeros((), jnp.int32)
    return State(st, buf, zero, zero, log.beacon_ids)


def step(state: State, event: Event, config: Config, params: Params, *, key=None):
    """One event: the DR increment's prediction, the ranges' update (each gated), the buffering
    of ranges to unmapped beacons and their delayed initialisation (module docstring; skipped
    when ``config.delayed`` is False).  Returns ``(state, StepOut)``.  ``params.outlier_gate``
    None is resolved here as :func:`run` resolves it (:func:`biased_range.resolve_outlier_gate`,
    host side), so the module's own ``PARAMS`` work."""
    del key
    p = params if params.outlier_gate is not None else resolve_outlier_gate(params)
    st, buf, n_reg, n_unm, beacon_ids = state
    N, W = buf.rng.shape
    K = event.z.shape[0]
    s = st.x[:NR]
    Q = odo_process_noise(s, event.u, event.dt, p)
    st = es.predict(st, MODEL, event.u, Q)
    slots, mapped = es.associate_known(st, event.ids, event.mask)
    st, info, nll, nll_dof, n_out = update_ranges(st, MODEL, event.z, slots, mapped, p)
    # buffer ranges of unmapped beacons with the current position estimate
    s = st.x[:NR]
    pv = 0.5 * (st.P[0, 0] + st.P[1, 1])
    finite = jnp.isfinite(event.z[:, 0])
    new = event.mask & ~mapped & finite
    # a non-finite range of an unmapped beacon is not buffered, and counted like a mapped one's
    # (update_ranges flags those): MASKED_INPUT
    dropped = jnp.any(event.mask & ~mapped & ~finite)
    st = st._replace(status=st.status | jnp.where(dropped, errors.MASKED_INPUT, 0).astype(st.status.dtype))
    beq = event.ids[:, None] == beacon_ids[None, :]
    known_id = jnp.any(beq, axis=1)
    bidx = jnp.argmax(beq, axis=1)
    for k in range(K):  # static, small
        ok = new[k] & known_id[k]
        b = bidx[k]
        w = buf.count[b] % W
        buf = _Buf(
            pos=buf.pos.at[b, w].set(jnp.where(ok, s[:2], buf.pos[b, w])),
            pos_var=buf.pos_var.at[b, w].set(jnp.where(ok, pv, buf.pos_var[b, w])),
            rng=buf.rng.at[b, w].set(jnp.where(ok, event.z[k, 0], buf.rng[b, w])),
            count=buf.count.at[b].add(ok.astype(jnp.int32)),
        )
    n_unm = n_unm + jnp.sum(new).astype(jnp.int32)
    # delayed initialisation of each unmapped beacon whose buffer is ready
    # (skipped statically with surveyed beacons: every beacon is mapped from the start)
    if config.delayed is not False:
        bias = st.x[NR - 1]

        def fit_one(pos, pos_var, rng, valid):
            def fit(bias_):  # (D1), robust, on the bias-corrected ranges
                return delayed_init.from_buffer(pos, pos_var, rng - bias_, valid, p.sigma_r**2, p.min_points,
                                                p.min_spread, robust=True)

            # the fit and its derivative in the bias in one pass (one copy of the fit in the program)
            (r, Pl), (dr, _) = jax.jvp(fit, (bias,), (jnp.ones_like(bias),))
            return r, Pl, dr.position

        # every beacon's fit at once; the registrations below stay in turn (each takes a free slot)
        fits, Pls, Gbs = jax.vmap(fit_one)(buf.pos, buf.pos_var, buf.rng, jnp.arange(W)[None, :] < buf.count[:, None])
        Pbb = st.P[NR - 1, NR - 1]

        def register(carry, b):  # one beacon; in turn, since each takes a free slot
            st, n_reg = carry
            bid, ok, position, Pl, Gb = b  # Gb (2,): ∂position/∂bias
            is_mapped = jnp.any((st.ids == bid) & st.active)
            Pll = Pl + Pbb * jnp.outer(Gb, Gb)
            Plx = Gb[:, None] * st.P[NR - 1][None, :]
            free = ~st.active
            ready = (~is_mapped) & ok & jnp.any(free) & jnp.all(jnp.isfinite(Pll))
            st = es.add_landmark(st, MODEL, jnp.argmax(free), position, symmetrize(Pll), Plx, bid, ok=ready)
            return (st, n_reg + ready.astype(jnp.int32)), None

        (st, n_reg), _ = jax.lax.scan(register, (st, n_reg), (beacon_ids, fits.ok, fits.position, Pls, Gbs))
    Pd = jnp.diagonal(st.P)
    out = StepOut(pos=st.x[0:2], pos_var=Pd[0:2], heading=st.x[2], bias=st.x[3], bias_var=Pd[3], nis=info.nis,
                  dof=info.dof, used=jnp.sum(info.used).astype(jnp.int32), gated=jnp.sum(info.gated).astype(jnp.int32),
                  nll=nll, nll_dof=nll_dof, outliers=n_out, monitored=jnp.sum(mapped).astype(jnp.int32),
                  smoother=(es.smoother_terms(st, MODEL), Q) if config.smooth else None)
    return State(st, buf, n_reg, n_unm, beacon_ids), out


def run(log: Log, config: Config = Config(), params: Params = PARAMS, *, key=None) -> Result:
    """2D range-only SLAM (default) or localisation with surveyed beacons (``log.beacons``), with
    odometry increments and a common range bias, as one jitted ``lax.scan`` of :func:`step`.
    Returns :class:`Result` (landmarks = beacons, heading filled; with surveyed beacons
    ``n_registered`` = N).  ``key`` is not used (accepted as every system's ``run`` accepts it).
    ``config.capacity`` must be an int >= N (or None: N); with delayed initialisation
    ``params.min_points`` must not exceed ``config.window`` (:class:`InputError` naming each).
    """
    del key
    N = check_ids_vector(log.beacon_ids, "log.beacon_ids")
    # 3.7 ran as 3, 0 as N, "5" as 5: a count or None (N)
    cap = N if config.capacity is None else check_int(config.capacity, "config.capacity",
                                                       what="an int (beacon slots)")
    if cap < N:
        raise InputError(f"config.capacity: {cap} < number of beacons {N}")
    if np.shape(log.pose0) != (3,):
        raise InputError(f"log.pose0: expected shape (3,), got {np.shape(log.pose0)}")
    if np.ndim(log.u) < 1 or np.shape(log.u)[-1] != 2:
        raise InputError(f"log.u: expected (d, dθ) increments, got shape {np.shape(log.u)}")
    check_log(log, u_width=2)  # t, dt, u, z, ids, mask: one length T >= 1; dt >= 0, whole ids
    if log.beacons is not None and np.shape(log.beacons) != (N, 2):
        raise InputError(f"log.beacons: expected shape ({N}, 2), got {np.shape(log.beacons)}")
    check_unique_ids(log.beacon_ids, "log.beacon_ids")
    for a, name in ((log.beacons, "log.beacons"), (log.pose0, "log.pose0"), (log.u, "log.u")):
        check_positions(a, name)
    check_params(params, positive=("sigma_r", "sigma_bias0", "p0_pos", "p0_th"),
                 nonneg=("alpha_d", "alpha_th", "beta_th", "sigma_d0", "sigma_th0", "q_bias", "min_spread"),
                 finite=("bias0",))
    if params.min_points is not None and is_concrete(params.min_points):
        check_scalar(params.min_points, "params.min_points", lower=1)
    check_int(config.window, "config.window", what="an int (ranges kept per beacon for its start)")
    dtype = jnp.asarray(log.z).dtype
    params = resolve_outlier_gate(params)
    config = config._replace(capacity=cap, window=int(config.window), smooth=bool(config.smooth),
                             delayed=log.beacons is None if config.delayed is None else bool(config.delayed))
    # a buffer holds at most config.window rows: no beacon could ever be mapped, silently
    if (config.delayed and params.min_points is not None and is_concrete(params.min_points)
            and float(params.min_points) > config.window):
        raise InputError(f"params.min_points: {params.min_points!r} exceeds config.window = {config.window} "
                         "(the rows a beacon's buffer holds), so no beacon could ever be mapped")
    return _run(log, config, _cast_params(params, dtype))


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params) -> Result:
    N = log.beacon_ids.shape[0]
    state0 = init(log, config, params)
    events = Event(dt=log.dt, u=log.u, z=log.z, ids=log.ids, mask=log.mask)
    state, outs = jax.lax.scan(lambda s, ev: step(s, ev, config, params), state0, events)
    rs = sst = None
    if config.smooth:
        terms, Qs = outs.smoother
        rs, sst = es.smooth_robot(MODEL, terms, log.u, Qs, state.slam, difference=_heading_difference)
    n_reg = state.n_registered + (0 if log.beacons is None else N)
    fields = (outs.pos, outs.pos_var, outs.heading, outs.bias, outs.bias_var, outs.nis, outs.dof, outs.used,
              outs.gated)
    slam = state.slam._replace(status=state.slam.status | cons.status_bits(jnp.sum(outs.outliers),
                                                                           jnp.sum(outs.monitored)))
    return _result(log.t, fields, slam, MODEL, n_reg, state.n_unmapped, rs, sst, outs.nll, outs.nll_dof,
                   outs.outliers, outs.monitored)
