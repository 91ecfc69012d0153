"""2D range-bearing EKF-SLAM on real logs (issue 9), on the generic EKF-SLAM engine.

A *system* module: it fixes the planar pose ``s = (x, y, φ)`` [m, m, rad], the
point landmarks ``l = (l_x, l_y)`` [m], the range-bearing sensor
(:mod:`jaxslam.sensors.range_bearing2d`), a motion model from
:mod:`jaxslam.dynamics.planar` and the data association, and plugs them into
:mod:`jaxslam.filters.ekf_slam` (``init``/``predict``/``update``/``register``/
``associate_known``/``associate_nn``).  All Jacobians are ``jax.jacfwd`` inside
the engine; hand forms exist only as test oracles.

One log (:class:`jaxslam.data.events.EventLog`, the input stream and the
measurement stream merged into event order) is **one jitted** ``lax.scan``.
Event k:

1. **Predict** over Δt_k = t_k − t_{k−1} with the held input u_k::

       s' = f(s, u_k, Δt_k)                         (config.motion)
       Q_k = J_u M_k J_uᵀ + Q_floor Δt_k,   J_u = ∂f/∂u (autodiff)
       M_k = M_c / Δt_k  ("rate": M_c is a density [(m/s)²·s, (rad/s)²·s]),
       M_k = M_c         ("increment": per increment)

   ``Q_floor`` [m²/s, m²/s, rad²/s] is an additive pose-noise density (unmodelled
   slip; the encoder-only input noise vanishes when the vehicle stands still).
   Motion models: ``"unicycle"`` (u = (v, ω), exact arc; MRCLAM), ``"ackermann"``
   (u = (v_e, α), laser-centred state, ``config.geometry``; Victoria Park),
   ``"increment"`` (u = (d, dθ), s ∘ Pose2(d, 0, dθ)).

2. **Measurement update**, under ``lax.cond`` only on events that carry
   measurements (most events are odometry-only; on 2 CPU cores a scan that
   always ran the O(n²·K) update would waste most of its time)::

       z = (r, β),  r = ‖l − p‖,  β = wrap(atan2(l_y − y, l_x − x) − φ)
       R = params.R (2×2) [m², rad²]

   a. validity: non-finite rows, rows outside ``params.[range_min, range_max]`` /
      ``params.[bearing_min, bearing_max]`` and (``"known"``) rows without an id (< 0)
      are masked and counted (``n_limited``); a present row with a NaN/Inf entry
      also flags ``MASKED_INPUT`` (the limits are a chosen selection, not bad
      input, and flag nothing);
   b. at most ``config.K`` rows per event are processed, the nearest first
      (closer detections are the more accurate); the rest are counted
      (``n_dropped``), never silently lost;
   c. association — ``"known"``: :func:`~jaxslam.filters.ekf_slam.associate_known`
      on the log's ids; mapped ids update, unmapped ids register (a repeated
      unmapped id in one event registers once, the repeats are counted as
      rejected).  ``"nn"`` (ids hidden): :func:`~jaxslam.filters.ekf_slam.associate_nn`,
      squared Mahalanobis distance d² on the marginal innovation covariance:
      d² < ``params.gate`` → matched (one measurement per landmark), d² >
      ``params.new_threshold`` → new landmark, otherwise ambiguous → discarded
      (counted as rejected);
   d. one joint engine update (factored Joseph form) with the matched rows,
      an optional per-measurement χ² ``params.update_gate`` (counted as gated);
   e. registration of the new landmarks at the posterior pose
      (:func:`~jaxslam.filters.ekf_slam.register`); a landmark without a free
      slot is counted in ``overflow`` and flags ``CAPACITY_OVERFLOW``.

The numbers of the gates and limits are :class:`Params` fields (traced: a new value never
recompiles); :class:`Config` holds sizes and switches only.  The dataset presets (MRCLAM,
Victoria Park: noise values and their sources, configs, log adapters) are in
:mod:`jaxslam.data.presets`.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..data.events import EventLog
from ..dynamics import planar
from ..errors import InputError, check_flag, has_bool
from ..filters import association as assoc
from ..filters import consistency as cons
from ..filters import ekf_slam as es
from ..linalg import check_int, check_mask, check_scalar, check_psd, check_whole_ids, is_concrete, wrap_angle
from ..sensors import range_bearing2d as rb

__all__ = [
    "Config",
    "Params",
    "Log",
    "Event",
    "State",
    "StepOut",
    "Result",
    "init",
    "step",
    "log_from_events",
    "make_model",
    "calibrated_input",
    "motion_fn",
    "run",
    "validate_config",
    "validate_params",
    "check_thresholds",
    "validate_log",
]

MOTIONS = planar.MOTIONS
ASSOCIATIONS = ("known", "nn", "jcbb")

class Config(NamedTuple):
    """Static choices (hashable; a change recompiles): sizes, counts and switches.  The numbers
    of the gates, limits and pruning are :class:`Params` fields (``gate``, ``new_threshold``,
    ``update_gate``, ``range_min`` … ``bearing_max``, ``prune_window_s``, ``prune_min_obs``).

    motion: "unicycle" | "ackermann" | "increment".
    capacity: landmark slots (state size n = 3 + 2·capacity; update cost O(n²·K)).
    K: measurement rows processed per event (nearest first; extra rows counted).
    association: "known" (log ids) | "nn" (ids ignored; Mahalanobis nearest neighbour) |
      "jcbb" (joint compatibility branch and bound).
    input_mode: "rate" (M_c a density, divided by Δt) | "increment" (M_c per increment).
    geometry: Ackermann geometry (motion "ackermann").
    calibrate: augment the robot block with input calibration c = (c_0, c_1, c_2), the true
      input being (c_0 u_0, c_1 u_1 + c_2) (odometry speed scale, turn-rate / steering scale
      and bias), estimated online (robot block 6 instead of 3).
    joint_gate: optional probability p (e.g. 0.99) of a joint-compatibility check of one
      event's nn matches (:func:`~jaxslam.filters.ekf_slam.joint_compatibility`): while the
      joint NIS of the m matched rows exceeds the χ²(2m) p-quantile the row that lowers it
      most is dropped (counted as rejected; it neither updates nor registers).  It stays
      here, a switch with its probability: the table of χ²(2m) quantiles, m = 1 … K, is built
      on the host at trace time (``stats.chi2_ppf_np``; JAX has no χ² inverse CDF and SciPy
      is not a run-time dependency), so a new p compiles a new program.
    robust: Student-t measurement model with ``params.robust_nu`` degrees of freedom in the
      update (:func:`~jaxslam.filters.ekf_slam.update`, ``robust``): outliers are
      down-weighted, never cut off.
    monitor: NIS monitor with covariance inflation (:mod:`jaxslam.filters.consistency`,
      ``params.monitor``): it watches the rows matched to mapped landmarks and, with
      association ``"nn"``, also the ambiguous rows (gate < d² ≤ new_threshold) at their
      nearest landmark's d² (the gate keeps matched rows below the monitor's trigger, so a
      monitor of those alone never acted with ids hidden).  Whether or not it is on, the run
      carries ``DIVERGED`` when more than 10 % of the matched rows were outliers (d² >
      ``params.monitor.outlier_gate``).
    jcbb_cand, jcbb_budget: association ``"jcbb"`` (:func:`jaxslam.filters.association.jcbb`):
      candidates kept per measurement and search nodes per event; the joint test is at
      ``joint_gate`` (default 0.99) and the individual gate at ``params.gate`` (a traced gate
      that is not a finite number > 0 pairs nothing and sets ``NON_FINITE`` in ``Result.status``).
    block: events per checkpointed block of the scan (0: none).  With a block, the reverse
      pass stores one state per block and recomputes the block's events: memory of a
      gradient over a whole log grows with the number of blocks, not of events.
    smooth: also return the RTS-smoothed robot trajectory (``Result.smoothed``,
      :func:`jaxslam.filters.ekf_slam.smooth_robot`: the map held static).  It records
      O(3·2·capacity) numbers per event and one Cholesky of the map block per event, so it
      suits maps of tens of landmarks; pruned landmarks and monitor inflations are not
      modelled by the backward pass (it treats the filtered map as static from each
      landmark's registration on).
    active_only: the update and the prediction work on the leading block of slots that holds
      the map (:func:`jaxslam.filters.ekf_slam.update`, ``predict``): they cost what the mapped
      landmarks need, not the capacity; the same estimates to rounding.  False: the whole state
      (cheaper to compile; the tuning targets' gradients use it).
    joseph: the update's covariance by the factored Joseph form (default); False: the standard
      form P − K S Kᵀ, half the products of the correction (``joseph`` of
      :func:`jaxslam.filters.ekf_slam.update`; docs/papers.md compares them).
    """

    motion: str = "unicycle"
    capacity: int = 16
    K: int = 8
    association: str = "known"
    input_mode: str = "rate"
    geometry: planar.AckermannGeometry = planar.VICTORIA_PARK
    calibrate: bool = False
    joint_gate: Optional[float] = None
    robust: bool = False
    monitor: bool = False
    jcbb_cand: int = 3
    jcbb_budget: int = 64
    block: int = 0
    smooth: bool = False
    active_only: bool = True
    joseph: bool = True


class Params(NamedTuple):
    """Tunable noise and thresholds (traced leaves: no recompilation, ``grad`` works).

    M_c: (2, 2) input noise — a density [(u-units)²·s] for rate inputs, per increment otherwise.
    Q_floor: (3, 3) additive pose-noise density [m²/s, m²/s, rad²/s].
    R: (2, 2) range-bearing covariance [m², rad²].
    P0: (3, 3) initial pose covariance [m², m², rad²].
    calib0: (3,) prior mean of the input calibration (default (1, 1, 0)); calib_P0: (3, 3)
      its prior covariance; calib_Q: (3, 3) its random-walk density [per s] (defaults 0).
      Read only with ``config.calibrate``.
    range_model: (2,) (k0, k2) or (3,) (k0, k2, a) of a camera range model
      r_meas = r (k0 + k2 β²) + a, β the measured bearing, a [m] a range offset (default 0):
      each measured range becomes (r_meas − a)/(k0 + k2 β²) before the update, and the
      likelihood (``Result.nll``) is that of the measured range (it adds log(k0 + k2 β²)
      per used row).  Default: none.  Learnt from the innovations (``jaxslam tune mrclam``).
    input_model: (3,) (c_0, c_1, c_2) of a fixed input correction: the filter moves with
      (c_0 u_0, c_1 u_1 + c_2) for the logged input u (odometry speed scale, turn-rate or
      steering scale and bias), and the input noise M_c is that of the corrected input.  The
      systematic part of the odometry error, where ``config.calibrate`` estimates a per-run
      calibration online.  Default: none (1, 1, 0).  Learnt from the innovations (``jaxslam
      tune mrclam``).
    robust_nu: () Student-t degrees of freedom (``config.robust``; default 5).
    monitor: :class:`jaxslam.filters.consistency.MonitorParams` (``config.monitor``;
      default :data:`MONITOR_DEFAULT`).

    Thresholds (:data:`THRESHOLDS`; traced like the noise, so a new value never recompiles; an
    optional one is off at None, and None ↔ a number changes the pytree — a switch that traces
    once more):

    gate: () χ²(2) threshold of an nn / jcbb individual match, d² < gate (default 9.21 = 99 %).
    new_threshold: () nn / jcbb d² above which a measurement starts a new landmark (default
      30.0; need 0 < gate ≤ new_threshold).
    update_gate: () optional χ²(2) gate on each used measurement's NIS in the update
      (default None: off).
    range_min, range_max [m], bearing_min, bearing_max [rad]: () optional validity limits of
      a row (default None: off).
    prune_window_s: () optional tentative-landmark pruning window [s] (default None: off).  A
      landmark that has not been matched (used in an update) at least ``prune_min_obs`` times
      within ``prune_window_s`` seconds of its registration is removed (mean, rows and
      columns of P zeroed, slot freed) and counted in ``n_pruned``; one that has is confirmed
      for good.  Clutter (a detection of a bush, a car, a person) rarely repeats; a tree does.
    prune_min_obs: () matches a tentative landmark needs within the window (default 2; a
      whole-number count, held as a float like every other leaf).
    """

    M_c: jax.Array
    Q_floor: jax.Array
    R: jax.Array
    P0: jax.Array
    calib0: Optional[jax.Array] = None
    calib_P0: Optional[jax.Array] = None
    calib_Q: Optional[jax.Array] = None
    range_model: Optional[jax.Array] = None
    robust_nu: Optional[jax.Array] = None
    input_model: Optional[jax.Array] = None
    monitor: Optional[cons.MonitorParams] = None
    gate: Any = 9.21
    new_threshold: Any = 30.0
    update_gate: Optional[Any] = None
    range_min: Optional[Any] = None
    range_max: Optional[Any] = None
    bearing_min: Optional[Any] = None
    bearing_max: Optional[Any] = None
    prune_window_s: Optional[Any] = None
    prune_min_obs: Any = 2.0


#: The :class:`Params` fields that are thresholds (scalars; the rest is noise).
THRESHOLDS = ("gate", "new_threshold", "update_gate", "range_min", "range_max", "bearing_min", "bearing_max",
              "prune_window_s", "prune_min_obs")


#: NIS monitor defaults: average over ~20 events with sightings, inflate when the mean NIS
#: per scalar exceeds 3 (E = 1), at most ×10 at once; outliers beyond χ²(2) 99 % = 9.21.
MONITOR_DEFAULT = cons.MonitorParams(alpha=0.05, threshold=3.0, max_factor=10.0, outlier_gate=9.21)


class Result(NamedTuple):
    """Whole-log result (T events, cap slots).

    pose: (T, 3) pose mean after event k; pose_cov: (T, 3, 3);
    calib: (T, 3) input calibration estimate ((1, 1, 0) when ``config.calibrate`` is off).
    landmarks: (cap, 2) final map means; landmark_covs: (cap, 2, 2); active: (cap,) bool;
    ids: (cap,) int32 log id of each slot ("known"; −1 for nn landmarks and free slots).
    n_meas: (T,) valid rows offered (after the limits); n_limited: (T,) rows masked by the
    validity limits or non-finite; n_dropped: (T,) valid rows beyond K;
    n_used: (T,) rows used in the update; n_gated: (T,) rows rejected by ``update_gate``;
    n_rejected: (T,) nn ambiguous rows (gate < d² ≤ new_threshold) and repeated new ids;
    n_registered: (T,) landmarks added; nis: (T,) joint NIS of the update; dof: (T,) its dof.
    overflow: () landmarks that found no free slot; status: () int32 OR-ed flags (jaxslam.errors).
    n_pruned: (T,) tentative landmarks removed after event k (``params.prune_window_s``).
    nll: (T,) negative log-likelihood of event k's used rows (Gaussian joint, or the sum of
    the rows' Student-t terms with ``config.robust``; nats); nll_dof: (T,) their scalar count.
    n_outliers: (T,) rows of mapped landmarks with d² > ``monitor.outlier_gate``;
    n_monitored: (T,) rows of mapped landmarks offered to the update;
    inflations: () NIS-monitor inflations of the robot covariance (``config.monitor``).
    """

    pose: jax.Array
    pose_cov: jax.Array
    calib: jax.Array
    landmarks: jax.Array
    landmark_covs: jax.Array
    active: jax.Array
    ids: jax.Array
    n_meas: jax.Array
    n_limited: jax.Array
    n_dropped: jax.Array
    n_used: jax.Array
    n_gated: jax.Array
    n_rejected: jax.Array
    n_registered: jax.Array
    nis: jax.Array
    dof: jax.Array
    overflow: jax.Array
    status: jax.Array
    n_pruned: Optional[jax.Array] = None
    nll: Optional[jax.Array] = None
    nll_dof: Optional[jax.Array] = None
    n_outliers: Optional[jax.Array] = None
    n_monitored: Optional[jax.Array] = None
    inflations: Optional[jax.Array] = None
    smoothed: Optional[jax.Array] = None
    smooth_status: Optional[jax.Array] = None


# ---------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------

def motion_fn(config: Config):
    """``f(s, u, dt)`` of ``config.motion``."""
    if config.motion not in MOTIONS:
        raise InputError(f"config.motion: expected one of {MOTIONS}, got {config.motion!r}")
    return planar.motion_model(config.motion, config.geometry)


def calibrated_input(c, u):
    """True input (c_0 u_0, c_1 u_1 + c_2) from the logged input ``u`` and calibration ``c``."""
    return jnp.stack([c[0] * u[0], c[1] * u[1] + c[2]])


def make_model(config: Config) -> es.SlamModel:
    """Engine model: motion(s, u, dt), range-bearing observe/inverse/residual.

    With ``config.calibrate`` the robot block is s = (x, y, φ, c_0, c_1, c_2); the pose moves
    with the calibrated input and c is constant (its random walk enters through Q).
    The range-bearing functions read only s[:3].  Equal configurations give the same model
    object (one built per motion, geometry and calibration), so the engine's steps called
    eagerly from :func:`step` find their compiled programs again.
    """
    try:
        return _cached_model(config.motion, config.geometry, bool(config.calibrate))
    except TypeError:  # an unhashable geometry: built afresh
        return _build_model(motion_fn(config), config.calibrate)


@functools.lru_cache(maxsize=32)
def _cached_model(motion: str, geometry, calibrate: bool) -> es.SlamModel:
    # motion_fn checks the motion's name (an InputError is not cached)
    return _build_model(motion_fn(Config(motion=motion, geometry=geometry)), calibrate)


def _build_model(f, calibrate: bool) -> es.SlamModel:
    if calibrate:
        def motion(s, u, dt):
            return jnp.concatenate([f(s[:3], calibrated_input(s[3:6], u), dt), s[3:6]])
        nr = 6
    else:
        motion, nr = f, 3
    return es.SlamModel(robot_dim=nr, lm_dim=2, meas_dim=2, motion=motion,
                        observe=rb.observe, inverse=rb.inverse, residual=rb.residual)


# ---------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------

def _cast_thresholds(params: Params, dtype) -> Params:
    """``params`` with its :data:`THRESHOLDS` as arrays of ``dtype`` (None stays None): a Python
    number and an array of the same value then share one compiled program."""
    return params._replace(**{f: None if getattr(params, f) is None else jnp.asarray(getattr(params, f), dtype)
                              for f in THRESHOLDS})


def _limits(z, mask, params: Params):
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    zr = jnp.where(finite, z[:, 0], 0.0)
    zb = jnp.where(finite, z[:, 1], 0.0)
    ok = finite
    if params.range_min is not None:
        ok = ok & (zr >= params.range_min)
    if params.range_max is not None:
        ok = ok & (zr <= params.range_max)
    if params.bearing_min is not None:
        ok = ok & (zb >= params.bearing_min)
    if params.bearing_max is not None:
        ok = ok & (zb <= params.bearing_max)
    return mask & ok, mask & ~ok


def _select_k(z, ids, valid, K: int):
    """The (at most) K valid rows with the smallest range, and how many valid rows were left out."""
    Kl = z.shape[0]
    if Kl <= K:
        pad = K - Kl
        z = jnp.concatenate([z, jnp.full((pad, 2), jnp.nan, z.dtype)]) if pad else z
        ids = jnp.concatenate([ids, jnp.full((pad,), -1, ids.dtype)]) if pad else ids
        valid = jnp.concatenate([valid, jnp.zeros((pad,), bool)]) if pad else valid
        return z, ids, valid, jnp.zeros((), jnp.int32)
    key = jnp.where(valid, jnp.where(jnp.isfinite(z[:, 0]), z[:, 0], jnp.inf), jnp.inf)
    order = jnp.argsort(key)[:K]
    sel_valid = valid[order]
    dropped = jnp.sum(valid) - jnp.sum(sel_valid)
    return z[order], ids[order], sel_valid, dropped.astype(jnp.int32)


def _chi2_table(p: float, K: int, dz: int):
    """χ²(dz·m) p-quantiles for m = 1 … K (host side, static; SciPy is not a run-time dependency)."""
    from ..stats import chi2_ppf_np

    return np.asarray([chi2_ppf_np(float(p), dz * m) for m in range(1, K + 1)])


def _range_gain(rm, bearing):
    """g = k0 + k2 β² of the camera range model (``Params.range_model``)."""
    return rm[0] + rm[1] * bearing ** 2


def _measure(st: es.SlamState, z, ids, valid, model, config: Config, R, nu, thr: Params):
    K = z.shape[0]
    dz = model.meas_dim
    zs = jnp.where(valid[:, None], z, 0.0)
    robust = nu if config.robust else None
    extra = None  # nn: (ambiguous rows, their nearest landmark's d²) for the NIS monitor
    if config.association == "known":
        slots, mapped = es.associate_known(st, ids, valid)
        st, info = es.update(st, model, zs, slots, mapped, R, None, gate=thr.update_gate, robust=robust,
                             row_stats=True, active_only=config.active_only, joseph=config.joseph)
        cand = valid & ~mapped
        new = es.first_of_each_id(ids, cand)  # a repeated new id registers once
        rejected = jnp.sum(cand & ~new).astype(jnp.int32)
        reg_ids = ids
        watched = mapped
    else:
        if config.association == "jcbb":
            jc = assoc.jcbb(st, model, zs, valid, R, None, gate=thr.gate,
                            thresholds=_chi2_table(config.joint_gate or 0.99, K, 2),
                            n_cand=config.jcbb_cand, budget=config.jcbb_budget)
            slots, matched = jnp.maximum(jc.slots, 0), jc.paired
            new = valid & ~matched & (jc.d2 > thr.new_threshold)
        else:
            slots, matched, new, d2_near = es.associate_nn(st, model, zs, valid, R, None, gate=thr.gate,
                                                     new_threshold=thr.new_threshold,
                                                     active_only=config.active_only)
            if config.joint_gate is not None:
                matched, _, _ = es.joint_compatibility(st, model, zs, slots, matched, R, None,
                                                       _chi2_table(config.joint_gate, K, 2))
        st, info = es.update(st, model, zs, slots, matched, R, None, gate=thr.update_gate, robust=robust,
                             row_stats=True, active_only=config.active_only, joseph=config.joseph)
        if config.association == "jcbb":
            # a traced bad gate / threshold pairs nothing: jcbb says so in its status (NON_FINITE),
            # which the run's status carries like the engine's own flags (0 for a valid gate)
            st = st._replace(status=st.status | jc.status)
        # ambiguous (between the gates) or losing a landmark to a closer measurement
        ambiguous = valid & ~matched & ~new
        rejected = jnp.sum(ambiguous).astype(jnp.int32)
        reg_ids = jnp.full((K,), -1, jnp.int32)
        watched = matched
        if config.association == "nn":
            # the NIS monitor also sees the ambiguous rows at their nearest landmark: with ids
            # hidden an over-confident pose turns mapped landmarks' sightings into such rows,
            # which the gate keeps out of the matched rows' NIS
            extra = (ambiguous & jnp.isfinite(d2_near), d2_near)
    n_before = jnp.sum(st.active).astype(jnp.int32)
    # (the engine's register skips its work when nothing is new, also for a vmapped batch)
    st = es.register(st, model, zs, reg_ids, new, R, None)
    registered = jnp.sum(st.active).astype(jnp.int32) - n_before
    counts = jnp.stack([
        jnp.sum(info.used).astype(jnp.int32),
        jnp.sum(info.gated).astype(jnp.int32),
        rejected,
        registered,
    ])
    nll, nll_dof = es.update_nll(info, dz, nu if config.robust else None)
    mon_rows, mon_d2 = watched, info.d2
    if extra is not None:
        mon_rows = watched | extra[0]
        mon_d2 = jnp.where(extra[0], extra[1].astype(info.d2.dtype), info.d2)
    return (st, counts, info.nis, info.dof.astype(jnp.int32), slots, info.used, info.d2, watched, nll, nll_dof,
            mon_d2, mon_rows)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
def _zero_slots(P, drop, nr: int, dl: int):
    """P with the rows and columns of the slots in ``drop`` (cap,) zeroed, in place: a loop over
    the dropped slots, O(n) each (a select over P would be O(n²) on every event that prunes).
    The derivative (custom JVP: the loop's length is traced) is the same mask on the tangent."""
    n = P.shape[0]
    gone = jnp.nonzero(drop, size=drop.shape[0], fill_value=0)[0]  # the dropped slots first
    z0 = jnp.int32(0)

    def zero(k, P):
        r = (nr + gone[k] * dl).astype(jnp.int32)
        P = jax.lax.dynamic_update_slice(P, jnp.zeros((dl, n), P.dtype), (r, z0))
        return jax.lax.dynamic_update_slice(P, jnp.zeros((n, dl), P.dtype), (z0, r))

    return jax.lax.fori_loop(jnp.int32(0), jnp.sum(drop, dtype=jnp.int32), zero, P)


@_zero_slots.defjvp
def _zero_slots_jvp(nr, dl, primals, tangents):
    P, drop = primals
    keep = jnp.concatenate([jnp.ones((nr,), bool), jnp.repeat(~drop, dl)])
    return _zero_slots(P, drop, nr, dl), jnp.where(keep[:, None] & keep[None, :], tangents[0], 0.0)


def _prune(st: es.SlamState, aux, active_before, slots, used, model, thr: Params):
    """Tentative-landmark bookkeeping and pruning after one event (``params.prune_window_s``).

    aux = (t, reg_t (cap,), n_match (cap,), confirmed (cap,)).  Slots registered in this
    event start their window at t; matched slots count one more match.  A tentative slot
    older than the window is confirmed (≥ ``prune_min_obs`` matches) or removed: mean and
    rows/columns of P zeroed in place (O(n) per removed slot), slot freed, id −1, under
    ``lax.cond``: run only on events that remove something.  Returns (state, aux, number removed).
    """
    t, reg_t, n_match, confirmed = aux
    nr, dl = model.robot_dim, model.lm_dim
    new = st.active & ~active_before
    reg_t = jnp.where(new, t, reg_t)
    n_match = jnp.where(new, 0, n_match)
    confirmed = confirmed & ~new
    n_match = n_match.at[slots].add(used.astype(jnp.int32))
    due = st.active & ~confirmed & (t - reg_t > thr.prune_window_s)
    drop = due & (n_match < thr.prune_min_obs)
    confirmed = confirmed | (due & ~drop)

    def remove(st_):
        keep = jnp.concatenate([jnp.ones((nr,), bool), jnp.repeat(~drop, dl)])
        return st_._replace(x=jnp.where(keep, st_.x, 0.0), P=_zero_slots(st_.P, drop, nr, dl),
                            active=st_.active & ~drop, ids=jnp.where(drop, -1, st_.ids))

    st = jax.lax.cond(jnp.any(drop), remove, lambda st_: st_, st)
    return st, (t, reg_t, n_match, confirmed), jnp.sum(drop, dtype=jnp.int32)


class Log(NamedTuple):
    """One run's inputs as arrays (T events; a batch adds a leading axis).

    dt: (T,) s since the previous event; u: (T, 2) held input (rates) or increment;
    z: (T, K, 2) [range m, bearing rad] rows; ids: (T, K) int32 landmark id of each row (−1:
    none); mask: (T, K) bool row present; pose0: (3,) initial pose [m, m, rad] at the first
    event — its dtype (float32/float64) is the computation dtype; is_input: optional (T,) bool,
    the events that carry an input (increments are applied there only; the EKF reads ``u``,
    which is zero elsewhere, and ignores it).  Padding events (dt = 0, no input, no rows) change
    nothing.  :func:`log_from_events` builds it from an :class:`~jaxslam.data.events.EventLog`.
    The planar systems (this EKF-SLAM, :mod:`jaxslam.systems.planar_fastslam`) share it.
    """

    dt: jax.Array
    u: jax.Array
    z: jax.Array
    ids: jax.Array
    mask: jax.Array
    pose0: jax.Array
    is_input: Any = None


class Event(NamedTuple):
    """One event of a :class:`Log` (the slice :func:`step` takes)."""

    dt: jax.Array  # ()
    u: jax.Array  # (2,)
    z: jax.Array  # (K, 2)
    ids: jax.Array  # (K,)
    mask: jax.Array  # (K,)


class State(NamedTuple):
    """The filter state between events.

    slam: the EKF-SLAM posterior (:class:`~jaxslam.filters.ekf_slam.SlamState`);
    t: () s since the first event; reg_t, n_match, confirmed: (cap,) tentative-landmark
    bookkeeping (registration time, matches, confirmed; ``params.prune_window_s``);
    monitor: the NIS monitor (:mod:`jaxslam.filters.consistency`).
    """

    slam: es.SlamState
    t: jax.Array
    reg_t: jax.Array
    n_match: jax.Array
    confirmed: jax.Array
    monitor: cons.Monitor


class StepOut(NamedTuple):
    """What :func:`step` reports for its event (stacked by :func:`run` into :class:`Result`)."""

    pose: jax.Array  # (3,)
    pose_cov: jax.Array  # (3, 3)
    calib: jax.Array  # (3,)
    n_meas: jax.Array
    n_limited: jax.Array
    n_dropped: jax.Array
    counts: jax.Array  # (4,) used, gated, rejected, registered
    nis: jax.Array
    dof: jax.Array
    n_pruned: jax.Array
    nll: jax.Array
    nll_dof: jax.Array
    n_outliers: jax.Array
    n_monitored: jax.Array
    smoother: Any = None  # (SmootherTerms, Q) with config.smooth


def log_from_events(events: EventLog, pose0) -> Log:
    """The :class:`Log` of an :class:`~jaxslam.data.events.EventLog` and a start pose (3,).

    The pose's dtype (float32/float64; an integer pose becomes the default float) sets the
    computation dtype; the log's arrays are cast to it.
    """
    pose0 = jnp.asarray(pose0)
    if not jnp.issubdtype(pose0.dtype, jnp.floating):
        pose0 = pose0.astype(jnp.result_type(float))
    dtype = pose0.dtype
    return Log(dt=jnp.asarray(events.dt, dtype), u=jnp.asarray(events.u, dtype), z=jnp.asarray(events.z, dtype),
               ids=jnp.asarray(events.ids, jnp.int32), mask=jnp.asarray(events.mask, bool), pose0=pose0,
               is_input=jnp.asarray(events.is_input, bool))


def _input_correction(params: Params, u, dtype):
    if params.input_model is None:
        return u
    im = jnp.asarray(params.input_model, dtype)
    return jnp.stack([im[0] * u[..., 0], im[1] * u[..., 1] + im[2]], axis=-1)


def init(log: Log, config: Config, params: Params, *, key=None) -> State:
    """The state before the first event: the robot at ``log.pose0`` with covariance ``params.P0``
    (and the input calibration's prior with ``config.calibrate``), an empty map."""
    del key
    pose0 = jnp.asarray(log.pose0)
    dtype = pose0.dtype
    P0 = jnp.asarray(params.P0, dtype)
    if config.calibrate:
        c0 = jnp.asarray([1.0, 1.0, 0.0] if params.calib0 is None else params.calib0, dtype)
        cP0 = jnp.zeros((3, 3), dtype) if params.calib_P0 is None else jnp.asarray(params.calib_P0, dtype)
        x0 = jnp.concatenate([pose0, c0])
        P0 = jax.scipy.linalg.block_diag(P0, cP0)
    else:
        x0 = pose0
    cap = int(config.capacity)
    return State(slam=es.init(x0, P0, cap, 2), t=jnp.zeros((), dtype), reg_t=jnp.zeros((cap,), dtype),
                 n_match=jnp.zeros((cap,), jnp.int32), confirmed=jnp.zeros((cap,), bool),
                 monitor=cons.init(dtype))


def step(state: State, event: Event, config: Config, params: Params, *, key=None):
    """One event (prediction over ``event.dt``, then the update with its rows): returns
    ``(state, StepOut)``.  See the module docstring for the two stages."""
    del key
    model = make_model(config)
    f = model.motion
    st = state.slam
    dtype = st.x.dtype
    nr = model.robot_dim
    K = int(config.K)
    dt_k = jnp.asarray(event.dt, dtype)
    u_k = _input_correction(params, jnp.asarray(event.u, dtype), dtype)
    z_k = jnp.asarray(event.z, dtype)
    id_k = jnp.asarray(event.ids, jnp.int32)
    m_k = jnp.asarray(event.mask, bool)
    M_c = jnp.asarray(params.M_c, dtype)
    Q_add = jnp.asarray(params.Q_floor, dtype)
    if config.calibrate:
        cQ = jnp.zeros((3, 3), dtype) if params.calib_Q is None else jnp.asarray(params.calib_Q, dtype)
        Q_add = jax.scipy.linalg.block_diag(Q_add, cQ)
    R = jnp.asarray(params.R, dtype)
    rm = None if params.range_model is None else jnp.asarray(params.range_model, dtype)
    rm_a = None if rm is None else (rm[2] if rm.shape[0] > 2 else jnp.zeros((), dtype))
    nu = jnp.asarray(5.0 if params.robust_nu is None else params.robust_nu, dtype)
    mon_p = cons.MonitorParams(*(jnp.asarray(v, dtype) for v in
                                 (MONITOR_DEFAULT if params.monitor is None else params.monitor)))

    s = st.x[:nr]
    M = planar.step_input_cov(M_c, dt_k, config.input_mode)
    Q = planar.input_noise_cov(f, s, u_k, dt_k, M) + Q_add * dt_k
    st = es.predict(st, model, u_k, Q, dt_k, active_only=config.active_only)
    thr = _cast_thresholds(params, dtype)
    valid, limited = _limits(z_k, m_k, thr)
    if config.association == "known":
        # a row without a log id cannot be associated by id: masked and counted
        limited = limited | (valid & (id_k < 0))
        valid = valid & (id_k >= 0)
    if rm is not None:  # the camera range model: r = (r_meas − a) / (k0 + k2 β²)
        # (invalid rows zeroed first: a NaN row would poison the gradient through 0 × NaN)
        z_k = jnp.where(valid[:, None], z_k, 0.0)
        z_k = jnp.stack([(z_k[:, 0] - rm_a) / _range_gain(rm, z_k[:, 1]), z_k[:, 1]], axis=-1)
    zk, idk, vk, dropped = _select_k(z_k, id_k, valid, K)

    def with_meas(st_):
        return _measure(st_, zk, idk, vk, model, config, R, nu, thr)

    def without(st_):
        zi, zb = jnp.zeros((), jnp.int32), jnp.zeros((K,), bool)
        return (st_, jnp.zeros((4,), jnp.int32), jnp.zeros((), dtype), zi, jnp.zeros((K,), jnp.int32),
                zb, jnp.zeros((K,), dtype), zb, jnp.zeros((), dtype), jnp.zeros((), dtype),
                jnp.zeros((K,), dtype), zb)

    active_before = st.active
    st, counts, nis, dof, slots_k, used_k, d2_k, watched, nll, nll_dof, mon_d2, mon_rows = jax.lax.cond(
        jnp.any(vk), with_meas, without, st)
    if rm is not None:
        # The filter sees r = (r_meas − a)/g: the density of the measured range carries the
        # change of variables, −log p(r_meas) = −log p(r) + log g.  Without it the likelihood
        # rewards any g < 1 (it shrinks the residuals it is scored on): a free k0 went to 1.31.
        nll = nll + jnp.sum(jnp.where(used_k, jnp.log(jnp.abs(_range_gain(rm, jnp.where(vk, zk[:, 1], 0.0)))),
                                      0.0))
    # consistency: the rows of mapped landmarks, before any gate or weighting
    mon = state.monitor
    if config.monitor:
        # unchecked per event: params.monitor is checked at the run's entry (validate_params),
        # and a NaN row of a diverging run is its status to report, not an error
        mon, st = cons._observe(mon, st, model, mon_d2, mon_rows, mon_p)
    n_out = cons._outliers(d2_k, watched, mon_p)
    t_k = state.t + dt_k
    aux = (t_k, state.reg_t, state.n_match, state.confirmed)
    if thr.prune_window_s is not None:
        st, aux, n_pr = _prune(st, aux, active_before, slots_k, used_k, model, thr)
    else:
        n_pr = jnp.zeros((), jnp.int32)
    cal = st.x[3:6] if config.calibrate else jnp.asarray([1.0, 1.0, 0.0], dtype)
    out = StepOut(pose=st.x[:3], pose_cov=st.P[:3, :3], calib=cal, n_meas=jnp.sum(valid).astype(jnp.int32),
                  n_limited=jnp.sum(limited).astype(jnp.int32), n_dropped=dropped, counts=counts, nis=nis,
                  dof=dof, n_pruned=n_pr, nll=nll, nll_dof=nll_dof, n_outliers=n_out,
                  n_monitored=jnp.sum(watched).astype(jnp.int32),
                  smoother=(es.smoother_terms(st, model), Q) if config.smooth else None)
    return State(slam=st, t=aux[0], reg_t=aux[1], n_match=aux[2], confirmed=aux[3], monitor=mon), out


def run(log: Log, config: Config, params: Params, *, key=None) -> Result:
    """EKF-SLAM over a whole log as one jitted ``lax.scan`` of :func:`step` (``config`` static,
    ``params`` and ``log`` traced: jit/vmap/grad-safe).  ``key`` is not used (the filter draws
    nothing; accepted as every system's ``run`` accepts it).  The config is checked here, and the
    params and log too when their values are concrete (an :class:`InputError` names the problem).
    """
    del key
    validate_config(config)
    if is_concrete(params):
        validate_params(params)
    validate_log(log)  # shapes always, values when concrete
    pose0 = jnp.asarray(log.pose0)
    if not jnp.issubdtype(pose0.dtype, jnp.floating):  # its dtype is the run's (as log_from_events)
        log = log._replace(pose0=pose0.astype(jnp.result_type(float)))
    return _run(log, config, _cast_thresholds(params, jnp.asarray(log.pose0).dtype))


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params) -> Result:
    model = make_model(config)
    dtype = jnp.asarray(log.pose0).dtype
    state0 = init(log, config, params)
    xs = Event(dt=jnp.asarray(log.dt, dtype), u=jnp.asarray(log.u, dtype), z=jnp.asarray(log.z, dtype),
               ids=jnp.asarray(log.ids, jnp.int32), mask=jnp.asarray(log.mask, bool))

    def body(state, ev):
        return step(state, ev, config, params)

    B = int(config.block)
    T = xs.dt.shape[0]
    if B > 0 and T > B:
        # checkpointed blocks: padded events (dt 0, no input, no rows) change nothing; the
        # blocked program rounds differently (~1e-15 relative, tests/tuning/test_real_logs.py)
        nb = -(-T // B)
        pad = nb * B - T
        xb = jax.tree.map(lambda a: jnp.concatenate([a, jnp.zeros((pad,) + a.shape[1:], a.dtype)]) if pad else a, xs)
        xb = jax.tree.map(lambda a: a.reshape((nb, B) + a.shape[1:]), xb)

        # and each event checkpointed inside its block: the reverse pass then keeps one carry
        # per event instead of the residuals of both branches of every ``cond`` (measured on
        # MRCLAM robot 1, 8801 events: value and gradient 2.7 -> 0.96 s)
        body_ckpt = jax.checkpoint(body)

        @jax.checkpoint
        def block(c, x):
            return jax.lax.scan(body_ckpt, c, x)

        state, outs = jax.lax.scan(block, state0, xb)
        outs = jax.tree.map(lambda a: a.reshape((nb * B,) + a.shape[2:])[:T], outs)
    else:
        state, outs = jax.lax.scan(body, state0, xs)
    st, mon = state.slam, state.monitor
    smoothed = smooth_status = None
    if config.smooth:
        terms, Qs = outs.smoother
        u_c = _input_correction(params, xs.u, dtype)
        rs, smooth_status = es.smooth_robot(model, terms, u_c, Qs, st, params=xs.dt,
                                            difference=_pose_difference)
        smoothed = rs[:, :3]
    status = st.status | cons.status_bits(jnp.sum(outs.n_outliers), jnp.sum(outs.n_monitored))
    # a present row with a NaN/Inf entry is masked by _limits before the engine sees it: flag it here
    bad_rows = jnp.any(xs.mask & ~jnp.all(jnp.isfinite(xs.z), axis=-1))
    status = status | jnp.where(bad_rows, jnp.int32(errors.MASKED_INPUT), jnp.int32(0))
    c = outs.counts
    return Result(
        pose=outs.pose, pose_cov=outs.pose_cov, calib=outs.calib,
        landmarks=es.landmarks(st, model), landmark_covs=es.landmark_covs(st, model),
        active=st.active, ids=st.ids,
        n_meas=outs.n_meas, n_limited=outs.n_limited, n_dropped=outs.n_dropped,
        n_used=c[:, 0], n_gated=c[:, 1], n_rejected=c[:, 2], n_registered=c[:, 3],
        nis=outs.nis, dof=outs.dof, overflow=st.overflow, status=status, n_pruned=outs.n_pruned,
        nll=outs.nll, nll_dof=outs.nll_dof, n_outliers=outs.n_outliers, n_monitored=outs.n_monitored,
        inflations=mon.inflations, smoothed=smoothed, smooth_status=smooth_status,
    )


def _pose_difference(a, b):
    """Robot-state difference with the heading (index 2) wrapped."""
    d = a - b
    return d.at[2].set(wrap_angle(d[2]))


# ---------------------------------------------------------------------------
# Parameter files (``jaxslam tune`` writes them, ``jaxslam dataset --params`` reads them)
# ---------------------------------------------------------------------------


def params_to_dict(params: Params) -> dict:
    """JSON-ready ``{field: value}`` of the set fields (matrices as nested lists); an optional
    threshold that is off is written as null, so :func:`params_from_dict` reads it back off
    whatever its base (left out, a base with the threshold on switched it back on)."""
    out = {}
    for k, v in params._asdict().items():
        if v is None:
            if k in THRESHOLDS:
                out[k] = None
            continue
        if k == "monitor":
            out[k] = {f: float(np.asarray(x)) for f, x in v._asdict().items()}
        else:
            a = np.asarray(v, np.float64)
            out[k] = a.tolist() if a.ndim else float(a)
    return out


def params_from_dict(d: dict, base: Params, dtype=np.float64, where: str = "params.noise") -> Params:
    """``base`` with the entries of ``d`` (a :func:`params_to_dict` dict, possibly partial).

    Unknown keys are an :class:`InputError` naming them; a matrix may be given as its diagonal.
    Keys absent from ``d`` keep ``base``'s value (a file written before the thresholds were
    :class:`Params` fields loads unchanged); an optional threshold given as null is off.
    """
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected an object, got {type(d).__name__}")
    fields = Params._fields
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {unknown}; expected some of {list(fields)}")
    vals = base._asdict()
    for k, v in d.items():
        if k == "monitor":
            if not isinstance(v, dict) or set(v) - set(cons.MonitorParams._fields):
                raise InputError(f"{where}.monitor: expected an object with keys "
                                 f"{list(cons.MonitorParams._fields)}, got {v!r}")
            cur = (MONITOR_DEFAULT if vals["monitor"] is None else vals["monitor"])._asdict()
            for f, x in v.items():  # (a string or a list was a bare ValueError / TypeError)
                if isinstance(x, (bool, np.bool_)):  # JSON true was read as 1.0
                    raise InputError(f"{where}.monitor.{f}: expected a number, got {x!r}")
                try:
                    cur[f] = check_scalar(x, f"{where}.monitor.{f}", finite=False)
                except OverflowError:  # a JSON integer beyond float range
                    raise InputError(f"{where}.monitor.{f}: expected a number, got {str(x)[:40]}...") from None
            vals[k] = cons.MonitorParams(**cur)
            continue
        if v is None and k in THRESHOLDS:  # an optional threshold switched off (JSON null)
            vals[k] = None
            continue
        try:
            if not _all_numbers(v):  # JSON true / "12.5" were read as 1.0 / 12.5 by the cast
                raise TypeError
            a = np.asarray(v, np.float64)
        except (TypeError, ValueError, OverflowError):  # (overflow: a JSON integer beyond float range)
            raise InputError(f"{where}.{k}: expected numbers, got {v!r}"[:300]) from None
        if k in _MATRIX_SHAPES and a.ndim == 1:
            a = np.diag(a)
        vals[k] = jnp.asarray(a, dtype)
    return validate_params(Params(**vals), where)  # errors name the entry, e.g. "--params: noise.R"


def _all_numbers(v) -> bool:
    """Whether ``v`` (a number, an array or nested lists) holds numbers only: no bool, no string."""
    if isinstance(v, (list, tuple)):
        return all(_all_numbers(x) for x in v)
    if isinstance(v, (bool, np.bool_, str, bytes)):
        return False
    if isinstance(v, np.ndarray) or hasattr(v, "dtype"):
        return np.issubdtype(np.asarray(v).dtype, np.number)
    return isinstance(v, (int, float, np.number))


def config_to_dict(config: Config) -> dict:
    """JSON-ready form of a :class:`Config` (the Ackermann geometry as a dict)."""
    out = config._asdict()
    out["geometry"] = config.geometry._asdict()
    return out


__all__ += ["params_to_dict", "params_from_dict", "config_to_dict", "MONITOR_DEFAULT", "THRESHOLDS"]


# ---------------------------------------------------------------------------
# Host-side validation
# ---------------------------------------------------------------------------

def validate_config(config: Config) -> Config:
    """Known motion/association/input mode; integer capacity and K >= 1; positive search sizes;
    the switches (``calibrate``, ``robust``, ``monitor``, ``smooth``, ``active_only``, ``joseph``)
    True or False; ``joint_gate`` None or a number in (0, 1)."""
    if config.motion not in MOTIONS:
        raise InputError(f"config.motion: expected one of {MOTIONS}, got {config.motion!r}")
    if config.association not in ASSOCIATIONS:
        raise InputError(f"config.association: expected one of {ASSOCIATIONS}, got {config.association!r}")
    if config.input_mode not in ("rate", "increment"):
        raise InputError(f"config.input_mode: expected 'rate' or 'increment', got {config.input_mode!r}")
    # a float capacity/K was truncated silently (16.5 -> 16 slots, True -> 1, "4" -> 4)
    check_int(config.capacity, "config.capacity", what="an int (landmark slots)")
    check_int(config.K, "config.K", what="an int (rows per event)")
    if config.association == "jcbb":
        check_int(config.jcbb_cand, "config.jcbb_cand", what="an int (candidates per measurement)")
        check_int(config.jcbb_budget, "config.jcbb_budget", what="an int (search nodes per event)")
    check_int(config.block, "config.block", lower=0, what="an int (events per checkpointed block)")
    for name in _SWITCHES:  # a string "no" is truthy: the switch silently stayed on
        check_flag(getattr(config, name), f"config.{name}")
    jg = config.joint_gate
    # (a string was a bare TypeError from the comparison; a bool is not a probability)
    if jg is not None and (isinstance(jg, (bool, np.bool_)) or not isinstance(jg, (int, float, np.integer, np.floating))
                           or not (0.0 < jg < 1.0)):
        raise InputError(f"config.joint_gate: need a probability in (0, 1), got {config.joint_gate}")
    return config


#: the on/off switches of :class:`Config` (True or False; :func:`validate_config`)
_SWITCHES = ("calibrate", "robust", "monitor", "smooth", "active_only", "joseph")


#: shapes of the matrix fields of :class:`Params` (R positive definite, the rest PSD)
_MATRIX_SHAPES = {"M_c": (2, 2), "Q_floor": (3, 3), "R": (2, 2), "P0": (3, 3), "calib_P0": (3, 3),
                  "calib_Q": (3, 3)}


def check_matrices(values: dict, where: str = "params", diagonal_ok: bool = True) -> None:
    """The matrix fields among ``values`` (name -> matrix, with ``diagonal_ok`` also its diagonal
    as a list, as a ``--params`` file may give it; None for an optional calibration matrix):
    shape and positive (semi-)definiteness, in NumPy on the host, so a ``--params`` file is
    checked before any log is read or any program compiles; raises :class:`InputError` naming
    ``where.name``."""
    for name, shp in _MATRIX_SHAPES.items():
        if name not in values or (values[name] is None and name.startswith("calib")):
            continue
        try:  # in its own floating dtype: check_psd allows a float32 matrix its rounding
            a = np.asarray(values[name])
            a = a if np.issubdtype(a.dtype, np.floating) else a.astype(np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}.{name}: expected numbers, got {values[name]!r}") from None
        if diagonal_ok and a.ndim == 1 and a.shape == shp[:1]:
            a = np.diag(a)
        if a.shape != shp:
            raise InputError(f"{where}.{name}: expected shape {shp}, got {a.shape}")
        check_psd(a, f"{where}.{name}", strict=(name == "R"))


def validate_params(params: Params, where: str = "params") -> Params:
    """Numbers, not bools; shapes (M_c (2,2), Q_floor (3,3), R (2,2), P0 (3,3)); PSD, R positive definite; the
    thresholds as :func:`check_thresholds` (scalars, not NaN; 0 < gate ≤ new_threshold,
    range_min < range_max, bearing_min < bearing_max; with pruning a positive window and a whole
    prune_min_obs ≥ 1).  Errors name ``where.field`` (e.g. ``--params: noise.R``)."""
    for k, v in params._asdict().items():  # True was read as 1.0 (update_gate=True gated at NIS 1)
        if any(has_bool(x) for x in (v if k == "monitor" and v is not None else (v,))):
            raise InputError(f"{where}.{k}: expected numbers, got {v!r}"[:300])
    a = params.calib0
    try:  # (a string entry was a bare TypeError from isfinite)
        a_ok = (_all_numbers(a) and np.shape(a) == (3,)
                and bool(np.all(np.isfinite(np.asarray(a, np.float64)))))
    except (TypeError, ValueError):
        a_ok = False
    if a is not None and not a_ok:
        raise InputError(f"{where}.calib0: expected a finite shape (3,), got {np.asarray(a)!r}")
    check_matrices({k: getattr(params, k) for k in _MATRIX_SHAPES}, where, diagonal_ok=False)
    if params.range_model is not None:
        a = np.asarray(params.range_model, np.float64)
        if a.shape not in ((2,), (3,)) or not np.all(np.isfinite(a)) or a[0] <= 0:
            raise InputError(f"{where}.range_model: expected finite (k0, k2) or (k0, k2, a) with k0 > 0, "
                             f"got {a.tolist()}")
    if params.input_model is not None:
        a = np.asarray(params.input_model, np.float64)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise InputError(f"{where}.input_model: expected finite (c_0, c_1, c_2), got {a.tolist()}")
    if params.robust_nu is not None:
        check_scalar(params.robust_nu, f"{where}.robust_nu", lower=0, strict=True)
    for f in ("gate", "new_threshold"):
        if getattr(params, f) is None:
            raise InputError(f"{where}.{f}: expected a number, got None")
    check_thresholds({f: getattr(params, f) for f in THRESHOLDS}, where)
    if params.monitor is not None:
        m = cons.MonitorParams(*(np.asarray(v, np.float64) for v in params.monitor))
        if not (0 < m.alpha <= 1 and m.threshold > 1 and m.max_factor >= 1 and m.outlier_gate > 0):
            raise InputError(f"{where}.monitor: need 0 < alpha <= 1, threshold > 1, max_factor >= 1, "
                             f"outlier_gate > 0; got {tuple(float(v) for v in m)}")
    return params


def check_thresholds(values: dict, where: str = "params") -> dict:
    """The :data:`THRESHOLDS` among ``values`` (name -> number or None: off) as floats, checked
    alone and against each other (0 < gate <= new_threshold, range_min < range_max, bearing_min <
    bearing_max, a positive pruning window with a whole number of matches >= 1); the relations
    are checked where both sides are given; update_gate > 0.  Host-side (a ``--params`` file is checked with it
    before any log is read); raises :class:`InputError` naming ``where.key``."""
    thr = {f: check_scalar(values[f], f"{where}.{f}", finite=False)
           for f in THRESHOLDS if values.get(f) is not None}
    if values.get("prune_window_s") is not None and "prune_min_obs" in values and values["prune_min_obs"] is None:
        raise InputError(f"{where}.prune_min_obs: pruning (prune_window_s) needs a count of matches, got None")
    if "gate" in thr and "new_threshold" in thr and not (0 < thr["gate"] <= thr["new_threshold"]):
        raise InputError(f"{where}.gate/new_threshold: need 0 < gate <= new_threshold, got "
                         f"{thr['gate']}, {thr['new_threshold']}")
    if "update_gate" in thr and not thr["update_gate"] > 0:  # a gate <= 0 rejected every row (GATED)
        raise InputError(f"{where}.update_gate: need > 0 (or None: off), got {thr['update_gate']}")
    if "prune_window_s" in thr and not thr["prune_window_s"] > 0:
        raise InputError(f"{where}.prune_window_s: need > 0, got {thr['prune_window_s']}")
    if "prune_min_obs" in thr and not (thr["prune_min_obs"] >= 1 and thr["prune_min_obs"] == np.floor(thr["prune_min_obs"])):
        raise InputError(f"{where}.prune_min_obs: a count of matches, expected a whole number >= 1, got "
                         f"{thr['prune_min_obs']}")
    for lo, hi in (("range_min", "range_max"), ("bearing_min", "bearing_max")):
        if lo in thr and hi in thr and not thr[lo] < thr[hi]:
            # an empty interval would drop every measurement as outside the limits
            raise InputError(f"{where}.{lo}/{hi}: need {lo} < {hi}, got {thr[lo]}, {thr[hi]}")
    return thr


def validate_log(log: Log) -> Log:
    """Shapes of a :class:`Log` (also when traced): T >= 1 events, u (T, 2), z (T, K, 2), ids/mask
    (T, K), pose0 (3,), a bool (or integer 0/1) mask; when its values are known, dt ≥ 0 finite,
    inputs and the start pose finite, the ids of the rows in use whole numbers."""
    T = np.shape(log.dt)[0] if np.ndim(log.dt) == 1 else -1
    if T < 0:
        raise InputError(f"log.dt: expected shape (T,), got {np.shape(log.dt)}")
    if T == 0:  # an empty log failed deep inside the run (an IndexError)
        raise InputError("log.dt: expected at least one event, got an empty log (T = 0)")
    if np.shape(log.u) != (T, 2):
        raise InputError(f"log.u: expected shape ({T}, 2), got {np.shape(log.u)}")
    zs = np.shape(log.z)
    if len(zs) != 3 or zs[0] != T or zs[2] != 2:
        raise InputError(f"log.z: expected shape ({T}, K, 2), got {zs}")
    for name in ("ids", "mask"):
        if np.shape(getattr(log, name)) != zs[:2]:
            raise InputError(f"log.{name}: expected shape {zs[:2]}, got {np.shape(getattr(log, name))}")
    if np.shape(log.pose0) != (3,):
        raise InputError(f"log.pose0: expected shape (3,), got {np.shape(log.pose0)}")
    check_mask(log.mask, "log.mask")
    if not is_concrete(log.dt, log.u, log.pose0):
        return log
    dt = np.asarray(log.dt)
    if not np.all(np.isfinite(dt)) or np.any(dt < 0):
        raise InputError("log.dt: must be finite and >= 0")
    if not np.all(np.isfinite(np.asarray(log.u))):
        raise InputError("log.u: contains NaN or Inf")
    if not np.all(np.isfinite(np.asarray(log.pose0))):
        raise InputError("log.pose0: contains NaN or Inf")
    if is_concrete(log.ids, log.mask):  # a fractional id was truncated onto another landmark
        check_whole_ids(log.ids, "log.ids", used=log.mask)
    return log
