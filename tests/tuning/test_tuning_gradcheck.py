"""Gradients of every loss against central finite differences (float64, 1e-4 relative).

The linear-Gaussian check of all three losses runs by default; the EKF-SLAM log filter (1 s
log) and the closed-loop LQR cost (2 s) are marked slow to keep the default suite under its
time budget (they mostly compile gradients).  In the default suite the EKF-SLAM filter's
gradient is checked against finite differences by
``tests/systems/test_systems_ekf_slam_3d.py`` and the UWB filter's by ``test_tuning_uwb.py``.
Longer logs and more directions: ``scripts/reproduce_tuning.py --parts gradcheck``
(``docs/results/tuning/gradcheck.json``: worst relative error 1.9e-7).

Directional derivatives: for a few random unit directions d, (L(θ + h d) − L(θ − h d)) / 2h
is compared with ∇L(θ)·d.  One jitted function returns the values of all losses of a target
and their Jacobian (``jax.jacrev`` with the values as aux), so each target compiles once; the
finite differences call the same compiled function (its gradient output is ignored there).
"""

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.tuning import losses as L
from jaxslam.tuning.targets import ekfslam3d as T3
from jaxslam.tuning.targets import figure8 as T8
from jaxslam.tuning.targets import linear_gaussian as TL

H = 1e-5  # step in θ (log-variance) units; truncation ~h², rounding ~eps/h: both ≪ 1e-4


def _check(fn, theta, n_dirs=2, seed=0, rtol=1e-4):
    """fn(theta) -> (values (k,), aux=values); compares jacrev with central differences."""
    jf = jax.jit(jax.jacrev(lambda th: (fn(th), fn(th)), has_aux=True))
    J, v0 = jf(theta)
    flat, unravel = jax.flatten_util.ravel_pytree(theta)
    Jflat = np.stack([np.asarray(jax.flatten_util.ravel_pytree(jax.tree.map(lambda a, i=i: a[i], J))[0])
                      for i in range(v0.shape[0])])
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(n_dirs):
        d = rng.normal(size=flat.shape[0])
        d /= np.linalg.norm(d)
        vp = np.asarray(jf(unravel(flat + H * d))[1])
        vm = np.asarray(jf(unravel(flat - H * d))[1])
        fd = (vp - vm) / (2 * H)
        an = Jflat @ d
        scale = np.maximum(np.abs(an), np.linalg.norm(Jflat, axis=1) * 1e-3)
        rel = np.abs(fd - an) / scale
        worst = max(worst, float(rel.max()))
        np.testing.assert_array_less(rel, rtol, err_msg=f"fd {fd} vs grad {an}")
    return worst, np.asarray(v0)


def test_linear_gaussian_losses_match_finite_differences():
    tg = TL.linear_gaussian("nll", train_runs=1, test_runs=1, T=60)
    item = jax.tree.map(lambda a: a[0], tg.train)

    def all_losses(th):
        m = tg.physical(th)
        means, nis, logdet, dof, covs = TL.lg_run(m["Q"], m["R"], item["z"])
        err = means - item["x"]
        nees = jax.vmap(lambda e, C: e @ jnp.linalg.solve(C, e))(err, covs)
        return jnp.stack([L.innovation_nll(nis, logdet, dof), L.mse(err), L.nees_loss(nees, 4)])

    worst, v = _check(all_losses, tg.theta0, n_dirs=2)
    assert np.all(np.isfinite(v))


@pytest.mark.slow  # ~60 s cold (compiles the EKF-SLAM gradient); figures: docs/results/tuning/gradcheck.json
def test_ekfslam3d_log_losses_match_finite_differences():
    """NLL, MSE and NEES of the filter on a 1 s recorded log (10 LiDAR frames), Q_c and R tuned."""
    from jaxslam.systems import ekf_slam_3d as sys3d

    logs = T3.make_slam_logs(3, 1, 1.0)
    log = jax.tree.map(lambda a: a[0], logs)
    cfg = sys3d.Config(capacity=40, checkpoint=True)
    ref = sys3d.imu_noise(__import__("jaxslam.sensors.imu", fromlist=["x"]).PAPER000_IMU)
    theta = {"Qc": jnp.log(jnp.asarray([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-6])),
             "R": jnp.log(jnp.diag(ref.R))}

    def all_losses(th):
        noise = ref._replace(Qc=jnp.diag(jnp.exp(th["Qc"])), R=jnp.diag(jnp.exp(th["R"])))
        res = sys3d.run(log, cfg, noise)
        return jnp.stack([T3.slam_loss(res, log, "nll"), T3.slam_loss(res, log, "mse"),
                          T3.slam_loss(res, log, "nees")])

    worst, v = _check(all_losses, theta, n_dirs=2)
    assert np.all(np.isfinite(v))


@pytest.mark.slow  # compiles the closed-loop gradient; figures: docs/results/tuning/gradcheck.json
def test_lqr_closed_loop_cost_matches_finite_differences():
    tg = T8.figure8_lqr(train_runs=1, test_runs=1, train_duration=2.0)
    item = jax.tree.map(lambda a: a[0], tg.train)
    worst, v = _check(lambda th: tg.loss_fn(th, item)[None], tg.theta0, n_dirs=2)
    assert np.isfinite(v[0]) and v[0] > 0
