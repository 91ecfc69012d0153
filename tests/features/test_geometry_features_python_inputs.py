"""jaxslam.geometry and jaxslam.features.lines called from Python with awkward input.

Each test failed on the code before the fix (probe items 8, 10, 11, 12, 19 and the
geometry/features part of 25): wrong shapes read through clamped indices, quaternions at
extreme scale, concrete zero quaternions, the degenerate line covariance, masks and keys that
were not masks or keys, complex arrays.  Numbers are checked against NumPy closed forms.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.features import lines as F
from jaxslam.geometry import euler as eu
from jaxslam.geometry import quaternion as qu

KEY = jax.random.PRNGKey(0)
XS = np.linspace(0.0, 2.0, 30)
PTS = jnp.asarray(np.stack([XS, np.ones_like(XS)], 1))  # the line y = 1
CFG = F.RansacConfig(n_hyp=16, max_lines=2)


def _np_qlog(q):
    """Oracle: 2 atan2(|v|, |w|) v/|v| in float64 after dividing by max|q| (NumPy)."""
    q = np.asarray(q, np.float64)
    q = q / np.max(np.abs(q))
    w, v = q[0], q[1:]
    n = np.linalg.norm(v)
    return 2.0 * np.arctan2(n, abs(w)) * np.sign(w if w != 0 else 1.0) * v / n


# ----------------------------------------------------------------------------- item 8


@pytest.mark.parametrize("call, needle", [
    (lambda: F.line_through(jnp.array([1.0]), jnp.array([2.0])), r"^line_through: p1 expected shape \(2,\)"),
    (lambda: F.line_through([1.0, 0.0], [1.0, 1.0, 7.0]), r"^line_through: p2 expected shape \(2,\)"),
    (lambda: F.point_line_distance(jnp.array([[1.0], [2.0]]), 1.0, 0.0),
     r"^point_line_distance: points expected shape \(\.\.\., 2\)"),
    (lambda: F.point_line_distance(jnp.array([[1.0, 0.0, 9.0]]), 1.0, 0.0),
     r"^point_line_distance: points expected shape \(\.\.\., 2\)"),
    (lambda: F.segment_endpoints(PTS, jnp.ones(1), 1.0, np.pi / 2), r"^weights: expected shape \(30,\)"),
    (lambda: F.segment_endpoints(jnp.ones((30, 3)), jnp.ones(30), 1.0, np.pi / 2),
     r"^points: expected shape \(N, 2\)"),
], ids=["lt-1", "lt-3", "pld-N1", "pld-N3", "seg-w1", "seg-N3"])
def test_line_geometry_refuses_wrong_shapes(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


def test_line_geometry_of_good_input():
    rho, theta = F.line_through([1.0, 0.0], [1.0, 1.0])  # the line x = 1
    assert float(rho) == pytest.approx(1.0) and float(theta) == pytest.approx(0.0, abs=1e-15)
    p = np.array([[3.0, 4.0], [0.5, -2.0]])
    want = np.abs(p @ [np.cos(0.3), np.sin(0.3)] - 1.2)
    np.testing.assert_allclose(np.asarray(F.point_line_distance(p, 1.2, 0.3)), want, rtol=1e-14)
    assert float(F.point_line_distance(p[0], 1.2, 0.3)) == pytest.approx(want[0], rel=1e-14)  # one point
    ends = np.asarray(F.segment_endpoints(PTS.tolist(), [1.0] * 30, 1.0, np.pi / 2))
    np.testing.assert_allclose(ends, [[2.0, 1.0], [0.0, 1.0]], atol=1e-12)


# ----------------------------------------------------------------------------- item 10


@pytest.mark.parametrize("dtype, scale, q0", [
    (np.float32, 1e20, [1.0, 0.3, -0.2, 0.1]), (np.float32, 1e-20, [1.0, 0.3, -0.2, 0.1]),
    (np.float32, 3e38, [1.0, 0.3, -0.2, 0.1]), (np.float32, 1e20, [1.0, 0.3, 0.0, 0.0]),
    (np.float64, 1e-150, [1.0, 1e-5, 0.0, 0.0]), (np.float64, 1e150, [0.1, 1.0, -0.2, 0.1]),
    (np.float64, 1e-300, [1.0, 0.3, -0.2, 0.1])])
def test_quaternions_at_extreme_scale(dtype, scale, q0):
    q0 = np.asarray(q0)
    q = jnp.asarray((q0 * scale).astype(dtype))
    assert np.all(np.isfinite(np.asarray(q)))
    tol = 1e-6 if dtype == np.float32 else 1e-14
    for log in (qu.qlog, jax.jit(qu.qlog)):  # eager (host-side range test) and traced
        np.testing.assert_allclose(np.asarray(log(q), np.float64), _np_qlog(q0), rtol=tol)
    for norm in (qu.qnormalize, jax.jit(qu.qnormalize)):
        np.testing.assert_allclose(np.asarray(norm(q), np.float64), q0 / np.linalg.norm(q0), rtol=tol)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_ordinary_quaternions_are_unchanged(dtype):
    rng = np.random.default_rng(3)
    q = rng.normal(size=(64, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[0], q[1] = [1, 0, 0, 0], [-1, 0, 0, 0]
    q[2:8] *= rng.uniform(0.01, 100, size=(6, 1))
    q = jnp.asarray(q.astype(dtype))
    # qnormalize: bit for bit the plain q / |q| (the power-of-two scaling is exact), eager and jitted
    np.testing.assert_array_equal(np.asarray(qu.qnormalize(q)), np.asarray(q / jnp.linalg.norm(q, axis=-1, keepdims=True)))
    np.testing.assert_array_equal(np.asarray(jax.jit(qu.qnormalize)(q)),
                                  np.asarray(jax.jit(lambda q: q / jnp.linalg.norm(q, axis=-1, keepdims=True))(q)))
    want = np.stack([_np_qlog(x) if np.any(x[1:]) else np.zeros(3) for x in np.asarray(q, np.float64)])
    np.testing.assert_allclose(np.asarray(qu.qlog(q), np.float64), want, atol=4 * np.finfo(dtype).eps)
    np.testing.assert_array_equal(np.asarray(qu.qlog(q)), np.asarray(jax.jit(qu.qlog)(q)))
    # gradients at the identity: finite, and the closed forms dlog/dq = [0 | 2I], dn/dq = I - e0 e0ᵀ
    e = jnp.asarray(np.array([1.0, 0, 0, 0], dtype))
    for jac in (jax.jacfwd, jax.jacrev):
        np.testing.assert_array_equal(np.asarray(jac(qu.qlog)(e)), np.hstack([np.zeros((3, 1)), 2 * np.eye(3)]))
        np.testing.assert_allclose(np.asarray(jac(qu.qnormalize)(e)), np.diag([0.0, 1, 1, 1]), atol=1e-7)


# ----------------------------------------------------------------------------- item 11


@pytest.mark.parametrize("call, needle", [
    (lambda z: qu.qnormalize(z), "^qnormalize: q is a zero quaternion"),
    (lambda z: qu.qrotate(z, jnp.array([1.0, 2.0, 3.0])), "^qrotate: q is a zero quaternion"),
    (lambda z: qu.dcm_from_quat(z), "^dcm_from_quat: q is a zero quaternion"),
    (lambda z: qu.euler_from_quat(z), "^euler_from_quat: q is a zero quaternion"),
    (lambda z: qu.qlog(z), "^qlog: q is a zero quaternion"),
    (lambda z: qu.qlog(jnp.stack([jnp.array([1.0, 0, 0, 0]), z])), r"^qlog: q is a zero quaternion \(at index \(1,\)\)"),
    (lambda z: qu.quat_from_dcm(jnp.zeros((3, 3))), "^quat_from_dcm: C is a zero matrix"),
], ids=["qnormalize", "qrotate", "dcm", "euler", "qlog", "qlog-batch", "quat_from_dcm"])
def test_concrete_zero_quaternion_is_refused(call, needle):
    with pytest.raises(InputError, match=needle):
        call(jnp.zeros(4))


def test_integer_zero_quaternion_is_refused_and_integer_ones_are_read():
    # an integer dtype's safe range was (0, inf): a zero quaternion of ints slipped through the
    # fast path (NaN from qnormalize, a zero DCM); a review found it
    for fn in (qu.qnormalize, qu.dcm_from_quat, qu.qlog):
        with pytest.raises(InputError, match=r"is a zero quaternion"):
            fn(np.zeros(4, int))
    np.testing.assert_array_equal(np.asarray(qu.qnormalize(np.array([[2, 0, 0, 0], [0, 3, 0, 0]]))),
                                  [[1.0, 0, 0, 0], [0, 1.0, 0, 0]])


def test_zero_quaternion_under_jit_is_unchanged():
    assert np.all(np.isnan(np.asarray(jax.jit(qu.qlog)(jnp.zeros(4)))))  # traced: no value check
    np.testing.assert_array_equal(np.asarray(jax.jit(qu.dcm_from_quat)(jnp.zeros(4))), np.zeros((3, 3)))
    tiny = jnp.asarray([1e-30, 0.0, 0.0, 0.0], jnp.float32)  # not zero: accepted eagerly, the identity
    np.testing.assert_array_equal(np.asarray(qu.qlog(tiny)), np.zeros(3))


# ----------------------------------------------------------------------------- item 12


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("pts, w", [
    ([[2.0, 3.0]], [1.0]),  # one point
    ([[2.0, 3.0], [2.0, 3.0]], [1.0, 1.0]),  # two identical points
    ([[2.0, 3.0], [2.0, 3.0], [2.0, 3.0], [5.0, 1.0]], [0.5, 0.5, 2.0, 0.0]),  # one distinct weighted point
    ([[2.0, 3.0], [4.0, 1.0]], [0.0, 0.0]),  # zero total weight
], ids=["one", "two-same", "weighted-same", "no-weight"])
def test_degenerate_line_covariance_is_huge_but_finite(dtype, pts, w):
    p, w = jnp.asarray(np.asarray(pts, dtype)), jnp.asarray(np.asarray(w, dtype))
    for cov_fn in (F.fit_line_cov, jax.jit(F.fit_line_cov)):
        cov = np.asarray(cov_fn(p, w, 0.02), np.float64)
        assert np.all(np.isfinite(cov)), cov
        assert cov[1, 1] > 1e6 and cov[0, 0] > 0.02**2 / 2  # var θ huge; var ρ at least σ²/N
        np.testing.assert_allclose(cov, cov.T, rtol=0, atol=0)
        assert np.linalg.eigvalsh(cov).min() >= -1e-9 * np.abs(cov).max()


def test_line_covariance_of_good_input_matches_its_closed_form():
    rng = np.random.default_rng(1)
    p = np.stack([np.linspace(0, 2, 25), 1.5 + 0.02 * rng.normal(size=25)], 1)
    rho, theta = (float(v) for v in F.fit_line(p, np.ones(25)))
    d = np.array([-np.sin(theta), np.cos(theta)])
    c = p.mean(0)
    sbar, u = c @ d, (p - c) @ d
    suu, s2 = u @ u, 0.02**2
    want = s2 * np.array([[1 / 25 + sbar**2 / suu, sbar / suu], [sbar / suu, 1 / suu]])
    np.testing.assert_allclose(np.asarray(F.fit_line_cov(p, np.ones(25), 0.02)), want, rtol=1e-9)


@pytest.mark.parametrize("w, sigma, needle", [
    (np.r_[np.ones(29), np.nan], 0.02, "^weights: must be finite"),
    (np.r_[np.ones(29), np.inf], 0.02, "^weights: must be finite"),
    (np.ones(30), np.inf, r"^sigma: expected a point noise σ > 0 \[m\] \(finite\)"),
])
def test_line_covariance_refuses_non_finite_weights_and_sigma(w, sigma, needle):
    with pytest.raises(InputError, match=needle):
        F.fit_line_cov(PTS, jnp.asarray(w), sigma)


# ----------------------------------------------------------------------------- item 19


@pytest.mark.parametrize("call, needle", [
    (lambda: F.extract_lines(KEY, PTS, jnp.full(30, 0.3), CFG), "^valid: expected a bool mask"),
    (lambda: F.extract_lines(KEY, PTS, jnp.full(30, np.nan), CFG), "^valid: expected a bool mask"),
    (lambda: F.extract_lines(KEY, PTS, jnp.full(30, 2), CFG), "^valid: expected a bool mask .* got the value 2"),
    (lambda: F.match_predicted(PTS, jnp.ones(30, bool), jnp.array([1.0]), jnp.array([np.pi / 2]),
                               jnp.array([0.2]), CFG), "^pred_mask: expected a bool mask"),
    (lambda: F.extract_lines(0, PTS, jnp.ones(30, bool), CFG), "^key: expected a PRNG key"),
    (lambda: F.extract_guided(7, PTS, jnp.ones(30, bool), jnp.array([1.0]), jnp.array([np.pi / 2]),
                              jnp.array([True]), CFG), "^key: expected a PRNG key"),
    (lambda: F.largest_run(jnp.array([0.5, 0.0, 0.5]), 0), "^mask: expected a bool mask"),
    (lambda: F.largest_run(jnp.ones((2, 3), bool), 1), r"^mask: expected shape \(N,\)"),
    (lambda: F.trim_run(jnp.ones((2, 3), bool), 1), r"^mask: expected shape \(N,\)"),
], ids=["valid-0.3", "valid-nan", "valid-2", "pred-mask", "key-int", "guided-key", "run-float", "run-2d",
        "trim-2d"])
def test_masks_and_keys_are_checked(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


def test_empty_runs_and_tiny_outlier_ratio():
    for f in (lambda m: F.largest_run(m, 2), lambda m: F.trim_run(m, 1)):
        out = f(jnp.zeros(0, bool))
        assert out.shape == (0,) and out.dtype == jnp.bool_
    # eq. 4.1 with ε -> 0: log(1 - p) / log(1 - (1 - ε)^m) -> 0 hypotheses, at least one is drawn
    assert F.n_hypotheses(0.99, 1e-300) == 1
    assert F.n_hypotheses(0.99, 1e-17) == 1
    assert F.n_hypotheses(0.99, 0.9) == 459  # unchanged
    # a 0/1 integer mask still works
    np.testing.assert_array_equal(np.asarray(F.largest_run(jnp.array([1, 1, 0, 0, 0, 1, 1, 1]), 1)),
                                  [0, 0, 0, 0, 0, 1, 1, 1])


# ----------------------------------------------------------------------------- item 25


@pytest.mark.parametrize("call, needle", [
    (lambda: qu.qexp(jnp.array([0.1j, 0, 0])), "^qexp: rotvec: expected a real array"),
    (lambda: qu.qlog(jnp.array([1, 0.1j, 0, 0])), "^qlog: q: expected a real array"),
    (lambda: qu.qmul(jnp.array([1, 0, 0, 0j]), jnp.array([1.0, 0, 0, 0])), "^qmul: p: expected a real array"),
    (lambda: eu.dcm_from_euler(jnp.array([0.1j, 0, 0])), "^dcm_from_euler: euler: expected a real array"),
    (lambda: eu.euler_from_dcm(jnp.eye(3) + 0j), "^euler_from_dcm: C: expected a real array"),
    (lambda: eu.C1(1j), "^C1: phi: expected a real array"),
    (lambda: eu.C3("a"), "^C3: psi: expected numbers"),
    (lambda: jax.jit(qu.qexp)(jnp.array([0.1j, 0, 0])), "^qexp: rotvec: expected a real array"),  # static
    (lambda: F.fit_line(PTS + 0j, jnp.ones(30)), "^points: expected a real array"),
    (lambda: F.fit_line(PTS, jnp.ones(30) + 0j), "^weights: expected a real array"),
    (lambda: F.extract_lines(KEY, PTS + 0j, jnp.ones(30, bool), CFG), "^points: expected a real array"),
    (lambda: F.match_predicted(PTS, jnp.ones(30, bool), jnp.array([1.0 + 0j]), jnp.array([1.5]),
                               jnp.array([True]), CFG), "^pred_rho: expected a real array"),
], ids=["qexp", "qlog", "qmul", "dcm_from_euler", "euler_from_dcm", "C1", "C3-str", "qexp-jit", "fit-points",
        "fit-weights", "extract", "match"])
def test_complex_input_is_refused(call, needle):
    with pytest.raises(InputError, match=needle):
        call()
