"""Review fixes: planar FastSLAM input checks, the range-only log's mask, the tuning losses'
dtype/edge cases.  Expectations are hand-computed or NumPy, never the code under test."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.filters import ekf_slam as es
from jaxslam.systems import biased_range as br
from jaxslam.systems import planar_fastslam as pf
from jaxslam.tuning import losses as L

T_ = 6


def _plog(**kw):
    d = dict(dt=np.full(T_, 0.1), u=np.tile([1.0, 0.1], (T_, 1)), z=np.tile([[5.0, 0.3], [4.0, -0.2]], (T_, 1, 1)),
             ids=np.tile(np.array([0, 1], np.int32), (T_, 1)), mask=np.ones((T_, 2), bool), pose0=np.zeros(3),
             is_input=None)
    d.update(kw)
    return pf.Log(**d)


CFG = pf.Config(n_particles=4, capacity=4, K=2)


def test_planar_fastslam_names_an_is_input_of_the_wrong_length_or_dtype():
    key = jax.random.PRNGKey(0)
    cfg = CFG._replace(motion="increment")
    # a wrong length failed inside the scan (ValueError); 0.5 was read as True
    with pytest.raises(InputError, match=r"^log\.is_input: expected shape \(6,\)"):
        pf.run(_plog(is_input=np.ones(3, bool)), cfg, pf.default_params(), key=key)
    with pytest.raises(InputError, match=r"^log\.is_input: expected a bool mask"):
        pf.run(_plog(is_input=np.full(T_, 0.5)), cfg, pf.default_params(), key=key)
    r = pf.run(_plog(is_input=np.ones(T_, np.int32)), cfg, pf.default_params(), key=key)
    assert float(r.used) == 2 * T_ - 2  # 2 rows per event, the first event registers both


@pytest.mark.parametrize("field", ["robust", "slot_by_id"])
def test_planar_fastslam_refuses_a_non_bool_switch(field):
    # "no" is truthy: the switch was silently on
    with pytest.raises(InputError, match=rf"^config\.{field}: expected True or False, got 'no'"):
        pf.run(_plog(), CFG._replace(**{field: "no"}), pf.default_params(), key=jax.random.PRNGKey(0))


@pytest.mark.parametrize("key", [np.array([1.0, 2.0]), "abc", jax.random.split(jax.random.PRNGKey(0), 2)])
def test_planar_fastslam_names_a_key_that_is_not_one_prng_key(key):
    # float key data, a string and a batch of keys failed inside the sampler (TypeError/ValueError)
    with pytest.raises(InputError, match=r"^key: expected a PRNG key"):
        pf.run(_plog(), CFG, pf.default_params(), key=key)


def test_planar_fastslam_accepts_a_typed_key():
    r = pf.run(_plog(), CFG, pf.default_params(), key=jax.random.key(0))
    assert float(r.used) == 2 * T_ - 2


def test_planar_default_params_refuse_negative_sigmas_and_keep_the_variances():
    with pytest.raises(InputError, match=r"^sigma_r: expected a non-negative finite scalar, got -0\.1"):
        pf.default_params(sigma_r=-0.1)  # squared into a valid R before
    with pytest.raises(InputError, match=r"^sigma_w: expected a non-negative finite scalar"):
        pf.default_params(sigma_w=float("nan"))
    with pytest.raises(InputError, match=r"^pose0_sigma: expected 3 finite numbers >= 0"):
        pf.default_params(pose0_sigma=(0.01, -0.01, 0.005))
    with pytest.raises(InputError, match=r"^floor: expected 3 finite numbers >= 0"):
        pf.default_params(floor=(1e-6, 1e-6))
    p = pf.default_params(sigma_r=0.2, sigma_b=0.03, sigma_v=0.5, sigma_w=0.1)
    np.testing.assert_allclose(np.asarray(p.R), [[0.04, 0.0], [0.0, 0.0009]], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(p.M_c), [[0.25, 0.0], [0.0, 0.01]], rtol=1e-6)


def _range_log(mask):
    T, K = 3, 2
    return types.SimpleNamespace(t=np.arange(T) * 0.1, dt=np.full(T, 0.1), z=np.ones((T, K, 1)),
                                 ids=np.zeros((T, K), np.int32), mask=mask, u=None)


def test_range_log_mask_must_be_bool_or_0_1():
    br.check_log(_range_log(np.ones((3, 2), bool)))
    br.check_log(_range_log(np.ones((3, 2), np.int32)))
    # a float mask failed inside the run with a TypeError; a 2 was read as True
    with pytest.raises(InputError, match=r"^log\.mask: expected a bool mask \(or 0/1 integers\), got dtype float64"):
        br.check_log(_range_log(np.full((3, 2), 0.5)))
    with pytest.raises(InputError, match=r"^log\.mask: expected a bool mask \(or 0/1 integers\), got the value 2"):
        br.check_log(_range_log(np.full((3, 2), 2)))


def test_nll_terms_keep_nus_float32_dtype_and_match_numpy():
    nu = np.array([0.3, -0.7], np.float32)
    S = np.array([[2.0, 0.3], [0.3, 0.5]])
    nis, logdet, dof = L.nll_terms(jnp.asarray(nu), S)
    assert nis.dtype == logdet.dtype == dof.dtype == jnp.float32  # nis/logdet were float64
    nu64 = nu.astype(np.float64)
    assert float(nis) == pytest.approx(nu64 @ np.linalg.solve(S, nu64), rel=1e-5)
    assert float(logdet) == pytest.approx(np.log(2.0 * 0.5 - 0.09), rel=1e-5)
    assert float(dof) == 2.0


def test_nll_terms_of_an_empty_innovation_are_zero():
    nis, logdet, dof = L.nll_terms(jnp.zeros(0), jnp.zeros((0, 0)))  # a ValueError in check_psd before
    assert (float(nis), float(logdet), float(dof)) == (0.0, 0.0, 0.0)


def test_innovation_nll_refuses_a_nan_count():
    with pytest.raises(InputError, match=r"^dof: expected counts >= 0"):  # the loss was NaN
        L.innovation_nll(jnp.ones(3), jnp.ones(3), jnp.array([1.0, np.nan, 1.0]))


def _range_model():
    return es.SlamModel(robot_dim=3, lm_dim=2, meas_dim=1, motion=lambda s, u, p: s,
                        observe=lambda s, l, p: br.range_observe(s, l))


def _range_state():
    s = np.array([1.0, 2.0, 0.3])  # (x, y, bias)
    lms = np.array([[4.0, 6.0], [-2.0, 2.0]])
    x = np.r_[s, lms.ravel()]
    B = np.random.default_rng(7).normal(size=(7, 7)) * 0.1
    P = B @ B.T + 1e-2 * np.eye(7)
    st = es.init(jnp.asarray(s), jnp.asarray(P[:3, :3]), 2, 2)._replace(
        x=jnp.asarray(x), P=jnp.asarray(P), active=jnp.ones(2, bool), ids=jnp.arange(2, dtype=jnp.int32))
    return st, s, lms, P


def test_slam_innovation_terms_take_a_0_1_valid_and_name_a_float_one():
    st, s, lms, P = _range_state()
    model = _range_model()
    z = np.array([[5.4], [3.2]])
    slots = np.array([0, 1])
    R = np.array([[0.04]])
    nis, logdet, dof = L.slam_innovation_terms(st, model, jnp.asarray(z), jnp.asarray(slots),
                                               jnp.asarray([1, 0], jnp.int32), jnp.asarray(R))
    # NumPy: one valid range to landmark 0, H = [(p-l)/r, 1, -(p-l)/r]
    d = s[:2] - lms[0]
    r = np.linalg.norm(d)
    H = np.zeros(7)
    H[:2], H[2], H[3:5] = d / r, 1.0, -d / r
    S = H @ P @ H + 0.04
    nu = 5.4 - (r + 0.3)
    assert float(nis) == pytest.approx(nu * nu / S, rel=1e-9)
    assert float(logdet) == pytest.approx(np.log(S), rel=1e-9)
    assert float(dof) == 1.0
    with pytest.raises(InputError, match=r"^valid: expected a bool mask"):  # a TypeError inside before
        L.slam_innovation_terms(st, model, jnp.asarray(z), jnp.asarray(slots), jnp.asarray([1.0, 0.0]),
                                jnp.asarray(R))
    with pytest.raises(InputError, match=r"^slots: expected shape \(2,\)"):
        L.slam_innovation_terms(st, model, jnp.asarray(z), jnp.asarray([0, 1, 1]), jnp.asarray([True, True]),
                                jnp.asarray(R))
    with pytest.raises(InputError, match=r"^z: expected shape \(K, 1\)"):
        L.slam_innovation_terms(st, model, jnp.asarray(z[:, 0]), jnp.asarray(slots), jnp.asarray([True, True]),
                                jnp.asarray(R))


def test_nees_loss_refuses_a_negative_nees():
    with pytest.raises(InputError, match=r"^nees: expected values >= 0"):  # log of a negative mean: NaN
        L.nees_loss(jnp.array([-1.0, -3.0]), 3)
    # (log(mean/n))^2 by hand: mean 6, n 3
    assert float(L.nees_loss(jnp.array([4.0, 8.0]), 3)) == pytest.approx(np.log(2.0) ** 2)
