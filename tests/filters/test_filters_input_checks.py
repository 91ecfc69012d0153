"""Bad input to the filters and the EKF-SLAM engine: an early InputError naming the argument,
or, inside a run, a flag (never a silent broadcast, a clamped index or a hidden failure).

The expected results are written by hand (shapes, counts, flags) or come from the same call
with the well-formed argument; none is computed by the path under test alone.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, ekf_slam as es, sqrt_ekf, sqrt_ukf, ukf
from jaxslam.sim import monte_carlo

F = np.array([[1.0, 0.1], [0.0, 1.0]])


def f(x, u):
    return jnp.asarray(F, x.dtype) @ x


def h(x):
    return x[:1]


ZS = np.random.default_rng(0).normal(size=(12, 1))
Q2 = 0.01 * np.eye(2)
R1 = 0.1 * np.eye(1)


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ekf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
@pytest.mark.parametrize("Q", [0.01 * np.eye(1), np.eye(3)], ids=["1x1", "3x3"])
def test_process_noise_of_the_wrong_size_is_named(mod, Q):
    # a (1, 1) Q used to broadcast onto every entry of the (2, 2) covariance
    with pytest.raises(InputError, match=r"^Q: expected shape \(2, 2\)"):
        mod.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q, R1)
    if mod is sqrt_ukf:
        with pytest.raises(InputError, match=r"^Q: expected shape \(2, 2\)"):
            mod.predict(sqrt_ekf.SqrtGaussian(jnp.zeros(2), jnp.eye(2)), f, None, Q)


def test_noise_jacobian_and_q_must_agree():
    L = np.array([[0.0], [1.0]])
    ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, 0.01 * np.eye(1), R1, noise_jac=L)
    with pytest.raises(InputError, match=r"^Q: expected shape \(1, 1\) \(noise_jac's columns\)"):
        ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1, noise_jac=L)
    with pytest.raises(InputError, match=r"^noise_jac: expected shape \(2, q\)"):
        ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1, noise_jac=np.eye(3))


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ekf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
def test_measurement_model_and_z_must_agree(mod):
    # h returns 2 values, z and R have 1: used to broadcast R onto a (2, 2) S, status 0
    g = (sqrt_ekf.SqrtGaussian if mod in (sqrt_ekf, sqrt_ukf) else ekf.Gaussian)(jnp.zeros(2), jnp.eye(2))
    with pytest.raises(InputError, match=r"^h: the measurement model returned shape \(2,\)"):
        mod.filter_scan(f, lambda x: x, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1)
    with pytest.raises(InputError, match=r"^h: "):
        mod.update(g, jnp.zeros(1), lambda x: x, R1)
    with pytest.raises(InputError, match=r"^R: expected shape \(1, 1\)"):
        mod.update(g, jnp.zeros(1), h, np.eye(2))
    # a mask of another size used to broadcast the innovation onto it (S (2, 2), dof 1)
    with pytest.raises(InputError, match=r"^mask: expected shape \(1,\)"):
        mod.update(g, jnp.zeros(1), h, R1, mask=jnp.array([True, False]))
    with pytest.raises(InputError, match=r"^us: expected a leading axis of 12 steps"):
        mod.filter_scan(f, h, np.zeros(2), np.eye(2), np.zeros((11, 1)), ZS, None, Q2, R1)


def test_an_eager_prediction_checks_a_concrete_q():
    g = ekf.Gaussian(jnp.zeros(2), jnp.eye(2))
    with pytest.raises(InputError, match=r"^Q: "):
        ekf.predict(g, f, None, -np.eye(2))  # used to return an indefinite covariance, unflagged
    out = jax.jit(lambda Q: ekf.predict(g, f, None, Q))(0.01 * jnp.eye(2))  # traced: shapes only
    np.testing.assert_allclose(np.asarray(out.cov), F @ F.T + 0.01 * np.eye(2), rtol=1e-12)


@pytest.mark.parametrize("mod", [ekf, ukf], ids=["ekf", "ukf"])
def test_a_scalar_q_is_the_variance_of_one_state(mod):
    g = ekf.Gaussian(jnp.zeros(1), jnp.eye(1))
    a = mod.predict(g, lambda x, u: x, None, 0.1)
    b = mod.predict(g, lambda x, u: x, None, 0.1 * jnp.eye(1))
    np.testing.assert_allclose(np.asarray(a.cov), np.asarray(b.cov), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(a.cov), [[1.1]], rtol=1e-12)


def test_non_finite_start_mean_and_short_inputs_are_named():
    with pytest.raises(InputError, match=r"^x0: contains NaN or Inf"):
        ekf.filter_scan(f, h, np.array([np.nan, 0.0]), np.eye(2), None, ZS, None, Q2, R1)

    def fu(x, u):
        return f(x, None) + u

    with pytest.raises(InputError, match=r"^us: expected a leading axis of 12 steps"):
        ekf.filter_scan(fu, h, np.zeros(2), np.eye(2), np.zeros((11, 2)), ZS, None, Q2, R1)
    ekf.filter_scan(fu, h, np.zeros(2), np.eye(2), np.zeros((12, 2)), ZS, None, Q2, R1)


def test_square_root_filter_takes_a_scalar_variance_for_one_measurement():
    a = sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, 0.1)
    b = sqrt_ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1)
    np.testing.assert_array_equal(np.asarray(a.means), np.asarray(b.means))


# --------------------------------------------------------------------------- EKF-SLAM engine

def _model():
    # 1-D robot, 1-D landmarks, relative position measurement
    return es.SlamModel(1, 1, 1, lambda s, u, p=None: s + u, lambda s, l, p=None: l - s,
                        lambda s, z, p=None: s + z)


def _log(T=12, K=3, seed=1):
    rng = np.random.default_rng(seed)
    lm = np.array([2.0, 5.0, -3.0, 7.0])
    ids = np.stack([rng.permutation(4)[:K] for _ in range(T)])
    x = np.cumsum(np.full(T, 0.2))
    z = (lm[ids] - x[:, None])[..., None] + 0.05 * rng.normal(size=(T, K, 1))
    return es.SlamLog(u=np.full((T, 1), 0.2), z=z, ids=ids.astype(np.int32), mask=np.ones((T, K), bool),
                      params=None)


def test_init_checks_its_arguments_and_casts_an_integer_mean():
    with pytest.raises(InputError, match=r"^robot_cov: expected shape \(3, 3\)"):
        es.init(jnp.zeros(3), jnp.eye(2), 8, 2)
    with pytest.raises(InputError, match=r"^robot_cov: "):
        es.init(jnp.zeros(2), -jnp.eye(2), 8, 2)
    with pytest.raises(InputError, match=r"^robot_mean: contains NaN"):
        es.init(jnp.array([np.nan, 0.0]), jnp.eye(2), 8, 2)
    with pytest.raises(InputError, match=r"^capacity: expected an int >= 1"):
        es.init(jnp.zeros(2), jnp.eye(2), 0, 2)
    st = es.init(np.array([0, -3, 0]), np.eye(3), 4, 2)
    assert jnp.issubdtype(st.x.dtype, jnp.floating) and st.x.shape == (11,)


def test_run_checks_its_start_state_and_predict_its_q():
    m = _model()
    st = es.init(jnp.zeros(1), jnp.eye(1), 8, 1)
    bad = st._replace(P=st.P.at[0, 0].set(-1.0))
    with pytest.raises(InputError, match=r"^state.P \(robot block\)"):
        es.run(m, bad, _log(), 0.04 * jnp.eye(1), 0.01 * jnp.eye(1))
    with pytest.raises(InputError, match=r"^Q: expected shape \(1, 1\)"):
        es.predict(st, m, jnp.ones(1), 0.04 * jnp.eye(2))


def test_a_new_id_in_several_rows_of_one_step_registers_once():
    log = _log()
    ids = np.array(log.ids)
    ids[0] = [7, 7, 7]  # first sighting of landmark 7, three rows of one step
    z = np.array(log.z)
    z[0, :, 0] = [4.0, 4.05, 3.95]
    log = log._replace(ids=ids, z=z)
    st = es.init(jnp.zeros(1), 0.01 * jnp.eye(1), 8, 1)
    out = es.run(_model(), st, log, 0.04 * jnp.eye(1), 0.01 * jnp.eye(1))
    final_ids = np.asarray(out.final.ids)
    assert np.sum(final_ids == 7) == 1  # was three slots holding the same landmark
    assert int(out.n_new[0]) == 1
    # a non-finite first row of the id registers nothing and must not hide the good ones
    z[0, 0, 0] = np.nan
    out = es.run(_model(), st, log._replace(z=z), 0.04 * jnp.eye(1), 0.01 * jnp.eye(1))
    assert np.sum(np.asarray(out.final.ids) == 7) == 1 and int(out.n_new[0]) == 1


def test_fractional_landmark_ids_are_refused_on_the_rows_in_use():
    log = _log()
    st = es.init(jnp.zeros(1), 0.01 * jnp.eye(1), 8, 1)
    ids = np.asarray(log.ids, float)
    mask = np.array(log.mask)
    ids[2, 1], mask[2, 1] = np.nan, False  # a masked row's id may hold anything
    out = es.run(_model(), st, log._replace(ids=ids, mask=mask), 0.04 * jnp.eye(1), 0.01 * jnp.eye(1))
    assert np.all(np.isfinite(np.asarray(out.log_likelihood)))
    ids[3, 0] = 1.5
    with pytest.raises(InputError, match=r"^log.ids: expected whole-number"):
        es.run(_model(), st, log._replace(ids=ids, mask=mask), 0.04 * jnp.eye(1), 0.01 * jnp.eye(1))


def test_update_drops_rows_whose_slot_is_outside_the_map():
    m = _model()
    st = es.init(jnp.zeros(1), 0.01 * jnp.eye(1), 4, 1)
    st = es.preload(st, m, jnp.array([[2.0], [5.0]]), 0.1 * jnp.ones((2, 1, 1)))
    z = jnp.array([[2.1], [4.9]])
    R = 0.01 * jnp.eye(1)
    ref, ref_info = es.update(st, m, z[1:], jnp.array([1]), jnp.array([True]), R)
    for bad_slot in (-1, 99):
        post, info = es.update(st, m, z, jnp.array([bad_slot, 1]), jnp.array([True, True]), R)
        assert np.asarray(info.used).tolist() == [False, True]  # slot −1 used to update slot 0
        np.testing.assert_allclose(np.asarray(post.x), np.asarray(ref.x), rtol=0, atol=1e-12)
        assert "masked_input" in errors.decode(post.status)


def test_a_rejected_update_has_no_likelihood():
    log = _log(T=20)
    Rs = np.tile(0.01 * np.eye(1), (20, 1, 1))
    Rs[10] = -50.0  # S not PD at step 10 (traced, so the host check cannot see it)
    st = es.init(jnp.zeros(1), 0.01 * jnp.eye(1), 8, 1)
    run = jax.jit(lambda R: es.run(_model(), st, log, 0.04 * jnp.eye(1), R))
    ll = np.asarray(run(jnp.asarray(Rs)).log_likelihood)
    assert np.isnan(ll[10])  # was 0: a sum over the run hid the failure
    assert np.all(np.isfinite(np.delete(ll, 10)))
    good = np.asarray(run(jnp.asarray(np.tile(0.01 * np.eye(1), (20, 1, 1)))).log_likelihood)
    np.testing.assert_array_equal(ll[:10], good[:10])


def test_a_rejected_prediction_has_no_likelihood():
    # a NaN Q at step 10 (traced): the prediction keeps its prior and sets NON_FINITE in the
    # sticky state status; the step's log-likelihood must say so too (it used to be finite)
    log = _log(T=20)
    Qs = np.tile(0.04 * np.eye(1), (20, 1, 1))
    Qs[10] = np.nan
    st = es.init(jnp.zeros(1), 0.01 * jnp.eye(1), 8, 1)
    run = jax.jit(lambda Q: es.run(_model(), st, log, Q, 0.01 * jnp.eye(1)))
    out = run(jnp.asarray(Qs))
    ll = np.asarray(out.log_likelihood)
    assert np.isnan(ll[10]) and np.all(np.isfinite(np.delete(ll, 10)))
    assert int(out.final.status) & errors.NON_FINITE
    good = np.asarray(run(jnp.asarray(np.tile(0.04 * np.eye(1), (20, 1, 1)))).log_likelihood)
    np.testing.assert_array_equal(ll[:10], good[:10])


# --------------------------------------------------------------------------- Monte Carlo runner

def test_monte_carlo_checks_chunk_and_the_detail_entry():
    def fn(key):
        return {"x": jax.random.normal(key, ())}

    for bad in (0, -1, 2.5):
        with pytest.raises(InputError, match=r"^chunk: expected None or an int >= 1"):
            monte_carlo.run(fn, 0, 4, chunk=bad)
    with pytest.raises(InputError, match=r"^runs: expected an int >= 1"):
        monte_carlo.run(fn, 0, 0)
    with pytest.raises(InputError, match=r"^fn: with detail=True it must return a dict holding a 'detail'"):
        monte_carlo.run(fn, 0, 2, detail=True)


def test_eager_update_and_register_name_a_bad_r_and_jit_flags_it():
    m = _model()
    st = es.init(jnp.zeros(1), 0.01 * jnp.eye(1), 4, 1)
    st = es.preload(st, m, jnp.array([[2.0], [5.0]]), 0.1 * jnp.ones((2, 1, 1)))
    z, slots, on = jnp.array([[2.1], [4.9]]), jnp.array([0, 1]), jnp.array([True, True])
    for R, needle in ((-0.01 * jnp.eye(1), "R[0]: not positive semi-definite"),
                      (jnp.ones((3, 1, 1)), "R: expected shape (1, 1) or (2, 1, 1)"),
                      (jnp.array([[[0.01]], [[jnp.nan]]]), "R[1]")):
        with pytest.raises(InputError, match=needle.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
            es.update(st, m, z, slots, on, R)
        with pytest.raises(InputError, match=needle.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
            es.register(st, m, z, jnp.array([7, 8]), on, R)
    # R broadcast from (1, dz, dz) or, for dz = 1, a scalar; R = 0 (a noise-free row) is allowed
    for R in (0.01 * jnp.ones((1, 1, 1)), 0.01, jnp.zeros((1, 1))):
        es.update(st, m, z, slots, on, R)
    with pytest.raises(InputError, match=r"mask: expected shape \(2,\)"):
        es.update(st, m, z, slots, jnp.array([True, False, True]), 0.01 * jnp.eye(1))
    # a masked row's R is not read: NaN there is fine
    R = jnp.array([[[0.01]], [[jnp.nan]]])
    post, info = es.update(st, m, z, slots, jnp.array([True, False]), R)
    assert np.asarray(info.used).tolist() == [True, False] and np.all(np.isfinite(np.asarray(post.P)))
    # under jit R is not concrete: a non-PD R rejects the update and flags it
    post, info = jax.jit(lambda R: es.update(st, m, z, slots, on, R))(-0.5 * jnp.eye(1))
    assert "not_psd" in errors.decode(post.status)
    np.testing.assert_array_equal(np.asarray(post.x), np.asarray(st.x))


def _bad_q_run(mod, Q):
    """A jitted run whose (traced) Q is not finite: (status (T,), log-likelihood (T,) or None)."""
    run = jax.jit(lambda q: mod.filter_scan(f, h, jnp.zeros(2), jnp.eye(2), None, ZS, None, q, R1))
    post = run(jnp.asarray(Q))
    return np.asarray(post.status), (np.asarray(post.log_likelihood) if hasattr(post, "log_likelihood") else None)


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ekf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
def test_a_non_finite_traced_q_is_flagged_never_a_silent_answer(mod):
    """Q = diag(1e-3, inf) or a NaN entry under jit: every filter flags the run (NOT_PSD or
    NON_FINITE) and, where it reports one, the log-likelihood is NaN.  Before, the sigma-point
    filters froze the state with status 0 (a finite, wrong NLL), and the square-root filters
    read the NaN as 0."""
    bad = np.int32(errors.NOT_PSD | errors.NON_FINITE)
    for Q in (np.diag([1e-3, np.inf]), np.array([[np.nan, 0.0], [0.0, 1e-3]])):
        status, ll = _bad_q_run(mod, Q)
        assert np.all(status & bad), status
        if ll is not None:
            assert np.all(np.isnan(ll)), ll
    # one bad step of a per-step Q: that step says so, the steps before it are untouched
    Qs = np.tile(Q2, (12, 1, 1))
    Qs[7, 0, 0] = np.nan
    status, ll = _bad_q_run(mod, Qs)
    assert status[7] & bad and not np.any(status[:7])
    if ll is not None:
        assert np.isnan(ll[7]) and np.all(np.isfinite(ll[:7]))


def test_psd_factor_of_a_non_finite_matrix_is_nan_under_jit():
    A = jnp.array([[jnp.nan, 0.0], [0.0, 1e-3]])
    assert np.all(np.isnan(np.asarray(jax.jit(sqrt_ekf.psd_factor)(A))))
    assert np.all(np.isnan(np.asarray(sqrt_ekf.psd_factor(np.asarray(A)))))  # eager, as before
    # a finite singular PSD matrix still factors (the eigen branch)
    L = np.asarray(jax.jit(sqrt_ekf.psd_factor)(jnp.diag(jnp.array([1.0, 0.0]))))
    np.testing.assert_allclose(L @ L.T, np.diag([1.0, 0.0]), atol=1e-12)


@pytest.mark.parametrize("mod", [ukf, sqrt_ukf], ids=["ukf", "sqrt_ukf"])
def test_with_update_first_a_failed_predict_is_the_next_steps(mod):
    # predict_first=False: step t updates, then predicts the prior of step t + 1 with Q_t, so a
    # NaN in Q_7 belongs to step 8 (whose prior it failed to make), and the last step's
    # prediction, which no step uses, flags nothing
    Qs = np.tile(Q2, (12, 1, 1))
    Qs[7, 0, 0] = np.nan
    Qs[11, 0, 0] = np.nan
    post = jax.jit(lambda q: mod.filter_scan(f, h, jnp.zeros(2), jnp.eye(2), None, ZS, None, q, R1,
                                             predict_first=False))(jnp.asarray(Qs))
    status = np.asarray(post.status)
    assert status[8] & errors.NON_FINITE and not np.any(np.delete(status, 8)), status
    if hasattr(post, "log_likelihood"):
        ll = np.asarray(post.log_likelihood)
        assert np.isnan(ll[8]) and np.all(np.isfinite(np.delete(ll, 8)))


# ---------------------------------------------------------------------------
# One step called by hand (a user's own loop): the same rules as a whole run
# ---------------------------------------------------------------------------

X3, P3, Q3, R2 = np.zeros(3), np.eye(3), 0.1 * np.eye(3), 0.1 * np.eye(2)


def f3(x, u):
    return x + u


def h3(x):
    return x[:2]


@pytest.mark.parametrize("mod", [ekf, ukf], ids=["ekf", "ukf"])
def test_an_integer_mean_is_promoted_not_truncated(mod):
    # jnp.array([0, 0, 0]) is an easy slip: the step must compute in floating point, as the
    # float mean does (the UKF used to return [0, 0, 0] as int64 for x + 1)
    u = np.ones(3)
    good = mod.predict(ekf.Gaussian(jnp.asarray(X3), jnp.asarray(P3)), f3, u, Q3)
    got = mod.predict(ekf.Gaussian(jnp.array([0, 0, 0]), jnp.asarray(P3)), f3, u, Q3)
    assert jnp.issubdtype(got.mean.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(got.mean), [1.0, 1.0, 1.0], rtol=0, atol=1e-15)  # UKF: weighted sum
    np.testing.assert_allclose(np.asarray(got.cov), np.asarray(good.cov), rtol=0, atol=1e-15)
    post, info = mod.update(ekf.Gaussian(jnp.array([0, 0, 0]), jnp.asarray(P3)), np.array([0.5, -0.5]), h3, R2)
    ref, _ = mod.update(ekf.Gaussian(jnp.asarray(X3), jnp.asarray(P3)), np.array([0.5, -0.5]), h3, R2)
    assert int(info.status) == 0
    np.testing.assert_allclose(np.asarray(post.mean), np.asarray(ref.mean), rtol=0, atol=1e-15)


@pytest.mark.parametrize("mod", [ekf, ukf], ids=["ekf", "ukf"])
def test_one_step_names_a_bad_state_r_or_gate(mod):
    st = ekf.Gaussian(jnp.asarray(X3), jnp.asarray(P3))
    z = np.array([0.5, -0.5])
    with pytest.raises(InputError, match=r"^state\.cov: expected shape \(3, 3\) \(the mean's size\)"):
        mod.predict(ekf.Gaussian(jnp.asarray(X3), jnp.eye(2)), f3, np.ones(3), Q3)
    with pytest.raises(InputError, match=r"^state\.mean: expected shape \(n,\)"):
        mod.update(ekf.Gaussian(jnp.zeros((3, 1)), jnp.asarray(P3)), z, h3, R2)
    with pytest.raises(InputError, match=r"^state\.cov: not positive semi-definite"):
        mod.update(ekf.Gaussian(jnp.asarray(X3), -0.01 * jnp.asarray(P3)), z, h3, R2)
    with pytest.raises(InputError, match=r"^R: not positive definite"):
        mod.update(st, z, h3, -R2)  # used to be accepted: a posterior variance of -0.11
    with pytest.raises(InputError, match=r"^R: not symmetric"):
        mod.update(st, z, h3, np.array([[0.1, 0.5], [0.0, 0.1]]))
    for gate in (float("nan"), -1.0, 0.0):  # NaN used to switch gating off (x > nan is False)
        with pytest.raises(InputError, match=r"^gate: must be a positive"):
            mod.update(st, z, h3, R2, gate=gate)
    # inside jit the values are unknown: nothing is raised, the flags speak (as before)
    post, info = jax.jit(lambda P: mod.update(ekf.Gaussian(jnp.asarray(X3), P), z, h3, R2))(-jnp.eye(3))
    assert int(info.status) & (errors.NOT_PSD | errors.NON_FINITE) or not bool(info.accepted)


def test_a_float32_mean_keeps_its_dtype_with_a_float64_covariance():
    # x64 on: a float32 mean with a float64 covariance used to give a float64 mean from the
    # update and a float32 mean with a float64 covariance from the predict
    st = ekf.Gaussian(jnp.zeros(3, jnp.float32), jnp.eye(3, dtype=jnp.float64))
    for g in (ekf.predict(st, f3, np.ones(3), Q3), ekf.update(st, np.array([0.5, -0.5]), h3, R2)[0],
              ukf.predict(st, f3, np.ones(3), Q3), ukf.update(st, np.array([0.5, -0.5]), h3, R2)[0]):
        assert g.mean.dtype == jnp.float32 and g.cov.dtype == jnp.float32


def test_num_iter_must_be_a_whole_count():
    st = ekf.Gaussian(jnp.asarray(X3), jnp.asarray(P3))
    for bad in (0, 2.5, True):
        with pytest.raises(InputError, match=r"^num_iter: must be an int >= 1"):
            ekf.update(st, np.array([0.5, -0.5]), h3, R2, num_iter=bad)


def test_update_batch_names_each_argument():
    st = ekf.Gaussian(jnp.zeros(2), jnp.eye(2))
    lms = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 3.0]])  # M = 3

    def rng(x, lm):
        return jnp.reshape(jnp.linalg.norm(x - lm), (1,))

    zs = np.array([[1.0], [2.0], [4.2]])
    R = 0.01 * np.eye(1)
    post, info = ekf.update_batch(st, zs, rng, R, lms)  # well formed
    assert info.nis.shape == (3,)
    cases = [
        (dict(zs=zs[:, 0]), r"^zs: expected shape \(M, m\)"),
        (dict(R=0.01 * np.eye(2)), r"^R: expected shape \(1, 1\) \(shared\) or \(3, 1, 1\)"),
        (dict(R=np.stack([R, -R, R])), r"^R\[1\]: not positive definite"),
        (dict(masks=np.ones(2, bool)), r"^masks: expected shape \(3,\) or \(3, 1\)"),
        (dict(lms=lms[:2]), r"^args\[0\]: every per-measurement argument needs a leading axis of size M = 3"),
        (dict(h=lambda x, lm: jnp.stack([jnp.linalg.norm(x - lm)] * 2)),
         r"^h: the measurement model returned shape \(2,\), but each row of zs has \(1,\)"),
        (dict(gate=float("nan")), r"^gate: must be a positive"),
    ]
    for change, msg in cases:
        a = dict(zs=zs, R=R, lms=lms, masks=None, h=rng, gate=None)
        a.update(change)
        with pytest.raises(InputError, match=msg):
            ekf.update_batch(st, a["zs"], a["h"], a["R"], a["lms"], masks=a["masks"], gate=a["gate"])


def test_ukf_run_refuses_a_singular_p0_an_ekf_run_takes_it():
    # the sigma points factor P: a zero initial variance would fail every step (the means
    # frozen, the likelihood NaN); the EKF needs no factor of P and runs
    P0 = np.diag([1.0, 0.0])
    ekf.filter_scan(f, h, np.zeros(2), P0, None, ZS, None, Q2, R1)
    with pytest.raises(InputError, match=r"^P0: not positive definite \(smallest eigenvalue 0"):
        ukf.filter_scan(f, h, np.zeros(2), P0, None, ZS, None, Q2, R1)


def _model2():
    # 2-D robot, 2-D landmarks, relative position: d_z = 2
    return es.SlamModel(2, 2, 2, lambda s, u, p=None: s + u, lambda s, l, p=None: l - s,
                        lambda s, z, p=None: s + z)


def test_engine_step_names_rows_options_and_sizes():
    m = _model2()
    st = es.preload(es.init(jnp.zeros(2), 0.01 * jnp.eye(2), 4, 2), m, jnp.array([[2.0, 0.0], [0.0, 3.0]]),
                    0.1 * jnp.stack([jnp.eye(2)] * 2))
    z = jnp.array([[2.1, 0.1], [0.1, 2.9]])
    R = 0.01 * jnp.eye(2)
    slots, on = jnp.array([0, 1]), jnp.array([True, True])
    ref, ref_info = es.update(st, m, z, slots, on, R)
    # lists are arrays (they used to fail on .shape / .astype)
    post, _ = es.update(st, m, z.tolist(), [0, 1], [True, True], R)
    np.testing.assert_array_equal(np.asarray(post.x), np.asarray(ref.x))
    cases = [
        # one measurement given as (d_z,) with K = d_z: used to be read as two 1-D rows and give
        # a wrong landmark estimate with a clean status
        (dict(z=z[0]), r"^z: expected shape \(K, 2\)"),
        (dict(z=jnp.zeros((2, 3))), r"^z: expected shape \(K, 2\)"),
        (dict(z=jnp.zeros((0, 2)), slots=jnp.zeros(0, jnp.int32), mask=jnp.zeros(0, bool)), r"^z: expected shape \(K, 2\) \(K ≥ 1"),
        (dict(slots=jnp.array([0, 1, 2])), r"^slots: expected shape \(2,\)"),
        (dict(slots=jnp.array([0.0, 1.0])), r"^slots: expected integers"),
        (dict(mask=jnp.array([True])), r"^mask: expected shape \(2,\)"),
        (dict(num_iter=0), r"^num_iter: must be an int >= 1"),
        (dict(robust=-1.0), r"^robust: the Student-t degrees of freedom must be > 0"),
        (dict(gate=float("nan")), r"^gate: must be a positive"),
    ]
    for change, msg in cases:
        a = dict(z=z, slots=slots, mask=on, num_iter=1, robust=None, gate=None)
        a.update(change)
        with pytest.raises(InputError, match=msg):
            es.update(st, m, a["z"], a["slots"], a["mask"], R, num_iter=a["num_iter"], robust=a["robust"],
                      gate=a["gate"])
    with pytest.raises(InputError, match=r"^lm_ids: expected shape \(2,\)"):
        es.register(st, m, z, jnp.array([7]), on, R)
    with pytest.raises(InputError, match=r"^z: expected shape \(K, 2\)"):
        es.register(st, m, jnp.zeros((2, 1)), jnp.array([7, 8]), on, R)
    # a negative Q given as a value (it used to drive the robot variance to 0, status clean)
    with pytest.raises(InputError, match=r"^Q: not positive semi-definite"):
        es.predict(st, m, jnp.zeros(2), -0.04 * jnp.eye(2))


def test_engine_state_must_fit_the_model():
    m = _model2()
    wrong_lm = es.init(jnp.zeros(2), jnp.eye(2), 4, 3)  # lm_dim 3 for a model with lm_dim 2
    wrong_robot = es.init(jnp.zeros(3), jnp.eye(3), 4, 2)
    for st in (wrong_lm, wrong_robot):
        with pytest.raises(InputError, match=r"^state: x \(\d+,\) and P \(\d+, \d+\) do not fit the model"):
            es.predict(st, m, jnp.zeros(2), 0.01 * jnp.eye(2))
        with pytest.raises(InputError, match=r"^state: x .* do not fit the model"):
            es.register(st, m, jnp.ones((1, 2)), jnp.array([3]), jnp.array([True]), 0.01 * jnp.eye(2))
    with pytest.raises(InputError, match=r"^means: contains NaN or Inf"):
        es.preload(es.init(jnp.zeros(2), jnp.eye(2), 4, 2), m, jnp.array([[np.nan, 0.0]]))
    with pytest.raises(InputError, match=r"^means: expected shape \(N, 2\)"):
        es.preload(es.init(jnp.zeros(2), jnp.eye(2), 4, 2), m, jnp.array([1.0, 2.0]))


def test_smoothers_refuse_a_run_with_no_steps():
    from jaxslam.filters import smoother

    zs0 = np.zeros((0, 1))
    post = ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, zs0, None, Q2, R1, save_smoother=True)
    assert post.means.shape == (0, 2)  # the filter itself runs zero steps
    with pytest.raises(InputError, match=r"^post: the filter run has no steps"):
        smoother.rts(post)
    with pytest.raises(InputError, match=r"^zs: the run has no steps"):
        smoother.fixed_lag(ekf.make_filter(f, h), np.zeros(2), np.eye(2), None, zs0, None, Q2, R1, lag=2)
    with pytest.raises(InputError, match=r"^zs: the run has no steps"):
        smoother.iterated(f, h, np.zeros(2), np.eye(2), None, zs0, None, Q2, R1)


def test_monte_carlo_names_an_empty_device_list_and_a_float_seed():
    fn = lambda k: {"x": jax.random.normal(k)}  # noqa: E731
    with pytest.raises(InputError, match=r"^devices: an empty list"):
        monte_carlo.run(fn, 0, 2, devices=[])
    with pytest.raises(InputError, match=r"^seed: expected an int"):
        monte_carlo.run(fn, 1.5, 2)


# ---------------------------------------------------------------------------
# FastSLAM steps, JCBB, trilateration, the iterated smoother (a probe of single calls)
# ---------------------------------------------------------------------------

def _fs_setup():
    from jaxslam.filters import fastslam as fs
    from jaxslam.sensors import range_bearing2d as rb2

    model = fs.LandmarkModel(2, 2, rb2.observe, rb2.inverse, rb2.residual)
    p = fs.init(jnp.zeros(3), 5, 4, 2)
    z = jnp.stack([rb2.observe(jnp.zeros(3), l) for l in jnp.array([[3.0, 0.0], [0.0, 3.0]])])
    return fs, model, p, z, jnp.diag(jnp.array([0.01, 0.001]))


def test_fastslam_steps_check_r_ids_gate_and_counts():
    fs, model, p, z, R = _fs_setup()
    ids, mask = jnp.array([0, 1]), jnp.array([True, True])
    # a negative R registered landmarks with a negative covariance; fractional ids were
    # truncated onto other landmarks; a NaN gate switched gating off
    with pytest.raises(InputError, match="^R: "):
        fs.observe_update(p, model, z, ids, mask, -R)
    with pytest.raises(InputError, match="^lm_ids: expected whole-number"):
        fs.observe_update(p, model, z, jnp.array([0.2, 1.7]), mask, R)
    with pytest.raises(InputError, match="^gate: "):
        fs.observe_update(p, model, z, ids, mask, R, gate=float("nan"))
    cov = jnp.broadcast_to(0.01 * jnp.eye(3), (5, 3, 3))
    key = jax.random.PRNGKey(0)
    with pytest.raises(InputError, match="^R: "):
        fs.propose_optimal(p, model, z, ids, mask, -R, cov, key)
    with pytest.raises(InputError, match="^lm_ids: expected whole-number"):
        fs.propose_optimal(p, model, z, jnp.array([0.6, 1.4]), mask, R, cov, key)
    with pytest.raises(InputError, match=r"^mask: expected shape \(2,\)"):
        fs.propose_optimal(p, model, z, ids, jnp.array([True]), R, cov, key)
    # counts are ints: 2.7 particles used to make 2, True made 1
    for bad in ({"n_particles": 2.7}, {"n_particles": True}, {"capacity": 2.5}, {"lm_dim": 1.9}):
        kw = {"n_particles": 5, "capacity": 4, "lm_dim": 2, **bad}
        with pytest.raises(InputError, match=f"^{next(iter(bad))}: expected an int"):
            fs.init(jnp.zeros(3), **kw)
    assert fs.init(jnp.zeros(3), np.int64(5), jnp.asarray(4), 2).pose.shape == (5, 3)
    # the same call with good arguments still runs
    q, _ = fs.observe_update(p, model, z, ids, mask, R)
    assert bool(q.active[:, :2].all())


def test_fastslam_set_operations_check_their_arguments():
    fs, model, p, z, R = _fs_setup()
    p = p._replace(pose=p.pose.at[:, 2].set(jnp.array([3.1, -3.1, 3.0, -3.0, 3.1])))
    with pytest.raises(InputError, match="^angle_mask: expected 3 bools"):
        fs.estimate(p, angle_mask=[False, True])  # wrapped y, averaged the heading linearly
    with pytest.raises(InputError, match="^angle_mask: expected 3 bools"):
        fs.estimate_var(p, angle_mask=[2])  # an index list read as flags
    mu, _ = fs.estimate(p, angle_mask=[False, False, True])
    assert abs(abs(float(mu[2])) - np.pi) < 0.1  # the circular mean, near ±π
    with pytest.raises(InputError, match=r"^idx: ancestor indices must lie in \[0, 5\)"):
        fs.resample_indices(p, jnp.array([99, -7, 0, 0, 0]))  # gave NaN poses
    with pytest.raises(InputError, match=r"^idx: expected \(5,\) integer"):
        fs.resample_indices(p, jnp.array([0, 1]))  # a 2-particle pose with 5 weights
    with pytest.raises(InputError, match="^loglik: expected one log-likelihood per particle"):
        fs.reweight(p, jnp.array([3.0]))  # broadcast
    key = jax.random.PRNGKey(1)
    with pytest.raises(InputError, match=r"^threshold: expected a number in \[0, 1\]"):
        fs.maybe_resample(p, key, float("nan"))  # never resampled
    with pytest.raises(InputError, match=r"^alpha: expected a number in \[0, 1\]"):
        fs.resample_soft(p, key, 2.0)
    with pytest.raises(InputError, match="^std: expected finite σ >= 0"):
        fs.propagate_additive(p, key, lambda x, a: (x, a), jnp.array([-1.0, -1.0, -1.0]))
    with pytest.raises(InputError, match="^std: expected finite σ >= 0"):
        fs.propagate_additive(p, key, lambda x, a: (x, a), jnp.ones((3, 3)))  # not lower-triangular
    with pytest.raises(InputError, match=r"^mean_fn: must return a \(3,\) pose mean"):
        fs.propagate_additive(p, key, lambda x, a: (x[:2], a), jnp.ones(3))


def test_jcbb_uses_the_engines_checks():
    from jaxslam.filters import association as A
    from jaxslam.sensors import range_bearing2d as rb2

    model = es.SlamModel(3, 2, 2, lambda s, u, p: s, rb2.observe, rb2.inverse, rb2.residual)
    st = es.preload(es.init(jnp.zeros(3), 0.01 * jnp.eye(3), 4, 2), model,
                    jnp.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0]]), jnp.stack([0.01 * jnp.eye(2)] * 3))
    z = jnp.stack([rb2.observe(jnp.zeros(3), l) for l in jnp.array([[3.0, 0.0], [0.0, 3.0]])]) + jnp.array([0.05, 0.02])
    mask, R, thr = jnp.array([True, True]), 0.01 * jnp.eye(2), jnp.array([5.99, 9.49])
    good = A.jcbb(st, model, z, mask, R, gate=100.0, thresholds=thr)
    # a short thresholds was index-clamped (the one-pairing threshold reused for two)
    with pytest.raises(InputError, match=r"^thresholds: expected \(2,\)"):
        A.jcbb(st, model, z, mask, R, gate=100.0, thresholds=thr[:1])
    with pytest.raises(InputError, match=r"^z: expected shape \(K, 2\)"):
        A.jcbb(st, model, jnp.pad(z, ((0, 0), (0, 1))), mask, R, gate=100.0, thresholds=thr)  # (K, 3)
    with pytest.raises(InputError, match=r"^mask: expected shape \(2,\)"):
        A.jcbb(st, model, z, mask[:1], R, gate=100.0, thresholds=thr)
    with pytest.raises(InputError, match="^R: expected shape"):
        A.jcbb(st, model, z, mask, 0.01, gate=100.0, thresholds=thr)  # was the all-0.01 matrix
    with pytest.raises(InputError, match="^R"):
        A.jcbb(st, model, z, mask, -R, gate=100.0, thresholds=thr)
    with pytest.raises(InputError, match="^gate: "):
        A.jcbb(st, model, z, mask, R, gate=float("nan"), thresholds=thr)
    with pytest.raises(InputError, match="^n_cand: expected an int"):
        A.jcbb(st, model, z, mask, R, gate=100.0, thresholds=thr, n_cand=2.7)
    other = es.init(jnp.zeros(3), 0.01 * jnp.eye(3), 4, 3)  # lm_dim 3 for a lm_dim-2 model
    with pytest.raises(InputError, match="^state: x"):
        A.jcbb(other, model, z, mask, R, gate=100.0, thresholds=thr)
    assert int(good.n_paired) == 2


def test_trilateration_checks_variances_side_and_shapes():
    from jaxslam.filters import trilateration as T

    pts = jnp.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0]])
    r = jnp.linalg.norm(pts - jnp.array([1.0, 2.0]), axis=1)
    for bad in (-0.01, float("nan")):  # a negative σ² gave a negative covariance with ok
        with pytest.raises(InputError, match="^range_var: "):
            T.trilaterate(pts, r, range_var=bad)
    with pytest.raises(InputError, match=r"^ranges: expected shape \(4,\)"):
        T.trilaterate(pts, r[:1])
    with pytest.raises(InputError, match=r"^mask: expected shape \(4,\)"):
        T.trilaterate(pts, r, mask=jnp.array([True]))
    with pytest.raises(InputError, match=r"^ranges: expected shape \(2,\)"):
        T.trilaterate(pts.T, r)  # transposed points: K = 2, named by the pairing
    with pytest.raises(InputError, match=r"^points: expected shape \(K, d\)"):
        T.trilaterate(pts[:, 0], r)
    fix = T.trilaterate(pts, r, range_var=0.01)
    np.testing.assert_allclose(np.asarray(fix.position), [1.0, 2.0], atol=1e-5)
    xs = jnp.array([0.0, -1.0, -2.0, -3.0])
    rl = jnp.sqrt((xs + 1.0) ** 2 + 4.0)
    for bad in (5.0, 0.0, float("nan")):  # any side was accepted, with ok
        with pytest.raises(InputError, match=r"^side: expected \+1 or -1"):
            T.trilaterate_line(xs, rl, side=bad)
    np.testing.assert_allclose(np.asarray(T.trilaterate_line(xs, rl, side=1.0).position), [-1.0, 2.0], atol=1e-4)


def test_iterated_smoother_and_sqrt_update_check_their_options():
    from jaxslam.filters import smoother

    for kw, needle in (({"num_iter": 2.9}, "^num_iter: "), ({"num_iter": True}, "^num_iter: "),
                       ({"tol": float("nan")}, "^tol: "), ({"robust": 1.345}, "^robust: ")):
        with pytest.raises(InputError, match=needle):
            smoother.iterated(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1, **kw)
    g = sqrt_ekf.from_gaussian(ekf.Gaussian(jnp.zeros(2), jnp.eye(2)))
    with pytest.raises(InputError, match="^gate: "):
        sqrt_ekf.update(g, jnp.zeros(1), h, R1, gate=float("nan"))  # never gated
    with pytest.raises(InputError, match=r"^gate: expected one χ² threshold"):
        ekf.update(ekf.Gaussian(jnp.zeros(2), jnp.eye(2)), jnp.zeros(1), h, R1, gate=jnp.array([1.0, 2.0]))


# ---------------------------------------------------------------------------
# Sigma-point filters: the transition's size, a scalar R, the square-root state and options
# ---------------------------------------------------------------------------

def test_ukf_predict_names_a_transition_of_the_wrong_size():
    # f returned (1,) for a (2,) state: broadcast onto both components (mean [0, 0], status 0)
    g = ekf.Gaussian(jnp.zeros(2), jnp.eye(2))
    for mod, st in ((ukf, g), (sqrt_ukf, sqrt_ekf.SqrtGaussian(jnp.zeros(2), jnp.eye(2)))):
        with pytest.raises(InputError, match=r"^f: the transition returned shape \(1,\), expected \(2,\)"):
            mod.predict(st, lambda x, u: x[:1], None, Q2, return_status=True)
    with pytest.raises(InputError, match=r"^f: the transition returned shape \(\), expected \(2,\)"):
        ukf.predict_with_cross(g, lambda x, u: x[0], None, Q2)
    with pytest.raises(InputError, match=r"^f: "):  # shapes are static: the same under jit
        jax.jit(lambda m: ukf.predict(ekf.Gaussian(m, jnp.eye(2)), lambda x, u: x[:1], None, Q2))(jnp.zeros(2))
    with pytest.raises(InputError, match=r"^f: "):
        ukf.filter_scan(lambda x, u: x[:1], h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1)


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ukf"])
def test_a_scalar_r_of_one_measurement_must_be_positive(mod):
    # only a 2-D R had its values checked: R = -1 gave a mean of 4.5e15 with status 0 (the
    # sigma-point filters), the EKF took it without a word (the prior kept, flags set)
    g = (sqrt_ekf.SqrtGaussian if mod is sqrt_ukf else ekf.Gaussian)(jnp.zeros(2), jnp.eye(2))
    z = jnp.array([1.0])
    for R in (-1.0, 0.0, np.array([-1.0]), float("nan")):
        with pytest.raises(InputError, match=r"^R: "):
            mod.update(g, z, h, R)
    a, ia = mod.update(g, z, h, 0.5)
    b, ib = mod.update(g, z, h, 0.5 * jnp.eye(1))
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(a.mean), [2.0 / 3.0, 0.0], rtol=1e-12)  # P 1, R 0.5: K = 1/1.5
    assert int(ia.status) == 0 == int(ib.status)
    # traced R: not checked, the failed factorisation is flagged and the prior kept
    post, info = jax.jit(lambda r: mod.update(g, z, h, r))(jnp.asarray(-2.0))  # S = 1 - 2
    assert int(info.status) & errors.NOT_PSD and not bool(info.accepted)
    np.testing.assert_array_equal(np.asarray(post.mean), [0.0, 0.0])


@pytest.mark.parametrize("mod", [sqrt_ekf, sqrt_ukf], ids=["sqrt_ekf", "sqrt_ukf"])
def test_square_root_filters_check_their_state_like_the_covariance_form(mod):
    # sqrt_ekf read any (mean, chol): an upper-triangular entry was dropped without a word, an
    # integer mean made an integer step
    S = sqrt_ekf.SqrtGaussian
    z = jnp.array([1.0])
    for st, needle in ((S(jnp.zeros(2), jnp.eye(3)), r"^state\.chol: expected shape \(2, 2\) \(the mean's size\)"),
                       (S(jnp.zeros((2, 1)), jnp.eye(2)), r"^state\.mean: expected shape \(n,\)"),
                       (S(jnp.zeros(2), jnp.full((2, 2), jnp.nan)), r"^state\.chol: contains NaN"),
                       (S(jnp.zeros(2), jnp.array([[1.0, 0.5], [0.0, 1.0]])), r"^state\.chol: expected a lower-triangular"),
                       (S(jnp.zeros(2), -jnp.eye(2)), r"^state\.chol: expected a factor with a non-negative diagonal")):
        with pytest.raises(InputError, match=needle):
            mod.predict(st, f, None, Q2)
        with pytest.raises(InputError, match=needle):
            mod.update(st, z, h, R1)
    # an integer mean is promoted, as the covariance form's: the same step as the float mean
    good = mod.update(S(jnp.zeros(2), jnp.eye(2)), z, h, R1)[0]
    got = mod.update(S(jnp.array([0, 0]), jnp.eye(2)), z, h, R1)[0]
    assert jnp.issubdtype(got.mean.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(got.mean), np.asarray(good.mean), rtol=0, atol=1e-15)
    # traced: shapes only (values unknown), the same step as eager
    jitted = jax.jit(lambda L: mod.update(S(jnp.zeros(2), L), z, h, R1)[0])(jnp.eye(2))
    np.testing.assert_allclose(np.asarray(jitted.mean), np.asarray(good.mean), rtol=1e-12, atol=1e-15)


def test_sqrt_ukf_matches_ukf_from_a_cholesky_factor():
    S = sqrt_ekf.SqrtGaussian
    z = jnp.array([1.0])
    # a lower-triangular factor from Cholesky passes and matches the UKF
    P = np.array([[2.0, 0.3], [0.3, 1.0]])
    a = sqrt_ukf.update(S(jnp.zeros(2), jnp.linalg.cholesky(jnp.asarray(P))), z, h, R1)[0]
    b = ukf.update(ekf.Gaussian(jnp.zeros(2), jnp.asarray(P)), z, h, R1)[0]
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), rtol=1e-12)


def test_sqrt_ukf_names_a_bad_q_r_gate_or_rule():
    st = sqrt_ekf.SqrtGaussian(jnp.zeros(2), jnp.eye(2))
    z = jnp.array([1.0])
    # these used to set a status only (NOT_PSD / NON_FINITE), where ukf raises
    with pytest.raises(InputError, match=r"^Q: not positive semi-definite"):
        sqrt_ukf.predict(st, f, None, -np.eye(2), return_status=True)
    with pytest.raises(InputError, match=r"^Q: contains NaN"):
        sqrt_ukf.predict(st, f, None, np.full((2, 2), np.nan), return_status=True)
    with pytest.raises(InputError, match=r"^Q_chol: contains NaN"):
        sqrt_ukf.predict(st, f, None, None, Q_chol=np.full((2, 1), np.nan))
    with pytest.raises(InputError, match=r"^R: not positive definite"):
        sqrt_ukf.update(st, z, h, -R1)
    with pytest.raises(InputError, match=r"^R: contains NaN"):
        sqrt_ukf.update(st, z, h, np.full((1, 1), np.nan))
    for gate in (-1.0, float("nan"), 0.0):  # -1 gated every update, NaN switched gating off
        with pytest.raises(InputError, match=r"^gate: must be a positive"):
            sqrt_ukf.update(st, z, h, R1, gate=gate)
        with pytest.raises(InputError, match=r"^gate: must be a positive"):
            sqrt_ukf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1, gate=gate)
    for call in (lambda: sqrt_ukf.update(st, z, h, R1, points="x"),
                 lambda: sqrt_ukf.predict(st, f, None, Q2, points="x"),
                 lambda: sqrt_ukf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, None, Q2, R1, points="x")):
        with pytest.raises(InputError, match=r"^points: expected a SigmaPoints rule"):
            call()
    # traced Q: shapes only; the non-finite prediction keeps the prior and says so
    out, status = jax.jit(lambda q: sqrt_ukf.predict(st, f, None, q, return_status=True))(jnp.full((2, 2), jnp.nan))
    assert int(status) & errors.NON_FINITE
    np.testing.assert_array_equal(np.asarray(out.chol), np.eye(2))
    # a finite gate still gates
    _, info = sqrt_ukf.update(st, jnp.array([10.0]), h, R1, gate=3.84)
    assert int(info.status) & errors.GATED


def test_sigma_points_check_and_promote_their_moments():
    with pytest.raises(InputError, match=r"^cov: expected shape \(2, 2\) \(the mean's size\), got \(3, 3\)"):
        ukf.sigma_points(jnp.zeros(2), jnp.eye(3))
    with pytest.raises(InputError, match=r"^mean: expected shape \(n,\), got \(\)"):
        ukf.sigma_points(0.0, jnp.eye(2))
    with pytest.raises(InputError, match=r"^mean: expected shape \(n,\), got \(2, 1\)"):
        ukf.sigma_points(jnp.zeros((2, 1)), jnp.eye(2))
    # an integer mean made integer weights: wm [0 0 0 0 0] (every weight truncated)
    got = ukf.sigma_points(jnp.array([0, 1]), 4.0 * jnp.eye(2))
    ref = ukf.sigma_points(jnp.array([0.0, 1.0]), 4.0 * jnp.eye(2))
    assert jnp.issubdtype(got.wm.dtype, jnp.floating) and jnp.issubdtype(got.points.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(got.wm), [0.0, 0.25, 0.25, 0.25, 0.25], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(got.wc), [2.0, 0.25, 0.25, 0.25, 0.25], rtol=0, atol=1e-15)
    s2 = 2.0 * np.sqrt(2.0)  # c = √n, L = 2 I
    np.testing.assert_allclose(np.asarray(got.points),
                               [[0, 1], [s2, 1], [0, 1 + s2], [-s2, 1], [0, 1 - s2]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(got.points), np.asarray(ref.points))
    # a float32 mean keeps its dtype (the cov follows it)
    assert ukf.sigma_points(jnp.zeros(2, jnp.float32), jnp.eye(2)).wm.dtype == jnp.float32
    with pytest.raises(InputError, match=r"^alpha: expected numbers"):
        ukf.unscented(alpha="1")


# ---------------------------------------------------------------------------
# Consistency monitor, association and delayed initialisation
# ---------------------------------------------------------------------------

def _slam2():
    m = _model2()
    st = es.preload(es.init(jnp.zeros(2), 0.1 * jnp.eye(2), 3, 2), m, jnp.array([[1.0, 0.0], [0.0, 1.0]]),
                    jnp.stack([0.1 * jnp.eye(2)] * 2), ids=jnp.array([0, 1]))
    return m, st


def test_inflate_robot_takes_a_finite_factor_of_at_least_one():
    from jaxslam.filters import consistency as C

    m, st = _slam2()
    for bad in (-1.0, 0.0, 0.5, float("nan"), float("inf")):  # -1: P all NaN; 0: robot block zeroed
        with pytest.raises(InputError, match="^factor: expected a finite inflation factor >= 1"):
            C.inflate_robot(st, m, bad)
    with pytest.raises(InputError, match=r"^factor: expected a scalar, got shape \(2,\)"):
        C.inflate_robot(st, m, jnp.ones(2))
    P = np.asarray(st.P)
    np.testing.assert_array_equal(np.asarray(C.inflate_robot(st, m, 1.0).P), P)
    P4 = np.asarray(C.inflate_robot(st, m, 4.0).P)
    D = np.diag([2.0, 2.0] + [1.0] * 6)  # √4 on the robot rows
    np.testing.assert_allclose(P4, D @ P @ D, rtol=1e-15)
    # traced (inside observe's cond): not checked
    jax.jit(lambda fct: C.inflate_robot(st, m, fct).P)(2.0)


def test_monitor_checks_its_params_rows_and_dtype():
    from jaxslam.filters import consistency as C

    m, st = _slam2()
    mon = C.init(jnp.float64)
    ok = C.MonitorParams(alpha=0.1, threshold=1.5, max_factor=4.0, outlier_gate=9.21)
    d2, v = jnp.array([100.0, 100.0]), jnp.array([True, True])
    for field, bad in (("alpha", -1.0), ("alpha", 2.0), ("alpha", 0.0), ("threshold", float("nan")),
                       ("max_factor", 0.5), ("outlier_gate", -1.0), ("outlier_gate", float("nan"))):
        with pytest.raises(InputError, match=rf"^params\.{field}: must be"):
            C.observe(mon, st, m, d2, v, ok._replace(**{field: bad}))
    with pytest.raises(InputError, match=r"^valid: expected shape \(3,\)"):
        C.observe(mon, st, m, jnp.ones(3), v, ok)
    with pytest.raises(InputError, match="^d2: NaN on a valid row"):
        C.observe(mon, st, m, jnp.array([jnp.nan, 1.0]), v, ok)
    C.observe(mon, st, m, jnp.array([jnp.nan, 1.0]), jnp.array([False, True]), ok)  # an invalid row may hold it
    mon2, st2 = C.observe(mon, st, m, d2, v, ok)  # r = 200 / 4 = 50, m = 0.9 + 5 = 5.9 > 1.5: f = 4
    assert int(mon2.inflations) == 1 and float(mon2.mean) == 1.0
    np.testing.assert_allclose(np.asarray(st2.P)[:2, :2], 4.0 * np.asarray(st.P)[:2, :2], rtol=1e-15)
    for bad in ("abc", jnp.int32):  # an integer running mean truncated the ratio
        with pytest.raises(InputError, match="^dtype: expected a floating dtype"):
            C.init(bad)


def test_outlier_counts_and_status_bits_check_their_inputs():
    from jaxslam.filters import consistency as C

    p = C.MonitorParams(alpha=0.1, threshold=1.5, max_factor=4.0, outlier_gate=9.21)
    v = jnp.array([True, True, False])
    assert int(C.outliers([1.0, 20.0, 30.0], v, p)) == 1 == int(C.outliers(jnp.array([1.0, 20.0, 30.0]), v, p))
    with pytest.raises(InputError, match=r"^valid: expected shape \(2,\) \(one per row of d2\)"):
        C.outliers(jnp.ones(2), v, p)
    with pytest.raises(InputError, match=r"^d2: expected shape \(K,\)"):
        C.outliers(jnp.ones((3, 1)), v, p)
    for bad in (-0.1, 1.5, float("nan")):  # -0.1: DIVERGED with no outlier at all
        with pytest.raises(InputError, match=r"^fraction: expected an outlier fraction in \[0, 1\]"):
            C.status_bits(0, 10, bad)
    assert int(C.status_bits(0, 10)) == 0 and int(C.status_bits(1, 10)) == 0
    assert int(C.status_bits(2, 10)) == errors.DIVERGED
    assert int(jax.jit(C.status_bits)(2, 10, 0.5)) == 0  # traced fraction: not checked


def test_jcbb_thresholds_and_individual_compatibility_are_checked():
    from jaxslam.filters import association as A

    m, st = _slam2()
    z, mask, R = jnp.array([[1.0, 0.0], [0.0, 1.0]]), jnp.array([True, True]), 0.01 * jnp.eye(2)
    thr = jnp.array([9.21, 13.28])
    good = A.jcbb(st, m, z, mask, R, gate=9.21, thresholds=thr)
    assert np.asarray(good.slots).tolist() == [0, 1]
    for bad in (jnp.array([jnp.nan, jnp.nan]), -thr, jnp.array([9.21, 0.0])):  # paired nothing, silently
        with pytest.raises(InputError, match=r"^thresholds: expected positive joint χ² thresholds"):
            A.jcbb(st, m, z, mask, R, gate=9.21, thresholds=bad)
    d2, _ = A.individual_compatibility(st, m, z, mask, R)
    assert d2.shape == (2, 3) and np.isinf(np.asarray(d2)[:, 2]).all()  # slot 2 unmapped
    for args, needle in (((z, mask, -R), r"^R\[0\]: not positive semi-definite"),
                         ((z, mask, jnp.eye(3)), r"^R: expected shape \(2, 2\)"),
                         ((jnp.ones(2), mask, R), r"^z: expected shape \(K, 2\)"),
                         ((z, jnp.array([True, True, True]), R), r"^mask: expected shape \(2,\)")):
        with pytest.raises(InputError, match=needle):
            A.individual_compatibility(st, m, *args)
    other = es.init(jnp.zeros(2), 0.01 * jnp.eye(2), 3, 3)  # lm_dim 3 for a lm_dim-2 model
    with pytest.raises(InputError, match="^state: x"):
        A.individual_compatibility(other, m, z, mask, R)


def test_delayed_init_checks_variances_shapes_and_takes_lists():
    from jaxslam.filters import delayed_init as D

    pts = jnp.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0]])
    rng = jnp.linalg.norm(pts - jnp.array([1.0, 2.0]), axis=1)
    val, pv = jnp.ones(4, bool), 0.01 * jnp.ones(4)
    fit, P = D.from_buffer(pts, pv, rng, val, 0.01)
    for bad in (-pv, pv.at[1].set(jnp.nan)):  # a negative variance shrank P_ll
        with pytest.raises(InputError, match=r"^point_var: expected finite variances >= 0"):
            D.from_buffer(pts, bad, rng, val, 0.01)
    # a row that is not averaged may hold anything
    D.from_buffer(pts, pv.at[3].set(-1.0), rng, val, 0.01, var_rows=jnp.array([True, True, True, False]))
    with pytest.raises(InputError, match=r"^point_var: expected shape \(4,\)"):
        D.from_buffer(pts, jnp.ones(3), rng, val, 0.01)
    with pytest.raises(InputError, match=r"^var_rows: expected shape \(4,\)"):
        D.from_buffer(pts, pv, rng, val, 0.01, var_rows=jnp.ones(3, bool))
    with pytest.raises(InputError, match=r"^points: expected numbers"):
        D.from_buffer("abc", pv, rng, val, 0.01)
    # lists and a 0/1 integer mask are read as arrays (they gave "Cannot determine dtype" / a
    # dtype error); a float mask is refused since 2026-12-06, as every mask of the library is
    _, P2 = D.from_buffer(pts.tolist(), pv.tolist(), rng, val, 0.01)
    np.testing.assert_array_equal(np.asarray(P2), np.asarray(P))
    np.testing.assert_allclose(np.asarray(fit.position), [1.0, 2.0], atol=1e-9)
    with pytest.raises(InputError, match=r"^valid: expected a bool mask \(or 0/1 integers\), got dtype float"):
        D.robust_trilaterate(pts, rng, jnp.ones(4), 0.01)
    a = D.robust_trilaterate(pts, rng, jnp.ones(4, jnp.int32), 0.01)
    b = D.robust_trilaterate(pts, rng, val, 0.01)
    np.testing.assert_array_equal(np.asarray(a.position), np.asarray(b.position))
    # a scalar point variance is every row's
    np.testing.assert_allclose(np.asarray(D.from_buffer(pts, 0.01, rng, val, 0.01)[1]), np.asarray(P), rtol=1e-15)
    # traced variances: shapes only
    jax.jit(lambda v: D.from_buffer(pts, v, rng, val, 0.01)[1])(-pv)


@pytest.mark.parametrize("bad", [np.nan, np.inf], ids=["nan", "inf"])
def test_a_non_finite_concrete_z_gives_the_ukf_the_ekf_answer(bad):
    """A concrete z with a NaN/Inf: the EKF raises nothing, returns the prior and sets NON_FINITE;
    the (square-root) UKF does the same (checked, not changed), and a mask on that entry uses the rest."""
    z, R, P0 = np.array([1.0, bad]), np.eye(2), np.eye(2)

    def hh(x):
        return x

    ref_post, ref = ekf.update(ekf.Gaussian(jnp.zeros(2), jnp.asarray(P0)), z, hh, R)
    assert int(ref.status) == errors.NON_FINITE and not bool(ref.accepted)
    np.testing.assert_array_equal(np.asarray(ref_post.mean), np.zeros(2))
    for post, info in (ukf.update(ekf.Gaussian(jnp.zeros(2), jnp.asarray(P0)), z, hh, R),
                       sqrt_ukf.update(sqrt_ekf.SqrtGaussian(jnp.zeros(2), jnp.asarray(P0)), z, hh, R)):
        assert int(info.status) == int(ref.status) and bool(info.accepted) == bool(ref.accepted)
        np.testing.assert_array_equal(np.asarray(post.mean), np.zeros(2))
    m = np.array([True, False])
    a = ekf.update(ekf.Gaussian(jnp.zeros(2), jnp.asarray(P0)), z, hh, R, mask=m)[0]
    b = ukf.update(ekf.Gaussian(jnp.zeros(2), jnp.asarray(P0)), z, hh, R, mask=m)[0]
    np.testing.assert_allclose(np.asarray(b.mean), np.asarray(a.mean), rtol=1e-6, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(b.cov)))


def _runners():
    from jaxslam.filters import gaussian, smoother
    return {
        "ekf": ekf.filter_scan, "ukf": ukf.filter_scan, "sqrt_ekf": sqrt_ekf.filter_scan,
        "sqrt_ukf": sqrt_ukf.filter_scan,
        "gaussian.run": lambda f_, h_, *a: gaussian.run(ekf.make_filter(f_, h_), *a),
        "fixed_lag": lambda f_, h_, *a: smoother.fixed_lag(ekf.make_filter(f_, h_), *a, lag=2),
        "iterated": lambda f_, h_, *a: smoother.iterated(f_, h_, *a, num_iter=2),
    }


_RUNS = ["ekf", "ukf", "sqrt_ekf", "sqrt_ukf", "gaussian.run", "fixed_lag", "iterated"]


def test_update_batch_joint_takes_an_h_without_per_measurement_args():
    # the joint mode vmapped h over its (empty) per-measurement args: a bare JAX ValueError
    st = ekf.Gaussian(jnp.zeros(2), jnp.eye(2))
    zs = np.array([[0.1], [0.2]])
    seq, info_s = ekf.update_batch(st, zs, h, R1, sequential=True)
    joint, info_j = ekf.update_batch(st, zs, h, R1)
    np.testing.assert_allclose(np.asarray(joint.mean), np.asarray(seq.mean), atol=1e-12)
    np.testing.assert_allclose(np.asarray(joint.cov), np.asarray(seq.cov), atol=1e-12)
    # by hand: two scalar updates of a unit prior with variance 0.1 -> mean 0.3/2.1
    np.testing.assert_allclose(float(joint.mean[0]), 0.3 / 2.1, rtol=1e-12)
    assert np.asarray(info_j.status).tolist() == [0, 0]


@pytest.mark.parametrize("run", _RUNS)
@pytest.mark.parametrize("bad", ["int2", "float05"])
def test_run_masks_must_be_bool_or_0_1(run, bad):
    # a 2 or a 0.5 in a mask was read as True, status 0
    m = np.ones(ZS.shape, int)
    m[3, 0] = 0
    masks = m.copy() if bad == "int2" else m.astype(float)
    masks[0, 0] = 2 if bad == "int2" else 0.5
    with pytest.raises(InputError, match=r"^masks: expected a bool mask \(or 0/1 integers\)"):
        _runners()[run](f, h, np.zeros(2), np.eye(2), None, ZS, masks, Q2, R1)


def test_run_takes_0_1_integer_masks_as_bool():
    m = np.ones(ZS.shape, int)
    m[3, 0] = 0
    a = ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, m, Q2, R1)
    b = ekf.filter_scan(f, h, np.zeros(2), np.eye(2), None, ZS, m.astype(bool), Q2, R1)
    np.testing.assert_array_equal(np.asarray(a.means), np.asarray(b.means))
    assert int(a.nis[3]) == 0 and int(b.nis[3]) == 0


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ekf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
def test_update_mask_must_be_bool_or_0_1(mod):
    g = (sqrt_ekf.SqrtGaussian if mod in (sqrt_ekf, sqrt_ukf) else ekf.Gaussian)(jnp.zeros(2), jnp.eye(2))
    for bad in (np.array([2, 0]), np.array([0.5, 1.0])):
        with pytest.raises(InputError, match=r"^mask: expected a bool mask \(or 0/1 integers\)"):
            mod.update(g, np.zeros(2), lambda x: x, 0.1 * np.eye(2), mask=bad)
    if mod is ekf:
        for bad in (np.array([2, 0]), np.array([[1, 0], [0.5, 1]])):
            with pytest.raises(InputError, match=r"^masks: expected a bool mask \(or 0/1 integers\)"):
                ekf.update_batch(g, np.zeros((2, 1)), h, R1, masks=bad)


@pytest.mark.parametrize("run", _RUNS)
def test_per_step_r_of_the_wrong_length_with_masks_is_named(run):
    # the PSD check of a per-step R on the masks' rows ran before its length check: a bare
    # NumPy broadcast error
    T = ZS.shape[0]
    R = np.stack([R1] * (T + 1))
    masks = np.ones(ZS.shape, bool)
    # (check_run_inputs names it, before any run casts R: the one message of all runs)
    msg = rf"^R: expected shape \(1, 1\) or \({T}, 1, 1\), got \({T + 1}, 1, 1\)$"
    with pytest.raises(InputError, match=msg):
        _runners()[run](f, h, np.zeros(2), np.eye(2), None, ZS, masks, Q2, R)


@pytest.mark.parametrize("run", _RUNS)
def test_run_refuses_complex_measurements(run):
    # cast to real with only a ComplexWarning, status 0
    with pytest.raises(InputError, match=r"^zs: expected a real array"):
        _runners()[run](f, h, np.zeros(2), np.eye(2), None, ZS + 1j, None, Q2, R1)
    # a complex start was cast to real before any check (ekf.filter_scan gave a ComplexWarning)
    with pytest.raises(InputError, match=r"^x0: "):
        _runners()[run](f, h, np.zeros(2) + 1j, np.eye(2), None, ZS, None, Q2, R1)


@pytest.mark.parametrize("mod", [ekf, ukf, sqrt_ekf, sqrt_ukf], ids=["ekf", "ukf", "sqrt_ekf", "sqrt_ukf"])
def test_update_refuses_a_complex_measurement(mod):
    g = (sqrt_ekf.SqrtGaussian if mod in (sqrt_ekf, sqrt_ukf) else ekf.Gaussian)(jnp.zeros(2), jnp.eye(2))
    with pytest.raises(InputError, match=r"^z: expected a real array"):
        mod.update(g, np.zeros(1) + 1j, h, R1)
    if mod is ekf:
        with pytest.raises(InputError, match=r"^zs: expected a real array"):
            ekf.update_batch(g, np.zeros((2, 1)) + 1j, h, R1)


def test_sqrt_ekf_checks_a_concrete_q_and_r_like_sqrt_ukf():
    # sqrt_ekf.predict gave a NaN factor for Q = -0.01 I; update kept the prior with NOT_PSD
    st = sqrt_ekf.SqrtGaussian(jnp.zeros(2), jnp.eye(2))
    R_bad = np.array([[0.05, 0.1], [0.1, 0.05]])
    for mod in (sqrt_ekf, sqrt_ukf):
        with pytest.raises(InputError, match=r"^Q: not positive semi-definite"):
            mod.predict(st, f, None, -0.01 * np.eye(2))
        with pytest.raises(InputError, match=r"^R: not positive definite"):
            mod.update(st, np.zeros(2), lambda x: x, R_bad)
    # a PSD (singular) Q is still taken
    out = sqrt_ekf.predict(st, f, None, np.diag([0.0, 0.01]))
    assert np.all(np.isfinite(np.asarray(out.chol)))


def test_ekf_update_under_jit_flags_an_indefinite_prior():
    # eagerly an InputError; traced, S = H P H^T + R still factored and the posterior kept a
    # negative variance with status 0
    P = jnp.array([[1.0, 0.0], [0.0, -0.5]])
    upd = jax.jit(lambda m, P, z: ekf.update(ekf.Gaussian(m, P), z, lambda x: x, jnp.eye(2)))
    post, info = upd(jnp.zeros(2), P, jnp.ones(2))
    assert int(info.status) & errors.NOT_PSD and not bool(info.accepted)
    np.testing.assert_array_equal(post.cov, P)  # the prior, unchanged
    # a PSD prior with a zero variance still updates (rounding is not a negative variance)
    post, info = upd(jnp.zeros(2), jnp.diag(jnp.array([1.0, 0.0])), jnp.ones(2))
    assert int(info.status) == 0 and bool(info.accepted)


def test_soft_resampling_refuses_a_mixture_weight_outside_0_1():
    from jaxslam.filters import resampling

    key, lw = jax.random.PRNGKey(0), jnp.log(jnp.array([0.1, 0.2, 0.3, 0.4]))
    for a in (2.0, -0.1, np.nan):
        with pytest.raises(InputError, match=r"^alpha: "):
            resampling.soft(key, lw, a)
    with pytest.raises(InputError, match=r"^alpha: "):
        resampling.soft(key, lw, np.array([0.5, 0.5]))
    # traced: used as if clipped to [0, 1]
    soft = jax.jit(resampling.soft)
    for a_out, a_in in ((2.0, 1.0), (-1.0, 0.0)):
        for got, want in zip(soft(key, lw, a_out), resampling.soft(key, lw, a_in)):
            np.testing.assert_allclose(got, want, rtol=1e-12)


def test_a_float32_sigma_point_update_rounding_below_zero_is_still_accepted():
    # A precise R (down to 1e-10) and an ill-conditioned S round a float32 UKF posterior variance a
    # little below zero.  The first form of the negative-variance check (64 eps x scale) rejected
    # such updates (14 in 300 random cases of this kind) and made the step's likelihood NaN; the
    # check is for an indefinite prior (negative variances of the prior's order): tolerance
    # sqrt(eps) x scale.  Which cases round below zero depends on the CPU's float32 code (case 21
    # did on one machine and not on an AVX-512 one), so the whole stream of 300 runs in one
    # vmapped program and every case that rounds below zero is checked (83 on the AVX-512 machine).
    from jaxslam.filters import ukf

    n = 5
    rng = np.random.default_rng(1)
    cases = []
    for _ in range(300):  # a review's random stream (not chosen by hand)
        spread = rng.uniform(0, 3)
        Qm, _ = np.linalg.qr(rng.standard_normal((n, n)))
        ev = 10 ** rng.uniform(-spread, spread, n)
        P = (0.5 * ((Qm * ev) @ Qm.T + ((Qm * ev) @ Qm.T).T)).astype(np.float32)
        x = rng.standard_normal(n).astype(np.float32)
        H = rng.standard_normal((n, n)).astype(np.float32)
        R = (np.eye(n) * 10 ** rng.uniform(-10, 0)).astype(np.float32)
        z = (H @ x + 0.01).astype(np.float32)
        cases.append((x, P, z, H, R))
    X, P, Z, H, R = (np.stack(c) for c in zip(*cases))
    upd = jax.jit(jax.vmap(lambda x, P, z, H, R: ukf.update(ukf.Gaussian(x, P), z, lambda v: H @ v, R)))
    post, info = upd(X, P, Z, H, R)
    low = np.diagonal(np.asarray(post.cov), axis1=1, axis2=2).min(axis=1)
    below = low < 0
    assert below.any()  # the stream does round below zero
    assert np.all(np.asarray(info.status)[below] == 0) and np.all(np.asarray(info.accepted)[below])
    scale = np.abs(np.diagonal(P, axis1=1, axis2=2)).max(axis=1)
    assert np.all(low[below] > -np.sqrt(np.finfo(np.float32).eps) * scale[below])
    # The tolerance itself, independent of the CPU: a float32 posterior variance 1e-4 x the prior's
    # largest below zero (the size met on the first machine) is accepted; one of the prior's order
    # (an indefinite prior) is NOT_PSD.
    from jaxslam.filters import gaussian

    prior = gaussian.Gaussian(jnp.zeros(2, jnp.float32), jnp.diag(jnp.asarray([5.8, 1.0], jnp.float32)))
    for v, want in ((-1e-4 * 5.8, 0), (-0.5, errors.NOT_PSD)):
        _, acc, st = gaussian.finalize(prior, jnp.ones(2, jnp.float32), jnp.diag(jnp.asarray([1.0, v], jnp.float32)),
                                       jnp.asarray(True), jnp.asarray(False), jnp.asarray(2))
        assert int(st) == want and bool(acc) == (want == 0), v
