"""Line-feature EKF-SLAM from a 2D laser with optical flow and IMU yaw rate (paper 004).

Thesis ch. 4.2, eq. 4.10-4.15 and Algorithm 2, on the shared engine
:mod:`jaxslam.filters.ekf_slam` (no second EKF).  The thesis writes the model
with complex numbers (p, V ∈ ℂ) and the quaternion unit k̂ for angles; jaxslam
implements the equivalent real model:

    robot  s = [p_x, p_y, V_x, V_y, ψ, r]                 (n_r = 6)
           p  position in the map frame [m]           (thesis p ∈ ℂ: p_x + i p_y)
           V  body-frame horizontal velocity [m/s]     (V ∈ ℂ, from the optical flow)
           ψ  yaw [rad], r yaw rate [rad/s]            (θ k̂, ω k̂, from the IMU)
    line   l = [ρ_F, θ_F], Hesse normal form in the map frame: points q with
           q·[cos θ_F, sin θ_F] = ρ_F                  (F = ρ_F + θ_F k̂)

Motion (eq. 4.10, one step Δt; V and r are random walks driven by Q):

    p' = p + R(ψ) V Δt,   V' = V,   ψ' = ψ + r Δt,   r' = r
    (the thesis' V e^{−θ k̂} Δt is the rotation of V by the yaw)

Observation of line i from the laser at the robot (eq. 4.10, h):

    ρ_s = ρ_F − (p_x cos θ_F + p_y sin θ_F),   θ_s = θ_F − ψ

(the thesis writes θ_F + θ_k; with ψ positive from x towards y, a line at map
angle θ_F appears at θ_F − ψ in the sensor frame — see docs/papers.md).
Optical flow and gyro are linear measurements of the robot block,
z_odo = [V_x, V_y, r] + v (thesis Alg. 2 feeds them to the time update; the
state holds V and ω, so jaxslam fuses them as measurements, with
:func:`jaxslam.filters.ekf_slam.update_robot`).

Jacobians: all by ``jax.jacfwd`` inside the engine.  The thesis' A (eq. 4.11)
agrees with ∂f/∂s (∂p/∂V = R(ψ)Δt, ∂p/∂ψ = R'(ψ) V Δt, ∂ψ/∂r = Δt); its H
(eq. 4.13-4.14) agrees on ∂ρ_s/∂p = −[cos θ_F, sin θ_F], ∂ρ_s/∂ρ_F = 1,
∂θ_s/∂θ_F = 1, and differs by a factor ½ (complex-derivative artefact) and
the sign of ∂ρ_s/∂θ_F = p_x sin θ_F − p_y cos θ_F (tests/systems check the
consistent entries against the thesis).

Lines have a double cover ((ρ, θ) and (−ρ, θ + π) are the same line): the
predicted ρ_s may be negative (the robot beyond the line from the map origin,
or on the infinite extension of a wall), while a scan fit always returns ρ ≥ 0.
:func:`line_residual` compares the measurement in whichever of its two
representations is closer in angle and wraps Δθ, so the innovation is smooth
through the ρ = 0 flip; :func:`jaxslam.features.lines.hesse_normalize` gives
the ρ ≥ 0 form for matching.  Registration inverts h and normalises ρ_F ≥ 0.

Per scan (Algorithm 2): predict; flow/gyro update; project the scan to the
ground with the IMU roll and pitch; predicted lines searched first
(:func:`jaxslam.features.lines.extract_guided`), matched ones update the map
(joint update, χ² gate); RANSAC on the remaining points proposes new lines,
which are registered when their Mahalanobis distance to every mapped line
exceeds ``new_threshold`` (so a mapped line the prior-guided search missed is
not mapped twice).

The system follows the package convention (:mod:`jaxslam.systems`): :class:`Config` (static),
:class:`Params` (traced), :class:`Log` (one flight), :class:`Event` (one scan of it),
``State`` (the engine's :class:`jaxslam.filters.ekf_slam.SlamState`), :class:`StepOut`,
:class:`Result`; :func:`init`, :func:`step` and :func:`run`.  RANSAC draws random numbers, so
``step`` and ``run`` require ``key``; ``run`` splits it into one key per scan.  A whole log is
one jitted ``lax.scan``; vmap over runs.
"""

from __future__ import annotations

import functools
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..errors import InputError
from ..features import lines as fl
from ..filters import ekf_slam as es
from ..linalg import (check_int, check_key, check_numbers, check_scalar, float_array, host_array, is_concrete,
                      wrap_angle)
from ..sensors import laser2d

__all__ = [
    "NR",
    "POS",
    "VEL",
    "YAW",
    "RATE",
    "Config",
    "Params",
    "NOISE_FIELDS",
    "THRESHOLDS",
    "Log",
    "Event",
    "State",
    "EkfInputs",
    "StepOut",
    "Result",
    "motion",
    "observe",
    "inverse",
    "line_residual",
    "odometry_observe",
    "make_model",
    "default_params",
    "init",
    "step",
    "run",
    "validate_params",
    "validate_log",
]

NR = 6
POS = slice(0, 2)
VEL = slice(2, 4)
YAW = 4
RATE = 5


class Config(NamedTuple):
    """Static settings (hashable; a change recompiles).

    dt: scan period [s] (URG-04LX: 0.1); capacity: line slots; ransac: RANSAC
    settings (``max_lines`` = new lines sought per scan); spec: the laser; record_inputs:
    also return the EKF inputs of every step (for the NumPy twin and debugging).  The gates
    and thresholds are numbers: :class:`Params`.
    """

    dt: float = 0.1
    capacity: int = 16
    ransac: fl.RansacConfig = fl.RansacConfig(n_hyp=128, max_lines=3, threshold=0.05,
                                              min_inliers=20, point_sigma=0.02, max_gap=10,
                                              trim_ends=3)
    spec: laser2d.LaserSpec = laser2d.URG04LX
    record_inputs: bool = False


class Params(NamedTuple):
    """Tunable (traced) filter parameters.

    Q: (6, 6) discrete process noise per step; R_odo: (3, 3) optical flow
    (2 rows, [m/s]²) and gyro yaw rate ([rad/s]²); R_line: (2, 2) added to each
    line fit's own covariance ([m², rad²]: model error floor); P0: (6, 6)
    initial robot covariance (the noise: :data:`NOISE_FIELDS`).

    Thresholds (scalars; traced too, so a new value never recompiles): match_gate:
    distance [m] within which scan points support a predicted line; min_update_inliers: a
    matched line updates the filter only with at least this many points; nis_gate: χ²(2)
    threshold of each matched line's NIS (99.9 %: 13.82); new_threshold: a RANSAC line is
    new only if its squared Mahalanobis distance to every mapped line exceeds this;
    min_line_rho: new lines closer than this [m] to the sensor are not mapped (clutter lining
    up through the sensor); min_line_length [m] and max_scatter_ratio: a new line is mapped
    only if its inlier segment is at least this long and its residual variance is at most
    this multiple of the laser's predicted point variance (:func:`_fit_quality`).
    """

    Q: jax.Array
    R_odo: jax.Array
    R_line: jax.Array
    P0: jax.Array
    match_gate: jax.Array = 0.08
    nis_gate: jax.Array = 13.82
    new_threshold: jax.Array = 50.0
    min_line_rho: jax.Array = 0.25
    min_update_inliers: jax.Array = 20.0
    min_line_length: jax.Array = 0.3
    max_scatter_ratio: jax.Array = 2.0


#: The noise fields of :class:`Params` (the rest are the thresholds, :data:`THRESHOLDS`).
NOISE_FIELDS = ("Q", "R_odo", "R_line", "P0")
THRESHOLDS = ("match_gate", "nis_gate", "new_threshold", "min_line_rho", "min_update_inliers",
              "min_line_length", "max_scatter_ratio")


class Log(NamedTuple):
    """One flight's sensor log (T scans; ranges NaN where invalid; a batch adds a leading axis;
    a valid range outside [spec.range_min, spec.range_max] is masked with ``MASKED_INPUT``).

    ranges: (T, n_beams) [m]; valid: (T, n_beams) bool; tilt: (T, 2) IMU roll
    and pitch [rad] (for the ground projection); flow: (T, 2) body velocity
    [m/s]; gyro: (T,) yaw rate [rad/s]; s0: (6,) initial robot state (the map
    frame is the start pose's frame when s0 is the true start).
    """

    ranges: jax.Array
    valid: jax.Array
    tilt: jax.Array
    flow: jax.Array
    gyro: jax.Array
    s0: jax.Array


class Event(NamedTuple):
    """One scan of a :class:`Log` (the slice :func:`step` takes).

    ranges: (n_beams,) [m]; valid: (n_beams,) bool; tilt: (2,) roll, pitch [rad]; flow: (2,)
    body velocity [m/s]; gyro: () yaw rate [rad/s]; index: () int32 the scan's number k
    (0, 1, …; new lines get the ids k·M + j, M = ``config.ransac.max_lines``).
    """

    ranges: jax.Array
    valid: jax.Array
    tilt: jax.Array
    flow: jax.Array
    gyro: jax.Array
    index: jax.Array


#: The state between scans: the engine's posterior (robot block and line map).
State = es.SlamState


class EkfInputs(NamedTuple):
    """What the EKF consumed at one step (``record_inputs``): enough to replay it.

    z_match (cap, 2), R_match (cap, 2, 2), used (cap,) after the gate;
    z_new (M, 2), R_new (M, 2, 2), reg (M,) registered candidates (in order).
    """

    z_match: jax.Array
    R_match: jax.Array
    used: jax.Array
    z_new: jax.Array
    R_new: jax.Array
    reg: jax.Array


class StepOut(NamedTuple):
    """Per-step output: robot mean (6,) and cov (6, 6), map (cap, 2), its
    marginal covs (cap, 2, 2), active (cap,), NIS of the line update and its dof,
    counts (matched, gated, new registered), status word, and the EKF inputs
    (``None`` unless ``record_inputs``)."""

    mean: jax.Array
    cov: jax.Array
    lines: jax.Array
    lines_cov: jax.Array
    active: jax.Array
    nis: jax.Array
    dof: jax.Array
    n_matched: jax.Array
    n_gated: jax.Array
    n_new: jax.Array
    status: jax.Array
    inputs: Optional[EkfInputs] = None


class Result(NamedTuple):
    """What :func:`run` returns: steps, the :class:`StepOut` of every scan (leading axis T);
    final, the :data:`State` after the last scan."""

    steps: StepOut
    final: State


# ---------------------------------------------------------------------------
# Model (eq. 4.10)
# ---------------------------------------------------------------------------

def motion(s, u, dt):
    """Eq. 4.10 time update of the robot over ``dt`` (u unused)."""
    c, sn = jnp.cos(s[YAW]), jnp.sin(s[YAW])
    v = s[VEL]
    dp = jnp.stack([c * v[0] - sn * v[1], sn * v[0] + c * v[1]]) * dt
    return s.at[POS].add(dp).at[YAW].add(s[RATE] * dt)


def observe(s, l, params=None):
    """Eq. 4.10 h: the map line l = [ρ_F, θ_F] seen from the robot, [ρ_s, θ_s] (unnormalised)."""
    rho_f, th_f = l[0], l[1]
    rho = rho_f - (s[0] * jnp.cos(th_f) + s[1] * jnp.sin(th_f))
    return jnp.stack([rho, th_f - s[YAW]])


def inverse(s, z, params=None):
    """Registration: the map line [ρ_F, θ_F] of a sensor-frame line z = [ρ_s, θ_s] (ρ_F ≥ 0)."""
    th = z[1] + s[YAW]
    rho = z[0] + s[0] * jnp.cos(th) + s[1] * jnp.sin(th)
    flip = rho < 0
    return jnp.stack([jnp.where(flip, -rho, rho), wrap_angle(jnp.where(flip, th + jnp.pi, th))])


def line_residual(z, zh):
    """Innovation z − ẑ on the double cover: z as (ρ, θ) or (−ρ, θ + π), whichever is closer
    in angle; Δθ wrapped to [−π, π)."""
    d1 = jnp.stack([z[0] - zh[0], wrap_angle(z[1] - zh[1])])
    d2 = jnp.stack([-z[0] - zh[0], wrap_angle(z[1] + jnp.pi - zh[1])])
    return jnp.where(jnp.abs(d2[1]) < jnp.abs(d1[1]), d2, d1)


def odometry_observe(s, params=None):
    """Optical flow (body velocity) and gyro yaw rate: [V_x, V_y, r]."""
    return jnp.stack([s[2], s[3], s[RATE]])


def make_model() -> es.SlamModel:
    """The engine model: robot 6, line 2, measurement 2."""
    return es.SlamModel(robot_dim=NR, lm_dim=2, meas_dim=2, motion=motion, observe=observe,
                        inverse=inverse, residual=line_residual)


def default_params(dt: float = 0.1, sigma_flow: float = 0.05, sigma_gyro: float = 0.005,
                   sigma_acc: float = 0.2, sigma_yaw_acc: float = 0.1, sigma_pos: float = 0.005,
                   sigma_line_rho: float = 0.005, sigma_line_theta_deg: float = 0.15,
                   dtype=jnp.float64) -> Params:
    """Filter parameters matched to the ``lineslam-room`` simulation (stated there).

    Q per step from continuous white-noise accelerations: the yaw/yaw-rate block is the
    exact nearly-constant-velocity form σ_α²[[Δt³/3, Δt²/2], [Δt²/2, Δt]] (σ_α =
    ``sigma_yaw_acc``); the body velocity gets σ_a² Δt per axis and the position
    σ_a² Δt³/3 + σ_pos² per axis (``sigma_pos``: the Euler step's error on the curved
    path), without the position-velocity cross term (it would rotate with the yaw).
    """
    q = np.zeros((NR, NR))
    qa, qy = sigma_acc ** 2, sigma_yaw_acc ** 2
    q[0, 0] = q[1, 1] = qa * dt ** 3 / 3 + sigma_pos ** 2
    q[2, 2] = q[3, 3] = qa * dt
    q[YAW, YAW] = qy * dt ** 3 / 3
    q[YAW, RATE] = q[RATE, YAW] = qy * dt ** 2 / 2
    q[RATE, RATE] = qy * dt
    return Params(
        Q=jnp.asarray(q, dtype),
        R_odo=jnp.asarray(np.diag([sigma_flow ** 2, sigma_flow ** 2, sigma_gyro ** 2]), dtype),
        R_line=jnp.asarray(np.diag([sigma_line_rho ** 2, np.deg2rad(sigma_line_theta_deg) ** 2]), dtype),
        P0=jnp.asarray(np.diag([1e-8, 1e-8, sigma_flow ** 2, sigma_flow ** 2, 1e-8, sigma_gyro ** 2]),
                       dtype),
        # the default thresholds as arrays of dtype (a tree_map over the parameters reaches them)
        **{f: host_array(Params._field_defaults[f], dtype) for f in THRESHOLDS},
    )


# ---------------------------------------------------------------------------
# Filter
# ---------------------------------------------------------------------------

class FitQuality(NamedTuple):
    """Quality of fitted lines (L,): cov_scale, wall_like, length [m]."""

    cov_scale: jax.Array
    wall_like: jax.Array
    length: jax.Array


def _fit_quality(lines: fl.Lines, pts, sig_pt, point_sigma, max_ratio: float = 2.0):
    """Residual variance of each line's inliers against the laser's predicted point variance.

    σ̂² = Σ d²/(n − 2) over the inliers (d: point-line distances).  ``cov_scale`` =
    max(σ̂², σ̄²)/point_sigma² rescales the fit covariance (computed for ``point_sigma``)
    to the scatter actually seen, never below the predicted one σ̄² (mean of the
    inliers' range-dependent σ²); ``wall_like`` = σ̂² ≤ ``max_ratio``·σ̄².
    """
    w = lines.inliers.astype(pts.dtype)  # (L, N)
    n = jnp.sum(w, axis=1)
    d = jax.vmap(lambda r, t: fl.point_line_distance(pts, r, t))(lines.rho, lines.theta)  # (L, N)
    s2 = jnp.sum(w * d * d, axis=1) / jnp.maximum(n - 2.0, 1.0)
    pred = jnp.sum(w * sig_pt[None, :] ** 2, axis=1) / jnp.maximum(n, 1.0)
    scale = jnp.maximum(s2, pred) / point_sigma ** 2
    length = jnp.linalg.norm(lines.endpoints[:, 1] - lines.endpoints[:, 0], axis=-1)
    return FitQuality(cov_scale=jnp.where(lines.valid, scale, 1.0), wall_like=s2 <= max_ratio * pred,
                      length=length)


def init(log: Log, config: Config, params: Params, *, key=None) -> State:
    """The state before the first scan: empty map, robot at ``log.s0`` with covariance
    ``params.P0`` (in the dtype of ``log.s0``; no random draw, ``key`` unused)."""
    del key
    s0 = jnp.asarray(log.s0)
    return es.init(s0, params.P0.astype(s0.dtype), config.capacity, 2)


def step(state: State, event: Event, config: Config, params: Params, *, key) -> tuple[State, StepOut]:
    """One scan of Algorithm 2.  ``key`` (required) drives the scan's RANSAC sampling.
    Returns ``(state, StepOut)``.  Returns marked valid but finite and outside
    [``config.spec.range_min``, ``range_max``] are not used, and set ``MASKED_INPUT``."""
    if key is None:
        raise InputError("key: line SLAM samples RANSAC hypotheses; give a PRNG key")
    st = state
    model = make_model()
    dtype = st.x.dtype
    cap = config.capacity
    st = es.predict(st, model, None, params.Q.astype(dtype), config.dt)
    z_odo = jnp.concatenate([jnp.asarray(event.flow, dtype), jnp.asarray(event.gyro, dtype)[None]])
    st, _ = es.update_robot(st, model, odometry_observe, z_odo, jnp.ones((3,), bool),
                            params.R_odo.astype(dtype))

    ranges = jnp.asarray(event.ranges, dtype)
    # a non-finite tilt (traced: the host check cannot see it) makes every point of the scan
    # unusable: the scan is masked and flagged MASKED_INPUT, as a non-finite flow or gyro is
    tilt = jnp.asarray(event.tilt, dtype)
    tilt_ok = jnp.all(jnp.isfinite(tilt))
    # a finite range outside [spec.range_min, spec.range_max] marked valid (a negative range
    # mirrored its wall through the sensor, 1e6 m mapped a line far away) is masked and flagged
    # MASKED_INPUT; a non-finite range stays the log's "no return"
    in_range = (ranges >= config.spec.range_min) & (ranges <= config.spec.range_max)
    bad_range = jnp.any(event.valid & jnp.isfinite(ranges) & ~in_range)
    st = st._replace(status=st.status | jnp.where(tilt_ok & ~bad_range, 0,
                                                  errors.MASKED_INPUT).astype(st.status.dtype))
    pvalid = event.valid & jnp.isfinite(ranges) & in_range & tilt_ok
    pts, pvalid = laser2d.scan_points(ranges, pvalid, config.spec, jnp.where(tilt_ok, tilt, 0.0))

    s = st.x[:NR]
    L = es.landmarks(st, model)
    zh = jax.vmap(lambda l: observe(s, l))(L)
    pr, pt = fl.hesse_normalize(zh[:, 0], zh[:, 1])
    thr = {f: host_array(getattr(params, f), dtype) for f in THRESHOLDS}
    matched, new, _ = fl.extract_guided(key, pts, pvalid, pr, pt, st.active, config.ransac, thr["match_gate"])

    R_line = params.R_line.astype(dtype)
    sig_pt = jnp.where(pvalid, laser2d.range_sigma(jnp.where(pvalid, ranges, 1.0), config.spec), 0.0)
    q_m = _fit_quality(matched, pts, sig_pt, config.ransac.point_sigma)
    z_m = jnp.stack([matched.rho, matched.theta], axis=-1)
    R_m = matched.cov * q_m.cov_scale[:, None, None] + R_line
    m_mask = matched.valid & st.active & (matched.n_inliers >= thr["min_update_inliers"])
    st, info = es.update(st, model, z_m, jnp.arange(cap), m_mask, R_m, gate=thr["nis_gate"])

    q_n = _fit_quality(new, pts, sig_pt, config.ransac.point_sigma, thr["max_scatter_ratio"])
    z_n = jnp.stack([new.rho, new.theta], axis=-1)
    R_n = new.cov * q_n.cov_scale[:, None, None] + R_line
    _, _, is_new, _ = es.associate_nn(st, model, z_n, new.valid, R_n, gate=thr["nis_gate"],
                                      new_threshold=thr["new_threshold"])
    # Clutter in front of the sensor can line up into a "line" through it (ρ ≈ 0): no wall is
    # that close to a flying vehicle, so such candidates are not mapped.  A new line must also
    # look like one wall: inlier scatter about the fit no larger than the
    # laser noise predicts (a line across a corner or through clutter scatters up to the
    # RANSAC threshold) and a segment of at least ``min_line_length``.  (With
    # ``ransac.max_gap`` every line is one run of beams: RANSAC cannot string a pillar face and
    # a nearly collinear wall behind it, or clutter on a line's extension, into one line.)
    reg = (new.valid & is_new & (new.rho >= thr["min_line_rho"]) & q_n.wall_like
           & (q_n.length >= thr["min_line_length"]))
    M = z_n.shape[0]
    ids = jnp.asarray(event.index, jnp.int32) * M + jnp.arange(M, dtype=jnp.int32)
    n_act0 = jnp.sum(st.active)
    st = es.register(st, model, z_n, ids, reg, R_n)
    n_new = jnp.sum(st.active) - n_act0

    inputs = (EkfInputs(z_match=z_m, R_match=R_m, used=info.used, z_new=z_n, R_new=R_n, reg=reg)
              if config.record_inputs else None)
    out = StepOut(
        mean=st.x[:NR],
        cov=st.P[:NR, :NR],
        lines=es.landmarks(st, model),
        lines_cov=es.landmark_covs(st, model),
        active=st.active,
        nis=info.nis,
        dof=info.dof,
        n_matched=jnp.sum(info.used).astype(jnp.int32),
        n_gated=jnp.sum(info.gated).astype(jnp.int32),
        n_new=n_new.astype(jnp.int32),
        status=st.status,
        inputs=inputs,
    )
    return st, out


def _check_log(log: Log, spec: laser2d.LaserSpec) -> int:
    """Shapes and dtypes of ``log`` (static, also under tracing); returns T."""
    n = spec.n_beams
    shp = np.shape(log.ranges)
    if len(shp) != 2 or shp[0] < 1 or shp[1] != n:
        raise InputError(f"log.ranges: expected shape (T, {n}) (T >= 1 scans of {n} beams for this "
                         f"laser), got {shp}")
    T = shp[0]
    for name, want in (("valid", (T, n)), ("tilt", (T, 2)), ("flow", (T, 2)), ("gyro", (T,)), ("s0", (NR,))):
        got = np.shape(getattr(log, name))
        if got != want:
            raise InputError(f"log.{name}: expected shape {want}, got {got}")
    vdt = getattr(log.valid, "dtype", None)
    vdt = np.asarray(log.valid).dtype if vdt is None else vdt
    if vdt != bool:
        raise InputError(f"log.valid: expected a bool mask, got dtype {vdt}")
    for name in ("ranges", "tilt", "flow", "gyro", "s0"):  # a string array failed deep in JAX
        x = getattr(log, name)
        if is_concrete(x) and not (isinstance(x, (jax.Array, np.ndarray)) and x.dtype.kind in "biuf"):
            check_numbers(x, f"log.{name}")
    return T


def _check_values(log: Log) -> None:
    """Values of a concrete ``log``: a finite start state and finite IMU tilt (a NaN tilt makes
    its scan unusable; traced, that scan is masked and flagged ``MASKED_INPUT``).  NaN ranges
    are the log's "no return" and a non-finite flow/gyro is masked with ``MASKED_INPUT``."""
    if is_concrete(log.s0) and not np.all(np.isfinite(np.asarray(log.s0, float))):
        raise InputError("log.s0: contains non-finite values")
    if is_concrete(log.tilt) and not np.all(np.isfinite(np.asarray(log.tilt, float))):
        raise InputError("log.tilt: contains NaN or Inf")


def _check_config(config: Config) -> None:
    check_scalar(config.dt, "config.dt", lower=0, strict=True)  # a negative dt ran backwards
    check_int(config.capacity, "config.capacity")


def run(log: Log, config: Config = Config(), params: Optional[Params] = None, *, key) -> Result:
    """Algorithm 2 over a whole log: one jitted ``lax.scan`` of :func:`step` (``config`` static).

    ``key`` (required; a PRNG key, else :class:`InputError` naming ``key``) drives the RANSAC
    sampling: it is split into one key per scan (deterministic given the key).  ``params`` None: :func:`default_params` for ``config.dt``
    in the dtype of ``log.s0``.  Shapes are checked here, also under tracing; values
    (finite ``log.s0``, PSD covariances) when they are concrete, else check a log from outside
    with :func:`validate_log` first.  A range marked valid outside the laser's
    [``range_min``, ``range_max``] is masked and flags its scan ``MASKED_INPUT`` (:func:`step`).
    Composes under ``jit`` / ``vmap``.
    """
    if key is None:
        raise InputError("key: line SLAM samples RANSAC hypotheses; give a PRNG key")
    check_key(key)  # an int seed, a batch of keys or a string failed deep in JAX
    _check_config(config)
    _check_log(log, config.spec)
    # an integer s0 made the run's dtype (and the default covariances) integer
    log = log._replace(s0=float_array(log.s0, "log.s0"))
    if params is None:
        params = default_params(config.dt, dtype=jnp.asarray(log.s0).dtype)
    _check_values(log)
    if is_concrete(params):
        validate_params(params)
    dtype = jnp.asarray(log.s0).dtype  # thresholds as arrays: a Python number and an array share one program
    params = params._replace(**{f: host_array(getattr(params, f), dtype) for f in THRESHOLDS})
    return _run(log, config, params, key)


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params, key) -> Result:
    st = init(log, config, params)
    T = log.ranges.shape[0]
    keys = jax.random.split(key, T)
    events = Event(ranges=log.ranges, valid=log.valid, tilt=log.tilt, flow=log.flow, gyro=log.gyro,
                   index=jnp.arange(T, dtype=jnp.int32))

    def body(st, ev_k):
        ev, k = ev_k
        return step(st, ev, config, params, key=k)

    final, steps = jax.lax.scan(body, st, (events, keys))
    return Result(steps=steps, final=final)


# ---------------------------------------------------------------------------
# Host-side validation
# ---------------------------------------------------------------------------

def validate_params(params: Params) -> Params:
    """Shapes, finiteness and positive (semi-)definiteness of every covariance; the thresholds
    finite, non-negative scalars."""
    from ..linalg import check_psd

    shapes = {"Q": (NR, NR), "R_odo": (3, 3), "R_line": (2, 2), "P0": (NR, NR)}
    for name, shp in shapes.items():
        a = check_numbers(getattr(params, name), f"params.{name}")
        if a.shape != shp:
            raise InputError(f"params.{name}: expected shape {shp}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"params.{name}: contains non-finite values")
        check_psd(a, f"params.{name}", strict=name in ("R_odo",))
    for name in THRESHOLDS:
        check_scalar(getattr(params, name), f"params.{name}", lower=0)
    return params


def validate_log(log: Log, spec: laser2d.LaserSpec = laser2d.URG04LX) -> Log:
    """Host-side checks of a concrete log: shapes (a scan of the wrong length raises InputError
    naming the beam count), numbers, the bool ``valid`` mask, a finite ``s0`` and ``tilt``."""
    _check_log(log, spec)
    _check_values(log)
    return log
