"""Scenario ``fastslam-helix`` (paper 001, Sec. IV-B): modified FastSLAM on the helix.

Truth (jaxslam's generator; paper 001 flew Gazebo/ROS, not reproducible here): paper 001's
quadcopter (eq. 1-4 with rotor speeds and the gyroscopic term, :mod:`jaxslam.dynamics.rotor`,
``PAPER001`` m = 1.477 kg, Ixx = Iyy = 0.01152, Izz = 0.0218 kg m²) integrated by RK4 at
T = 0.01 s, flown by paper 000's DF-LQR (with the flatness feedforward) acting on the true
state: the controller runs in the NED layout through the converters of
:mod:`jaxslam.dynamics.rotor` with the paper-001 mass/inertia and PD gains placed at
ω_n = 25 rad/s, ζ = 0.8 for that inertia; its thrust/torques are turned into rotor speeds by
the inverse mixer and the rotor speeds drive the truth and are the filter's input.

* Path: :class:`jaxslam.control.trajectories.Helix` defaults (radius 1 m, 20 s per turn,
  0.5 m altitude climbing 0.03 m/s), the vehicle starting at rest on the helix's first point
  with a 3 s blend of the reference (no take-off transient).
* Landmarks: the four poles [±2, ±2, −1] of paper 001 (z up), all observed every LiDAR frame
  (360° LiDAR, no FOV), known data association.
* IMU: 100 Hz, :func:`jaxslam.sensors.imu.PAPER001_IMU` (bias on every axis at ``--bias``;
  paper 000's noise densities; Gauss-Markov drift τ = 100 s with 10 % of the bias as its
  stationary σ, drawn at the start); accelerometer as specific force (``--accel`` kinematic
  for the paper's eq. 7 form, used by truth and filter alike).
* LiDAR: 10 Hz, world-frame eq. 13-14 (``--lidar body`` for paper 000's body-frame model),
  σ = (0.33°, 0.3°, 0.1 m).

Filter (:mod:`jaxslam.systems.fastslam_001`): its defaults, the IMU's white noise and drift
model as R^I, A^b, Q^b, a bias prior σ of ten times the bias level (:func:`bias_prior_sigma`),
the LiDAR σ's as R^S, and the paper-001 inertia (or ``PAPER001_MISMATCH`` with
``--inertia-mismatch``).

Metrics (per run):

* ``pos_rmse_m``, ``att_rmse_deg``: RMS over all IMU samples of the norm of the weighted-mean
  position / wrapped Euler-angle error; ``vel_rmse_mps`` likewise;
* ``landmark_rmse_m``: RMS over the landmarks of ‖μ̂_j − m_j‖, weighted map at the end;
* ``accel_bias_err``, ``gyro_bias_err``: final ‖(b̂0 + b̂1) − (b0 + b1)‖ of each sensor (the
  observable total offset; the baseline "estimates" 0), and ``*_frac`` = that divided by
  ‖b0‖ (the true constant bias, bias·√3); ``accel_b0_err`` / ``gyro_b0_err`` for b0 alone;
* ``neff_min``: smallest effective sample size after a weight update; ``resamples``: count.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...control import dflqr, trajectories
from ...control.attitude_pd import gains_from_bandwidth
from ...dynamics import rotor
from ...dynamics.integrators import rk4_step
from ...dynamics.params import PAPER001, PAPER001_MISMATCH, QuadParams
from ...errors import InputError
from ...geometry.euler import dcm_from_euler
from ...linalg import wrap_angle
from ...sensors import imu as imu_mod
from ...sensors import landmarks as lm_mod
from ...sensors import lidar3d
from ...sensors import range_bearing3d as rb
from ...systems import fastslam_001 as fs1
from .. import monte_carlo
from .builtin import DECLARED
from .registry import Scenario, ScenarioResult, _checked_args, _duration_flown, program_key, register

DT = 0.01
LIDAR_EVERY = 10
RAMP_S = 3.0

__all__ = ["DT", "LIDAR_EVERY", "TruthSetup", "Flight001", "helix_001", "truth_setup", "fly",
           "bias_prior_sigma", "make_filter", "evaluate", "build", "run_scenario"]


class TruthSetup(NamedTuple):
    """Everything the truth generator needs (pytree; numbers traced).

    quad: true :class:`~jaxslam.dynamics.params.RotorQuadParams`.  ctrl: DF-LQR parameters
    (NED layout, paper-001 mass/inertia).  traj: trajectory (NED flat outputs).
    imu: :class:`~jaxslam.sensors.imu.ImuSpec`.  lidar: RangeBearingSpec (σ's).
    landmarks: (L, 3) z-up world [m].  x0: (12,) paper-001 start state.
    K: (4, 7) DF-LQR gain (computed once by :func:`truth_setup`, outside the flight's jit).
    """

    quad: Any
    ctrl: Any
    traj: Any
    imu: Any
    lidar: Any
    landmarks: Any
    x0: Any
    K: Any


class Flight001(NamedTuple):
    """A simulated paper-001 flight (T IMU samples, F LiDAR frames, L landmarks).

    t (T+1,) s; truth (T+1, 12) paper-001 states; rotor (T, 4) rad/s over each step;
    imu (T, 6) measured; offset (T, 12) true [b0a, b0ω, b1a, b1ω] at each sample;
    z (F, L, 3) [α, β, r]; mask (F, L); ref (T+1, 4) desired NED [x, y, z, ψ].
    """

    t: Any
    truth: Any
    rotor: Any
    imu: Any
    offset: Any
    z: Any
    mask: Any
    ref: Any


def helix_001():
    """The helix of paper 001's scenario: Helix defaults, started on its own first point."""
    h = trajectories.Helix()
    p0 = h.center[0] + h.radius, h.center[1], h.center[2]
    return h._replace(start=tuple(float(v) for v in p0), ramp_time=RAMP_S)


def truth_setup(bias: float, dtype, quad=PAPER001) -> TruthSetup:
    """Truth of ``fastslam-helix`` (module docstring) with the IMU bias level ``bias``."""
    traj = helix_001()
    qp = QuadParams(quad.mass, quad.inertia, quad.g)
    ctrl = dflqr.DFLQRParams(pd=gains_from_bandwidth(np.asarray(quad.inertia), 25.0, 0.8),
                             quad=qp)
    x0_ned = jnp.zeros((12,), dtype).at[0:3].set(jnp.asarray(traj.start, dtype))
    K = jax.jit(lambda c: dflqr.gain(c, dtype))(ctrl)
    return TruthSetup(
        quad=quad, ctrl=ctrl, traj=traj,
        imu=imu_mod.PAPER001_IMU(bias, rate=1.0 / DT),
        lidar=rb.PAPER001_RANGE_BEARING,
        landmarks=lm_mod.pole_landmarks(dtype),
        x0=rotor.state_from_ned(x0_ned),
        K=K,
    )


def fly(setup: TruthSetup, key, n_frames: int, lidar_every: int = LIDAR_EVERY,
        lidar: str = "world", accel_mode: str = "specific_force") -> Flight001:
    """Simulate the truth and its sensors in one ``lax.scan`` (module docstring).

    key → (k_bias, k_imu, k_lidar).  Returns :class:`Flight001` of T = n_frames·lidar_every
    samples.
    """
    dtype = setup.x0.dtype
    T = int(n_frames) * int(lidar_every)
    dt = jnp.asarray(DT, dtype)
    quad = type(setup.quad)(*(jnp.asarray(v, dtype) for v in setup.quad))
    K = jnp.asarray(setup.K, dtype)
    t_ctrl = jnp.arange(T, dtype=dtype) * dt
    refs = jax.vmap(lambda tt: dflqr.reference_at(tt, setup.traj, setup.ctrl, feedforward=True,
                                                  dtype=dtype))(t_ctrl)

    def body(x, ref):
        u_ned, _ = dflqr.control_ref(rotor.state_to_ned(x), ref, K, setup.ctrl, feedforward=True)
        w = rotor.rotor_speeds_from_input(rotor.input_from_ned(u_ned), quad)
        xn = rk4_step(rotor.f, x, w, dt, quad)
        ideal = fs1.imu_ideal_zup(xn, rotor.f(xn, w, quad), quad.g, accel_mode)
        return xn, (xn, w, ideal)

    _, (xs, ws, ideal) = jax.lax.scan(body, setup.x0, refs)
    k_b, k_w, k_l = jax.random.split(key, 3)
    b0 = imu_mod.bias_drift_init(k_b, setup.imu, dtype=dtype)
    k_b2 = jax.random.fold_in(k_b, 1)
    off = imu_mod.bias_drift_rollout(k_b2, b0, setup.imu, dt, T)
    white = imu_mod.sample_white_noise(k_w, setup.imu, (T,), dtype)
    imu = imu_mod.corrupt(ideal, off, white)
    offset = jnp.concatenate([off.bias, off.drift], axis=1)  # (T, 12) = [b0a, b0ω, b1a, b1ω]
    truth = jnp.concatenate([setup.x0[None], xs], axis=0)
    xf = truth[lidar_every::lidar_every]  # (F, 12): state at each frame's last sample
    lms = setup.landmarks
    if lidar == "world":
        y = jax.vmap(lambda x: lidar3d.spherical_from_cartesian(lms - x[0:3]))(xf)
    else:
        y = jax.vmap(lambda x: lidar3d.spherical_from_cartesian(
            (lms - x[0:3]) @ dcm_from_euler(x[6:9])))(xf)
    y = y + rb.sample_noise(k_l, setup.lidar, (xf.shape[0], lms.shape[0]), dtype)
    y = y.at[..., 0].set(wrap_angle(y[..., 0]))
    t = jnp.arange(T + 1, dtype=dtype) * dt
    ref = jax.vmap(lambda tt: trajectories.flat_output(setup.traj, tt))(t)
    mask = jnp.ones(y.shape[:2], bool)
    return Flight001(t, truth, ws, imu, offset, y, mask, ref)


def bias_prior_sigma(bias: float) -> float:
    """Std of the filter's bias prior: ten times the bias level, at least 1e-3 (jaxslam's
    choice: a datasheet bound on the offset).  It sets P_{0|0} of the bias KF and the
    uncompensated-offset allowance of the kinematics baseline's proposal."""
    return max(10.0 * abs(float(bias)), 1e-3)


def _params_json(prm) -> dict:
    """The filter parameters of the run JSON's config (the quadcopter's apart); None stays None
    (``resample_threshold`` None: resample at every update; it used to be written as NaN)."""
    return {k: None if v is None else np.asarray(v, float).tolist() for k, v in prm._asdict().items()
            if k != "quad"}


def make_filter(options: dict, dtype):
    """(Config, Params) of the scenario options."""
    model = options["model"]
    thr = float(options["resample_threshold"])
    cfg = fs1.Config(
        model=model, n_particles=int(options["particles"]), lidar=options["lidar"], weights=options["weights"],
        stage2=options["stage2"], accel_mode=options["accel"],
        resampling=options["resampling"], capacity=4, lidar_every=LIDAR_EVERY, dt=DT,
    )
    quad = PAPER001_MISMATCH if options["inertia_mismatch"] else PAPER001
    bias = float(options["bias"])
    spec = imu_mod.PAPER001_IMU(bias, rate=1.0 / DT)
    prm = fs1.default_params(model, spec, quad=quad, dt=DT, dtype=dtype,
                             bias_prior_sigma=bias_prior_sigma(bias))
    prm = prm._replace(resample_threshold=None if thr >= 1.0 else thr, soft_alpha=float(options["soft_alpha"]))
    return fs1.validate_config(cfg), prm


def evaluate(fl: Flight001, res, landmarks, bias: float):
    """Per-run metrics of one flight (jit/vmap-safe); see the module docstring."""
    st = res.steps
    truth = fl.truth[1:]
    e_p = st.pose_mean[:, 0:3] - truth[:, 0:3]
    e_v = st.pose_mean[:, 3:6] - truth[:, 3:6]
    e_a = wrap_angle(st.pose_mean[:, 6:9] - truth[:, 6:9])

    def rms(e):
        return jnp.sqrt(jnp.mean(jnp.sum(e * e, axis=1)))

    fr = res.frames
    mu = fr.map_mean[-1]
    lm_err = jnp.sqrt(jnp.mean(jnp.sum((mu - landmarks) ** 2, axis=1)))
    b_hat = st.bias_mean[-1]
    b_true = fl.offset[-1]
    tot_hat = b_hat[0:6] + b_hat[6:12]
    tot_true = b_true[0:6] + b_true[6:12]
    b0_norm = abs(bias) * math.sqrt(3.0)
    nan = jnp.asarray(jnp.nan, truth.dtype)
    acc_err = jnp.linalg.norm(tot_hat[0:3] - tot_true[0:3])
    gyr_err = jnp.linalg.norm(tot_hat[3:6] - tot_true[3:6])
    deg = 180.0 / math.pi
    p = res.final.particles
    out = {
        "pos_rmse_m": rms(e_p),
        "vel_rmse_mps": rms(e_v),
        "att_rmse_deg": rms(e_a) * deg,
        "landmark_rmse_m": lm_err,
        "accel_bias_err": acc_err,
        "gyro_bias_err": gyr_err,
        "accel_bias_err_frac": acc_err / b0_norm if b0_norm > 0 else nan,
        "gyro_bias_err_frac": gyr_err / b0_norm if b0_norm > 0 else nan,
        "accel_b0_err": jnp.linalg.norm(b_hat[0:3] - b_true[0:3]),
        "gyro_b0_err": jnp.linalg.norm(b_hat[3:6] - b_true[3:6]),
        "neff_min": res.final.neff_min,
        "resamples": p.resamples.astype(truth.dtype),
    }
    counts = {
        "status": p.status,
        "overflow": p.overflow,
        "underflow": p.underflow,
        "non_finite": jnp.logical_not(jnp.all(jnp.isfinite(st.pose_mean))).astype(jnp.int32),
    }
    return out, counts


def _check_options(options):
    n = options["particles"]
    if isinstance(n, bool) or int(n) != n or int(n) <= 0:
        raise InputError(f"--particles: must be a positive integer, got {n!r}")
    b = float(options["bias"])
    if not (math.isfinite(b) and b >= 0):
        raise InputError(f"--bias: must be a finite value >= 0, got {b}")
    thr = float(options["resample_threshold"])
    if not (0.0 < thr <= 1.0):
        raise InputError(f"--resample-threshold: must be in (0, 1], got {thr}")
    a = float(options["soft_alpha"])
    if not (0.0 <= a <= 1.0):
        raise InputError(f"--soft-alpha: must be in [0, 1], got {a}")


def build(options: dict, dtype):
    """(one_run(key) -> (metrics, counts), flight(key) -> (Flight001, Result), cfg, prm, nf).

    ``options`` is completed and checked like the command line's options, ``dtype`` must be
    float32 or float64 (:func:`jaxslam.sim.scenarios.registry.check_options`).
    """
    options = _checked_args(SCENARIO, options, dtype)[0]
    _check_options(options)
    dtype = jnp.dtype(dtype)
    opts = dict(options)
    cfg, prm = make_filter(opts, dtype)
    setup = truth_setup(float(opts["bias"]), dtype)
    nf = int(round(float(opts["duration"]) / (DT * LIDAR_EVERY)))
    ids = jnp.arange(setup.landmarks.shape[0], dtype=jnp.int32)

    def flight(key, cfg=cfg):
        k_truth, k_filt = jax.random.split(key)
        fl = fly(setup, k_truth, nf, LIDAR_EVERY, cfg.lidar, cfg.accel_mode)
        log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor, imu=fl.imu, z=fl.z, ids=ids, mask=fl.mask)
        res = fs1.run(log, cfg, prm, key=k_filt)
        return fl, res

    def one_run(key, detail=False):
        # detail=True also returns the flight and the particle history (for the plots;
        # Monte Carlo keeps run 0's), from the program that computes the metrics.
        fl, res = flight(key, cfg._replace(save_particles=True) if detail else cfg)
        m, c = evaluate(fl, res, setup.landmarks, float(opts["bias"]))
        out = {"metrics": m, "counts": c}
        if detail:
            out["detail"] = {"flight": fl, "result": res}
        return out

    return one_run, flight, cfg, prm, nf, setup


def run_scenario(runs, seed, dtype, options, progress, params=None, plots=False):
    """``jaxslam run fastslam-helix`` (registry entry point)."""
    from ...errors import decode

    options, params = _checked_args(SCENARIO, options, dtype, params, plots)  # no --params schema: refused there
    one_run, flight, cfg, prm, nf, setup = build(options, dtype)
    # The particle set is vmapped inside a run; on a CPU a second vmap over runs gains nothing.
    mc = monte_carlo.run(lambda k: one_run(k, detail=plots), seed, runs, chunk=options.get("chunk"),
                         progress=progress, cpu_batching="loop", detail=plots,
                         program_key=program_key("fastslam-helix", options, params, dtype))
    out = mc.out
    counts = out["counts"]
    status_any = int(np.bitwise_or.reduce(np.asarray(counts["status"]).ravel()))
    flags = {
        "capacity_overflow": int(np.sum(counts["overflow"])),
        "masked_measurements": 0,
        "non_finite": int(np.sum(counts["non_finite"])),
        "weight_underflow": int(np.sum(counts["underflow"])),
    }

    def plot(directory):
        from ...plotting import fastslam as fp

        d = out["detail"]
        return fp.plot_all("fastslam-helix", d["flight"], d["result"], np.asarray(setup.landmarks),
                           directory)

    config = {
        "duration_s": float(options["duration"]),
        "duration_flown_s": _duration_flown(nf * LIDAR_EVERY, DT),  # whole LiDAR frames
        "dt_s": DT,
        "imu_rate_hz": 1.0 / DT,
        "lidar_rate_hz": 1.0 / (DT * LIDAR_EVERY),
        "landmarks_zup_m": np.asarray(setup.landmarks, float).tolist(),
        "filter": {k: v for k, v in cfg._asdict().items()},
        "filter_params": _params_json(prm),
        "filter_quad": {k: np.asarray(v, float).tolist() for k, v in prm.quad._asdict().items()},
        "threads": mc.threads,  # host threads that ran the flights (monte_carlo "loop")
        **options,
    }
    return ScenarioResult(
        config=config,
        metrics=out["metrics"],
        consistency=None,
        flags=flags,
        timing={"compile_s": mc.compile_s, "run_s": mc.run_s},
        interrupted=mc.interrupted,
        plot=plot if plots else None,
        extra={"status_flags": decode(status_any), "devices": mc.n_devices},
    )


OPTIONS = DECLARED["fastslam-helix"].options  # declared in builtin.py (read there without JAX)

SCENARIO = register(Scenario(
    name="fastslam-helix",
    description=DECLARED["fastslam-helix"].description,
    options=OPTIONS,
    run=lambda runs, seed, dtype, options, progress, params=None, plots=False: run_scenario(
        runs, seed, dtype, options, progress, params, plots),
))
