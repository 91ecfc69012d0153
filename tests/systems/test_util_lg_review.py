"""Review fixes: util_range's start-up under jit flags an anchor it could not fit (the status is
carried into the run), and the linear-Gaussian tuning target records the dtype it computes in.
Oracles: the anchors' true positions and the count of ranges per anchor (NumPy), the flag bits
of jaxslam.errors, the dtype JAX computes in."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import errors
from jaxslam.systems import util_range as ur
from jaxslam.tuning.targets import linear_gaussian as LG

from test_util_range_review import A4, _walk  # the same anchors and walk (same folder)


_startup_jit = jax.jit(ur.startup, static_argnames="iters")


def test_startup_under_jit_flags_an_anchor_without_ranges_and_run_carries_it():
    t, aid, z, P = _walk(n_anchors=3)  # anchor 3 never ranged: not fittable
    assert not np.any(aid[t <= 10.0] == 3)
    su = _startup_jit(t, aid, z, P, np.arange(4), 10.0)
    assert int(su.status) & errors.DEGENERATE
    ev = ur.util_events(t, aid, z, t_start=10.0 + 1e-9)
    res = ur.run(ur.log_from_events(ev, np.arange(4), startup=su, dtype=jnp.float64))
    assert int(res.status) & errors.DEGENERATE


def test_startup_fitted_anchors_carry_no_flag_float64_and_float32():
    t, aid, z, P = _walk()
    for dtype, tol in ((np.float64, 0.3), (np.float32, 0.3)):
        su = _startup_jit(t.astype(dtype), aid, z.astype(dtype), P.astype(dtype), np.arange(4), 10.0)
        assert int(su.status) == errors.OK, dtype
        assert su.anchors.dtype == dtype
        # the true anchors (NumPy) within the window's fit precision
        assert np.max(np.linalg.norm(np.asarray(su.anchors, np.float64) - A4, axis=1)) < tol, dtype
        ev = ur.util_events(t, aid, z, t_start=10.0 + 1e-9)
        res = ur.run(ur.log_from_events(ev, np.arange(4), startup=su, dtype=dtype))
        assert not int(res.status) & (errors.DEGENERATE | errors.NON_FINITE), dtype


def test_startup_anchor_with_two_ranges_is_degenerate():
    # anchor 3 ranged twice in the window: 3 coordinates from 2 ranges are not fixed
    t, aid, z, P = _walk(n_anchors=3)
    k = np.nonzero(t <= 10.0)[0][[5, 40]]
    aid = aid.copy()
    aid[k] = 3
    z = z.copy()
    z[k] = np.linalg.norm(P[k] - A4[3], axis=1) - 0.25
    su = ur.startup(t, aid, z, P, np.arange(4), 10.0)  # eager: accepted (it has ranges)
    assert int(su.status) & errors.DEGENERATE


def test_hand_made_startup_without_status_runs():
    su = ur.Startup(anchors=jnp.asarray(A4[:2]), bias=jnp.asarray(0.0), cov=0.01 * jnp.eye(7),
                    n_used=jnp.asarray(10), n_rejected=jnp.asarray(0), rms=jnp.asarray(0.1),
                    p0=jnp.asarray([1.0, 2.0, 0.5]), v0=jnp.zeros(3), t0=jnp.asarray(1.0))
    assert su.status is None
    ev = ur.util_events([3.0, 3.1], [0, 1], [np.linalg.norm([1.0, 2.0, 0.3]), 3.6])
    res = ur.run(ur.log_from_events(ev, np.arange(2), startup=su, dtype=jnp.float64))
    assert not int(res.status) & (errors.DEGENERATE | errors.NON_FINITE)


def test_linear_gaussian_config_dtype_is_the_computed_dtype_with_x64_off():
    with jax.enable_x64(False):
        tg = LG.linear_gaussian("nll", train_runs=1, test_runs=1, T=5)  # default dtype float64
        computed = tg.train["z"].dtype
        assert computed == np.float32
        assert tg.config["dtype"] == "float32"
        assert all(a.dtype == np.float32 for a in jax.tree.leaves(tg.theta0))
    tg = LG.linear_gaussian("nll", train_runs=1, test_runs=1, T=5)
    assert tg.config["dtype"] == "float64" and tg.train["z"].dtype == np.float64


# --- further review items ------------------------------------------------------------------------

import pytest  # noqa: E402

from jaxslam.errors import InputError  # noqa: E402


@pytest.mark.parametrize("t, tof_t, name, idx", [([0.0, np.nan, 0.2], [0.1], "t", 1),
                                                 ([0.0, 0.1, 0.2], [0.1, np.nan], "tof_t", 1),
                                                 ([0.0, 0.1, 0.2], [np.inf], "tof_t", 0)])
def test_util_events_with_tof_names_the_non_finite_time(t, tof_t, name, idx):
    # was "meas_t: non-finite time at index 3/4" (the merged array's name and index)
    with pytest.raises(InputError, match=rf"^{name}: non-finite time at index {idx}$"):
        ur.util_events(t, [0, 1, 0], [1.0, 2.0, 3.0], tof_t=tof_t, tof=[1.0] * len(tof_t))


def test_lg_simulate_refuses_an_integer_dtype():
    Q, R = np.diag(LG.LG_Q_TRUE), np.asarray(LG.LG_R_TRUE)
    with pytest.raises(InputError, match=r"^dtype: "):  # was a silently truncated int32 log
        LG.lg_simulate(jax.random.PRNGKey(0), 5, Q, R, dtype=jnp.int32)


def test_lg_run_refuses_an_empty_log():
    Q, R = np.diag(LG.LG_Q_TRUE), np.asarray(LG.LG_R_TRUE)
    with pytest.raises(InputError, match=r"^z: "):  # its nll was 0.0, its mse NaN
        LG.lg_run(Q, R, jnp.zeros((0, 4)))


def test_lg_run_matches_a_numpy_kalman_filter():
    # guard for the fixes above: the oracle filter equals a NumPy Joseph-form KF
    Q, R = np.diag(LG.LG_Q_TRUE), np.asarray(LG.LG_R_TRUE)
    z = np.asarray(LG.lg_simulate(jax.random.PRNGKey(1), 30, Q, R)["z"])
    A = np.array([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    x, P, I4, nis = np.zeros(4), np.eye(4), np.eye(4), []
    for zk in z:
        x, P = A @ x, A @ P @ A.T + Q
        S = P + R
        K = P @ np.linalg.inv(S)
        nis.append((zk - x) @ np.linalg.solve(S, zk - x))
        x, P = x + K @ (zk - x), (I4 - K) @ P @ (I4 - K).T + K @ R @ K.T
    means, nis_j, _, _, covs = LG.lg_run(Q, R, jnp.asarray(z))
    np.testing.assert_allclose(np.asarray(means[-1]), x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(covs[-1]), P, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(nis_j), nis, rtol=1e-9, atol=1e-10)
