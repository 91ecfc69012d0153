"""Scenarios ``ekfslam3d-unknown`` and ``ekfslam3d-known`` (paper 000, Sec. 3).

The 50 s figure-8 of ``track-figure8`` flown with the DF-LQR acting on the
EKF estimate (``--control-on estimate``, the paper's setting) or on truth;
40 landmarks of Table 3 drawn per run around the figure-8 centre; IMU at
100 Hz with Table 5's densities, LiDAR at 10 Hz with Table 4's FOV and noise.

Metrics (all per run; ``_axis`` = mean of the three per-axis RMSEs, plain =
RMSE of the 3D error norm, √(mean_t ‖e‖²) — the paper does not say which it
uses; both are reported):

* ``pos_rmse_m``, ``vel_rmse_mps`` (body-frame velocity, the filter's state),
  ``att_rmse_deg`` (Euler angles, wrapped) over the whole flight at 100 Hz, as
  the paper computes it, and ``*_settled`` over t > 10 s;
* ``landmark_rmse_m``: RMS over the landmarks mapped at the end of ‖l̂ − l‖
  (with hidden ids: each estimate against its nearest true landmark), and
  ``landmark_rmse_axis_m`` the mean of its per-axis RMSEs (unknown mode only; both NaN
  when no landmark is mapped);
* ``landmarks_mapped``; ``track_pos_rmse_settled_m`` (true vs desired path);
* consistency: ANEES of the robot block (average NEES over runs, expected 9)
  at every LiDAR frame (10 Hz, after the update) with two-sided 95 % χ² bounds
  for N runs at one time, averaged over the flight and per 10 s window
  (``consistency_detail.anees_windows``), the fraction of frames whose
  run-average lies inside the bounds, and the normalised mean NIS
  Σ NIS / Σ dof with its χ² bounds.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np

from ... import metrics as mx
from ... import runtime
from ...control import dflqr
from ...errors import InputError
from ...sensors import imu as imu_mod
from ...sensors import landmarks as lm_mod
from ...systems import ekf_slam_3d as sys3d
from .. import monte_carlo
from ..simulate import controls, n_frames, simulate
from .builtin import DECLARED
from .registry import (Scenario, ScenarioResult, _checked_args, _duration_flown, program_key,
                       register)
from .tracking import (DT, FRAME_STEPS, SETTLED_AFTER_S, controller_from_dict, controller_to_dict,
                       make_setup, paper000_figure8, tracking_metrics)

# Table 3: 40, the default of --landmarks (read from the declaration, so the two cannot drift)
N_LANDMARKS = next(o.default for o in DECLARED["ekfslam3d-known"].options if o.name == "landmarks")
WINDOW_S = 10.0
# What each statistic of ``consistency`` covers (docs/cli.md, "consistency"): the NEES is of the
# 9-state robot block, the NIS of every LiDAR row, normalised per degree of freedom.
CONSISTENCY_BLOCKS = sys3d.CONSISTENCY_BLOCKS

__all__ = ["build", "evaluate", "run_scenario"]


def _noise(q: str, mode: str, dtype, params=None):
    if q == "paper":
        noise = sys3d.paper_noise(mode, dtype)
    elif q == "imu":
        noise = sys3d.imu_noise(imu_mod.PAPER000_IMU, dtype)
    else:
        raise InputError(f"--q: expected 'paper' or 'imu', got {q!r}")
    if params and "noise" in params:
        noise = sys3d.params_from_dict(params["noise"], noise, dtype)
    return sys3d.validate_params(noise)


def _checked(options, mode, dtype, params=None, plots=False):
    # The options completed and checked as ``jaxslam run ekfslam3d-MODE`` checks them
    # (registry.check_options: a misspelt key, "False" for a flag, 64.9 slots or True landmarks
    # were taken as given), the dtype, ``params`` and ``plots`` as ``Scenario.run`` checks them.
    if mode not in _SCENARIOS:
        raise InputError(f"mode: expected one of {sorted(_SCENARIOS)}, got {mode!r}")
    return _checked_args(_SCENARIOS[mode], options, dtype, params, plots)


def build(options: dict, mode: str, dtype, params=None):
    """(one_run(key) -> outputs, cfg, noise, setup factory) for the given options.

    ``options`` is completed with the defaults and checked like the scenario's command-line
    options (:func:`jaxslam.sim.scenarios.registry.check_options`); ``dtype`` must be float32
    or float64 (float64 with JAX's x64 on) and ``params`` is checked against the scenario's
    ``--params`` schema: an :class:`InputError` names the offending option or key.
    """
    options, params = _checked(options, mode, dtype, params)
    dtype = jnp.dtype(dtype)
    duration = float(options["duration"])  # >= one frame: its Option's lower bound (check_options)
    cap = int(options["capacity"])  # capacity, landmarks, max_obs >= 1: their Options' lower bounds
    n_lm = int(options["landmarks"])
    if mode == "known" and cap < n_lm:
        raise InputError(f"--capacity: {cap} slots cannot hold the {n_lm} known landmarks")
    noise = _noise(options["q"], mode, dtype, params)
    ctrl = dflqr.paper000_params()
    if params and "controller" in params:
        ctrl = controller_from_dict(params["controller"], ctrl)
    cfg = sys3d.Config(
        mode=mode,
        association=options["association"],
        capacity=cap,
        max_obs=int(options["max_obs"]),
        accel_mode=options["accel"],
        dt=DT,
        g=float(ctrl.quad.g),
        save_map=False,
    )
    traj = paper000_figure8(options["altitude"], 0.0)
    center = np.asarray(traj.center, float)
    ff = not options["no_feedforward"]
    nf = n_frames(duration, DT, FRAME_STEPS)
    control_on = options["control_on"]
    # Gain and reference are the same for every run: one small program, outside the runs'.
    K, refs = controls(make_setup(traj, dtype, ctrl=ctrl), nf * FRAME_STEPS, ff,
                       compiler_options=runtime.compiler_options())

    def flight(key, noise, save_map=False):
        k_lm, k_fl = jax.random.split(key)
        lms = lm_mod.generate_landmarks(k_lm, n_lm,
                                        center=center, dtype=dtype)
        setup = make_setup(traj, dtype, landmarks=lms, ctrl=ctrl)
        est = sys3d.make_estimator(cfg._replace(save_map=save_map), noise, landmarks_true=lms)
        fl = simulate(setup, k_fl, nf, FRAME_STEPS, estimator=est, control_on=control_on,
                      K=K, feedforward=ff, refs=refs)
        return fl, lms

    def one_run(key, noise=noise, detail=False):
        # detail=True also returns the whole flight (for the plots; Monte Carlo keeps run 0's),
        # so the plots come from the program that computes the metrics.
        fl, lms = flight(key, noise, save_map=detail)
        out = evaluate(fl, lms, cfg)
        if detail:
            out["detail"] = {"flight": fl, "landmarks": lms}
        return out

    return one_run, flight, cfg, noise, nf


def evaluate(fl, lms, cfg):
    """Per-run metrics and consistency series of one flight (jit/vmap-safe)."""
    t = fl.t[1:]
    truth = fl.truth[1:]
    st = fl.est_steps
    e = jax.vmap(sys3d.robot_error)(st.mean, truth)
    settled = t > SETTLED_AFTER_S

    def rmse_norm(err, w=None):
        return mx.rmse_norm(err) if w is None else mx.rmse_norm_where(err, w)

    def rmse_axis(err):
        return jnp.mean(jnp.sqrt(jnp.mean(err * err, axis=0)))

    deg = 180.0 / jnp.pi
    slam = fl.est_final.slam
    active = slam.active
    L_hat = slam.x[sys3d.NX:].reshape(-1, 3)
    if cfg.association == "known":
        true_of_slot = lms[jnp.clip(slam.ids, 0, lms.shape[0] - 1)]
    else:
        d = jnp.linalg.norm(L_hat[:, None, :] - lms[None, :, :], axis=-1)
        true_of_slot = lms[jnp.argmin(d, axis=1)]
    # the inactive slots masked with where (a stale non-finite slot times 0 was NaN)
    lm_err_axis = jnp.where(active[:, None], (L_hat - true_of_slot) ** 2, 0.0)
    lm_err2 = jnp.sum(lm_err_axis, axis=1)
    n_act = jnp.sum(active)
    lm_rmse = jnp.where(n_act > 0, jnp.sqrt(jnp.sum(lm_err2) / jnp.maximum(n_act, 1)), jnp.nan)
    trk = tracking_metrics(fl.t, fl.truth, fl.ref)
    out = {
        "pos_rmse_m": rmse_norm(e[:, 0:3]),
        "pos_rmse_axis_m": rmse_axis(e[:, 0:3]),
        "vel_rmse_mps": rmse_norm(e[:, 3:6]),
        "vel_rmse_axis_mps": rmse_axis(e[:, 3:6]),
        "att_rmse_deg": rmse_norm(e[:, 6:9]) * deg,
        "att_rmse_axis_deg": rmse_axis(e[:, 6:9]) * deg,
        "pos_rmse_settled_m": rmse_norm(e[:, 0:3], settled),
        "vel_rmse_settled_mps": rmse_norm(e[:, 3:6], settled),
        "att_rmse_settled_deg": rmse_norm(e[:, 6:9], settled) * deg,
        "track_pos_rmse_settled_m": trk["track_pos_rmse_settled_m"],
        "max_tilt_deg": trk["max_tilt_deg"],
    }
    if cfg.mode == "unknown":
        out["landmark_rmse_m"] = lm_rmse
        # NaN with nothing mapped, as landmark_rmse_m (it was 0.0: a perfect map of nothing)
        out["landmark_rmse_axis_m"] = jnp.where(n_act > 0, jnp.mean(
            jnp.sqrt(jnp.sum(lm_err_axis, axis=0) / jnp.maximum(n_act, 1))), jnp.nan)
        out["landmarks_mapped"] = n_act.astype(e.dtype)
    series = {
        "nees": fl.est_frames.nees,
        "nis": fl.est_frames.nis,
        "nis_dof": fl.est_frames.dof,
    }
    counts = {
        "capacity_overflow": slam.overflow,
        "dropped": fl.est_final.dropped,
        "masked": fl.est_final.masked,
        "status": slam.status,
        "non_finite": jnp.logical_not(
            jnp.all(jnp.isfinite(st.mean)) & jnp.all(jnp.isfinite(fl.truth))
        ).astype(jnp.int32),
    }
    return {"metrics": out, "series": series, "counts": counts}


def consistency(series, t, runs, n=sys3d.NX):
    """ANEES (whole flight, per 10 s window), fraction of steps in bounds, mean NIS."""
    nees = np.asarray(series["nees"], float)  # (runs, T)
    per_step = np.nanmean(nees, axis=0)
    lo, hi = mx.anees_bounds(n, runs)
    lo, hi = float(lo), float(hi)
    windows = []
    t = np.asarray(t)
    for w0 in np.arange(0.0, t[-1] - 1e-9, WINDOW_S):
        sel = (t > w0) & (t <= w0 + WINDOW_S)
        if np.any(sel):
            a = float(np.mean(per_step[sel]))
            windows.append({"t0_s": float(w0), "t1_s": float(min(w0 + WINDOW_S, t[-1])),
                            "anees": a, "inside": bool(lo <= a <= hi)})
    nis = np.asarray(series["nis"], float)
    dof = np.asarray(series["nis_dof"], float)
    tot = float(dof.sum())
    nis_mean = float(nis.sum() / tot) if tot > 0 else float("nan")
    nlo, nhi = mx.mean_chi2_bounds(tot, tot) if tot > 0 else (float("nan"), float("nan"))
    return {
        "anees": float(np.mean(per_step)),
        "anees_bounds": [lo, hi],
        "nis_mean": nis_mean,
        "nis_bounds": [float(nlo), float(nhi)],
        "anees_fraction_in_bounds": mx.steps_inside(per_step, (lo, hi)),
        "anees_windows": windows,
        "anees_settled": float(np.mean(per_step[t > SETTLED_AFTER_S])) if np.any(t > SETTLED_AFTER_S) else float("nan"),
    }, per_step


def run_scenario(name, mode, runs, seed, dtype, options, progress, params=None, plots=False):
    """``jaxslam run ekfslam3d-*``: build the flight, run ``runs`` vmapped Monte Carlo seeds
    (chunked, with progress) and return the scenario result (metrics, consistency, flags)."""
    options, params = _checked(options, mode, dtype, params, plots)
    one_run, flight, cfg, noise, nf = build(options, mode, dtype, params)
    mc = monte_carlo.run(lambda k: one_run(k, detail=plots), seed, runs, chunk=options.get("chunk"),
                         progress=progress, cpu_batching="loop", detail=plots,
                         program_key=program_key(name, options, params, dtype))
    runs = mc.runs  # the finished runs: fewer than asked when interrupted (Ctrl-C)
    out = mc.out
    t = (np.arange(nf * FRAME_STEPS) + 1) * DT
    t_frames = (np.arange(nf) + 1) * DT * FRAME_STEPS
    cons, per_step = consistency(out["series"], t_frames, runs)
    counts = out["counts"]
    status_any = int(np.bitwise_or.reduce(np.asarray(counts["status"]).ravel()))
    from ...errors import decode

    flags = {
        "capacity_overflow": int(np.sum(counts["capacity_overflow"])),
        "masked_measurements": int(np.sum(counts["masked"])),
        "dropped_measurements": int(np.sum(counts["dropped"])),
        "non_finite": int(np.sum(counts["non_finite"])),
    }

    def plot(directory):
        from ...plotting import slam3d

        d = out["detail"]  # run 0, from the same program as the metrics
        return slam3d.plot_all(name, d["flight"], np.asarray(d["landmarks"]), t, t_frames, per_step,
                               cons, runs, directory, cfg)

    config = {
        "mode": mode,
        "duration_s": float(options["duration"]),
        "duration_flown_s": _duration_flown(nf * FRAME_STEPS, DT),  # whole LiDAR frames
        "dt_s": DT,
        "imu_rate_hz": 1.0 / DT,
        "lidar_rate_hz": 1.0 / (DT * FRAME_STEPS),
        "landmark_centre_ned_m": [0.0, 0.0, -float(options["altitude"])],
        "noise": sys3d.params_to_dict(noise),
        "estimator": {**cfg._asdict(),  # the thresholds are Params, reported beside the switches
                      **{f: None if getattr(noise, f) is None else float(getattr(noise, f))
                         for f in ("gate", "nn_gate", "nn_new")}},
        "anees_window_s": WINDOW_S,
        "threads": mc.threads,  # host threads that ran the flights (monte_carlo "loop")
        **options,
    }
    return ScenarioResult(
        config=config,
        metrics=out["metrics"],
        consistency={**{k: cons[k] for k in ("anees", "anees_bounds", "nis_mean", "nis_bounds")},
                     "anees_steps_inside": cons["anees_fraction_in_bounds"], **CONSISTENCY_BLOCKS},
        flags=flags,
        timing={"compile_s": mc.compile_s, "run_s": mc.run_s},
        interrupted=mc.interrupted,
        plot=plot if plots else None,
        extra={"status_flags": decode(status_any),
               "consistency_detail": {k: v for k, v in cons.items()
                                      if k not in ("anees", "anees_bounds", "nis_mean", "nis_bounds")},
               "devices": mc.n_devices},
    )


def params_schema(mode: str, options: dict, dtype) -> dict:
    """What a ``--params`` file may set (:mod:`jaxslam.paramfile`): the filter's noise for
    ``--q`` and the DF-LQR weights and PD gains, with their defaults."""
    return {"noise": sys3d.params_to_dict(_noise(options["q"], mode, dtype)),
            "controller": controller_to_dict(dflqr.paper000_params())}


_SCENARIOS: dict = {}  # mode -> its registered Scenario (the options build checks against)


def _register(mode):
    name = f"ekfslam3d-{mode}"
    _SCENARIOS[mode] = register(Scenario(
        name=name,
        description=DECLARED[name].description,
        options=DECLARED[name].options,
        run=lambda runs, seed, dtype, options, progress, params=None, plots=False: run_scenario(
            name, mode, runs, seed, dtype, options, progress, params, plots),
        params=lambda options, dtype: params_schema(mode, options, dtype),
    ))


for _mode in ("unknown", "known"):
    _register(_mode)
