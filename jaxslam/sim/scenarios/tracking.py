"""Scenarios ``track-figure8`` (paper 000) and ``track-helix`` (paper 001).

DF-LQR trajectory tracking on the true state (no estimator), IMU noise
simulated on the way.  Metrics:

* ``track_pos_rmse_m``: √(mean_t ‖ρ(t) − ρ_d(t)‖²) over the whole flight (3D norm);
* ``track_pos_rmse_settled_m``: the same over t > 10 s;
* ``track_yaw_rmse_deg``: RMS of the wrapped ψ − ψ_d;
* ``max_tilt_deg``: max over the flight of acos(cos φ cos θ) (angle of b̂3 from n̂3);
* ``settle_time_s``: the first time after which ‖ρ − ρ_d‖ stays below 0.1 m
  (``SETTLE_TOL_M``) for the rest of the flight (the duration if it never does; a
  non-finite error counts as outside).
"""

from __future__ import annotations


import jax.numpy as jnp
import numpy as np

from ... import metrics
from ...control import dflqr, trajectories
from ...dynamics import euler_ned
from ...errors import InputError, has_bool
from ...linalg import check_numbers, check_scalar, list_array, wrap_angle
from ...sensors import imu as imu_mod
from ...sensors import lidar3d
from .. import monte_carlo
from ..simulate import FlightSetup, n_frames, simulate
from .builtin import DECLARED
from .registry import Scenario, ScenarioResult, _duration_flown, program_key, register

SETTLE_TOL_M = 0.1
SETTLED_AFTER_S = 10.0
DT = 0.01  # control / IMU step [s] (100 Hz)
FRAME_STEPS = 10  # control steps per sensor frame (10 Hz LiDAR)

__all__ = ["tracking_metrics", "make_setup", "paper000_figure8", "controller_to_dict",
           "controller_from_dict", "SETTLE_TOL_M", "SETTLED_AFTER_S", "DT"]


def paper000_figure8(altitude: float = 3.0, ramp: float = 0.0):
    """The figure-8 of jaxslam's paper-000 scenarios (the paper gives no numbers).

    Gerono lemniscate 10 m × 5 m (a_x = 5, a_y = 2.5), period 25 s (two loops in
    50 s), heading along the path (the forward-looking LiDAR sweeps the landmark
    field; with a fixed heading its ±45° field of view sees only the landmarks to
    the north), centre above the origin at ``altitude`` metres (NED z = −altitude).  With ``ramp = 0`` the reference starts on the figure-8
    while the vehicle starts at rest at the origin, as in the paper.
    """
    for v, nm in ((altitude, "altitude"), (ramp, "ramp")):
        if isinstance(v, (bool, np.bool_)):  # check_scalar took True as 1 m / 1 s
            raise InputError(f"{nm}: expected a finite scalar, got {v!r}")
    altitude = check_scalar(altitude, "altitude")  # NaN failed only when traced ("center: ...")
    ramp = check_scalar(ramp, "ramp", lower=0)  # a negative blend was flown as 0
    return trajectories.Figure8(center=(0.0, 0.0, -float(altitude)), ramp_time=float(ramp),
                                heading_along_path=1.0)


def controller_to_dict(ctrl) -> dict:
    """JSON-ready DF-LQR parameters (Q̃, R̃ as full matrices, PD gains)."""
    return {
        "Q": np.asarray(ctrl.Q, float).tolist(),
        "R": np.asarray(ctrl.R, float).tolist(),
        "kp": np.asarray(ctrl.pd.kp, float).tolist(),
        "kd": np.asarray(ctrl.pd.kd, float).tolist(),
    }


def controller_from_dict(d: dict, default):
    """DF-LQR parameters from a (partial) dict of ``--params``: Q, R (matrices or diagonals), kp, kd.

    A bad entry is an :class:`InputError` naming the key as written, ``params.controller.KEY``
    (:func:`jaxslam.control.dflqr.validate` is given these names for the keys of ``d``; a
    field taken from ``default`` keeps its own name, ``params.Q`` / ``params.pd.kp``).
    """
    if not isinstance(d, dict):  # a string was read as its letters: "unknown entries ['a', ...]"
        raise InputError(f"params.controller: expected a dict of Q, R, kp, kd, got {type(d).__name__}")
    unknown = set(d) - {"Q", "R", "kp", "kd"}
    if unknown:
        raise InputError(f"params.controller: unknown entries {sorted(unknown)}; expected Q, R, kp, kd")
    out = default
    for k in ("Q", "R"):
        if k in d:
            a = check_numbers(d[k], f"params.controller.{k}")  # "1.5" was parsed as a number
            _refuse_bools(d[k], f"params.controller.{k}")
            out = out._replace(**{k: np.diag(a) if a.ndim == 1 else a})
    pd = out.pd
    for k in ("kp", "kd"):
        if k in d:
            v = check_numbers(d[k], f"params.controller.{k}")
            _refuse_bools(d[k], f"params.controller.{k}")
            # (a single number: tuple() of it raised a bare TypeError; validate names its shape)
            pd = pd._replace(**{k: tuple(v.tolist()) if v.ndim else v.item()})
    out = out._replace(pd=pd)
    return dflqr.validate(out, names={k: f"params.controller.{k}" for k in d})


def _refuse_bools(v, name: str) -> None:
    """true/false are not weights or gains (check_numbers read True as 1; paramfile refuses them)."""
    if has_bool(v):
        raise InputError(f"{name}: expected numbers, got {v!r}"[:300])


def tracking_metrics(t, truth, ref):
    """Tracking metrics (module docstring) of one flight; jit/vmap-safe, scalars out.

    ``t`` (T,), ``truth`` (T, 12) and ``ref`` (T, 4) (:class:`jaxslam.sim.simulate.Flight`'s),
    T >= 1; other shapes are an :class:`InputError` naming the argument (a (1, 4) ``ref`` was
    broadcast against the whole flight).  A non-finite position error counts as outside the
    settling tolerance (it was counted as settled).  Nested lists are read as arrays (they
    raised a bare ``TypeError``).
    """
    t, truth, ref = (list_array(a, nm) for a, nm in ((t, "t"), (truth, "truth"), (ref, "ref")))
    T = np.shape(t)[0] if np.ndim(t) == 1 else None
    if T is None or T < 1:
        raise InputError(f"t: expected shape (T,) with T >= 1, got {tuple(np.shape(t))}")
    for a, nm, d in ((truth, "truth", 12), (ref, "ref", 4)):
        if np.ndim(a) != 2 or np.shape(a)[0] != T or np.shape(a)[1] < d:
            raise InputError(f"{nm}: expected shape ({T}, {d}) to match t, got {tuple(np.shape(a))}")
    e = truth[:, :3] - ref[:, :3]
    e2 = jnp.sum(e * e, axis=1)
    settled = t > SETTLED_AFTER_S
    yaw = wrap_angle(truth[:, 8] - ref[:, 3])
    tilt = jnp.arccos(jnp.clip(jnp.cos(truth[:, 6]) * jnp.cos(truth[:, 7]), -1.0, 1.0))
    outside = ~(jnp.sqrt(e2) < SETTLE_TOL_M)  # NaN is outside, not settled
    last_out = jnp.max(jnp.where(outside, jnp.arange(t.shape[0]), -1))
    settle = jnp.where(last_out < 0, t[0], t[jnp.minimum(last_out + 1, t.shape[0] - 1)])
    settle = jnp.where(last_out == t.shape[0] - 1, t[-1], settle)
    return {
        "track_pos_rmse_m": jnp.sqrt(jnp.mean(e2)),
        "track_pos_rmse_settled_m": metrics.rmse_norm_where(e, settled),  # empty window: NaN
        "track_yaw_rmse_deg": jnp.degrees(jnp.sqrt(jnp.mean(yaw * yaw))),
        "max_tilt_deg": jnp.degrees(jnp.max(tilt)),
        "settle_time_s": settle,
    }


def make_setup(traj, dtype, landmarks=None, ctrl=None, x0=None) -> FlightSetup:
    """A flight of paper 000's quadcopter on ``traj`` starting at rest at the origin."""
    ctrl = dflqr.paper000_params() if ctrl is None else ctrl
    lm = jnp.zeros((0, 3), dtype) if landmarks is None else landmarks
    x0 = euler_ned.hover_state(dtype=dtype) if x0 is None else x0
    return FlightSetup(
        traj=traj,
        ctrl=ctrl,
        imu=imu_mod.PAPER000_IMU._replace(rate=1.0 / DT),
        lidar=lidar3d.PAPER000_LIDAR,
        landmarks=lm,
        x0=x0,
        dt=DT,
    )


def _run_tracking(name, traj_factory, runs, seed, dtype, options, progress, params=None, plots=False):
    duration = float(options["duration"])  # >= one frame: its Option's lower bound (check_options)
    dtype = jnp.dtype(dtype)
    traj = traj_factory(options)
    ctrl = dflqr.paper000_params()
    if params and "controller" in params:
        ctrl = controller_from_dict(params["controller"], ctrl)
    ff = not options.get("no_feedforward", False)
    setup = make_setup(traj, dtype, ctrl=ctrl)
    nf = n_frames(duration, DT, FRAME_STEPS)

    def one(key):
        fl = simulate(setup, key, nf, FRAME_STEPS, feedforward=ff)
        m = tracking_metrics(fl.t, fl.truth, fl.ref)
        m["non_finite"] = jnp.logical_not(jnp.all(jnp.isfinite(fl.truth))).astype(jnp.int32)
        if plots:  # run 0's flight for the plots, from this same program
            m["detail"] = fl
        return m

    mc = monte_carlo.run(one, seed, runs, chunk=options.get("chunk"), progress=progress, detail=plots,
                         program_key=program_key(name, options, params, dtype))
    metrics = {k: v for k, v in mc.out.items() if k not in ("non_finite", "detail")}

    def plot(directory):
        from ...plotting import flight as fp

        fl = mc.out["detail"]
        paths = [
            fp.save(fp.trajectory_3d(fl.truth[:, :3], fl.ref[:, :3], title=f"{name}: 3D path"),
                    directory, f"{name}_trajectory3d"),
            fp.save(fp.states_over_time(fl.t, fl.truth, fl.ref, title=f"{name}: tracking"),
                    directory, f"{name}_states"),
            fp.save(fp.inputs_over_time(fl.t[1:], fl.u, title=f"{name}: inputs"),
                    directory, f"{name}_inputs"),
        ]
        return paths

    config = {
        "duration_s": duration,
        "duration_flown_s": _duration_flown(nf * FRAME_STEPS, DT),  # whole LiDAR frames
        "dt_s": DT,
        "imu_rate_hz": 1.0 / DT,
        "trajectory": {k: _jsonable(v) for k, v in traj._asdict().items()},
        "controller": controller_to_dict(ctrl),
        "feedforward": ff,
        "settle_tol_m": SETTLE_TOL_M,
        "settled_after_s": SETTLED_AFTER_S,
        **{k: v for k, v in options.items()},
    }
    return ScenarioResult(
        config=config,
        metrics=metrics,
        consistency=None,
        flags={"capacity_overflow": 0, "masked_measurements": 0,
               "non_finite": int(np.sum(mc.out["non_finite"]))},
        timing={"compile_s": mc.compile_s, "run_s": mc.run_s},
        interrupted=mc.interrupted,
        plot=plot if plots else None,
        extra={"devices": mc.n_devices},
    )


def _jsonable(v):
    a = np.asarray(v)
    return a.tolist() if a.ndim else float(a)




def _figure8(options):
    return paper000_figure8(options["altitude"], options["ramp"])


def params_schema(options, dtype) -> dict:
    """What a ``--params`` file may set (:mod:`jaxslam.paramfile`): DF-LQR weights and PD gains."""
    return {"controller": controller_to_dict(dflqr.paper000_params())}


def _helix(options):
    return trajectories.Helix()


register(Scenario(
    name="track-figure8",
    description=DECLARED["track-figure8"].description,
    options=DECLARED["track-figure8"].options,
    run=lambda runs, seed, dtype, options, progress, params=None, plots=False: _run_tracking(
        "track-figure8", _figure8, runs, seed, dtype, options, progress, params, plots),
    params=params_schema,
))

register(Scenario(
    name="track-helix",
    description=DECLARED["track-helix"].description,
    options=DECLARED["track-helix"].options,
    run=lambda runs, seed, dtype, options, progress, params=None, plots=False: _run_tracking(
        "track-helix", _helix, runs, seed, dtype, options, progress, params, plots),
    params=params_schema,
))
