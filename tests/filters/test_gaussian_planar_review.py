"""Defects a review of gaussian.py (shared Gaussian-filter code), ukf.py and the planar EKF-SLAM
system found: each test compares with a hand-written expectation, never with the code itself."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, gaussian as g, sqrt_ekf as se, sqrt_ukf as su, ukf

jax.config.update("jax_enable_x64", True)


def _h1(x):
    return jnp.zeros((1,), x.dtype)


# --- (a) an empty state (n = 0) ---------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_empty_state_is_an_input_error_naming_the_state(dtype):
    # every Gaussian filter ended in NumPy's bare "cannot reshape array of size 0 into shape (0,0)"
    s = g.Gaussian(np.zeros(0, dtype), np.zeros((0, 0), dtype))
    Q0 = np.zeros((0, 0), dtype)
    z, R = np.zeros(1, dtype), np.eye(1, dtype=dtype)
    calls = {
        "ekf.predict": lambda: ekf.predict(s, None, None, Q0),
        "ekf.update": lambda: ekf.update(s, z, _h1, R),
        "ukf.predict": lambda: ukf.predict(s, None, None, Q0),
        "ukf.update": lambda: ukf.update(s, z, _h1, R),
        "sqrt_ekf.update": lambda: se.update(se.SqrtGaussian(s.mean, s.cov), z, _h1, R),
        "sqrt_ukf.update": lambda: su.update(se.SqrtGaussian(s.mean, s.cov), z, _h1, R),
    }
    for name, call in calls.items():
        with pytest.raises(InputError, match=r"^state\.mean: expected a state of at least one component"):
            call()
    zs = np.zeros((3, 1), dtype)
    for scan in (ekf.filter_scan, ukf.filter_scan):
        with pytest.raises(InputError, match=r"^x0: expected a state of at least one component"):
            scan(None, _h1, np.zeros(0, dtype), Q0, None, zs, None, Q0, R)
    with pytest.raises(InputError, match=r"^x0: expected a state of at least one component"):
        g.run(ekf.make_filter(None, _h1), np.zeros(0, dtype), Q0, None, zs, None, Q0, R)
    # the sigma-point rule keeps its own message for n = 0 (tests/filters/test_sigma_review.py)
    with pytest.raises(InputError, match=r"^points: a sigma-point rule needs a state of at least one"):
        ukf.sigma_points(np.zeros(0, dtype), Q0)


def test_size_one_state_still_runs_and_matches_the_scalar_kalman_filter():
    # n = 1 is the smallest state and must keep working: hand-computed scalar Kalman update
    x, P, r, zv = 1.0, 2.0, 0.5, 3.0
    post, info = ekf.update(g.Gaussian(np.array([x]), np.array([[P]])), np.array([zv]), lambda s: s, np.array([[r]]))
    k = P / (P + r)
    np.testing.assert_allclose(np.asarray(post.mean), [x + k * (zv - x)], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(post.cov), [[(1 - k) * P]], rtol=1e-12)
    assert float(info.nis) == pytest.approx((zv - x) ** 2 / (P + r), rel=1e-12)


# --- (c) booleans for the unscented parameters ------------------------------------------------

@pytest.mark.parametrize("kw", [dict(alpha=True), dict(alpha=np.bool_(True)), dict(beta=True),
                                dict(kappa=False), dict(kappa=np.bool_(False))])
def test_unscented_refuses_booleans(kw):
    # unscented(True) was read as alpha = 1 (and beta=True as beta = 1), like gate=True once was
    name = next(iter(kw))
    with pytest.raises(InputError, match=rf"^{name}: must be a finite number, got "):
        ukf.unscented(**kw)


def test_unscented_numbers_still_give_the_hand_computed_weights():
    # n = 2, alpha = 0.5, beta = 2, kappa = 0: lambda = 0.25 * 2 - 2 = -1.5, n + lambda = 0.5
    rule = ukf.unscented(np.float64(0.5), 2, 0)
    wm, wc, c = rule.weights(2)
    np.testing.assert_allclose(wm, [-3.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(wc, [-3.0 + 1 - 0.25 + 2, 1.0, 1.0, 1.0, 1.0])
    assert c == pytest.approx(np.sqrt(0.5))


# --- (b) planar EKF-SLAM, association "jcbb": jcbb's status reaches the run's -------------------

def _planar():
    from jaxslam.systems import planar_ekf_slam as pe

    T_ = 4
    log = pe.Log(dt=np.full(T_, 0.1), u=np.tile([1.0, 0.1], (T_, 1)),
                 z=np.tile([[5.0, 0.3], [4.0, -0.2]], (T_, 1, 1)),
                 ids=np.tile(np.array([0, 1], np.int32), (T_, 1)), mask=np.ones((T_, 2), bool), pose0=np.zeros(3))
    cfg = pe.Config(capacity=4, K=2, association="jcbb")
    prm = pe.Params(M_c=0.01 * np.eye(2), Q_floor=1e-4 * np.eye(3), R=np.diag([0.1, 0.01]), P0=1e-3 * np.eye(3))
    return pe, log, cfg, prm


def test_planar_jcbb_run_flags_a_traced_bad_gate():
    # association.jcbb sets NON_FINITE for a traced NaN / non-positive gate (it then pairs
    # nothing), but the planar system dropped that status: the run said status 0
    pe, log, cfg, prm = _planar()
    f = jax.jit(lambda gt: pe.run(log, cfg, prm._replace(gate=gt)).status)
    for bad in (np.nan, -1.0):
        assert int(f(jnp.asarray(bad))) & errors.NON_FINITE, bad
    # a valid gate (traced or not) adds no flag: the event's landmarks are registered, then matched
    ok = int(f(jnp.asarray(9.21)))
    assert ok & errors.NON_FINITE == 0
    res = pe.run(log, cfg, prm)
    assert int(res.status) == ok
    assert int(res.status) & errors.NON_FINITE == 0


# --- planar EKF-SLAM: config and parameter-file checks ----------------------------------------

def test_planar_config_switches_must_be_bools_and_joint_gate_a_number():
    pe, log, cfg, prm = _planar()
    cfg = cfg._replace(association="known")
    for name in ("calibrate", "robust", "monitor", "smooth", "active_only", "joseph"):
        # a string "no" is truthy: the switch was silently on (calibrate="no" grew the robot block)
        for bad in ("no", 1, None):
            with pytest.raises(InputError, match=rf"^config\.{name}: expected True or False, got "):
                pe.validate_config(cfg._replace(**{name: bad}))
    # a string joint_gate was a bare TypeError from the comparison
    for bad in ("0.99", [0.99], True):
        with pytest.raises(InputError, match=r"^config\.joint_gate: need a probability in \(0, 1\), got "):
            pe.validate_config(cfg._replace(association="nn", joint_gate=bad))
    # numbers and NumPy bools still pass
    for jg in (0.99, np.float32(0.5), None):
        pe.validate_config(cfg._replace(association="nn", joint_gate=jg, calibrate=np.bool_(False)))


@pytest.mark.parametrize("d, key", [({"gate": True}, "gate"), ({"gate": "12.5"}, "gate"),
                                    ({"R": ["0.1", "0.01"]}, "R"), ({"R": [True, True]}, "R"),
                                    ({"update_gate": 10 ** 400}, "update_gate"), ({"R": [10 ** 400, 1.0]}, "R")])
def test_params_from_dict_refuses_bools_strings_and_huge_ints(d, key):
    # JSON true / "12.5" were read as 1.0 / 12.5; an integer beyond float range was a bare OverflowError
    pe, _, _, prm = _planar()
    with pytest.raises(InputError, match=rf"^params\.noise\.{key}: expected numbers, got "):
        pe.params_from_dict(d, prm)


def test_params_from_dict_monitor_refuses_bools_and_huge_ints():
    pe, _, _, prm = _planar()
    for bad in (True, 10 ** 400):
        with pytest.raises(InputError, match=r"^params\.noise\.monitor\.alpha: expected a number"):
            pe.params_from_dict({"monitor": {"alpha": bad}}, prm)


def test_params_from_dict_still_reads_numbers_and_diagonals():
    pe, _, _, prm = _planar()
    out = pe.params_from_dict({"gate": 12, "R": [0.25, 0.0004], "update_gate": None,
                               "monitor": {"alpha": 0.1}}, prm)
    assert float(out.gate) == 12.0 and out.update_gate is None
    np.testing.assert_array_equal(np.asarray(out.R), [[0.25, 0.0], [0.0, 0.0004]])
    assert float(out.monitor.alpha) == 0.1 and float(out.monitor.threshold) == 3.0


# --- ukf: a traced bad gate, a hand-built rule with a bool ------------------------------------

@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ukf_traced_bad_gate_is_flagged_and_keeps_the_prior(dtype):
    # a traced NaN gate switched gating off (nis > nan is False): the outlier was accepted, status 0
    x0, P0 = np.zeros(2, dtype), np.eye(2, dtype=dtype)
    zs = np.array([[100.0, 0.0]], dtype)
    R, Q = np.eye(2, dtype=dtype), np.zeros((2, 2), dtype)
    run = jax.jit(lambda gt: ukf.filter_scan(None, lambda x: x, x0, P0, None, zs, None, Q, R, gate=gt))
    for bad in (np.nan, -1.0, 0.0):
        out = run(jnp.asarray(bad, dtype))
        st = int(out.status[0])
        assert st & errors.NON_FINITE and st & errors.GATED, (bad, st)
        np.testing.assert_array_equal(np.asarray(out.means[0]), [0.0, 0.0])  # the prior kept
        assert np.isnan(float(out.log_likelihood[0]))
    # a valid traced gate: the outlier (NIS = 100² / 2 = 5000) is gated as a number would gate it
    out = run(jnp.asarray(9.21, dtype))
    assert int(out.status[0]) == errors.GATED
    # and a generous one lets it through with the scalar Kalman gain P / (P + R) = 1/2
    out = run(jnp.asarray(1e4, dtype))
    assert int(out.status[0]) == 0
    np.testing.assert_allclose(np.asarray(out.means[0]), [50.0, 0.0], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(out.cov_diags[0]), [0.5, 0.5], rtol=1e-5)


def test_hand_built_sigma_rule_refuses_booleans():
    for kw in (dict(alpha=True), dict(beta=np.bool_(True)), dict(kappa=False)):
        rule = ukf.SigmaPoints("unscented", **{**dict(alpha=1.0, beta=2.0, kappa=0.0), **kw})
        with pytest.raises(InputError, match=rf"^points: {next(iter(kw))} must be a finite number"):
            rule.weights(2)


def test_planar_validate_params_refuses_bools_and_string_calib0():
    # update_gate=True was read as a gate at NIS 1; robust_nu=True as nu = 1; a bool R as the identity;
    # a string entry of calib0 was a bare TypeError from isfinite (or read as a number)
    pe, log, cfg, prm = _planar()
    for k, v in (("update_gate", True), ("robust_nu", np.bool_(True)), ("range_model", [True, 0.0]),
                 ("R", np.eye(2, dtype=bool)), ("gate", True)):
        with pytest.raises(InputError, match=rf"^params\.{k}: expected numbers, got "):
            pe.validate_params(prm._replace(**{k: v}))
    with pytest.raises(InputError, match=r"^params\.monitor: expected numbers, got "):
        pe.validate_params(prm._replace(monitor=pe.MONITOR_DEFAULT._replace(alpha=True)))
    for bad in ([1, 1, "0"], ["a", 1, 0]):
        with pytest.raises(InputError, match=r"^params\.calib0: expected a finite shape \(3,\)"):
            pe.validate_params(prm._replace(calib0=bad))
    # numbers (Python, NumPy, JAX, float32) still pass
    pe.validate_params(prm._replace(update_gate=9.21, robust_nu=np.float32(5.0), calib0=jnp.asarray([1.0, 1.0, 0.0]),
                                    R=np.diag([0.1, 0.01]).astype(np.float32)))
