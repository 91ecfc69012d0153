"""Tuning target: the closed loop with the estimator in it (``ekfslam3d-unknown|known --target loop``).

The DF-LQR weights Q̃, R̃ (paper 000 Table 2), the filter's IMU noise density Q_imu, or both,
by the gradient of a closed-loop objective through the whole flight: truth dynamics, IMU and
LiDAR, the EKF-SLAM estimator and the DF-LQR acting on its estimate (``control_on="estimate"``,
what ``jaxslam run ekfslam3d-*`` flies).  ``track-figure8 --target lqr`` tunes the weights with
the controller on the truth; here the controller sees what the filter believes, so the weights
and the noise interact.

Decisions (no paper covers this):

* **Pathwise gradient.**  Every random draw (landmarks, IMU and LiDAR noise, the initial
  estimate) comes from the run's key and does not depend on θ, so the gradient of a run's
  objective is the derivative of one fixed flight; the mean over vmapped seeds estimates the
  gradient of the expected objective.  What the derivative cannot see: which landmarks are
  visible (the field of view is a hard edge) and the per-frame compaction of the sightings —
  discrete choices, held fixed at their values on the flight.
* **Objective per run**, all terms with fixed weights (not tuned):
  J = mean_t ‖ρ − ρ_d‖² + w_u mean_t ‖ũ‖² + w_tilt mean_t max(0, tilt − tilt_max)²
  + w_mse mean_t ‖ρ̂ − ρ‖² + w_nees (log(ANEES / 9))².
  ũ is the LQR correction recomputed from the flown true states (the yardstick of
  ``track-figure8 --target lqr``, so both sets of weights are scored alike); the tilt term is a
  soft constraint (default: above 12°, w_tilt = 10 per rad²); the MSE and NEES terms are off by
  default (``--w-mse``, ``--w-nees``): the NEES term keeps a tuning of the noise from buying
  accuracy with over-confidence.
* **What is tuned** (``tune``): ``"lqr"`` (Q̃ 7, R̃ 4 log-diagonal from Table 2), ``"noise"``
  (Q_imu 6 log-diagonal from the ``--q imu`` densities; P0, R and Q_c = 0 held), ``"both"``.
  ``structure`` shapes Q_imu as the noise target's does: ``"imu"`` (one density per axis, 6) or
  ``"imu_iso"`` (one per sensor, accelerometer and gyro, Table 5's form, 2).
* **Runs.**  Training flights use ``keys_for(seed, M)``, held-out flights ``keys_for(seed + 1,
  M)``: the flights (landmarks and noise) of ``jaxslam run ekfslam3d-{mode} --seed seed+1``.
  Training flights may be shorter than the 50 s evaluation (``--duration``, default 10 s).
  ``jax.checkpoint`` per LiDAR frame bounds the gradient's memory; the training flights run one
  after another (``lax.map``).
* **Evaluation** (held out, estimator in the loop, ``eval_duration`` s): the start, the result,
  the ``--q imu`` filter with Table 2's weights, with ``tune="both"`` the result's weights flown
  with the ``--q imu`` filter (``after_weights_q_imu``: what the tuned controller's flights do
  to the estimator, apart from the tuned noise), and, with ``compare``, a controller read from a
  file (e.g. the truth-tuned weights of ``jaxslam tune track-figure8 --target lqr``), each with
  the closed-loop cost, its terms, peak tilt, the estimator's RMSE and ANEES with χ² bounds.
"""

from __future__ import annotations

import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from ... import runtime
from ...errors import InputError
from ...linalg import check_float_dtype, check_scalar, safe_norm
from .. import losses as L
from .. import params as P
from . import Target, DECLARED, _check_duration, _check_keywords, _fixed_mode, diag_list, keys, register_target
from .ekfslam3d import eval_command, tie_imu_axes

__all__ = ["STRUCTURES", "TUNE", "closed_loop_objective", "controller_file", "ekfslam3d_loop", "tilt_angle"]

TUNE = ("lqr", "noise", "both")
STRUCTURES = ("imu", "imu_iso")  # Q_imu per axis or per sensor (the noise target's names)


def tilt_angle(phi, theta):
    """Angle between the body z axis and the vertical, arccos(cos φ cos θ) [rad], written with a
    norm whose gradient stays finite at level flight (where arccos' derivative is infinite)."""
    s_t = safe_norm(jnp.stack([jnp.sin(phi), jnp.cos(phi) * jnp.sin(theta)], axis=-1))
    return jnp.arctan2(s_t, jnp.cos(phi) * jnp.cos(theta))


def closed_loop_objective(fl, ctrl, traj, K, feedforward: bool, w: dict, refs=None):
    """The terms of the per-run objective (module docstring) of one flight ``fl`` flown with
    the estimator in the loop.  ``w``: weights ``w_u``, ``w_tilt``, ``tilt_max_rad``, ``w_mse``,
    ``w_nees``; ``refs``: the flight's reference grid, if at hand.  Returns a dict of scalars with
    ``objective`` (J) and its terms."""
    from ...systems import ekf_slam_3d as sys3d
    from .figure8 import tracking_and_effort

    dtype = fl.truth.dtype
    track, effort = tracking_and_effort(fl, ctrl, traj, K, feedforward, refs)
    phi, theta = fl.truth[1:, 6], fl.truth[1:, 7]
    tilt = tilt_angle(phi, theta)
    over = jnp.maximum(tilt - jnp.asarray(w["tilt_max_rad"], dtype), 0.0)
    tilt_pen = jnp.mean(over * over)
    err = jax.vmap(sys3d.robot_error)(fl.est_steps.mean, fl.truth[1:])
    mse = jnp.mean(jnp.sum(err[:, :3] ** 2, axis=1))
    nees_term = L.nees_loss(fl.est_frames.nees, sys3d.NX)
    J = (track + jnp.asarray(w["w_u"], dtype) * effort + jnp.asarray(w["w_tilt"], dtype) * tilt_pen
         + jnp.asarray(w["w_mse"], dtype) * mse + jnp.asarray(w["w_nees"], dtype) * nees_term)
    return {"objective": J, "closed_loop_cost": track + jnp.asarray(w["w_u"], dtype) * effort,
            "tracking_ms_m2": track, "effort_ms": effort, "tilt_penalty": tilt_pen,
            "est_pos_ms_m2": mse, "nees_term": nees_term}


def controller_file(path, default):
    """The DF-LQR weights of a ``--params`` file or a whole ``jaxslam tune`` report."""
    from ... import paramfile
    from ...sim.scenarios.tracking import controller_from_dict

    obj = paramfile.load(path, name="--compare")
    if "params_after" in obj:
        obj = obj["params_after"]
    if not isinstance(obj, dict) or not isinstance(obj.get("controller"), dict):
        raise InputError(f"--compare: {str(path)!r} has no 'controller' section (a --params file or a "
                         "'jaxslam tune ... --target lqr' report)")
    return controller_from_dict(obj["controller"], default)


def ekfslam3d_loop(loss: str = "cost", train_runs: int = 4, test_runs: int = 16, seed: int = 0,
                   dtype=jnp.float64, mode: str = "unknown", train_duration: float = 10.0,
                   eval_duration: float = 50.0, tune: str = "lqr", w_u: float = 0.1,
                   w_tilt: float = 10.0, tilt_max_deg: float = 12.0, w_mse: float = 0.0,
                   w_nees: float = 0.0, compare=None, checkpoint: bool = True,
                   feedforward: bool = True, structure: str = "imu", **_ignored) -> Target:
    """Target: DF-LQR weights and/or the filter's Q_imu through the closed loop with the
    EKF-SLAM estimator in it (module docstring).  ``loss`` is ``"cost"`` (the objective J with
    the given weights); ``tune`` one of :data:`TUNE`; ``structure`` one of :data:`STRUCTURES`
    (Q_imu's form); ``compare``: a file whose controller is evaluated beside the start and the
    result.  ``dtype``, the durations, ``tilt_max_deg`` and ``seed`` are checked before anything
    is compiled (InputError naming each)."""
    _check_keywords(_ignored, "ekfslam3d --target loop")
    from ...control import dflqr
    from ...sensors import imu as imu_mod
    from ...sensors import landmarks as lm_mod
    from ...sim.scenarios import ekfslam3d as scen
    from ...sim.scenarios import registry
    from ...sim.scenarios.tracking import DT, FRAME_STEPS, controller_to_dict, make_setup, paper000_figure8
    from ...sim.simulate import controls, n_frames, simulate
    from ...systems import ekf_slam_3d as sys3d

    dtype = check_float_dtype(dtype)
    if loss != "cost":
        raise InputError(f"--loss: the loop target uses the closed-loop objective ('cost'), got {loss!r}")
    if mode not in ("unknown", "known"):
        raise InputError(f"mode: expected 'unknown' or 'known', got {mode!r}")
    if tune not in TUNE:
        raise InputError(f"--tune: expected one of {', '.join(TUNE)}, got {tune!r}")
    if structure not in STRUCTURES:
        raise InputError(f"--structure: the loop target tunes the IMU density Q_imu, one of "
                         f"{', '.join(STRUCTURES)}; got {structure!r}")
    if structure != "imu" and tune == "lqr":
        raise InputError(f"--structure {structure}: shapes the noise, so it needs --tune noise or both")
    for name, v in (("--w-u", w_u), ("--w-tilt", w_tilt), ("--w-mse", w_mse), ("--w-nees", w_nees)):
        check_scalar(v, name, lower=0)
    real = isinstance(tilt_max_deg, (int, float, np.integer, np.floating)) and not isinstance(tilt_max_deg, bool)
    if not (real and 0 < tilt_max_deg < 90):  # a string was a bare TypeError
        raise InputError(f"--tilt-max: expected (0, 90) degrees, got {tilt_max_deg}")
    for name, v in (("--duration", train_duration), ("--eval-duration", eval_duration)):
        _check_duration(v, name, DT * FRAME_STEPS)  # a string or None was a bare TypeError
    if int(train_runs) < 1 or int(test_runs) < 1:
        raise InputError(f"runs: --train-runs and --test-runs must be >= 1, got {train_runs}, {test_runs}")
    train = keys(seed, train_runs)  # a bad seed is refused here, not after the references compile
    test = keys(seed + 1, test_runs)

    base = dflqr.paper000_params()
    cmp_ctrl = None if compare is None else controller_file(compare, base)
    ref_noise = sys3d.imu_noise(imu_mod.PAPER000_IMU, dtype)
    opts = {o.name: o.default for o in registry.get(f"ekfslam3d-{mode}").options}
    n_lm = int(opts["landmarks"])
    cfg = sys3d.Config(mode=mode, association=opts["association"], capacity=int(opts["capacity"]),
                       max_obs=int(opts["max_obs"]), accel_mode=opts["accel"], dt=DT, g=float(base.quad.g),
                       save_map=False, active_only=False)  # a gradient: see targets.ekfslam3d
    traj = paper000_figure8(float(opts["altitude"]), 0.0)
    center = np.asarray(traj.center, float)
    nf_train = n_frames(train_duration, DT, FRAME_STEPS)
    nf_eval = n_frames(eval_duration, DT, FRAME_STEPS)
    w = {"w_u": float(w_u), "w_tilt": float(w_tilt), "tilt_max_rad": math.radians(tilt_max_deg),
         "w_mse": float(w_mse), "w_nees": float(w_nees)}

    specs, mats = {}, {}
    if tune in ("lqr", "both"):
        specs.update(Q=P.CovSpec("diag", 7), R=P.CovSpec("diag", 4))
        mats.update(Q=np.asarray(base.Q), R=np.asarray(base.R))
    if tune in ("noise", "both") and structure == "imu":
        specs["Qimu"] = P.CovSpec("diag", 6)
        mats["Qimu"] = np.asarray(ref_noise.Qimu)
    elif tune in ("noise", "both"):  # [accelerometer, gyro] densities, each shared by its 3 axes
        specs["Qimu_sensor"] = P.CovSpec("diag", 2)
        mats["Qimu_sensor"] = np.diag(np.diag(np.asarray(ref_noise.Qimu))[[0, 3]])
    theta0 = P.pack(specs, mats, dtype=dtype)

    def physical(theta):
        m = tie_imu_axes(P.unpack(specs, theta))
        ctrl = base._replace(Q=m["Q"], R=m["R"]) if "Q" in m else base
        noise = ref_noise._replace(Qimu=m["Qimu"]) if "Qimu" in m else ref_noise
        return ctrl, noise

    # The reference depends on time and the quadcopter only, not on Q̃, R̃ or the noise: one small
    # program per duration, outside the differentiated flight (whose compile it would otherwise
    # carry, with the trajectory's nested derivatives).
    refs_for = {nf: controls(make_setup(traj, dtype, ctrl=base), nf * FRAME_STEPS, feedforward,
                             compiler_options=runtime.compiler_options())[1] for nf in {nf_train, nf_eval}}

    def fly(ctrl, noise, key, nf, ck):
        k_lm, k_fl = jax.random.split(key)  # the split of the ekfslam3d scenario's flights
        lms = lm_mod.generate_landmarks(k_lm, n_lm, center=center, dtype=dtype)
        setup = make_setup(traj, dtype, landmarks=lms, ctrl=ctrl)
        K = dflqr.gain(ctrl, dtype)
        est = sys3d.make_estimator(cfg, noise, landmarks_true=lms)
        fl = simulate(setup, k_fl, nf, FRAME_STEPS, estimator=est, control_on="estimate", K=K,
                      feedforward=feedforward, refs=refs_for[nf], checkpoint=ck)
        return fl, lms, K

    def loss_fn(theta, key):
        ctrl, noise = physical(theta)
        fl, _, K = fly(ctrl, noise, key, nf_train, checkpoint)
        return closed_loop_objective(fl, ctrl, traj, K, feedforward, w, refs_for[nf_train])["objective"]

    @jax.jit
    def _eval(ctrl, noise, ks):
        def one(k):
            fl, lms, K = fly(ctrl, noise, k, nf_eval, False)
            out = scen.evaluate(fl, lms, cfg)
            terms = closed_loop_objective(fl, ctrl, traj, K, feedforward, w, refs_for[nf_eval])
            return {"metrics": {**out["metrics"], **terms}, "series": out["series"],
                    "non_finite": out["counts"]["non_finite"]}

        return jax.vmap(one)(ks)

    t_frames = (np.arange(nf_eval) + 1) * DT * FRAME_STEPS

    def evaluate(physicals: dict) -> dict:
        res = {}
        for label, (ctrl, noise) in physicals.items():
            # Q̃, R̃ as arrays first (Table 2's are nested tuples): one program for every row
            ctrl = ctrl._replace(Q=jnp.asarray(ctrl.Q, dtype), R=jnp.asarray(ctrl.R, dtype))
            ctrl = jax.tree.map(lambda a: jnp.asarray(a, dtype), ctrl)
            noise = jax.tree.map(lambda a: jnp.asarray(a, dtype), noise)
            out = jax.tree.map(np.asarray, _eval(ctrl, noise, test))
            cons, _ = scen.consistency(out["series"], t_frames, test_runs)
            metrics = dict(out["metrics"])
            metrics["diverged_flights"] = np.asarray(out["non_finite"], float)
            res[label] = {"metrics": metrics,
                          "consistency": {k: cons[k] for k in ("anees", "anees_bounds", "nis_mean", "nis_bounds",
                                                               "anees_fraction_in_bounds")}}
        return res

    def to_params(phys):  # both sections, so `jaxslam run --params` flies exactly what was evaluated
        ctrl, noise = phys
        return {"controller": {k: v for k, v in controller_to_dict(ctrl).items() if k in ("Q", "R")},
                "noise": sys3d.params_to_dict(noise)}

    def describe(theta):
        return {k: diag_list(v) for k, v in P.unpack(specs, theta).items()}

    references = {"q_imu_table2": (base, ref_noise)}
    if cmp_ctrl is not None:
        references["compare"] = (cmp_ctrl, ref_noise)

    def after_references(phys):  # --tune both: the tuned weights flown with the --q imu filter
        return {"after_weights_q_imu": (phys[0], ref_noise)} if tune == "both" else {}

    config = {"mode": mode, "tune": tune, **({} if tune == "lqr" else {"structure": structure}),
              "train_duration_s": float(train_duration),
              "eval_duration_s": float(eval_duration), "train_seed": int(seed), "test_seed": int(seed + 1),
              "train_runs": int(train_runs), "test_runs": int(test_runs), "weights": dict(w, tilt_max_deg=tilt_max_deg),
              "checkpoint": bool(checkpoint), "feedforward": bool(feedforward), "dtype": dtype.name,
              "compare": None if compare is None else pathlib.Path(compare).name,  # no machine path
              "objective": "mean|rho - rho_d|^2 + w_u mean|u_tilde|^2 + w_tilt mean max(0, tilt - tilt_max)^2 "
                           "+ w_mse mean|rho_hat - rho|^2 + w_nees log(ANEES/9)^2",
              "fixed": {"P0": "--q imu P0", "R": "Table 4", "Qc": "0",
                        **({} if tune != "noise" else {"controller": "Table 2"}),
                        **({} if tune != "lqr" else {"Qimu": "--q imu (Table 5 densities)"})},
              "evaluation": f"ekfslam3d-{mode} flights (DF-LQR on the estimate), {eval_duration:g} s, "
                            f"seeds keys_for({seed + 1}, {test_runs})"}
    cmd = eval_command(mode, test_runs, seed + 1, eval_duration)
    return Target(scenario=f"ekfslam3d-{mode}", target="loop", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references=references, to_params=to_params, describe=describe, config=config,
                  eval_command=cmd, log_objective=True, sequential=True, after_references=after_references)


for _m in ("unknown", "known"):
    register_target(f"ekfslam3d-{_m}", "loop", _fixed_mode(ekfslam3d_loop, _m, "loop"),
                    DECLARED[(f"ekfslam3d-{_m}", "loop")])
