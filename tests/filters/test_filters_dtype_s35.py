"""The Gaussian runs (``ekf``, ``ukf``, ``sqrt_ekf``, ``sqrt_ukf`` ``filter_scan`` and
``gaussian.run``) judge ``P0``, ``Q`` and ``R`` as given (float64) and then cast them to the run's
dtype (``x0``'s): a covariance that does not survive that cast (an entry that overflows to inf,
a variance that underflows to 0) is refused up front, naming the argument.  Before, since
check_psd judges a badly scaled matrix at unit diagonal (``diag(1e200, 1)`` is PD in float64),
such an ``R`` given to a float32 run was accepted and every step failed (status flags, the prior
kept).  Also: one message for a ``Q`` of the wrong size in every run.

Expected messages and flags are written by hand; "unchanged" results are compared with the
same run given the argument already in the run's dtype.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, gaussian, sqrt_ekf, sqrt_ukf, ukf

F = np.array([[1.0, 0.1], [0.0, 1.0]])


def f(x, u):
    return jnp.asarray(F, x.dtype) @ x


def h(x):
    return x


T = 6
ZS = np.random.default_rng(3).normal(size=(T, 2)).astype(np.float32)


def _gaussian_run(f, h, x0, P0, us, zs, masks, Q, R):
    return gaussian.run(ekf.make_filter(f, h), x0, P0, us, zs, masks, Q, R)


RUNS = {"ekf": ekf.filter_scan, "ukf": ukf.filter_scan, "sqrt_ekf": sqrt_ekf.filter_scan,
        "sqrt_ukf": sqrt_ukf.filter_scan, "gaussian.run": _gaussian_run}


def _run(name, dtype=np.float32, masks=None, **kw):
    a = dict(P0=np.eye(2), Q=0.01 * np.eye(2), R=0.1 * np.eye(2))
    a.update(kw)
    return RUNS[name](f, h, np.zeros(2, dtype), a["P0"], None, ZS, masks, a["Q"], a["R"])


# --- 1. a covariance that does not fit the run's dtype ------------------------------------------

@pytest.mark.parametrize("name", list(RUNS))
@pytest.mark.parametrize("arg", ["P0", "Q", "R"])
@pytest.mark.parametrize("value, message", [
    (np.diag([1e200, 1.0]), "entry 1e+200 does not fit float32, the run's dtype (x0's): it overflows to inf"),
    (np.diag([1.0, 1e-50]), "variance 1e-50 does not fit float32, the run's dtype (x0's): it underflows to 0"),
    (np.array([[1.0, 1e39], [1e39, 1e80]]),
     "entry 1e+39 does not fit float32, the run's dtype (x0's): it overflows to inf"),
], ids=["overflow", "underflow", "off-diagonal-overflow"])
def test_a_covariance_that_does_not_fit_a_float32_run_is_refused(name, arg, value, message):
    # before: accepted (PD in float64) and then inf / 0 in float32: R's overflow flagged every
    # step NON_FINITE with the means stuck at x0 (P0's: refused by ekf/ukf only as "contains NaN
    # or Inf", run by the square-root filters); an underflowed variance ran with a singular matrix
    with pytest.raises(InputError) as e:
        _run(name, **{arg: value})
    assert str(e.value) == f"{arg}: {message}"


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")  # the masked row's cast
@pytest.mark.parametrize("name", list(RUNS))
def test_a_per_step_r_is_named_by_its_step_and_its_masked_rows_are_not_read(name):
    R = np.stack([0.1 * np.eye(2)] * T)
    R[4] = np.diag([0.1, 1e200])
    with pytest.raises(InputError) as e:
        _run(name, R=R)
    assert str(e.value) == "R[4]: entry 1e+200 does not fit float32, the run's dtype (x0's): it overflows to inf"
    # the same entry on a masked measurement's row is not used (may hold anything, NaN included)
    masks = np.ones((T, 2), bool)
    masks[4, 1] = False
    got = _run(name, R=R, masks=masks)
    R[4, 1, 1] = np.nan
    ref = _run(name, R=R, masks=masks)
    np.testing.assert_array_equal(np.asarray(got.means), np.asarray(ref.means))
    np.testing.assert_array_equal(np.asarray(got.status), np.asarray(ref.status))


def test_sqrt_ekf_q_chol_that_overflows_the_run_is_refused():
    # before: status NON_FINITE at every step
    C = np.diag([1e200, 1.0])
    with pytest.raises(InputError) as e:
        sqrt_ekf.filter_scan(f, h, np.zeros(2, np.float32), np.eye(2), None, ZS, None, None, 0.1 * np.eye(2),
                             Q_chol=C)
    assert str(e.value) == "Q_chol: entry 1e+200 does not fit float32, the run's dtype (x0's): it overflows to inf"


@pytest.mark.parametrize("name", list(RUNS))
def test_ordinary_and_float64_runs_are_unchanged(name):
    # a float64 run keeps today's decision on a badly scaled R (PD, judged at unit diagonal)
    out = _run(name, dtype=np.float64, R=np.diag([1e200, 1.0]))
    assert np.asarray(out.means).dtype == np.float64
    assert not np.any(np.asarray(out.status) & (errors.NOT_PSD | errors.NON_FINITE))
    # a float64 R that fits float32 (a subnormal variance and one near the largest float32
    # included) is accepted: the run of the values already cast, bit for bit (R is cast before
    # use in every run; the square-root runs factor P0 and Q as given, so those are not compared)
    R = np.diag([1e-40, 3e38])
    a = _run(name, R=R)
    b = _run(name, R=R.astype(np.float32))
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb) >= 7
    for x, y in zip(la, lb):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# --- 2. one message for a Q of the wrong size ---------------------------------------------------

@pytest.mark.parametrize("name", ["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
@pytest.mark.parametrize("Q, got", [(np.eye(3), "(3, 3)"), (np.ones((T, 3, 3)), f"({T}, 3, 3)"),
                                    (0.1, "()")], ids=["3x3", "per-step", "scalar"])
def test_every_run_names_a_q_of_the_wrong_size_alike(name, Q, got):
    # before: ekf/ukf said "Q: expected shape (2, 2) (the state's size), got (3, 3)" (from the
    # step), the square-root runs "... (2, 2) or (6, 2, 2), got (3, 3)"
    with pytest.raises(InputError) as e:
        _run(name, dtype=np.float64, Q=Q)
    assert str(e.value) == f"Q: expected shape (2, 2) or ({T}, 2, 2), got {got}"


@pytest.mark.parametrize("name", ["ekf", "ukf", "sqrt_ekf"])
def test_a_q_against_noise_jac_is_named_alike(name):
    # before: ekf/ukf "Q: expected shape (1, 1) (noise_jac's columns), got (2, 2)", sqrt_ekf
    # "Q: expected shape (1, 1) or (6, 1, 1), got (2, 2)"
    L = np.array([[0.0], [1.0]])
    with pytest.raises(InputError) as e:
        RUNS[name](f, h, np.zeros(2), np.eye(2), None, ZS, None, 0.01 * np.eye(2), 0.1 * np.eye(2),
                   noise_jac=L)
    assert str(e.value) == f"Q: expected shape (1, 1) (noise_jac's columns) or ({T}, 1, 1), got (2, 2)"
    RUNS[name](f, h, np.zeros(2), np.eye(2), None, ZS, None, 0.01 * np.eye(1), 0.1 * np.eye(2), noise_jac=L)
