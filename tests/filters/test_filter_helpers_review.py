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


# ---------------------------------------------------------------------------
# 5. trilateration: traced bad variance / side -> ok False; lists; named errors
# ---------------------------------------------------------------------------

from jaxslam.filters import trilateration as tr  # noqa: E402

PTS = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0], [4.0, 3.0]])
RNG = np.linalg.norm(PTS - np.array([1.0, 1.0]), axis=1)
XS = np.array([0.0, -1.0, -2.0, -3.0])
RNG_LINE = np.hypot(1.0 - XS, 2.0)


def test_trilaterate_traced_bad_range_var_is_not_ok():
    run = jax.jit(lambda v: tr.trilaterate(PTS, RNG, range_var=v))
    for bad in (-1.0, np.nan):
        res = run(bad)
        assert not bool(res.ok) and int(res.status) & errors.DEGENERATE
    good = run(0.1)
    assert bool(good.ok) and int(good.status) == 0
    np.testing.assert_allclose(good.cov, tr.trilaterate(PTS, RNG, range_var=0.1).cov, rtol=1e-12)


def test_trilaterate_line_traced_bad_side_is_not_ok():
    run = jax.jit(lambda s: tr.trilaterate_line(XS, RNG_LINE, side=s))
    res = run(5.0)
    assert not bool(res.ok) and int(res.status) & errors.DEGENERATE
    for s in (1.0, -1.0):
        res = run(s)
        assert bool(res.ok)
        np.testing.assert_allclose(res.position, [1.0, 2.0 * s], atol=1e-9)
    with pytest.raises(InputError, match=r"^side: "):
        tr.trilaterate_line(XS, RNG_LINE, side=5.0)


def test_trilaterate_accepts_lists_and_names_bad_numbers():
    res = tr.trilaterate(PTS.tolist(), RNG.tolist())
    np.testing.assert_allclose(res.position, tr.trilaterate(PTS, RNG).position)
    np.testing.assert_allclose(tr.trilaterate_line(XS.tolist(), RNG_LINE.tolist()).position,
                               tr.trilaterate_line(XS, RNG_LINE).position)
    with pytest.raises(InputError, match=r"^min_points: "):
        tr.trilaterate(PTS, RNG, min_points="3")
    with pytest.raises(InputError, match=r"^range_var: "):
        tr.trilaterate(PTS, RNG, range_var="a")
    with pytest.raises(InputError, match=r"^min_spread: "):
        tr.trilaterate(PTS, RNG, min_spread="x")
    with pytest.raises(InputError, match=r"^min_points: "):
        tr.trilaterate_line(XS, RNG_LINE, min_points="3")
    with pytest.raises(InputError, match=r"^min_baseline: "):
        tr.trilaterate_line(XS, RNG_LINE, min_baseline="x")


# ---------------------------------------------------------------------------
# 6. smoother.rts: post and difference named
# ---------------------------------------------------------------------------

from jaxslam.filters import ekf  # noqa: E402


def test_rts_names_bad_post_and_difference():
    with pytest.raises(InputError, match=r"^post: "):
        sm.rts(None)
    post = ekf.filter_scan(_cv, _h, jnp.array([0.0, 1.0]), jnp.eye(2), None, _zs(), None,
                           0.01 * jnp.eye(2), 0.1 * jnp.eye(1), save_smoother=True)
    with pytest.raises(InputError, match=r"^difference: "):
        sm.rts(post, difference=lambda a, b: jnp.sum(a - b))
    with pytest.raises(InputError, match=r"^difference: "):
        sm.rts(post, difference="sub")
    np.testing.assert_array_equal(sm.rts(post, difference=lambda a, b: a - b).means,
                                  sm.rts(post).means)
