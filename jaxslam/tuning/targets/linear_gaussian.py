"""Tuning target: the linear-Gaussian oracle (``linear-gaussian --target noise``).

A 2D constant-velocity model with position and velocity measurements and known Q, R: the
maximum-likelihood estimate of Q, R is consistent, so NLL tuning must recover them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import InputError
from ...filters import ekf as ekf_mod
from ...linalg import (check_finite, check_float_dtype, check_int, check_numbers, check_psd, check_scalar, check_shape,
                       is_concrete)
from .. import losses as L
from .. import params as P
from . import Target, DECLARED, _check_keywords, diag_list, keys, register_target

__all__ = ['lg_simulate', 'lg_run', 'linear_gaussian', 'LG_DT', 'LG_Q_TRUE', 'LG_R_TRUE', 'FILTERS']


def _check_model(dt, **mats):
    """InputError naming the argument: ``dt`` > 0 and each matrix (4, 4) and PSD (values only
    when concrete; traced values are checked by shape only)."""
    if is_concrete(dt):
        check_scalar(dt, "dt", lower=0, strict=True)
    for name, M in mats.items():
        if M is None:
            continue
        if not hasattr(M, "shape"):
            M = check_numbers(M, name)
        check_shape(M, (4, 4), name)
        if is_concrete(M):
            check_psd(M, name)


def _sqrt_psd(M):
    """A square root L (L Lᵀ = M) of a PSD matrix: the Cholesky factor when it exists (finite),
    else the symmetric root with eigenvalues clipped at zero (a singular M); traceable."""
    C = jnp.linalg.cholesky(M)
    w, V = jnp.linalg.eigh(0.5 * (M + M.T))
    return jnp.where(jnp.all(jnp.isfinite(C)), C, V * jnp.sqrt(jnp.clip(w, 0, None)))


def _lg_model(dt):
    A = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    return A, np.eye(4)


# Chosen so every entry is identified from the innovations with good precision: position and
# velocity are both measured (a position fix and a Doppler velocity), and each process-noise
# entry is comparable to the measurement noise of the same channel, so neither swamps the other
# (with position-only measurements the position process noise is nearly confounded with R and
# 10⁴ samples pin it to no better than ±100 %).
LG_DT = 1.0
LG_Q_TRUE = (0.06, 0.08, 0.1, 0.2)  # diag Q of the oracle [m², m², (m/s)², (m/s)²] per step
LG_R_TRUE = ((0.05, 0.02, 0.0, 0.0),  # full R: correlated position noise [m²], velocity [(m/s)²]
             (0.02, 0.04, 0.0, 0.0),
             (0.0, 0.0, 0.1, 0.0),
             (0.0, 0.0, 0.0, 0.15))


def lg_simulate(key, T: int, Q, R, dt: float = LG_DT, dtype=jnp.float64):
    """Simulate the oracle x' = A x + w, z = x + v (w ~ N(0, Q), v ~ N(0, R)); T steps.

    x = [p_x, p_y, v_x, v_y]: 2D constant velocity with step ``dt``; the position and the
    velocity are measured.  Returns ``{"z": (T, 4), "x": (T, 4)}`` (state after each step;
    x_0 = 0) in ``dtype`` (a floating dtype, else :class:`InputError` naming ``dtype``).  The noise is drawn and the model simulated in the wider of
    ``dtype`` and JAX's default float (float64 with x64 on) and the result cast to ``dtype``,
    so one key gives the same data in every precision, rounded: a float32 log is the float64
    log rounded to float32 (drawn in float32, its samples were unrelated to float64's).
    A PSD but singular Q or R (Q = 0: a noise-free motion model) is drawn with its symmetric
    square root (eigenvalues clipped at zero) where its Cholesky factor does not exist (it was
    NaN, and so was every sample); a positive-definite one keeps its Cholesky draws.
    """
    T = check_int(T, "T", lower=1)
    _check_model(dt, Q=Q, R=R)
    out_dtype = check_float_dtype(dtype)  # an integer dtype truncated the simulated log
    dtype = jnp.promote_types(out_dtype, jnp.result_type(float))  # float64 with x64 on: one stream
    A, H = (jnp.asarray(a, dtype) for a in _lg_model(dt))
    Lq, Lr = _sqrt_psd(jnp.asarray(Q, dtype)), _sqrt_psd(jnp.asarray(R, dtype))
    kw, kv = jax.random.split(key)
    w = jax.random.normal(kw, (T, 4), dtype) @ Lq.T
    v = jax.random.normal(kv, (T, 4), dtype) @ Lr.T

    def step(x, wv):
        x = A @ x + wv[0]
        return x, (H @ x + wv[1], x)

    _, (z, x) = jax.lax.scan(step, jnp.zeros(4, dtype), (w, v))
    return {"z": z.astype(out_dtype), "x": x.astype(out_dtype)}


#: the filters the oracle target runs (``--filter``); on this linear model each is the KF
FILTERS = ("ekf", "ukf", "cubature")


def lg_run(Q, R, z, dt: float = LG_DT, P0=None, filter: str = "ekf"):
    """Kalman filter of the oracle over z (T, 4) with :mod:`jaxslam.filters.ekf` (``filter``
    "ekf") or the sigma-point filter of :mod:`jaxslam.filters.ukf` ("ukf": unscented points;
    "cubature"), which on this linear model is the same Kalman filter.

    Returns (means (T, 4), nis (T,), logdet (T,), dof (T,), nees-ready covs (T, 4, 4)).
    Known now, a z with NaN or Inf is an InputError naming ``z``, as is an empty z; ``P0`` (default I)
    may be a list.
    """
    from ...filters import ukf as ukf_mod

    if filter not in FILTERS:
        raise InputError(f"--filter: expected one of {', '.join(FILTERS)}, got {filter!r}")
    if not hasattr(z, "dtype"):  # a list: the same numbers as an array
        z = jnp.asarray(check_numbers(z, "z"))
    check_shape(z, (None, 4), "z")
    if z.shape[0] == 0:  # a loss over no step was silently 0 (nll) or NaN (mse)
        raise InputError("z: expected at least one measurement row, got shape (0, 4)")
    check_finite(z, "z")  # a NaN measurement made the loss NaN silently
    _check_model(dt, Q=Q, R=R, P0=P0)
    dtype = z.dtype
    A, H = (jnp.asarray(a, dtype) for a in _lg_model(dt))
    P0 = jnp.eye(4, dtype=dtype) if P0 is None else jnp.asarray(P0, dtype)  # a list broke the scan's carry
    pts = None if filter == "ekf" else (ukf_mod.unscented() if filter == "ukf" else ukf_mod.cubature())

    def step(g, zk):
        if pts is None:
            g = ekf_mod.predict(g, lambda x, u: A @ x, None, Q)
            g, info = ekf_mod.update(g, zk, lambda x: H @ x, R)
        else:
            g = ukf_mod.predict(g, lambda x, u: A @ x, None, Q, points=pts)
            g, info = ukf_mod.update(g, zk, lambda x: H @ x, R, points=pts)
        nis, logdet, dof = L.nll_terms(info.innovation, info.S)
        return g, (g.mean, nis, logdet, dof, g.cov)

    _, out = jax.lax.scan(step, ekf_mod.Gaussian(jnp.zeros(4, dtype), P0), z)
    return out


def linear_gaussian(loss: str = "nll", train_runs: int = 4, test_runs: int = 4, seed: int = 0,
                    dtype=jnp.float64, T: int = 2000, q0_scale: float = 4.0, r0_scale: float = 0.25,
                    filter: str = "ekf", **_ignored) -> Target:
    """Oracle target: diag Q (log-diagonal) and full R (log-Cholesky) of a 2D constant-velocity
    Kalman filter measuring position and velocity, with known truth (:data:`LG_Q_TRUE`, :data:`LG_R_TRUE`), started at
    ``q0_scale``·Q and ``r0_scale``·diag(R) (a diagonal first guess).  Losses nll / mse / nees on the filtered state.
    ``filter``: one of :data:`FILTERS`; the loss and its gradient run through that filter.
    ``dtype`` float64 with JAX's x64 off computes in float32, and ``config["dtype"]`` records float32."""
    if filter not in FILTERS:
        raise InputError(f"--filter: expected one of {', '.join(FILTERS)}, got {filter!r}")
    _check_keywords(_ignored, "linear-gaussian --target noise")
    T = check_int(T, "T", lower=1)
    train_runs = check_int(train_runs, "train_runs", lower=1)
    test_runs = check_int(test_runs, "test_runs", lower=1)
    q0_scale = check_scalar(q0_scale, "q0_scale", lower=0, strict=True)
    r0_scale = check_scalar(r0_scale, "r0_scale", lower=0, strict=True)
    # the dtype computed in: float64 asked for with x64 off runs in float32, and config says so
    dtype = jnp.dtype(jax.dtypes.canonicalize_dtype(check_float_dtype(dtype)))
    if loss not in ("nll", "mse", "nees"):
        raise InputError(f"--loss: expected nll, mse or nees, got {loss!r}")
    Qt, Rt = np.diag(LG_Q_TRUE), np.asarray(LG_R_TRUE)
    specs = {"Q": P.CovSpec("diag", 4), "R": P.CovSpec("chol", 4)}
    # A user's first guess has no correlation: the start is diagonal (wrong scale, wrong shape).
    theta0 = P.pack(specs, {"Q": q0_scale * Qt, "R": r0_scale * np.diag(np.diag(Rt))}, dtype=dtype)

    def physical(theta):
        return P.unpack(specs, theta)

    def data(s, runs):
        return jax.jit(jax.vmap(lambda k: lg_simulate(k, T, Qt, Rt, dtype=dtype)))(keys(s, runs))

    def loss_fn(theta, item):
        m = physical(theta)
        means, nis, logdet, dof, covs = lg_run(m["Q"], m["R"], item["z"], filter=filter)
        if loss == "nll":
            return L.innovation_nll(nis, logdet, dof)
        err = means - item["x"]
        if loss == "mse":
            return L.mse(err)
        nees = jax.vmap(lambda e, C: e @ jnp.linalg.solve(C, e))(err, covs)
        return L.nees_loss(nees, 4)

    train, test = data(seed, train_runs), data(seed + 1, test_runs)

    @jax.jit
    def _eval(Q, R, items):  # Q, R are arguments: one program for every label and call
        Q, R = jnp.asarray(Q, dtype), jnp.asarray(R, dtype)

        def per(item):
            means, nis, logdet, dof, covs = lg_run(Q, R, item["z"], filter=filter)
            err = means - item["x"]
            return {"nll": L.innovation_nll(nis, logdet, dof),
                    "pos_rmse_m": jnp.sqrt(jnp.mean(jnp.sum(err[:, :2] ** 2, 1))),
                    "vel_rmse_mps": jnp.sqrt(jnp.mean(jnp.sum(err[:, 2:] ** 2, 1)))}
        return jax.vmap(per)(items)

    def evaluate(physicals):
        res = {}
        for label, m in physicals.items():
            Q, R = (v if hasattr(v, "dtype") else np.asarray(v, float) for v in (m["Q"], m["R"]))
            res[label] = {"metrics": jax.tree.map(np.asarray, _eval(Q, R, test)), "consistency": None}
        return res

    def describe(theta):
        m = physical(theta)
        return {"Q": diag_list(m["Q"]), "R": [float(v) for v in np.asarray(m["R"]).ravel()]}

    config = {"T": int(T), "train_runs": int(train_runs), "test_runs": int(test_runs), "seed": int(seed),
              "Q_true": list(LG_Q_TRUE), "R_true": [list(r) for r in LG_R_TRUE],
              "q0_scale": float(q0_scale), "r0_scale": float(r0_scale), "dtype": dtype.name, "filter": filter}
    return Target(scenario="linear-gaussian", target="noise", loss=loss, specs=specs, theta0=theta0,
                  loss_fn=loss_fn, train=train, test=test, physical=physical, evaluate=evaluate,
                  references={"true": {"Q": Qt, "R": Rt}},
                  to_params=lambda m: {"noise": {k: np.asarray(v).tolist() for k, v in m.items()}},
                  describe=describe, config=config, log_objective=loss == "mse")


register_target("linear-gaussian", "noise", linear_gaussian, DECLARED[("linear-gaussian", "noise")])
