"""Defects a review of the generic Gaussian filters found (ekf, ukf, sqrt_ekf, sqrt_ukf,
gaussian.run): each is now a clear InputError naming the argument, or a status flag under jit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, gaussian as g, sqrt_ekf as se, sqrt_ukf as su, ukf

jax.config.update("jax_enable_x64", True)

G = ekf.Gaussian


def _s():
    return G(jnp.array([1.0, 2.0]), jnp.eye(2))


Z = np.array([1.5, 2.5])
R = 0.1 * np.eye(2)
Q = 0.1 * np.eye(2)


def _scalar_res(a, b):
    return (a - b).sum()


# --- 1. a residual of the wrong shape ------------------------------------------------------

@pytest.mark.parametrize("path", ["ekf", "sqrt_ekf", "ukf", "sqrt_ukf", "batch", "batch_seq", "run"])
def test_residual_wrong_shape_is_input_error(path):
    s = _s()
    calls = {
        "ekf": lambda: ekf.update(s, Z, lambda x: x, R, residual=_scalar_res),
        "sqrt_ekf": lambda: se.update(se.from_gaussian(s), Z, lambda x: x, R, residual=_scalar_res),
        "ukf": lambda: ukf.update(s, Z, lambda x: x, R, residual=_scalar_res),
        "sqrt_ukf": lambda: su.update(se.from_gaussian(s), Z, lambda x: x, R, residual=_scalar_res),
        "batch": lambda: ekf.update_batch(s, Z[None], lambda x: x, R, residual=_scalar_res),
        "batch_seq": lambda: ekf.update_batch(s, Z[None], lambda x: x, R, residual=_scalar_res,
                                              sequential=True),
        "run": lambda: g.run(ekf.make_filter(None, lambda x: x, residual=_scalar_res), s.mean, s.cov,
                             None, Z[None], None, Q, R),
    }
    with pytest.raises(InputError, match=r"residual: returned shape \(\), expected \(2,\)"):
        calls[path]()


def test_residual_right_shape_unchanged():
    s = _s()
    a, _ = ekf.update(s, Z, lambda x: x, R)
    b, _ = ekf.update(s, Z, lambda x: x, R, residual=lambda u, v: u - v)
    np.testing.assert_array_equal(np.asarray(a.mean), np.asarray(b.mean))
    np.testing.assert_allclose(np.asarray(a.mean), [1.5 - 0.5 / 11, 2.5 - 0.5 / 11], rtol=1e-12)


# --- 2. transition output, Q / Q_chol shapes, list outputs ----------------------------------

@pytest.mark.parametrize("f", [lambda x, u: x.sum(), lambda x, u: x[:1]])
def test_ekf_predict_wrong_transition_shape(f):
    with pytest.raises(InputError, match=r"f: the transition returned shape"):
        ekf.predict(_s(), f, None, Q)


def test_ekf_make_filter_wrong_transition_shape():
    s = _s()
    with pytest.raises(InputError, match=r"f: the transition returned shape"):
        g.run(ekf.make_filter(lambda x, u: x.sum(), lambda x: x), s.mean, s.cov, jnp.zeros((1, 2)),
              Z[None], None, Q, R)


def test_sqrt_ekf_predict_shapes():
    st = se.from_gaussian(_s())
    with pytest.raises(InputError, match=r"f: the transition returned shape \(\), expected \(2,\)"):
        se.predict(st, lambda x, u: x.sum(), None, Q)
    with pytest.raises(InputError, match=r"Q: expected shape \(2, 2\)"):
        se.predict(st, lambda x, u: x, None, np.eye(3))
    with pytest.raises(InputError, match=r"Q_chol: expected shape \(2, k\)"):
        se.predict(st, lambda x, u: x, None, Q_chol=np.eye(3))
    with pytest.raises(InputError, match=r"noise_jac: expected shape \(2, q\)"):
        se.predict(st, lambda x, u: x, None, np.eye(1), noise_jac=np.ones((3, 1)))
    # valid calls still work
    out = se.predict(st, lambda x, u: x, None, Q)
    np.testing.assert_allclose(np.asarray(se.to_gaussian(out).cov), 1.1 * np.eye(2), rtol=1e-12)


def test_list_outputs_of_models_are_read_as_arrays():
    s = _s()
    p = ekf.predict(s, lambda x, u: [x[0], x[1]], None, Q)
    np.testing.assert_allclose(np.asarray(p.cov), 1.1 * np.eye(2), rtol=1e-12)
    ref, _ = ekf.update(s, Z, lambda x: x, R)
    for upd in (ekf.update, ukf.update):
        post, _ = upd(s, Z, lambda x: [x[0], x[1]], R)
        np.testing.assert_allclose(np.asarray(post.mean), np.asarray(ref.mean), rtol=1e-10)
    post, _ = se.update(se.from_gaussian(s), Z, lambda x: [x[0], x[1]], R)
    np.testing.assert_allclose(np.asarray(post.mean), np.asarray(ref.mean), rtol=1e-10)
    pu = ukf.predict(s, lambda x, u: [x[0], x[1]], None, Q)
    np.testing.assert_allclose(np.asarray(pu.mean), [1.0, 2.0], rtol=1e-12)


# --- 3. chi2_gate's max_dof ------------------------------------------------------------------

def test_chi2_gate_smaller_than_measurement_is_refused():
    gate = ekf.chi2_gate(0.99, 1)
    s = _s()
    z = np.array([3.2, 4.2])
    for call in (lambda: ekf.update(s, z, lambda x: x, R, gate=gate),
                 lambda: ukf.update(s, z, lambda x: x, R, gate=gate),
                 lambda: se.update(se.from_gaussian(s), z, lambda x: x, R, gate=gate),
                 lambda: su.update(se.from_gaussian(s), z, lambda x: x, R, gate=gate),
                 lambda: ekf.update_batch(s, z[None], lambda x: x, R, gate=gate)):
        with pytest.raises(InputError, match=r"gate: built for at most 1"):
            call()
    # NIS 8.8: under chi2_2(0.99) = 9.21 (accepted), over chi2_1(0.99) = 6.63 (the clipped table)
    _, info = ekf.update(s, z, lambda x: x, R, gate=ekf.chi2_gate(0.99, 2))
    assert int(info.status) == 0 and bool(info.accepted)
    np.testing.assert_allclose(float(info.nis), 8.8, rtol=1e-12)


def test_chi2_gate_beyond_its_table_under_a_traced_mask_uses_the_quantile_not_its_last_value():
    """A traced mask cannot be checked before running: a step with more valid components than
    the gate's ``max_dof`` read the table's last threshold (χ²₁ for a 3-dof NIS).  Now the
    Wilson–Hilferty quantile (exact for 2 dof), against SciPy's χ² quantile."""
    from scipy.stats import chi2

    for p, tol in ((0.9, 0.007), (0.99, 0.007), (0.9999, 0.035)):
        gate = ekf.chi2_gate(p, 1)
        got = np.asarray(jax.jit(gate)(jnp.arange(1, 40)))
        want = chi2.ppf(p, np.arange(1, 40))
        assert got[0] == pytest.approx(want[0], rel=1e-12)  # the table itself is unchanged
        assert got[1] == pytest.approx(want[1], rel=1e-6)  # 2 dof: closed form, float32 table
        np.testing.assert_allclose(got[2:], want[2:], rtol=tol)
    # a 3-component measurement, NIS 10: inside χ²₃(0.99) = 11.34, outside χ²₁(0.99) = 6.63
    s3 = G(jnp.zeros(3), jnp.eye(3))
    z = jnp.array([np.sqrt(20.0), 0.0, 0.0])
    run = jax.jit(lambda m: ekf.update(s3, z, lambda x: x, jnp.eye(3), mask=m, gate=ekf.chi2_gate(0.99, 1)))
    _, info = run(jnp.ones(3, bool))
    np.testing.assert_allclose(float(info.nis), 10.0, rtol=1e-12)
    assert bool(info.accepted) and int(info.status) == 0


@pytest.mark.parametrize("max_dof", [1.5, True, "2", 0])
def test_chi2_gate_max_dof_must_be_int(max_dof):
    with pytest.raises(InputError, match="max_dof"):
        ekf.chi2_gate(0.99, max_dof)


# --- 4. angle_residual's mask ----------------------------------------------------------------

def test_angle_residual_mask_length_and_dtype():
    with pytest.raises(InputError, match="angle_mask"):
        ekf.angle_residual([True])(jnp.zeros(2), jnp.array([6.0, 6.0]))
    with pytest.raises(InputError, match="angle_mask"):
        ekf.angle_residual([0.5, 0])
    with pytest.raises(InputError, match="angle_mask"):
        ekf.angle_residual([[True, False]])
    nu = ekf.angle_residual([1, 0])(jnp.zeros(2), jnp.array([6.0, 6.0]))
    np.testing.assert_allclose(np.asarray(nu), [2 * np.pi - 6.0, -6.0], rtol=1e-12)


# --- 5. static flags and options -------------------------------------------------------------

def test_truthy_strings_refused_as_flags():
    s = _s()
    with pytest.raises(InputError, match="sequential"):
        ekf.update_batch(s, Z[None], lambda x: x, R, sequential="no")
    flt = ekf.make_filter(None, lambda x: x)
    for kw in ("save_cov", "predict_first", "save_smoother"):
        with pytest.raises(InputError, match=kw):
            g.run(flt, s.mean, s.cov, None, Z[None], None, Q, R, **{kw: "no"})
    with pytest.raises(InputError, match="return_status"):
        ukf.predict(s, lambda x, u: x + u, jnp.ones(2), Q, return_status="no")
    with pytest.raises(InputError, match="return_status"):
        ukf.predict_with_cross(s, lambda x, u: x + u, jnp.ones(2), Q, return_status="no")
    with pytest.raises(InputError, match="return_status"):
        su.predict(se.from_gaussian(s), lambda x, u: x + u, jnp.ones(2), Q, return_status="no")
    with pytest.raises(InputError, match="gate"):
        ekf.update(s, Z, lambda x: x, R, gate=True)
    with pytest.raises(InputError, match="num_iter"):
        ekf.make_filter(None, lambda x: x, num_iter=1.5)
    with pytest.raises(InputError, match="gate"):
        ekf.make_filter(None, lambda x: x, gate="x")
    with pytest.raises(InputError, match="h_takes_input"):
        ukf.make_filter(None, lambda x: x, h_takes_input="no")
    with pytest.raises(InputError, match="h_takes_input"):
        ekf.make_filter(None, lambda x: x, h_takes_input="no")


# --- 6. non-finite mean, non-PSD cov of from_gaussian ----------------------------------------

def test_nan_mean_refused_eagerly():
    bad = G(jnp.array([np.nan, 1.0]), jnp.eye(2))
    with pytest.raises(InputError, match=r"state\.mean: contains NaN or Inf"):
        ekf.update(bad, Z, lambda x: x, R)
    with pytest.raises(InputError, match=r"state\.mean: contains NaN or Inf"):
        ukf.predict(bad, None, None, Q)


def test_from_gaussian_refuses_non_psd_cov():
    with pytest.raises(InputError, match=r"g\.cov"):
        se.from_gaussian(G(jnp.ones(2), jnp.array([[1.0, 0.0], [0.0, -1.0]])))
    with pytest.raises(InputError, match=r"g\.cov"):
        se.from_gaussian(G(jnp.ones(2), jnp.array([[1.0, 0.0], [0.0, np.nan]])))
    with pytest.raises(InputError, match=r"g\.mean"):
        se.from_gaussian(G(jnp.array([np.inf, 1.0]), jnp.eye(2)))


# --- 7. a traced negative Q is flagged -------------------------------------------------------

def test_traced_negative_q_flags_not_psd():
    s = _s()
    for f in (lambda x, u: x + u, None):
        out, st = jax.jit(lambda q: ukf.predict(s, f, jnp.ones(2), q, return_status=True))(-3 * jnp.eye(2))
        assert int(st) & errors.NOT_PSD
        np.testing.assert_array_equal(np.asarray(out.cov), np.eye(2))  # the prior is kept
    _, st = jax.jit(lambda q: su.predict(se.from_gaussian(s), lambda x, u: x + u, jnp.ones(2), q,
                                         return_status=True))(-3 * jnp.eye(2))
    assert int(st) == errors.NOT_PSD
    _, st = jax.jit(lambda q: su.predict(se.from_gaussian(s), lambda x, u: x + u, jnp.ones(2), q,
                                         return_status=True))(jnp.full((2, 2), np.nan))
    assert int(st) == errors.NON_FINITE
    flt = ekf.make_filter(lambda x, u: x, lambda x: x)
    st = jax.jit(lambda q: g.run(flt, s.mean, s.cov, jnp.zeros((1, 2)), Z[None], None, q, R).status)(
        -3 * jnp.eye(2))
    assert int(st[0]) & errors.NOT_PSD
    st = jax.jit(lambda q: g.run(flt, s.mean, s.cov, jnp.zeros((1, 2)), Z[None], None, q, R).status)(Q)
    assert int(st[0]) == 0


# --- 8. empty and scalar measurements --------------------------------------------------------

def test_empty_measurement_is_input_error():
    s = _s()
    for call in (lambda: ekf.update(s, np.zeros(0), lambda x: x[:0], np.zeros((0, 0))),
                 lambda: ukf.update(s, np.zeros(0), lambda x: x[:0], np.zeros((0, 0))),
                 lambda: se.update(se.from_gaussian(s), np.zeros(0), lambda x: x[:0], np.zeros((0, 0))),
                 lambda: su.update(se.from_gaussian(s), np.zeros(0), lambda x: x[:0], np.zeros((0, 0)))):
        with pytest.raises(InputError, match=r"z: expected at least one measurement component"):
            call()


def test_scalar_measurement_is_one_component():
    s = _s()
    ref, ref_info = ekf.update(s, np.array([1.5]), lambda x: x[:1], np.array([[0.1]]))
    a, info = ekf.update(s, 1.5, lambda x: x[0], 0.1)
    np.testing.assert_array_equal(np.asarray(a.mean), np.asarray(ref.mean))
    assert info.innovation.shape == (1,) and float(info.nis) == float(ref_info.nis)
    for upd, st in ((ukf.update, s), (se.update, se.from_gaussian(s)), (su.update, se.from_gaussian(s))):
        b, _ = upd(st, 1.5, lambda x: x[0], 0.1)
        np.testing.assert_allclose(np.asarray(b.mean), np.asarray(ref.mean), rtol=1e-10)


def test_sqrt_filter_scan_flags():
    s = _s()
    for scan in (se.filter_scan, su.filter_scan):
        for kw in ("predict_first", "save_chol"):
            with pytest.raises(InputError, match=kw):
                scan(None, lambda x: x, s.mean, s.cov, None, Z[None], None, Q, R, **{kw: "no"})


def test_sqrt_ekf_predict_reads_a_scalar_q_of_one_state_as_ekf_predict_does():
    """sqrt_ekf.predict now checks Q with gaussian.check_process_noise, as ekf.predict does: a
    scalar Q is the variance of a one-component state (it was refused, "expected shape (1, 1)")."""
    from jaxslam.filters import sqrt_ekf as se_

    out = se_.predict(se_.SqrtGaussian(jnp.array([1.0]), jnp.eye(1)), lambda x, u: 2.0 * x, None, 0.1)
    np.testing.assert_allclose(np.asarray(out.chol) ** 2, [[4.1]], rtol=1e-14)  # F P Fᵀ + Q, F = 2


def test_ekf_predict_reports_its_status_like_the_sigma_point_predict():
    """``ekf.predict(..., return_status=True)``: 0 for a good step; ``NOT_PSD`` for a traced
    negative Q (a concrete one is refused before); ``NON_FINITE`` for a transition that returns
    NaN — the bits a run puts in its step's status, now visible from a single step (it had no
    status at all).  The moments are as computed."""
    s = _s()
    out, st = ekf.predict(s, lambda x, u: x + u, jnp.ones(2), Q, return_status=True)
    assert int(st) == 0
    np.testing.assert_allclose(np.asarray(out.mean), np.asarray(s.mean) + 1.0)
    np.testing.assert_allclose(np.asarray(out.cov), np.asarray(s.cov + Q), rtol=1e-12)
    neg = jax.jit(lambda q: ekf.predict(s, lambda x, u: x, None, q, return_status=True))(-100.0 * jnp.eye(2))
    assert int(neg[1]) == errors.NOT_PSD
    nan = ekf.predict(s, lambda x, u: x * jnp.nan, None, Q, return_status=True)
    assert int(nan[1]) & errors.NON_FINITE
    with pytest.raises(InputError, match="return_status"):
        ekf.predict(s, lambda x, u: x, None, Q, return_status="no")
    assert isinstance(ekf.predict(s, lambda x, u: x, None, Q), ekf.Gaussian)  # the default: moments only
