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

   a. validity: non-finite rows, rows outside ``[range_min, range_max]`` /
      ``[bearing_min, bearing_max]`` and (``"known"``) rows without an id (< 0)
      are masked and counted (``n_limited``);
   b. at most ``config.K`` rows per event are processed, the nearest first
      (closer detections are the more accurate); the rest are counted
      (``n_dropped``), never silently lost;
   c. association — ``"known"``: :func:`~jaxslam.filters.ekf_slam.associate_known`
      on the log's ids; mapped ids update, unmapped ids register (a repeated
      unmapped id in one event registers once, the repeats are counted as
      rejected).  ``"nn"`` (ids hidden): :func:`~jaxslam.filters.ekf_slam.associate_nn`,
      squared Mahalanobis distance d² on the marginal innovation covariance:
      d² < ``gate`` → matched (one measurement per landmark), d² >
      ``new_threshold`` → new landmark, otherwise ambiguous → discarded
      (counted as rejected);
   d. one joint engine update (factored Joseph form) with the matched rows,
      an optional per-measurement χ² ``update_gate`` (counted as gated);
   e. registration of the new landmarks at the posterior pose
      (:func:`~jaxslam.filters.ekf_slam.register`); a landmark without a free
      slot is counted in ``overflow`` and flags ``CAPACITY_OVERFLOW``.

Noise values and their sources are with the presets (:func:`mrclam_params`,
:func:`victoria_park_params`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..data.events import EventLog
from ..dynamics import planar
from ..errors import InputError
from ..filters import ekf_slam as es
from ..linalg import check_psd
from ..sensors import range_bearing2d as rb

__all__ = [
    "PlanarConfig",
    "PlanarParams",
    "PlanarResult",
    "MRCLAM_RANGE_SIGMA",
    "MRCLAM_BEARING_SIGMA",
    "mrclam_raw_sigma",
    "make_model",
    "calibrated_input",
    "motion_fn",
    "mrclam_params",
    "victoria_park_params",
    "victoria_park_config",
    "mrclam_config",
    "mrclam_log",
    "MRCLAM_RANGE_MODEL",
    "MRCLAM_CORRECTED_SIGMA",
    "MRCLAM_ODOMETRY_DELAY",
    "run",
    "run_arrays",
    "validate_config",
    "validate_params",
    "validate_log",
]

MOTIONS = planar.MOTIONS
ASSOCIATIONS = ("known", "nn")

#: MRCLAM dataset 6 landmark residual MADs (data README §5) × 1.4826 ≈ σ, robots 1 and 2.
MRCLAM_RANGE_SIGMA = {1: 0.053 * 1.4826, 2: 0.121 * 1.4826}  # m
MRCLAM_BEARING_SIGMA = {1: 0.0074 * 1.4826, 2: 0.0062 * 1.4826}  # rad

#: MRCLAM camera range model r_meas = r_true·(k0 + k2 β²) (β the measured bearing): ranges are
#: too long at the image centre and too short at its edges (README §5 residuals binned by
#: bearing: robot 1 +0.085 m at |β| < 0.15, −0.18 to −0.27 m at |β| > 0.45).  Least squares of
#: r_meas/r_true on the FIRST HALF of robot 1's log (t < 386 s) against GT + surveyed
#: landmarks (scripts/dev_mrclam_diagnostics.py).  Robot 1 range MAD 0.053 → 0.019 m (its
#: held-out second half: 0.056 → 0.019 m).  Robot 2's camera differs in k0 (its own fit:
#: 1.050, −0.503): with these values robot 2 keeps a +0.075 m range bias (MAD 0.121 → 0.030 m).
MRCLAM_RANGE_MODEL = (1.0246, -0.4624)
#: σ [m, rad] of the corrected residuals, 1.4826·MAD on the first half of robot 1 (same script).
MRCLAM_CORRECTED_SIGMA = (0.0242, 0.0120)
#: Odometry (commanded velocity) delay [s]: the sample stamped τ describes the motion at
#: τ + delay.  GT heading change vs ∫ω over 1 s windows: residual RMS minimal near 0.2–0.25 s
#: on robot 1's first half (0.032 rad at 0 s → 0.023 rad) and on robot 2.
MRCLAM_ODOMETRY_DELAY = 0.2


class PlanarConfig(NamedTuple):
    """Static choices (hashable; a change recompiles).

    motion: "unicycle" | "ackermann" | "increment".
    capacity: landmark slots (state size n = 3 + 2·capacity; update cost O(n²·K)).
    K: measurement rows processed per event (nearest first; extra rows counted).
    association: "known" (log ids) | "nn" (ids ignored; Mahalanobis nearest neighbour).
    gate: χ²(2) threshold of an nn match (default 9.21 = 99 %).
    new_threshold: nn d² above which a measurement starts a new landmark.
    update_gate: optional χ²(2) gate on each used measurement's NIS in the update.
    input_mode: "rate" (M_c a density, divided by Δt) | "increment" (M_c per increment).
    range_min, range_max [m], bearing_min, bearing_max [rad]: validity limits (None: off).
    geometry: Ackermann geometry (motion "ackermann").
    calibrate: augment the robot block with input calibration c = (c_0, c_1, c_2), the true
      input being (c_0 u_0, c_1 u_1 + c_2) (odometry speed scale, turn-rate / steering scale
      and bias), estimated online (robot block 6 instead of 3).
    prune_window_s, prune_min_obs: tentative-landmark pruning (None: off).  A landmark
      that has not been matched (used in an update) at least ``prune_min_obs`` times
      within ``prune_window_s`` seconds of its registration is removed (mean, rows and
      columns of P zeroed, slot freed) and counted in ``n_pruned``; one that has is
      confirmed for good.  Clutter (a detection of a bush, a car, a person) rarely
      repeats; a tree does.
    joint_gate: optional probability p (e.g. 0.99) of a joint-compatibility check of one
      event's nn matches (:func:`~jaxslam.filters.ekf_slam.joint_compatibility`): while the
      joint NIS of the m matched rows exceeds the χ²(2m) p-quantile the row that lowers it
      most is dropped (counted as rejected; it neither updates nor registers).
    """

    motion: str = "unicycle"
    capacity: int = 16
    K: int = 8
    association: str = "known"
    gate: float = 9.21
    new_threshold: float = 30.0
    update_gate: Optional[float] = None
    input_mode: str = "rate"
    range_min: Optional[float] = None
    range_max: Optional[float] = None
    bearing_min: Optional[float] = None
    bearing_max: Optional[float] = None
    geometry: planar.AckermannGeometry = planar.VICTORIA_PARK
    calibrate: bool = False
    prune_window_s: Optional[float] = None
    prune_min_obs: int = 2
    joint_gate: Optional[float] = None


class PlanarParams(NamedTuple):
    """Tunable noise (traced leaves: no recompilation, ``grad`` works).

    M_c: (2, 2) input noise — a density [(u-units)²·s] for rate inputs, per increment otherwise.
    Q_floor: (3, 3) additive pose-noise density [m²/s, m²/s, rad²/s].
    R: (2, 2) range-bearing covariance [m², rad²].
    P0: (3, 3) initial pose covariance [m², m², rad²].
    calib0: (3,) prior mean of the input calibration (default (1, 1, 0)); calib_P0: (3, 3)
      its prior covariance; calib_Q: (3, 3) its random-walk density [per s] (defaults 0).
      Read only with ``config.calibrate``.
    """

    M_c: jax.Array
    Q_floor: jax.Array
    R: jax.Array
    P0: jax.Array
    calib0: Optional[jax.Array] = None
    calib_P0: Optional[jax.Array] = None
    calib_Q: Optional[jax.Array] = None


class PlanarResult(NamedTuple):
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
    n_pruned: (T,) tentative landmarks removed after event k (``config.prune_window_s``).
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


# ---------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------

def motion_fn(config: PlanarConfig):
    """``f(s, u, dt)`` of ``config.motion``."""
    if config.motion not in MOTIONS:
        raise InputError(f"config.motion: expected one of {MOTIONS}, got {config.motion!r}")
    return planar.motion_model(config.motion, config.geometry)


def calibrated_input(c, u):
    """True input (c_0 u_0, c_1 u_1 + c_2) from the logged input ``u`` and calibration ``c``."""
    return jnp.stack([c[0] * u[0], c[1] * u[1] + c[2]])


def make_model(config: PlanarConfig) -> es.SlamModel:
    """Engine model: motion(s, u, dt), range-bearing observe/inverse/residual.

    With ``config.calibrate`` the robot block is s = (x, y, φ, c_0, c_1, c_2); the pose moves
    with the calibrated input and c is constant (its random walk enters through Q).
    The range-bearing functions read only s[:3].
    """
    f = motion_fn(config)
    if config.calibrate:
        def motion(s, u, dt):
            return jnp.concatenate([f(s[:3], calibrated_input(s[3:6], u), dt), s[3:6]])
        nr = 6
    else:
        motion, nr = f, 3
    return es.SlamModel(robot_dim=nr, lm_dim=2, meas_dim=2, motion=motion,
                        observe=rb.observe, inverse=rb.inverse, residual=rb.residual)


# ---------------------------------------------------------------------------
# Presets
# ---------------------------------------------------------------------------

def mrclam_raw_sigma(robot: int):
    """(σ_r [m], σ_β [rad]) of the raw MRCLAM camera measurements of ``robot``.

    Robots 1 and 2: 1.4826·MAD of their dataset-6 residuals (data README §5).  Other robots
    (other datasets) have no measured figure here: robot 2's, the larger range spread, is used.
    """
    r = int(robot) if int(robot) in MRCLAM_RANGE_SIGMA else 2
    return MRCLAM_RANGE_SIGMA[r], MRCLAM_BEARING_SIGMA[r]


def mrclam_params(robot: int = 1, sigma_v: float = 0.01, sigma_w: float = 0.02,
                  floor=(1e-4, 1e-4, 1e-4), r_scale: float = 4.0, p0=(1e-6, 1e-6, 1e-6),
                  calib_sigma=(0.1, 0.15, 0.01), calib_rw=(0.0, 0.0, 0.0),
                  dtype=jnp.float64, corrected: bool = False) -> PlanarParams:
    """MRCLAM dataset 6 preset (units: m, rad, s).

    ``corrected=True``: for a log built by :func:`mrclam_log` with its corrections (camera
    range model and odometry delay applied).  R = diag(σ_r², σ_β²)·r_scale with σ = ``MRCLAM_CORRECTED_SIGMA``
    (1.4826·MAD of the corrected residuals on the first half of robot 1), the same for both
    robots.  ``corrected=False`` (default): for the raw log, σ = 1.4826·MAD of the raw residuals against
    ground truth (data README §5: robot 1 range MAD 0.053 m, bearing 0.0074 rad; robot 2
    0.121 m, 0.0062 rad; full runs).  r_scale 4 chosen on robot 1 (×1 was worse: 0.23 m gated,
    0.136 m ungated).  M_c = diag(σ_v², σ_ω²) [(m/s)²·s, (rad/s)²·s] and the pose floor
    density are tuned on the first 300 s of robot 1 (scripts/dev_mrclam_diagnostics.py; not in the
    dataset paper).  P0 small: the run starts at the first ground-truth pose.  The ``calib_*``
    values (read only with ``config.calibrate``) are not recommended for MRCLAM: online input
    calibration converges near the GT-fitted turn scale/bias but raised the ATE
    (scripts/dev_mrclam_diagnostics.py).
    """
    if corrected:
        sr, sb = MRCLAM_CORRECTED_SIGMA
    else:
        sr, sb = mrclam_raw_sigma(robot)
    return PlanarParams(
        M_c=jnp.diag(jnp.asarray([sigma_v**2, sigma_w**2], dtype)),
        Q_floor=jnp.diag(jnp.asarray(floor, dtype)),
        R=jnp.diag(jnp.asarray([sr**2, sb**2], dtype)) * r_scale,
        P0=jnp.diag(jnp.asarray(p0, dtype)),
        calib0=jnp.asarray([1.0, 1.0, 0.0], dtype),
        calib_P0=jnp.diag(jnp.asarray(calib_sigma, dtype) ** 2),
        calib_Q=jnp.diag(jnp.asarray(calib_rw, dtype) ** 2),
    )


def mrclam_config(association: str = "known", capacity: Optional[int] = None, K: int = 8,
                  update_gate: Optional[float] = None, corrected: bool = False, **kw) -> PlanarConfig:
    """MRCLAM: unicycle odometry, 15 landmarks, at most 7 rows per camera frame.

    Capacity 16 with known ids; 32 with nn (spurious new landmarks).  ``update_gate``
    (default: χ²(2) 99 % = 9.21 for the raw log, 99.9 % = 13.8 with ``corrected``) rejects the
    residual outliers (range errors up to 1 m, data README §5).
    With the tight corrected R the 99 % gate (9.21) locks the filter out after a sighting gap
    (robot 2: 1639 rows gated, ATE 0.81 m; robot 1: 0.1236 vs 0.1226 m at 13.8).  NOTE: the
    lock-out was seen on robot 2, so this value is not chosen on robot 1 alone.
    With ``association="nn"`` the corrected (tight) R is NOT better: robot 1 ATE 1.11 m vs
    0.19 m with the raw log and ``mrclam_params(corrected=False)``, gate 9.21 (mis-association
    of the close landmarks 6/7/8); use the raw preset for nn (scripts/dev_mrclam_diagnostics.py).
    """
    if capacity is None:
        capacity = 16 if association == "known" else 32
    if update_gate is None:
        update_gate = 13.8 if corrected else 9.21
    return PlanarConfig(motion="unicycle", capacity=capacity, K=K, association=association,
                        update_gate=update_gate, **kw)


def mrclam_log(data, K: int = 8, t_end=None, range_model=MRCLAM_RANGE_MODEL,
               odometry_delay: float = MRCLAM_ODOMETRY_DELAY):
    """Event log and start pose of one MRCLAM robot (:class:`jaxslam.data.mrclam.MrclamData`).

    Corrections (host side; ``None``/0 turns one off): ranges divided by ``k0 + k2 β²``
    (``range_model``, see ``MRCLAM_RANGE_MODEL``); odometry stamps shifted by
    ``odometry_delay`` [s] (``MRCLAM_ODOMETRY_DELAY``).  ``t_end`` defaults to the last
    ground-truth time (robot 1 stops there).  The start pose is ground truth interpolated at
    the first event (the robot stands still before its first odometry row).
    Returns ``(EventLog, pose0 (3,) float64)``; pair it with ``mrclam_params(corrected=True)``.
    """
    from ..data.events import merge_events

    z = np.array(data.meas, np.float64)
    if range_model is not None:
        k0, k2 = (float(c) for c in range_model)
        z[:, 0] = z[:, 0] / (k0 + k2 * z[:, 1] ** 2)
    t_end = float(data.gt_t[-1]) if t_end is None else t_end
    log = merge_events(np.asarray(data.odom_t, np.float64) + float(odometry_delay), data.odom,
                       data.meas_t, z, data.meas_id, K=K, input_mode="rate", t_end=t_end)
    t0 = log.t[0]
    th = np.unwrap(np.asarray(data.gt[:, 2], np.float64))
    pose0 = np.array([np.interp(t0, data.gt_t, data.gt[:, 0]), np.interp(t0, data.gt_t, data.gt[:, 1]),
                      np.interp(t0, data.gt_t, th)])
    return log, pose0


def victoria_park_params(sigma_v: float = 0.7, sigma_a: float = 0.06, floor=(0.0, 0.0, 0.0),
                         sigma_r: float = 0.25, sigma_b: float = math.radians(0.375),
                         p0=(1e-6, 1e-6, 1e-6), dtype=jnp.float64) -> PlanarParams:
    """Victoria Park preset (units: m, rad, s); chosen on t < 500 s of the log only.

    Sources: RFS-SLAM's ``cfg/*_VictoriaPark.xml`` gives speed variance 0.2 (m/s)², steering
    0.025 rad² (per 40 Hz input, ×15 inflation) and R = diag(0.025 m², 2.5e-5 rad²) ×75
    inflation (σ_r ≈ 1.37 m, σ_β ≈ 0.043 rad).  Input noise σ_v = 0.7 (m/s)·√s, σ_α = 0.06
    rad·√s: a grid on t < 500 s (σ_v ∈ {0.3, 0.7}, σ_α ∈ {0.02, 0.06}; ATE vs GPS 1.58–1.74 m
    across it, input noise ×1/4 was worse: 1.70 m there, 3.40 m whole run).  Range-bearing
    noise σ_r = 0.25 m, σ_β = 0.375°: an R grid on t < 500 s with :func:`victoria_park_config`
    (float32): (σ_r, σ_β) = (1 m, 1.5°) 1.67 m, (0.5, 0.75°) 1.59, (0.25, 0.375°) 1.43,
    (0.177, 0.265°) 1.36, (0.125, 0.1875°) 1.32, (0.088, 0.133°) 1.30, (0.0625, 0.094°)
    17.2 m (diverges).  The chosen value stays a factor 4 in variance away from that cliff
    (the last 0.1 m of the grid is not worth the risk on unseen data).  Held-out part
    (t ≥ 500 s) and whole run: see docs/datasets.md (the map then exceeds capacity 256 —
    counted and flagged ``CAPACITY_OVERFLOW``; capacity 384 gives the same ATE without
    overflow at about twice the run time).  The 1000–1100 s window (new ground, 8 m RMS at
    R ×16) flips between ~2 and ~8 m under small changes of gate, new-landmark threshold, R,
    a diameter filter or ``joint_gate``: fragile single-hypothesis association, not noise
    tuning.  Start pose (0, 0, 0).
    """
    return PlanarParams(
        M_c=jnp.diag(jnp.asarray([sigma_v**2, sigma_a**2], dtype)),
        Q_floor=jnp.diag(jnp.asarray(floor, dtype)),
        R=jnp.diag(jnp.asarray([sigma_r**2, sigma_b**2], dtype)),
        P0=jnp.diag(jnp.asarray(p0, dtype)),
    )


def victoria_park_config(capacity: int = 256, K: int = 8, range_max: float = 40.0,
                         prune_window_s: Optional[float] = 2.0, prune_min_obs: int = 4,
                         **kw) -> PlanarConfig:
    """Victoria Park: Ackermann, nn association, range limits 5 m – ``range_max``, pruning.

    RFS-SLAM limits range to 5–70 m; a tighter maximum keeps the far, poorly conditioned
    detections (bearing error × range) out of both the map and the update (30 m was tried:
    no better, 2.97 m vs 2.83 m whole-run ATE with the earlier R of 1 m / 1.5°).  Tentative
    landmarks not matched 4 times within 2 s of registration are pruned (chosen on the first
    500 s and the whole run, scripts/dev_victoria_park_ekf.py; with R = 1 m / 1.5° the map
    then kept 237 landmarks, 781 registered, 544 pruned, no overflow; with the preset's
    tighter R it exceeds 256 slots: 407 registrations refused, counted and flagged).  K = 8
    rows per scan, nearest first (t < 500 s: K 4 / 6 / 8 / 10 → 1.62 / 1.54 / 1.43 / 1.42 m).
    Cost per measurement event is O(capacity²·K): capacity 256, K 8 runs the whole log in
    6.4–10.9 s (median 8.6 s over 13 runs) after compile in float32 on the 2-core dev
    machine (capacity 384 without pruning: 19.2 s; float32 vs float64 poses differ < 0.2 mm
    over the first 300 s).
    """
    base = dict(motion="ackermann", capacity=capacity, K=K, association="nn",
                range_min=5.0, range_max=range_max, prune_window_s=prune_window_s,
                prune_min_obs=prune_min_obs)
    base.update(kw)
    return PlanarConfig(**base)


# ---------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------

def _limits(z, mask, config: PlanarConfig):
    finite = jnp.all(jnp.isfinite(z), axis=-1)
    zr = jnp.where(finite, z[:, 0], 0.0)
    zb = jnp.where(finite, z[:, 1], 0.0)
    ok = finite
    if config.range_min is not None:
        ok = ok & (zr >= config.range_min)
    if config.range_max is not None:
        ok = ok & (zr <= config.range_max)
    if config.bearing_min is not None:
        ok = ok & (zb >= config.bearing_min)
    if config.bearing_max is not None:
        ok = ok & (zb <= config.bearing_max)
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
    from ..metrics import chi2_ppf_np

    return np.asarray([chi2_ppf_np(float(p), dz * m) for m in range(1, K + 1)])


def _first_of_id(ids, cand):
    """cand & no earlier candidate with the same id (a repeated new id registers once)."""
    K = ids.shape[0]
    same = (ids[:, None] == ids[None, :]) & cand[None, :] & (jnp.arange(K)[None, :] < jnp.arange(K)[:, None])
    return cand & ~jnp.any(same, axis=1)


def _measure(st: es.SlamState, z, ids, valid, model, config: PlanarConfig, R):
    K = z.shape[0]
    zs = jnp.where(valid[:, None], z, 0.0)
    if config.association == "known":
        slots, mapped = es.associate_known(st, ids, valid)
        st, info = es.update(st, model, zs, slots, mapped, R, None, gate=config.update_gate)
        cand = valid & ~mapped
        new = _first_of_id(ids, cand)
        rejected = jnp.sum(cand & ~new).astype(jnp.int32)
        reg_ids = ids
    else:
        slots, matched, new, _ = es.associate_nn(st, model, zs, valid, R, None, gate=config.gate,
                                                 new_threshold=config.new_threshold)
        if config.joint_gate is not None:
            matched, _, _ = es.joint_compatibility(st, model, zs, slots, matched, R, None,
                                                   _chi2_table(config.joint_gate, K, 2))
        st, info = es.update(st, model, zs, slots, matched, R, None, gate=config.update_gate)
        # ambiguous (between the gates) or losing a landmark to a closer measurement
        rejected = jnp.sum(valid & ~matched & ~new).astype(jnp.int32)
        reg_ids = jnp.full((K,), -1, jnp.int32)
    n_before = jnp.sum(st.active).astype(jnp.int32)
    # registration writes rows/columns of P per candidate: skipped (cond) when nothing is new
    st = jax.lax.cond(jnp.any(new), lambda st_: es.register(st_, model, zs, reg_ids, new, R, None),
                      lambda st_: st_, st)
    registered = jnp.sum(st.active).astype(jnp.int32) - n_before
    counts = jnp.stack([
        jnp.sum(info.used).astype(jnp.int32),
        jnp.sum(info.gated).astype(jnp.int32),
        rejected,
        registered,
    ])
    return st, counts, info.nis, info.dof.astype(jnp.int32), slots, info.used


def _prune(st: es.SlamState, aux, active_before, slots, used, model, config: PlanarConfig):
    """Tentative-landmark bookkeeping and pruning after one event (``config.prune_window_s``).

    aux = (t, reg_t (cap,), n_match (cap,), confirmed (cap,)).  Slots registered in this
    event start their window at t; matched slots count one more match.  A tentative slot
    older than the window is confirmed (≥ ``prune_min_obs`` matches) or removed: mean and
    rows/columns of P zeroed, slot freed, id −1 — one O(n²) select under ``lax.cond``, run
    only on events that remove something.  Returns (state, aux, number removed).
    """
    t, reg_t, n_match, confirmed = aux
    nr, dl = model.robot_dim, model.lm_dim
    new = st.active & ~active_before
    reg_t = jnp.where(new, t, reg_t)
    n_match = jnp.where(new, 0, n_match)
    confirmed = confirmed & ~new
    n_match = n_match.at[slots].add(used.astype(jnp.int32))
    due = st.active & ~confirmed & (t - reg_t > config.prune_window_s)
    drop = due & (n_match < int(config.prune_min_obs))
    confirmed = confirmed | (due & ~drop)

    def remove(st_):
        keep = jnp.concatenate([jnp.ones((nr,), bool), jnp.repeat(~drop, dl)])
        return st_._replace(x=jnp.where(keep, st_.x, 0.0),
                            P=jnp.where(keep[:, None] & keep[None, :], st_.P, 0.0),
                            active=st_.active & ~drop, ids=jnp.where(drop, -1, st_.ids))

    st = jax.lax.cond(jnp.any(drop), remove, lambda st_: st_, st)
    return st, (t, reg_t, n_match, confirmed), jnp.sum(drop, dtype=jnp.int32)


@functools.partial(jax.jit, static_argnames=("config",))
def run_arrays(dt, u, z, ids, mask, pose0, params: PlanarParams, config: PlanarConfig) -> PlanarResult:
    """The jitted scan on raw arrays (vmap-able over runs): see :func:`run`.

    dt (T,), u (T, 2), z (T, K_log, 2), ids (T, K_log) int, mask (T, K_log) bool, pose0 (3,).
    The computation dtype is ``pose0``'s (float32 or float64).
    """
    model = make_model(config)
    f = model.motion
    pose0 = jnp.asarray(pose0)
    dtype = pose0.dtype
    dt = jnp.asarray(dt, dtype)
    u = jnp.asarray(u, dtype)
    z = jnp.asarray(z, dtype)
    ids = jnp.asarray(ids, jnp.int32)
    mask = jnp.asarray(mask, bool)
    M_c = jnp.asarray(params.M_c, dtype)
    Q_floor = jnp.asarray(params.Q_floor, dtype)
    R = jnp.asarray(params.R, dtype)
    nr = model.robot_dim
    P0 = jnp.asarray(params.P0, dtype)
    if config.calibrate:
        c0 = jnp.asarray([1.0, 1.0, 0.0] if params.calib0 is None else params.calib0, dtype)
        cP0 = jnp.zeros((3, 3), dtype) if params.calib_P0 is None else jnp.asarray(params.calib_P0, dtype)
        cQ = jnp.zeros((3, 3), dtype) if params.calib_Q is None else jnp.asarray(params.calib_Q, dtype)
        x0 = jnp.concatenate([pose0, c0])
        P0 = jax.scipy.linalg.block_diag(P0, cP0)
        Q_add = jax.scipy.linalg.block_diag(Q_floor, cQ)
    else:
        x0, Q_add = pose0, Q_floor
    st0 = es.init(x0, P0, config.capacity, 2)
    K = int(config.K)
    ones = jnp.asarray([1.0, 1.0, 0.0], dtype)

    def body(carry, inp):
        st, aux = carry  # aux: (t, registration time (cap,), match count (cap,), confirmed (cap,))
        dt_k, u_k, z_k, id_k, m_k = inp
        s = st.x[:nr]
        M = planar.step_input_cov(M_c, dt_k, config.input_mode)
        Q = planar.input_noise_cov(f, s, u_k, dt_k, M) + Q_add * dt_k
        st = es.predict(st, model, u_k, Q, dt_k)
        valid, limited = _limits(z_k, m_k, config)
        if config.association == "known":
            # a row without a log id cannot be associated by id: masked and counted
            limited = limited | (valid & (id_k < 0))
            valid = valid & (id_k >= 0)
        zk, idk, vk, dropped = _select_k(z_k, id_k, valid, K)

        def with_meas(st_):
            return _measure(st_, zk, idk, vk, model, config, R)

        def without(st_):
            return (st_, jnp.zeros((4,), jnp.int32), jnp.zeros((), dtype), jnp.zeros((), jnp.int32),
                    jnp.zeros((K,), jnp.int32), jnp.zeros((K,), bool))

        active_before = st.active
        st, counts, nis, dof, slots_k, used_k = jax.lax.cond(jnp.any(vk), with_meas, without, st)
        t_k = aux[0] + dt_k
        aux = (t_k,) + aux[1:]
        if config.prune_window_s is not None:
            st, aux, n_pr = _prune(st, aux, active_before, slots_k, used_k, model, config)
        else:
            n_pr = jnp.zeros((), jnp.int32)
        cal = st.x[3:6] if config.calibrate else ones
        out = (st.x[:3], st.P[:3, :3], cal, jnp.sum(valid).astype(jnp.int32),
               jnp.sum(limited).astype(jnp.int32), dropped, counts, nis, dof, n_pr)
        return (st, aux), out

    cap = int(config.capacity)
    aux0 = (jnp.zeros((), dtype), jnp.zeros((cap,), dtype), jnp.zeros((cap,), jnp.int32),
            jnp.zeros((cap,), bool))
    (st, _), outs = jax.lax.scan(body, (st0, aux0), (dt, u, z, ids, mask))
    pose, pose_cov, calib, n_meas, n_limited, n_dropped, counts, nis, dof, n_pruned = outs
    return PlanarResult(
        pose=pose, pose_cov=pose_cov, calib=calib,
        landmarks=es.landmarks(st, model), landmark_covs=es.landmark_covs(st, model),
        active=st.active, ids=st.ids,
        n_meas=n_meas, n_limited=n_limited, n_dropped=n_dropped,
        n_used=counts[:, 0], n_gated=counts[:, 1], n_rejected=counts[:, 2], n_registered=counts[:, 3],
        nis=nis, dof=dof, overflow=st.overflow, status=st.status, n_pruned=n_pruned,
    )


def run(log: EventLog, pose0, config: PlanarConfig, params: PlanarParams, validate: bool = True) -> PlanarResult:
    """EKF-SLAM over a whole :class:`EventLog` as one jitted ``lax.scan``.

    ``pose0`` (3,) initial pose [m, m, rad] at ``log.t[0]``; its dtype (float32/float64)
    sets the computation dtype.  ``config`` static; ``params`` traced.  With ``validate``
    the config, params and log are checked on the host first (InputError names the problem).
    """
    if validate:
        validate_config(config)
        validate_params(params)
        validate_log(log)
    pose0 = jnp.asarray(pose0)
    if not jnp.issubdtype(pose0.dtype, jnp.floating):
        pose0 = pose0.astype(jnp.result_type(float))
    return run_arrays(log.dt, log.u, log.z, log.ids, log.mask, pose0, params, config)


# ---------------------------------------------------------------------------
# Host-side validation
# ---------------------------------------------------------------------------

def validate_config(config: PlanarConfig) -> PlanarConfig:
    """Known motion/association/input mode; positive capacity, K and gates."""
    if config.motion not in MOTIONS:
        raise InputError(f"config.motion: expected one of {MOTIONS}, got {config.motion!r}")
    if config.association not in ASSOCIATIONS:
        raise InputError(f"config.association: expected one of {ASSOCIATIONS}, got {config.association!r}")
    if config.input_mode not in ("rate", "increment"):
        raise InputError(f"config.input_mode: expected 'rate' or 'increment', got {config.input_mode!r}")
    if int(config.capacity) < 1 or int(config.K) < 1:
        raise InputError(f"config.capacity and config.K must be >= 1, got {config.capacity}, {config.K}")
    if not (0 < config.gate <= config.new_threshold):
        raise InputError(f"config.gate/new_threshold: need 0 < gate <= new_threshold, got "
                         f"{config.gate}, {config.new_threshold}")
    if config.joint_gate is not None and not (0.0 < config.joint_gate < 1.0):
        raise InputError(f"config.joint_gate: need a probability in (0, 1), got {config.joint_gate}")
    if config.prune_window_s is not None and not (config.prune_window_s > 0 and int(config.prune_min_obs) >= 1):
        raise InputError(f"config.prune_window_s/prune_min_obs: need > 0 and >= 1, got "
                         f"{config.prune_window_s}, {config.prune_min_obs}")
    return config


def validate_params(params: PlanarParams) -> PlanarParams:
    """Shapes (M_c (2,2), Q_floor (3,3), R (2,2), P0 (3,3)); PSD, R positive definite."""
    for name, shp in (("M_c", (2, 2)), ("Q_floor", (3, 3)), ("R", (2, 2)), ("P0", (3, 3)),
                      ("calib0", (3,)), ("calib_P0", (3, 3)), ("calib_Q", (3, 3))):
        if getattr(params, name) is None and name.startswith("calib"):
            continue
        a = np.asarray(getattr(params, name))
        if name == "calib0":
            if a.shape != shp or not np.all(np.isfinite(a)):
                raise InputError(f"params.calib0: expected a finite shape {shp}, got {a!r}")
            continue
        if a.shape != shp:
            raise InputError(f"params.{name}: expected shape {shp}, got {a.shape}")
        check_psd(a, f"params.{name}", strict=(name == "R"))
    return params


def validate_log(log: EventLog) -> EventLog:
    """Shapes of an EventLog for the 2D system: u (T, 2), z (T, K, 2), ids/mask (T, K); dt ≥ 0 finite."""
    T = np.shape(log.dt)[0]
    if np.shape(log.u) != (T, 2):
        raise InputError(f"log.u: expected shape ({T}, 2), got {np.shape(log.u)}")
    zs = np.shape(log.z)
    if len(zs) != 3 or zs[0] != T or zs[2] != 2:
        raise InputError(f"log.z: expected shape ({T}, K, 2), got {zs}")
    for name in ("ids", "mask"):
        if np.shape(getattr(log, name)) != zs[:2]:
            raise InputError(f"log.{name}: expected shape {zs[:2]}, got {np.shape(getattr(log, name))}")
    dt = np.asarray(log.dt)
    if not np.all(np.isfinite(dt)) or np.any(dt < 0):
        raise InputError("log.dt: must be finite and >= 0")
    if not np.all(np.isfinite(np.asarray(log.u))):
        raise InputError("log.u: contains NaN or Inf")
    return log
