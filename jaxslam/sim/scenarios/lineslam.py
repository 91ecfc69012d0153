"""Scenario ``lineslam-room``: line-feature EKF-SLAM in an L-shaped room (paper 004 ch. 4).

The quadrotor flies a closed path through an indoor map of 10 walls and scans
them with a Hokuyo URG-04LX (:data:`jaxslam.sensors.laser2d.URG04LX`) at 10 Hz;
the filter is :mod:`jaxslam.systems.line_slam_004` (Algorithm 2).  The thesis
gives no map or path for its simulation (Figs. 4.1-4.4 are not in its text),
so jaxslam states its own:

* map: an L-shaped room — main hall x ∈ [−2, 6], y ∈ [−2, 1] m and an arm
  x ∈ [−2, 2], y ∈ [1, 4] m (6 walls) — and a 0.6 × 0.4 m pillar centred at
  (3.5, −0.5) m (4 walls): 10 walls on 10 distinct lines, none through the map
  origin;
* path: the ellipse p(t) = (2 + 3 cos ωt, −0.5 + 1.1 sin ωt) m around the
  pillar with a 30 s period (speed ≤ 0.63 m/s), yaw along the velocity plus
  0.3 sin(0.5 t) rad (so the body velocity has a lateral part), roll and pitch
  2° sinusoids known to the filter (IMU attitude, used for the ground
  projection); 60 s (two laps, 600 scans);
* sensors: the URG-04LX model (σ = 1 cm to 1 m, 1 % beyond; 0.02-4 m), 5 % of
  the returns replaced by clutter in front of the wall, optical flow σ = 0.05 m/s
  per axis, gyro yaw rate σ = 0.005 rad/s, all Gaussian;
* filter: starts at the true pose (the map frame is the world frame),
  :func:`jaxslam.systems.line_slam_004.default_params` (matched to these noises).

Metrics per run: ``pos_rmse_m``, ``yaw_rmse_deg`` (over all scans),
``line_rho_err_m`` / ``line_theta_err_deg`` (RMS over the mapped lines at the
end, each compared with the nearest true line on the double cover),
``lines_mapped``, ``lines_spurious`` (mapped lines farther than 0.3 m / 5° from
every true line; excluded from the line errors), ``anees`` (time-averaged NEES
of the pose [p_x, p_y, ψ], 3 dof), ``max_pos_err_m``.  Consistency: the per-step
ANEES over runs against the two-sided 95 % χ² bounds, and the mean NIS of the
line updates.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ... import metrics as mx
from ...errors import InputError, decode
from ...features import lines as fl
from ...linalg import wrap_angle
from ...sensors import laser2d
from ...systems import line_slam_004 as LS
from .. import monte_carlo
from .builtin import DECLARED
from .registry import Scenario, ScenarioResult, _checked_args, _duration_flown, program_key, register

__all__ = ["ROOM", "PILLAR", "Setup", "room_walls", "make_setup", "simulate", "evaluate", "build", "consistency",
           "run_scenario", "true_lines"]

ROOM = ((-2.0, -2.0), (6.0, -2.0), (6.0, 1.0), (2.0, 1.0), (2.0, 4.0), (-2.0, 4.0))
PILLAR = ((3.2, -0.7), (3.8, -0.7), (3.8, -0.3), (3.2, -0.3))
SPURIOUS_RHO_M = 0.3
SPURIOUS_THETA_DEG = 5.0


def room_walls() -> np.ndarray:
    """The 10 wall segments (W, 2, 2) of the scenario map."""
    return np.concatenate([laser2d.walls_from_polygon(np.asarray(ROOM)),
                           laser2d.walls_from_polygon(np.asarray(PILLAR))], axis=0)


def true_lines(walls) -> np.ndarray:
    """Distinct Hesse lines (ρ ≥ 0, θ) of wall segments (host side; collinear walls merged)."""
    out = []
    for a, b in np.asarray(walls, float):
        rho, th = (float(v) for v in fl.line_through(a, b))
        if not any(abs(rho - r) < 1e-9 and abs(math.remainder(th - t, 2 * math.pi)) < 1e-9 for r, t in out):
            out.append((rho, th))
    return np.asarray(out)


class Setup(NamedTuple):
    """Host-side description of the flight: scan times t_1..t_T (T,), truth (T, 6) robot
    states [p, V_body, ψ, r] at those times, s0 (6,) the state at t_0 = 0 (where the filter
    starts; each step predicts from t_{k−1} to t_k), tilt (T, 2), walls (W, 2, 2), true
    lines (N, 2), noises."""

    ts: np.ndarray
    truth: np.ndarray
    s0: np.ndarray
    tilt: np.ndarray
    walls: np.ndarray
    lines: np.ndarray
    sigma_flow: float
    sigma_gyro: float
    outlier_prob: float


def make_setup(duration: float = 60.0, dt: float = 0.1, period: float = 30.0, tilt_deg: float = 2.0,
               sigma_flow: float = 0.05, sigma_gyro: float = 0.005, outlier_prob: float = 0.05) -> Setup:
    """Truth of the flight (analytic derivatives; validated options)."""
    for name, v, lo in (("duration", duration, dt), ("dt", dt, 0.0), ("period", period, 0.0)):
        if not (math.isfinite(v) and v > lo):
            raise InputError(f"--{name}: must be a finite number > {lo:g}, got {v}")
    for name, v in (("sigma_flow", sigma_flow), ("sigma_gyro", sigma_gyro), ("tilt_deg", tilt_deg)):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"--{name.replace('_', '-')}: must be >= 0, got {v}")
    if not 0.0 <= outlier_prob < 1.0:
        raise InputError(f"--outlier-prob: must be in [0, 1), got {outlier_prob}")
    T = int(round(duration / dt))
    t = np.arange(T + 1) * dt
    w = 2 * math.pi / period
    x, y = 2 + 3 * np.cos(w * t), -0.5 + 1.1 * np.sin(w * t)
    dx, dy = -3 * w * np.sin(w * t), 1.1 * w * np.cos(w * t)
    ddx, ddy = -3 * w * w * np.cos(w * t), -1.1 * w * w * np.sin(w * t)
    heading = np.unwrap(np.arctan2(dy, dx))
    yaw = heading + 0.3 * np.sin(0.5 * t)
    rate = (dx * ddy - dy * ddx) / (dx * dx + dy * dy) + 0.15 * np.cos(0.5 * t)
    c, s = np.cos(yaw), np.sin(yaw)
    vb = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)
    truth = np.stack([x, y, vb[:, 0], vb[:, 1], yaw, rate], axis=1)
    a = math.radians(tilt_deg)
    tilt = np.stack([a * np.sin(0.7 * t), a * np.cos(0.4 * t)], axis=1)
    walls = room_walls()
    return Setup(ts=t[1:], truth=truth[1:], s0=truth[0], tilt=tilt[1:], walls=walls, lines=true_lines(walls),
                 sigma_flow=float(sigma_flow), sigma_gyro=float(sigma_gyro),
                 outlier_prob=float(outlier_prob))


def simulate(key, setup: Setup, spec: laser2d.LaserSpec, dtype):
    """One flight's log (jit/vmap-safe in ``key``).  Returns :class:`LS.Log`."""
    dtype = jnp.dtype(dtype)
    truth = jnp.asarray(setup.truth, dtype)
    tilt = jnp.asarray(setup.tilt, dtype)
    walls = jnp.asarray(setup.walls, dtype)
    wmask = jnp.ones((walls.shape[0],), bool)
    T = truth.shape[0]
    k_scan, k_flow, k_gyro = jax.random.split(key, 3)
    keys = jax.random.split(k_scan, T)

    def one(k, s, tl):
        pose = jnp.stack([s[0], s[1], s[LS.YAW]])
        r, v, _ = laser2d.scan(k, pose, walls, wmask, spec, tilt=tl, outlier_prob=setup.outlier_prob)
        return r, v

    ranges, valid = jax.vmap(one)(keys, truth, tilt)
    flow = truth[:, LS.VEL] + setup.sigma_flow * jax.random.normal(k_flow, (T, 2), dtype)
    gyro = truth[:, LS.RATE] + setup.sigma_gyro * jax.random.normal(k_gyro, (T,), dtype)
    return LS.Log(ranges=ranges, valid=valid, tilt=tilt, flow=flow, gyro=gyro,
                  s0=jnp.asarray(setup.s0, dtype))


def evaluate(setup: Setup, res: LS.Result):
    """Per-run metrics, per-step NEES/NIS series and counts (jit/vmap-safe)."""
    st = res.steps
    dtype = st.mean.dtype
    truth = jnp.asarray(setup.truth, dtype)
    e = st.mean - truth
    e = e.at[:, LS.YAW].set(wrap_angle(e[:, LS.YAW]))
    deg = 180.0 / jnp.pi
    epos = jnp.sqrt(jnp.sum(e[:, :2] ** 2, axis=1))
    ep = jnp.concatenate([e[:, :2], e[:, LS.YAW:LS.YAW + 1]], axis=1)
    idx = jnp.array([0, 1, LS.YAW])
    Pp = st.cov[:, idx[:, None], idx[None, :]]
    nees = mx.nees(ep, Pp)

    tl = jnp.asarray(setup.lines, dtype)
    L = st.lines[-1]
    act = st.active[-1]
    # (ρ, θ) error of each mapped line against each true line, on the double cover: (cap, N, 2)
    err = jax.vmap(lambda l: jax.vmap(lambda t: LS.line_residual(l, t))(tl))(L)
    score = jnp.abs(err[..., 0]) / SPURIOUS_RHO_M + jnp.abs(err[..., 1]) * deg / SPURIOUS_THETA_DEG
    best = jnp.argmin(score, axis=1)
    e_best = jnp.take_along_axis(err, best[:, None, None], axis=1)[:, 0]  # (cap, 2)
    good = act & (jnp.abs(e_best[:, 0]) <= SPURIOUS_RHO_M) & (jnp.abs(e_best[:, 1]) * deg <= SPURIOUS_THETA_DEG)
    n_good = jnp.sum(good)
    denom = jnp.maximum(n_good, 1)
    out = {
        "pos_rmse_m": jnp.sqrt(jnp.mean(epos ** 2)),
        "yaw_rmse_deg": jnp.sqrt(jnp.mean(e[:, LS.YAW] ** 2)) * deg,
        "line_rho_err_m": jnp.where(n_good > 0, jnp.sqrt(jnp.sum(jnp.where(good, e_best[:, 0] ** 2, 0.0)) / denom),
                                    jnp.nan),
        "line_theta_err_deg": jnp.where(n_good > 0, jnp.sqrt(jnp.sum(jnp.where(good, e_best[:, 1] ** 2, 0.0))
                                                             / denom) * deg, jnp.nan),
        "lines_mapped": jnp.sum(act).astype(dtype),
        "lines_spurious": jnp.sum(act & ~good).astype(dtype),
        "anees": jnp.mean(nees),
        "max_pos_err_m": jnp.max(epos),
    }
    # Distinct true lines found (two slots on one true line would show as mapped > found).
    found = jnp.zeros((tl.shape[0],), bool).at[best].max(good)
    out["true_lines_found"] = jnp.sum(found).astype(dtype)
    series = {"nees": nees, "nis": st.nis, "dof": st.dof, "pos_err_m": epos}
    counts = {"status": st.status[-1], "overflow": res.final.overflow,
              "gated": jnp.sum(st.n_gated), "matched": jnp.sum(st.n_matched),
              "non_finite": (~(jnp.all(jnp.isfinite(st.mean)) & jnp.all(jnp.isfinite(st.cov)))).astype(jnp.int32)}
    return {"metrics": out, "series": series, "counts": counts}


def build(options: dict, dtype, params=None):
    """Scenario pieces ``(one_run, flight, cfg, fp, setup)``; ``one_run(key)`` is jit/vmap-safe.

    ``options`` is completed and checked like the command line's options, ``dtype`` must be
    float32 or float64 and ``params`` is checked against the scenario's ``--params`` schema
    (:func:`jaxslam.sim.scenarios.registry.check_options`).
    """
    options, params = _checked_args(SCENARIO, options, dtype, params)
    cap = int(options["capacity"])  # >= 1: its Option's lower bound, checked above
    setup = make_setup(float(options["duration"]), 0.1, tilt_deg=float(options["tilt_deg"]),
                       outlier_prob=float(options["outlier_prob"]))
    cfg = LS.Config(capacity=cap)
    fp = LS.default_params(cfg.dt, dtype=dtype)
    if params and "filter" in params:
        vals = fp._asdict()
        for k, v in dict(params["filter"]).items():
            if k not in LS.NOISE_FIELDS:
                raise InputError(f"params.filter: unknown entry {k!r}; expected {list(LS.NOISE_FIELDS)}")
            a = np.asarray(v, float)
            vals[k] = jnp.asarray(np.diag(a) if a.ndim == 1 else a, dtype)
        fp = LS.Params(**vals)
    fp = LS.validate_params(fp)

    def flight(key, fp=fp):
        k_sim, k_f = jax.random.split(key)
        log = simulate(k_sim, setup, cfg.spec, dtype)
        return log, LS.run(log, cfg, fp, key=k_f)

    def one_run(key, fp=fp, detail=False):
        log, res = flight(key, fp)
        out = evaluate(setup, res)
        if detail:  # run 0's log and filter record for the plots, from this same program
            out["detail"] = {"log": log, "result": res}
        return out

    return one_run, flight, cfg, fp, setup


def params_schema(options, dtype) -> dict:
    """What a ``--params`` file may set (:mod:`jaxslam.paramfile`): the filter's noise."""
    fp = LS.default_params(LS.Config(capacity=1).dt, dtype=dtype)
    return {"filter": {k: np.asarray(getattr(fp, k)) for k in LS.NOISE_FIELDS}}


def run_scenario(runs, seed, dtype, options, progress, params=None, plots=False):
    """Monte Carlo over ``runs`` seeded flights (see the module docstring)."""
    options, params = _checked_args(SCENARIO, options, dtype, params, plots)
    one_run, flight, cfg, fp, setup = build(options, dtype, params)
    mc = monte_carlo.run(lambda k: one_run(k, detail=plots), seed, runs, chunk=options.get("chunk"),
                         progress=progress, detail=plots,
                         program_key=program_key("lineslam-room", options, params, dtype))
    runs = mc.runs  # the finished runs: fewer than asked when interrupted (Ctrl-C)
    out = mc.out
    cons, per_step = consistency(out["series"], runs)
    lo, hi = cons["anees_bounds"]
    counts = out["counts"]
    status_any = int(np.bitwise_or.reduce(np.asarray(counts["status"]).ravel()))
    flags = {
        "capacity_overflow": int(np.sum(counts["overflow"])),
        "gated_line_measurements": int(np.sum(counts["gated"])),
        "matched_line_measurements": int(np.sum(counts["matched"])),
        "non_finite": int(np.sum(counts["non_finite"])),
        "diverged_runs": int(np.sum(np.asarray(out["metrics"]["max_pos_err_m"]) > 1.0)),
    }

    def plot(directory):
        from ...plotting import lines as lplot

        log, res = out["detail"]["log"], out["detail"]["result"]
        return lplot.plot_all("lineslam-room", setup, cfg, log, res, per_step, (lo, hi), directory)

    config = {
        "walls": setup.walls.tolist(),
        "true_lines_rho_theta": setup.lines.tolist(),
        "steps": int(setup.ts.shape[0]),
        "duration_flown_s": _duration_flown(setup.ts.shape[0], cfg.dt),  # whole scans
        "dt_s": cfg.dt,
        "laser": cfg.spec._asdict(),
        "ransac": cfg.ransac._asdict(),
        "match_gate_m": float(fp.match_gate),
        "nis_gate": float(fp.nis_gate),
        "new_threshold": float(fp.new_threshold),
        "sigma_flow_mps": setup.sigma_flow,
        "sigma_gyro_radps": setup.sigma_gyro,
        "filter_params": {k: np.asarray(getattr(fp, k), float).tolist() for k in LS.NOISE_FIELDS},
        **options,
    }
    return ScenarioResult(
        config=config,
        metrics=dict(out["metrics"]),
        consistency={**cons,
                     # what each statistic covers (docs/cli.md, "consistency")
                     "anees_block": "robot pose (x, y, yaw)", "anees_dim": 3,
                     "nis_block": "matched wall lines (rho, theta), per degree of freedom", "nis_dim": 1},
        flags=flags,
        timing={"compile_s": mc.compile_s, "run_s": mc.run_s},
        interrupted=mc.interrupted,
        plot=plot if plots else None,
        extra={"status_flags": decode(status_any),
               "consistency_detail": {"pose_dof": 3, "fraction_steps_in_bounds": cons["anees_steps_inside"]}},
    )


def consistency(series, runs):
    """Pose ANEES over ``runs`` Monte Carlo runs: its time average and the fraction of steps
    whose run average is inside the per-step χ²(3) bounds; the mean NIS per degree of freedom
    with its bounds.  ``series``: ``nees`` (runs, T), ``nis`` and ``dof`` (runs, T).  Returns
    the report's statistics and the per-step ANEES."""
    per_step = np.nanmean(np.asarray(series["nees"], float), axis=0)
    lo, hi = (float(b) for b in mx.anees_bounds(3, runs))
    tot = float(np.asarray(series["dof"], float).sum())
    nlo, nhi = mx.mean_chi2_bounds(tot, tot) if tot > 0 else (math.nan, math.nan)
    return {"anees": float(np.mean(per_step)), "anees_bounds": [lo, hi],
            "nis_mean": float(np.asarray(series["nis"], float).sum() / tot) if tot > 0 else math.nan,
            "nis_bounds": [float(nlo), float(nhi)],
            "anees_steps_inside": mx.steps_inside(per_step, (lo, hi))}, per_step


SCENARIO = register(Scenario(
    name="lineslam-room",
    description=DECLARED["lineslam-room"].description,
    options=DECLARED["lineslam-room"].options,
    run=run_scenario,
    params=params_schema,
))
