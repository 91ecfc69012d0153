"""Bad input to the tuning modules (losses, params, optimize, targets) raises InputError naming
the argument before any compute."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.tuning import losses as L
from jaxslam.tuning import optimize as O
from jaxslam.tuning import params as P
from jaxslam.tuning import targets as TG
from jaxslam.tuning.targets import linear_gaussian as LG


def _quad(th, item):
    return jnp.sum((th["a"] - item) ** 2)


@pytest.mark.parametrize("call, msg", [
    (lambda: L.nll_terms(jnp.ones(2), jnp.eye(3)), r"^S: expected shape \(2, 2\)"),
    (lambda: L.nll_terms(jnp.ones(2), jnp.eye(2), jnp.ones(3, bool)), r"^mask: expected shape \(2,\)"),
    (lambda: L.nll_terms("ab", jnp.eye(2)), r"^nu: expected numbers"),
    (lambda: L.innovation_nll(jnp.ones(3), jnp.ones(2), jnp.ones(3)), r"^logdet: expected shape \(3,\)"),
    (lambda: L.innovation_nll(jnp.ones(3), jnp.ones(3), -jnp.ones(3)), r"^dof: expected counts >= 0"),
    (lambda: L.mse(jnp.ones((4, 2)), weights=-1.0), r"^weights: expected non-negative"),
    (lambda: L.mse(jnp.ones((4, 2)), weights=jnp.ones(3)), r"^weights: expected a number or shape \(2,\)"),
    (lambda: L.mse(jnp.ones((4, 2)), mask=jnp.ones(3, bool)), r"^mask: expected shape \(4,\)"),
    (lambda: L.mse(jnp.ones((0, 2))), r"^err: expected a non-empty"),
    (lambda: L.nees_loss(jnp.ones(4), 0), r"^n: expected a state dimension"),
    (lambda: L.nees_loss(jnp.ones(4), -3), r"^n: expected a state dimension"),
    (lambda: L.nees_loss(jnp.ones(4), 3, mask=jnp.zeros(4, bool)), r"^mask: selects no step"),
    (lambda: L.nees_loss(jnp.ones(4), 3, mask=jnp.ones(3, bool)), r"^mask: expected shape \(4,\)"),
    (lambda: L.nees_loss(jnp.ones(0), 3), r"^nees: expected a non-empty"),
])
def test_losses_refuse_bad_input(call, msg):
    with pytest.raises(InputError, match=msg):
        call()


def test_losses_accept_lists_and_traced_masks():
    assert float(L.mse([[1.0, 2.0]])) == pytest.approx(5.0)
    assert float(L.nees_loss([3.0, 3.0], 3)) == pytest.approx(0.0)
    nis, logdet, dof = L.nll_terms([1.0, 2.0], np.eye(2))
    assert float(nis) == pytest.approx(5.0) and float(dof) == 2.0
    # traced all-False mask: no value check (nothing raises under jit)
    out = jax.jit(lambda m: L.nees_loss(jnp.ones(4), 3, mask=m))(jnp.zeros(4, bool))
    assert out.shape == ()


@pytest.mark.parametrize("call, msg", [
    (lambda: P.cov_from_log_diag(jnp.zeros((2, 2))), r"^theta: expected a vector"),
    (lambda: P.n_params(P.CovSpec("diag", -2)), r"^n: expected a matrix size"),
    (lambda: P.n_params(P.CovSpec("chol", 2.5)), r"^n: expected a matrix size"),
    (lambda: P.cov_from_theta(P.CovSpec("diag", 0), jnp.ones(0)), r"^n: expected a matrix size"),
    (lambda: P.cov_from_log_chol(jnp.ones(2), 2), r"^theta: expected shape \(3,\)"),
    (lambda: P.cov_from_log_chol(jnp.ones(3), 2.0), r"^n: expected a matrix size"),
    (lambda: P.log_diag_from_cov("abc"), r"^M: expected numbers"),
    (lambda: P.log_diag_from_cov(np.eye(2), floor="1e-3"), r"^floor: must be > 0"),
    (lambda: P.pack({"Q": ("diag", 2)}, {"Q": np.eye(2)}), r"^spec: expected a CovSpec"),
])
def test_params_refuse_bad_input(call, msg):
    with pytest.raises(InputError, match=msg):
        call()


def test_params_accept_lists():
    np.testing.assert_allclose(np.asarray(P.cov_from_log_chol([0.0, 0.0, 0.0], 2)), np.eye(2))
    np.testing.assert_allclose(np.asarray(P.cov_from_theta(P.CovSpec("diag", 2), [0.0, 0.0])), np.eye(2))


@pytest.mark.parametrize("kw, msg", [
    (dict(final_lr_frac=-1.0), r"^final_lr_frac: expected a number in \[0, 1\]"),
    (dict(final_lr_frac=float("nan")), r"^final_lr_frac: expected a number in \[0, 1\]"),
    (dict(steps=2.5), r"^steps: expected an int"),
    (dict(steps=float("nan")), r"^steps: expected an int"),
    (dict(lr="0.1"), r"^lr: expected a positive finite number \(--lr\)"),
])
def test_make_optimizer_refuses_bad_input(kw, msg):
    a = dict(lr=0.1, steps=10)
    a.update(kw)
    with pytest.raises(InputError, match=msg):
        O.make_optimizer(a.pop("lr"), a.pop("steps"), **a)


@pytest.mark.parametrize("kw, msg", [
    (dict(batch_size=2.5, key=jax.random.PRNGKey(0)), r"^batch_size: expected an int >= 1"),
    (dict(batch_size=2, key=5), r"^key: expected a PRNG key"),
    (dict(eval_every=1.5, test=jnp.arange(2.0)), r"^eval_every: expected an int >= 0"),
    (dict(eval_every=1, test={"x": jnp.arange(2.0)}), r"^test: the loss cannot be evaluated on this held-out batch"),
    (dict(eval_every=1, test=jnp.zeros(())), r"^test: every array needs the same leading axis"),
    (dict(b2="0.9"), r"^b2: must be in \(0, 1\), got '0.9'"),  # (a bare TypeError before)
    (dict(b2=None), r"^b2: must be in \(0, 1\), got None"),
    (dict(explode_ratio="5"), r"^explode_ratio: expected a finite number > 1 or None, got '5'"),
    (dict(explode_ratio=1.0), r"^explode_ratio: expected a finite number > 1 or None"),
])
def test_fit_refuses_bad_input(kw, msg):
    with pytest.raises(InputError, match=msg):
        O.fit(_quad, {"a": jnp.array(0.0)}, jnp.arange(4.0), 2, **kw)


def test_fit_accepts_typed_and_raw_keys():
    for key in (jax.random.PRNGKey(0), jax.random.key(0)):
        res = O.fit(_quad, {"a": jnp.array(0.0)}, jnp.arange(4.0), 1, batch_size=2, key=key)
        assert len(res.history) == 2


_R = type("R", (), {"nll": np.ones(3), "nll_dof": np.ones(3)})()


@pytest.mark.parametrize("call, msg", [
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=5, train_run=8), r"^train_run: unknown keyword"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=5, train_runs=0), r"^train_runs: expected an int >= 1"),
    # every simulation target refuses a misspelled keyword before it builds anything
    (lambda: TG.get("ekfslam3d-unknown", "noise", "nll", captacity=8), r"^captacity: unknown keyword"),
    (lambda: TG.get("ekfslam3d-unknown", "loop", "cost", w_nee=1.0), r"^w_nee: unknown keyword"),
    (lambda: TG.get("track-figure8", "lqr", "cost", start_sigm=0.1), r"^start_sigm: unknown keyword"),
    (lambda: TG.get("uwb-circle", "noise", "mse", mod="slam"), r"^mod: unknown keyword"),
    # and so does every real-log target, before it reads a file
    (lambda: TG.get("mrclam", "noise", "nll", test_robot=(5,)), r"^test_robot: unknown keyword"),
    (lambda: TG.get("plaza", "noise", "nll", tmax=100.0), r"^tmax: unknown keyword"),
    (lambda: TG.get("util-uwb", "noise", "nll", anchor_offset=True), r"^anchor_offset: unknown keyword"),
    (lambda: TG.get("victoria-park", "noise", "nll", robots=(1,)), r"^robots: unknown keyword"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=5, test_runs=-1), r"^test_runs: expected an int >= 1"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=0), r"^T: expected an int >= 1"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=-3), r"^T: expected an int >= 1"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=5, q0_scale=-1.0), r"^q0_scale: expected a positive"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=5, seed="x"), r"^seed: expected an int"),
    (lambda: TG.get("linear-gaussian", "noise", "nll", T=5, dtype="float7"), r"^dtype: expected a floating dtype"),
    (lambda: LG.lg_simulate(jax.random.PRNGKey(0), 5, -np.eye(4), np.eye(4)), r"^Q: not positive semi-definite"),
    (lambda: LG.lg_simulate(jax.random.PRNGKey(0), 5, np.eye(3), np.eye(4)), r"^Q: expected shape \(4, 4\)"),
    (lambda: LG.lg_simulate(jax.random.PRNGKey(0), 5, np.eye(4), np.eye(4), dt=0.0), r"^dt: expected a positive"),
    (lambda: LG.lg_simulate(jax.random.PRNGKey(0), 2.5, np.eye(4), np.eye(4)), r"^T: expected an int >= 1"),
    (lambda: LG.lg_run(jnp.eye(4), jnp.eye(4), jnp.zeros((3, 4)), P0=-jnp.eye(4)), r"^P0: not positive semi-definite"),
    (lambda: LG.lg_run(jnp.eye(4), jnp.eye(2), jnp.zeros((3, 4))), r"^R: expected shape \(4, 4\)"),
    (lambda: LG.lg_run(jnp.eye(4), jnp.eye(4), jnp.zeros((3, 2))), r"^z: expected shape \(\*, 4\)"),
    (lambda: TG.keys(0, -1), r"^runs: expected an int >= 1"),
    (lambda: TG.keys(0, 2.7), r"^runs: expected an int >= 1"),
    (lambda: TG.heldout_nll(_R, held=np.array([1, 1, 0])), r"^held: expected a bool mask of shape \(3,\)"),
    (lambda: TG.heldout_nll(_R, held=np.ones(2, bool)), r"^held: expected a bool mask of shape \(3,\)"),
    (lambda: TG.diag_list([1.0, 2.0, 3.0]), r"^M: expected a matrix"),
])
def test_targets_refuse_bad_input(call, msg):
    with pytest.raises(InputError, match=msg):
        call()


def test_targets_accept_cli_keywords_and_valid_helpers():
    tg = TG.get("linear-gaussian", "noise", "nll", T=3, train_runs=1, test_runs=1, seed=0, dtype=jnp.float64,
                eval_duration=None, checkpoint=True, cov="diag", tune_r=False, structure="qc", filter="ekf")
    assert tg.train["z"].shape == (1, 3, 4)
    assert TG.heldout_nll(_R, held=np.array([True, True, False])) == pytest.approx(1.0)
    assert TG.diag_list(np.diag([1.0, 2.0])) == [1.0, 2.0]
    assert TG.keys(0, 2).shape[0] == 2


def test_window_nll_refuses_weights_of_another_length():
    res = type("R", (), {"nll": jnp.ones(3), "nll_dof": jnp.ones(3)})()
    with pytest.raises(InputError, match=r"^weights: expected one weight per event, shape \(3,\)"):
        TG.window_nll(res, weights=jnp.ones(2))
    assert float(TG.window_nll(res, weights=jnp.ones(3))) == pytest.approx(1.0)


def test_fit_accepts_a_test_batch_with_extra_entries_the_loss_reads_fine():
    train = {"z": jnp.arange(4.0)}
    test = {"z": jnp.arange(2.0), "w": jnp.ones(2)}
    res = O.fit(lambda th, it: (th["a"] - it["z"]) ** 2, {"a": jnp.array(0.0)}, train, 1, test=test, eval_every=1)
    assert res.history[-1]["test_loss"] == pytest.approx(0.5, rel=0.5)


def test_nll_terms_refuses_a_non_bool_concrete_mask_and_a_non_pd_s():
    nu, S = jnp.array([1.0, 2.0, 3.0]), jnp.eye(3)
    want = L.nll_terms(nu, S, jnp.array([True, False, True]))
    assert float(want[2]) == 2.0
    # a float mask, or integers other than 0/1, are refused (a mask [2, 0, 1] counted dof 3, not 2)
    for bad in (np.array([2, 0, 1]), np.array([1.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.5])):
        with pytest.raises(InputError, match="^mask: expected a bool mask"):
            L.nll_terms(nu, S, bad)
    # bool and 0/1 integer masks give the same answer
    for ok in ([True, False, True], jnp.array([1, 0, 1]), [1, 0, 1]):
        np.testing.assert_array_equal(np.asarray(L.nll_terms(nu, S, ok)), np.asarray(want))
    # a concrete S that is not PD gave NaN NIS and log det silently
    for bad_S in (jnp.diag(jnp.array([1.0, -1.0, 1.0])), jnp.zeros((3, 3))):
        with pytest.raises(InputError, match="^S: not positive definite"):
            L.nll_terms(nu, bad_S)
    with pytest.raises(InputError, match="^S: contains NaN or Inf"):
        L.nll_terms(nu, jnp.eye(3).at[0, 0].set(jnp.nan))
    # traced: no value check, nothing raises, results as before
    out = jax.jit(L.nll_terms)(nu, S, jnp.array([1, 0, 1]))
    np.testing.assert_array_equal(np.asarray(out), np.asarray(want))
    assert np.isnan(float(jax.jit(L.nll_terms)(nu, jnp.diag(jnp.array([1.0, -1.0, 1.0])))[0]))


def test_small_well_conditioned_covariances_and_the_exp_range():
    """Review of 2026-12-07: a strict PSD check with an absolute floor of 1e-12 refused a
    well-conditioned matrix of small entries (an IMU bias density: NumPy's Cholesky takes it);
    a variance outside the dtype's range made a singular or infinite matrix without a word."""
    for s in (1e-14, 1e-12, 1e-10, 1.0, 1e10):
        M = s * np.array([[2.0, 0.5], [0.5, 1.0]])
        th = P.log_chol_from_cov(M, dtype=jnp.float64)
        np.testing.assert_allclose(np.asarray(P.cov_from_log_chol(th, 2)), M, rtol=1e-12)
        np.testing.assert_allclose(np.linalg.cholesky(M) @ np.linalg.cholesky(M).T, M, rtol=1e-14)  # the oracle
    nis, logdet, dof = L.nll_terms(np.array([1e-7, -2e-7]), 1e-13 * np.array([[2.0, 0.5], [0.5, 1.0]]))
    S = 1e-13 * np.array([[2.0, 0.5], [0.5, 1.0]])
    nu = np.array([1e-7, -2e-7])
    assert float(nis) == pytest.approx(nu @ np.linalg.solve(S, nu), rel=1e-10)
    assert float(logdet) == pytest.approx(np.linalg.slogdet(S)[1], rel=1e-12)
    with pytest.raises(InputError, match=r"^M: not positive definite"):
        P.log_chol_from_cov(np.array([[1.0, 1.0], [1.0, 1.0]]))  # singular: still refused
    for M, dt in ((np.diag([1e-50, 1.0]), jnp.float32), (np.diag([1e40, 1.0]), jnp.float32)):
        with pytest.raises(InputError, match=r"^M: a variance of .* is outside float32's range"):
            P.log_diag_from_cov(M, dtype=dt)
    with pytest.raises(InputError, match=r"^M: a variance of .* is outside float32's range"):
        P.log_chol_from_cov(np.diag([1e40, 1e39]), dtype=jnp.float32)
    assert np.isfinite(np.asarray(P.log_diag_from_cov(np.diag([1e-50, 1.0]), dtype=jnp.float64))).all()
