"""A traced (jit) gate / association threshold that is not > 0 in the SLAM engines.

``x > nan`` is False: a NaN gate switched gating off (every row used) and a NaN nearest-neighbour
gate / new-landmark threshold matched and registered nothing, all with status 0 (a concrete bad
value is an InputError, a traced one cannot be).  Now, as ``gaussian.gate_test`` does for the
Gaussian filters: the rows are gated (the prior kept) and ``NON_FINITE`` is set.  A valid gate
keeps its flags (status 0 on an exact measurement).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.filters import ekf_slam as es
from jaxslam.filters import fastslam as fs

from test_ekf_slam_engine_inputs import M, Q, R, _state
from test_filters_fastslam import LMS, MODEL as FS_MODEL, R_NP

BAD = (np.nan, -1.0, 0.0)
# the robot at the origin (heading 0) sees landmark (2, 1) at range √5, bearing atan2(1, 2), and
# (1, -2) at range √5, bearing atan2(-2, 1): hand-computed, exact
Z_EXACT = np.array([[np.sqrt(5.0), np.arctan2(1.0, 2.0)], [np.sqrt(5.0), np.arctan2(-2.0, 1.0)]])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ekf_slam_update_traced_bad_gate_gates_every_row_and_flags_non_finite(dtype):
    st = _state(dtype)
    z = jnp.asarray(Z_EXACT + np.array([[0.02, 0.0], [0.0, 0.0]]), dtype)
    Rj = jnp.asarray(R, dtype)
    f = jax.jit(lambda g: es.update(st, M, z, jnp.array([0, 1]), jnp.ones(2, bool), Rj, gate=g))
    good_st, good = f(jnp.asarray(9.21, dtype))
    assert int(good_st.status) == 0 and np.asarray(good.used).all() and not bool(good.rejected)
    for g in BAD:
        new, info = f(jnp.asarray(g, dtype))
        assert int(new.status) == errors.NON_FINITE | errors.GATED, g
        assert bool(info.rejected), g
        np.testing.assert_array_equal(np.asarray(info.used), [False, False])
        np.testing.assert_array_equal(np.asarray(info.gated), [True, True])
        # the prior, untouched
        np.testing.assert_array_equal(np.asarray(new.x), np.asarray(st.x))
        np.testing.assert_array_equal(np.asarray(new.P), np.asarray(st.P))
    # no row to use: nothing to flag
    new, _ = jax.jit(lambda g: es.update(st, M, z, jnp.array([0, 1]), jnp.zeros(2, bool), Rj, gate=g))(
        jnp.asarray(np.nan, dtype))
    assert int(new.status) == 0


def _log(T=3):
    z = np.tile(Z_EXACT, (T, 1, 1))
    return es.SlamLog(u=np.zeros((T, 2)), z=z, ids=np.tile([0, 1], (T, 1)), mask=np.ones((T, 2), bool))


def test_ekf_slam_run_traced_bad_nn_thresholds_flag_non_finite():
    st = _state()
    log = _log()._replace(ids=None)
    f = jax.jit(lambda g, n: es.run(M, st, log, Q, R, association="nn", nn_gate=g, nn_new=n))
    good = f(11.34, 30.0)
    assert not int(good.final.status) & errors.NON_FINITE
    assert np.isfinite(np.asarray(good.log_likelihood)).all()
    np.testing.assert_array_equal(np.asarray(good.n_used), [2, 2, 2])
    for g, n in ((np.nan, 30.0), (11.34, np.nan), (-1.0, 30.0), (11.34, 0.0)):
        out = f(g, n)
        assert int(out.final.status) & errors.NON_FINITE, (g, n)
        assert np.isnan(np.asarray(out.log_likelihood)).all(), (g, n)


def test_ekf_slam_run_traced_bad_gate_flags_non_finite_and_nan_likelihood():
    st = _state()
    f = jax.jit(lambda g: es.run(M, st, _log(), Q, R, association="known", gate=g))
    good = f(9.21)
    assert int(good.final.status) == 0
    np.testing.assert_array_equal(np.asarray(good.n_used), [2, 2, 2])
    bad = f(np.nan)
    assert int(bad.final.status) & errors.NON_FINITE
    np.testing.assert_array_equal(np.asarray(bad.n_used), [0, 0, 0])
    np.testing.assert_array_equal(np.asarray(bad.n_gated), [2, 2, 2])
    assert np.isnan(np.asarray(bad.log_likelihood)).all()
    # the map is the preloaded one, untouched (the robot does not move: u = 0)
    np.testing.assert_array_equal(np.asarray(bad.final.x), np.asarray(st.x))


def _particles(dtype):
    p = fs.init(np.zeros(3, dtype), 2, 4, 2)
    # the particles at the origin see landmarks 0 and 1 exactly (hand-computed range / bearing)
    d = LMS[:2]
    z = np.stack([np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])], axis=1)
    p, _ = fs.observe_update(p, FS_MODEL, z.astype(dtype), np.arange(2), np.ones(2, bool), R_NP.astype(dtype))
    return p, z


@pytest.mark.parametrize("solver", ["closed", "ekf"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_fastslam_observe_update_traced_bad_gate_gates_and_flags(solver, dtype):
    p, z = _particles(dtype)
    z = jnp.asarray(z + np.array([[0.01, 0.0], [0.0, 0.0]]), dtype)
    f = jax.jit(lambda g: fs.observe_update(p, FS_MODEL, z, np.arange(2), np.ones(2, bool),
                                            R_NP.astype(dtype), gate=g, solver=solver))
    q, info = f(jnp.asarray(100.0, dtype))
    assert int(info.status) & (errors.NON_FINITE | errors.GATED) == 0
    assert np.asarray(info.used).all()
    for g in BAD:
        q, info = f(jnp.asarray(g, dtype))
        assert int(info.status) & errors.NON_FINITE and int(info.status) & errors.GATED, g
        assert int(q.status) & errors.NON_FINITE, g
        assert not np.asarray(info.used).any() and np.asarray(info.gated).all(), g
        np.testing.assert_array_equal(np.asarray(q.lm_mean), np.asarray(p.lm_mean))
        np.testing.assert_array_equal(np.asarray(q.lm_cov), np.asarray(p.lm_cov))


def test_fastslam_propose_optimal_traced_bad_gate_flags_non_finite():
    p, z = _particles(np.float64)
    cov = np.broadcast_to(1e-3 * np.eye(3), (2, 3, 3))
    key = jax.random.PRNGKey(0)
    f = jax.jit(lambda g: fs.propose_optimal(p, FS_MODEL, jnp.asarray(z), np.arange(2), np.ones(2, bool),
                                             R_NP, cov, key, gate=g))
    _, ll, _, st = f(100.0)
    assert not int(st) & errors.NON_FINITE
    assert np.all(np.asarray(ll) != 0.0)
    for g in BAD:
        _, ll, _, st = f(g)
        assert int(st) & errors.NON_FINITE, g
        np.testing.assert_array_equal(np.asarray(ll), [0.0, 0.0])  # no row informed the proposal


def test_joint_compatibility_refuses_a_short_or_non_positive_threshold_table():
    """A NaN table kept every match (NIS > NaN is False) and a (1,) table for two rows was read
    past its end (clamped), both without a word."""
    from jaxslam.errors import InputError

    st = _state()
    z = Z_EXACT + np.array([[0.0, 0.3], [0.0, 0.0]])  # row 0 far off in bearing
    args = (st, M, z, jnp.array([0, 1]), jnp.ones(2, bool), R, None)
    with pytest.raises(InputError, match=r"^thresholds: expected χ² thresholds > 0, got nan at index 0"):
        es.joint_compatibility(*args, np.array([np.nan, np.nan]))
    with pytest.raises(InputError, match=r"^thresholds: expected χ² thresholds > 0, got -1.0 at index 1"):
        es.joint_compatibility(*args, np.array([9.21, -1.0]))
    with pytest.raises(InputError, match=r"^thresholds: expected shape \(2,\)"):
        es.joint_compatibility(*args, np.array([9.21]))
    # χ²(2) and χ²(4) 0.99 quantiles (SciPy: 9.2103, 13.2767); a longer table is fine
    kept, dropped, _ = es.joint_compatibility(*args, np.array([9.2103, 13.2767, 16.8119]))
    np.testing.assert_array_equal(np.asarray(kept), [False, True])
    np.testing.assert_array_equal(np.asarray(dropped), [True, False])


@pytest.mark.parametrize("which", ["maybe_resample", "resample_soft"])
def test_fastslam_resampling_flags_a_traced_nan_threshold(which):
    p = fs.init(np.zeros(3), 4, 2, 2)
    # weights (0.7, 0.1, 0.1, 0.1): N_eff = 1 / Σ w² = 1 / 0.52 ≈ 1.92 < 0.9·4 (hand-computed)
    p = p._replace(log_w=jnp.log(jnp.asarray([0.7, 0.1, 0.1, 0.1])))
    key = jax.random.PRNGKey(0)
    if which == "maybe_resample":
        f = jax.jit(lambda t: fs.maybe_resample(p, key, t))
    else:
        f = jax.jit(lambda t: fs.resample_soft(p, key, 0.5, threshold=t))
    good = f(0.9)
    assert int(good.resamples) == 1 and int(good.status) == 0
    bad = f(np.nan)
    assert int(bad.resamples) == 0
    assert int(bad.status) & errors.NON_FINITE


def test_add_landmark_refuses_or_flags_a_non_finite_mean_or_cross_covariance():
    """A NaN mean or cross-covariance was written into the state (the slot active, status 0)."""
    from jaxslam.errors import InputError

    st = es.init(jnp.zeros(3), 1e-3 * jnp.eye(3), 4, 2)
    n = st.x.shape[0]
    good_mean, good_lx = np.array([1.0, 2.0]), np.zeros((2, n))
    bad_mean, bad_lx = np.array([np.nan, 2.0]), np.full((2, n), np.inf)
    with pytest.raises(InputError, match=r"^mean: contains NaN or Inf"):
        es.add_landmark(st, M, 0, bad_mean, 0.1 * np.eye(2), good_lx, 5)
    with pytest.raises(InputError, match=r"^cov_lx: contains NaN or Inf"):
        es.add_landmark(st, M, 0, good_mean, 0.1 * np.eye(2), bad_lx, 5)
    es.add_landmark(st, M, 0, bad_mean, 0.1 * np.eye(2), good_lx, 5, ok=False)  # nothing to write
    f = jax.jit(lambda m, c, lx: es.add_landmark(st, M, 1, m, c, lx, 5))
    ok = f(good_mean, 0.1 * np.eye(2), good_lx)
    assert int(ok.status) == 0 and bool(ok.active[1])
    np.testing.assert_array_equal(np.asarray(ok.x[5:7]), good_mean)
    for m, c, lx in ((bad_mean, 0.1 * np.eye(2), good_lx), (good_mean, np.full((2, 2), np.nan), good_lx),
                     (good_mean, 0.1 * np.eye(2), bad_lx)):
        out = f(m, c, lx)
        assert int(out.status) == errors.NON_FINITE
        assert not np.asarray(out.active).any()
        np.testing.assert_array_equal(np.asarray(out.x), np.asarray(st.x))
        np.testing.assert_array_equal(np.asarray(out.P), np.asarray(st.P))
