"""Linear-Gaussian oracle: NLL tuning finds the maximum-likelihood Q, R (known truth).

The loss is checked against an independent NumPy Kalman filter likelihood; the optimiser
must reach (or beat) the likelihood of the true parameters; the slow test recovers Q and R
within 10 % on a long log (the acceptance figure of issue 7, also in docs/results/tuning).
"""

import math

import numpy as np
import pytest

from jaxslam.tuning import optimize as O
from jaxslam.tuning.targets import linear_gaussian as T


def _numpy_nll(Q, R, zs, dt=T.LG_DT):
    """−log p(z) per scalar measurement of the oracle, NumPy Kalman filter (x0 = 0, P0 = I)."""
    A = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    tot, n = 0.0, 0
    for z in zs:
        x, Pm = np.zeros(4), np.eye(4)
        for zk in z:
            x = A @ x
            Pm = A @ Pm @ A.T + Q
            S = Pm + R
            nu = zk - x
            tot += 0.5 * (nu @ np.linalg.solve(S, nu) + np.linalg.slogdet(S)[1] + 4 * math.log(2 * math.pi))
            n += 4
            K = Pm @ np.linalg.inv(S)
            x = x + K @ nu
            IK = np.eye(4) - K
            Pm = IK @ Pm @ IK.T + K @ R @ K.T
    return tot / n


@pytest.fixture(scope="module")
def small():
    tg = T.linear_gaussian("nll", train_runs=2, test_runs=1, T=500, seed=0)
    res = O.fit(tg.loss_fn, tg.theta0, tg.train, 40, 0.3)
    return tg, res


def test_loss_equals_independent_numpy_likelihood(small):
    """The recorded losses at the start and at the result (history records 0 and last)."""
    tg, res = small
    zs = np.asarray(tg.train["z"])
    for th, rec in ((tg.theta0, res.history[0]), (res.theta, res.history[-1])):
        m = tg.physical(th)
        np.testing.assert_allclose(rec["loss"], _numpy_nll(np.asarray(m["Q"]), np.asarray(m["R"]), zs), rtol=1e-10)


def test_nll_tuning_reaches_the_likelihood_of_the_truth(small):
    tg, res = small
    assert res.stopped is None
    zs = np.asarray(tg.train["z"])
    start, tuned = res.history[0]["loss"], res.history[-1]["loss"]
    truth = _numpy_nll(np.diag(T.LG_Q_TRUE), np.asarray(T.LG_R_TRUE), zs)
    assert start - truth > 0.05  # the start is clearly wrong
    assert tuned <= truth  # the maximum-likelihood estimate beats the truth on its own data
    m = tg.physical(res.theta)
    # The best-identified entries (velocity noise, x-position measurement) are already close.
    q = np.diag(np.asarray(m["Q"])) / np.asarray(T.LG_Q_TRUE)
    assert abs(q[2] - 1) < 0.25 and abs(q[3] - 1) < 0.25
    assert abs(float(m["R"][0, 0]) / T.LG_R_TRUE[0][0] - 1) < 0.25


@pytest.mark.slow
def test_nll_tuning_recovers_q_r_within_10_percent():
    tg = T.linear_gaussian("nll", train_runs=4, test_runs=1, T=5000, seed=0)
    res = O.fit(tg.loss_fn, tg.theta0, tg.train, 400, 0.3)
    m = tg.physical(res.theta)
    Qt, Rt = np.diag(T.LG_Q_TRUE), np.asarray(T.LG_R_TRUE)
    np.testing.assert_allclose(np.diag(np.asarray(m["Q"])), np.diag(Qt), rtol=0.10)
    R = np.asarray(m["R"])
    nz = Rt != 0
    np.testing.assert_allclose(R[nz], Rt[nz], rtol=0.10)
    corr = R / np.sqrt(np.outer(np.diag(R), np.diag(R)))
    assert np.max(np.abs(corr[~nz])) < 0.10
