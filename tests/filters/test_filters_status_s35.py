"""The four generic filters (``ekf``, ``ukf``, ``sqrt_ekf``, ``sqrt_ukf``) flag the same traced
failure with the same status bits, take a scalar ``Q`` in a whole run wherever one step's predict
takes it, and refuse boolean ``x0`` / ``P0`` / ``zs`` / ``Q`` / ``R`` by name.

The bits follow the documented meaning (``jaxslam.errors``, ``gaussian.failure_status``): a NaN/Inf
that reaches a step is ``NON_FINITE`` (and not also ``NOT_PSD`` because the NaN made a Cholesky
factor NaN); a finite covariance that does not factor is ``NOT_PSD`` (and not also ``NON_FINITE``
because the failed factor produced a NaN).  Before (2026-12-07, this file's model): a NaN ``R``
gave 34 in ekf/ukf and 32 in the square-root filters, a NaN ``x0`` 2 in ekf/sqrt_ekf and 34 in
ukf/sqrt_ukf, a NaN ``Q`` 34 in ekf/sqrt_ekf and 2 in ukf/sqrt_ukf.

Expected values are written by hand (flags, messages) or are the same call with the equivalent
well-formed argument (a (1, 1) ``Q`` for a scalar one).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, gaussian, sqrt_ekf, sqrt_ukf, ukf

MODS = {"ekf": ekf, "ukf": ukf, "sqrt_ekf": sqrt_ekf, "sqrt_ukf": sqrt_ukf}
DTYPES = [np.float64, np.float32]
T = 3
NF, NP = errors.NON_FINITE, errors.NOT_PSD


def f(x, u):
    return x


def h(x):  # linear: the EKF's S does not see a NaN mean (the UKF's sigma points do)
    return x[:1]


def _moments(dt):
    return dict(x0=np.zeros(2, dt), P0=np.eye(2, dtype=dt), Q=(0.1 * np.eye(2)).astype(dt),
                R=np.eye(1, dtype=dt))


def _bad(name, dt):
    """The traced failures: (argument, bad value)."""
    m = _moments(dt)
    nan_x0, inf_x0, nan_P0, nan_Q = m["x0"].copy(), m["x0"].copy(), m["P0"].copy(), m["Q"].copy()
    nan_x0[0], inf_x0[0], nan_P0[0, 0], nan_Q[0, 0] = np.nan, np.inf, np.nan, np.nan
    return {"x0-nan": ("x0", nan_x0), "x0-inf": ("x0", inf_x0), "P0-nan": ("P0", nan_P0),
            "Q-nan": ("Q", nan_Q), "R-nan": ("R", np.full((1, 1), np.nan, dt)),
            "R-inf": ("R", np.full((1, 1), np.inf, dt)), "R-neg": ("R", -np.eye(1, dtype=dt))}[name]


@pytest.mark.parametrize("dt", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("predict_first", [True, False], ids=["predict-first", "update-first"])
@pytest.mark.parametrize("mod", list(MODS))
def test_a_traced_failure_sets_the_same_bits_in_all_four_runs(mod, predict_first, dt):
    run = jax.jit(lambda x0, P0, Q, R: MODS[mod].filter_scan(
        f, h, x0, P0, None, jnp.ones((T, 1), dt), None, Q, R, predict_first=predict_first).status)
    m = _moments(dt)
    assert np.asarray(run(**m)).tolist() == [0] * T  # a clean run: no flag
    for case, want in (("x0-nan", NF), ("x0-inf", NF), ("P0-nan", NF), ("Q-nan", NF), ("R-nan", NF),
                       ("R-inf", NF), ("R-neg", NP)):
        arg, value = _bad(case, dt)
        status = np.asarray(run(**{**m, arg: value})).tolist()
        # a NaN Q with the update first: step 0 updates (x0, P0) before any prediction
        expect = [0] + [want] * (T - 1) if (case == "Q-nan" and not predict_first) else [want] * T
        assert status == expect, (mod, case, status)
    # eagerly the same values are known and refused by name before anything runs (unchanged)
    for case, message in (("x0-nan", r"^x0: contains NaN or Inf"), ("R-nan", r"^R: contains NaN or Inf")):
        arg, value = _bad(case, dt)
        a = {**m, arg: value}
        with pytest.raises(InputError, match=message):
            MODS[mod].filter_scan(f, h, a["x0"], a["P0"], None, np.ones((T, 1), dt), None, a["Q"], a["R"],
                                  predict_first=predict_first)


@pytest.mark.parametrize("dt", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("mod", list(MODS))
def test_a_traced_failure_sets_the_same_bits_in_all_four_updates(mod, dt):
    sq = mod.startswith("sqrt")
    state = (sqrt_ekf.SqrtGaussian if sq else ekf.Gaussian)(jnp.zeros(2, dt), jnp.eye(2, dtype=dt))

    @jax.jit
    def upd(mean, R):
        _, info = MODS[mod].update(state._replace(mean=mean), jnp.ones(1, dt), h, R)
        return info.status

    zero, one = np.zeros(2, dt), np.eye(1, dtype=dt)
    assert int(upd(zero, one)) == 0
    assert int(upd(zero, np.full((1, 1), np.nan, dt))) == NF  # was 34 (ekf, ukf) / 32 (sqrt)
    assert int(upd(np.array([np.nan, 0.0], dt), one)) == NF  # was 2 (ekf, sqrt_ekf) / 34 (ukf, sqrt_ukf)
    assert int(upd(zero, -one)) == NP  # S = 1 - 1 singular: was 34 in ekf / ukf (an Inf from the solve)
    # eagerly the values are known: refused by name, as before
    with pytest.raises(InputError, match=r"^R: contains NaN or Inf"):
        MODS[mod].update(state, jnp.ones(1, dt), h, np.full((1, 1), np.nan, dt))


def test_ukf_predict_and_batch_update_flag_a_nan_prior_non_finite():
    # the sigma points of a NaN covariance fail their factor: that is the NaN's failure
    P = jnp.array([[jnp.nan, 0.0], [0.0, 1.0]])
    st = jax.jit(lambda P: ukf.predict(ekf.Gaussian(jnp.zeros(2), P), f, None, 0.1 * jnp.eye(2),
                                       return_status=True)[1])
    assert int(st(P)) == NF  # was NOT_PSD
    assert int(st(jnp.array([[1.0, 2.0], [2.0, 1.0]]))) == NP  # finite, indefinite: NOT_PSD, as before
    # ekf.update_batch: the marginal and the joint factorisation follow the same rule
    bat = jax.jit(lambda R: ekf.update_batch(ekf.Gaussian(jnp.zeros(2), jnp.eye(2)), jnp.ones((2, 1)), h,
                                             R)[1].status)
    assert np.asarray(bat(jnp.full((2, 1, 1), jnp.nan))).tolist() == [NF, NF]  # was [34, 34]
    assert np.asarray(bat(-jnp.ones((2, 1, 1)))).tolist() == [NP, NP]


# --- a scalar Q in a whole run ------------------------------------------------------------------

def _one(x, u):
    return 0.9 * x


def _h1(x):
    return x


@pytest.mark.parametrize("dt", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
@pytest.mark.parametrize("mod", list(MODS))
def test_a_run_takes_a_scalar_q_for_one_noise_input_as_predict_does(mod, jit, dt):
    zs = np.array([[0.5], [0.2], [-0.1], [0.3]], dt)
    x0, P0, R = np.zeros(1, dt), np.eye(1, dtype=dt), np.full((1, 1), 0.2, dt)

    def run(Q, R=R):
        call = lambda Q, R: MODS[mod].filter_scan(_one, _h1, x0, P0, None, zs, None, Q, R)  # noqa: E731
        out = jax.jit(call)(Q, R) if jit else call(Q, R)
        return np.asarray(out.means), np.asarray(out.cov_diags), np.asarray(out.status)

    ref = run(np.full((1, 1), 0.05, dt))
    assert ref[0].dtype == dt and not np.any(ref[2])
    for Q in (np.asarray(0.05, dt), np.full((1,), 0.05, dt)):  # refused before: "expected a square matrix"
        for a, b in zip(run(Q), ref):
            np.testing.assert_array_equal(a, b)
    # and a (1,) R for one measurement, as update takes it (refused before: "R: expected shape (1, 1)")
    for a, b in zip(run(np.full((1, 1), 0.05, dt), np.full((1,), 0.2, dt)), ref):
        np.testing.assert_array_equal(a, b)
    # the single step takes the same scalar
    g = (sqrt_ekf.SqrtGaussian if mod.startswith("sqrt") else ekf.Gaussian)(jnp.zeros(1, dt), jnp.eye(1, dtype=dt))
    MODS[mod].predict(g, _one, None, np.asarray(0.05, dt))


@pytest.mark.parametrize("mod", list(MODS))
def test_a_scalar_q_of_a_two_component_state_is_refused_by_name(mod):
    # as in predict: a scalar is the variance of a single noise input only
    with pytest.raises(InputError, match=r"^Q: expected shape \(2, 2\)"):
        MODS[mod].filter_scan(f, h, np.zeros(2), np.eye(2), None, np.ones((T, 1)), None, 0.1, np.eye(1))
    with pytest.raises(InputError, match=r"^Q: not positive semi-definite"):
        MODS[mod].filter_scan(_one, _h1, np.zeros(1), np.eye(1), None, np.ones((T, 1)), None, -0.1, np.eye(1))


@pytest.mark.parametrize("mod", ["ekf", "ukf", "sqrt_ekf"])
def test_a_run_takes_a_scalar_q_beside_a_one_column_noise_jac(mod):
    G = np.array([[0.5], [1.0]])
    zs = np.array([[0.5], [0.2], [-0.1]])
    out = [MODS[mod].filter_scan(f, h, np.zeros(2), np.eye(2), None, zs, None, Q, np.eye(1), noise_jac=G)
           for Q in (0.3, 0.3 * np.eye(1))]
    np.testing.assert_array_equal(np.asarray(out[0].means), np.asarray(out[1].means))
    np.testing.assert_array_equal(np.asarray(out[0].cov_diags), np.asarray(out[1].cov_diags))


# --- booleans are not numbers -------------------------------------------------------------------

RUNS = {**{k: m.filter_scan for k, m in MODS.items()},
        "gaussian.run": lambda f, h, *a: gaussian.run(ekf.make_filter(f, h), *a)}


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
@pytest.mark.parametrize("arg", ["x0", "P0", "zs", "Q", "R"])
@pytest.mark.parametrize("name", list(RUNS))
def test_a_run_refuses_booleans_by_name(name, arg, jit):
    good = dict(x0=np.zeros(2), P0=np.eye(2), zs=np.ones((T, 1)), Q=np.eye(2), R=np.eye(1))
    bad = {"x0": np.array([True, False]), "P0": np.eye(2, dtype=bool), "zs": np.ones((T, 1), bool),
           "Q": np.eye(2, dtype=bool), "R": np.ones((1, 1), bool)}[arg]

    def call(v):
        a = {**good, arg: v}
        return RUNS[name](f, h, a["x0"], a["P0"], None, a["zs"], None, a["Q"], a["R"])

    RUNS[name](f, h, *(good[k] for k in ("x0", "P0")), None, good["zs"], None, good["Q"], good["R"])
    with pytest.raises(InputError, match=rf"^{arg}: expected numbers, got booleans"):
        jax.jit(call)(bad) if jit else call(bad)  # before: True read as 1, the run went ahead
    if not jit:  # a list holding a bool too
        with pytest.raises(InputError, match=rf"^{arg}: expected numbers, got booleans"):
            call(bad.tolist())


def test_sqrt_ekf_refuses_a_boolean_q_chol():
    with pytest.raises(InputError, match=r"^Q_chol: expected numbers, got booleans"):
        sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, np.ones((T, 1)), None, None, np.eye(1),
                             Q_chol=np.eye(2, dtype=bool))


@pytest.mark.parametrize("which", ["P0", "Q"])
@pytest.mark.parametrize("predict_first", [True, False])
def test_an_indefinite_traced_p0_or_q_is_not_psd_in_all_four_runs(which, predict_first):
    # a finite covariance that fails to factor is NOT_PSD (the rule above); the square-root runs
    # factor P0 and Q before the scan into a NaN factor, and said NON_FINITE at every step
    F = jnp.array([[1.0, 0.1], [0.0, 1.0]])
    us, zs = jnp.zeros((3, 1)), jnp.ones((3, 1))
    P0 = jnp.diag(jnp.array([1.0, -1.0])) if which == "P0" else jnp.eye(2)
    Q = jnp.diag(jnp.array([0.1, -5.0])) if which == "Q" else 0.1 * jnp.eye(2)
    got = {}
    for name, mod in (("ekf", ekf), ("ukf", ukf), ("sqrt_ekf", sqrt_ekf), ("sqrt_ukf", sqrt_ukf)):
        run = jax.jit(lambda P0, Q, mod=mod: mod.filter_scan(lambda x, u: F @ x, lambda x: x[:1], jnp.zeros(2), P0,
                                                             us, zs, None, Q, 0.1 * jnp.eye(1),
                                                             predict_first=predict_first).status)
        got[name] = np.asarray(run(P0, Q)).tolist()
    # (with the update first, an indefinite Q is first used after step 0's update)
    want = [0 if which == "Q" and not predict_first else errors.NOT_PSD] + [errors.NOT_PSD] * 2
    assert got == {k: want for k in got}, got
