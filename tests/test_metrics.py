"""Tests of jaxslam.metrics against NumPy/SciPy oracles and closed forms."""

import json

import jax
import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from jaxslam import metrics
from jaxslam.errors import InputError


# --------------------------------------------------------------------------
# RMSE
# --------------------------------------------------------------------------

def test_rmse_definitions_by_hand():
    err = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0], [1.0, -2.0, 2.0]])
    # per axis: sqrt((9+0+1)/3), sqrt((16+0+4)/3), sqrt((0+4+4)/3)
    np.testing.assert_allclose(np.asarray(metrics.rmse(err)),
                               np.sqrt([10 / 3, 20 / 3, 8 / 3]), rtol=1e-15)
    # norm: sqrt((25 + 4 + 9)/3)
    np.testing.assert_allclose(float(metrics.rmse_norm(err)), np.sqrt(38 / 3), rtol=1e-15)
    np.testing.assert_allclose(float(metrics.rmse_norm(err)) ** 2,
                               float(np.sum(np.asarray(metrics.rmse(err)) ** 2)), rtol=1e-14)
    # batched over runs: (R, T, d) with axis=1
    errs = np.stack([err, 2 * err])
    np.testing.assert_allclose(np.asarray(metrics.rmse_norm(errs, axis=1)),
                               [np.sqrt(38 / 3), 2 * np.sqrt(38 / 3)], rtol=1e-15)
    np.testing.assert_allclose(np.asarray(metrics.rmse(errs, axis=1))[1],
                               2 * np.sqrt([10 / 3, 20 / 3, 8 / 3]), rtol=1e-15)


# --------------------------------------------------------------------------
# NEES / NIS
# --------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_nees_nis_against_numpy(dtype):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(7, 5, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(4)
    e = rng.normal(size=(7, 5, 4))
    ref = np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])
    got = jax.jit(metrics.nees)(e.astype(dtype), P.astype(dtype))
    assert got.shape == (7, 5) and got.dtype == dtype
    tol = 1e-4 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(np.asarray(got), ref, rtol=tol)
    # Broadcasting one covariance over many errors; nis is the same statistic.
    got = metrics.nis(e.astype(dtype), P[0, 0].astype(dtype))
    ref = np.einsum("...i,...i->...", e, e @ np.linalg.inv(P[0, 0]).T)
    np.testing.assert_allclose(np.asarray(got), ref, rtol=tol)


def test_nees_not_pd_is_nan():
    assert np.isnan(float(metrics.nees(np.ones(2), -np.eye(2))))


# --------------------------------------------------------------------------
# Chi-square quantiles
# --------------------------------------------------------------------------

DOFS = np.array([1, 2, 3, 4, 6, 10, 25, 60, 150, 400, 1000, 3000, 10_000, 30_000, 100_000])
PS = np.array([1e-8, 1e-4, 0.005, 0.025, 0.05, 0.3, 0.5, 0.7, 0.95, 0.975, 0.995, 1 - 1e-6])


def test_chi2_ppf_matches_scipy_float64():
    P, K = np.meshgrid(PS, DOFS)
    rng = np.random.default_rng(1)
    # Random probabilities and non-integer dof, including dof < 1.
    pr = rng.uniform(1e-6, 1 - 1e-6, 500)
    kr = 10 ** rng.uniform(-1, 5, 500)
    edges_p = np.array([0.0, 1.0, -0.1, 1.1, 0.5])
    edges_k = np.array([3.0, 3.0, 3.0, 3.0, 0.0])
    p = np.concatenate([P.ravel(), pr, edges_p])
    k = np.concatenate([K.ravel(), kr, edges_k])
    got = np.asarray(jax.jit(metrics.chi2_ppf)(p, k))  # one compilation
    n = P.size + pr.size
    np.testing.assert_allclose(got[:n], stats.chi2.ppf(p[:n], k[:n]), rtol=1e-9)
    ed = got[n:]
    assert ed[0] == 0 and ed[1] == np.inf and np.all(np.isnan(ed[2:]))


def test_chi2_ppf_float32():
    P, K = np.meshgrid(PS[1:-1], DOFS)
    got = jax.jit(metrics.chi2_ppf)(P.astype(np.float32), K.astype(np.int32))
    assert got.dtype == np.float32 and np.all(np.isfinite(got))
    # float32 regularised incomplete gamma limits the accuracy at large dof.
    np.testing.assert_allclose(np.asarray(got), stats.chi2.ppf(P, K), rtol=5e-4)


def test_chi2_ppf_np_matches_scipy():
    for k in (1, 2, 5, 37, 800, 12_345, 100_000):
        for p in (1e-6, 0.025, 0.5, 0.975, 1 - 1e-6):
            assert metrics.chi2_ppf_np(p, k) == pytest.approx(stats.chi2.ppf(p, k), rel=1e-10)
    assert metrics.chi2_ppf_np(0.0, 3) == 0.0 and metrics.chi2_ppf_np(1.0, 3) == np.inf
    with pytest.raises(InputError):
        metrics.chi2_ppf_np(1.5, 3)


def test_bounds_against_scipy():
    for n, N in [(3, 1), (4, 50), (9, 200), (15, 1000)]:
        lo, hi = metrics.anees_bounds(n, N)
        assert isinstance(lo, float) and isinstance(hi, float)
        np.testing.assert_allclose(
            (lo, hi), (stats.chi2.ppf(0.025, n * N) / N, stats.chi2.ppf(0.975, n * N) / N),
            rtol=1e-10)
    lo, hi = metrics.mean_chi2_bounds(5000, 1800, alpha=0.01)
    np.testing.assert_allclose(
        (lo, hi), (stats.chi2.ppf(0.005, 5000) / 1800, stats.chi2.ppf(0.995, 5000) / 1800),
        rtol=1e-10)
    with pytest.raises(InputError, match="n_runs"):
        metrics.anees_bounds(3, 0)
    with pytest.raises(InputError, match="alpha"):
        metrics.mean_chi2_bounds(3, 2, alpha=1.5)


# --------------------------------------------------------------------------
# Windows and summaries
# --------------------------------------------------------------------------

def test_windowed_mean_against_loop():
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.05, 0.15, 103))
    x = rng.normal(size=(4, 103))
    x[1, 7] = np.nan  # a missing value is excluded, not zero
    w = metrics.windowed_mean(x, t, 2.0)
    t0 = t[0]
    n_win = int(np.ceil((t[-1] - t0) / 2.0))
    assert w.mean.shape == (n_win,)
    for k in range(n_win):
        sel = (t >= t0 + 2 * k) & ((t < t0 + 2 * (k + 1)) | (k == n_win - 1))
        vals = x[:, sel].ravel()
        vals = vals[np.isfinite(vals)]
        assert w.count[k] == vals.size
        np.testing.assert_allclose(w.mean[k], vals.mean(), rtol=1e-13)
        assert w.t_start[k] == pytest.approx(t0 + 2 * k)
    assert w.count.sum() == x.size - 1
    # 1-D input and a single window.
    w1 = metrics.windowed_mean(x[0], t, 1e3)
    np.testing.assert_allclose(w1.mean, [x[0].mean()], rtol=1e-13)
    with pytest.raises(InputError, match="t"):
        metrics.windowed_mean(x, t[:-1], 1.0)
    with pytest.raises(InputError, match="window_s"):
        metrics.windowed_mean(x, t, 0.0)


def test_summarize_is_json_ready():
    v = np.array([3.0, 1.0, 2.0, 10.0, 4.0])
    s = metrics.summarize(v)
    assert set(s) == {"mean", "median", "p95", "max", "per_run"}
    assert s["mean"] == 4.0 and s["median"] == 3.0 and s["max"] == 10.0
    assert s["p95"] == pytest.approx(np.percentile(v, 95))
    assert s["per_run"] == [3.0, 1.0, 2.0, 10.0, 4.0]
    assert json.loads(json.dumps(s)) == s
    assert all(type(s[k]) is float for k in ("mean", "median", "p95", "max"))
    assert np.isnan(metrics.summarize([1.0, np.nan])["mean"])


# --------------------------------------------------------------------------
# Alignment, ATE, RPE
# --------------------------------------------------------------------------

def test_umeyama_recovers_similarity_and_ate():
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(50, 3)) * 5
    Rt = Rotation.from_rotvec([0.3, -0.8, 1.2]).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    est = (truth - t) @ Rt / 1.7  # truth = 1.7 R est + t
    R, tt, s = metrics.umeyama(est, truth, with_scale=True)
    np.testing.assert_allclose(np.asarray(R), Rt, atol=1e-12)
    np.testing.assert_allclose(np.asarray(tt), t, atol=1e-12)
    np.testing.assert_allclose(float(s), 1.7, rtol=1e-12)
    assert float(metrics.ate(est, truth, align="sim")) < 1e-12
    # Rigid alignment of a rigidly moved, noisy trajectory: ATE equals the
    # RMSE of the noise after the least-squares fit, below the raw noise RMSE.
    noise = 0.01 * rng.normal(size=truth.shape)
    est2 = (truth + noise - t) @ Rt
    ate = float(metrics.ate(est2, truth))
    assert 0.8 * np.sqrt(np.mean(np.sum(noise**2, 1))) < ate
    assert ate <= np.sqrt(np.mean(np.sum(noise**2, 1)))
    assert float(metrics.ate(est2, truth, align="none")) > 1.0
    # Reflection guard: a mirrored point set still yields a proper rotation.
    R2, _, _ = metrics.umeyama(truth * np.array([1, 1, -1]), truth)
    assert np.linalg.det(np.asarray(R2)) == pytest.approx(1.0)


@pytest.mark.parametrize("align", ["rigid", "sim"])
def test_ate_gradient_matches_central_differences_and_is_finite_without_spread(align):
    """The alignment is held fixed in the gradient (envelope theorem): central differences of
    the ATE itself are the oracle, on a 3-D trajectory, a flat one (no z spread) and a noisy
    estimate of a straight line (the optimal rotation is then any one about the line, and the
    gradient is still unique); an estimate that never moved had a NaN gradient (the SVD's
    derivative at repeated zero singular values) and now has a finite one.  (An exactly
    straight *estimate* is a kink of the ATE: there central differences average two slopes.)"""
    rng = np.random.default_rng(5)
    tt = np.linspace(0.0, 3.0, 12)
    helix = np.c_[np.cos(tt), np.sin(2 * tt), 0.3 * tt]
    flat = helix * np.array([1.0, 1.0, 0.0])
    line = np.c_[tt, 2 * tt, np.ones_like(tt)]
    f = jax.jit(metrics.ate, static_argnums=2)
    g = jax.jit(jax.grad(metrics.ate), static_argnums=2)
    h = 1e-6
    for est, tru in ((helix + 0.05 * rng.normal(size=helix.shape), helix),
                     (flat + 0.05 * rng.normal(size=flat.shape), flat),
                     (line + 0.05 * rng.normal(size=line.shape), line)):
        an = np.asarray(g(est, tru, align))
        fd = np.zeros_like(est)
        for i in range(est.shape[0]):
            for j in range(3):
                ep, em = est.copy(), est.copy()
                ep[i, j] += h
                em[i, j] -= h
                fd[i, j] = (float(f(ep, tru, align)) - float(f(em, tru, align))) / (2 * h)
        assert np.max(np.abs(an - fd)) <= 1e-6 * np.max(np.abs(fd))
    still = np.ones_like(line)
    assert np.all(np.isfinite(np.asarray(g(still, line, align))))
    assert np.all(np.isfinite(np.asarray(jax.grad(metrics.ate, argnums=1)(line, still, align))))


def test_rpe_by_hand():
    truth = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    est = truth + np.array([[5.0, 5.0], [5.0, 5.0], [5.5, 5.0], [5.5, 5.0]])
    # lag 1 displacement errors: 0, 0.5, 0 -> sqrt(0.25/3)
    assert float(metrics.rpe(est, truth)) == pytest.approx(np.sqrt(0.25 / 3))
    # lag 2: 0.5, 0.5 -> 0.5
    assert float(metrics.rpe(est, truth, lag=2)) == pytest.approx(0.5)
    with pytest.raises(InputError, match="lag"):
        metrics.rpe(est, truth, lag=4)
    with pytest.raises(InputError, match="align"):
        metrics.ate(est, truth, align="affine")


def _se2_align_closed_form(src, dst):
    """Independent 2D oracle: θ = atan2(Σ a×b, Σ a·b) on centred points, then t."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    th = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    return R, md - R @ ms


def test_se2_ate_matches_closed_form_oracle():
    rng = np.random.default_rng(7)
    s = np.linspace(0, 6 * np.pi, 300)
    truth = np.stack([4 * np.cos(s) + 0.3 * s, 2 * np.sin(2 * s)], 1)
    th, t = 2.4, np.array([-3.0, 7.5])  # beyond ±π/2, where a small-angle fit would fail
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    est = (truth + 0.05 * rng.normal(size=truth.shape)) @ R.T + t
    Ro, to = _se2_align_closed_form(est, truth)
    expected = np.sqrt(np.mean(np.sum((est @ Ro.T + to - truth) ** 2, 1)))
    assert float(metrics.ate(est, truth)) == pytest.approx(expected, rel=1e-10)
    Ru, tu, _ = metrics.umeyama(est, truth)
    np.testing.assert_allclose(np.asarray(Ru), Ro, atol=1e-12)
    np.testing.assert_allclose(np.asarray(tu), to, atol=1e-10)


def test_rpe_se2_by_hand_and_invariance():
    truth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, np.pi / 2], [2.0, 1.0, np.pi / 2]])
    assert [float(v) for v in metrics.rpe_se2(truth, truth)] == pytest.approx([0.0, 0.0], abs=1e-15)
    # Same trajectory moved rigidly: no relative error.
    c, s = np.cos(1.0), np.sin(1.0)
    moved = np.stack([c * truth[:, 0] - s * truth[:, 1] + 3, s * truth[:, 0] + c * truth[:, 1] - 1,
                      truth[:, 2] + 1.0], 1)
    assert [float(v) for v in metrics.rpe_se2(moved, truth)] == pytest.approx([0.0, 0.0], abs=1e-12)
    # One step too long by 0.3 m (the 2nd → 3rd, along x while heading 0): translation errors
    # of the three relative motions are 0, 0.3, 0 → RMSE 0.3/√3; a wrong turn at the last
    # pose, by 3.2 rad (wraps to 3.2 − 2π), gives an angle RMSE of |3.2 − 2π|/√3.
    est = truth.copy()
    est[2:, 0] += 0.3
    est[3, 2] += 3.2
    tr, rot = metrics.rpe_se2(est, truth)
    assert float(tr) == pytest.approx(0.3 / np.sqrt(3))
    assert float(rot) == pytest.approx(abs(3.2 - 2 * np.pi) / np.sqrt(3))
    with pytest.raises(InputError, match="lag"):
        metrics.rpe_se2(est, truth, lag=4)


def test_map_error_by_id_with_both_alignments():
    true_lm = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 3.0], [5.0, 5.0]])
    true_ids = np.array([10, 11, 12, 13])
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    est = (true_lm[[2, 0, 1]] - np.array([1.0, 2.0])) @ R  # ids 12, 10, 11 in another frame
    est_ids = np.array([12, 10, 11])
    me = metrics.map_error(np.vstack([est, [[np.nan, 0.0]]]), np.append(est_ids, 13), true_lm, true_ids)
    assert me.rmse == pytest.approx(0.0, abs=1e-12) and sorted(me.ids.tolist()) == [10, 11, 12]
    # A given transform (identity) is used as is: every error is that of the raw estimate.
    me2 = metrics.map_error(est, est_ids, true_lm, true_ids, transform=(np.eye(2), np.zeros(2)))
    np.testing.assert_allclose(me2.errors, np.linalg.norm(est - true_lm[[2, 0, 1]], axis=1))
    with pytest.raises(InputError, match="no estimated landmark"):
        metrics.map_error(est, np.array([1, 2, 3]), true_lm, true_ids)
    # A true id listed twice has no single truth: named, not resolved to the last row.
    with pytest.raises(InputError, match=r"true_ids: .*repeated: \[11\]"):
        metrics.map_error(est, est_ids, true_lm, np.array([10, 11, 12, 11]))


def test_sim_alignment_of_an_estimate_without_spread_is_finite():
    """An estimate that never moved has no scale; the similarity alignment maps it onto the
    truth's mean (any scale does), so its ATE is the truth's spread about its mean, not NaN."""
    truth = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    est = np.ones((4, 2))
    R, t, s = metrics.umeyama(est, truth, with_scale=True)
    assert np.isfinite(float(s)) and np.all(np.isfinite(np.asarray(t)))
    spread = np.sqrt(np.mean(np.sum((truth - truth.mean(0)) ** 2, axis=1)))
    assert float(metrics.ate(est, truth, align="sim")) == pytest.approx(spread, rel=1e-12)


def test_interp_poses_wraps_heading_and_refuses_extrapolation():
    t = np.array([0.0, 1.0])
    P = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, 4.0, -np.pi + 0.1]])
    out = metrics.interp_poses(np.array([0.5, -0.1, 1.1]), t, P)
    np.testing.assert_allclose(out[0, :2], [1.0, 2.0])
    assert abs(abs(out[0, 2]) - np.pi) < 1e-12  # through ±π, not through 0
    assert np.all(np.isnan(out[1:]))
    # times that go backwards would make np.interp return wrong poses: refused, as are shapes
    # that do not pair one pose with one time
    with pytest.raises(InputError, match="t: the pose times must be finite and non-decreasing"):
        metrics.interp_poses(np.array([0.5]), np.array([1.0, 0.0]), P)
    with pytest.raises(InputError, match="poses: expected one"):
        metrics.interp_poses(np.array([0.5]), t, P[:1])
    with pytest.raises(InputError, match="t_query and t"):
        metrics.interp_poses(np.array([[0.5]]), t, P)


def test_tum_round_trip(tmp_path):
    t = np.array([0.0, 0.5, 1.25])
    xy = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0]])
    yaw = np.array([0.0, np.pi / 2, -3.0])
    path = metrics.write_tum(tmp_path / "sub" / "traj.txt", t, xy, yaw=yaw)
    tt, p, q = metrics.read_tum(path)
    np.testing.assert_allclose(tt, t)
    np.testing.assert_allclose(p, np.c_[xy, np.zeros(3)])
    np.testing.assert_allclose(2 * np.arctan2(q[:, 2], q[:, 3]), yaw, atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-8)
    with pytest.raises(InputError, match="positions"):
        metrics.write_tum(tmp_path / "x.txt", t, xy[:2])


def test_trajectory_metrics_name_mismatched_or_transposed_inputs():
    rng = np.random.default_rng(3)
    tru = rng.normal(size=(10, 3))
    est = tru + 0.01 * rng.normal(size=(10, 3))
    ok = float(metrics.ate(est, tru))
    assert 0 < ok < 0.05
    cases = [
        (lambda: metrics.ate(est[:9], tru), r"^est_pos and true_pos: the same \(T, d\) shape expected"),
        (lambda: metrics.rpe(est, tru[:8]), r"^est_pos and true_pos: the same \(T, d\) shape expected"),
        (lambda: metrics.ate(est[:, :2], tru), r"^est_pos and true_pos: the same"),
        # a transposed (3, T) pair used to return a plausible number
        (lambda: metrics.ate(est.T, tru.T), r"^est_pos: expected shape \(T, d\) with d in 1..3"),
        (lambda: metrics.ate(est[:1], tru, align="none"), r"^est_pos and true_pos: the same"),
        (lambda: metrics.ate(est[:, 0], tru[:, 0]), r"^est_pos: expected shape \(T, d\)"),
        (lambda: metrics.rpe(est, tru, lag=1.7), r"^lag: must be an int"),
        (lambda: metrics.steps_inside([1.0, 2.0], (3.0, 1.0)), r"^bounds: expected \(lo, hi\) with lo <= hi"),
        (lambda: metrics.consistency_verdict(1.0, (0.5, 2.0), kind="foo"), r"^kind: expected one of"),
    ]
    for call, msg in cases:
        with pytest.raises(InputError, match=msg):
            call()
    assert metrics.consistency_verdict(1.0, (0.5, 2.0), kind=None) == "ok"
    assert np.isnan(metrics.steps_inside([1.0, 2.0], (np.nan, 3.0)))  # no bounds: no verdict, no error
    assert metrics.steps_inside_text(metrics.steps_inside([1.0], (np.nan, 3.0))) == "undefined"


def test_review_fixes_of_2026_12_07():
    """Four defects a review reproduced, each against a closed form."""
    # 1-D similarity alignment of a mirrored estimate: the best s >= 0 is 0 (the quadratic in s
    # has its minimum below 0), so the ATE is the spread of the truth, not 0 (s = -1 mirrored it).
    tru = np.array([[0.0], [1.0], [3.0], [7.0], [2.0]])
    est = -tru + 4.0
    R, t, s = metrics.umeyama(est, tru, with_scale=True)
    assert float(s) == 0.0
    assert float(metrics.ate(est, tru, align="sim")) == pytest.approx(np.std(tru), rel=1e-12)
    # windowed_mean: NaN is a missing value, an inf (a diverged run) is kept, as summarize keeps it
    x = np.array([[1.0, np.nan, np.inf, 3.0]])
    w = metrics.windowed_mean(x, np.array([0.0, 0.1, 0.2, 0.3]), 1.0)
    assert np.isinf(w.mean[0]) and int(w.count[0]) == 3
    w = metrics.windowed_mean(np.array([[1.0, np.nan, 2.0, 3.0]]), np.array([0.0, 0.1, 0.2, 0.3]), 1.0)
    assert w.mean[0] == 2.0 and int(w.count[0]) == 3
    # three bounds are a bad input, as in steps_inside, not a missing value
    with pytest.raises(InputError, match="bounds: expected two numbers"):
        metrics.consistency_verdict(1.0, (0.0, 2.0, 5.0))
    with pytest.raises(InputError, match="bounds: expected two numbers"):
        metrics.steps_inside(np.ones(3), (0.0, 2.0, 5.0))
    assert metrics.consistency_verdict(1.0, (0.0, np.nan)) == "undefined"
    # an infinite dof has no quantile (chi2_ppf gives NaN there)
    with pytest.raises(InputError, match="finite dof"):
        metrics.chi2_ppf_np(0.5, np.inf)
