"""Scenarios ``uwb-circle``, ``uwb-square`` and ``uwb-rough`` (paper 003, Sec. IV-A, B, C).

A drone flies a planar path at constant height, measuring its range to N UWB
anchors and its three body rates; the filter is
:mod:`jaxslam.systems.uwb_slam_2d` (range-only EKF-SLAM with the paper's
trilateration start-up, or localisation against the known anchors).

World layout (jaxslam's choice; the paper's figures are not in its text, which
says only that the end anchor of the start-up sits at (0, 0) and that the
circle passes through it):

* anchors A = (−3, 0) (start of the forced straight-line run), B = (0, 0) (its
  end, where the EKF starts), C = (−1.5, 2.5); ``--anchors 4..6`` adds
  D = (1, 2), E = (−4, 2.5), F = (−1, −2), which the SLAM filter maps by the
  delayed initialisation.  With this layout the start-up frame (origin B, +x
  from A to B, +y towards C) *is* the world frame; the code still computes the
  truth → start-up-frame transform (possibly a reflection) from the anchor the
  start-up chose, so other layouts compare correctly.
* start-up: the drone flies from A to B at ``--startup-speed`` (0.15 m/s, the
  circle's speed), one sample per Δt, and arrives at B at t = 0.
* I ``uwb-circle``: [−1.5 + 1.5 cos(0.1t), 1.5 sin(0.1t)] (the paper's circle,
  centred so that it starts at B and passes through A), yaw rate 0.2 sin(0.1t),
  roll and pitch rates 0; 126 s (two laps).
* II ``uwb-square``: the 3 m square B → (0, 3) → (−3, 3) → A → B at 0.15 m/s
  (20 s per side, corners taken sharply), two laps (160 s); the paper's staged
  angular motion: roll rate π/180 for t ∈ [0, 60) s, pitch rate π/360 for
  [40, 100) s, yaw rate π/180 for [80, 140) s (paper: iterations; Δt = 1 s).
* III ``uwb-rough``: 12 straight patches between timed waypoints at speeds
  0.09–0.28 m/s with sudden turns, a lateral wiggle (±0.3 m, 8 s period)
  between 60 and 90 s, piecewise-constant roll/pitch/yaw rates switching sign
  plus a yaw sinusoid; 150 s.
* noise: uniform ±0.2 m on ranges and ±0.002 rad/s on rates (paper), or
  Gaussian of the same variance (``--noise gaussian``).

Frames of comparison: estimates live in the start-up frame (SLAM) or the anchors'
frame (localisation); the truth is mapped into it.  Attitude is compared with
the truth relative to the attitude at t = 0 (the filter's reference, paper
Sec. III-D-1; attitude is decoupled from position in this model, so a map-frame
rotation does not touch it).  ``*_aligned_*`` metrics apply the best-fit 2D rigid
transform (:func:`jaxslam.metrics.umeyama`, estimated → true trajectory) to the
trajectory and the map.

Metrics (per run): ``pos_rmse_m`` (RMSE of the 2D position error norm over the
filter steps), ``pos_err_max_m`` (largest position error), ``vel_rmse_mps``,
``yaw_rmse_deg``, ``att_rmse_deg`` (roll, pitch, yaw together),
``pos_rmse_aligned_m``; SLAM only: ``landmark_rmse_m`` (anchors mapped at the
end), ``landmark_rmse_aligned_m``, ``init_landmark_err_m`` (RMS error of the
anchors mapped by the start-up, right after it), ``init_trilat_err_m`` (the
trilaterated anchor), ``landmarks_mapped``; localisation only:
``init_pos_err_m`` (the initial LS fix); ``nees_pos_mean`` / ``nees_robot_mean``
(time-averaged NEES of the run).  Consistency: per-step ANEES of the position
(2 states; the headline ``consistency.anees``: what the anchors observe) and of
the whole robot block (10 states, ``consistency.anees_robot``; details in
``consistency_detail.robot``) over the runs
with two-sided 95 % χ² bounds per step, their time averages, the fraction of
steps inside, 20 s windows, the NEES spread against χ²'s, and the normalised
mean NIS.  The robot-block NEES against these *deterministic* manoeuvres
measures how well Q matches them (roll and pitch rates that are exactly zero
make any random-walk attitude model conservative), which is why the position
is the headline.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ... import metrics as mx
from ...control.trajectories import Circle
from ...control.trajectories_2d import CirclePath, PolylinePath, RateProfile, planar_states
from ...errors import InputError
from ...linalg import wrap_angle
from ...sensors import uwb
from ...stats import nees as _nees
from ...systems import uwb_slam_2d as U
from .. import monte_carlo
from .builtin import DECLARED
from .registry import Scenario, ScenarioResult, _checked_args, _duration_flown, program_key, register

__all__ = ["ANCHORS", "SCENARIOS", "Setup", "SimOut", "make_setup", "simulate",
           "evaluate", "build", "run_scenario", "consistency", "consistency_summary"]

ANCHORS = ((-3.0, 0.0), (0.0, 0.0), (-1.5, 2.5), (1.0, 2.0), (-4.0, 2.5), (-1.0, -2.0))
START, END = 0, 1
WINDOW_S = 20.0
SCENARIOS = ("circle", "square", "rough")
_PI = math.pi


def _circle():
    c = CirclePath(Circle(center=(-1.5, 0.0, -1.0)))
    return c, c, 126.0


def _square():
    side, v = 3.0, 0.15
    leg = side / v
    corners = [(0.0, 0.0), (0.0, side), (-side, side), (-side, 0.0)]
    pts = [corners[i % 4] for i in range(9)]
    path = PolylinePath(times=np.arange(9) * leg, points=np.asarray(pts))
    att = RateProfile(t0=np.array([0.0, 40.0, 80.0]), t1=np.array([60.0, 100.0, 140.0]),
                      r=np.array([[_PI / 180, 0, 0], [0, _PI / 360, 0], [0, 0, _PI / 180]]),
                      sin_amp=np.zeros(3), sin_omega=np.zeros(3))
    return path, att, 2 * 4 * leg


_ROUGH_WAYPOINTS = np.array([
    (0, 0.0, 0.0), (10, 0.5, 1.5), (18, -0.5, 2.8), (30, -2.0, 3.2), (36, -3.2, 2.0),
    (50, -3.5, 0.3), (60, -2.0, -0.8), (75, -0.5, 0.5), (90, -1.5, 1.5), (100, 0.3, 1.0),
    (115, -1.0, -1.2), (130, -3.0, 1.2), (150, 0.0, 0.0)])
_ROUGH_RATES = (  # (t0, t1, axis, rate rad/s)
    (0, 15, 0, 0.02), (15, 35, 0, -0.03), (50, 80, 0, 0.015), (100, 120, 0, -0.02),
    (5, 25, 1, 0.01), (30, 45, 1, -0.02), (70, 85, 1, 0.03), (110, 140, 1, -0.01),
    (0, 10, 2, 0.05), (20, 30, 2, -0.08), (40, 50, 2, 0.1), (60, 100, 2, -0.04), (120, 135, 2, 0.06))


def _rough():
    w = _ROUGH_WAYPOINTS
    path = PolylinePath(times=w[:, 0], points=w[:, 1:], wiggle_amp=0.3, wiggle_period=8.0,
                        wiggle_t0=60.0, wiggle_t1=90.0)
    r = np.zeros((len(_ROUGH_RATES), 3))
    for i, (_, _, ax, rate) in enumerate(_ROUGH_RATES):
        r[i, ax] = rate
    att = RateProfile(t0=np.array([a[0] for a in _ROUGH_RATES], float),
                      t1=np.array([a[1] for a in _ROUGH_RATES], float), r=r,
                      sin_amp=np.array([0.0, 0.0, 0.03]), sin_omega=np.array([0.0, 0.0, 0.3]))
    return path, att, 150.0


_PATHS = {"circle": _circle, "square": _square, "rough": _rough}
_planar_states_jit = jax.jit(planar_states)  # eager vmap-of-jvp dispatch costs seconds


class Setup(NamedTuple):
    """Everything one simulated flight needs (host-side values; static sizes).

    ts: (T,) filter times [s]; startup_pos: (Ts, 2) true start-up positions [m];
    anchors: (N, 2) world anchors [m]; truth: (T, 10) true planar states (world);
    noise: UwbNoise; dist: "uniform"/"gaussian"; max_range: m (inf = unlimited).
    """

    ts: np.ndarray
    startup_pos: np.ndarray
    anchors: np.ndarray
    truth: np.ndarray
    noise: uwb.UwbNoise
    dist: str
    max_range: float


class SimOut(NamedTuple):
    """One simulated flight: truth (T, 10) world, the log (``log.anchors`` None; a
    localisation run uses ``log._replace(anchors=anchors)``), anchors (N, 2) world."""

    truth: jax.Array
    log: U.Log
    anchors: jax.Array


def make_setup(scenario: str, duration=None, dt: float = 1.0, n_anchors: int = 3,
               startup_speed: float = 0.15, dist: str = "uniform",
               noise: uwb.UwbNoise = uwb.PAPER003_NOISE, max_range: float = math.inf,
               anchors=None) -> Setup:
    """Validated setup of a scenario (raises InputError naming a bad option)."""
    if scenario not in _PATHS:
        raise InputError(f"scenario: expected one of {SCENARIOS}, got {scenario!r}")
    path, att, dur0 = _PATHS[scenario]()
    duration = dur0 if duration is None else float(duration)
    _check_dt(dt)
    if not (math.isfinite(duration) and duration >= 2 * dt):
        raise InputError(f"--duration: must be at least 2 Δt = {2 * dt} s, got {duration}")
    if not (math.isfinite(startup_speed) and startup_speed > 0):
        raise InputError(f"--startup-speed: must be > 0 m/s, got {startup_speed}")
    if dist not in ("uniform", "gaussian"):
        raise InputError(f"--noise: expected 'uniform' or 'gaussian', got {dist!r}")
    if not max_range > 0:
        raise InputError(f"--max-range: must be > 0 m (or inf), got {max_range}")
    if anchors is None:
        if not 3 <= int(n_anchors) <= len(ANCHORS):
            raise InputError(f"--anchors: must be in [3, {len(ANCHORS)}], got {n_anchors}")
        anchors = np.asarray(ANCHORS[: int(n_anchors)], float)
    anchors = U.validate_anchors(anchors)
    a, b = anchors[START], anchors[END]
    length = float(np.linalg.norm(b - a))
    Ts = int(round(length / (startup_speed * dt))) + 1
    if Ts < 3:
        raise InputError(f"--startup-speed: the start-up run needs at least 3 samples, got {Ts} "
                         f"({length:.3g} m at {startup_speed} m/s, Δt = {dt} s)")
    s = np.linspace(0.0, 1.0, Ts)[:, None]
    startup_pos = a[None, :] + s * (b - a)[None, :]
    T = int(round(duration / dt))
    ts = (np.arange(T) + 1) * dt
    truth = np.asarray(_planar_states_jit(path, att, jnp.asarray(ts)), dtype=np.float64)
    # The path starts at the end anchor B (where the start-up leaves the drone).
    return Setup(ts=ts, startup_pos=startup_pos, anchors=anchors, truth=truth, noise=noise,
                 dist=dist, max_range=float(max_range))


def simulate(key, setup: Setup, dtype) -> SimOut:
    """Draw one flight's measurements (jit/vmap-safe in ``key``).

    Keys by purpose: start-up ranges, flight ranges, gyro.  Ranges beyond
    ``max_range`` are not received (mask False, value NaN).
    """
    dtype = jnp.dtype(dtype)
    k_s, k_r, k_g = jax.random.split(key, 3)
    anchors = jnp.asarray(setup.anchors, dtype)
    truth = jnp.asarray(setup.truth, dtype)
    sp = jnp.asarray(setup.startup_pos, dtype)
    n = setup.noise

    def ranges(P):
        return jax.vmap(lambda p: uwb.ranges_to(p, anchors))(P)

    d_s = ranges(sp)
    d = ranges(truth[:, :2])
    z_s = d_s + uwb.sample_noise(k_s, d_s.shape, n.range_half_width, setup.dist, dtype)
    z = d + uwb.sample_noise(k_r, d.shape, n.range_half_width, setup.dist, dtype)
    g = truth[:, 7:10] + uwb.sample_noise(k_g, (truth.shape[0], 3), n.gyro_half_width, setup.dist, dtype)
    m_s = d_s <= setup.max_range
    m = d <= setup.max_range
    log = U.Log(startup_ranges=jnp.where(m_s, z_s, jnp.nan), startup_mask=m_s,
                ranges=jnp.where(m, z, jnp.nan), range_mask=m, gyro=g)
    return SimOut(truth=truth, log=log, anchors=anchors)


def evaluate(sim: SimOut, res: U.Result, cfg: U.Config):
    """Per-run metrics, per-step NEES series and counts (jit/vmap-safe)."""
    truth = sim.truth
    anchors = sim.anchors
    dtype = res.steps.mean.dtype
    if cfg.mode == "slam":
        M, o = U.startup_frame(anchors, res.startup.ref_anchor, cfg.start_anchor, cfg.end_anchor)
    else:
        M, o = jnp.eye(2, dtype=dtype), jnp.zeros((2,), dtype)
    pos_t = (truth[:, :2] - o) @ M.T
    vel_t = truth[:, 2:4] @ M.T
    anc_t = (anchors - o) @ M.T
    x_t = jnp.concatenate([pos_t, vel_t, truth[:, 4:10]], axis=1)
    st = res.steps
    e = st.mean - x_t
    e = e.at[:, 4:7].set(wrap_angle(e[:, 4:7]))
    epos = jnp.sqrt(jnp.sum(e[:, :2] ** 2, axis=1))
    deg = 180.0 / jnp.pi

    def rmse(err):
        return jnp.sqrt(jnp.mean(jnp.sum(err * err, axis=1)))

    R, t, _ = mx.umeyama(st.mean[:, :2], pos_t)
    pos_al = st.mean[:, :2] @ R.T + t
    out = {
        "pos_rmse_m": rmse(e[:, :2]),
        "pos_err_max_m": jnp.max(epos),
        "vel_rmse_mps": rmse(e[:, 2:4]),
        "yaw_rmse_deg": rmse(e[:, 6:7]) * deg,
        "att_rmse_deg": rmse(e[:, 4:7]) * deg,
        "pos_rmse_aligned_m": rmse(pos_al - pos_t),
    }
    if cfg.mode == "slam":
        act = res.final.slam.active
        L = st.landmarks[-1]
        n_act = jnp.maximum(jnp.sum(act), 1)
        err2 = jnp.sum((L - anc_t) ** 2, axis=1)
        err2_al = jnp.sum((L @ R.T + t - anc_t) ** 2, axis=1)
        out["landmark_rmse_m"] = jnp.sqrt(jnp.sum(jnp.where(act, err2, 0.0)) / n_act)
        out["landmark_rmse_aligned_m"] = jnp.sqrt(jnp.sum(jnp.where(act, err2_al, 0.0)) / n_act)
        ini = res.startup.initialised
        e0 = jnp.sum((res.startup.landmarks - anc_t) ** 2, axis=1)
        out["init_landmark_err_m"] = jnp.sqrt(jnp.sum(jnp.where(ini, e0, 0.0)) / jnp.maximum(jnp.sum(ini), 1))
        ref = jnp.clip(res.startup.ref_anchor, 0, anchors.shape[0] - 1)
        out["init_trilat_err_m"] = jnp.where(res.startup.ref_anchor >= 0, jnp.sqrt(e0[ref]), jnp.nan)
        out["landmarks_mapped"] = jnp.sum(act).astype(dtype)
    else:
        out["init_pos_err_m"] = jnp.sqrt(jnp.sum((res.startup.robot_pos - _pos0(sim, M, o)) ** 2))
    if res.smoothed is not None:  # the RTS-smoothed trajectory, scored like the filter's
        e_s = res.smoothed - x_t
        e_s = e_s.at[:, 4:7].set(wrap_angle(e_s[:, 4:7]))
        out["smoothed_pos_rmse_m"] = rmse(e_s[:, :2])
        out["smoothed_pos_err_max_m"] = jnp.max(jnp.sqrt(jnp.sum(e_s[:, :2] ** 2, axis=1)))
        out["smoothed_vel_rmse_mps"] = rmse(e_s[:, 2:4])
        out["smoothed_yaw_rmse_deg"] = rmse(e_s[:, 6:7]) * deg
        out["smoothed_att_rmse_deg"] = rmse(e_s[:, 4:7]) * deg
    nees_robot = jax.vmap(_nees)(e, st.cov)
    nees_pos = jax.vmap(_nees)(e[:, :2], st.cov[:, :2, :2])
    out["nees_pos_mean"] = jnp.mean(nees_pos)
    out["nees_robot_mean"] = jnp.mean(nees_robot)
    series = {"nees_robot": nees_robot, "nees_pos": nees_pos, "nis": st.nis, "nis_dof": st.dof,
              "pos_err_m": epos, "pending": st.pending}
    counts = {
        "masked": res.final.masked,
        "near": res.final.near,
        "status": res.final.slam.status,
        "non_finite": jnp.logical_not(jnp.all(jnp.isfinite(st.mean)) & jnp.all(jnp.isfinite(st.cov))
                                      ).astype(jnp.int32),
        "nees_undefined": jnp.sum(~jnp.isfinite(nees_robot)).astype(jnp.int32),
        "unmapped_at_end": jnp.sum(~res.final.slam.active).astype(jnp.int32),
        "startup_status": res.startup.status,
    }
    if res.smooth_status is not None:
        counts["smoother_failed"] = jnp.sum(res.smooth_status != 0).astype(jnp.int32)
    return {"metrics": out, "series": series, "counts": counts}


def _pos0(sim: SimOut, M, o):
    # True position at t = 0 (the end anchor: the start-up ends there), in the comparison frame.
    return (sim.anchors[END] - o) @ M.T


def consistency(series, t, runs):
    """ANEES (robot 10 states and position 2) per step with 95 % bounds; windows; mean NIS."""
    out = {}
    t = np.asarray(t)
    per_step_all = {}
    for name, n in (("robot", U.NR), ("pos", 2)):
        nees = np.asarray(series[f"nees_{name}"], float)
        per_step = np.nanmean(nees, axis=0)
        lo, hi = mx.anees_bounds(n, runs)
        wins = []
        for w0 in np.arange(0.0, t[-1] - 1e-9, WINDOW_S):
            sel = (t > w0) & (t <= w0 + WINDOW_S)
            if np.any(sel):
                cnt = int(np.sum(np.isfinite(nees[:, sel])))
                a = float(np.nanmean(nees[:, sel]))
                wlo, whi = mx.mean_chi2_bounds(n * max(cnt, 1), max(cnt, 1))
                wins.append({"t0_s": float(w0), "t1_s": float(min(w0 + WINDOW_S, t[-1])), "anees": a,
                             "per_step_bounds_inside": bool(lo <= a <= hi)})
        out[name] = {"anees": float(np.mean(per_step)), "bounds": [float(lo), float(hi)], "dof": n,
                     "fraction_steps_in_bounds": mx.steps_inside(per_step, (lo, hi)),
                     "windows": wins,
                     # NEES spread: a χ²(n) has variance 2n; uniform noise gives a narrower one.
                     "nees_var_over_2n": float(np.nanvar(nees) / (2 * n)),
                     "fraction_nees_above_chi2_95": float(np.nanmean(nees > mx.chi2_ppf_np(0.95, n)))}
        per_step_all[name] = per_step
    nis = np.asarray(series["nis"], float)
    dof = np.asarray(series["nis_dof"], float)
    tot = float(dof.sum())
    nlo, nhi = mx.mean_chi2_bounds(tot, tot) if tot > 0 else (math.nan, math.nan)
    out["nis_mean"] = float(nis.sum() / tot) if tot > 0 else math.nan
    out["nis_bounds"] = [float(nlo), float(nhi)]
    return out, per_step_all


POS_BLOCK = "position (x, y)"
ROBOT_BLOCK = "robot block (x, y, v_x, v_y, roll, pitch, yaw, 3 body rates)"
NIS_BLOCK = "UWB ranges and gyro rates, per degree of freedom"


def consistency_summary(cons):
    """The run JSON's ``consistency`` from :func:`consistency`'s first output: the headline
    position ANEES (``anees``), the 10-state robot-block ANEES (``anees_robot``) and the mean NIS,
    each with its bounds, ``_block`` and ``_dim`` (docs/cli.md, "consistency")."""
    return {"anees": cons["pos"]["anees"], "anees_bounds": cons["pos"]["bounds"],
            "anees_block": POS_BLOCK, "anees_dim": cons["pos"]["dof"],
            "anees_steps_inside": cons["pos"]["fraction_steps_in_bounds"],
            "anees_robot": cons["robot"]["anees"], "anees_robot_bounds": cons["robot"]["bounds"],
            "anees_robot_block": ROBOT_BLOCK, "anees_robot_dim": cons["robot"]["dof"],
            "anees_robot_steps_inside": cons["robot"]["fraction_steps_in_bounds"],
            "nis_mean": cons["nis_mean"], "nis_bounds": cons["nis_bounds"],
            "nis_block": NIS_BLOCK, "nis_dim": 1}


# ---------------------------------------------------------------------------
# Building and running
# ---------------------------------------------------------------------------

def _json_threshold(name, v):
    """A threshold of :class:`~jaxslam.systems.uwb_slam_2d.Params` for the run JSON (counts as ints)."""
    if v is None:
        return None
    return int(np.asarray(v)) if name.endswith("_points") else float(np.asarray(v))


def _check_dt(dt) -> None:
    if not (math.isfinite(dt) and dt > 0):
        raise InputError(f"--dt: must be a positive number of seconds, got {dt}")


def _filter_params(options, dtype, params=None):
    _check_dt(float(options["dt"]))  # before the filter's Q is built from it (a --params run named Q)
    model = options["model"]
    noise = uwb.PAPER003_NOISE
    if options["filter"] == "paper":
        fp = U.paper_params(model, options["dt"], noise, dtype)
        r_scaled = False
    elif options["filter"] == "matched":
        fp = U.matched_params(model, options["dt"], noise, dtype=dtype)
        r_scaled = True
    else:
        raise InputError(f"--filter: expected 'paper' or 'matched', got {options['filter']!r}")
    if params and "filter" in params:
        d = dict(params["filter"])
        unknown = set(d) - set(U.NOISE_FIELDS) - {"r_scaled"}
        if unknown:
            raise InputError(f"params.filter: unknown entries {sorted(unknown)}; expected "
                             f"{list(U.NOISE_FIELDS) + ['r_scaled']}")
        r_scaled = bool(d.pop("r_scaled", r_scaled))
        vals = fp._asdict()
        for k, v in d.items():
            a = np.asarray(v, float)
            if k in ("Q", "P0") and a.ndim == 1:
                a = np.diag(a)
            vals[k] = jnp.asarray(a, dtype)
        fp = U.Params(**vals)
    return U.validate_params(fp), r_scaled


def params_schema(options, dtype) -> dict:
    """What a ``--params`` file may set (:mod:`jaxslam.paramfile`): the filter's parameters for
    ``--filter`` and ``--model``, and whether R is scaled with distance."""
    fp, r_scaled = _filter_params(options, dtype)
    return {"filter": {**{k: np.asarray(getattr(fp, k)) for k in U.NOISE_FIELDS}, "r_scaled": bool(r_scaled)}}


def _checked(scenario, options, dtype, params=None, plots=False):
    # The arguments of build / run_scenario checked as ``Scenario.run`` checks them.
    if scenario not in _SCENARIOS:
        raise InputError(f"scenario: expected one of {SCENARIOS}, got {scenario!r}")
    return _checked_args(_SCENARIOS[scenario], options, dtype, params, plots)


def build(scenario: str, options: dict, dtype, params=None):
    """Scenario pieces: ``(one_run, flight, cfg, filter_params, setup)``.

    ``one_run(key, fp=default, truth=None)`` -> metrics/series/counts of one flight
    (jit/vmap-safe); ``flight(key, fp, truth)`` -> (SimOut, Result).  ``fp`` (the
    filter parameters) and ``truth`` are traced, so neither recompiles.  ``options`` is
    completed and checked like the command line's options, ``dtype`` must be float32 or float64
    and ``params`` is checked against the scenario's ``--params`` schema
    (:func:`jaxslam.sim.scenarios.registry.check_options`).
    """
    options, params = _checked(scenario, options, dtype, params)
    dtype = jnp.dtype(dtype)
    mode = options["mode"]
    if mode not in ("slam", "localization"):
        raise InputError(f"--mode: expected 'slam' or 'localization', got {mode!r}")
    uwb.check_model(options["model"])
    mr = float(options["max_range"])
    setup = make_setup(scenario, options.get("duration"), float(options["dt"]), int(options["anchors"]),
                       float(options["startup_speed"]), options["noise"],
                       max_range=math.inf if mr <= 0 else mr)
    fp, r_scaled = _filter_params(options, dtype, params)
    cfg = U.Config(model=options["model"], mode=mode, dt=float(options["dt"]), r_scaled=r_scaled,
                   debias=r_scaled, start_anchor=START, end_anchor=END,
                   delayed_init=setup.anchors.shape[0] > 3, smooth=bool(options.get("smooth", False)))
    if mode == "slam" and math.isfinite(setup.max_range):
        # A layout where the start-up cannot see three anchors is a usage error, not a NaN.
        d = np.linalg.norm(setup.startup_pos[:, None, :] - setup.anchors[None], axis=-1)
        seen = (d <= setup.max_range) & (d[:, END:END + 1] <= setup.max_range)
        n_pts = seen.sum(axis=0)
        if not seen[0, END] or sum(1 for i in range(len(n_pts)) if i not in (START, END)
                                   and n_pts[i] >= fp.startup_min_points) < 1:
            raise InputError(f"--max-range: fewer than three anchors in range during the start-up "
                             f"(samples in range per anchor: {n_pts.tolist()})")
    if mode == "localization" and math.isfinite(setup.max_range):
        # the t = 0 fix (or a later start-up sample's) needs three anchors in range; without one
        # every run started from the anchors' centroid, flagged DEGENERATE only
        d = np.linalg.norm(setup.startup_pos[:, None, :] - setup.anchors[None], axis=-1)
        in_range = (d <= setup.max_range).sum(axis=1)
        if in_range.max() < 3:
            raise InputError(f"--max-range: fewer than three anchors in range at every start-up sample "
                             f"(at most {int(in_range.max())}): the position fix at t = 0 cannot be made")

    anchors_known = jnp.asarray(setup.anchors, dtype)

    def flight(key, fp=fp, truth=None):
        # ``truth`` (T, 10) may replace the scenario's (e.g. another path of the same length,
        # traced): one compiled function then serves every scenario of that length.
        stp = setup if truth is None else setup._replace(truth=truth)
        sim = simulate(key, stp, dtype)
        log = sim.log._replace(anchors=anchors_known) if mode == "localization" else sim.log
        res = U.run(log, cfg, fp)
        return sim, res

    def one_run(key, fp=fp, truth=None, detail=False):
        sim, res = flight(key, fp, truth)
        out = evaluate(sim, res, cfg)
        if detail:  # run 0's flight for the plots, from the program that computes the metrics
            out["detail"] = {"sim": sim, "result": res, "eval": {k: v for k, v in out.items()}}
        return out

    return one_run, flight, cfg, fp, setup


def run_scenario(scenario, runs, seed, dtype, options, progress, params=None, plots=False):
    """Monte Carlo over ``runs`` seeded flights; see the module docstring."""
    options, params = _checked(scenario, options, dtype, params, plots)
    one_run, flight, cfg, fp, setup = build(scenario, options, dtype, params)
    mc = monte_carlo.run(lambda k: one_run(k, detail=plots), seed, runs, chunk=options.get("chunk"),
                         progress=progress, detail=plots,
                         program_key=program_key(f"uwb-{scenario}", options, params, dtype))
    runs = mc.runs  # the finished runs: fewer than asked when interrupted (Ctrl-C)
    out = mc.out
    cons, per_step = consistency(out["series"], setup.ts, runs)
    counts = out["counts"]
    from ...errors import decode

    status_any = int(np.bitwise_or.reduce(np.asarray(counts["status"]).ravel()))
    flags = {
        "capacity_overflow": 0,
        "masked_measurements": int(np.sum(counts["masked"])),
        "near_anchor_skipped": int(np.sum(counts["near"])),
        "non_finite": int(np.sum(counts["non_finite"])),
        "nees_undefined_steps": int(np.sum(counts["nees_undefined"])),
        "runs_with_unmapped_anchors": int(np.sum(np.asarray(counts["unmapped_at_end"]) > 0)),
        "degenerate_startups": int(np.sum((np.asarray(counts["startup_status"]) & 8) > 0)),
    }
    if cfg.smooth:
        flags["smoother_failed_steps"] = int(np.sum(counts["smoother_failed"]))
    metrics = dict(out["metrics"])

    def plot(directory):
        from ...plotting import uwb as uplot

        d = out["detail"]
        sim, res, ev = d["sim"], d["result"], d["eval"]
        return uplot.plot_all(f"uwb-{scenario}", sim, res, ev, setup, cfg, per_step, cons, runs,
                              directory)

    config = {
        "scenario": scenario,
        "anchors_world_m": setup.anchors.tolist(),
        "start_anchor": START,
        "end_anchor": END,
        "startup_samples": int(setup.startup_pos.shape[0]),
        "steps": int(setup.ts.shape[0]),
        "duration_flown_s": _duration_flown(setup.ts.shape[0], float(options["dt"])),  # whole steps of dt
        "frame": ("start-up frame (origin end anchor, +x start->end, +y towards the trilaterated "
                  "anchor)" if cfg.mode == "slam" else "anchors' (world) frame"),
        "noise_half_widths": {"range_m": setup.noise.range_half_width,
                              "gyro_radps": setup.noise.gyro_half_width},
        "filter_params": {k: np.asarray(getattr(fp, k), float).tolist() for k in U.NOISE_FIELDS},
        # the thresholds are Params fields (traced) but are reported with the static choices
        "estimator": {**cfg._asdict(), **{k: _json_threshold(k, getattr(fp, k)) for k in U.Params._fields
                                          if k not in U.NOISE_FIELDS}},
        **options,
    }
    return ScenarioResult(
        config=config,
        metrics=metrics,
        consistency=consistency_summary(cons),
        flags=flags,
        timing={"compile_s": mc.compile_s, "run_s": mc.run_s},
        interrupted=mc.interrupted,
        plot=plot if plots else None,
        extra={"status_flags": decode(status_any), "consistency_detail": cons,
               "max_pos_err_m": float(np.max(np.asarray(metrics["pos_err_max_m"])))},
    )


_SCENARIOS: dict = {}  # "circle" -> its registered Scenario (the options build checks against)


def _register(sc):
    _SCENARIOS[sc] = register(Scenario(
        name=f"uwb-{sc}",
        description=DECLARED[f"uwb-{sc}"].description,
        options=DECLARED[f"uwb-{sc}"].options,
        run=lambda runs, seed, dtype, options, progress, params=None, plots=False: run_scenario(
            sc, runs, seed, dtype, options, progress, params, plots),
        params=params_schema,
    ))


for _sc in SCENARIOS:
    _register(_sc)
