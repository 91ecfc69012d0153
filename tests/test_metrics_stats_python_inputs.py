"""jaxslam.metrics and jaxslam.stats called from Python with inputs a probe found mishandled:
integer points (a truncated Umeyama scale), masks of the wrong shape or dtype, fractional or
non-finite landmark ids, a transposed quaternion array, Student-t NLLs at large ν, NaN
gradients at zero error, bad window arguments, complex arrays, an infinite run in a summary
and TUM files that are not TUM files.

Oracles: closed forms (the Student-t NLL for even d, where log Γ(ν/2 + d/2) − log Γ(ν/2) is a
finite sum of logs, and its derivatives), SciPy's ``t.logpdf`` / ``multivariate_t.logpdf`` at
moderate ν, the Gaussian limit at ν ≥ 10¹⁷, NumPy, and central finite differences.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as sps

from jaxslam import metrics, stats
from jaxslam.errors import InputError

LOG2PI = math.log(2.0 * math.pi)


# ---------------------------------------------------------------------------
# Umeyama / ATE with integer points (item 4)
# ---------------------------------------------------------------------------

def test_umeyama_and_ate_read_integer_points_as_floats():
    src = np.array([[0, 0], [2, 0], [0, 2], [1, 3]])
    dst = np.array([[0, 0], [3, 0], [0, 3], [2, 5]])
    R_f, t_f, s_f = metrics.umeyama(src.astype(float), dst.astype(float), with_scale=True)
    R_i, t_i, s_i = metrics.umeyama(src, dst, with_scale=True)  # the scale was truncated to 1
    assert jnp.issubdtype(s_i.dtype, jnp.floating)
    np.testing.assert_allclose(float(s_i), float(s_f), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(R_i), np.asarray(R_f), rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(np.asarray(t_i), np.asarray(t_f), rtol=1e-15, atol=1e-15)
    # an exact similarity: dst = 1.5 src
    _, _, s = metrics.umeyama(np.array([[0, 0], [2, 0], [0, 2]]), np.array([[0, 0], [3, 0], [0, 3]]), with_scale=True)
    assert float(s) == pytest.approx(1.5, rel=1e-14)
    # ATE with integer positions: was 0.963, is the float answer 0.229
    assert float(metrics.ate(src, dst, "sim")) == pytest.approx(float(metrics.ate(src * 1.0, dst * 1.0, "sim")),
                                                               rel=1e-14)
    # shapes that do not pair points are named (a bare TypeError inside JAX before)
    with pytest.raises(InputError, match=r"^src and dst: the same \(N, d\) shape"):
        metrics.umeyama(np.ones((3, 2)), np.ones((4, 2)))
    with pytest.raises(InputError, match=r"^src: expected shape \(N, d\)"):
        metrics.umeyama(np.ones(3), np.ones(3))


# ---------------------------------------------------------------------------
# rmse_norm_where's mask (item 5)
# ---------------------------------------------------------------------------

def test_rmse_norm_where_refuses_a_mask_that_does_not_fit():
    err = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    for where in (np.array([True]), np.ones((3, 1), bool)):  # broadcast: 2.0 instead of 1.155
        with pytest.raises(InputError, match=r"^where: expected shape \(3,\)"):
            metrics.rmse_norm_where(err, where)
    for where in (np.array([0.5, 0.5, 2.0]), np.array([np.nan, 1.0, 1.0])):  # read as weights
        with pytest.raises(InputError, match=r"^where: expected a bool mask"):
            metrics.rmse_norm_where(err, where)
    with pytest.raises(InputError, match=r"^where: expected a bool mask"):  # dtype: also under jit
        jax.jit(metrics.rmse_norm_where)(err, jnp.ones(3))
    # valid masks (bool, 0/1 integers, traced): NumPy oracle
    w = np.array([True, False, True])
    ref = np.sqrt(np.sum(np.sum(err ** 2, 1) * w) / w.sum())
    assert float(metrics.rmse_norm_where(err, w)) == pytest.approx(ref, rel=1e-15)
    assert float(metrics.rmse_norm_where(err, w.astype(int))) == pytest.approx(ref, rel=1e-15)
    assert float(jax.jit(metrics.rmse_norm_where)(err, w)) == pytest.approx(ref, rel=1e-15)
    assert np.isnan(float(metrics.rmse_norm_where(err, np.zeros(3, bool))))


# ---------------------------------------------------------------------------
# map_error ids (item 6)
# ---------------------------------------------------------------------------

def test_map_error_refuses_ids_that_would_be_truncated():
    lm = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]])
    true4 = np.vstack([lm, [[50.0, 50.0]]])
    cases = [
        ((lm, [1, 2.7, 3], true4, [1, 2, 3, 4]), "^est_ids: expected whole-number"),  # matched to 2
        ((lm, [1, 2, 3], true4, [1, 2, 3, 2.5]), "^true_ids: expected whole-number"),  # overwrote id 2
        ((lm, [1, np.nan, 3], lm, [1, 2, 3]), "^est_ids: expected whole-number"),  # bare ValueError
        ((lm, [1, np.inf, 3], lm, [1, 2, 3]), "^est_ids: expected whole-number"),  # OverflowError
        ((lm, [1, 2, 3], lm, [1, np.nan, 3]), "^true_ids: expected whole-number"),
        ((lm, [-0.5, 2, 3], true4, [0, 2, 3, 4]), None),  # < 0: ignored, never read as id 0
        ((lm, ["a", "b", "c"], lm, [1, 2, 3]), "^est_ids: expected numeric landmark ids"),
    ]
    for args, needle in cases:
        if needle is None:
            me = metrics.map_error(*args, transform=(np.eye(2), np.zeros(2)))
            assert sorted(me.ids.tolist()) == [2, 3] and me.rmse == 0.0
            continue
        with pytest.raises(InputError, match=needle):
            metrics.map_error(*args)
    # whole-number float ids, a NaN id on an ignored row (position not finite): accepted
    est = np.vstack([lm, [[np.nan, 0.0]]])
    me = metrics.map_error(est, [1.0, 2.0, 3.0, np.nan], lm, np.array([1.0, 2.0, 3.0]))
    assert sorted(me.ids.tolist()) == [1, 2, 3] and me.rmse == pytest.approx(0.0, abs=1e-12)


# ---------------------------------------------------------------------------
# write_tum / read_tum (items 7, 26)
# ---------------------------------------------------------------------------

def test_write_tum_refuses_quaternions_that_are_not_one_per_row(tmp_path):
    t = np.arange(3.0)
    p = np.arange(9.0).reshape(3, 3)
    q = np.array([[0, 0, 0, 1], [0, 0, 0.6, 0.8], [0.1, 0.2, 0.3, 0.927]])
    for bad in (q.T.copy(), q[:, :3], q.ravel()):  # (4, T) was reshaped into scrambled rows
        with pytest.raises(InputError, match=r"^quat_xyzw: expected shape \(3, 4\)"):
            metrics.write_tum(tmp_path / "a.txt", t, p, quat_xyzw=bad)
    assert not (tmp_path / "a.txt").exists()
    tt, pp, qq = metrics.read_tum(metrics.write_tum(tmp_path / "b.txt", t, p, quat_xyzw=q))
    np.testing.assert_allclose(qq, q, atol=1e-9)
    np.testing.assert_allclose(pp, p, atol=1e-9)


def test_read_tum_names_files_that_are_not_tum(tmp_path):
    (tmp_path / "ragged.txt").write_text("1 2 3 4 5 6 7 8\n1 2 3\n")
    (tmp_path / "words.txt").write_text("1 2 3 4 5 6 7 x\n")
    (tmp_path / "empty.txt").write_text("# timestamp tx ty tz qx qy qz qw\n")
    for name, needle in (("ragged.txt", "not a TUM trajectory"), ("words.txt", "not a TUM trajectory"),
                         ("empty.txt", "no trajectory lines"), ("missing.txt", "not found")):
        with pytest.raises(InputError, match=needle) as e:
            metrics.read_tum(tmp_path / name)
        assert name in str(e.value)
    with pytest.raises(InputError, match="is a folder"):  # IsADirectoryError before
        metrics.read_tum(tmp_path)


# ---------------------------------------------------------------------------
# Student-t NLL at large ν (item 9)
# ---------------------------------------------------------------------------

def _nll_even(d2, ld, nu, dim):
    """Closed form for even d: log Γ(ν/2 + m) − log Γ(ν/2) = Σ_{k<m} log(ν/2 + k), m = d/2, so
    the NLL is ½ ld + (ν+d)/2 log1p(d²/ν) + m log 2π + Σ_{k<m} [log(ν/2) − log(ν/2 + k)]."""
    m = dim // 2
    return (0.5 * ld + 0.5 * (nu + dim) * math.log1p(d2 / nu) + m * LOG2PI
            - sum(math.log1p(2.0 * k / nu) for k in range(m)))


NUS = (60.0, 61.0, 500.0, 1e4, 1e6, 1e8, 1e12, 1e17, 1e300)


@pytest.mark.parametrize("dim", [2, 4])
def test_student_t_nll_at_large_nu_matches_the_closed_form(dim):
    d2 = np.array([0.0, 1.0, 30.0])
    ld = 0.3
    for nu in NUS:
        ref = np.array([_nll_even(x, ld, nu, dim) for x in d2])
        got = np.asarray(stats.student_t_nll(jnp.asarray(d2), ld, nu, dim))
        # float64 ν = 1e17 gave 40.3 for d = 2 (2.49); ν = 1e6 was 1e-10 off
        np.testing.assert_allclose(got, ref, rtol=2e-15, atol=2e-15, err_msg=f"nu={nu}")
        if nu < 3e38:  # float32 rows: ν = 1e6 gave 2.46 (2.338), ν = 1e8 -44.4
            got32 = stats.student_t_nll(jnp.asarray(d2, jnp.float32), jnp.float32(ld), nu, dim)
            assert got32.dtype == jnp.float32
            ref32 = np.array([_nll_even(float(np.float32(x)), float(np.float32(ld)), float(np.float32(nu)), dim)
                              for x in d2])
            np.testing.assert_allclose(np.asarray(got32), ref32, rtol=3e-7, atol=3e-7, err_msg=f"nu={nu}")
    # a list of rows is an array (a bare TypeError before)
    np.testing.assert_allclose(np.asarray(stats.student_t_nll(d2.tolist(), ld, 1e6, dim)),
                               [_nll_even(x, ld, 1e6, dim) for x in d2], rtol=2e-15)
    # a ν beyond float32's range with float32 rows is the Gaussian (it was NaN)
    g = stats.student_t_nll(jnp.asarray(d2, jnp.float32), jnp.float32(ld), 1e300, dim)
    np.testing.assert_allclose(np.asarray(g), 0.5 * (d2 + ld + dim * LOG2PI), rtol=3e-7)


def test_student_t_nll_at_large_nu_for_odd_dimensions():
    # d = 1: SciPy's t.logpdf at moderate ν (its own gammaln difference is ~eps·ν log ν off: 2e-12
    # at ν = 1e4); d = 3: multivariate_t; the Gaussian at ν ≥ 1e17
    x = np.array([0.0, 1.0, 5.0])
    for nu in (3.0, 59.0, 60.0, 200.0, 1e3):
        got = np.asarray(stats.student_t_nll(jnp.asarray(x * x), 0.0, nu, 1))
        np.testing.assert_allclose(got, -sps.t.logpdf(x, nu), rtol=1e-12)
        pts = np.stack([x, 0.5 * x, -x], 1)
        got3 = np.asarray(stats.student_t_nll(jnp.asarray(np.sum(pts ** 2, 1)), 0.0, nu, 3))
        ref3 = -sps.multivariate_t(loc=np.zeros(3), shape=np.eye(3), df=nu).logpdf(pts)
        np.testing.assert_allclose(got3, ref3, rtol=1e-12)
    for nu in (1e17, 1e300):  # the O(1/ν) correction is below double precision
        for dim in (1, 3):
            got = np.asarray(stats.student_t_nll(jnp.asarray(x * x), 0.0, nu, dim))
            np.testing.assert_allclose(got, 0.5 * (x * x + dim * LOG2PI), rtol=2e-15)


def test_student_t_nll_gradients_at_large_nu_are_finite_and_right():
    ld = 0.3
    f = jax.jit(jax.grad(lambda nu, d2, dim=2: stats.student_t_nll(d2, ld, nu, dim), argnums=(0, 1)))
    for nu in (61.0, 500.0, 1e4):
        for d2 in (0.5, 30.0):
            g_nu, g_d2 = (float(v) for v in f(nu, d2))
            # d = 2 closed form: ∂/∂ν = ½ log1p(d²/ν) − (ν+2) d² / (2 ν (ν + d²)), ∂/∂d² = (ν+2) / (2 (ν + d²))
            assert g_nu == pytest.approx(0.5 * math.log1p(d2 / nu) - (nu + 2) * d2 / (2 * nu * (nu + d2)), rel=1e-9)
            assert g_d2 == pytest.approx((nu + 2) / (2 * (nu + d2)), rel=1e-14)
    # d = 3 on both sides of the switch to Stirling's series (ν = 60): central differences
    nll3 = jax.jit(lambda nu, d2: stats.student_t_nll(d2, ld, nu, 3))
    g3 = jax.jit(jax.grad(lambda nu, d2: stats.student_t_nll(d2, ld, nu, 3), argnums=(0, 1)))
    for nu in (59.0, 60.0, 61.0, 1e3):
        for d2 in (0.0, 2.0):
            h = 1e-3 * nu
            fd_nu = (float(nll3(nu + h, d2)) - float(nll3(nu - h, d2))) / (2 * h)
            hd = 1e-4
            fd_d2 = (float(nll3(nu, d2 + hd)) - float(nll3(nu, max(d2 - hd, 0.0)))) / (hd + min(d2, hd))
            gn, gd = (float(v) for v in g3(nu, d2))
            assert gn == pytest.approx(fd_nu, rel=1e-5, abs=1e-12), (nu, d2)
            assert gd == pytest.approx(fd_d2, rel=1e-4), (nu, d2)
    # the value is continuous where the branch changes
    a, b = float(nll3(60.0 * (1 - 1e-12), 2.0)), float(nll3(60.0, 2.0))
    assert abs(a - b) < 1e-13
    # huge and infinite ν, float32 too: finite gradients
    for nu in (1e17, 1e300, math.inf):
        assert all(np.isfinite(float(v)) for v in f(nu, 1.0))
    g32 = jax.grad(lambda nu, d2: stats.student_t_nll(d2, jnp.float32(ld), nu, 2), argnums=(0, 1))(
        jnp.float32(1e8), jnp.float32(1.0))
    assert all(np.isfinite(float(v)) for v in g32) and float(g32[1]) == pytest.approx(0.5, rel=1e-6)


# ---------------------------------------------------------------------------
# Gradients at zero error (item 15)
# ---------------------------------------------------------------------------

def test_error_metrics_have_finite_gradients_at_zero_error():
    z2 = jnp.zeros((4, 2))
    z3 = jnp.zeros((4, 3))
    line = jnp.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.5]])
    calls = {
        "rmse": (lambda e: jnp.sum(metrics.rmse(e)), z2),
        "rmse_norm": (metrics.rmse_norm, z2),
        "rmse_norm_where": (lambda e: metrics.rmse_norm_where(e, jnp.array([True, True, False, True])), z2),
        "ate none": (lambda e: metrics.ate(e, line, "none"), line),
        "ate rigid": (lambda e: metrics.ate(e, line), line),
        "ate sim": (lambda e: metrics.ate(e, line, "sim"), line),
        # estimate along x, truth along y: an exact rigid fit of a straight (collinear) line
        "ate straight line": (lambda e: metrics.ate(e, line[:3, ::-1]), line[:3]),
        "rpe": (lambda e: metrics.rpe(e, line), line),
        "rpe_se2 trans": (lambda e: metrics.rpe_se2(e, z3)[0], z3),
        "rpe_se2 rot": (lambda e: metrics.rpe_se2(e, z3)[1], z3),
    }
    for name, (fn, x) in calls.items():
        g = np.asarray(jax.grad(fn)(x))
        assert np.all(np.isfinite(g)), name  # was NaN
        if "rigid" not in name and "sim" not in name and "line" not in name:
            # exactly zero error: the zero subgradient (an aligned fit leaves a rounding residual
            # of ~1e-16, whose direction the gradient then follows: finite, not zero)
            np.testing.assert_array_equal(g, 0.0, err_msg=name)
    # values and gradients away from zero are unchanged: NumPy and the closed form e / (T · rmse)
    e = np.array([[3.0, 4.0], [0.0, 1.0], [1.0, -2.0], [0.5, 0.5]])
    r = np.sqrt(np.mean(np.sum(e * e, 1)))
    assert float(metrics.rmse_norm(e)) == r
    np.testing.assert_array_equal(np.asarray(metrics.rmse(e)), np.sqrt(np.mean(e * e, 0)))
    np.testing.assert_allclose(np.asarray(jax.grad(metrics.rmse_norm)(jnp.asarray(e))), e / (4 * r), rtol=1e-14)
    assert np.isnan(float(metrics.rmse_norm(np.array([[np.nan, 0.0]]))))


# ---------------------------------------------------------------------------
# windowed_mean (item 21)
# ---------------------------------------------------------------------------

def test_windowed_mean_refuses_times_and_windows_it_cannot_use():
    x = [1.0, 2.0, 3.0, 4.0]
    for t in ([0, np.nan, 2, 3], [0, 1, 2, np.inf]):  # IndexError / OverflowError before
        with pytest.raises(InputError, match="^t: the times must be finite"):
            metrics.windowed_mean(x, t, 2.0)
    for w in (np.inf, np.nan, "2", -1.0, 0.0, None):  # inf: NaN window starts
        with pytest.raises(InputError, match="^window_s: must be a finite number > 0"):
            metrics.windowed_mean(x, [0, 1, 2, 3], w)
    # 1 µs windows over 10⁶ s: 10¹² windows (7 TiB) asked for
    with pytest.raises(InputError, match=r"^window_s: 1e-06 s splits the 1e\+06 s span of t into 1e\+12 windows"):
        metrics.windowed_mean([1.0, 2.0], [0.0, 1e6], 1e-6)
    with pytest.raises(InputError, match="^x: expected numbers"):
        metrics.windowed_mean(["a"], [0.0], 1.0)
    w = metrics.windowed_mean(x, [0, 1, 2, 3], 2.0)
    np.testing.assert_array_equal(w.mean, [1.5, 3.5])
    np.testing.assert_array_equal(w.t_start, [0.0, 2.0])


# ---------------------------------------------------------------------------
# summarize with an infinite run (item 26)
# ---------------------------------------------------------------------------

def test_summarize_p95_of_an_infinite_run():
    assert metrics.summarize([1.0, np.inf])["p95"] == np.inf  # was NaN (inf − inf in NumPy's lerp)
    assert metrics.summarize([-np.inf, 1.0])["p95"] == -np.inf
    assert np.isnan(metrics.summarize([-np.inf, np.inf])["p95"])
    assert np.isnan(metrics.summarize([1.0, np.nan, np.inf])["p95"])  # NaN still propagates
    rng = np.random.default_rng(0)
    for n in (1, 2, 7, 21, 100):  # finite values: exactly NumPy's
        v = rng.normal(size=n)
        assert metrics.summarize(v)["p95"] == float(np.percentile(v, 95.0))
    with pytest.raises(InputError, match="^per_run: expected numbers"):
        metrics.summarize(["a"])


# ---------------------------------------------------------------------------
# Complex inputs (item 25)
# ---------------------------------------------------------------------------

def test_complex_inputs_are_refused():
    I2 = np.eye(2)
    cases = [
        (lambda: stats.nees(jnp.array([1j, 0]), I2), "^err: expected a real array"),  # gave -1+0j
        (lambda: stats.nees(np.ones(2), I2 * (1 + 1j)), "^cov: expected a real array"),
        (lambda: jax.jit(stats.nees)(jnp.array([1j, 0]), I2), "^err: expected a real array"),
        (lambda: stats.nis(np.ones(2), I2 + 0j), "^S: expected a real array"),
        (lambda: stats.student_t_nll(1.0 + 0j, 0.0, 5.0, 2), "^d2: expected a real array"),
        (lambda: stats.student_t_nll(1.0, 0.0, 5.0 + 1j, 2), "^nu: expected a real array"),
        (lambda: stats.student_t_nll(1.0, 1j, 5.0, 2), "^logdet: expected a real array"),
        (lambda: stats.chi2_ppf(0.5 + 0j, 2), "^p: expected a real array"),
        (lambda: stats.chi2_ppf(0.5, 2 + 1j), "^dof: expected a real array"),
        (lambda: stats.chi2_ppf_np(0.5 + 1j, 2), "^p: expected a real array"),
        (lambda: stats.student_t_d2_ppf_np(0.5, 3 + 1j), "^nu: expected a real array"),
        (lambda: stats.mean_chi2_bounds(3 + 1j, 2), "^dof_total: expected a real array"),
        (lambda: metrics.rmse(jnp.array([[1j]])), "^err: expected a real array"),
        (lambda: metrics.ate(np.ones((3, 2)) * 1j, np.ones((3, 2))), "^est_pos: expected a real array"),
        (lambda: metrics.summarize([1 + 1j]), "^per_run: expected a real array"),
    ]
    for call, needle in cases:
        with pytest.raises(InputError, match=needle):
            call()


def test_bounds_must_be_two_numbers_in_order():
    with pytest.raises(InputError, match=r"^bounds: expected two numbers"):
        metrics.steps_inside([1.0, 2.0], (0.5, 1.5, 2.5))  # was a bare unpacking ValueError
    with pytest.raises(InputError, match=r"^bounds: expected \(lo, hi\) with lo <= hi"):
        metrics.consistency_verdict(1.0, (2.0, 0.5))  # a value between them read "OUTSIDE"
    assert metrics.consistency_verdict(1.0, (0.5, 2.0)) == "ok"
    assert metrics.consistency_verdict(1.0, (np.nan, 2.0)) == "undefined"


def test_map_error_refuses_a_repeated_estimated_id_and_a_bad_transform():
    true_lm, true_ids = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0]]), np.array([1, 2, 3])
    est = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0], [9.0, 9.0]])
    I2, z2 = np.eye(2), np.zeros(2)
    with pytest.raises(InputError, match=r"^est_ids: each id may appear once .* \[2\]"):
        metrics.map_error(est, np.array([1, 2, 3, 2]), true_lm, true_ids, transform=(I2, z2))
    # a repeated id on an unused row (negative id, or a NaN position) is no repeat
    est_nan = est.copy()
    est_nan[3] = np.nan
    me = metrics.map_error(est_nan, np.array([1, 2, 3, 2]), true_lm, true_ids, transform=(I2, z2))
    assert me.rmse == 0.0 and sorted(me.ids.tolist()) == [1, 2, 3]
    for bad, needle in (((I2,), r"^transform: expected \(R, t\)"), ((np.eye(3), z2), r"^transform: expected R \(2, 2\)"),
                        ((I2, z2, np.array([1.0, 2.0])), r"^transform: expected a finite scalar")):
        with pytest.raises(InputError, match=needle):
            metrics.map_error(est[:3], np.array([1, 2, 3]), true_lm, true_ids, transform=bad)
    me = metrics.map_error(est[:3], np.array([1, 2, 3]), true_lm, true_ids, transform=(I2, z2 + 1.0, 2.0))
    # estimates doubled and shifted by 1: errors |x + 1| per landmark, by hand
    want = np.linalg.norm(2 * est[:3] + 1.0 - true_lm, axis=1)
    np.testing.assert_allclose(me.errors, want, rtol=1e-15)


def test_write_tum_refuses_an_empty_trajectory(tmp_path):
    with pytest.raises(InputError, match=r"^t: no poses to write"):
        metrics.write_tum(tmp_path / "e.txt", np.zeros(0), np.zeros((0, 3)))
    assert not (tmp_path / "e.txt").exists()
