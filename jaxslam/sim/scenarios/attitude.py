"""Scenario ``attitude-smc``: paper 004's quaternion sliding-mode attitude simulation (ch. 3.4).

The attitude subsystem eq. 3.13 (app. B's vehicle: m = 1.3 kg, J ≈ diag(0.0119, 0.0119,
0.0219) kg m²) starts at rest 90° about [1, −7, 3]/‖·‖ and is driven to q_d = 30° about ẑ
(ch. 3.4's printed values) by the law eq. 3.20 (:mod:`jaxslam.control.smc`), under one of
app. B's perturbations ξ (rad/s², added to ω̇, eq. 3.17) bounded by
‖ξ‖ < L2 + L1‖x‖ with (L1, L2) = ``perturbation_scale`` × the admissible maxima of Theorem
3.1 in app. B's Frobenius form for the chosen gains.  25 s at dt = 1 ms (app. B), RK4 with
quaternion renormalisation, control and ξ held over each step.

Options: ``perturbation`` constant | sinusoidal | random | none; ``gains`` thesis (ch. 3.4
printed K1, K2; P from app. B's LQR) | prototype (eq. 6.1; P from the Lyapunov equation with
Q = I) | lqr (designed here by :func:`jaxslam.control.smc.lqr_gains`); ``torque`` direct
(app. B, τ = u: the code behind Figs. 3.2-3.7, default) | exact (eq. 3.15); ``tau_max`` (N m per axis, 0.18 = app. B; ≤ 0: none);
``switching`` tanh | sign; ``eps`` (tanh width); ``duration``; ``dt``;
``perturbation_scale``.

Runs are vmapped over seeds (:mod:`jaxslam.sim.monte_carlo`): only the random perturbation
differs between runs; constant and sinusoidal runs are identical.

Metrics per run: ``att_err_rms_deg`` (RMS over the run of ‖θ_e‖, θ_e = qlog(q ⊗ q_d*)),
``att_err_final_deg`` (mean ‖θ_e‖ over the last 1 s), ``rate_err_rms_dps`` (RMS of
‖ω − ω_d‖), ``max_torque`` (largest |τ_i| applied, N m), ``settle_time_s`` (first time
after which ‖θ_e‖ stays below 1°; 0 if it always is, NaN if it never settles; a non-finite
‖θ_e‖ is not below).  No filter,
so ``consistency`` is None.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ...control import smc
from ...errors import InputError
from .. import monte_carlo
from .builtin import DECLARED
from .registry import Scenario, ScenarioResult, _checked_args, _duration_flown, program_key, register

__all__ = ["SETTLE_DEG", "FINAL_WINDOW_S", "resolve_gains", "build", "run_scenario", "metrics"]

SETTLE_DEG = 1.0
FINAL_WINDOW_S = 1.0


def resolve_gains(name):
    """(SMCGains, P) for the ``gains`` option; P = None means Lyapunov with Q = I."""
    if name == "thesis":
        return smc.THESIS_SIM, np.asarray(smc.lqr_gains().P1)
    if name == "prototype":
        return smc.PROTOTYPE, None
    if name == "lqr":
        d = smc.lqr_gains()
        return smc.SMCGains(np.asarray(d.K1), np.asarray(d.K2)), np.asarray(d.P1)
    raise InputError(f"--gains: expected 'thesis', 'prototype' or 'lqr', got {name!r}")


def metrics(norms, dt):
    """Per-run metrics from :attr:`smc.Rollout.norms` (T, 3), T >= 1, at steps of ``dt`` s
    (finite, > 0); see the module docstring.  Other shapes or steps are an :class:`InputError`
    (a (T, 2) array read its rates as torques, dt = 0 was a ZeroDivisionError).  A non-finite
    ‖θ_e‖ counts as above the settling threshold (it was counted as settled)."""
    if np.ndim(norms) != 2 or np.shape(norms)[1] != 3 or np.shape(norms)[0] < 1:
        raise InputError(f"norms: expected shape (T, 3) with T >= 1, got {tuple(np.shape(norms))}")
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
        raise InputError(f"dt: expected a finite number > 0, got {dt!r}")
    norms = jnp.asarray(norms)
    dtp = norms.dtype
    T = norms.shape[0]
    deg = jnp.asarray(180.0 / math.pi, dtp)
    e, w, tq = norms[:, 0], norms[:, 1], norms[:, 2]
    n_final = max(1, min(T, int(round(FINAL_WINDOW_S / dt))))
    above = ~(e * deg < SETTLE_DEG)  # NaN is above, not settled
    idx = jnp.arange(T)
    last = jnp.max(jnp.where(above, idx, -1))
    settle = jnp.where(last < 0, 0.0, jnp.where(last >= T - 1, jnp.nan, (last + 1) * dt))
    return {
        "att_err_rms_deg": deg * jnp.sqrt(jnp.mean(e * e)),
        "att_err_final_deg": deg * jnp.mean(e[T - n_final:]),
        "rate_err_rms_dps": deg * jnp.sqrt(jnp.mean(w * w)),
        "max_torque": jnp.max(tq),
        "settle_time_s": settle.astype(dtp),
    }


def _check_options(options):
    for nm in ("duration", "dt", "eps", "perturbation_scale"):
        v = options[nm]
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise InputError(f"--{nm.replace('_', '-')}: expected a finite positive number, got {v!r}")
    if options["dt"] > options["duration"]:
        raise InputError(f"--dt: step {options['dt']} s is longer than --duration {options['duration']} s")
    tm = options["tau_max"]
    if tm is not None and not (isinstance(tm, (int, float)) and not math.isnan(tm)):
        raise InputError(f"--tau-max: expected a number (<= 0: no limit), got {tm!r}")
    smc.validate(perturbation_name=options["perturbation"], model=options["torque"],
                 switching=options["switching"])


def build(options, dtype):
    """Scenario pieces: ``(one_run, rollout, setup)``.

    ``one_run(key)`` -> metrics dict of one run (jit/vmap-safe); ``rollout(key, record)``
    -> :class:`smc.Rollout`; ``setup`` holds the resolved configuration (host side).
    ``options`` is completed and checked like the command line's options, ``dtype`` must be
    float32 or float64 (:func:`jaxslam.sim.scenarios.registry.check_options`).
    """
    options = _checked_args(SCENARIO, options, dtype)[0]
    _check_options(options)
    dtype = jnp.dtype(dtype)
    gains, P = resolve_gains(options["gains"])
    L1, L2 = smc.perturbation_bounds(gains, P, options["perturbation_scale"])
    dt = float(options["dt"])
    steps = int(round(float(options["duration"]) / dt))
    tm = options["tau_max"]
    tau_max = None if tm is None or tm <= 0 else float(tm)
    inertia = smc.PAPER004_APPB.inertia
    smc.validate(gains, inertia, dt=dt, eps=options["eps"], tau_max=tau_max)
    g = smc.SMCGains(jnp.asarray(gains.K1, dtype), jnp.asarray(gains.K2, dtype))
    xa0 = smc.initial_state(dtype)
    q_d = jnp.asarray(smc.QD_CH34, dtype)
    J = jnp.asarray(inertia, dtype)
    bounds = (jnp.asarray(L1, dtype), jnp.asarray(L2, dtype))

    def rollout(key, record=False):
        return smc.closed_loop(xa0, q_d, g, J, dt, steps, key, bounds,
                               perturbation_name=options["perturbation"], eps=options["eps"],
                               switching=options["switching"], model=options["torque"],
                               tau_max=tau_max, record=record)

    def one_run(key, detail=False):
        r = rollout(key, record=detail)
        m = metrics(r.norms, dt)
        m["non_finite"] = jnp.any(~jnp.isfinite(r.norms)).astype(jnp.int32)
        if detail:  # run 0's recorded rollout for the plots, from this same program
            m["detail"] = r
        return m

    # ξ reaches (1 − 1e-10) of the bound: that is the (L1, L2) the theorem is checked at
    shrink = 1.0 - 1e-10
    rep = smc.theorem31(np.asarray(gains.K1, float), np.asarray(gains.K2, float), L1 * shrink,
                        L2 * shrink, P)
    setup = {
        "gain_matrices": {"K1": np.asarray(gains.K1, float).tolist(), "K2": np.asarray(gains.K2, float).tolist()},
        "L1": L1, "L2": L2, "steps": steps, "tau_max_Nm": tau_max,
        "duration_flown_s": _duration_flown(steps, dt),  # whole steps of dt
        "inertia_kgm2": list(inertia), "mass_kg": smc.PAPER004_APPB.mass,
        "q0": list(smc.Q0_CH34), "q_d": list(smc.QD_CH34),
        "theorem31": {k: float(getattr(rep, k)) for k in
                      ("L1_max", "L2_max", "holds", "L1_max_rigorous", "L1_max_conservative",
                       "ball_radius", "lambda_min_Q")},
    }
    return one_run, rollout, setup


def run_scenario(runs, seed, dtype, options, progress, params=None, plots=False):
    """Monte Carlo over ``runs`` seeds; see the module docstring."""
    options, params = _checked_args(SCENARIO, options, dtype, params, plots)  # no --params schema: refused there
    one_run, rollout, setup = build(options, dtype)
    mc = monte_carlo.run(lambda k: one_run(k, detail=plots), seed, runs, progress=progress, detail=plots,
                         program_key=program_key("attitude-smc", options, params, dtype))
    out = dict(mc.out)
    recorded = out.pop("detail", None)
    non_finite = int(np.sum(out.pop("non_finite")))
    dt = float(options["dt"])

    def plot(directory):
        from ...plotting import attitude as aplot

        name = f"attitude-smc_{options['perturbation']}_{options['gains']}"
        return aplot.plot_all(name, dt, recorded, np.asarray(smc.QD_CH34), directory,
                              tau_max=setup["tau_max_Nm"])

    config = {"model": "paper 004 eq. 3.13 attitude, RK4 + renormalisation",
              "dt": dt, "duration": float(options["duration"]), **setup, **options}
    return ScenarioResult(
        config=config,
        metrics={k: np.asarray(v) for k, v in out.items()},
        consistency=None,
        flags={"capacity_overflow": 0, "masked_measurements": 0, "non_finite": non_finite},
        timing={"compile_s": mc.compile_s, "run_s": mc.run_s},
        interrupted=mc.interrupted,
        plot=plot if plots else None,
        extra={"theorem31": setup["theorem31"]},
    )


OPTIONS = DECLARED["attitude-smc"].options  # declared in builtin.py (read there without JAX)

SCENARIO = register(Scenario(
    name="attitude-smc",
    description=DECLARED["attitude-smc"].description,
    options=OPTIONS,
    run=run_scenario,
))
