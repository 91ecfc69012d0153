"""Edge inputs of the four generic Gaussian runs (``ekf``, ``ukf``, ``sqrt_ekf``, ``sqrt_ukf``):
one rule for a failed prediction, a traced negative process-noise variance flagged, measurements
that do not fit the run's dtype refused, and the square-root runs' factors taken before the cast.

The tests here failed on the code before (2026-12-08): a traced ``Q`` with a negative variance that
``P + Q`` absorbed gave status 0 in ekf/ukf; a NaN prediction was carried to the end of the ekf and
sqrt_ekf runs while the sigma-point runs updated the previous step's belief with the step's z; a
``zs`` of 1e300 in a float32 run became inf (status NON_FINITE, no error); sqrt_ukf factored a
float32-rounded ``P0``, and a per-step ``Q`` was factored after the cast in both square-root runs.

Expected values are written by hand (flags, messages), are NumPy's float64 Cholesky factor, or are
a property of the rule itself (a skipped step's moments are the previous step's).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, sqrt_ekf, sqrt_ukf, ukf

MODS = {"ekf": ekf, "ukf": ukf, "sqrt_ekf": sqrt_ekf, "sqrt_ukf": sqrt_ukf}
NF, NP = errors.NON_FINITE, errors.NOT_PSD


def f(x, u):
    return jnp.array([x[0] + x[1], x[1]])


def f_fails(x, u):  # NaN where u > 0: a failed prediction at that step
    return jnp.where(u > 0, jnp.nan, 1.0) * jnp.array([x[0] + x[1], x[1]])


def h(x):
    return x[:1]


def _scan(name, fm, x0, P0, us, zs, Q, R, pf=True, masks=None):
    mod = MODS[name]
    kw = {"save_chol": True} if name.startswith("sqrt") else {"save_cov": True}
    return mod.filter_scan(fm, h, x0, P0, us, zs, masks, Q, R, predict_first=pf, **kw)


def _covs(name, post):
    if name.startswith("sqrt"):
        L = np.asarray(post.chols)
        return L @ np.swapaxes(L, -1, -2)
    return np.asarray(post.covs)


# ---------------------------------------------------------------------------
# 1. a traced negative R: not checked
# ---------------------------------------------------------------------------

# (a traced R with a tiny negative variance whose S still factors is not checked in the
# covariance forms: each update's check made a small EKF run ~25 % slower; gaussian.negative_variance)


# ---------------------------------------------------------------------------
# 2. a failed prediction: one rule in the four runs
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("pf", [True, False])
@pytest.mark.parametrize("name", list(MODS))
def test_a_failed_prediction_is_skipped_alike(name, pf):
    x0, P0, Q, R = np.zeros(2), np.eye(2), 0.01 * np.eye(2), np.array([[0.1]])
    zs = np.array([[0.0], [1.0], [2.0], [3.0], [4.0]])
    us = np.array([0.0, 1.0, 0.0, 0.0, 0.0])  # f fails at the predict made with us[1]
    post = _scan(name, f_fails, x0, P0, us, zs, Q, R, pf)
    bad = 1 if pf else 2  # the step whose prior that predict was to make
    want = [0] * 5
    want[bad] = NF
    assert np.asarray(post.status).tolist() == want
    means, covs = np.asarray(post.means), _covs(name, post)
    assert np.all(np.isfinite(means)) and np.all(np.isfinite(covs))  # the NaN is not carried
    # the flagged step made no update: it kept the belief the failed predict started from
    np.testing.assert_array_equal(means[bad], means[bad - 1])
    np.testing.assert_allclose(covs[bad], covs[bad - 1], rtol=1e-14, atol=0)
    assert float(post.nis[bad]) == 0.0
    if hasattr(post, "log_likelihood"):
        ll = np.asarray(post.log_likelihood)
        assert np.isnan(ll[bad]) and np.all(np.isfinite(np.delete(ll, bad)))
    # and the run goes on from it: the rest is the run started from that belief
    if pf:  # the next step predicts from the kept belief with us[2]
        rest = _scan(name, f, means[bad], covs[bad], us[bad + 1:], zs[bad + 1:], Q, R, pf)
    else:  # the kept belief is the next step's prior... after the predict with us[bad]
        rest_u = _scan(name, f, means[bad], covs[bad], us[bad:bad + 1], zs[bad + 1:bad + 2], Q, R, True)
        np.testing.assert_allclose(means[bad + 1], np.asarray(rest_u.means)[0], rtol=1e-10, atol=1e-12)
        return
    np.testing.assert_allclose(means[bad + 1:], np.asarray(rest.means), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("pf", [True, False])
def test_the_four_runs_agree_after_a_failed_prediction(pf):
    x0, P0, Q, R = np.zeros(2), np.eye(2), 0.01 * np.eye(2), np.array([[0.1]])
    zs = np.arange(5.0)[:, None]
    us = np.array([0.0, 1.0, 0.0, 0.0, 0.0])
    ref = _scan("ekf", f_fails, x0, P0, us, zs, Q, R, pf)
    for name in ("ukf", "sqrt_ekf", "sqrt_ukf"):
        post = _scan(name, f_fails, x0, P0, us, zs, Q, R, pf)
        np.testing.assert_array_equal(np.asarray(post.status), np.asarray(ref.status))
        np.testing.assert_allclose(np.asarray(post.means), np.asarray(ref.means), rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------------
# 6. a traced Q with a negative variance that P + Q absorbs
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("pf", [True, False])
@pytest.mark.parametrize("name", list(MODS))
def test_traced_negative_Q_variance_is_not_psd_in_every_run(name, pf):
    # P0 = 10 I and Q = diag(-0.5, 0.01): every predicted variance stays positive, so the
    # covariance runs said 0 (the square-root runs, which factor Q, NOT_PSD)
    x0, P0, R = np.zeros(2), 10.0 * np.eye(2), np.array([[0.1]])
    zs = np.arange(3.0)[:, None]
    run = jax.jit(lambda Q: MODS[name].filter_scan(f, h, x0, P0, None, zs, None, Q, R, predict_first=pf))
    status = np.asarray(run(np.diag([-0.5, 0.01])).status).tolist()
    assert status == ([NP, NP, NP] if pf else [0, NP, NP])


# ---------------------------------------------------------------------------
# 4. measurements that do not fit the run's dtype
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(MODS))
def test_zs_that_overflow_the_run_dtype_are_refused_by_name(name):
    x0, P0, Q, R = np.zeros(2, np.float32), np.eye(2), 0.01 * np.eye(2), np.array([[0.1]])
    zs = np.array([[1.0], [1e300], [2.0]])
    with pytest.raises(InputError, match=r"zs\[1\]: entry 1e\+300 does not fit float32"):
        MODS[name].filter_scan(f, h, x0, P0, None, zs, None, Q, R)
    # a masked entry is never read: it may hold anything, as NaN there may
    masks = np.array([[True], [False], [True]])
    with np.errstate(over="ignore"):  # (the cast of the masked entry: inf, never read)
        post = MODS[name].filter_scan(f, h, x0, P0, None, zs, masks, Q, R)
    assert np.asarray(post.status).tolist() == [0, 0, 0]
    # in float64 the value fits
    MODS[name].filter_scan(f, h, x0.astype(np.float64), P0, None, zs, None, Q, R)


# ---------------------------------------------------------------------------
# 5. the square-root runs factor P0 and Q before the cast
# ---------------------------------------------------------------------------

def _spd(seed, n=3):
    A = np.random.default_rng(seed).normal(size=(n, n))
    return A @ A.T + 0.1 * np.eye(n)


@pytest.mark.parametrize("name", ["sqrt_ekf", "sqrt_ukf"])
def test_sqrt_runs_start_from_the_float32_factor_of_P0(name):
    # nothing measured at step 0 and the update first: chols[0] is the run's factor of P0,
    # which must be the float64 factor cast (sqrt_ukf factored the float32-rounded P0)
    x0, zs, masks = np.zeros(3, np.float32), np.zeros((2, 1)), np.zeros((2, 1), bool)
    for seed in range(4):
        P0 = _spd(seed)
        post = MODS[name].filter_scan(lambda x, u: x, h, x0, P0, None, zs, masks, 0.01 * np.eye(3),
                                      np.array([[0.1]]), predict_first=False, save_chol=True)
        np.testing.assert_array_equal(np.asarray(post.chols[0]), np.linalg.cholesky(P0).astype(np.float32))


@pytest.mark.parametrize("name", ["sqrt_ekf", "sqrt_ukf"])
def test_sqrt_runs_factor_a_per_step_Q_as_a_single_one(name):
    # T copies of one Q give the run of that Q (a per-step Q was cast, then factored in float32)
    T = 3
    x0, zs, masks = np.zeros(3, np.float32), np.zeros((T, 1)), np.zeros((T, 1), bool)
    for seed in range(4):
        Q = _spd(seed + 10)
        one = MODS[name].filter_scan(lambda x, u: x, h, x0, np.eye(3), None, zs, masks, Q, np.array([[0.1]]),
                                     save_chol=True)
        per = MODS[name].filter_scan(lambda x, u: x, h, x0, np.eye(3), None, zs, masks, np.stack([Q] * T),
                                     np.array([[0.1]]), save_chol=True)
        np.testing.assert_array_equal(np.asarray(per.chols), np.asarray(one.chols))


@pytest.mark.parametrize("name", sorted(MODS))
def test_a_psd_q_whose_diagonal_rounds_below_zero_is_not_a_failure(name):
    """Review (s36): Q = G Qc Gᵀ of a singular (fully correlated) Qc is PSD; its third variance
    rounds to −1.06e-16, which check_psd accepts.  negative_variance had no tolerance, so the
    EKF and UKF runs flagged every predict NOT_PSD, skipped every step and gave NaN
    log-likelihoods (the square-root runs ran normally)."""
    a, b = 0.7, 2.3
    Qc = np.array([[a, np.sqrt(a * b)], [np.sqrt(a * b), b]])
    rng = np.random.default_rng(0)
    for _ in range(10000):  # a pair whose exact-zero variance rounds below 0
        a, b = rng.uniform(0.1, 3, 2)
        Qc = np.array([[a, np.sqrt(a * b)], [np.sqrt(a * b), b]])
        G = np.array([[1.0, 0.0], [0.0, 1.0], [1 / np.sqrt(a), -1 / np.sqrt(b)]])
        Q = G @ Qc @ G.T
        if Q[2, 2] < 0:
            break
    assert -1e-15 < Q[2, 2] < 0
    zs = np.arange(4.0)[:, None]
    post = jax.jit(lambda Q: MODS[name].filter_scan(lambda x, u: x, lambda x: x[:1], np.zeros(3), np.eye(3), None,
                                                    zs, None, Q, np.array([[0.1]])))(Q)
    assert np.asarray(post.status).tolist() == [0, 0, 0, 0]
    assert np.asarray(post.means)[-1, 0] > 2.5  # the updates were made (0 when every step was skipped)
    # a clearly negative variance is still NOT_PSD
    Qn = np.diag([0.01, 0.01, -1e-3])
    post = jax.jit(lambda Q: MODS[name].filter_scan(lambda x, u: x, lambda x: x[:1], np.zeros(3), np.eye(3), None,
                                                    zs, None, Q, np.array([[0.1]])))(Qn)
    assert all(int(s_) & errors.NOT_PSD for s_ in np.asarray(post.status))
