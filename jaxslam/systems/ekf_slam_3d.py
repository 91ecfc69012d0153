"""Paper 000's 3D EKF-SLAM: IMU-driven 9-state quadcopter + LiDAR [α, β, δ] landmarks.

A *system* module: it chooses the state order, the tabled P0/Q/R and the
initialisation, and plugs its model into the generic engine
(:mod:`jaxslam.filters.ekf_slam`).  Nothing here is a filter of its own.

Equations (paper 000; errata in docs/papers.md):

* state s = [ρ (3, NED m), v_B (3, body m/s), Λ = (φ, θ, ψ) (3, rad)]  (eq. 24)
* input λ = IMU [f_B (3) specific force m/s², ω_B (3) rad/s]; the paper's
  eq. 25 feeds only a_z = −f_T/m; jaxslam takes the 3-axis specific force
  (``accel_mode="3axis"``, default) and keeps the a_z-only form
  (``accel_mode="az"``: f_B = [0, 0, a_z]).
* ṡ = f_s(s, λ) = [C_NB v_B,  −ω × v_B + C_NBᵀ g n̂3 + f_B,  D(Λ) ω]
  (eq. 2 with the thrust/mass term replaced by the measured specific force).
* discretisation: one RK4 step over the IMU interval with the IMU reading
  interpolated linearly between the two samples (first-order hold; a held
  sample left a model error larger than the IMU noise, STYLE.md).
* process noise (eq. 27 integrates a continuous-time Q, so Q is a spectral
  density): Q_d = (Q_c + G Q_imu Gᵀ) Δt with G = ∂f_s/∂λ.  ``--q paper`` uses
  Q_c of Tables 6/7 and Q_imu = 0; ``--q imu`` uses Q_c = 0 and
  Q_imu = diag(ND_a² I₃, ND_g² I₃) from Table 5's noise densities, i.e. white
  noise on the accelerometer (enters v̇) and gyro (enters v̇ through −ω×v and
  Λ̇ through D); see docs/papers.md for the derivation.
* LiDAR update: eq. 30-43 with the corrected eq. 31 (errata), registration
  eq. 44-53 — both through the engine with closed-form Jacobians
  (``sensors.lidar3d.measure_state_and_jacobians``, ``inverse_state_and_jacobians``).
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..dynamics.integrators import rk4_field, rk4_linearized
from ..errors import InputError
from ..filters import ekf_slam as es
from ..geometry.euler import dcm_from_euler, euler_rate_matrix, rotate_jacobian
from ..linalg import (check_int, check_mask, check_numbers, check_psd, check_scalar, host_array, is_concrete,
                      small_matmul, wrap_angle)
from ..sensors import lidar3d
from ..stats import nees as _nees

__all__ = [
    "NX",
    "Config",
    "Params",
    "State",
    "f_cont",
    "motion",
    "motion_and_jacobian",
    "state_jacobian",
    "input_jacobian",
    "process_noise",
    "make_model",
    "paper_noise",
    "imu_noise",
    "TABLE6_P0",
    "TABLE6_Q",
    "TABLE7_P0",
    "TABLE7_Q",
    "validate_params",
]

NX = 9

TABLE6_P0 = (0.01,) * 6 + (0.02,) * 3  # known landmarks, Table 6
TABLE6_Q = (0.01,) * 6 + (0.02,) * 3
TABLE7_P0 = (0.001,) * 3 + (0.1,) * 3 + (0.0,) * 3  # unknown landmarks, Table 7
TABLE7_Q = (0.2, 0.2, 0.05, 0.01, 0.01, 0.01, 0.02, 0.2, 0.2)


class Params(NamedTuple):
    """Filter numbers (traced leaves: a new value never recompiles, ``grad`` w.r.t. them works).

    P0: (9, 9) initial robot covariance.
    Qc: (9, 9) additive continuous-time process noise density (Tables 6-7).
    Qimu: (6, 6) IMU white-noise density [accel (m/s²)²/Hz, gyro (rad/s)²/Hz].
    R: (3, 3) LiDAR covariance diag(σ_α², σ_β², σ_δ²) (Table 4).
    gate: χ²(3) gate of each mapped-landmark update (None: off, as in the paper; switching it
      on or off changes the program, a new value does not).
    nn_gate, nn_new: nearest-neighbour association thresholds on the 3-dof Mahalanobis
      distance (``config.association == "nn"``): match below ``nn_gate`` (χ²₃ 99 % = 11.34),
      new landmark above ``nn_new`` (30).
    The noise matrices are :data:`NOISE_FIELDS` (what ``--params`` files and
    :func:`params_to_dict` carry); the thresholds keep their defaults there.
    """

    P0: jax.Array
    Qc: jax.Array
    Qimu: jax.Array
    R: jax.Array
    gate: Optional[jax.Array] = None
    nn_gate: jax.Array = 11.34  # χ²₃ 99 %
    nn_new: jax.Array = 30.0


#: The noise fields of :class:`Params` (the rest are thresholds).
NOISE_FIELDS = ("P0", "Qc", "Qimu", "R")


def f_cont(s, imu, g, accel_mode: str = "3axis"):
    """ṡ = f_s(s, λ) (paper 000 eq. 24 with the IMU as input).  s (9,), imu (6,) -> (9,).

        ṡ = [C v,  −ω × v + g C₃,:ᵀ + f_B,  D(Λ) ω],  D(Λ) ω = [p + α tθ,  β,  α / cθ]

    with α = sφ q + cφ r, β = cφ q − sφ r (ω = [p, q, r]; eq. 3).  Written once, with its
    Jacobian, in :func:`state_jacobian`'s helper (under ``jit`` the unused Jacobian is removed).
    """
    return _field_and_jacobian(s, imu, g, accel_mode)[0]


def state_jacobian(s, imu, g, accel_mode: str = "3axis"):
    """F = ∂f_s/∂s (paper 000 eq. 28) in closed form.  s (9,), imu (6,) -> (9, 9).

    With a = C₁(φ)ᵀ e₂ = [0, cφ, −sφ] and α, β as in :func:`f_cont`:

        ∂(C v)/∂v = C,  ∂(C v)/∂(φ, θ, ψ) = [C (e₁ × v),  C (a × v),  e₃ × C v]  (``geometry.euler.rotate_jacobian``)
        ∂v̇/∂v = −[ω]×,  ∂v̇/∂(φ, θ) = g ∂(C₃,:)/∂(φ, θ) = g [[0, cφcθ, −sφcθ], [−cθ, −sφsθ, −cφsθ]]ᵀ
        ∂Λ̇/∂(φ, θ) = [[β tθ, α/cθ²], [−α, 0], [β/cθ, α sθ/cθ²]]

    f_s does not depend on ρ (zero columns) or on ψ through v̇ and Λ̇.  Equal to ``jax.jacfwd``
    of :func:`f_cont` (tests); the closed form is what the prediction's second derivatives
    (a gradient through the filter) go through, at a fraction of the kernels of autodiff's.
    """
    _, A = _field_and_jacobian(s, imu, g, accel_mode)
    return jnp.concatenate([jnp.zeros((NX, 3), A.dtype), A], axis=1)


def _field_and_jacobian(s, imu, g, accel_mode):
    """(f_s (9,), ∂f_s/∂[v_B, Λ] (9, 6)): :func:`f_cont` and :func:`state_jacobian` without ρ's
    zero columns, from one set of trigonometric terms."""
    v = s[3:6]
    # 3×3 products as multiply-and-sum: they fuse with their neighbours (a dot is a kernel
    # of its own per product)
    C = dcm_from_euler(s[6:9])
    sn, cs = jnp.sin(s[6:8]), jnp.cos(s[6:8])
    sf, st, cf, ct = sn[0], sn[1], cs[0], cs[1]
    f_b = imu[0:3]
    if accel_mode == "az":
        f_b = jnp.zeros_like(f_b).at[2].set(f_b[2])
    w = imu[3:6]
    p, q, r = w[0], w[1], w[2]
    g = jnp.asarray(g, s.dtype)
    z = jnp.zeros_like(sf)
    al, be = sf * q + cf * r, cf * q - sf * r
    tt, ic = st / ct, 1.0 / ct
    pos_dot = jnp.sum(C * v, axis=-1)
    xdot = jnp.concatenate([pos_dot, -jnp.cross(w, v) + g * C[2, :] + f_b,
                            jnp.stack([p + al * tt, be, al * ic])])
    d_pos = rotate_jacobian(s[6:9], v, C)
    d_vel = g * jnp.stack([jnp.stack([z, -ct, z]), jnp.stack([cf * ct, -sf * st, z]),
                           jnp.stack([-sf * ct, -cf * st, z])])
    d_att = jnp.stack([jnp.stack([be * tt, al * ic * ic, z]), jnp.stack([-al, z, z]),
                       jnp.stack([be * ic, al * st * ic * ic, z])])
    neg_skew_w = jnp.stack([jnp.stack([z, r, -q]), jnp.stack([-r, z, p]), jnp.stack([q, -p, z])])
    A = jnp.concatenate([jnp.concatenate([C, d_pos], axis=1),
                         jnp.concatenate([neg_skew_w, d_vel], axis=1),
                         jnp.concatenate([jnp.zeros((3, 3), s.dtype), d_att], axis=1)], axis=0)
    return xdot, A


def input_jacobian(s, accel_mode: str = "3axis"):
    """G = ∂f_s/∂λ in closed form (the IMU's entry into Q_d).  s (9,) -> (9, 6):
    ∂v̇/∂f_B = I (``"az"``: e₃e₃ᵀ), ∂v̇/∂ω = [v]× (−ω × v = v × ω), ∂Λ̇/∂ω = D(Λ) (eq. 3)."""
    v = s[3:6]
    z = jnp.zeros_like(v[0])
    skew_v = jnp.stack([jnp.stack([z, -v[2], v[1]]), jnp.stack([v[2], z, -v[0]]),
                        jnp.stack([-v[1], v[0], z])])
    acc = jnp.eye(3, dtype=s.dtype) if accel_mode != "az" else jnp.diag(jnp.asarray([0.0, 0.0, 1.0], s.dtype))
    z3 = jnp.zeros((3, 3), s.dtype)
    return jnp.concatenate([jnp.concatenate([z3, z3], axis=1), jnp.concatenate([acc, skew_v], axis=1),
                            jnp.concatenate([z3, euler_rate_matrix(s[6:9])], axis=1)], axis=0)


def _stage_input(u, c):
    a, b = u[:6], u[6:]
    return a + (b - a) * c


def _wrap_attitude(s):
    return s.at[6:9].set(wrap_angle(s[6:9]).at[1].set(s[7]))


def motion(s, u, params):
    """One RK4 step over Δt with a first-order hold of the IMU.

    u: (12,) = [imu at t_k (6), imu at t_k+Δt (6)]; params = (dt, g, accel_mode).
    """
    dt, g, accel_mode = params
    s_new = rk4_field(lambda x, c: f_cont(x, _stage_input(u, c), g, accel_mode), s, jnp.asarray(dt, s.dtype))
    return _wrap_attitude(s_new)


def motion_and_jacobian(s, u, params):
    """:func:`motion` and its Jacobian ∂s'/∂s (9, 9): the RK4 step's exact derivative, by the chain
    rule through its stages from the closed-form eq. 28 (:func:`state_jacobian`;
    ``dynamics.integrators.rk4_linearized``).  The engine's prediction uses it in place of
    forward-mode autodiff of :func:`motion` (``SlamModel.motion_jacobian``); equal to
    ``jax.jacfwd(motion)`` to rounding (tests)."""
    dt, g, accel_mode = params
    s_new, F = rk4_linearized(lambda x, c: f_cont(x, _stage_input(u, c), g, accel_mode), s,
                              jnp.asarray(dt, s.dtype),
                              jacobian=lambda x, c: _field_and_jacobian(x, _stage_input(u, c), g, accel_mode),
                              skip=3)
    return _wrap_attitude(s_new), F


def process_noise(s, imu, noise: Params, dt, g, accel_mode: str = "3axis"):
    """Q_d = (Q_c + G Q_imu Gᵀ) Δt, G = ∂f_s/∂λ at (s, λ) (first-order; see module doc;
    G in closed form, :func:`input_jacobian`), in ``s``'s dtype (Q_c, Q_imu are cast to it, as
    P0 and R are)."""
    del imu, g  # G does not depend on the IMU reading or on gravity
    G = input_jacobian(s, accel_mode)
    Qc, Qimu = jnp.asarray(noise.Qc, s.dtype), jnp.asarray(noise.Qimu, s.dtype)
    return (Qc + small_matmul(small_matmul(G, Qimu), G.T)) * jnp.asarray(dt, s.dtype)


def _observe(s, l, params):
    return lidar3d.measure_state(s, l)


def _observe_and_jacobians(s, l, params):
    return lidar3d.measure_state_and_jacobians(s, l)


def _inverse(s, z, params):
    return lidar3d.inverse_state(s, z)


def _inverse_and_jacobians(s, z, params):
    return lidar3d.inverse_state_and_jacobians(s, z)


def make_model() -> es.SlamModel:
    """The paper-000 SLAM model for the generic engine (robot 9, landmark 3, meas 3)."""
    return es.SlamModel(
        robot_dim=NX,
        lm_dim=3,
        meas_dim=3,
        motion=motion,
        observe=_observe,
        motion_jacobian=motion_and_jacobian,
        observe_jacobian=_observe_and_jacobians,
        inverse_jacobian=_inverse_and_jacobians,
        inverse=_inverse,
        residual=lidar3d.innovation,
    )


def _thresholds(dtype) -> dict:
    """The default thresholds of :class:`Params` as arrays of ``dtype`` (so a ``tree_map``
    over the parameters, e.g. ``astype``, reaches them; ``gate`` None stays None)."""
    return {f: host_array(Params._field_defaults[f], dtype) for f in ("nn_gate", "nn_new")}


def _lidar_R(dtype):
    return lidar3d.measurement_cov(lidar3d.PAPER000_LIDAR, dtype)


def paper_noise(mode: str, dtype=jnp.float64) -> Params:
    """P0/Q of Table 6 (``mode="known"``) or Table 7 (``"unknown"``); R of Table 4."""
    if mode == "known":
        P0, Q = TABLE6_P0, TABLE6_Q
    elif mode == "unknown":
        P0, Q = TABLE7_P0, TABLE7_Q
    else:
        raise InputError(f"mode: expected 'known' or 'unknown', got {mode!r}")
    return Params(  # built on the host: no eager programs to compile
        P0=jnp.asarray(np.diag(np.asarray(P0, np.float64)), dtype),
        Qc=jnp.asarray(np.diag(np.asarray(Q, np.float64)), dtype),
        Qimu=jnp.asarray(np.zeros((6, 6)), dtype),
        R=_lidar_R(dtype),
        **_thresholds(dtype),
    )


# Initial uncertainty used with the IMU-derived Q: the flight starts on the ground at a
# surveyed point, so the initial error is small (1 cm, 1 cm/s, 0.1 deg per axis).
IMU_P0 = (1e-4,) * 3 + (1e-4,) * 3 + (math.radians(0.1) ** 2,) * 3


def imu_noise(imu_spec, dtype=jnp.float64, P0=IMU_P0) -> Params:
    """Q from Table 5's noise densities (``--q imu``), R of Table 4, small P0."""
    nd_a = float(imu_spec.accel_noise_density)
    nd_g = float(imu_spec.gyro_noise_density)
    qimu = np.asarray([nd_a**2] * 3 + [nd_g**2] * 3, np.float64)
    return Params(  # built on the host: no eager programs to compile
        P0=jnp.asarray(np.diag(np.asarray(P0, np.float64)), dtype),
        Qc=jnp.asarray(np.zeros((NX, NX)), dtype),
        Qimu=jnp.asarray(np.diag(qimu), dtype),
        R=_lidar_R(dtype),
        **_thresholds(dtype),
    )


def validate_params(params: Params) -> Params:
    """Host-side checks: shapes and PSD of P0, Qc, Qimu; R positive definite; the thresholds
    positive scalars, not booleans (``gate`` may be None; ``True`` is not "on"), nn_gate <= nn_new."""
    shapes = {"P0": (NX, NX), "Qc": (NX, NX), "Qimu": (6, 6), "R": (3, 3)}
    for name, shp in shapes.items():
        a = check_numbers(getattr(params, name), f"params.{name}")
        if a.shape != shp:
            raise InputError(f"params.{name}: expected shape {shp}, got {a.shape}")
        check_psd(a, f"params.{name}", strict=(name == "R"))
    for name in ("gate", "nn_gate", "nn_new"):
        if _has_bool(getattr(params, name)):  # gate=True ("on") was read as a χ² gate of 1
            raise InputError(f"params.{name}: expected a positive finite scalar, got {getattr(params, name)!r}")
        if getattr(params, name) is not None or name != "gate":
            check_scalar(getattr(params, name), f"params.{name}", lower=0, strict=True)
    # match below nn_gate, new landmark above nn_new: nn_new < nn_gate made a row both (the
    # planar EKF's gate <= new_threshold)
    if not float(params.nn_new) >= float(params.nn_gate):
        raise InputError(f"params.nn_new: need nn_gate <= nn_new, got nn_gate {float(params.nn_gate)}, "
                         f"nn_new {float(params.nn_new)}")
    return params


# ---------------------------------------------------------------------------
# The estimator in the closed loop (jaxslam.systems.estimator.Estimator)
# ---------------------------------------------------------------------------

class Config(NamedTuple):
    """Static choices of the paper-000 estimator (hashable; a change recompiles).

    mode: "unknown" (SLAM, landmarks registered on first sight) or "known"
      (localisation against the true map, held in the padded map with zero covariance).
    association: "known" (landmark ids, as in the paper) or "nn" (ids hidden,
      nearest-neighbour Mahalanobis with a new-landmark threshold).
    capacity: landmark slots.  max_obs: measurements processed per frame (the visible, usable
      ones, i.e. not masked, are compacted into this many; extras are counted as dropped).
    accel_mode: "3axis" or "az" (paper eq. 25).  dt: IMU step [s].  g: gravity.
    (The update gate and the association thresholds are numbers: :class:`Params`.)
    save_map: store the landmark means at every frame (for plots; memory F·cap·3).
    fov_check: mask (and count) measurements outside ``lidar``'s field of view by more than 5σ.
    checkpoint: :func:`run` wraps its per-frame body in ``jax.checkpoint`` (a gradient through
      a log then stores one state per frame and recomputes the frame's IMU steps).
    active_only: the update and the prediction work on the leading block of slots that holds
      the map (:func:`jaxslam.filters.ekf_slam.update`, ``predict``): they cost what the mapped
      landmarks need, not the capacity; the same estimates to rounding.  False: the whole state
      (cheaper to compile; the tuning targets' gradients use it).
    joseph: False (default): the update's covariance by paper 000's eq. 43, the standard form
      P − K S Kᵀ (one rank-m correction); True: the factored Joseph form (twice the correction's
      products).  Over 10⁵ IMU steps of the closed loop both keep P symmetric and positive
      definite in float64 and float32, agree to rounding, and both fail alike in float32 when R
      is shrunk 10⁴× below the sensor's noise (``joseph`` of
      :func:`jaxslam.filters.ekf_slam.update`; docs/papers.md, "Eq. 43").
    """

    mode: str = "unknown"
    association: str = "known"
    capacity: int = 64
    max_obs: int = 16
    accel_mode: str = "3axis"
    dt: float = 0.01
    g: float = 9.81
    save_map: bool = False
    fov_check: bool = True
    lidar: lidar3d.LidarSpec = lidar3d.PAPER000_LIDAR
    checkpoint: bool = False
    active_only: bool = True
    joseph: bool = False


class State(NamedTuple):
    """The filter between events: the engine's posterior and the running counts of measurements
    dropped (beyond ``max_obs``) and masked (non-finite, outside the field of view, or in
    ``mode == association == "known"`` an id not in the known map)."""

    slam: es.SlamState
    dropped: jax.Array  # () int32 visible usable measurements beyond max_obs, summed
    masked: jax.Array  # () int32 visible measurements masked (see above), summed


class StepOut(NamedTuple):
    """What every IMU step reports: the robot mean and covariance diagonal after it."""

    mean: jax.Array  # (9,) robot mean after the step
    var: jax.Array  # (9,) robot covariance diagonal


class FrameOut(NamedTuple):
    """What every LiDAR frame reports: NEES against the truth (when given), NIS and counts."""

    nees: jax.Array  # () robot-block NEES against the truth after the frame's update
    nis: jax.Array  # () joint NIS of the frame's update
    dof: jax.Array  # () its degrees of freedom
    logdet: jax.Array  # () log det of its joint innovation covariance (innovation likelihood)
    n_active: jax.Array  # () mapped landmarks after the frame
    n_visible: jax.Array  # () landmarks in the FOV
    landmarks: Any  # (cap, 3) means (only with save_map) else None
    lm_var: Any  # (cap, 3) diagonal variances (only with save_map) else None



#: What the consistency statistics of this estimator cover (run JSON ``*_block`` / ``*_dim``):
#: the NEES of the robot block, the NIS of the LiDAR rows per degree of freedom.
CONSISTENCY_BLOCKS = {
    "anees_block": "robot block (position, body velocity, attitude)", "anees_dim": NX,
    "nis_block": "LiDAR rows (azimuth, elevation, range), per degree of freedom", "nis_dim": 1,
}


def robot_error(s_hat, x_true):
    """Estimation error of the 9-state against the 12-state truth, angles wrapped."""
    e = s_hat - x_true[:NX].astype(s_hat.dtype)
    return e.at[6:9].set(wrap_angle(e[6:9]))


def _fov_tolerance(sp: lidar3d.LidarSpec) -> lidar3d.LidarSpec:
    # Visibility is decided on the true geometry; noise can push a genuine measurement a little
    # past the FOV edge, so the check allows 5σ before calling a measurement impossible.
    return sp._replace(az_min=sp.az_min - 5 * sp.sigma_az, az_max=sp.az_max + 5 * sp.sigma_az,
                       el_min=sp.el_min - 5 * sp.sigma_el, el_max=sp.el_max + 5 * sp.sigma_el,
                       range_min=sp.range_min - 5 * sp.sigma_range,
                       range_max=sp.range_max + 5 * sp.sigma_range)


def _check_config(config: Config, n_known=None, name: str = "log.landmarks"):
    if config.mode not in ("known", "unknown"):
        raise InputError(f"config.mode: expected 'known' or 'unknown', got {config.mode!r}")
    if config.association not in ("known", "nn"):
        raise InputError(f"config.association: expected 'known' or 'nn', got {config.association!r}")
    if config.accel_mode not in ("3axis", "az"):  # any other string ran the 3-axis model
        raise InputError(f"config.accel_mode: expected '3axis' or 'az', got {config.accel_mode!r}")
    check_int(config.capacity, "config.capacity", what="an int (landmark slots)")
    check_int(config.max_obs, "config.max_obs", what="an int (measurements per frame)")
    # dt <= 0 froze the estimate or ran it backwards; a NaN g made every state NaN
    check_scalar(config.dt, "config.dt", lower=0, strict=True)
    check_scalar(config.g, "config.g")
    if config.mode == "known":
        if n_known is None:
            raise InputError(f"{name}: required with config.mode 'known' (the known map)")
        if n_known > config.capacity:
            raise InputError(f"config.capacity: {config.capacity} slots cannot hold the {n_known} known landmarks")


def _check_known_map(landmarks, config: Config, name: str) -> None:
    """The known map (``config.mode == "known"``), when its values are known: numbers, finite.
    A NaN/Inf position was preloaded inside the jitted run, and every frame's update came out
    non-finite (status NON_FINITE | NOT_PSD, the robot mean zeroed) instead of being refused."""
    if config.mode == "known" and landmarks is not None and is_concrete(landmarks):
        if not np.all(np.isfinite(check_numbers(landmarks, name))):
            raise InputError(f"{name}: contains NaN or Inf")


def _float_dtype(s0):
    """The filter's dtype for the start ``s0``: its own if floating, else JAX's default float (as
    :func:`jaxslam.filters.ekf_slam.init` casts an integer mean; an integer dtype had cast P0 and
    the thresholds to integers: P0 0, gate 0.9 → 0)."""
    dt = jnp.result_type(s0)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def initial_state(s0, config: Config, params: Params, landmarks=None) -> State:
    """The filter state at ``s0`` (9,) with covariance ``params.P0``; the known map preloaded with
    zero covariance in ``config.mode == "known"`` (``landmarks`` (L, 3)).  An integer ``s0`` runs
    in JAX's default float."""
    dtype = _float_dtype(s0)
    st = es.init(s0, params.P0.astype(dtype), config.capacity, 3)
    if config.mode == "known":
        st = es.preload(st, make_model(), landmarks)
    z = jnp.zeros((), jnp.int32)
    return State(st, z, z)


def propagate(state: State, imu_prev, imu_now, config: Config, params: Params) -> State:
    """One IMU interval (eq. 24-29): RK4 prediction with the interpolated IMU, Q_d with the
    closed-form G (:func:`process_noise`)."""
    st = state.slam
    s = st.x[:NX]
    Qd = process_noise(s, 0.5 * (imu_prev + imu_now), params, config.dt, config.g, config.accel_mode)
    st = es.predict(st, make_model(), jnp.concatenate([imu_prev, imu_now]), Qd,
                    (config.dt, config.g, config.accel_mode), active_only=config.active_only)
    return state._replace(slam=st)


def correct(state: State, y, ids, visible, config: Config, params: Params, x_true=None):
    """One LiDAR frame (eq. 30-53): non-finite and out-of-FOV visible rows masked and counted
    (with ``config.mode == config.association == "known"`` also a row whose id is not in the
    known map; the status gets MASKED_INPUT), the remaining visible rows compacted to
    ``config.max_obs`` (extras counted as dropped), association, update, registration
    (``"unknown"``).  ``x_true`` (12,): for the frame's NEES only (None: NaN).  Returns
    ``(state, FrameOut)``."""
    cfg = config
    model = make_model()
    mparams = (cfg.dt, cfg.g, cfg.accel_mode)
    st = state.slam
    visible = jnp.asarray(visible, bool)
    L = y.shape[0]
    M = min(cfg.max_obs, L)
    # Non-finite or out-of-FOV measurements are masked and counted, never used; masked before
    # the compaction, so they take none of the max_obs slots.
    usable = jnp.all(jnp.isfinite(y), axis=-1)
    if cfg.fov_check:
        usable = usable & lidar3d.in_fov(jnp.where(jnp.isfinite(y), y, 0.0), _fov_tolerance(cfg.lidar))
    if cfg.mode == "known" and cfg.association == "known":
        # an id outside the known map is neither updated nor registered (run refuses a concrete one)
        usable = usable & es.associate_known(st, ids, visible)[1]
    masked = jnp.sum(visible & ~usable)
    good = visible & usable
    order = jnp.argsort(~good, stable=True)[:M]
    y_s, id_s, vis_s = y[order], ids[order], good[order]
    dropped = jnp.sum(good) - jnp.sum(vis_s)
    R = params.R.astype(st.x.dtype)
    if cfg.association == "known":
        slots, mapped = es.associate_known(st, id_s, vis_s)
        new = es.first_of_each_id(id_s, vis_s & ~mapped)  # a repeated new id registers once
    else:
        slots, mapped, new, _ = es.associate_nn(
            st, model, y_s, vis_s, R, mparams, gate=jnp.asarray(params.nn_gate, st.x.dtype),
            new_threshold=jnp.asarray(params.nn_new, st.x.dtype), active_only=cfg.active_only,
        )
    gate = None if params.gate is None else jnp.asarray(params.gate, st.x.dtype)
    st, info = es.update(st, model, y_s, slots, mapped, R, mparams, gate=gate,
                          active_only=cfg.active_only, joseph=cfg.joseph)
    if cfg.mode == "unknown":
        st = es.register(st, model, y_s, id_s, new, R, mparams)
    if x_true is None:
        nees = jnp.asarray(jnp.nan, st.x.dtype)
    else:
        nees = _nees(robot_error(st.x[:NX], x_true), st.P[:NX, :NX])
    out = FrameOut(
        nees=nees,
        nis=info.nis,
        dof=info.dof,
        logdet=info.logdet,
        n_active=jnp.sum(st.active),
        n_visible=jnp.sum(visible),
        landmarks=es.landmarks(st, model) if cfg.save_map else None,
        lm_var=jnp.diagonal(es.landmark_covs(st, model), axis1=-2, axis2=-1) if cfg.save_map else None,
    )
    st = st._replace(status=st.status | jnp.where(masked > 0, jnp.int32(errors.MASKED_INPUT), 0))
    return State(st, state.dropped + dropped.astype(jnp.int32), state.masked + masked.astype(jnp.int32)), out


def make_estimator(config: Config, params: Params, landmarks_true=None):
    """Build the :class:`jaxslam.systems.estimator.Estimator` of paper 000's EKF-SLAM (the closed
    loop's view of :func:`propagate` and :func:`correct`; its ``init`` draws the initial error
    from ``params.P0``).

    ``params`` is traced (differentiable); ``config`` static.  In ``mode="known"``
    ``landmarks_true`` (L, 3) must be given and ``config.capacity`` ≥ L.  ``config`` and, when
    its values are concrete, ``params`` are checked as :func:`run` checks them
    (:func:`validate_params`): an :class:`InputError` naming the field.
    """
    from .estimator import Estimator

    _check_config(config, None if landmarks_true is None else int(np.shape(landmarks_true)[0]), "landmarks_true")
    _check_known_map(landmarks_true, config, "landmarks_true")
    if is_concrete(params):  # as run() checks them (a non-PSD R or a (8, 8) P0 was taken as given)
        validate_params(params)

    def init(key, x0):
        dtype = x0.dtype
        P0 = params.P0.astype(dtype)
        # Initial error drawn from P0 (eigen-decomposition: P0 may be singular, Table 7).
        w, V = jnp.linalg.eigh(0.5 * (P0 + P0.T))
        e0 = V @ (jnp.sqrt(jnp.clip(w, 0.0)) * jax.random.normal(key, (NX,), dtype))
        return initial_state(x0[:NX] + e0, config, params, landmarks_true)

    def ctrl_state(est, imu_now):
        return jnp.concatenate([est.slam.x[:NX], imu_now[3:6]])

    def step_out(est, x_true):
        # Cheap per-step record (mean and variances); the NEES, which needs a Cholesky
        # factor, is taken once per LiDAR frame in ``correct``.
        return StepOut(mean=est.slam.x[:NX], var=jnp.diagonal(est.slam.P[:NX, :NX]))

    return Estimator(init, functools.partial(propagate, config=config, params=params),
                     lambda est, y, ids, visible, x_true=None: correct(est, y, ids, visible, config, params, x_true),
                     ctrl_state, step_out)


__all__ += ["StepOut", "FrameOut", "make_estimator", "robot_error", "CONSISTENCY_BLOCKS", "initial_state",
            "propagate", "correct"]


def params_to_dict(noise: Params) -> dict:
    """JSON-ready form of the noise of :class:`Params` (:data:`NOISE_FIELDS`, full matrices as
    nested lists)."""
    return {k: np.asarray(getattr(noise, k), float).tolist() for k in NOISE_FIELDS}


def params_from_dict(d: dict, default: Params, dtype) -> Params:
    """Read a (partial) noise dict, e.g. from ``jaxslam tune`` / ``--params``.

    Each entry is a full matrix or a list of diagonal values; missing entries keep
    ``default``.  Unknown keys are an error naming them; so is an entry that is not numbers
    (a string, a ragged list, true/false), of the wrong shape, non-finite, or not symmetric
    positive semi-definite: an :class:`InputError` naming ``params.noise.KEY`` (they were a
    bare ``ValueError`` or accepted).  That ``R`` is strictly positive definite is
    :func:`validate_params`'s check.
    """
    if not isinstance(d, dict):
        raise InputError(f"params.noise: expected a dict of {list(NOISE_FIELDS)}, got {type(d).__name__}")
    unknown = set(d) - set(NOISE_FIELDS)
    if unknown:
        raise InputError(f"params.noise: unknown entries {sorted(unknown)}; expected {list(NOISE_FIELDS)}")
    shapes = {"P0": (NX, NX), "Qc": (NX, NX), "Qimu": (6, 6), "R": (3, 3)}
    vals = default._asdict()
    for k, v in d.items():
        name = f"params.noise.{k}"
        try:
            a = check_numbers(v, name)  # a string, None, a ragged list: InputError naming it
        except OverflowError:  # an integer beyond float range
            raise InputError(f"{name}: holds a number too large for a float") from None
        if _has_bool(v):  # true/false are not numbers (paramfile refuses them too)
            raise InputError(f"{name}: expected numbers, got {v!r}"[:300])
        n = shapes[k][0]
        if a.shape == (n,):
            a = np.diag(a)
        if a.shape != shapes[k]:
            raise InputError(f"{name}: expected shape {shapes[k]} (or its {n} diagonal values), got {a.shape}")
        src = np.asarray(v).dtype  # a float32 array keeps its rounding room in check_psd
        check_psd(a.astype(src) if src.kind == "f" else a, name)  # finite, symmetric, PSD
        vals[k] = jnp.asarray(a, dtype)
    return Params(**vals)


def _has_bool(v) -> bool:
    if isinstance(v, (bool, np.bool_)):
        return True
    if isinstance(v, (list, tuple)):
        return any(_has_bool(x) for x in v)
    return getattr(v, "dtype", None) == np.bool_


__all__ += ["params_to_dict", "params_from_dict", "NOISE_FIELDS"]


class Log(NamedTuple):
    """A recorded flight (one run; a batch adds a leading axis).  T = F · k IMU steps, k the
    IMU steps per LiDAR frame (read from the shapes).

    s0: (9,) initial estimate [ρ m, v_B m/s, Λ rad] (its covariance is ``params.P0``).
    imu: (T + 1, 6) IMU samples at t = 0, Δt, …, TΔt [m/s², rad/s] (sample 0 precedes the
      first prediction).
    y: (F, L, 3) LiDAR [α, β, δ] per frame, taken after every k predictions; visible: (F, L)
      bool; ids: (L,) or (F, L) int32 landmark ids.
    truth: optional (T + 1, 12) true states: the frames' NEES are computed against it (a real
      log has none).
    landmarks: (L, 3) the known map [m] (``config.mode == "known"``; else unused).
    """

    s0: jax.Array
    imu: jax.Array
    y: jax.Array
    visible: jax.Array
    ids: jax.Array
    truth: Any = None
    landmarks: Any = None


class Result(NamedTuple):
    """What :func:`run` returns (one run).

    means: (T, 9) robot mean after every prediction step (the last step of a frame: before the
      frame's LiDAR update; ``final`` holds the state after the last update).
    frames: :class:`FrameOut` of every LiDAR frame (leading axis F): NEES (NaN without
      ``log.truth``), the update's joint NIS, degrees of freedom and log det S (the terms of
      the innovation likelihood), landmark counts.
    final: the final :class:`State`.
    """

    means: jax.Array
    frames: FrameOut
    final: State


def _check_log(log: Log) -> int:
    """Shapes of ``log`` (static, also under tracing); returns k (IMU steps per frame)."""
    if np.ndim(log.visible) != 2:
        raise InputError(f"log.visible: expected shape (F, L), got {np.shape(log.visible)}")
    F, L = np.shape(log.visible)
    if np.shape(log.y) != (F, L, 3):
        raise InputError(f"log.y: expected shape ({F}, {L}, 3) to match log.visible, got {np.shape(log.y)}")
    T1 = np.shape(log.imu)[0] if np.ndim(log.imu) == 2 else -1
    if np.ndim(log.imu) != 2 or np.shape(log.imu)[1] != 6 or F == 0 or (T1 - 1) % F or T1 < F + 1:
        raise InputError(f"log.imu: expected shape (F·k + 1, 6) for {F} frames of k IMU steps, "
                         f"got {np.shape(log.imu)}")
    if np.shape(log.s0) != (NX,):
        raise InputError(f"log.s0: expected shape ({NX},), got {np.shape(log.s0)}")
    check_mask(log.visible, "log.visible")
    if np.ndim(log.ids) not in (1, 2) or np.shape(log.ids)[-1] != L or np.shape(log.ids)[:-1] not in ((), (F,)):
        raise InputError(f"log.ids: expected shape ({L},) or ({F}, {L}), got {np.shape(log.ids)}")
    if log.truth is not None and np.shape(log.truth) != (T1, 12):
        raise InputError(f"log.truth: expected shape ({T1}, 12), got {np.shape(log.truth)}")
    return (T1 - 1) // F


def _check_known_ids(log: Log, config: Config) -> None:
    """With ``config.mode == config.association == "known"`` and concrete ``log.ids``: every
    visible row's id is one of the known map's 0 … L_map − 1 (an id outside it was neither used
    nor registered; traced, :func:`correct` masks and counts it)."""
    if config.mode != "known" or config.association != "known" or not is_concrete(log.ids):
        return
    n_known = int(np.shape(log.landmarks)[0])
    ids = np.broadcast_to(np.asarray(log.ids), np.shape(log.visible))
    used = np.asarray(log.visible, bool) if is_concrete(log.visible) else np.ones(ids.shape, bool)
    bad = ids[used & ((ids < 0) | (ids >= n_known))]
    if bad.size:
        raise InputError(f"log.ids: visible rows must name a landmark of the known map (0 … {n_known - 1}), "
                         f"got the id {bad.flat[0]}")


class Event(NamedTuple):
    """One LiDAR frame of a :class:`Log` (the slice :func:`step` takes): its k IMU intervals,
    then the frame.  imu_prev, imu_now: (k, 6) the samples at each interval's ends; y: (L, 3);
    ids: (L,); visible: (L,); x_true: (12,) the truth at the frame (None: no NEES)."""

    imu_prev: jax.Array
    imu_now: jax.Array
    y: jax.Array
    ids: jax.Array
    visible: jax.Array
    x_true: Any = None


def init(log: Log, config: Config, params: Params, *, key=None) -> State:
    """The state before the first IMU interval: ``log.s0`` with covariance ``params.P0`` (no random
    draw), the known map ``log.landmarks`` preloaded in ``config.mode == "known"``."""
    del key
    return initial_state(jnp.asarray(log.s0), config, params,
                         log.landmarks if config.mode == "known" else None)


def step(state: State, event: Event, config: Config, params: Params, *, key=None):
    """One frame: k predictions (:func:`propagate`) then the LiDAR update (:func:`correct`).
    Returns ``(state, (means (k, 9) after each prediction, FrameOut))``."""
    del key

    def imu_step(e, ab):
        e = propagate(e, ab[0], ab[1], config, params)
        return e, e.slam.x[:NX]

    state, means = jax.lax.scan(imu_step, state, (event.imu_prev, event.imu_now))
    state, out = correct(state, event.y, event.ids, event.visible, config, params, event.x_true)
    return state, (means, out)


def _events(log: Log, k: int) -> Event:
    F = log.visible.shape[0]
    x_frames = log.truth[k::k] if log.truth is not None else None
    return Event(imu_prev=log.imu[:-1].reshape(F, k, 6), imu_now=log.imu[1:].reshape(F, k, 6), y=log.y,
                 ids=jnp.broadcast_to(log.ids, log.visible.shape), visible=log.visible, x_true=x_frames)


def run(log: Log, config: Config, params: Params, *, key=None) -> Result:
    """Paper 000's EKF-SLAM on one recorded log, open loop: one ``lax.scan`` of :func:`step` over
    the frames (the estimator of the closed loop, :func:`make_estimator`, paper 000 eq. 24-53).

    Differentiable in every leaf of ``params`` (P0 included: the initial state is ``log.s0`` with
    covariance ``params.P0``, no random draw) and of ``log``; ``config`` static
    (``config.checkpoint``: ``jax.checkpoint`` on the per-frame body, so a gradient stores one
    state per frame).  ``key`` is not used (the filter draws nothing); it is accepted as every
    system's ``run`` accepts it.  Shapes are checked here, values (PSD covariances) by
    :func:`validate_params` when they are concrete.  Jitted (``config`` static); compose under
    ``jit``/``vmap``/``grad``.
    """
    del key
    _check_log(log)
    if is_concrete(log.s0) and not np.all(np.isfinite(np.asarray(log.s0, np.float64))):
        raise InputError("log.s0: contains NaN or Inf")  # every mean came out NaN
    _check_config(config, None if log.landmarks is None else int(np.shape(log.landmarks)[0]))
    _check_known_map(log.landmarks, config, "log.landmarks")
    _check_known_ids(log, config)
    if is_concrete(params):
        validate_params(params)
    dtype = _float_dtype(log.s0)  # thresholds as arrays: a Python number and an array share one program
    params = params._replace(**{f: None if getattr(params, f) is None else host_array(getattr(params, f), dtype)
                                for f in ("gate", "nn_gate", "nn_new")})
    return _run(log, config, params)


@functools.partial(jax.jit, static_argnums=1)
def _run(log: Log, config: Config, params: Params) -> Result:
    k = _check_log(log)
    body = functools.partial(step, config=config, params=params)
    if config.checkpoint:
        body = jax.checkpoint(body)
    e, (means, frames) = jax.lax.scan(body, init(log, config, params), _events(log, k))
    return Result(means=means.reshape(-1, NX), frames=frames, final=e)


__all__ += ["Log", "Event", "Result", "init", "step", "run"]
