"""Tuning target: the Plaza range-only SLAM's noise learned from its logs, ``jaxslam tune plaza``.

The loss is the innovation negative log-likelihood per range of the training sequences' whole
logs — every range of an initialised beacon against the filter's own predicted variance,
through the same jitted scan ``jaxslam dataset plaza`` runs (beacons unknown: SLAM with
delayed initialisation) — differentiated end to end.  No ground truth (GPS) enters the loss:
it is used only for the held-out ATE.  The delayed initialisation is differentiated too (the
beacon's trilateration moves with the buffered positions and the bias; which rows it keeps and
when it fires are held constant, as every comparison is).

Parametrisation (log-parametrised, positive by construction): θ = {"log_noise": log [σ_r,
α_d, α_θ, β_θ, σ_d0, σ_θ0, q_b]} — the range σ [m] and the odometry noise of
:class:`jaxslam.systems.plaza_range.Params` (ODO): distance and heading noise per metre/radian
moved, heading noise per metre, their time floors, the bias random-walk density.  The
likelihood is Student-t with ν = 5 and no hard gate (as the UTIL and MRCLAM targets; a gate
drops the disagreeing rows from the likelihood).

Protocol (docs/datasets.md): fit on one sequence, evaluate on the other (``--robots 1
--test-robots 2`` and the reverse); ``--test-robots none`` evaluates the training sequences
themselves.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...data import catalogue
from ...errors import InputError
from . import (DECLARED, DEFAULT_ROBOTS, dataset_eval_command, STUDENT_T_NU, Target, _check_keywords, _check_robots,
               _check_window, heldout_nll, metrics_entry, register_target)

__all__ = ["plaza_logs", "plaza_noise", "NOISE_FIELDS", "NU"]

#: the learned fields of ``plaza_range.Params``, in θ's order
NOISE_FIELDS = ("sigma_r", "alpha_d", "alpha_th", "beta_th", "sigma_d0", "sigma_th0", "q_bias")
#: Student-t degrees of freedom of the fitted range likelihood (fixed)
NU = STUDENT_T_NU


def plaza_logs(data, sequences, dtype=jnp.float64, t_max: float | None = None):
    """The Plaza sequences as ``jaxslam dataset plaza`` runs them (beacons unknown).

    Returns ``[(log, data, gt), ...]``: the :class:`jaxslam.systems.plaza_range.Log`, the loaded
    :class:`~jaxslam.data.plaza.PlazaData` and its GPS poses with the heading offset applied.
    ``t_max``: keep the first seconds of each log (the fit window).
    """
    from ...data.plaza import load_plaza
    from ...systems import plaza_range as pr

    t_max = _check_window(t_max)  # a string was a bare TypeError, NaN or a negative window a message naming t_end
    out = []
    for r in sequences:
        d = load_plaza(data, int(r))
        ev = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range)
        if t_max is not None:
            span = float(ev.t[-1] - ev.t[0])
            if t_max > span:
                raise InputError(f"--window: Plaza {r}'s log covers {span:.1f} s, shorter than the {t_max:g} s "
                                 f"fit window; give --window {int(span)} or less")
            ev = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range, t_end=float(ev.t[0]) + t_max)
        log = pr.log_from_events(ev, np.asarray(d.start_pose(), np.float64), np.asarray(d.node_id), dtype=dtype)
        gt = np.asarray(d.gt, np.float64).copy()
        gt[:, 2] = gt[:, 2] + d.heading_offset
        out.append((log, d, gt))
    return out


def plaza_noise(loss: str = "nll", data=None, robots=DEFAULT_ROBOTS["plaza"]["robots"],
                test_robots=DEFAULT_ROBOTS["plaza"]["test_robots"], dtype=jnp.float64,
                t_max: float | None = None, **_ignored):
    """Target ``jaxslam tune plaza``: the Plaza SLAM's noise from its logs.

    ``robots``: training sequences (1, 2); ``test_robots``: held out (their NLL is the test loss,
    their ATE against GPS the evaluation); empty: evaluate on the training sequences.
    """
    _check_keywords(_ignored, "plaza")
    from ...data import presets, runners
    from ...systems import plaza_range as pr

    if loss != "nll":
        raise InputError(f"--loss: the real-log targets learn by innovation likelihood only (nll); got {loss!r}")
    robots = _check_robots(robots, "robots", "--robots", allow_empty=True)  # empty: said below
    test_robots = _check_robots(test_robots, "test_robots", "--test-robots", allow_empty=True)
    t_max = _check_window(t_max)
    data = catalogue.data_root(data)
    bad = [r for r in robots + test_robots if r not in (1, 2)]
    if bad:
        raise InputError(f"--robots/--test-robots: Plaza has sequences 1 and 2, got {bad}")
    if not robots:
        raise InputError("--robots: give at least one training sequence (1, 2)")
    if set(robots) & set(test_robots):
        raise InputError(f"--test-robots: {sorted(set(robots) & set(test_robots))} also in --robots; "
                         "a held-out sequence must not be trained on")
    train = plaza_logs(data, robots, dtype, t_max)
    eval_seq = test_robots or robots
    ev_logs = plaza_logs(data, eval_seq, dtype)
    base = presets.plaza_params(preset="hand")
    theta0 = {"log_noise": jnp.log(jnp.asarray([getattr(base, f) for f in NOISE_FIELDS], dtype))}
    cfg = pr.Config()

    def physical(th):
        s = jnp.exp(jnp.asarray(th["log_noise"], dtype))
        return base._replace(**{f: s[i] for i, f in enumerate(NOISE_FIELDS)}, gate=None, nu=NU)

    def loss_fn(th, item):
        p = physical(th)
        tot = cnt = 0.0
        for lg in item:  # the sequences differ in length: one program each, summed
            r = pr.run(lg, cfg, p)
            tot, cnt = tot + jnp.sum(r.nll), cnt + jnp.sum(r.nll_dof)
        return tot / jnp.maximum(cnt, 1.0)

    def batch(logs):
        return tuple(jax.tree.map(lambda a: a[None], lg) for lg, _, _ in logs)

    def evaluate(labelled):
        out = {}
        for label, prm in labelled.items():
            m = {"ate_m": [], "nll": [], "map_err_m": [], "range_bias_m": [], "outlier_fraction": []}
            for lg, d, gt in ev_logs:
                res = pr.run(lg, cfg, prm)
                est = np.concatenate([np.asarray(res.pos, np.float64),
                                      np.asarray(res.heading, np.float64)[:, None]], 1)
                act = np.asarray(res.active)
                mm, _ = runners.evaluate_planar(np.asarray(lg.t), est, d.gt_t, gt,
                                                lm=np.asarray(res.landmarks, np.float64)[act],
                                                lm_ids=np.asarray(res.landmark_ids)[act], lm_true=d.node_xy,
                                                lm_true_ids=np.asarray(d.node_id))
                m["ate_m"].append(mm["ate_m"])
                m["map_err_m"].append(mm.get("map_err_m", np.nan))
                m["nll"].append(heldout_nll(res))
                m["range_bias_m"].append(float(res.bias_final))
                m["outlier_fraction"].append(float(np.sum(res.n_outliers)) / max(float(np.sum(res.n_monitored)), 1.0))
            out[label] = metrics_entry(m)
        return out

    def describe(th):
        p = physical(th)
        return {f: [float(getattr(p, f))] for f in NOISE_FIELDS}

    def to_params(p):
        return {"dataset": "plaza", "noise": presets.plaza_params_to_dict(p)}

    return Target(
        scenario="plaza", target="noise", loss="nll", specs={}, theta0=theta0, loss_fn=loss_fn,
        train=batch(train), test=batch(ev_logs) if test_robots else None,
        physical=physical, evaluate=evaluate, references={"hand_gaussian_gated": base},
        to_params=to_params, describe=describe,
        config={"dataset": "plaza", "robots": list(robots), "test_robots": list(test_robots),
                "evaluated_on": (f"held-out sequences {list(test_robots)} (whole logs)" if test_robots else
                                 f"the training sequences {list(robots)} (whole logs; nothing held out)"),
                "t_max_s": t_max, "nu": NU, "filter": "beacons unknown (SLAM, delayed initialisation), Student-t "
                                                      "ranges (nu fixed), no gate",
                "parametrisation": "log " + ", ".join(NOISE_FIELDS),
                "loss": "Student-t innovation NLL per range over the training logs"},
        eval_command=dataset_eval_command("plaza", eval_seq),  # one command per evaluated sequence
        sequential=True,
    )


register_target("plaza", "noise", plaza_noise, DECLARED[("plaza", "noise")])
