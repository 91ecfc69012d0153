"""Tuning target: paper 000's EKF-SLAM noise on recorded logs (``ekfslam3d-unknown|known --target noise``).

The process-noise density Q_c of the IMU-driven filter (optionally the LiDAR R, or the IMU
density Q_imu).  Training data are **recorded logs**: flights are simulated once (DF-LQR on
the truth, IMU and LiDAR noise drawn), then the loss runs
:func:`jaxslam.systems.ekf_slam_3d.run` — the filter alone, open loop, exactly what a user
does with a real log — and never differentiates the closed loop.  Held-out evaluation flies
the full closed-loop scenario (DF-LQR on the estimate) on seeds never used in training.

Decisions (no paper covers tuning):

* The tuned matrix is Q_c (Table 7's form, log-diagonal by default), started
  from Table 7 with Q_imu = 0 — "the paper's filter, re-tuned".  P0 is held at the
  ``--q imu`` value and R at Table 4 (unless ``tune_r``) in training and evaluation:
  the scenario draws each run's initial estimate from P0, so changing P0 would change the
  flights themselves, and the comparison with the ``--q imu`` reference would no longer be
  on equal flights.  The saved ``--params`` file holds P0, Q_c, Q_imu and R, so
  ``jaxslam run ekfslam3d-unknown --params TUNED.json`` reproduces the evaluation whatever ``--q``.
* Training logs are flown with the controller on the truth (a log does not depend on the
  filter being tuned) and may be shorter than the 50 s scenario; the first IMU sample of a
  log is the noise-free reading at the initial hover (what :func:`simulate` uses), and the
  initial estimate is drawn from P0.  Seeds: training runs use ``keys_for(seed, M)``, the
  held-out test runs ``keys_for(seed + 1, M)`` — the seeds of ``jaxslam run --seed seed+1``.
* NLL needs the joint innovation covariance of each frame: the engine's update reports its
  NIS, log det S and degrees of freedom (:class:`jaxslam.filters.ekf_slam.UpdateInfo`), from
  the prior and the estimator's own measurement selection, so nothing is formed twice; the
  NLL target uses known association and no gate (its ``Params`` carry none), so that the
  update's measurements are the log's.
* ``jax.checkpoint`` wraps the body of the outer (per LiDAR frame) scan (``Config.checkpoint``), so the backward
  pass stores one carry per frame and recomputes the ten inner steps: memory grows with the
  number of frames, not of IMU steps.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import InputError
from ...systems import ekf_slam_3d as sys3d
from .. import losses as L
from .. import params as P
from . import Target, DECLARED, _check_duration, _check_keywords, _fixed_mode, diag_list, keys, register_target

__all__ = ["STRUCTURES", "make_slam_logs", "slam_loss", "ekfslam3d_noise", "eval_command", "tie_imu_axes"]

STRUCTURES = ("qc", "imu", "imu_iso")  # what is tuned (see ekfslam3d_noise)


def _scenario_options(mode: str, **over) -> dict:
    from ...sim.scenarios import registry

    opts = {o.name: o.default for o in registry.get(f"ekfslam3d-{mode}").options}
    opts.update(over)
    return opts


_LOG_MAKERS: dict = {}


def _log_maker(n_landmarks: int, nf: int, dtype, altitude: float):
    """One jitted, vmapped flight recorder per static configuration (compiled once)."""
    from ...dynamics import euler_ned
    from ...sensors import imu as imu_mod
    from ...sensors import landmarks as lm_mod
    from ...sim.scenarios.tracking import FRAME_STEPS, make_setup, paper000_figure8
    from ...sim.simulate import simulate

    k = (n_landmarks, nf, jnp.dtype(dtype).name, float(altitude))
    if k in _LOG_MAKERS:
        return _LOG_MAKERS[k]
    traj = paper000_figure8(altitude, 0.0)
    center = np.asarray(traj.center, float)

    def one(key, sqrtP0):
        k_lm, k_fl, k_e = jax.random.split(key, 3)
        lms = lm_mod.generate_landmarks(k_lm, n_landmarks, center=center, dtype=dtype)
        setup = make_setup(traj, dtype, landmarks=lms)
        fl = simulate(setup, k_fl, nf, FRAME_STEPS, feedforward=True)
        quad = setup.ctrl.quad
        x0 = setup.x0
        imu0 = imu_mod.imu_ideal(x0, euler_ned.f(x0, euler_ned.hover_input(quad, dtype), quad), quad.g)
        s0 = x0[:9] + sqrtP0 @ jax.random.normal(k_e, (9,), dtype)
        return sys3d.Log(s0=s0, imu=jnp.concatenate([imu0[None].astype(dtype), fl.imu]), y=fl.lidar_y,
                       visible=fl.lidar_mask, ids=jnp.arange(n_landmarks, dtype=jnp.int32),
                       truth=fl.truth, landmarks=lms)

    _LOG_MAKERS[k] = jax.jit(jax.vmap(one, in_axes=(0, None)))
    return _LOG_MAKERS[k]


def make_slam_logs(seed: int, runs: int, duration: float, n_landmarks: int = 40, P0=None,
                   dtype=jnp.float64, altitude: float = 3.0):
    """Simulate ``runs`` flights of the paper-000 figure-8 once and return their logs.

    Flights as in the ``ekfslam3d`` scenarios (40 Table 3 landmarks per run, Table 4/5
    sensors, 100 Hz IMU, 10 Hz LiDAR) with the DF-LQR on the truth.  Run i uses
    ``keys_for(seed, runs)[i]`` split into (landmarks, flight, initial error); the initial
    estimate is the true start plus an error drawn from ``P0`` (9, 9), finite symmetric PSD
    (default: the ``--q imu`` P0); ``duration`` a number of seconds >= 0.1 (else InputError
    naming ``P0`` / ``duration``).  Returns a :class:`jaxslam.systems.ekf_slam_3d.Log` batch (leading axis
    runs, with the true states and landmarks) in ``dtype``.
    """
    if int(runs) < 1:
        raise InputError(f"runs: must be >= 1, got {runs}")
    return _logs(keys(seed, runs), duration, n_landmarks, P0, dtype, altitude)


def _logs(ks, duration, n_landmarks, P0, dtype, altitude):
    """The logs of the runs keyed by ``ks`` (runs, ...) in one call of the vmapped recorder."""
    from ...linalg import check_numbers, check_psd, check_shape
    from ...sim.scenarios.tracking import FRAME_STEPS
    from ...sim.simulate import n_frames

    if isinstance(duration, (bool, np.bool_)) or not isinstance(duration, (int, float, np.integer, np.floating)):
        raise InputError(f"duration: expected a number of seconds, got {duration!r}"[:300])  # was a bare TypeError
    if not (duration >= 0.1 and math.isfinite(duration)):
        raise InputError(f"duration: must be at least 0.1 s, got {duration}")

    if P0 is None:
        P0 = np.diag(sys3d.IMU_P0)
    else:  # a negative-definite P0 was clipped to 0 (the start was the truth), a (3, 3) a bare TypeError
        P0 = check_shape(check_numbers(P0, "P0"), (sys3d.NX, sys3d.NX), "P0")
        check_psd(P0, "P0")
    w, V = np.linalg.eigh(0.5 * (P0 + P0.T))
    sqrtP0 = jnp.asarray(V * np.sqrt(np.clip(w, 0, None)), dtype)
    nf = n_frames(duration, 0.01, FRAME_STEPS)
    return _log_maker(int(n_landmarks), nf, jnp.dtype(dtype), altitude)(ks, sqrtP0)


def eval_command(mode: str, runs: int, seed: int, duration: float) -> str:
    """The ``jaxslam run ekfslam3d-{mode}`` command that flies a target's held-out 'after' row."""
    return (f"jaxslam run ekfslam3d-{mode} --runs {runs} --seed {seed}"
            f"{'' if duration == 50.0 else f' --duration {duration:g}'} --params TUNED.json")


def slam_loss(res, log, loss: str, weights=None):
    """Per-run loss of a :class:`jaxslam.systems.ekf_slam_3d.Result` on ``log``: ``"nll"`` (the
    frames' innovation likelihood), ``"mse"`` (robot error against ``log.truth``) or ``"nees"``
    (the frames' robot NEES: the run needs ``log.truth``)."""
    if loss == "nll":
        return L.innovation_nll(res.frames.nis, res.frames.logdet, res.frames.dof.astype(res.means.dtype))
    if loss == "mse":
        err = jax.vmap(sys3d.robot_error)(res.means, log.truth[1:])
        return L.mse(err, weights)
    if loss == "nees":
        return L.nees_loss(res.frames.nees, sys3d.NX)
    raise InputError(f"loss: expected 'nll', 'mse' or 'nees', got {loss!r}")


def tie_imu_axes(m: dict) -> dict:
    """``m`` (unpacked parameters) with a per-sensor ``Qimu_sensor`` (2, 2) — [accelerometer,
    gyro] densities — replaced by the 6×6 ``Qimu`` that repeats each on its three axes (the
    ``imu_iso`` structure, Table 5's form); unchanged without it.  Shared by the noise and loop
    targets."""
    if "Qimu_sensor" in m:
        m["Qimu"] = jnp.diag(jnp.repeat(jnp.diag(m.pop("Qimu_sensor")), 3))
    return m


def ekfslam3d_noise(loss: str = "nll", train_runs: int = 4, test_runs: int = 8, seed: int = 0,
                    dtype=jnp.float64, mode: str = "unknown", train_duration: float = 10.0,
                    eval_duration: float = 50.0, capacity: int | None = None, tune_r: bool = False,
                    cov: str = "diag", start: str = "paper", mse_weights=None,
                    checkpoint: bool = True, eval_chunk: int | None = None, structure: str = "qc",
                    **_ignored) -> Target:
    """Target: Q_c (and optionally R) of paper 000's EKF-SLAM, tuned on recorded logs.

    ``structure``: ``"qc"`` tunes the 9×9 process-noise density Q_c directly (Table 7's form,
    Q_imu = 0); ``"imu"`` tunes the 6×6 IMU density Q_imu that enters through the filter's own
    G Q_imu Gᵀ (paper 000 eq. 27 with the IMU as the noise input; Q_c = 0): the structure says
    that position is the integral of velocity and the noise enters through the IMU, leaving 6
    parameters.  With ``start="paper"`` it starts from Table 7's velocity and attitude entries
    (0.01 m²/s³ ×3, then 0.02, 0.2, 0.2 rad²/s) read as accelerometer and gyro densities.
    ``"imu_iso"``: the same with one density per sensor (Table 5's form, 2 parameters: the
    three axes of a sensor share it), started from the means of those Table 7 entries.
    ``start``: ``"paper"`` (Table 6/7, as above) or ``"imu"`` (the IMU-derived Q, projected
    on Q_c's diagonal for ``structure="qc"``).  ``cov``: ``"diag"`` (log-diagonal) or ``"chol"``
    (log-Cholesky, full matrix).  ``capacity``: landmark slots of the training filter, an int
    >= 1 (default: the number of landmarks, 40, which cannot overflow; estimates do not depend
    on the capacity).  ``mse_weights``: the ``mse`` loss's weights of the 9 state components
    (a number or 9 non-negative numbers; default ones); with another loss they would be
    ignored and are refused.  Evaluation: the ``ekfslam3d-{mode}`` scenario, ``eval_duration``
    seconds (checked before the training logs are simulated), ``test_runs`` seeds from
    ``seed + 1``, ``eval_chunk`` (an int >= 1, default all) of them per call.  See the module docstring.
    """
    _check_keywords(_ignored, "ekfslam3d --target noise")
    from ...linalg import check_float_dtype, check_int, check_numbers
    from ...sensors import imu as imu_mod
    from ...sim.scenarios import ekfslam3d as scen
    from ...sim.scenarios.tracking import DT, FRAME_STEPS

    dtype = check_float_dtype(dtype)
    if mode not in ("unknown", "known"):
        raise InputError(f"mode: expected 'unknown' or 'known', got {mode!r}")
    # checked before the training logs are simulated (it was caught only after, naming --duration);
    # train_duration is checked by _logs before anything is simulated
    _check_duration(eval_duration, "--eval-duration", DT * FRAME_STEPS)
    if eval_chunk is not None:  # 'x' failed only at evaluate, after the fit; 2.5 ran as 2
        eval_chunk = check_int(eval_chunk, "eval_chunk", lower=1, what="a number of runs per evaluation call (int)")
    if cov not in P.KINDS:
        raise InputError(f"--cov: expected one of {P.KINDS}, got {cov!r}")
    if loss not in ("nll", "mse", "nees"):
        raise InputError(f"--loss: expected nll, mse or nees, got {loss!r}")
    if start not in ("paper", "imu"):
        raise InputError(f"start: expected 'paper' or 'imu', got {start!r}")
    if structure not in STRUCTURES:
        raise InputError(f"--structure: expected one of {STRUCTURES}, got {structure!r}")
    if structure == "imu_iso" and cov != "diag":
        raise InputError("--structure imu_iso: two densities (accelerometer, gyro); use --cov diag")
    if capacity is not None:  # 0 built and failed only when traced, naming config.capacity
        capacity = check_int(capacity, "capacity", lower=1, what="a number of landmark slots (int)")
    if mse_weights is not None:  # checked before the simulation, not at the first trace
        if loss != "mse":
            raise InputError(f"mse_weights: only the mse loss reads them (it would be ignored), got loss {loss!r}")
        mw = check_numbers(mse_weights, "mse_weights")
        if mw.shape not in ((), (sys3d.NX,)) or not np.all(np.isfinite(mw)) or np.any(mw < 0):
            raise InputError(f"mse_weights: expected a number or {sys3d.NX} finite non-negative numbers (one per "
                             f"state component), got {mse_weights!r}"[:300])
    ref = sys3d.imu_noise(imu_mod.PAPER000_IMU, dtype)
    nda2 = float(imu_mod.PAPER000_IMU.accel_noise_density) ** 2
    ndg2 = float(imu_mod.PAPER000_IMU.gyro_noise_density) ** 2
    Qc_paper = np.asarray(sys3d.paper_noise(mode, dtype).Qc)
    if structure == "qc":
        name, n = "Qc", sys3d.NX
        M0 = Qc_paper if start == "paper" else np.diag([1e-12] * 3 + [nda2] * 3 + [ndg2] * 3)
    elif structure == "imu":
        name, n = "Qimu", 6
        M0 = np.diag(np.diag(Qc_paper)[3:]) if start == "paper" else np.asarray(ref.Qimu)
    else:  # one density per sensor, the form of Table 5: [accelerometer, gyro]
        name, n = "Qimu_sensor", 2
        q7 = np.diag(Qc_paper)
        M0 = np.diag([np.mean(q7[3:6]), np.mean(q7[6:9])] if start == "paper" else [nda2, ndg2])
    specs = {name: P.CovSpec(cov, n)}
    mats = {name: M0}
    if tune_r:
        specs["R"] = P.CovSpec(cov, 3)
        mats["R"] = np.asarray(ref.R)
    theta0 = P.pack(specs, mats, dtype=dtype)
    n_lm = scen.N_LANDMARKS
    cap = n_lm if capacity is None else int(capacity)
    # active_only off: a gradient through vmapped runs gains nothing from it (the derivative of
    # the tiled correction is the dense one) and its branches doubled the step's compile
    # (measured: 7.05 -> 17.6 s)
    cfg = sys3d.Config(mode=mode, capacity=cap, dt=DT, g=9.81, checkpoint=bool(checkpoint),
                       active_only=False)
    if mode == "known" and cap < n_lm:
        raise InputError(f"capacity: {cap} slots cannot hold the {n_lm} known landmarks")

    def physical(theta):
        m = P.unpack(specs, theta)
        tie_imu_axes(m)
        return sys3d.Params(P0=ref.P0.astype(dtype), Qc=m.get("Qc", jnp.zeros((sys3d.NX, sys3d.NX), dtype)),
                                 Qimu=m.get("Qimu", jnp.zeros((6, 6), dtype)), R=m.get("R", ref.R.astype(dtype)))

    w = None if mse_weights is None else jnp.asarray(mse_weights, dtype)

    def loss_fn(theta, log):
        # the frames' NEES (a Cholesky each) only when the loss reads it
        res = sys3d.run(log if loss == "nees" else log._replace(truth=None), cfg, physical(theta))
        return slam_loss(res, log, loss, w)

    # Training and held-out logs from one call of the recorder (one program, not one per batch size).
    if int(train_runs) < 1 or int(test_runs) < 1:
        raise InputError(f"runs: --train-runs and --test-runs must be >= 1, got {train_runs}, {test_runs}")
    both = _logs(np.concatenate([keys(seed, train_runs), keys(seed + 1, test_runs)]), train_duration, n_lm,
                 np.asarray(ref.P0), dtype, 3.0)
    both = jax.tree.map(np.asarray, both)  # split on the host: slicing device arrays compiles per leaf
    train = jax.tree.map(lambda a: jax.device_put(a[:train_runs]), both)
    test = jax.tree.map(lambda a: jax.device_put(a[train_runs:]), both)

    opts = _scenario_options(mode, duration=float(eval_duration))
    one_run, _, ecfg, _, nf = scen.build(opts, mode, dtype)
    test_seed = seed + 1

    fn = jax.jit(jax.vmap(one_run, in_axes=(0, None)))  # compiled on the first evaluate, then reused

    def evaluate(physicals: dict) -> dict:
        ks = keys(test_seed, test_runs)
        chunk = test_runs if eval_chunk is None else max(1, min(int(eval_chunk), test_runs))
        t_frames = (np.arange(nf) + 1) * DT * FRAME_STEPS
        res = {}
        for label, noise in physicals.items():
            noise = jax.tree.map(lambda a: jnp.asarray(a, dtype), noise)
            outs = [jax.tree.map(np.asarray, fn(ks[i:i + chunk], noise))
                    for i in range(0, test_runs, chunk)]
            out = jax.tree.map(lambda *a: np.concatenate(a, 0), *outs)
            cons, _ = scen.consistency(out["series"], t_frames, test_runs)
            res[label] = {"metrics": out["metrics"],
                          "consistency": {**{k: cons[k] for k in ("anees", "anees_bounds", "nis_mean",
                                                                  "nis_bounds", "anees_fraction_in_bounds")},
                                          **scen.CONSISTENCY_BLOCKS}}
        return res

    def to_params(noise):
        return {"noise": sys3d.params_to_dict(noise)}

    def describe(theta):
        m = P.unpack(specs, theta)
        return {k: diag_list(v) for k, v in m.items()}

    config = {"mode": mode, "train_duration_s": float(train_duration), "eval_duration_s": float(eval_duration),
              "train_seed": int(seed), "test_seed": int(test_seed), "train_runs": int(train_runs),
              "test_runs": int(test_runs), "capacity_train": cap, "cov": cov, "tune_r": bool(tune_r),
              "start": start, "structure": structure, "checkpoint": bool(checkpoint), "dtype": dtype.name,
              "mse_weights": None if mse_weights is None else (float(mw) if mw.ndim == 0 else [float(v) for v in mw]),
              "fixed": {"P0": "--q imu P0 (diag 1e-4 x6, (0.1 deg)^2 x3)",
                        **({"Qimu": "0"} if structure == "qc" else {"Qc": "0"}),
                        **({} if tune_r else {"R": "Table 4"})},
              "logs": "simulated once, DF-LQR on the truth; filter run open loop on the logs",
              "evaluation": f"ekfslam3d-{mode} scenario (closed loop, DF-LQR on the estimate), "
                            f"{eval_duration:g} s, seeds keys_for({test_seed}, {test_runs})"}
    cmd = eval_command(mode, test_runs, test_seed, eval_duration)
    return Target(scenario=f"ekfslam3d-{mode}", target="noise", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={"q_imu": ref}, to_params=to_params, describe=describe, config=config,
                  eval_command=cmd, log_objective=loss == "mse", sequential=True)


for _m in ("unknown", "known"):
    register_target(f"ekfslam3d-{_m}", "noise", _fixed_mode(ekfslam3d_noise, _m, "noise"),
                    DECLARED[(f"ekfslam3d-{_m}", "noise")])
