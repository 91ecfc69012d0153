"""Paper 001's modified two-stage FastSLAM with joint IMU bias/drift estimation.

A *system* module: it fixes paper 001's state order, models, noise and stage logic and plugs
them into the generic particle core (:mod:`jaxslam.filters.fastslam`, resampling in
:mod:`jaxslam.filters.resampling`) and the generic EKF (:mod:`jaxslam.filters.ekf`, used for
the per-particle bias/drift Kalman filter).  Nothing here is a filter of its own.

State and frames (paper 001 eq. 1-4, z-up world frame W, body frame z-up; see
:mod:`jaxslam.dynamics.rotor`): every particle carries

    x^D = [x, y, z, ẋ, ẏ, ż, φ, θ, ψ, p, q, r]   (12,)   position/velocity in W (m, m/s),
          3-2-1 Euler angles of R_b^w (rad), body rates (rad/s)

plus the mean of its bias/drift KF x^B = [b0a, b0ω, b1a, b1ω] (12,) (eq. 11, order of the
paper) and a padded map of landmark EKFs (Table 3).

One IMU sample (100 Hz, :func:`imu_stage`), the dynamics-based filter (Table 2):

1. Step 1: x^D_k ~ N(RK4(f, x^D_{k−1}, ω_rotor,k−1), Q) with f of eq. 1-4 driven by the four
   rotor speeds (mixer and gyroscopic Ω_r of :mod:`jaxslam.dynamics.rotor`) and the filter's
   own physical parameters (``Params.quad``; the inertia-mismatch test changes them).
2. Step 2: bias KF prediction x̂^B = A^b x̂^B, P = A^b P A^bᵀ + Q^b (eq. 11, Table 4) through
   :func:`jaxslam.filters.ekf.predict`.
3. Step 3: IMU weight p(z^I | x^D, x̂^B_{k|k−1}) (eq. 26, 28): ``weights="exact"`` integrates
   the bias posterior out, N(z̄; H_b x̂, H_b P H_bᵀ + R^I); ``weights="paper"`` uses the mean
   (eq. 26's delta approximation), N(z̄; H_b x̂, R^I).  z̄ = z^I − h^d(x^D) (eq. 12, Table 4).
4. Step 4: bias KF update with z̄ (:func:`jaxslam.filters.ekf.linear_update_shared`); on the
   first sample the mean is re-initialised by the least-squares minimum-norm solution H_b⁺ z̄
   (Table 4 per the errata: H_bᵀH_b is singular, so the pseudo-inverse replaces
   (H_bᵀH_b)⁻¹H_bᵀ).
5. Step 6: resample (ESS threshold or every step) — poses, bias means and maps together.
6. Step 8 (stage 2, rates): ω^i ~ p(ω | ω_m, x̂^B_{k|k}) = N(ω_m − H_ω x̂^B, R_ω [+ H_ω P H_ωᵀ])
   — the gyroscope's inverse sensor model (eq. 9, 32-34).

One LiDAR frame (:func:`lidar_stage`, at the IMU sample it belongs to):

5. Step 3/5: landmark EKF updates / registrations and the LiDAR weight (eq. 27-28, Table 3)
   in the core (:func:`jaxslam.filters.fastslam.observe_update`, known data association,
   id j in slot j), then Step 6 (resample).
6. Step 8 (stage 2, position): x^{D1,i} ~ p(x^{D1} | z^S, μ^i) — the LiDAR's inverse model
   (eq. 15) solved for the sensor position: each observed landmark gives p_j = μ_j − ϱ(z_j)
   (world model) or μ_j − R_b^w ϱ(z_j) (body model), with covariance J R^S Jᵀ [+ Σ_j]
   (J = ∂p_j/∂z_j by ``jax.jacfwd``); the landmarks of a frame are fused by information
   (the product of their Gaussians) and one sample is drawn per particle.

The kinematics-based baseline (``model="kinematics"``): plain FastSLAM 1.0 with the IMU as
input (no calibration): x^D_k = RK4 of ṗ = v, v̇ = R a_m − g e3 (specific force; or R a_m in
the paper's kinematic accelerometer form), Λ̇ = D(Λ) ω_m with the IMU interpolated linearly
between samples, plus Q; ω in the state is the last gyro reading; weights from the LiDAR only.

Decisions (the paper is silent or wrong; also in docs/papers.md, paper 001):

* **Bias KF covariance is shared.**  A^b, Q^b, H_b and R^I do not depend on the particle, and
  the re-initialisation happens at the same sample for every particle, so P_{k|k} is the same
  for all particles (a Riccati recursion that ignores the data).  It is stored once
  (``State.bias_cov`` (12, 12)) and only the means are per particle (``aux`` (N, 12)); the
  gain is the same for all of them, so one factorisation updates the whole set
  (:func:`jaxslam.filters.ekf.linear_update_shared`).  Exactly equal to N separate KFs.
* **Random numbers**: each noise of a step (proposal, rates, position) is one draw for the
  whole set ((N, 12), (N, 3), (N, 3)), not one key per particle (on a CPU the key split cost
  as much as the draw).
* **Re-initialisation covariance** (Table 4 gives only the mean): the KF posterior covariance
  of the first update from ``Params.bias_p0``.  The first IMU sample carries no weight
  (the bias prior is uninformative there; the paper re-initialises at k = 1).
* **Weights ``"paper"``** = the paper's delta approximations everywhere: eq. 26 (bias mean),
  eq. 27 (landmark mean, the core's ``weights="mean"``) and eq. 34 (stage 2 samples ignore
  P^B and Σ_j).  ``"exact"`` (default) integrates both Gaussians out.
* **Table 2 uses x̂^B_{k|k−1}** in the weight (step 3) while eq. 28 prints x̂^B_{k|k}; the
  predictive (k|k−1) is the correct marginal likelihood and is used.
* **Resampling**: the paper resamples at every step (Step 6, ``threshold=None``); the default
  here is N_eff < 0.5 N (fewer resampling events, less impoverishment); both are options, as
  is soft resampling (``resampling="soft"``, differentiable weights).  Stage 2 does not change
  the weights (the paper's 1/N after its every-step resampling).
* **IMU and LiDAR at the same instant** are processed sequentially (IMU stage, then LiDAR
  stage, each with its own weight and resampling decision): Bayes-equivalent to the paper's
  joint weight (eq. 28) and lets IMU-only samples skip the LiDAR work.
* **Accelerometer**: specific force (default, errata) h^d_a = R_b^wᵀ(a_w + g e3) = (u1/m) e3
  for the drag-free model (attitude-independent); ``accel_mode="kinematic"`` is the paper's
  eq. 7, R_b^wᵀ a_w (which makes the accelerometer an inclinometer).
* **Gyroscope row of h^d** (eq. 12 prints "R_b^ω ω_b"): the gyro measures ω_b (eq. 9); h^d_ω = ω_b.
* **Drift discretisation**: eq. 11's Euler form (A = 1 − T/τ, Q = T² σ²), from
  :func:`jaxslam.sensors.imu.drift_transition` (``default_params(drift_method="exact")``
  available).
* **Proposal noise Q** (paper: "generally non-Gaussian ... known pdf", no values): Gaussian,
  diagonal, per step; defaults in :data:`DEFAULT_DYN_SIGMA` (model-error allowance) and, for
  the kinematics baseline, that allowance plus the IMU white noise integrated over the step.
* **Position regeneration** fuses all landmarks of the frame (the paper assumes one per
  step and says the extension is direct); particles in which no observed landmark is mapped
  keep their stage-1 position.  Velocity is not regenerated (the paper regenerates only
  x^{D1} and x^{D4}).

What stage 2 does to the estimator (measured in docs/results/paper001, derived in
docs/papers.md, paper 001): regenerating ω from the gyro makes the KF's gyro innovation
independent of the gyro-bias error (the bias stays at its re-initialisation value unless
particle selection corrects it) and re-injects gyro noise that the next IMU weight chases
(N_eff collapses, resampling at ~every sample); regenerating the position from the LiDAR
discards the evidence through which velocity and tilt errors become visible to the
attitude-free world-frame LiDAR.  In exchange, the filter is insensitive to an inertia
mismatch.  ``stage2="none"`` keeps the rotor-driven rates (gyro bias observable, but the
mismatch then corrupts ω and the bias).

Bad samples: a non-finite IMU sample is skipped (the dynamics model predicts through it; the
kinematics model keeps its previous sample) and non-finite LiDAR rows are skipped by the update
and by the position regeneration; both set ``MASKED_INPUT`` in the particles' status
(``tests/faults/test_faults_flight_systems.py``).  Before, either turned the estimate into NaN.

Which entry point: :func:`run` (one ``lax.scan`` over the whole flight; nested scan: LiDAR
frames outside, IMU samples inside) for recorded data and Monte Carlo (``vmap`` over keys);
:func:`step` (one IMU sample plus an optional LiDAR frame) for users driving their own loop.
Both are pure and jit/vmap-safe; ``config`` is static, ``params`` traced (so ``grad`` w.r.t.
the noise variances works; :func:`with_log_noise` maps log-variances onto them).
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..dynamics import rotor
from ..dynamics.integrators import rk4_step
from ..dynamics.params import PAPER001, RotorQuadParams, validate_params
from ..errors import InputError
from ..filters import ekf
from ..filters import fastslam as fs
from ..geometry.euler import dcm_from_euler, euler_rates
from ..linalg import (check_int, check_mask, check_numbers, check_scalar, check_whole_ids, cholesky_small,
                      host_array, inv_small, is_concrete, reworded, symmetrize)
from ..sensors import imu as imu_mod
from ..sensors import lidar3d

__all__ = [
    "NX",
    "NB",
    "POS",
    "VEL",
    "ATT",
    "RATE",
    "ANGLE_MASK",
    "H_B",
    "DEFAULT_DYN_SIGMA",
    "DEFAULT_POSE0_SIGMA",
    "Config",
    "Params",
    "Log",
    "Event",
    "State",
    "StepOut",
    "FrameOut",
    "Result",
    "default_params",
    "validate_config",
    "validate_params_001",
    "with_log_noise",
    "bias_model",
    "h_imu",
    "imu_ideal_zup",
    "landmark_model",
    "dynamics_mean",
    "dynamics_sample",
    "kinematics_mean",
    "kinematics_sample",
    "regenerate_rates",
    "position_posterior",
    "regenerate_position",
    "init",
    "imu_stage",
    "lidar_stage",
    "step",
    "run",
    "estimate",
    "bias_estimate",
]

Array = Any

NX = 12
"""Particle pose dimension (paper 001 eq. 4)."""
NB = 12
"""Bias/drift state dimension x^B = [b0a, b0ω, b1a, b1ω] (eq. 11)."""
POS, VEL, ATT, RATE = rotor.POS, rotor.VEL, rotor.ATT, rotor.RATE
ANGLE_MASK = (False,) * 6 + (True,) * 3 + (False,) * 3
"""Pose components that are angles (Euler φ, θ, ψ)."""

H_B = np.block([[np.eye(3), np.zeros((3, 3)), np.eye(3), np.zeros((3, 3))],
                [np.zeros((3, 3)), np.eye(3), np.zeros((3, 3)), np.eye(3)]])
"""(6, 12) H_b of eq. 12 (NumPy constant; offset = b0 + b1 per sensor axis)."""
_H_B_PINV = np.linalg.pinv(H_B)  # (12, 6) = ½[I; I] blocks: minimum-norm LS (errata)

DEFAULT_DYN_SIGMA = (1e-4,) * 3 + (3e-4,) * 3 + (1e-5,) * 3 + (1e-5,) * 3
"""Per-step std of the dynamics proposal noise: position m, velocity m/s, attitude rad,
rates rad/s (jaxslam's choice: an allowance for unmodelled forces and torques)."""

DEFAULT_POSE0_SIGMA = (0.01,) * 3 + (0.01,) * 3 + (0.002,) * 3 + (1e-4,) * 3
"""Std of the initial particle cloud around the given start state (jaxslam's choice)."""

_MODELS = ("dynamics", "kinematics")
_LIDARS = ("world", "body")
_WEIGHTS = ("exact", "paper")
_STAGE2 = ("paper", "rates", "none")
_ACCEL = ("specific_force", "kinematic")


class Config(NamedTuple):
    """Static choices of the filter (hashable; a change recompiles).

    model: "dynamics" (paper 001, rotor-input proposal + bias KF) | "kinematics" (baseline,
        IMU-driven FastSLAM 1.0 without calibration).
    n_particles: N (paper: 500).
    lidar: "world" (eq. 13-15, default) | "body" (paper 000's body-frame bearing model).
    weights: "exact" (default) | "paper" (eq. 26-28 mean approximations).
    stage2: "paper" (Step 8: regenerate position and rates, default) | "rates" (rates only) |
        "none" (stage 1 only).  Ignored by the kinematics baseline.
    accel_mode: "specific_force" (default) | "kinematic" (paper eq. 7).
    resampling: scheme name of :data:`jaxslam.filters.resampling.SCHEMES` or "soft".
    (The resampling threshold and the soft-resampling mixture weight are numbers: :class:`Params`.)
    capacity: landmark slots per particle (ids 0..capacity−1, id j in slot j).
    lidar_every: IMU samples per LiDAR frame (static; 10 = 10 Hz at T = 0.01 s).
    dt: IMU / control step T [s] (paper: 0.01 s).
    save_particles: keep the particle positions (N, 3) and weights at every frame (plots).
    regen_noise: stage 2 draws the rates from the gyro's inverse model (True, the paper) or
        sets them to its mean ω_m − b̂ω (False).
    """

    model: str = "dynamics"
    n_particles: int = 500
    lidar: str = "world"
    weights: str = "exact"
    stage2: str = "paper"
    accel_mode: str = "specific_force"
    resampling: str = "systematic"
    capacity: int = 4
    lidar_every: int = 10
    dt: float = 0.01
    save_particles: bool = False
    regen_noise: bool = True


class Params(NamedTuple):
    """Traced numbers of the filter (differentiate w.r.t. any leaf).

    quad: :class:`~jaxslam.dynamics.params.RotorQuadParams` of the filter's model (mass kg,
        inertia (3,) kg m², g m/s², rotor constants).
    proposal_var: (12,) per-step variance of the proposal noise Q (units² of the pose).
    imu_var: (6,) R^I diagonal [accel (m/s²)², gyro (rad/s)²] (eq. 12).
    lidar_var: (3,) R^S diagonal [σ_α², σ_β² (rad²), σ_r² (m²)] (eq. 14, jaxslam order).
    drift_a: (6,) drift transition 1 − T/τ (eq. 11) [accel, gyro axes].
    drift_q: (6,) drift process-noise variance per step T² σ_b1² (eq. 11).
    bias_p0: (12,) initial bias/drift KF variances (Table 4 P_{0|0}, diagonal).
    pose0_var: (12,) variance of the initial particle cloud.
    resample_threshold: () resample when N_eff < threshold·N; None resamples at every weight
        update (the paper's Step 6; also the right choice for soft resampling, whose loss is
        then smooth in the parameters; None ↔ a number is a switch and retraces once).
    soft_alpha: () mixture weight α of soft resampling (used when ``config.resampling == "soft"``).
    """

    quad: Any
    proposal_var: Array
    imu_var: Array
    lidar_var: Array
    drift_a: Array
    drift_q: Array
    bias_p0: Array
    pose0_var: Array
    resample_threshold: Optional[Array] = 0.5
    soft_alpha: Array = 0.5


class State(NamedTuple):
    """Filter state (pytree).

    particles: :class:`jaxslam.filters.fastslam.Particles`; ``pose`` (N, 12), ``aux`` the
        bias/drift KF means (N, 12) (zeros for the kinematics baseline).
    bias_cov: (12, 12) bias/drift KF covariance, shared by all particles (module docstring).
    k: () int32 number of IMU samples processed.
    neff_min: () smallest N_eff seen after a weight update.
    imu_prev: (6,) previous IMU sample (first-order hold of the kinematics baseline).
    """

    particles: Any
    bias_cov: Array
    k: Array
    neff_min: Array
    imu_prev: Array


class Log(NamedTuple):
    """Everything :func:`run` needs: one flight (T IMU samples, F = T / lidar_every frames).

    x0: (12,) start state the particle cloud is centred on (its float dtype sets the run's).
    rotor_w: (T, 4) rotor speeds [rad/s] over each step (the dynamics model's input).
    imu: (T, 6) IMU samples (sample k at the end of step k) [accel m/s², gyro rad/s].
    z: (F, L, 3) LiDAR frames [α, β, r]; frame f is taken with IMU sample
        (f + 1)·lidar_every − 1.
    ids: (L,) int32 landmark ids (known association, id j in slot j).
    mask: (F, L) bool.
    """

    x0: Array
    rotor_w: Array
    imu: Array
    z: Array
    ids: Array
    mask: Array


class Event(NamedTuple):
    """Inputs of one :func:`step` (one IMU sample and the LiDAR frame taken with it, if any).

    rotor: (4,) rotor speeds ω_1..ω_4 applied over the step [rad/s] (dynamics model input).
    imu: (6,) IMU sample at the end of the step [accel m/s², gyro rad/s] (body frame, z up).
    z: (L, 3) LiDAR measurements [α, β, r] (rad, rad, m); ids: (L,) int32 landmark ids;
    mask: (L,) bool, all False when the step has no LiDAR frame.
    """

    rotor: Array
    imu: Array
    z: Array
    ids: Array
    mask: Array


class StepOut(NamedTuple):
    """Saved after every IMU sample: weighted pose mean (12,) and variance (12,), bias/drift
    mean (12,) and variance (12,) (shared KF covariance + spread of the particle means), the
    variance (6,) of the total offset b0 + b1 per sensor axis (H_b P H_bᵀ + spread; b0 and b1
    are strongly anti-correlated, so it is far below the sum of their variances), N_eff after
    the IMU weight ()."""

    pose_mean: Array
    pose_var: Array
    bias_mean: Array
    bias_var: Array
    offset_var: Array
    neff: Array


class FrameOut(NamedTuple):
    """Saved after every LiDAR frame: N_eff after the LiDAR weight (), weighted map mean
    (cap, 3) and variance (cap, 3), particle positions (N, 3) or None, the particle weights
    (N,) or None (``save_particles``)."""

    neff: Array
    map_mean: Array
    map_var: Array
    particles: Any
    log_w: Any


class Result(NamedTuple):
    """Output of :func:`run`: final :class:`State`, ``steps`` (:class:`StepOut` with a
    leading T axis), ``frames`` (:class:`FrameOut` with a leading F axis)."""

    final: Any
    steps: Any
    frames: Any


# ---------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------

def bias_model(params: Params, dtype):
    """(A^b (12,), Q^b (12,)) diagonals of eq. 11: A = blkdiag(I, I, a_a I, a_ω I),
    Q = blkdiag(0, 0, q_a I, q_ω I) in the order [b0a, b0ω, b1a, b1ω]."""
    one = jnp.ones((6,), dtype)
    a = jnp.concatenate([one, jnp.asarray(params.drift_a, dtype)])
    q = jnp.concatenate([jnp.zeros((6,), dtype), jnp.asarray(params.drift_q, dtype)])
    return a, q


def _imu_noise_sigma(spec, dtype):
    sa, sg = imu_mod.white_noise_sigma(spec)
    return jnp.concatenate([sa, sg]).astype(dtype)


def default_params(model: str = "dynamics", imu_spec=None, lidar_spec=None,
                   quad: RotorQuadParams = PAPER001, dt: float = 0.01, dtype=None,
                   drift_method: str = "euler", bias_prior_sigma: float = 0.01,
                   dyn_sigma=DEFAULT_DYN_SIGMA, pose0_sigma=DEFAULT_POSE0_SIGMA) -> Params:
    """Filter parameters of paper 001's system (jaxslam's choices where the paper is silent).

    Args:
      model: "dynamics" or "kinematics" (sets the proposal noise, see module docstring).
      imu_spec: :class:`~jaxslam.sensors.imu.ImuSpec` of the IMU (default
        ``PAPER001_IMU(0.0005)``); its white-noise σ give R^I, its drift model A^b, Q^b.
      lidar_spec: :class:`~jaxslam.sensors.range_bearing3d.RangeBearingSpec` (default
        paper 000's σ = 0.33°, 0.3°, 0.1 m).
      quad: the filter's physical parameters (``PAPER001_MISMATCH`` for the robustness test).
      dt: IMU step [s].  dtype: float dtype (default JAX's default float).
      drift_method: "euler" (eq. 11) or "exact".
      bias_prior_sigma: std of the bias and drift prior P_{0|0} [m/s², rad/s] (all 12).
      dyn_sigma: (12,) per-step model-error std of the proposal (module docstring).
      pose0_sigma: (12,) std of the initial particle cloud.

    Returns:
      :class:`Params`.
    """
    from ..sensors import range_bearing3d as rb

    if model not in _MODELS:
        raise InputError(f"model: expected one of {_MODELS}, got {model!r}")
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    imu_spec = imu_mod.PAPER001_IMU(0.0005) if imu_spec is None else imu_spec
    lidar_spec = rb.PAPER001_RANGE_BEARING if lidar_spec is None else lidar_spec
    sig = _imu_noise_sigma(imu_spec, dtype)
    a, q = imu_mod.drift_transition(imu_spec, jnp.asarray(dt, dtype), method=drift_method,
                                    dtype=dtype)
    var = jnp.asarray(dyn_sigma, dtype) ** 2
    if model == "kinematics":
        # The IMU drives the kinematic model: its white noise integrated over one step enters
        # the velocity (accelerometer) and the attitude (gyro); the rate state is the gyro.
        # The uncompensated offset gets the same allowance per step as white noise of the
        # bias prior's size (the usual inflation of Q for an uncalibrated IMU).
        sa, sg = sig[0:3], sig[3:6]
        h = jnp.asarray(dt, dtype)
        sb = jnp.asarray(bias_prior_sigma, dtype)
        var = var + jnp.concatenate([(0.5 * sa * h * h) ** 2, (sa * h) ** 2 + (sb * h) ** 2,
                                     (sg * h) ** 2 + (sb * h) ** 2, sg ** 2 + sb ** 2])
    lv = jnp.diag(rb.measurement_cov(lidar_spec, dtype))
    return Params(
        quad=type(quad)(*(jnp.asarray(v, dtype) for v in quad)),
        proposal_var=var,
        imu_var=sig * sig,
        lidar_var=lv,
        drift_a=a,
        drift_q=q,
        bias_p0=jnp.full((NB,), float(bias_prior_sigma) ** 2, dtype),
        pose0_var=jnp.asarray(pose0_sigma, dtype) ** 2,
        # the default resampling numbers as arrays of dtype (a tree_map over the parameters reaches them)
        resample_threshold=host_array(Params._field_defaults["resample_threshold"], dtype),
        soft_alpha=host_array(Params._field_defaults["soft_alpha"], dtype),
    )


def with_log_noise(params: Params, log_q=None, log_r=None) -> Params:
    """Replace Q (``proposal_var``) by exp(log_q) (12,) and R^S (``lidar_var``) by exp(log_r)
    (3,) — the unconstrained parametrisation for ``grad`` / tuning."""
    if log_q is not None:
        params = params._replace(proposal_var=jnp.exp(log_q))
    if log_r is not None:
        params = params._replace(lidar_var=jnp.exp(log_r))
    return params


def validate_config(cfg: Config) -> Config:
    """Host-side check of a :class:`Config`; raises InputError naming the field."""
    if not isinstance(cfg, Config):
        raise InputError(f"config: expected Config, got {type(cfg).__name__}")
    for name, allowed in (("model", _MODELS), ("lidar", _LIDARS), ("weights", _WEIGHTS),
                          ("stage2", _STAGE2), ("accel_mode", _ACCEL)):
        if getattr(cfg, name) not in allowed:
            raise InputError(f"config.{name}: expected one of {allowed}, got {getattr(cfg, name)!r}")
    from ..filters import resampling as rs

    if cfg.resampling != "soft" and cfg.resampling not in rs.SCHEMES:
        raise InputError(f"config.resampling: expected 'soft' or one of {sorted(rs.SCHEMES)}, "
                         f"got {cfg.resampling!r}")
    n = cfg.n_particles
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise InputError(f"config.n_particles: expected a positive integer, got {n!r}")
    if int(n) <= 0:
        raise InputError(f"config.n_particles: must be >= 1, got {n}")
    # a float 4.5 was truncated, a string "4" accepted
    check_int(cfg.capacity, "config.capacity")
    check_int(cfg.lidar_every, "config.lidar_every")
    for name in ("save_particles", "regen_noise"):  # a string "no" read as True
        errors.check_flag(getattr(cfg, name), f"config.{name}")
    # a string dt failed with NumPy's bare "could not convert"
    reworded(lambda: check_scalar(cfg.dt, "config.dt", lower=0, strict=True),
             f"config.dt: must be a positive number of seconds, got {cfg.dt!r}")
    return cfg


def validate_params_001(params: Params) -> Params:
    """Host-side check of :class:`Params` (shapes, finite, variances ≥ 0, R > 0)."""
    if not isinstance(params, Params):
        raise InputError(f"params: expected Params, got {type(params).__name__}")
    try:
        validate_params(params.quad)
    except InputError as e:
        raise InputError(f"params.quad: {e}") from None
    for name, n, strict in (("proposal_var", 12, False), ("imu_var", 6, True),
                            ("lidar_var", 3, True), ("drift_a", 6, False),
                            ("drift_q", 6, False), ("bias_p0", 12, True),
                            ("pose0_var", 12, False)):
        v = check_numbers(getattr(params, name), f"params.{name}")
        if v.shape != (n,):
            raise InputError(f"params.{name}: expected shape ({n},), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise InputError(f"params.{name}: contains NaN or Inf")
        if np.any(v < 0) or (strict and np.any(v <= 0)):
            raise InputError(f"params.{name}: must be {'> 0' if strict else '>= 0'}, got {v.tolist()}")
    if params.resample_threshold is not None:  # a string failed with NumPy's bare "could not convert"
        reworded(lambda: check_scalar(params.resample_threshold, "params.resample_threshold", lower=0, strict=True),
                 f"params.resample_threshold: expected None or a fraction in (0, 1], got "
                 f"{params.resample_threshold!r}", upper=1.0)
    reworded(lambda: check_scalar(params.soft_alpha, "params.soft_alpha", lower=0),
             f"params.soft_alpha: expected a value in [0, 1], got {params.soft_alpha!r}", upper=1.0)
    return params


# ---------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------

def imu_ideal_zup(x, xdot, g, accel_mode: str = "specific_force"):
    """Noise-free IMU reading h^d of paper 001 eq. 12 in the z-up frames.

    Args:
      x: (12,) paper-001 state; xdot: (12,) its time derivative (ẍ, ÿ, z̈ = xdot[3:6]);
      g: gravity [m/s²]; accel_mode: "specific_force" R_b^wᵀ(a_w + g e3) (default, errata) or
      "kinematic" R_b^wᵀ a_w (eq. 7).
    Returns (6,) [accel m/s², ω_b rad/s] in body axes (z up).
    """
    R = dcm_from_euler(x[ATT])
    a = xdot[VEL]
    if accel_mode == "specific_force":
        a = a + jnp.stack([0.0 * g, 0.0 * g, jnp.asarray(g, a.dtype)])
    return jnp.concatenate([R.T @ a, x[RATE]])


def h_imu(x, rotor_w, quad, accel_mode: str = "specific_force"):
    """h^d(x^D) of eq. 12 for the dynamics filter: IMU predicted from the particle's state and
    the rotor input of the step (filter model ``quad``).  Returns (6,).

    With ``accel_mode="specific_force"`` the accelerometer row is
    :func:`jaxslam.dynamics.rotor.specific_force` (thrust over mass along b̂3, equal to
    R_b^wᵀ(ẍ + g e3) for the drag-free model of eq. 1-4, without evaluating it).
    """
    if accel_mode == "specific_force":
        return jnp.concatenate([rotor.specific_force(rotor_w, quad, x.dtype), x[RATE]])
    xdot = rotor.f(x, rotor_w, quad)
    return imu_ideal_zup(x, xdot, quad.g, accel_mode)


def _observe_world(pose, l, params=None):
    return lidar3d.spherical_from_cartesian(l - pose[POS])


def _observe_body(pose, l, params=None):
    R = dcm_from_euler(pose[ATT])
    return lidar3d.spherical_from_cartesian(R.T @ (l - pose[POS]))


def _inverse_world(pose, z, params=None):
    return pose[POS] + lidar3d.cartesian_from_spherical(z)


def _inverse_body(pose, z, params=None):
    return pose[POS] + dcm_from_euler(pose[ATT]) @ lidar3d.cartesian_from_spherical(z)


def landmark_model(lidar: str = "world") -> fs.LandmarkModel:
    """The LiDAR model as a core :class:`~jaxslam.filters.fastslam.LandmarkModel`.

    "world": paper 001 eq. 13-15 (world-frame differences, attitude-free), y = [α, β, r];
    "body": paper 000's model c = R_b^wᵀ(m − p) in paper 001's z-up frames (elevation
    positive above the body x-y plane).  Residual wraps the azimuth.
    """
    if lidar == "world":
        return fs.LandmarkModel(3, 3, _observe_world, _inverse_world, lidar3d.innovation)
    if lidar == "body":
        return fs.LandmarkModel(3, 3, _observe_body, _inverse_body, lidar3d.innovation)
    raise InputError(f"lidar: expected one of {_LIDARS}, got {lidar!r}")


def dynamics_mean(pose, aux, rotor_w, params: Params, dt, drift_a):
    """The noise-free part of Table 2 Steps 1-2 for one particle: RK4(f, x^D, ω_rotor) (eq. 4)
    and the bias-mean prediction A^b x̂^B (eq. 11) through :func:`jaxslam.filters.ekf.predict`.

    pose (12,), aux (12,) bias mean, rotor_w (4,) rad/s, params, dt s, drift_a (12,) diagonal
    of A^b.  Returns (pose', aux').  :func:`imu_stage` adds the proposal noise to a whole
    particle set at once (:func:`jaxslam.filters.fastslam.propagate_additive`).
    """
    dtype = pose.dtype
    xn = rk4_step(rotor.f, pose, jnp.asarray(rotor_w, dtype), dt, params.quad)
    # Only the mean is kept (the shared covariance is predicted once, see imu_stage).
    m = ekf.predict(ekf.Gaussian(aux, jnp.zeros((NB, NB), dtype)),
                    lambda b, u: drift_a * b, None, jnp.zeros((NB, NB), dtype)).mean
    return xn, m


def dynamics_sample(pose, aux, key, rotor_w, params: Params, dt, drift_a):
    """Table 2 Step 1-2 for one particle: x^D ~ N(RK4(f, x^D, ω_rotor), Q) (eq. 4) and the
    bias-mean prediction A^b x̂^B (eq. 11): :func:`dynamics_mean` plus √Q ε, ε ~ N(0, I)
    drawn with ``key`` (reparametrised, differentiable in Q).  Returns (pose', aux')."""
    xn, m = dynamics_mean(pose, aux, rotor_w, params, dt, drift_a)
    return xn + _proposal_noise(key, params, pose.dtype), m


def _proposal_noise(key, params: Params, dtype):
    """√Q ε, ε ~ N(0, I) (12,) for one particle (a set draws (N, 12) at once in imu_stage)."""
    return jnp.sqrt(jnp.asarray(params.proposal_var, dtype)) * jax.random.normal(key, (NX,), dtype)


def _f_kin(x, imu, g, accel_mode):
    R = dcm_from_euler(x[ATT])
    a = R @ imu[0:3]
    if accel_mode == "specific_force":
        a = a - jnp.stack([0.0 * g, 0.0 * g, jnp.asarray(g, a.dtype)])
    return jnp.concatenate([x[VEL], a, euler_rates(x[ATT], imu[3:6]), jnp.zeros((3,), x.dtype)])


def kinematics_mean(pose, aux, imu_prev, imu_now, params: Params, dt,
                    accel_mode: str = "specific_force"):
    """Noise-free kinematics (IMU-driven) proposal of the baseline for one particle.

    RK4 of ṗ = v, v̇ = R a_m − g e3 (or R a_m, paper eq. 7 form), Λ̇ = D(Λ) ω_m with the IMU
    interpolated linearly between ``imu_prev`` and ``imu_now`` (first-order hold, STYLE.md),
    then ω := ω_m(now).  No bias compensation (the paper's baseline "without calibration").
    Returns (pose', aux unchanged).
    """
    dtype = pose.dtype
    h = jnp.asarray(dt, dtype)
    g = params.quad.g
    u0, u1 = jnp.asarray(imu_prev, dtype), jnp.asarray(imu_now, dtype)
    um = 0.5 * (u0 + u1)
    k1 = _f_kin(pose, u0, g, accel_mode)
    k2 = _f_kin(pose + 0.5 * h * k1, um, g, accel_mode)
    k3 = _f_kin(pose + 0.5 * h * k2, um, g, accel_mode)
    k4 = _f_kin(pose + h * k3, u1, g, accel_mode)
    xn = pose + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return xn.at[RATE].set(u1[3:6]), aux


def kinematics_sample(pose, aux, key, imu_prev, imu_now, params: Params, dt,
                      accel_mode: str = "specific_force"):
    """Kinematics proposal of the baseline for one particle: :func:`kinematics_mean` plus
    N(0, Q) drawn with ``key``.  Returns (pose', aux unchanged)."""
    xn, aux = kinematics_mean(pose, aux, imu_prev, imu_now, params, dt, accel_mode)
    return xn + _proposal_noise(key, params, pose.dtype), aux


def _rates_mean(bias_mean, gyro):
    """ω_m − (b̂0ω + b̂1ω): the mean of the gyroscope's inverse model (eq. 32-34); (..., 12)
    bias means → (..., 3)."""
    return gyro - bias_mean[..., 3:6] - bias_mean[..., 9:12]


def regenerate_rates(pose, bias_mean, key, gyro, gyro_cov):
    """Stage 2, Step 8 (eq. 32-34): ω ~ N(ω_m − (b̂0ω + b̂1ω), gyro_cov) for one particle.

    pose (12,), bias_mean (12,), gyro (3,) rad/s, gyro_cov (3, 3) (R_ω, plus H_ω P H_ωᵀ for
    exact weights); ``key`` None sets the mean.  Returns the pose with its rates replaced.
    (:func:`imu_stage` does the same for a whole set with one draw and one factor.)
    """
    mean = _rates_mean(bias_mean, gyro)
    if key is None:
        return pose.at[RATE].set(mean)
    L = cholesky_small(gyro_cov)
    return pose.at[RATE].set(mean + L @ jax.random.normal(key, (3,), pose.dtype))


def position_posterior(pose, lm_mean, lm_cov, active, z, ids, mask, R, lidar="world",
                       exact=True):
    """Stage 2, Step 8: the Gaussian p(x^{D1} | z^S, μ) of the LiDAR inverse model (eq. 15).

    For each observed, mapped landmark j: p_j = μ_j − ϱ(z_j) (world) or μ_j − R_b^w ϱ(z_j)
    (body), covariance C_j = J R Jᵀ (+ Σ_j when ``exact``), J = ∂p_j/∂z_j (``jax.jacfwd``);
    fused as P = (Σ C_j⁻¹)⁻¹, m = P Σ C_j⁻¹ p_j.  The 3×3 inverses are closed forms
    (:func:`jaxslam.linalg.inv_small`): no LAPACK call per particle under ``vmap``.

    Args: pose (12,); lm_mean (cap, 3), lm_cov (cap, 3, 3), active (cap,) — the particle's
    map (id j in slot j); z (L, 3), ids (L,), mask (L,); R (3, 3) R^S.
    Returns (m (3,), P (3, 3), any_ok): ``any_ok`` False when no observed landmark is mapped
    (m, P are then meaningless: the position is kept).
    """
    dtype = pose.dtype
    cap = lm_mean.shape[0]
    slot = jnp.clip(ids, 0, cap - 1)
    ok = mask & (ids >= 0) & (ids < cap) & active[slot]
    Rot = dcm_from_euler(pose[ATT]) if lidar == "body" else None

    def one(zj, mu, Sig):
        def g(zz):
            c = lidar3d.cartesian_from_spherical(zz)
            return mu - (Rot @ c if Rot is not None else c)

        pj = g(zj)
        J = jax.jacfwd(g)(zj)
        C = J @ R @ J.T
        if exact:
            C = C + Sig
        return pj, symmetrize(C)

    pj, C = jax.vmap(one)(z.astype(dtype), lm_mean[slot], lm_cov[slot])
    eye = jnp.eye(3, dtype=dtype)
    C = jnp.where(ok[:, None, None], C, eye)
    Ci = inv_small(C)[0] * ok[:, None, None]
    info = jnp.sum(Ci, axis=0)
    eta = jnp.einsum("lij,lj->i", Ci, jnp.where(ok[:, None], pj, 0.0))
    any_ok = jnp.any(ok)
    info = jnp.where(any_ok, info, eye)
    P = symmetrize(inv_small(info)[0])
    return P @ eta, P, any_ok


def regenerate_position(pose, lm_mean, lm_cov, active, z, ids, mask, key, R, lidar="world",
                        exact=True):
    """Stage 2, Step 8: x^{D1} ~ p(x^{D1} | z^S, μ) (:func:`position_posterior`), one draw
    m + chol(P) ε with ``key``.  Arguments as :func:`position_posterior`.

    Returns the pose with the regenerated position (unchanged if nothing was usable).
    (:func:`lidar_stage` does the same for a whole set with one draw.)
    """
    m, P, any_ok = position_posterior(pose, lm_mean, lm_cov, active, z, ids, mask, R, lidar, exact)
    return _position_draw(pose, m, P, any_ok, jax.random.normal(key, (3,), pose.dtype))


def _position_draw(pose, m, P, any_ok, eps):
    """The pose with position m + chol(P) ε, or unchanged when ``any_ok`` is False."""
    return pose.at[POS].set(jnp.where(any_ok, m + cholesky_small(P) @ eps, pose[POS]))


# ---------------------------------------------------------------------------
# Filter
# ---------------------------------------------------------------------------

def init(log: Log, config: Config, params: Params, *, key) -> State:
    """Initial particle set (Table 2 "Initialization"): ``config.n_particles`` poses
    ~ N(log.x0, diag(pose0_var)) drawn with ``key`` (required), bias means 0, shared bias
    covariance diag(bias_p0), equal weights, empty maps.  Only ``log.x0`` is read.

    Raises InputError when ``key`` is None, the config is bad (``n_particles`` ≤ 0 or not an
    integer, ...) or ``log.x0`` is not (12,).
    """
    if key is None:
        raise InputError("key: FastSLAM draws particles; give a PRNG key")
    validate_config(config)
    if np.shape(log.x0) != (NX,):
        raise InputError(f"log.x0: expected shape (12,), got {np.shape(log.x0)}")
    N = int(config.n_particles)
    x0 = jnp.asarray(log.x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    x0 = x0.astype(dtype)
    eps = jax.random.normal(key, (N * NX,), dtype).reshape(N, NX)
    poses = x0 + jnp.sqrt(jnp.asarray(params.pose0_var, dtype)) * eps
    # fs.init validates its pose on the host (np.asarray), so it gets a concrete placeholder
    # and the (possibly traced) cloud is put in afterwards: init stays jit/vmap-safe.
    p = fs.init(np.zeros((N, NX), np.dtype(dtype)), N, int(config.capacity), 3,
                aux=np.zeros((N, NB), np.dtype(dtype)), aux_per_particle=True)
    p = p._replace(pose=poses, aux=jnp.zeros((N, NB), dtype))
    return State(
        particles=p,
        bias_cov=jnp.diag(jnp.asarray(params.bias_p0, dtype)),
        k=jnp.zeros((), jnp.int32),
        neff_min=jnp.asarray(float(N), dtype),
        imu_prev=jnp.full((6,), jnp.nan, dtype),
    )


def _resample(p, key, config: Config, params: Params):
    if config.resampling == "soft":
        return fs.resample_soft(p, key, params.soft_alpha, threshold=params.resample_threshold)
    return fs.maybe_resample(p, key, params.resample_threshold, config.resampling)


def imu_stage(state: State, rotor_w, imu, key, config: Config,
              params: Params):
    """One IMU sample (Table 2 Steps 1-4, 6 and the rates part of Step 8); see module
    docstring.  rotor_w (4,) rad/s applied over the step; imu (6,) sample at its end.
    Returns (State, StepOut)."""
    p = state.particles
    dtype = p.pose.dtype
    dt = jnp.asarray(config.dt, dtype)
    imu = jnp.asarray(imu, dtype)
    k_prop, k_res, k_s2 = jax.random.split(key, 3)
    # "first": no finite sample seen yet (init sets imu_prev to NaN) -> the Table 4 re-initialisation.
    first = ~jnp.all(jnp.isfinite(state.imu_prev))
    a_b, q_b = bias_model(params, dtype)
    # A non-finite IMU sample is skipped and flagged MASKED_INPUT, never turned into a NaN state:
    # the dynamics model predicts through it without the measurement (and a skipped first sample
    # leaves the re-initialisation to the next finite one); the kinematics model (IMU as the
    # input) holds its previous sample, or keeps its poses before any finite sample.
    imu_ok = jnp.all(jnp.isfinite(imu))
    imu_next_prev = jnp.where(imu_ok, imu, state.imu_prev)  # NaN until a finite sample arrives
    imu = jnp.where(imu_ok, imu, jnp.where(first, jnp.zeros_like(imu), state.imu_prev))
    p = p._replace(status=p.status | jnp.where(imu_ok, jnp.int32(0), jnp.int32(errors.MASKED_INPUT)))

    if config.model == "kinematics":
        prev = jnp.where(first, imu, state.imu_prev)
        moved = fs.propagate_additive(p, k_prop, lambda x, a, u0, u1: kinematics_mean(
            x, a, u0, u1, params, dt, config.accel_mode),
            jnp.sqrt(jnp.asarray(params.proposal_var, dtype)), prev, imu)
        p = moved._replace(pose=jnp.where(imu_ok | ~first, moved.pose, p.pose))
        neff = fs.neff(p)
        st = state._replace(particles=p, k=state.k + 1, imu_prev=imu_next_prev)
        return st, _step_out(st, neff)

    rotor_w = jnp.asarray(rotor_w, dtype)
    # Steps 1-2: poses from the dynamics (one (N, 12) noise draw), bias means predicted (per
    # particle) ...
    p = fs.propagate_additive(p, k_prop, lambda x, a, w: dynamics_mean(x, a, w, params, dt, a_b),
                              jnp.sqrt(jnp.asarray(params.proposal_var, dtype)), rotor_w)
    # ... and the shared bias covariance predicted once.
    Q_b = jnp.diag(q_b)
    prior = ekf.predict(ekf.Gaussian(p.aux[0], state.bias_cov), lambda b, u: a_b * b, None, Q_b)
    P_pred = prior.cov
    R_I = jnp.diag(jnp.asarray(params.imu_var, dtype))
    zbar = imu - jax.vmap(lambda x: h_imu(x, rotor_w, params.quad, config.accel_mode))(p.pose)

    # Step 4 (KF update): A^b, Q^b, H_b and R^I are the same for every particle, so the gain
    # and the posterior covariance are too: one factorisation for the set, the means moved by
    # one product (ekf.linear_update_shared; equal to N separate ekf.update calls).
    H = jnp.asarray(H_B, dtype)
    innov = zbar - p.aux @ H.T
    m_post, P_post, _, _, nis, kf_ok, logdet = ekf.linear_update_shared(
        p.aux, P_pred, innov, H, R_I, jnp.ones((6,), bool))
    # A failed factorisation (R^I > 0 makes S PD, so only overflow) keeps the prediction.
    m_post = jnp.where(kf_ok, m_post, p.aux)
    P_post = jnp.where(kf_ok, P_post, P_pred)
    # Table 4 re-initialisation at the first sample: minimum-norm least squares H_b⁺ z̄.
    m_reinit = zbar @ jnp.asarray(_H_B_PINV, dtype).T
    m_post = jnp.where(first & imu_ok, m_reinit, m_post)
    m_post = jnp.where(imu_ok, m_post, p.aux)  # a skipped sample: the prediction (propagate made it)
    P_post = jnp.where(imu_ok, P_post, P_pred)

    # Step 3: IMU weight with the predicted bias (k|k−1); none at the re-initialisation.
    half = jnp.asarray(0.5 * 6 * math.log(2 * math.pi), dtype)
    if config.weights == "exact":
        ll = -0.5 * (nis + logdet) - half
    else:
        iv = 1.0 / jnp.asarray(params.imu_var, dtype)
        ll = -0.5 * (jnp.sum(innov * innov * iv, axis=1) - jnp.sum(jnp.log(iv))) - half
    ll = jnp.where(first | ~imu_ok, jnp.zeros_like(ll), ll)
    p = p._replace(aux=m_post)
    p = fs.reweight(p, ll)
    neff = fs.neff(p)
    p = _resample(p, k_res, config, params)

    # Step 8 (rates): gyroscope inverse sensor model with the updated bias; its covariance is
    # shared, so one 3×3 factor and one (N, 3) draw serve the set.
    if config.stage2 in ("paper", "rates"):
        Hw = H[3:6]
        G = jnp.diag(jnp.asarray(params.imu_var, dtype)[3:6])
        if config.weights == "exact":
            G = G + Hw @ P_post @ Hw.T
        rates = _rates_mean(p.aux, imu[3:6])
        if config.regen_noise:
            eps = jax.random.normal(k_s2, rates.shape, dtype)
            rates = rates + eps @ cholesky_small(symmetrize(G)).T
        p = p._replace(pose=jnp.where(imu_ok, p.pose.at[:, RATE].set(rates), p.pose))
    st = State(particles=p, bias_cov=P_post, k=state.k + 1,
                     neff_min=jnp.minimum(state.neff_min, neff), imu_prev=imu_next_prev)
    return st, _step_out(st, neff)


def lidar_stage(state: State, z, ids, mask, key, config: Config,
                params: Params):
    """One LiDAR frame (Table 2 Steps 3, 5, 6 and the position part of Step 8).

    z (L, 3) [α, β, r]; ids (L,) int32 known landmark ids (slot = id); mask (L,) bool.
    Returns (State, FrameOut).
    """
    p = state.particles
    dtype = p.pose.dtype
    k_res, k_s2 = jax.random.split(key)
    model = landmark_model(config.lidar)
    R = jnp.diag(jnp.asarray(params.lidar_var, dtype))
    wmode = "exact" if config.weights == "exact" else "mean"
    z = jnp.asarray(z, dtype)
    p, _ = fs.observe_update(p, model, z, ids, mask, R, None, weights=wmode, slot_by_id=True)
    # The core skipped (and flagged) the non-finite rows; the position regeneration skips them too.
    used = mask & jnp.all(jnp.isfinite(z), axis=-1)
    z = jnp.where(used[:, None], z, jnp.zeros((), dtype))
    neff = fs.neff(p)
    p = _resample(p, k_res, config, params)
    if config.model == "dynamics" and config.stage2 == "paper":
        m, P, any_ok = jax.vmap(lambda x, mu, c, a: position_posterior(
            x, mu, c, a, z, ids, used, R, config.lidar, config.weights == "exact"))(
            p.pose, p.lm_mean, p.lm_cov, p.active)
        eps = jax.random.normal(k_s2, m.shape, dtype)  # one (N, 3) draw for the set
        p = p._replace(pose=jax.vmap(_position_draw)(p.pose, m, P, any_ok, eps))
    st = state._replace(particles=p, neff_min=jnp.minimum(state.neff_min, neff))
    return st, _frame_out(st, neff, config)


def _step_out(state: State, neff) -> StepOut:
    mean, var = fs.estimate_var(state.particles, ANGLE_MASK)
    bm, bv = bias_estimate(state)
    H = jnp.asarray(H_B, bm.dtype)
    w = jnp.exp(state.particles.log_w)
    off = state.particles.aux @ H.T
    ov = jnp.diagonal(H @ state.bias_cov @ H.T) + w @ ((off - H @ bm) ** 2)
    return StepOut(mean, var, bm, bv, ov, neff)


def _frame_out(state: State, neff, config: Config) -> FrameOut:
    mp = fs.map_mean(state.particles)
    var = jnp.diagonal(mp.cov, axis1=-2, axis2=-1)
    if config.save_particles:
        return FrameOut(neff, mp.mean, var, state.particles.pose[:, POS], state.particles.log_w)
    return FrameOut(neff, mp.mean, var, None, None)


def estimate(state: State):
    """Weighted pose mean (12,) (circular mean for the Euler angles) and covariance (12, 12)."""
    return fs.estimate(state.particles, ANGLE_MASK)


def bias_estimate(state: State):
    """Weighted bias/drift mean (12,) and variance (12,) = diag(shared P) + spread of means."""
    p = state.particles
    w = jnp.exp(p.log_w)
    m = w @ p.aux
    spread = w @ ((p.aux - m) ** 2)
    return m, jnp.diagonal(state.bias_cov) + spread


def step(state: State, event: Event, config: Config, params: Params, *, key):
    """One IMU sample and, when ``event.mask`` has any True entry, the LiDAR frame taken at
    its end (:func:`imu_stage` then :func:`lidar_stage` under ``lax.cond``).

    Returns (State, StepOut).  Equal to what :func:`run` does at each sample; use
    :func:`run` for whole flights (one scan, no per-step dispatch).  ``key`` is required.
    """
    if key is None:
        raise InputError("key: FastSLAM draws particles; give a PRNG key")
    k_imu, k_lid = jax.random.split(key)
    state, out = imu_stage(state, event.rotor, event.imu, k_imu, config, params)

    def with_lidar(s):
        return lidar_stage(s, event.z, event.ids, event.mask, k_lid, config, params)[0]

    state = jax.lax.cond(jnp.any(event.mask), with_lidar, lambda s: s, state)
    return state, out


def _check_log(log: Log, config: Config):
    """Host-side shape checks of a :class:`Log` (and, when concrete, finite ``x0``)."""
    E = int(config.lidar_every)
    if np.shape(log.x0) != (NX,):
        raise InputError(f"log.x0: expected shape (12,), got {np.shape(log.x0)}")
    if np.ndim(log.imu) != 2 or np.shape(log.imu)[1:] != (6,):
        raise InputError(f"log.imu: expected shape (T, 6), got {np.shape(log.imu)}")
    T = np.shape(log.imu)[0]
    if np.shape(log.rotor_w) != (T, 4):
        raise InputError(f"log.rotor_w: expected shape ({T}, 4), got {np.shape(log.rotor_w)}")
    if np.ndim(log.z) != 3 or np.shape(log.z)[2:] != (3,):
        raise InputError(f"log.z: expected shape (F, L, 3), got {np.shape(log.z)}")
    F, L = np.shape(log.z)[:2]
    if np.shape(log.ids) != (L,):
        raise InputError(f"log.ids: expected shape ({L},), got {np.shape(log.ids)}")
    if np.shape(log.mask) != (F, L):
        raise InputError(f"log.mask: expected shape ({F}, {L}), got {np.shape(log.mask)}")
    if T != F * E:
        raise InputError(f"log.imu: {T} samples do not make {F} frames of lidar_every = {E}")
    if F == 0:  # an empty log failed deep inside the run (an IndexError)
        raise InputError("log.z: expected at least one LiDAR frame, got an empty log (F = 0, T = 0)")
    for name in ("x0", "rotor_w", "imu", "z", "ids"):  # a string array failed deep in NumPy/JAX
        x = getattr(log, name)
        if is_concrete(x) and not (isinstance(x, (jax.Array, np.ndarray)) and x.dtype.kind in "biuf"):
            check_numbers(x, f"log.{name}")
    check_mask(log.mask, "log.mask")
    if is_concrete(log.x0) and not np.all(np.isfinite(np.asarray(log.x0, np.float64))):
        raise InputError("log.x0: contains NaN or Inf")
    if is_concrete(log.rotor_w) and not np.all(np.isfinite(np.asarray(log.rotor_w, np.float64))):
        # unlike a non-finite IMU sample (skipped and flagged) it turned every pose NaN
        raise InputError("log.rotor_w: contains NaN or Inf")
    if is_concrete(log.ids, log.mask):  # a fractional id was truncated onto another landmark
        check_whole_ids(log.ids, "log.ids", used=np.any(np.asarray(log.mask), axis=0))


def run(log: Log, config: Config, params: Params, *, key) -> Result:
    """A whole flight in one jitted nested ``lax.scan`` (LiDAR frames outside, IMU samples
    inside).

    Args:
      log: :class:`Log` (``x0`` (12,), ``rotor_w`` (T, 4), ``imu`` (T, 6), ``z`` (F, L, 3),
        ``ids`` (L,), ``mask`` (F, L)); T must equal F · lidar_every.  Non-finite IMU samples
        and LiDAR rows are skipped and flagged (module docstring), not rejected.
      config: :class:`Config` (static).  params: :class:`Params` (traced).
      key: PRNG key (required; split into the initial-cloud key and one key per IMU sample).
    Returns :class:`Result`.  Works under an outer ``jit`` / ``vmap`` (traced log, key).

    Raises:
      InputError: no key, a bad config, log shapes that disagree with it, a non-finite
        ``log.x0`` or bad params (values checked when concrete).
    """
    if key is None:
        raise InputError("key: FastSLAM draws particles; give a PRNG key")
    validate_config(config)
    _check_log(log, config)
    if is_concrete(params):
        validate_params_001(params)
    log = log._replace(ids=jnp.asarray(log.ids, jnp.int32), mask=jnp.asarray(log.mask, bool))
    dtype = jnp.asarray(log.x0).dtype  # the numbers as arrays: a Python number and an array share one program
    thr = params.resample_threshold
    params = params._replace(resample_threshold=None if thr is None else host_array(thr, dtype),
                             soft_alpha=host_array(params.soft_alpha, dtype))
    return _run(log, config, params, key)


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params, key) -> Result:
    E = int(config.lidar_every)
    T = log.imu.shape[0]
    F = log.z.shape[0]
    k_init, k_run = jax.random.split(key)
    state = init(log, config, params, key=k_init)
    dtype = state.particles.pose.dtype
    # One key per IMU sample, split as in :func:`step` (IMU stage, LiDAR stage).
    keys = jax.vmap(lambda k: jnp.stack(jax.random.split(k)))(jax.random.split(k_run, T))
    keys = keys.reshape((F, E) + keys.shape[1:])
    rw = jnp.asarray(log.rotor_w, dtype).reshape(F, E, 4)
    im = jnp.asarray(log.imu, dtype).reshape(F, E, 6)
    ids = log.ids

    def frame(s, inp):
        rws, ims, ks, zf, mf = inp

        def inner(s2, x):
            w, u, k2 = x
            return imu_stage(s2, w, u, k2[0], config, params)

        s, outs = jax.lax.scan(inner, s, (rws, ims, ks))
        s, fo = lidar_stage(s, zf, ids, mf, ks[-1, 1], config, params)
        return s, (outs, fo)

    final, (outs, frames) = jax.lax.scan(frame, state, (rw, im, keys, jnp.asarray(log.z, dtype),
                                                        jnp.asarray(log.mask, bool)))
    steps = jax.tree_util.tree_map(lambda a: a.reshape((T,) + a.shape[2:]), outs)
    return Result(final, steps, frames)
