"""Review fixes of jaxslam.filters.association (JCBB) and jaxslam.filters.fastslam.

Each test compares against values written here by hand or with NumPy, never against the code
under test:

* a NaN log-likelihood in ``reweight`` used to drop its particle without a flag;
* ``resample_indices`` stored an unnormalised ``log_w`` as given (``estimate`` then scaled the
  mean by ``Σ exp(log_w)``), in the caller's dtype, and kept a NaN;
* a traced NaN / non-positive ``gate`` or threshold of ``jcbb`` paired nothing, with no flag;
* ``resample_soft`` with a ``threshold``, called eagerly, traced and compiled its
  ``lax.cond`` again at every call.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import compilation, errors
from jaxslam.errors import InputError
from jaxslam.filters import association as A
from jaxslam.filters import ekf_slam as es
from jaxslam.filters import fastslam as fs
from jaxslam.sensors import range_bearing2d as rb


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("jit", [False, True])
def test_reweight_flags_a_nan_loglik(dtype, jit):
    p = fs.init(np.zeros(3, dtype), 4, 2, 2)
    ll = jnp.asarray([0.0, np.nan, np.log(2.0), 0.0], dtype)
    q = (jax.jit(fs.reweight) if jit else fs.reweight)(p, ll)
    # hand: weights ∝ (1, 0, 2, 1) → (0.25, 0, 0.5, 0.25)
    np.testing.assert_allclose(np.exp(np.asarray(q.log_w, np.float64)), [0.25, 0.0, 0.5, 0.25], rtol=1e-6)
    assert int(q.status) & errors.NON_FINITE
    assert q.log_w.dtype == dtype
    ok = fs.reweight(p, jnp.asarray([0.0, -np.inf, 0.0, 0.0], dtype))  # −inf is a valid weight 0
    assert int(ok.status) == 0


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_resample_indices_normalises_log_w_in_the_particles_dtype(dtype):
    p = fs.init(np.zeros(3, dtype), 4, 2, 2)
    poses = np.arange(12.0).reshape(4, 3)
    p = p._replace(pose=jnp.asarray(poses, dtype))
    idx = np.array([3, 2, 1, 0])
    lw = np.log(np.array([1.0, 2.0, 3.0, 4.0]))  # not normalised (Σ w = 10), float64
    q = fs.resample_indices(p, idx, lw)
    w = np.array([1.0, 2.0, 3.0, 4.0]) / 10.0
    assert q.log_w.dtype == dtype
    np.testing.assert_allclose(np.asarray(q.log_w, np.float64), np.log(w), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(q.pose), poses[idx])
    mu, _ = fs.estimate(q)
    np.testing.assert_allclose(np.asarray(mu, np.float64), w @ poses[idx], rtol=1e-6)


def test_resample_indices_refuses_a_nan_log_w_and_flags_a_traced_one():
    p = fs.init(np.zeros(3), 4, 2, 2)
    idx = np.arange(4)
    with pytest.raises(InputError, match="log_w"):
        fs.resample_indices(p, idx, np.array([0.0, np.nan, 0.0, 0.0]))
    with pytest.raises(InputError, match="log_w"):
        fs.resample_indices(p, idx, np.full(4, -np.inf))
    q = jax.jit(fs.resample_indices)(p, idx, jnp.array([0.0, jnp.nan, 0.0, 0.0]))
    np.testing.assert_allclose(np.exp(np.asarray(q.log_w)), [1 / 3, 0.0, 1 / 3, 1 / 3], rtol=1e-12)
    assert int(q.status) & errors.NON_FINITE
    q = jax.jit(fs.resample_indices)(p, idx, jnp.full(4, jnp.nan))
    np.testing.assert_allclose(np.exp(np.asarray(q.log_w)), np.full(4, 0.25), rtol=1e-12)
    assert int(q.status) & errors.DEGENERATE


MODEL = es.SlamModel(robot_dim=3, lm_dim=2, meas_dim=2, motion=None, observe=rb.observe,
                     inverse=rb.inverse, residual=rb.residual)


def _state(dtype=np.float64):
    x = np.array([0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 5.0], dtype)
    return es.SlamState(x=jnp.asarray(x), P=jnp.asarray(0.01 * np.eye(7), dtype), active=jnp.ones(2, bool),
                        ids=jnp.arange(2, dtype=jnp.int32), status=jnp.int32(0), overflow=jnp.int32(0))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_jcbb_flags_a_traced_bad_gate_or_threshold(dtype):
    st = _state(dtype)
    # the robot at the origin sees landmark 0 at (5, 0) and landmark 1 at (0, 5) exactly
    z = jnp.asarray([[5.0, 0.0], [5.0, np.pi / 2]], dtype)
    R = jnp.asarray(0.01 * np.eye(2), dtype)
    mask = jnp.ones(2, bool)
    thr = jnp.asarray([9.21, 13.28], dtype)
    f = jax.jit(lambda g, t: A.jcbb(st, MODEL, z, mask, R, gate=g, thresholds=t))
    good = f(jnp.asarray(9.21, dtype), thr)
    np.testing.assert_array_equal(np.asarray(good.slots), [0, 1])
    assert int(good.status) == 0
    for g, t in ((np.nan, thr), (-1.0, thr), (9.21, jnp.asarray([np.nan, 13.28], dtype)),
                 (9.21, jnp.asarray([9.21, 0.0], dtype))):
        bad = f(jnp.asarray(g, dtype), t)
        assert int(bad.status) & errors.NON_FINITE, (g, t)
    eager = A.jcbb(st, MODEL, z, mask, R, gate=9.21, thresholds=thr)
    np.testing.assert_array_equal(np.asarray(eager.slots), [0, 1])
    assert int(eager.status) == 0


def test_resample_soft_with_a_threshold_called_eagerly_compiles_once():
    compilation.clear_programs()
    p = fs.init(np.zeros(3), 32, 4, 2)

    def call(seed):
        lw = jnp.asarray(np.random.default_rng(seed).normal(size=32))
        return fs.resample_soft(p._replace(log_w=lw - jax.scipy.special.logsumexp(lw)),
                                jax.random.PRNGKey(seed), 0.5, threshold=0.99)

    call(0)
    with compilation.account() as acc:
        out = call(1)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    # every particle keeps its pose (all zero) and the new weights are normalised (NumPy)
    np.testing.assert_allclose(np.logaddexp.reduce(np.asarray(out.log_w)), 0.0, atol=1e-12)
    assert int(out.resamples) == 1
