"""Paper 003's range-only UWB EKF-SLAM in 2D, on the generic EKF-SLAM engine.

A *system* module: it fixes the state order, the motion and observation models,
the tabled Q and R, the trilateration start-up and the localisation mode, and
plugs them into :mod:`jaxslam.filters.ekf_slam` (``init``/``predict``/
``update``/``add_landmark``).  It is not a filter of its own.

Interface (every system's): :class:`Config` (static), :class:`Params` (traced noise and thresholds),
:class:`Log` (one flight; ``anchors`` known in localisation mode, None for SLAM),
:class:`Event` (one step's slice), :class:`State`, :class:`StepOut`, :class:`Result`;
:func:`init`, :func:`step`, and :func:`run` (host-side checks, then one jitted
``lax.scan`` of :func:`step`).

State (engine order; paper 003 eq. 14 with a documented permutation)::

    engine  x = [x, y, v_x, v_y, α, β, θ, w_α, w_β, w_θ | l_1x, l_1y, ..., l_Nx, l_Ny]
    eq. 14  x = [x, y, v_x, v_y, l_1x, l_1y, ..., l_Nx, l_Ny, α, β, θ, w_α, w_β, w_θ]

The engine keeps the robot block first and the padded map after it, so the
paper's trailing attitude block moves in front of the map;
:func:`paper_permutation` gives ``x_eq14 = x_engine[perm]`` (and the same
permutation of P's rows and columns).  Units: m, m/s, rad, rad/s.

Equations (paper 003; errata in docs/papers.md):

* motion (eq. 12, 15) with an explicit Δt (errata: the paper steps with a unit
  time): p ← p + v Δt, v ← v, angles ← angles + w Δt, w ← w; landmarks static.
* process noise (eq. 27): the paper's diagonal Q = diag(0.01, 0.01, 0.1, 0.1,
  0…0, π/15 ×3, 1 ×3) is per iteration; jaxslam reads it as a density per
  second, Q_d = Q Δt (identical at the paper's Δt = 1).  The landmark entries
  are the engine's static map.  :func:`ncv_process_noise` also offers the
  white-noise-acceleration ("nearly constant velocity") Q_d of a continuous
  model, used by the matched (consistent) preset.
* UWB observation: squared range (eq. 17, the paper's) or plain range
  (eq. 16); gyro observation (eq. 19) Ω = w.  Eq. 20 stacks them into one
  update; jaxslam applies the N range rows and then the 3 gyro rows as two
  engine updates at the same step.  The gyro rows are linear in the state, so
  the second update equals the joint eq. 20 update exactly (sequential
  processing of measurements with independent noise is exact for a linear
  model, and the range rows are linearised at the same prior in both).
  H comes from ``jax.jacfwd`` (eq. 18, 21 are the tests' oracles).
* update: the engine's factored Joseph form (errata: eq. 10 carries a stray E).
* R (Sec. IV): diag(0.2 per UWB row, 0.01 per gyro row) with the squared-range
  model (units m⁴ and (rad/s)²).  The paper gives no R for the plain range
  model; jaxslam uses 0.2² = 0.04 m² (the paper's 0.2 "similar to the maximum
  deviation" read as a standard deviation in metres).
* start-up (Sec. III-D, eq. 22-26), :func:`startup`: the drone flies straight
  from anchor ``start`` to anchor ``end``.  Its recorded positions are
  (−d_end(k), 0); the end anchor is the origin with zero variance, the start
  anchor is (−D, 0) with D the first range to the end anchor, variance = the
  range variance σ² on both axes (the paper's "observations variance"; its
  y error is in fact zero in the start-up frame).  The remaining anchors are
  trilaterated from the recorded line (:func:`jaxslam.filters.trilateration.trilaterate_line`):
  eq. 26 is rank deficient on a line (see that module), so the along-line
  coordinate comes from eq. 26 and the offset from the mean of y².  The sign
  of y is unobservable from a line: the anchor with the largest offset is
  put on +y (this choice fixes the reflection of the map frame) and
  initialised, with variance residual_max² on both axes (the paper's "square
  of the largest error observed in the Least Squares algorithm", read as the
  largest range residual in metres).  Every other anchor has an unknown side
  and waits for the **delayed initialisation**.
* delayed initialisation (paper silent; issue 6): the estimated robot
  positions and the ranges are buffered (``buffer_size`` samples every
  ``buffer_stride`` steps); an anchor not yet mapped is trilaterated from the
  buffer (:func:`jaxslam.filters.trilateration.trilaterate`, the general
  multi-point least-squares initialiser) once the buffered poses spread at
  least ``params.min_spread`` metres in their weakest direction and at least
  ``params.delayed_min_points`` ranges are valid.  Collinear poses therefore never
  produce a garbage landmark: the anchor stays unmapped and the step's
  ``pending`` flag says so.  Its covariance is the LS covariance (from σ²)
  plus the mean robot position variance of the buffered poses on both axes;
  cross-covariances are not formed (as in the paper's start-up).  Worth its
  compile time only with more than three anchors (the scenarios switch it on
  then): with three, a third anchor that fails the start-up leaves two anchors
  on one line, which cannot localise the robot off it — flagged ``DEGENERATE``.
* near-anchor gate (plain range model; paper silent): a range is skipped (and counted
  in ``near``) when the predicted distance is below 3 σ_r (0.35 m with the paper's
  noise).  There the direction of ∂d/∂p comes from the estimation error, and a range
  larger than predicted pushes the estimate further along that random direction:
  leaving the end anchor perpendicular to the start-up line, 2 of 100 SLAM runs on the
  square followed the mirror image (≈ 6 m error) without the gate, none with it.  A gate
  relative to √tr(P) was tried first and ran away (skipped ranges → larger P → more
  skipped; 56 m errors).  The squared model needs no gate (its H = 2 (p − l) vanishes
  at the anchor).
* robot initial state (Sec. III-D-1): position, attitude, velocity and rates
  0 at the end anchor; P0 = ``params.P0`` (the paper preset: all zero, "the
  exact initial position of the vehicle"; velocities and rates are not
  mentioned, zero as well).
* localisation mode (known anchors, the common UWB positioning use): the
  anchors are held in the map with zero covariance (the engine then never
  moves them) and the robot position is initialised by a single-epoch
  least-squares fix from the ranges at t = 0 (eq. 26 with the anchors as the
  known points), with the fix's propagated covariance (fallback: the latest
  good start-up fix, inflated for the time since; see :func:`init_localization`).
* measurements: a range that is received but not finite or ≤ 0, and a
  non-finite gyro sample, are masked, counted (``masked``) and flagged
  ``MASKED_INPUT``; a range not received (``range_mask`` False, e.g. out of
  range) is simply absent.
* matched preset (not in the paper; for consistency checks): R from the
  simulated variance; the squared-range R scales with the distance
  (``r_scaled``: R_k = 4 z_k² σ² + 2σ⁴ at the *measured* range z_k — the
  predicted range was tried first and let a badly started filter take
  metre-sized squared-range steps next to an anchor, where the predicted range
  and hence R are tiny), and the measurement is debiased (``debias``:
  z_k² − σ², since E[(d + δ)²] = d² + σ²); white-noise-acceleration Q.  The
  paper's R is constant.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..errors import InputError
from ..filters import ekf_slam as es
from ..filters import trilateration as tri
from ..linalg import check_int, check_mask, check_numbers, check_psd, check_scalar, host_array, is_concrete, wrap_angle
from ..sensors import uwb

__all__ = [
    "NR",
    "PAPER_Q",
    "PAPER_R_SQUARED",
    "PAPER_R_RANGE",
    "PAPER_R_GYRO",
    "Config",
    "Params",
    "NOISE_FIELDS",
    "Log",
    "Event",
    "StartupResult",
    "InitBuffer",
    "State",
    "StepOut",
    "Result",
    "paper_permutation",
    "to_paper_order",
    "motion",
    "paper_process_noise",
    "ncv_process_noise",
    "paper_params",
    "matched_params",
    "MATCHED_Q_ACC",
    "MATCHED_Q_ANG_ACC",
    "MATCHED_P0",
    "make_model",
    "make_gyro_model",
    "startup",
    "startup_frame",
    "init_slam",
    "init_localization",
    "init",
    "step",
    "run",
    "validate_params",
    "validate_log",
    "validate_anchors",
]

NR = 10  # robot block: [x, y, vx, vy, α, β, θ, wα, wβ, wθ]
POS, VEL, ANG, RATE = slice(0, 2), slice(2, 4), slice(4, 7), slice(7, 10)

# Paper 003 eq. 27, robot entries in engine order (per iteration = per second here).
PAPER_Q = (0.01, 0.01, 0.1, 0.1) + (math.pi / 15,) * 3 + (1.0,) * 3
PAPER_R_SQUARED = 0.2  # m⁴, Sec. IV
PAPER_R_RANGE = 0.04  # m², jaxslam's reading for eq. 16 (module docstring)
PAPER_R_GYRO = 0.01  # (rad/s)², Sec. IV


class Config(NamedTuple):
    """Static choices (hashable; a change recompiles): sizes, indices and switches.

    model: "squared" (eq. 17, paper) or "range" (eq. 16).
    mode: "slam" (anchors unknown, trilateration start-up) or "localization" (known anchors).
    dt: filter step Δt [s] (paper: 1 iteration).
    r_scaled: squared model only — R_k = 4 z_k² σ² + 2σ⁴ at the measured range z_k instead
      of the constant ``params.r_range``; the range model always uses ``params.r_range``.
    start_anchor, end_anchor: anchor indices of the forced straight-line start-up (static: they
      pick columns of the start-up ranges and are checked on the host against the log).
    delayed_init: buffer poses and map the remaining anchors later (SLAM mode).
    buffer_size, buffer_stride: delayed-initialisation buffer (samples, steps between samples;
      the size is a shape, the stride the buffer's sampling period).
    debias: squared model only — subtract σ² (``params.range_var``) from each measured
      squared range, whose mean is d² + σ² (not in the paper; the matched preset uses it).
    smooth: also the RTS-smoothed robot trajectory (``Result.smoothed``, ``smooth_status``):
      the backward pass of :func:`jaxslam.filters.ekf_slam.smooth_robot` over the run, the map
      held static (an anchor mapped late has no map term before it was mapped).  Offline: each
      step records O(10 · 2N) extra numbers.

    The thresholds (start-up and delayed-init point counts and spread, the χ² gate, the
    near-anchor gate, the localisation speed bound) are :class:`Params` fields: traced, so a
    new value never recompiles.
    """

    model: str = "squared"
    mode: str = "slam"
    dt: float = 1.0
    r_scaled: bool = False
    start_anchor: int = 0
    end_anchor: int = 1
    delayed_init: bool = True
    buffer_size: int = 24
    buffer_stride: int = 2
    debias: bool = False
    smooth: bool = False


class Params(NamedTuple):
    """Filter noise and thresholds (traced leaves: a new value never recompiles, and ``grad``
    w.r.t. the noise works).  The presets (:func:`paper_params`, :func:`matched_params`) set the
    noise; the thresholds keep their defaults unless replaced (``params._replace(gate=9.0)``).

    Q: (10, 10) discrete process noise per step (engine order; units² of the state per step).
    P0: (10, 10) initial robot covariance (SLAM mode; localisation replaces the position
      block by the LS fix covariance).
    r_range: () variance of one UWB row when not scaled [m⁴ squared model, m² range model].
    r_gyro: () variance of one gyro row [(rad/s)²].
    range_var: () σ² of one measured range [m²] (start-up and delayed-init variances, r_scaled).
    startup_min_points: valid samples an anchor needs in the start-up to be trilaterated
      (default 3; a count that is only compared, so a float works and ``grad`` over the whole
      Params stays legal).
    min_spread: weakest-direction spread of the buffered poses required by the delayed
      initialisation [m] (default 0.5).
    delayed_min_points: valid ranges an anchor needs in the delayed-init buffer (default 6).
    gate: optional χ² gate (1 dof) on each range; None = off (default, paper).  None ↔ a number
      changes the pytree (a switch: one more trace); another number does not.
    init_speed_bound: localisation — speed bound [m/s] that inflates an initial fix taken
      before t = 0 (see :func:`init_localization`; default 0.5).
    near_gate: plain range model only — skip a range whose predicted distance d̂ is below
      ``near_gate`` · σ_r (σ_r² = ``range_var``): there the direction of ∂d/∂p is set by the
      estimation error, not the geometry (default 3.0; None: off).
    """

    Q: jax.Array
    P0: jax.Array
    r_range: jax.Array
    r_gyro: jax.Array
    range_var: jax.Array
    startup_min_points: Any = 3.0
    min_spread: Any = 0.5
    delayed_min_points: Any = 6.0
    gate: Optional[Any] = None
    init_speed_bound: Any = 0.5
    near_gate: Optional[Any] = 3.0


#: The :class:`Params` fields that are filter noise (set by the presets; what a scenario's
#: ``--params`` file sets); the remaining fields are the thresholds.
NOISE_FIELDS = ("Q", "P0", "r_range", "r_gyro", "range_var")


class Log(NamedTuple):
    """Everything :func:`run` needs: one flight (simulated or real), N anchors.

    startup_ranges: (Ts, N) ranges [m] during the forced straight-line run, sample 0 at the
      start anchor, sample Ts−1 at the end anchor at t = 0 (where the EKF starts).
    startup_mask: (Ts, N) bool range received.
    ranges: (T, N) ranges [m] at t_k = k Δt, k = 1..T.
    range_mask: (T, N) bool range received (False: no measurement, e.g. out of range).
    gyro: (T, 3) gyro rates [rad/s] at t_k (non-finite = masked and counted).
    anchors: (N, 2) known anchor positions [m] for ``mode="localization"`` (the known map, in
      the frame the estimates are wanted in); None for ``mode="slam"``.
    """

    startup_ranges: jax.Array
    startup_mask: jax.Array
    ranges: jax.Array
    range_mask: jax.Array
    gyro: jax.Array
    anchors: Any = None


class Event(NamedTuple):
    """One step of a :class:`Log` (the slice :func:`step` takes)."""

    ranges: jax.Array  # (N,) [m]
    range_mask: jax.Array  # (N,) bool received
    gyro: jax.Array  # (3,) [rad/s]


class StartupResult(NamedTuple):
    """Map after the start-up (SLAM) or the initial fix (localisation).

    landmarks: (N, 2) initial anchor means [m] (start-up frame); cov: (N, 2, 2) [m²].
    initialised: (N,) bool anchor mapped at the start.
    positions: (Ts, 2) robot positions assumed during the start-up, (−d_end(k), 0) [m].
    residual_max: (N,) largest range residual of each trilaterated anchor [m].
    ref_anchor: () int32 anchor that fixed the reflection (+y); −1 if none.
    robot_pos: (2,) initial robot position [m]; robot_cov: (2, 2) its covariance [m²].
    status: () int32 (DEGENERATE: fewer than three anchors mapped, or a degenerate fix).
    """

    landmarks: jax.Array
    cov: jax.Array
    initialised: jax.Array
    positions: jax.Array
    residual_max: jax.Array
    ref_anchor: jax.Array
    robot_pos: jax.Array
    robot_cov: jax.Array
    status: jax.Array


class InitBuffer(NamedTuple):
    """Ring buffer of estimated poses and ranges for the delayed initialisation.

    pos: (W, 2) estimated robot positions [m]; pos_var: (W,) mean of their x/y variances [m²];
    ranges: (W, N) [m]; valid: (W, N) bool; count: () int32 samples written so far.
    """

    pos: jax.Array
    pos_var: jax.Array
    ranges: jax.Array
    valid: jax.Array
    count: jax.Array


class State(NamedTuple):
    """Scan carry: engine state, delayed-init buffer, step counter, measurement counts."""

    slam: es.SlamState
    buffer: InitBuffer
    k: jax.Array  # () int32 steps done
    masked: jax.Array  # () int32 received measurements masked as invalid, summed
    near: jax.Array  # () int32 ranges skipped by the near-anchor gate, summed


class StepOut(NamedTuple):
    """What one step records (small; the full covariance is not stacked).

    mean: (10,) robot mean; cov: (10, 10) robot covariance; landmarks: (N, 2) map means;
    lm_cov: (N, 2, 2) marginal map covariances; active: (N,) bool mapped;
    nis: () joint NIS of the step's updates; dof: () its degrees of freedom;
    pending: () bool some anchor still unmapped; status: () int32 OR-ed status so far;
    smoother: the step's :class:`~jaxslam.filters.ekf_slam.SmootherTerms` (``config.smooth``),
    else None.
    """

    mean: jax.Array
    cov: jax.Array
    landmarks: jax.Array
    lm_cov: jax.Array
    active: jax.Array
    nis: jax.Array
    dof: jax.Array
    pending: jax.Array
    status: jax.Array
    smoother: Any = None


class Result(NamedTuple):
    """Output of :func:`run`: per-step records (:class:`StepOut`, T leading), final
    :class:`State`, and the :class:`StartupResult` (start-up map or initial fix); with
    ``config.smooth`` also ``smoothed`` (T, 10) robot means and ``smooth_status`` (T,) int32
    (``NOT_PSD`` where a gain could not be formed), else None."""

    steps: StepOut
    final: State
    startup: StartupResult
    smoothed: Any = None
    smooth_status: Any = None


# ---------------------------------------------------------------------------
# State order
# ---------------------------------------------------------------------------

def paper_permutation(n_anchors: int) -> np.ndarray:
    """Indices ``perm`` with x_eq14 = x_engine[perm] (paper 003 eq. 14); (10 + 2N,) int."""
    n = int(n_anchors)
    lm = list(range(NR, NR + 2 * n))
    return np.asarray([0, 1, 2, 3] + lm + list(range(4, NR)), dtype=np.int64)


def to_paper_order(x, P, n_anchors: int):
    """(x, P) in engine order -> eq. 14 order: (x[perm], P[perm][:, perm])."""
    perm = paper_permutation(n_anchors)
    return x[perm], P[perm][:, perm]


# ---------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------

def motion(s, u, dt):
    """Constant-velocity step (paper 003 eq. 12, 15 with explicit Δt).

    s: (10,) robot state; u: unused (no odometry, paper Sec. III-B); dt: step [s].
    Returns (10,): p + v Δt, v, angles + w Δt, w.
    """
    dt = jnp.asarray(dt, s.dtype)
    return jnp.concatenate([s[POS] + s[VEL] * dt, s[VEL], s[ANG] + s[RATE] * dt, s[RATE]])


def paper_process_noise(dt, dtype=jnp.float64, q=PAPER_Q):
    """Q_d = diag(eq. 27 robot entries) · Δt  (10, 10); equals eq. 27 at Δt = 1.

    Built on the host (NumPy) when ``dt`` and ``q`` are known now: no eager programs to compile."""
    xp = np if is_concrete(dt, q) else jnp
    return host_array(xp.diag(xp.asarray(q, np.float64)) * dt, dtype)


def ncv_process_noise(dt, q_acc, q_ang_acc, dtype=jnp.float64):
    """White-noise-acceleration Q_d (10, 10) of the constant-velocity model.

    Per position axis q_acc [m²/s³] and per attitude axis q_ang_acc [rad²/s³]:
    [[Δt³/3, Δt²/2], [Δt²/2, Δt]] · q on (position, velocity) and (angle, rate).
    Not in paper 003 (its eq. 27 is diagonal); used by :func:`matched_params`.
    """
    xp = np if is_concrete(dt, q_acc, q_ang_acc) else jnp  # host-built when known now
    blk = xp.asarray([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    pairs = [(0, 2, q_acc), (1, 3, q_acc), (4, 7, q_ang_acc), (5, 8, q_ang_acc), (6, 9, q_ang_acc)]
    eye = np.eye(NR)
    Q = sum(q * (eye[[i, j]].T @ blk @ eye[[i, j]]) for i, j, q in pairs)  # blk on rows/cols (i, j)
    return host_array(Q, dtype)


def _default_thresholds(dtype) -> dict:
    """The threshold fields of :class:`Params` at their defaults, as arrays of ``dtype`` (None stays)."""
    return {k: None if v is None else host_array(v, dtype) for k, v in Params._field_defaults.items()}


def paper_params(model: str = "squared", dt: float = 1.0, noise: uwb.UwbNoise = uwb.PAPER003_NOISE,
                 dtype=jnp.float64) -> Params:
    """Paper 003 preset: Q of eq. 27 (· Δt), R of Sec. IV, P0 = 0 (Sec. III-D-1)."""
    uwb.check_model(model)
    r = PAPER_R_SQUARED if model == "squared" else PAPER_R_RANGE
    return Params(  # built on the host: no eager programs to compile
        Q=paper_process_noise(dt, dtype),
        P0=host_array(np.zeros((NR, NR)), dtype),
        r_range=host_array(r, dtype),
        r_gyro=host_array(PAPER_R_GYRO, dtype),
        range_var=host_array(uwb.uniform_variance(noise.range_half_width), dtype),
        **_default_thresholds(dtype),
    )


# Matched preset: white-noise acceleration densities that cover the deterministic manoeuvres
# of the three scenarios (the circle's 0.015 m/s², the square's corners, the rough path's
# 0.3 m/s jumps; yaw-rate changes up to 0.1 rad/s per step) — tuned on 100 localisation
# runs with Gaussian noise for a position ANEES inside its bounds (docs/papers.md, paper 003).
MATCHED_Q_ACC = 1e-2  # m²/s³
MATCHED_Q_ANG_ACC = 3e-4  # rad²/s³
MATCHED_P0 = (0.0, 0.0, 0.3**2, 0.3**2, 0.0, 0.0, 0.0, 0.1**2, 0.1**2, 0.1**2)


def matched_params(model: str = "squared", dt: float = 1.0, noise: uwb.UwbNoise = uwb.PAPER003_NOISE,
                   q_acc: float = MATCHED_Q_ACC, q_ang_acc: float = MATCHED_Q_ANG_ACC,
                   p0=MATCHED_P0, dtype=jnp.float64) -> Params:
    """Preset matched to the simulated noise: R from σ² = a²/3, NCV process noise.

    Use with ``Config(r_scaled=True, debias=True)`` for the squared model
    (R_k = 4 d̂² σ² + 2σ⁴, measurements z² − σ²).
    """
    uwb.check_model(model)
    s2 = uwb.uniform_variance(noise.range_half_width)
    return Params(  # built on the host: no eager programs to compile
        Q=ncv_process_noise(dt, q_acc, q_ang_acc, dtype),
        P0=host_array(np.diag(np.asarray(p0, np.float64)), dtype),
        r_range=host_array(s2 if model == "range" else uwb.squared_range_variance(1.0, s2), dtype),
        r_gyro=host_array(uwb.uniform_variance(noise.gyro_half_width), dtype),
        range_var=host_array(s2, dtype),
        **_default_thresholds(dtype),
    )


def make_model(model: str = "squared") -> es.SlamModel:
    """The UWB range model for the engine: robot 10, landmark 2, one row per anchor (eq. 16/17).
    One model object per range model, so the engine's steps called eagerly find their compiled
    programs again."""
    uwb.check_model(model)
    return _range_model(model)


@functools.lru_cache(maxsize=None)
def _range_model(model: str) -> es.SlamModel:
    def observe(s, l, params):
        return uwb.observe_range(s[POS], l, model)

    return es.SlamModel(robot_dim=NR, lm_dim=2, meas_dim=1, motion=motion, observe=observe)


def _gyro_observe(s, l, params):
    # Eq. 19 does not involve a landmark; the engine's update addresses a slot, and the
    # Jacobian with respect to that slot's landmark is zero, so any active slot serves.
    return uwb.gyro(s[RATE])


def make_gyro_model() -> es.SlamModel:
    """The gyro rows of eq. 20 (eq. 19) as an engine model (meas 3, landmark-independent)."""
    return es.SlamModel(robot_dim=NR, lm_dim=2, meas_dim=3, motion=motion, observe=_gyro_observe)


# ---------------------------------------------------------------------------
# Start-up and initial states
# ---------------------------------------------------------------------------

def startup_frame(anchors, ref, start: int = 0, end: int = 1):
    """World → start-up frame of the trilateration start-up: p_S = M (p_W − origin).

    ``anchors`` (N, 2) world positions; ``ref`` the anchor that fixed the side (from
    :class:`StartupResult`); ``start``/``end`` the anchors of the straight-line start-up
    (``Config.start_anchor``/``end_anchor``).  Returns (M (2, 2), origin (2,)): origin at the
    end anchor, +x from the start to the end anchor, +y on the side of anchor ``ref`` (det M = −1
    when that needs a reflection; ``ref`` < 0: no reflection).
    """
    a, b = anchors[start], anchors[end]
    u = (b - a) / jnp.linalg.norm(b - a)
    v = jnp.stack([-u[1], u[0]])
    c = anchors[jnp.clip(ref, 0, anchors.shape[0] - 1)]
    side = jnp.sign(jnp.dot(v, c - b))
    side = jnp.where((ref < 0) | (side == 0), 1.0, side).astype(anchors.dtype)
    return jnp.stack([u, side * v]), b


def startup(startup_ranges, startup_mask, config: Config, params: Params) -> StartupResult:
    """Forced straight-line start-up and LS trilateration (paper 003 Sec. III-D, eq. 22-26).

    startup_ranges: (Ts, N) [m]; startup_mask: (Ts, N) bool.  Jit-able (``config`` static).
    Frame (the *start-up frame*): origin at the end anchor, +x from the start anchor to
    the end anchor, +y towards the anchor with the largest offset from the line.
    See the module docstring for the variances.  Returns :class:`StartupResult`.
    """
    dtype = params.range_var.dtype
    z = jnp.asarray(startup_ranges, dtype)
    Ts, N = z.shape
    ok = startup_mask & uwb.valid_ranges(z)
    a, b = config.start_anchor, config.end_anchor
    d_end = jnp.where(ok[:, b], z[:, b], 0.0)
    xs = -d_end
    first = jnp.argmax(ok[:, b])
    D = d_end[first]
    have_end = jnp.any(ok[:, b])
    positions = jnp.stack([xs, jnp.zeros_like(xs)], axis=1)

    def one(zi, oki):
        return tri.trilaterate_line(xs, zi, oki & ok[:, b], side=1.0,
                                    min_points=params.startup_min_points)

    res = jax.vmap(one, in_axes=(1, 1))(z, ok)
    others = (jnp.arange(N) != a) & (jnp.arange(N) != b)
    cand = res.ok & others & have_end
    offset2 = jnp.where(cand, res.position[:, 1] ** 2, -1.0)
    ref = jnp.argmax(offset2)
    has_ref = jnp.any(cand)

    L = jnp.zeros((N, 2), dtype)
    L = L.at[a].set(jnp.stack([-D, jnp.zeros((), dtype)]))
    L = jnp.where((jnp.arange(N) == ref)[:, None] & has_ref, res.position, L)
    s2 = params.range_var
    eye = jnp.eye(2, dtype=dtype)
    C = jnp.zeros((N, 2, 2), dtype)
    C = C.at[a].set(s2 * eye)
    C = jnp.where(((jnp.arange(N) == ref) & has_ref)[:, None, None],
                  (res.residual_max ** 2)[:, None, None] * eye, C)
    init = (jnp.arange(N) == b) | ((jnp.arange(N) == a) & (D > 0)) | ((jnp.arange(N) == ref) & has_ref)
    init = init & have_end
    n_init = jnp.sum(init)
    status = (jnp.where(n_init < 3, errors.DEGENERATE, 0)
              | jnp.where(first > 0, errors.DEGENERATE, 0)
              | jnp.where(jnp.any(startup_mask & ~uwb.valid_ranges(z)), errors.MASKED_INPUT, 0))
    return StartupResult(
        landmarks=L,
        cov=C,
        initialised=init,
        positions=positions,
        residual_max=jnp.where(cand, res.residual_max, 0.0),
        ref_anchor=jnp.where(has_ref, ref, -1).astype(jnp.int32),
        robot_pos=jnp.zeros((2,), dtype),
        robot_cov=params.P0[POS, POS],
        status=jnp.asarray(status, jnp.int32),
    )


def _empty_buffer(config: Config, n_anchors: int, dtype) -> InitBuffer:
    W = config.buffer_size
    return InitBuffer(
        pos=jnp.zeros((W, 2), dtype),
        pos_var=jnp.zeros((W,), dtype),
        ranges=jnp.zeros((W, n_anchors), dtype),
        valid=jnp.zeros((W, n_anchors), bool),
        count=jnp.zeros((), jnp.int32),
    )


def _with_map(st: es.SlamState, model: es.SlamModel, means, covs, ok):
    """Write anchors i (slot i, id i) with zero cross-covariance where ok[i]."""
    n = st.x.shape[0]
    N = means.shape[0]

    def body(i, s):
        return es.add_landmark(s, model, i, means[i], covs[i], jnp.zeros((2, n), st.x.dtype), i,
                               ok=ok[i])

    return jax.lax.fori_loop(0, N, body, st)


def init_slam(start: StartupResult, config: Config, params: Params) -> State:
    """EKF-SLAM state after the start-up: robot at the end anchor, mapped anchors written."""
    dtype = params.P0.dtype
    N = start.landmarks.shape[0]
    model = make_model(config.model)
    st = es.init(jnp.zeros((NR,), dtype), params.P0, N, 2)
    st = _with_map(st, model, start.landmarks, start.cov, start.initialised)
    st = st._replace(status=st.status | start.status)
    z = jnp.zeros((), jnp.int32)
    return State(st, _empty_buffer(config, N, dtype), z, z, z)


def init_localization(anchors, startup_ranges, startup_mask, config: Config, params: Params):
    """Localisation with known anchors (N, 2): robot fixed by LS trilateration at t = 0.

    startup_ranges, startup_mask: (Ts, N) ranges [m] of the start-up samples; the last
    one is at t = 0.  The fix (eq. 26 with the anchors as the known points) gives the
    position and its propagated covariance.  If the t = 0 fix is degenerate (fewer than
    three valid ranges — e.g. a range ≤ 0 on top of an anchor — or collinear anchors), the
    latest non-degenerate start-up fix j is used, its covariance inflated by
    (``params.init_speed_bound`` · (Ts − 1 − j) Δt)² per axis for the motion since; with no
    usable fix at all ``DEGENERATE`` is set and the anchors' centroid is used with a
    variance of the anchors' squared extent.  Returns (State, StartupResult).
    """
    dtype = params.P0.dtype
    anchors = jnp.asarray(anchors, dtype)
    N = anchors.shape[0]
    z = jnp.asarray(startup_ranges, dtype)
    Ts = z.shape[0]
    fixes = jax.vmap(lambda zi, mi: tri.trilaterate(anchors, zi, mi, range_var=params.range_var))(
        z, startup_mask)
    any_ok = jnp.any(fixes.ok)
    j = Ts - 1 - jnp.argmax(fixes.ok[::-1])
    lag = (Ts - 1 - j).astype(dtype) * (jnp.asarray(config.dt, dtype)
                                        * jnp.asarray(params.init_speed_bound, dtype))
    eye = jnp.eye(2, dtype=dtype)
    centre = jnp.mean(anchors, axis=0)
    extent2 = jnp.max(jnp.sum((anchors - centre) ** 2, axis=1))
    pos = jnp.where(any_ok, fixes.position[j], centre)
    pcov = jnp.where(any_ok, fixes.cov[j] + lag * lag * eye, extent2 * eye)
    P0 = params.P0.at[POS, POS].set(pcov).at[POS, 2:].set(0.0).at[2:, POS].set(0.0)
    s0 = jnp.zeros((NR,), dtype).at[POS].set(pos)
    model = make_model(config.model)
    st = es.init(s0, P0, N, 2)
    st = _with_map(st, model, anchors, jnp.zeros((N, 2, 2), dtype), jnp.ones((N,), bool))
    status = (jnp.where(any_ok, 0, errors.DEGENERATE)
              | jnp.where(jnp.any(startup_mask & ~uwb.valid_ranges(z)), errors.MASKED_INPUT, 0))
    status = jnp.asarray(status, jnp.int32)
    st = st._replace(status=st.status | status)
    start = StartupResult(
        landmarks=anchors,
        cov=jnp.zeros((N, 2, 2), dtype),
        initialised=jnp.ones((N,), bool),
        positions=jnp.zeros((0, 2), dtype),
        residual_max=jnp.zeros((N,), dtype),
        ref_anchor=jnp.asarray(-1, jnp.int32),
        robot_pos=pos,
        robot_cov=pcov,
        status=status,
    )
    z0 = jnp.zeros((), jnp.int32)
    return State(st, _empty_buffer(config, N, dtype), z0, z0, z0), start


# ---------------------------------------------------------------------------
# One filter step
# ---------------------------------------------------------------------------

def _range_R(z, ok, cfg, params, N, dtype):
    if cfg.model == "squared" and cfg.r_scaled:
        # Scaled with the *measured* range: the predicted one can be far off (a wrong start,
        # a pass next to an anchor), and a tiny R there lets the squared-range update jump.
        d = jnp.where(ok, z, 0.0)
        r = uwb.squared_range_variance(d, params.range_var)
    else:
        r = jnp.broadcast_to(params.r_range, (N,))
    return r.astype(dtype)[:, None, None]


def _near_anchor(st, N, k, range_var):
    """(N,) bool: predicted distance < k · σ_r (σ_r² = ``range_var``)."""
    L = st.x[NR:].reshape(N, 2)
    d2 = jnp.sum((L - st.x[POS]) ** 2, axis=1)
    return d2 < (k * k) * range_var


def _delayed_init(fs: State, z, ok, cfg: Config, params: Params, model):
    st = fs.slam
    buf = fs.buffer
    W = cfg.buffer_size
    dtype = st.x.dtype
    push = (fs.k % cfg.buffer_stride) == 0
    i = buf.count % W
    pv = 0.5 * (st.P[0, 0] + st.P[1, 1])
    buf = InitBuffer(
        pos=buf.pos.at[i].set(jnp.where(push, st.x[POS], buf.pos[i])),
        pos_var=buf.pos_var.at[i].set(jnp.where(push, pv, buf.pos_var[i])),
        ranges=buf.ranges.at[i].set(jnp.where(push, jnp.where(ok, z, 0.0), buf.ranges[i])),
        valid=buf.valid.at[i].set(jnp.where(push, ok, buf.valid[i])),
        count=buf.count + push.astype(jnp.int32),
    )
    filled = jnp.arange(W) < buf.count

    def one(zi, vi):
        return tri.trilaterate(buf.pos, zi, vi & filled, range_var=params.range_var,
                               min_points=params.delayed_min_points, min_spread=params.min_spread)

    res = jax.vmap(one, in_axes=(1, 1))(buf.ranges, buf.valid)
    new = res.ok & ~st.active
    n_f = jnp.maximum(jnp.sum(filled), 1).astype(dtype)
    pvar = jnp.sum(jnp.where(filled, buf.pos_var, 0.0)) / n_f
    cov = res.cov + pvar * jnp.eye(2, dtype=dtype)[None]
    st = _with_map(st, model, res.position, cov, new)
    return fs._replace(slam=st, buffer=buf)


def step(state: State, event: Event, config: Config, params: Params, *, key=None):
    """One EKF step at t_k: predict over Δt, UWB update, gyro update, delayed init.

    Paper 003 eq. 4-9 with eq. 12/15 (motion), eq. 16/17 + 19 (observations), Joseph form.
    ``event``: the step's :class:`Event` (ranges (N,) [m], range_mask (N,) bool received,
    gyro (3,) rad/s).  ``config`` static; ``key`` unused (every system's ``step`` takes it).
    Returns (State, StepOut).  Jit-able; use :func:`run` for a whole log.
    """
    del key
    fs, cfg = state, config
    z, zmask, gyro_z = event.ranges, event.range_mask, event.gyro
    model = make_model(cfg.model)
    gmodel = make_gyro_model()
    st = fs.slam
    dtype = st.x.dtype
    N = z.shape[0]
    z = jnp.asarray(z, dtype)
    gyro_z = jnp.asarray(gyro_z, dtype)

    st = es.predict(st, model, None, params.Q.astype(dtype), cfg.dt)

    valid = uwb.valid_ranges(z)
    ok = zmask & valid
    received_ok = ok  # the delayed-init buffer keeps near-anchor ranges (LS has no linearisation)
    bad = zmask & ~valid
    if cfg.model == "range" and params.near_gate is not None:
        near = (_near_anchor(st, N, jnp.asarray(params.near_gate, dtype), params.range_var.astype(dtype))
                & ok & st.active)
        ok = ok & ~near
    else:
        near = jnp.zeros_like(ok)
    zz = jnp.where(ok, z, 0.0)
    if cfg.model == "squared":
        # (d + δ)² has mean d² + σ²: the debiased measurement removes the offset.
        meas = zz * zz - (params.range_var if cfg.debias else 0.0)
    else:
        meas = zz
    R = _range_R(z, ok, cfg, params, N, dtype)
    st, info_r = es.update(st, model, meas[:, None], jnp.arange(N), ok, R, None, gate=params.gate)

    g_ok = jnp.all(jnp.isfinite(gyro_z)) & jnp.any(st.active)
    g_bad = ~jnp.all(jnp.isfinite(gyro_z))
    slot = jnp.argmax(st.active)[None]
    Rg = params.r_gyro.astype(dtype) * jnp.eye(3, dtype=dtype)
    st, info_g = es.update(st, gmodel, jnp.where(jnp.isfinite(gyro_z), gyro_z, 0.0)[None], slot,
                           g_ok[None], Rg, None)

    n_bad = jnp.sum(bad) + g_bad.astype(jnp.int32)
    st = st._replace(status=st.status | jnp.where(n_bad > 0, errors.MASKED_INPUT, 0))
    fs = fs._replace(slam=st, masked=fs.masked + n_bad.astype(jnp.int32),
                     near=fs.near + jnp.sum(near).astype(jnp.int32))
    if cfg.mode == "slam" and cfg.delayed_init:
        fs = _delayed_init(fs, z, received_ok, cfg, params, model)
    fs = fs._replace(k=fs.k + 1)
    st = fs.slam
    pending = ~jnp.all(st.active)
    out = StepOut(
        mean=st.x[:NR],
        cov=st.P[:NR, :NR],
        landmarks=es.landmarks(st, model),
        lm_cov=es.landmark_covs(st, model),
        active=st.active,
        nis=info_r.nis + info_g.nis,
        dof=info_r.dof + info_g.dof,
        pending=pending,
        status=st.status,
        smoother=es.smoother_terms(st, model) if cfg.smooth else None,
    )
    return fs, out


def _init(log: Log, config: Config, params: Params):
    """(State, StartupResult) before the first step (:func:`init`; :func:`run` keeps both).
    ``State.masked`` starts at the start-up's received ranges masked as invalid (the status
    already said ``MASKED_INPUT`` for them; the count said 0)."""
    if config.mode == "slam":
        start = startup(log.startup_ranges, log.startup_mask, config, params)
        st = init_slam(start, config, params)
    elif config.mode == "localization":
        if log.anchors is None:
            raise InputError("log.anchors: required in mode='localization'")
        st, start = init_localization(log.anchors, log.startup_ranges, log.startup_mask, config, params)
    else:
        raise InputError(f"config.mode: expected 'slam' or 'localization', got {config.mode!r}")
    bad = jnp.sum(jnp.asarray(log.startup_mask, bool) & ~uwb.valid_ranges(jnp.asarray(log.startup_ranges)))
    return st._replace(masked=st.masked + bad.astype(jnp.int32)), start


def init(log: Log, config: Config, params: Params, *, key=None) -> State:
    """The state before the first step (t = 0).  SLAM: the straight-line start-up
    (:func:`startup`) mapped by :func:`init_slam`; localisation: the known ``log.anchors`` and
    the LS fix of :func:`init_localization`.  ``key`` unused."""
    del key
    return _init(log, config, params)[0]


def _check_log_arrays(log: Log, T: int) -> None:
    """At least one step; numbers (a string array failed deep in JAX); bool or integer masks (a float mask
    failed inside the scan)."""
    if T == 0:  # an empty log failed deep inside the run (an IndexError)
        raise InputError("log.ranges: expected at least one step, got an empty log (T = 0)")
    for name in ("startup_ranges", "ranges", "gyro"):
        x = getattr(log, name)
        if is_concrete(x) and not (isinstance(x, (jax.Array, np.ndarray)) and x.dtype.kind in "biuf"):
            check_numbers(x, f"log.{name}")
    for name in ("startup_mask", "range_mask"):
        check_mask(getattr(log, name), f"log.{name}")


def _check_anchor_indices(config: Config, N: int) -> None:
    a = check_int(config.start_anchor, "config.start_anchor", lower=0)  # a float failed as an indexer
    b = check_int(config.end_anchor, "config.end_anchor", lower=0)
    if not (a < N and b < N) or a == b:
        raise InputError(f"config.start_anchor/end_anchor: need two distinct anchors in [0, {N}), got {a}, {b}")


def _check(log: Log, config: Config, params: Params) -> None:
    """Host-side checks of :func:`run`'s inputs (shapes always; values when concrete)."""
    if config.mode not in ("slam", "localization"):
        raise InputError(f"config.mode: expected 'slam' or 'localization', got {config.mode!r}")
    if config.model not in uwb.MODELS:
        raise InputError(f"config.model: expected one of {uwb.MODELS}, got {config.model!r}")
    for name in ("debias", "r_scaled", "smooth", "delayed_init"):  # a string "no" read as True
        errors.check_flag(getattr(config, name), f"config.{name}")
    check_int(config.buffer_size, "config.buffer_size", what="an int (delayed-initialisation samples)")
    check_int(config.buffer_stride, "config.buffer_stride", what="an int (steps between buffer samples)")
    if is_concrete(config.dt):  # a NaN dt froze the positions (NON_FINITE), 0 silently stopped time
        check_scalar(config.dt, "config.dt", lower=0, strict=True)
    shp = np.shape(log.startup_ranges)
    if len(shp) != 2 or shp[0] < 1:
        raise InputError(f"log.startup_ranges: expected shape (Ts, N), got {shp}")
    Ts, N = shp
    if np.ndim(log.ranges) != 2 or np.shape(log.ranges)[1] != N:
        raise InputError(f"log.ranges: expected shape (T, {N}), got {np.shape(log.ranges)}")
    T = np.shape(log.ranges)[0]
    for name, shape in (("startup_mask", (Ts, N)), ("range_mask", (T, N)), ("gyro", (T, 3))):
        if np.shape(getattr(log, name)) != shape:
            raise InputError(f"log.{name}: expected shape {shape}, got {np.shape(getattr(log, name))}")
    _check_log_arrays(log, T)
    if config.mode == "slam":
        if log.anchors is not None:
            raise InputError("log.anchors: known anchors are for mode='localization'; give None in mode='slam'")
        _check_anchor_indices(config, N)
    else:
        if log.anchors is None:
            raise InputError("log.anchors: required in mode='localization'")
        if np.shape(log.anchors) != (N, 2):
            raise InputError(f"log.anchors: expected shape ({N}, 2), got {np.shape(log.anchors)}")
        if is_concrete(log.anchors):
            validate_anchors(log.anchors, "log.anchors")
    for name, shape in (("Q", (NR, NR)), ("P0", (NR, NR)), ("r_range", ()), ("r_gyro", ()), ("range_var", ())):
        v = getattr(params, name)
        if is_concrete(v) and not isinstance(v, (jax.Array, np.ndarray)):
            check_numbers(v, f"params.{name}")  # a string: "expected numbers", not a shape ()
        if np.shape(getattr(params, name)) != shape:
            raise InputError(f"params.{name}: expected shape {shape}, got {np.shape(getattr(params, name))}")
    for name in Params._fields:
        v = getattr(params, name)
        if name not in NOISE_FIELDS and v is not None and np.shape(v) != ():
            raise InputError(f"params.{name}: expected a scalar, got shape {np.shape(v)}")
    if is_concrete(params):
        validate_params(params)


def run(log: Log, config: Config = Config(), params: Optional[Params] = None, *, key=None) -> Result:
    """Whole log as one jitted ``lax.scan`` of :func:`step` (start-up or known-anchor fix first).

    ``config`` static (``config.mode`` "localization" needs ``log.anchors``, "slam" needs
    None); ``params`` default: :func:`paper_params` of ``config.model`` and ``config.dt``;
    ``key`` unused.  Inputs are checked on the host (shapes; values when concrete) and
    raise InputError naming the argument; data problems that the filter flags instead
    (masked samples, a degenerate start-up) are :func:`validate_log`'s.  Works under an outer
    ``jax.jit`` / ``jax.vmap`` (traced log and params).
    """
    del key
    x = log.ranges
    if is_concrete(x) and not (isinstance(x, (jax.Array, np.ndarray)) and x.dtype.kind in "biuf"):
        check_numbers(x, "log.ranges")  # before its dtype picks the default parameters'
    if params is None:
        if config.model not in uwb.MODELS:
            raise InputError(f"config.model: expected one of {uwb.MODELS}, got {config.model!r}")
        if is_concrete(config.dt):  # (the defaults are built from it: a string was NumPy's own error)
            check_scalar(config.dt, "config.dt", lower=0, strict=True)
        params = paper_params(config.model, config.dt, dtype=jnp.result_type(log.ranges, float))
    _check(log, config, params)
    return _run(log, config, _thresholds_as_arrays(params))


def _thresholds_as_arrays(params: Params) -> Params:
    """The threshold fields as arrays of the noise's dtype (None stays None): a Python number and
    an array of the same value then reach ``_run`` with the same type, so neither retraces."""
    dtype = jnp.result_type(params.range_var)
    return params._replace(**{k: None if getattr(params, k) is None else host_array(getattr(params, k), dtype)
                              for k in Params._fields if k not in NOISE_FIELDS})


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params) -> Result:
    fs, start = _init(log, config, params)
    events = Event(ranges=log.ranges, range_mask=log.range_mask, gyro=log.gyro)
    final, steps = jax.lax.scan(lambda c, ev: step(c, ev, config, params), fs, events)
    if not config.smooth:
        return Result(steps=steps, final=final, startup=start)
    T = steps.mean.shape[0]
    dtype = steps.mean.dtype
    Qs = jnp.broadcast_to(params.Q.astype(dtype), (T, NR, NR))

    def difference(a, b):  # robot states: the three angles wrapped
        d = a - b
        return d.at[ANG].set(wrap_angle(d[ANG]))

    rs, sst = es.smooth_robot(make_model(config.model), steps.smoother, None, Qs, final.slam,
                              params=jnp.full((T,), config.dt, dtype), difference=difference)
    return Result(steps=steps._replace(smoother=None), final=final, startup=start, smoothed=rs,
                  smooth_status=sst)


# ---------------------------------------------------------------------------
# Host-side validation (public boundary, before jit)
# ---------------------------------------------------------------------------

def validate_params(params: Params) -> Params:
    """Shapes and PSD of Q, P0; positive r_range, r_gyro, range_var; finite non-negative scalar
    thresholds (``gate`` and ``near_gate`` may be None: off)."""
    for name, shp in (("Q", (NR, NR)), ("P0", (NR, NR))):
        a = check_numbers(getattr(params, name), f"params.{name}")
        if a.shape != shp:
            raise InputError(f"params.{name}: expected shape {shp}, got {a.shape}")
        check_psd(a, f"params.{name}")
    for name in ("r_range", "r_gyro", "range_var"):
        check_scalar(getattr(params, name), f"params.{name}", lower=0, strict=True)
    for name in Params._fields:
        if name in NOISE_FIELDS or getattr(params, name) is None:
            continue
        check_scalar(getattr(params, name), f"params.{name}", lower=0)
    return params


def validate_anchors(anchors, name: str = "anchors", min_separation: float = 1e-6) -> np.ndarray:
    """(N, 2) finite anchors, N ≥ 3, no two closer than ``min_separation`` [m], not all collinear."""
    A = check_numbers(anchors, name)
    if A.ndim != 2 or A.shape[1] != 2:
        raise InputError(f"{name}: expected shape (N, 2), got {A.shape}")
    if A.shape[0] < 3:
        raise InputError(f"{name}: range-only positioning needs at least 3 anchors, got {A.shape[0]}")
    if not np.all(np.isfinite(A)):
        raise InputError(f"{name}: contains NaN or Inf")
    d = np.linalg.norm(A[:, None, :] - A[None, :, :], axis=-1)
    d[np.diag_indices(A.shape[0])] = np.inf
    i, j = np.unravel_index(np.argmin(d), d.shape)
    if d[i, j] < min_separation:
        raise InputError(f"{name}: anchors {i} and {j} coincide (distance {d[i, j]:.3g} m)")
    c = A - A.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[-1] <= 1e-9 * max(sv[0], 1e-300):
        raise InputError(f"{name}: all anchors are collinear; a 2D fix is not defined")
    return A


def validate_log(log: Log, config: Config, strict: bool = False, params: Optional[Params] = None) -> Log:
    """Host-side checks of a log before :func:`run` (raises InputError naming the problem).

    Shapes; N ≥ 3 anchors; in SLAM mode: start ≠ end anchor, a range to the end anchor
    at the first start-up sample, and at least three anchors in range during the start-up
    (end anchor, start anchor, and one more with ``params.startup_min_points`` valid samples;
    ``params`` None: the default, 3);
    in localisation mode: valid ``log.anchors`` (:func:`validate_anchors`).  With ``strict``
    a received range that is NaN/Inf or ≤ 0, or a non-finite gyro sample, is an error;
    otherwise such samples are masked and counted by the filter.
    """
    sr = check_numbers(log.startup_ranges, "log.startup_ranges")
    if sr.ndim != 2 or sr.shape[0] < 1:
        raise InputError(f"log.startup_ranges: expected shape (Ts, N), got {sr.shape}")
    Ts, N = sr.shape
    if N < 3:
        raise InputError(f"log: range-only SLAM needs at least 3 anchors, got {N}")
    r = check_numbers(log.ranges, "log.ranges")
    if r.ndim != 2 or r.shape[1] != N:
        raise InputError(f"log.ranges: expected shape (T, {N}), got {r.shape}")
    T = r.shape[0]
    for name, arr, shp in (("startup_mask", log.startup_mask, (Ts, N)), ("range_mask", log.range_mask, (T, N)),
                           ("gyro", log.gyro, (T, 3))):
        if np.shape(arr) != shp:
            raise InputError(f"log.{name}: expected shape {shp}, got {np.shape(arr)}")
    _check_log_arrays(log, T)
    sm = np.asarray(log.startup_mask, bool)
    rm = np.asarray(log.range_mask, bool)
    with np.errstate(invalid="ignore"):
        s_ok = sm & np.isfinite(sr) & (sr > 0)
        r_bad = rm & ~(np.isfinite(r) & (r > 0))
        s_bad = sm & ~(np.isfinite(sr) & (sr > 0))
    if strict:
        for name, bad in (("log.startup_ranges", s_bad), ("log.ranges", r_bad)):
            if np.any(bad):
                k, i = np.argwhere(bad)[0]
                raise InputError(f"{name}: received range at sample {k}, anchor {i} is "
                                 f"{(sr if name.endswith('startup_ranges') else r)[k, i]!r} "
                                 "(must be finite and > 0)")
        g = np.asarray(log.gyro, dtype=np.float64)
        if not np.all(np.isfinite(g)):
            raise InputError("log.gyro: contains NaN or Inf")
    if config.mode == "slam":
        if log.anchors is not None:
            raise InputError("log.anchors: known anchors are for mode='localization'; give None in mode='slam'")
        _check_anchor_indices(config, N)
        a, b = int(config.start_anchor), int(config.end_anchor)
        if not s_ok[0, b]:
            raise InputError(f"log.startup_ranges: no valid range to the end anchor {b} at the start "
                             "of the forced run (the start anchor's position −D needs it)")
        if sr[0, b] <= 1e-6:
            raise InputError(f"log.startup_ranges: start and end anchors coincide (D = {sr[0, b]:.3g} m)")
        on_line = s_ok & s_ok[:, b:b + 1]
        n_pts = on_line.sum(axis=0)
        n_min = Params._field_defaults["startup_min_points"] if params is None else params.startup_min_points
        n_min = float(np.asarray(n_min))
        others = [i for i in range(N) if i not in (a, b) and n_pts[i] >= n_min]
        if len(others) < 1:
            raise InputError(
                "log.startup_ranges: fewer than three anchors in range during the start-up: "
                f"besides the start/end anchors ({a}, {b}) no anchor has {n_min:g} "
                f"valid ranges (counts per anchor: {n_pts.tolist()})")
    elif config.mode == "localization":
        if log.anchors is None:
            raise InputError("log.anchors: required in mode='localization'")
        A = validate_anchors(log.anchors, "log.anchors")
        if A.shape[0] != N:
            raise InputError(f"log.anchors: expected {N} anchors (the log's), got {A.shape[0]}")
    else:
        raise InputError(f"config.mode: expected 'slam' or 'localization', got {config.mode!r}")
    return log
