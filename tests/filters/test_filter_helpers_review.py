"""Review probes of the generic filter helpers (resampling, trilateration, smoother)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.filters import resampling as rs

KEY = jax.random.PRNGKey(0)
SCHEME_FNS = [rs.multinomial, rs.stratified, rs.systematic, rs.residual]


# ---------------------------------------------------------------------------
# 1. resampling: log_w must be one (N,) vector; n an int; key a PRNG key
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("fn", SCHEME_FNS)
def test_schemes_refuse_bad_log_w_n_key(fn):
    with pytest.raises(InputError, match=r"^log_w: expected shape \(N,\)"):
        fn(KEY, jnp.zeros((2, 3)))  # batched weights were flattened into one CDF
    with pytest.raises(InputError, match=r"^log_w: "):
        fn(KEY, jnp.zeros((0,)))
    with pytest.raises(InputError, match=r"^log_w: "):
        fn(KEY, jnp.zeros(()))
    for bad in (1.5, True, "3"):
        with pytest.raises(InputError, match=r"^n: "):
            fn(KEY, jnp.zeros(3), bad)
    with pytest.raises(InputError, match=r"^key: "):
        fn(0, jnp.zeros(3))
    with pytest.raises(InputError, match=r"^log_w: "):
        rs.resample(KEY, jnp.zeros((2, 3)))
    with pytest.raises(InputError, match=r"^log_w: "):
        rs.soft(KEY, jnp.zeros((2, 3)), 0.5)
    with pytest.raises(InputError, match=r"^key: "):
        rs.soft(0, jnp.zeros(3), 0.5)


@pytest.mark.parametrize("fn", SCHEME_FNS)
def test_schemes_under_vmap_see_one_row(fn):
    lw = jnp.log(jnp.asarray([[0.1, 0.2, 0.7], [0.5, 0.25, 0.25]]))
    keys = jax.random.split(KEY, 2)
    batched = jax.jit(jax.vmap(fn))(keys, lw)
    for i in range(2):
        np.testing.assert_array_equal(batched[i], fn(keys[i], lw[i]))


# ---------------------------------------------------------------------------
# 2. resampling: the uniform fallback is reported
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("scheme", sorted(rs.SCHEMES))
def test_resample_ok_flags_unnormalisable_weights(scheme):
    f = jax.jit(rs.resample_ok, static_argnums=(2, 3))
    for bad in ([-np.inf] * 4, [np.nan] * 4, [0.0, np.inf, 0.0, 0.0]):
        idx, ok = f(KEY, jnp.asarray(bad), scheme, None)
        assert not bool(ok)
        np.testing.assert_array_equal(idx, rs.resample(KEY, jnp.asarray(bad), scheme))
    lw = jnp.log(jnp.asarray([0.1, 0.2, 0.3, 0.4]))
    idx, ok = f(KEY, lw, scheme, 6)
    assert bool(ok)
    np.testing.assert_array_equal(idx, rs.resample(KEY, lw, scheme, 6))


# ---------------------------------------------------------------------------
# 3-4. smoother.iterated: Q checked on the init path; NaN robust weight and NaN tol flagged
# ---------------------------------------------------------------------------

from jaxslam import errors  # noqa: E402
from jaxslam.filters import smoother as sm  # noqa: E402


def _cv(x, u):
    return jnp.array([x[0] + 0.1 * x[1], x[1]])


def _h(x):
    return x[:1]


def _zs():
    return (jnp.arange(6.0) * 0.1)[:, None]


@pytest.mark.parametrize("init", [None, "zeros"])
@pytest.mark.parametrize("Q", [0.01 * np.eye(1), 0.01 * np.ones((6, 1, 1))])
def test_iterated_checks_q_shape_with_init(init, Q):
    init = None if init is None else jnp.zeros((6, 2))
    with pytest.raises(InputError, match=r"^Q: expected shape \(2, 2\)"):
        sm.iterated(_cv, _h, jnp.array([0.0, 1.0]), jnp.eye(2), None, _zs(), None,
                    jnp.asarray(Q), 0.1 * jnp.eye(1), num_iter=3, init=init)


def test_iterated_flags_nan_robust_weight_and_nan_tol():
    args = (_cv, _h, jnp.array([0.0, 1.0]), jnp.eye(2), None, _zs(), None,
            0.01 * jnp.eye(2), 0.1 * jnp.eye(1))
    out = sm.iterated(*args, num_iter=3, robust=lambda r: r * jnp.nan)
    assert np.all(np.asarray(out.status) & errors.NON_FINITE)
    good = sm.iterated(*args, num_iter=3, robust=sm.huber_weight())
    assert not np.any(np.asarray(good.status) & errors.NON_FINITE)

    run = jax.jit(lambda tol: sm.iterated(*args, num_iter=3, tol=tol).status)
    assert np.all(np.asarray(run(jnp.nan)) & errors.NOT_CONVERGED)
    assert not np.any(np.asarray(run(1e-3)) & errors.NOT_CONVERGED)
