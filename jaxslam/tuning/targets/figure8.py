"""Tuning target: the DF-LQR weights on the figure-8 (``track-figure8 --target lqr``).

The weights Q̃, R̃ of paper 000 Table 2, by the gradient of a closed-loop cost through the
differentiable CARE and the simulation scan (the controller on the truth).

With the controller on the truth the scenario's flight is deterministic,
  so training and held-out runs differ by a random initial state (hover at a position offset
  of σ = 0.5 m per axis, yaw σ = 0.1 rad; ``start_sigma``); the nominal start (the flight of
  ``jaxslam run track-figure8``) is reported as well.  Cost per run (fixed evaluation
  weights, not the tuned ones): J = mean_t ‖ρ − ρ_d‖² + w_u mean_t ‖ũ‖², ũ the LQR correction
  (m/s², rad/s) recomputed from the flown states, w_u = 0.1 by default.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import InputError, check_flag
from .. import params as P
from . import Target, DECLARED, _check_keywords, diag_list, keys, register_target

__all__ = ['figure8_lqr', 'tracking_and_effort']


def tracking_and_effort(fl, ctrl, traj, K, feedforward: bool, refs=None):
    """(mean_t ‖ρ − ρ_d‖², mean_t ‖ũ‖²) of a flight: ũ the LQR correction recomputed from the flown
    true states with gain ``K`` (the yardstick both closed-loop targets score weights by).
    ``refs``: the flight's reference grid (:func:`jaxslam.sim.simulate.reference_grid`, flat over
    the T control steps) when the caller has it; computed here otherwise."""
    from ...control import dflqr

    dtype = fl.truth.dtype
    T = fl.u.shape[0]
    if refs is None:
        refs = jax.vmap(lambda tt: dflqr.reference_at(tt, traj, ctrl, feedforward=feedforward,
                                                      dtype=dtype))(fl.t[:T])

    def utilde(x, ref):
        _, info = dflqr.control_ref(x, ref, K, ctrl, feedforward=feedforward)
        return info.u_lqr - ref.u_d

    ut = jax.vmap(utilde)(fl.truth[:T], refs)
    e = fl.truth[:, :3] - fl.ref[:, :3]
    return jnp.mean(jnp.sum(e * e, axis=1)), jnp.mean(jnp.sum(ut * ut, axis=1))


def _lqr_run(ctrl, x0, key, traj, nf, feedforward, w_u, checkpoint):
    """Closed-loop figure-8 from ``x0``; returns per-run metrics incl. the cost J."""
    from ...control import dflqr
    from ...sim.scenarios.tracking import FRAME_STEPS, make_setup, tracking_metrics
    from ...sim.simulate import simulate

    dtype = x0.dtype
    setup = make_setup(traj, dtype, ctrl=ctrl, x0=x0)
    K = dflqr.gain(ctrl, dtype)
    fl = simulate(setup, key, nf, FRAME_STEPS, K=K, feedforward=feedforward, checkpoint=checkpoint)
    track, effort = tracking_and_effort(fl, ctrl, traj, K, feedforward)
    m = tracking_metrics(fl.t, fl.truth, fl.ref)
    m = {k: m[k] for k in ("track_pos_rmse_m", "track_pos_rmse_settled_m", "track_yaw_rmse_deg", "max_tilt_deg")}
    m.update(closed_loop_cost=track + jnp.asarray(w_u, dtype) * effort, tracking_ms_m2=track,
             effort_ms=effort)
    return m


def figure8_lqr(loss: str = "cost", train_runs: int = 4, test_runs: int = 8, seed: int = 0,
                dtype=jnp.float64, train_duration: float = 25.0, eval_duration: float = 50.0,
                w_u: float = 0.1, start_sigma: float = 0.5, feedforward: bool = True,
                checkpoint: bool = True, **_ignored) -> Target:
    """Target: DF-LQR weights Q̃ (7), R̃ (4) on ``track-figure8`` (paper 000 eq. 10-13).

    Cost per run J = mean ‖ρ − ρ_d‖² + ``w_u`` · mean ‖ũ‖² (module docstring) through the
    differentiable CARE (:func:`jaxslam.control.lqr.care`) and the closed-loop scan.
    Log-diagonal parametrisation started from Table 2 (R̃ per errata).  Training and test
    runs start from random hover offsets (``start_sigma`` m per axis, yaw σ 0.1 rad; drawn in
    float64 when x64 is on, whatever ``dtype``, so one seed gives the same starts rounded); the
    evaluation also reports the nominal start of ``jaxslam run track-figure8``.  ``w_u`` and
    ``start_sigma`` are finite numbers >= 0, ``feedforward`` and ``checkpoint`` True or False
    (else InputError naming each).
    """
    _check_keywords(_ignored, "track-figure8 --target lqr")
    from ...control import dflqr
    from ...dynamics import euler_ned
    from ...sim.scenarios.tracking import FRAME_STEPS, controller_to_dict, paper000_figure8
    from ...linalg import check_float_dtype, check_scalar
    from ...sim.simulate import n_frames

    dtype = check_float_dtype(dtype)
    # NaN or negative gave a NaN or negative cost (whose log the fit takes); "no" was a truthy flag
    w_u = check_scalar(w_u, "w_u", lower=0)
    start_sigma = check_scalar(start_sigma, "start_sigma", lower=0)
    feedforward = check_flag(feedforward, "feedforward")
    checkpoint = check_flag(checkpoint, "checkpoint")
    if loss != "cost":
        raise InputError(f"--loss: the lqr target uses the closed-loop cost ('cost'), got {loss!r}")
    base = dflqr.paper000_params()
    specs = {"Q": P.CovSpec("diag", 7), "R": P.CovSpec("diag", 4)}
    theta0 = P.pack(specs, {"Q": np.asarray(base.Q), "R": np.asarray(base.R)}, dtype=dtype)
    traj = paper000_figure8(3.0, 0.0)
    nf_train = n_frames(train_duration, 0.01, FRAME_STEPS)
    nf_eval = n_frames(eval_duration, 0.01, FRAME_STEPS)

    def physical(theta):
        m = P.unpack(specs, theta)
        return base._replace(Q=m["Q"], R=m["R"])

    # drawn in the wider of dtype and JAX's default float, then cast (as linear_gaussian does): a
    # float32 target starts from the float64 target's states, rounded (drawn in float32 they were unrelated)
    wide = jnp.promote_types(dtype, jnp.result_type(float))

    def starts(s, runs):
        ks = keys(s, runs)

        def one(k):
            k1, k2, k3 = jax.random.split(k, 3)
            pos = (start_sigma * jax.random.normal(k1, (3,), wide)).astype(dtype)
            yaw = (0.1 * jax.random.normal(k2, (), wide)).astype(dtype)
            return {"x0": euler_ned.hover_state(pos, yaw, dtype=dtype), "key": k3}

        return jax.vmap(one)(ks)

    def loss_fn(theta, item):
        m = _lqr_run(physical(theta), item["x0"], item["key"], traj, nf_train, feedforward, w_u, checkpoint)
        return m["closed_loop_cost"]

    train = starts(seed, train_runs)
    test = starts(seed + 1, test_runs)
    nominal = {"x0": euler_ned.hover_state(dtype=dtype), "key": keys(seed + 1, 1)[0]}

    @jax.jit
    def _eval(ctrl, items):
        return jax.vmap(lambda it: _lqr_run(ctrl, it["x0"], it["key"], traj, nf_eval, feedforward, w_u,
                                            False))(items)

    def evaluate(physicals):
        res = {}
        for label, ctrl in physicals.items():
            ctrl = ctrl._replace(Q=jnp.asarray(ctrl.Q, dtype), R=jnp.asarray(ctrl.R, dtype))
            out = jax.tree.map(np.asarray, _eval(ctrl, test))
            nom = jax.tree.map(np.asarray, _eval(ctrl, jax.tree.map(lambda a: a[None], nominal)))
            metrics = dict(out)
            metrics.update({f"nominal_{k}": v for k, v in nom.items()
                            if k in ("closed_loop_cost", "track_pos_rmse_m", "track_pos_rmse_settled_m")})
            res[label] = {"metrics": metrics, "consistency": None}
        return res

    def describe(theta):
        return {k: diag_list(v) for k, v in P.unpack(specs, theta).items()}

    config = {"train_duration_s": float(train_duration), "eval_duration_s": float(eval_duration),
              "train_seed": int(seed), "test_seed": int(seed + 1), "train_runs": int(train_runs),
              "test_runs": int(test_runs), "w_u": float(w_u), "start_sigma_m": float(start_sigma),
              "start_yaw_sigma_rad": 0.1, "feedforward": bool(feedforward), "checkpoint": bool(checkpoint),
              "dtype": dtype.name,
              "cost": "mean_t |rho - rho_d|^2 + w_u mean_t |u_tilde|^2 (u_tilde: LQR correction)",
              "evaluation": f"closed loop {eval_duration:g} s from held-out random starts "
                            f"(keys_for({seed + 1}, {test_runs})) and from the nominal start"}
    return Target(scenario="track-figure8", target="lqr", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={}, to_params=lambda c: {"controller": {k: v for k, v in controller_to_dict(c).items()
                                                                     if k in ("Q", "R")}},
                  describe=describe, config=config,
                  eval_command="jaxslam run track-figure8 --params TUNED.json",
                  eval_note="flies from the nominal start",
                  log_objective=True)


register_target("track-figure8", "lqr", figure8_lqr, DECLARED[("track-figure8", "lqr")])
