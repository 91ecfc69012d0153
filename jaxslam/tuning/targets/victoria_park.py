"""Tuning target: Victoria Park's noise learned from the log's start, ``jaxslam tune victoria-park``.

The loss is the innovation negative log-likelihood per scalar of the laser rows the shipped
filter associates (nearest neighbour, Gaussian update, the preset's range limits and pruning)
over the fit window t < ``t_max`` (default 500 s, the window the hand-set preset was chosen on),
through the same scan ``jaxslam dataset victoria-park`` runs, block-checkpointed
(``jax.checkpoint`` per 128 events) — no GPS in the loss.  Which rows are associated is a
comparison and is held constant under differentiation.

Parametrisation (log-parametrised, positive by construction): θ = {"log_sigma": log [σ_v, σ_α,
σ_r, σ_β]} — the speed and steering noise densities of the Ackermann inputs and the laser's
range and bearing σ (:func:`jaxslam.data.presets.victoria_park_params`); the pose-noise floor
stays zero and the laser has no range model, as in the preset.

Cost: the map of the fit window peaks at ~133 landmarks, so the fit runs at the smallest
capacity (a multiple of 32) holding 1.25 × the peak measured at the starting point — the same
filter as at the dataset's 512 slots while no registration is refused, and ~7× cheaper to
differentiate (the covariance correction's derivative is dense).  The evaluation reports the
registrations the fit capacity would refuse in the window at each parameter set
(``refused_in_fit_window``; 0 means the fit ran the dataset's filter).

Protocol (docs/datasets.md): fit on t < 500 s, evaluate on the rest (held-out NLL of the events
after the window, ATE against the GPS fixes after 500 s and over the whole log).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ...data import catalogue
from ...errors import InputError
from . import Target, DECLARED, _check_keywords, _check_window, register_target, heldout_nll, metrics_entry, window_nll

__all__ = ["victoria_park_noise"]


def _logs(data, t_split: float):
    """The whole Victoria Park event log (as the EKF runner builds it) and its first
    ``t_split`` seconds (the events before its start + t_split, that instant excluded: it is
    held out; checked against the log's span), from one load."""
    from ...data.events import merge_events
    from ...data.victoria_park import load_victoria_park

    d = load_victoria_park(data)

    def build(t_end=None):
        return merge_events(d.input_t, d.inputs, d.det_t, d.det, K=None, input_mode="rate", t_end=t_end)

    whole = build()
    span = float(whole.t[-1] - whole.t[0])
    if not 0.0 < t_split < span:
        raise InputError(f"--window: the fit window must end inside the log (0 - {span:.0f} s), got {t_split:g} s")
    # the fit window is t < start + t_split (the held-out events are t >= it): merge_events keeps
    # t <= t_end, so an event exactly at the split was both fitted and held out
    return whole, build(float(np.nextafter(float(whole.t[0]) + t_split, -np.inf)))


def victoria_park_noise(loss: str = "nll", data=None, dtype=jnp.float64, t_max: float | None = None, **_ignored):
    """Target ``jaxslam tune victoria-park``: the EKF's input and laser noise from the log's start.

    ``t_max``: the fit window [s] (default 500); the events after it are held out.
    """
    _check_keywords(_ignored, "victoria-park")
    t_max = _check_window(t_max)
    from ...data import presets, runners
    from ...systems import planar_ekf_slam as pe

    if loss != "nll":
        raise InputError(f"--loss: the real-log targets learn by innovation likelihood only (nll); got {loss!r}")
    data = catalogue.data_root(data)
    t_split = 500.0 if t_max is None else float(t_max)
    whole, fit_log = _logs(data, t_split)
    base = presets.victoria_park_params(dtype=dtype)
    s0 = np.sqrt(np.concatenate([np.diag(np.asarray(base.M_c, np.float64)), np.diag(np.asarray(base.R, np.float64))]))
    theta0 = {"log_sigma": jnp.asarray(np.log(s0), dtype)}

    def physical(th):
        s = jnp.exp(jnp.asarray(th["log_sigma"], dtype))
        return base._replace(M_c=jnp.diag(s[:2] ** 2), R=jnp.diag(s[2:] ** 2))

    def item_of(log):
        it = pe.log_from_events(log, jnp.zeros(3, dtype))
        return jax.tree.map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating)
                            else jnp.asarray(a), it)

    train_item = item_of(fit_log)
    # capacity: the window's map at the start (peak of registered − pruned), with room to move
    probe = pe.run(train_item, presets.victoria_park_config(), physical(theta0))
    peak = int(np.max(np.cumsum(np.asarray(probe.n_registered, np.int64) - np.asarray(probe.n_pruned, np.int64))))
    cap = int(32 * math.ceil(1.25 * max(peak, 1) / 32))
    cfg = presets.victoria_park_config(capacity=cap)._replace(block=128)
    held = np.asarray(whole.t) >= float(whole.t[0]) + t_split
    test_item = item_of(whole)
    w_test = jnp.asarray(held, dtype)
    cfg_eval = presets.victoria_park_config()._replace(block=128)

    def loss_fn(th, item):
        if "w" in item:  # the held-out events of the whole log (dataset capacity)
            return window_nll(pe.run(item["log"], cfg_eval, physical(th)), item["w"])
        return window_nll(pe.run(item["log"], cfg, physical(th)))

    def evaluate(labelled):
        out = {}
        for label, prm in labelled.items():
            run = runners.run_dataset("victoria-park", data, dtype=np.dtype(dtype),
                                      params={"dataset": "victoria-park", "noise": pe.params_to_dict(prm)})
            r = pe.run(test_item, cfg_eval, prm)
            # the GPS error on each side of this target's split (the held-out NLL's), not the
            # dataset runner's fixed 500 s
            split = runners.split_ate(run.evaluation, float(whole.t[0]) + t_split, f"{t_split:g}")
            m = {"ate_m": [run.metrics["ate_m"]],
                 **{k: [split.get(k, np.nan)] for k in (f"ate_t_ge_{t_split:g}s_m", f"ate_t_lt_{t_split:g}s_m")},
                 "nll": [heldout_nll(r, held)],
                 "landmarks_mapped": [float(run.counts["landmarks_mapped"])],
                 "refused_in_fit_window": [float(pe.run(train_item, cfg, prm).overflow)],
                 "outlier_fraction": [float(run.metrics.get("outlier_fraction_mapped", np.nan))]}
            out[label] = metrics_entry(m)
        return out

    def describe(th):
        s = np.exp(np.asarray(th["log_sigma"], np.float64))
        return {"sigma_v": [float(s[0])], "sigma_a": [float(s[1])], "sigma_r": [float(s[2])], "sigma_b": [float(s[3])]}

    def to_params(p):
        return {"dataset": "victoria-park",
                "noise": {k: v for k, v in pe.params_to_dict(p).items() if k in ("M_c", "R")}}

    return Target(
        scenario="victoria-park", target="noise", loss="nll", specs={}, theta0=theta0, loss_fn=loss_fn,
        train={"log": jax.tree.map(lambda a: a[None], train_item)},
        test={"log": jax.tree.map(lambda a: a[None], test_item), "w": w_test[None]},
        physical=physical, evaluate=evaluate, references={}, to_params=to_params, describe=describe,
        config={"dataset": "victoria-park", "fit_window_s": [float(whole.t[0]), float(whole.t[0]) + t_split],
                "evaluated_on": f"the events after {t_split:g} s (held out) and the GPS fixes there; whole log beside",
                "fit_capacity": cap, "fit_window_peak_landmarks": peak,
                "filter": "the shipped EKF-SLAM (Ackermann, nn association, Gaussian update, range limits, pruning)",
                "parametrisation": "log sigma_v, sigma_a (input noise densities), sigma_r, sigma_b (laser)",
                "loss": "Gaussian innovation NLL per scalar over the fit window's associated rows"},
        eval_command="jaxslam dataset victoria-park --data DIR --params TUNED.json",
        sequential=True,
    )


register_target("victoria-park", "noise", victoria_park_noise, DECLARED[("victoria-park", "noise")])
