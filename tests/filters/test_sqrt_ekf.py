"""Tests of the square-root EKF (jaxslam.filters.sqrt_ekf).

Oracles, independent of the code under test:

* a closed-form linear Kalman filter written here in NumPy (float64), with masked
  components dropped from the update and an NIS gate;
* the covariance-form EKF (:mod:`jaxslam.filters.ekf`) on nonlinear models (unicycle
  motion, range-bearing measurements), comparing ``L Lᵀ`` with ``P``;
* a float64 run of the square-root filter as the reference of the float32 long run, where
  the float32 covariance form is shown to fail on the same inputs;
* SciPy chi-square quantiles for the gates, NumPy ``slogdet`` for the log-determinant.

float32 paths get float32 arrays explicitly (the conftest enables x64 for the tests only).
"""

import functools
import time

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf
from jaxslam.filters import sqrt_ekf as se
from jaxslam.sensors import range_bearing2d as rb

from cv_model import DT, F_CV, G_CV, H_CV, P0_CV, Q_CV, R_CV, X0_CV  # noqa: F401
T_CV = 80
GATE_P = 0.99


def f_cv(x, u):
    return jnp.asarray(F_CV, x.dtype) @ x + jnp.asarray(G_CV, x.dtype) @ u


def h_pos(x):
    return x[:2]


def assert_close(a, b, tol):
    """|a − b| ≤ tol · max(1, max|b|), entrywise."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    scale = max(1.0, float(np.max(np.abs(b))))
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * scale)


def covs_of(chols):
    L = np.asarray(chols, np.float64)
    return np.einsum("...ij,...kj->...ik", L, L)


# --------------------------------------------------------------------------
# NumPy oracle and data
# --------------------------------------------------------------------------

def np_kf(x0, P0, us, zs, masks=None, gate=None, predict_first=True):
    """Closed-form Kalman filter (float64); masked components dropped; NIS gate."""
    x, P = x0.astype(float).copy(), P0.astype(float).copy()
    means, covs, nis_all, gated_all = [], [], [], []
    for t in range(zs.shape[0]):
        def upd(x, P, t=t):
            mk = np.ones(zs.shape[1], bool) if masks is None else masks[t]
            if not mk.any():
                return x, P, 0.0, False
            Hs, Rs, zv = H_CV[mk], R_CV[np.ix_(mk, mk)], zs[t][mk]
            S = Hs @ P @ Hs.T + Rs
            nu = zv - Hs @ x
            nis = float(nu @ np.linalg.solve(S, nu))
            thr = None if gate is None else (gate(int(mk.sum())) if callable(gate) else gate)
            if thr is not None and nis > thr:
                return x, P, nis, True
            K = np.linalg.solve(S, Hs @ P).T
            A = np.eye(len(x)) - K @ Hs
            return x + K @ nu, A @ P @ A.T + K @ Rs @ K.T, nis, False

        if predict_first:
            x, P = F_CV @ x + G_CV @ us[t], F_CV @ P @ F_CV.T + Q_CV
            x, P, nis, g = upd(x, P)
            means.append(x), covs.append(P)
        else:
            x, P, nis, g = upd(x, P)
            means.append(x), covs.append(P)
            x, P = F_CV @ x + G_CV @ us[t], F_CV @ P @ F_CV.T + Q_CV
        nis_all.append(nis), gated_all.append(g)
    return np.array(means), np.array(covs), np.array(nis_all), np.array(gated_all)


def simulate_cv(seed, T=T_CV):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 2)) * 0.3
    x = X0_CV + rng.multivariate_normal(np.zeros(4), P0_CV)
    Lq, Lr = np.linalg.cholesky(Q_CV), np.linalg.cholesky(R_CV)
    zs = []
    for t in range(T):
        x = F_CV @ x + G_CV @ us[t] + Lq @ rng.normal(size=4)
        zs.append(H_CV @ x + Lr @ rng.normal(size=2))
    return us, np.array(zs)


@functools.cache
def cv_runner(predict_first=True, callable_gate=False):
    """One jitted square-root CV filter per static option set (masks, numeric gate traced)."""
    gfun = ekf.chi2_gate(GATE_P, 2) if callable_gate else None

    @jax.jit
    def run(x0, P0, us, zs, masks, gate):
        return se.filter_scan(f_cv, h_pos, x0, P0, us, zs, masks, Q_CV, R_CV,
                              gate=gfun if callable_gate else gate, save_chol=True,
                              predict_first=predict_first)

    return run


# --------------------------------------------------------------------------
# Linear-Gaussian model: equals the closed-form Kalman filter
# --------------------------------------------------------------------------

def _cv_case(case, seed):
    us, zs = simulate_cv(seed)
    masks = np.ones(zs.shape, bool)
    if case in ("masked", "masked_gated"):
        rng = np.random.default_rng(seed + 100)
        masks = rng.random(zs.shape) > 0.35
        masks[5] = False  # a step with nothing valid
        zs = np.where(masks, zs, np.nan)  # garbage where invalid: must not leak
    if case in ("gated", "masked_gated"):
        zs = zs.copy()
        zs[[10, 31, 57]] += 8.0  # outliers, far beyond the 99 % gate
        masks[[10, 31, 57], 0] = True
        zs[[10, 31, 57], 0] = simulate_cv(seed)[1][[10, 31, 57], 0] + 8.0
    return us, zs, masks


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("case, predict_first", [
    ("plain", True), ("plain", False), ("masked", True), ("gated", True), ("masked_gated", True),
])
def test_linear_model_equals_numpy_kalman_filter(case, predict_first, dtype):
    us, zs, masks = _cv_case(case, seed=1)
    gated_case = "gated" in case
    thr = stats.chi2.ppf(GATE_P, 2) if gated_case else np.inf
    run = cv_runner(predict_first, callable_gate=(case == "masked_gated"))
    post = run(X0_CV.astype(dtype), P0_CV.astype(dtype), us.astype(dtype), zs.astype(dtype),
               masks, dtype(thr))

    gate = None
    if case == "gated":
        gate = thr
    elif case == "masked_gated":
        gate = lambda d: stats.chi2.ppf(GATE_P, d)
    ref_m, ref_P, ref_nis, ref_gated = np_kf(X0_CV, P0_CV, us, zs, masks, gate, predict_first)

    assert post.means.dtype == dtype and post.chols.dtype == dtype and post.nis.dtype == dtype
    L = np.asarray(post.chols)
    assert np.all(np.triu(L, 1) == 0) and np.all(np.diagonal(L, 0, 1, 2) > 0)
    tol = 1e-10 if dtype == np.float64 else 1e-4
    assert_close(post.means, ref_m, tol)
    assert_close(covs_of(post.chols), ref_P, tol)
    assert_close(post.cov_diags, np.diagonal(ref_P, 0, 1, 2), tol)
    np.testing.assert_allclose(np.asarray(post.nis), ref_nis, rtol=10 * tol, atol=10 * tol)
    np.testing.assert_array_equal(np.asarray(post.dof), masks.sum(1))
    status = np.asarray(post.status)
    np.testing.assert_array_equal((status & errors.GATED) != 0, ref_gated)
    assert np.all((status & ~errors.GATED) == 0)
    if gated_case:
        assert ref_gated.sum() >= 3  # the outliers were rejected (and nothing else broke)
    assert_close(covs_of(post.final.chol), ref_P[-1], tol)  # the last filtered estimate


# --------------------------------------------------------------------------
# Nonlinear model: equals the covariance-form EKF
# --------------------------------------------------------------------------

LANDMARKS = np.array([[4.0, 1.0], [-2.0, 5.0], [1.0, -3.0]])
R_RB = np.diag([0.05**2, 0.02**2])
Q_UNI = np.diag([0.02**2, 0.01**2])  # speed, yaw-rate noise entering through G


def f_uni(x, u):
    v, w = u[0], u[1]
    return x + DT * jnp.stack([v * jnp.cos(x[2]), v * jnp.sin(x[2]), w])


def g_uni(x, u):
    c, s = jnp.cos(x[2]), jnp.sin(x[2])
    z = jnp.zeros((), x.dtype)
    return DT * jnp.stack([jnp.stack([c, z]), jnp.stack([s, z]), jnp.stack([z, jnp.ones((), x.dtype)])])


def h_rb(x, lm):
    return rb.observe(x, lm)


def h_rb_all(x):
    return jnp.concatenate([rb.observe(x, jnp.asarray(lm, x.dtype)) for lm in LANDMARKS])


RES_ALL = ekf.angle_residual([False, True] * len(LANDMARKS))


@functools.cache
def step_pair():
    """Both filters' predict + update on a batch of states (vmapped, one compile per dtype)."""

    def one(x, A, u, z, lm, mask, gate):
        P = A @ A.T + 0.01 * jnp.eye(3, dtype=x.dtype)
        g = ekf.Gaussian(x, P)
        s = se.from_gaussian(g)
        gp = ekf.predict(g, f_uni, u, Q_UNI, noise_jac=g_uni)
        sp = se.predict(s, f_uni, u, Q_UNI, noise_jac=g_uni)
        gp2 = ekf.predict(g, f_uni, u, 1e-3 * jnp.eye(3, dtype=x.dtype))
        sp2 = se.predict(s, f_uni, u, 1e-3 * jnp.eye(3, dtype=x.dtype))
        gu, gi = ekf.update(gp, z, h_rb, R_RB, lm, residual=rb.residual, mask=mask, gate=gate)
        su, si = se.update(sp, z, h_rb, R_RB, lm, residual=rb.residual, mask=mask, gate=gate)
        return (gp, sp, gp2, sp2, gu, gi, su, si)

    return jax.jit(jax.vmap(one))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_nonlinear_steps_equal_covariance_form(dtype):
    B = 64
    rng = np.random.default_rng(3)
    x = np.column_stack([rng.normal(size=(B, 2)) * 2, rng.uniform(-np.pi, np.pi, B)])
    A = rng.normal(size=(B, 3, 3)) * 0.3
    u = np.column_stack([rng.uniform(0.5, 2.0, B), rng.normal(size=B) * 0.3])
    lm = LANDMARKS[rng.integers(0, 3, B)] + 5.0
    z = np.stack([np.asarray(rb.observe(jnp.asarray(xi), jnp.asarray(li))) for xi, li in zip(x, lm)])
    z = z + rng.normal(size=z.shape) * [0.3, 0.05]  # innovations of a few σ: some gated
    z[:, 1] = (z[:, 1] + np.pi) % (2 * np.pi) - np.pi
    mask = rng.random((B, 2)) > 0.25
    z = np.where(mask, z, np.nan)
    gate = np.full(B, stats.chi2.ppf(0.95, 2))
    gate[: B // 2] = np.inf  # half ungated: more accepted updates to compare
    c = lambda a: np.asarray(a, dtype)
    gp, sp, gp2, sp2, gu, gi, su, si = step_pair()(c(x), c(A), c(u), c(z), c(lm), mask, c(gate))

    tol = 1e-10 if dtype == np.float64 else 1e-4
    for g, s in [(gp, sp), (gp2, sp2), (gu, su)]:
        assert s.mean.dtype == dtype and s.chol.dtype == dtype
        assert_close(s.mean, g.mean, tol)
        assert_close(covs_of(s.chol), g.cov, tol)
    for name in ("dof", "accepted", "status"):
        np.testing.assert_array_equal(np.asarray(getattr(si, name)), np.asarray(getattr(gi, name)))
    acc = np.asarray(gi.accepted)
    assert 10 < acc.sum() < B  # some accepted, some gated or with nothing valid
    assert np.any(np.asarray(gi.status) & errors.GATED)
    np.testing.assert_allclose(np.asarray(si.nis), np.asarray(gi.nis), rtol=10 * tol, atol=tol)
    assert_close(si.innovation, gi.innovation, tol)
    assert_close(si.S, gi.S, tol)
    L = np.asarray(su.chol)
    assert np.all(np.triu(L, 1) == 0) and np.all(np.diagonal(L, 0, 1, 2) >= 0)


@functools.cache
def rb_runners():
    gate = ekf.chi2_gate(0.999, 2 * len(LANDMARKS))
    kw = {"residual": RES_ALL, "gate": gate, "noise_jac": g_uni}
    run_c = jax.jit(lambda x0, P0, us, zs, mk: ekf.filter_scan(
        f_uni, h_rb_all, x0, P0, us, zs, mk, Q_UNI, np.kron(np.eye(3), R_RB), **kw))
    run_s = jax.jit(lambda x0, P0, us, zs, mk: se.filter_scan(
        f_uni, h_rb_all, x0, P0, us, zs, mk, Q_UNI, np.kron(np.eye(3), R_RB), **kw))
    return run_c, run_s


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_nonlinear_scan_equals_covariance_form(dtype):
    """Unicycle + range-bearing to 3 landmarks, masks, angle residuals, a callable gate."""
    T = 150
    rng = np.random.default_rng(4)
    us = np.column_stack([1.0 + 0.2 * np.sin(np.arange(T) / 10), 0.3 * np.cos(np.arange(T) / 17)])
    x = np.array([0.0, 0.0, 0.2])
    zs = []
    for t in range(T):
        x = np.asarray(f_uni(jnp.asarray(x), jnp.asarray(us[t])))
        x = x + np.array([0.002, 0.002, 0.001]) * rng.normal(size=3)
        zs.append(np.asarray(h_rb_all(jnp.asarray(x))) + np.tile([0.05, 0.02], 3) * rng.normal(size=6))
    zs = np.array(zs)
    masks = np.repeat(rng.random((T, 3)) > 0.3, 2, axis=1)
    zs[40, 0] += 3.0  # one gross range outlier, gated
    masks[40, :2] = True
    x0 = np.array([0.05, -0.05, 0.25])
    P0 = np.diag([0.1, 0.1, 0.05])
    run_c, run_s = rb_runners()
    c = lambda a: np.asarray(a, dtype)
    pc = run_c(c(x0), c(P0), c(us), c(zs), masks)
    ps = run_s(c(x0), c(P0), c(us), c(zs), masks)
    tol = 1e-9 if dtype == np.float64 else 1e-4
    assert ps.means.dtype == dtype
    assert_close(ps.means, pc.means, tol)
    np.testing.assert_allclose(np.asarray(ps.cov_diags), np.asarray(pc.cov_diags), rtol=10 * tol)
    np.testing.assert_array_equal(np.asarray(ps.status), np.asarray(pc.status))
    assert np.asarray(ps.status)[40] & errors.GATED
    np.testing.assert_allclose(np.asarray(ps.nis), np.asarray(pc.nis), rtol=10 * tol, atol=tol)
    assert_close(covs_of(ps.final.chol), pc.final.cov, tol)


# --------------------------------------------------------------------------
# The float32 long run where the covariance form fails
# --------------------------------------------------------------------------

# Two random-walk states (a, b), one very precise sensor of z = a + C_LR b.  The
# combination orthogonal to (1, C_LR) is unobservable and keeps its prior variance
# (~P0_LR); the measured one is known to ~R_LR: the covariance's eigenvalues span ~10⁹.
T_LR = 100_000
P0_LR = 100.0  # prior variance of a and b (σ = 10)
Q_LR = 1e-8  # random-walk variance per step, both states
R_LR = 1e-6  # sensor variance (σ = 1e-3)
C_LR = 0.7
H_LR = np.array([1.0, C_LR])


def f_rw(x, u):
    return x


def h_lr(x):
    return x[:1] + C_LR * x[1:]


@functools.cache
def long_runners():
    def args(zs):
        dt = zs.dtype
        return (jnp.zeros(2, dt), P0_LR * jnp.eye(2, dtype=dt), None, zs, None,
                Q_LR * jnp.eye(2, dtype=dt), jnp.full((1, 1), R_LR, dt))

    run_c = jax.jit(lambda zs: ekf.filter_scan(f_rw, h_lr, *args(zs), save_cov=True))
    run_s = jax.jit(lambda zs: se.filter_scan(f_rw, h_lr, *args(zs), save_chol=True))
    return run_c, run_s


def test_float32_long_poorly_observable_run_stays_pd():
    """10⁵ float32 steps (one jitted scan each): the covariance form loses definiteness,
    the square-root form stays positive definite and close to a float64 reference.

    The covariance trajectory of this linear model does not depend on the data, only on
    (P0, Q, R, C) and on the arithmetic.  Stored in float32, the covariance holds entries
    ~50 while the measured combination has variance ~1e-8 (condition number ~1e9): the
    rounding of its entries (u·50 ≈ 3e-6) exceeds R, so the covariance form's posterior
    comes out indefinite at the first update, the next innovation covariance is negative
    (NOT_PSD, update rejected), and the random-walk noise Q = 1e-8 (below u·100) rounds
    away, so it never recovers: the estimate of the measured combination stops following
    the data.  The square-root factor has entries ~10 and ~1e-4 and carries the range.

    Bounds (set from the design):

    * covariance form: NOT_PSD and a negative eigenvalue on > 90 % of the steps, and a mean
      error > 10 σ (σ of the float64 reference) along the measured direction h;
    * square-root form: no flag, finite, diag L > 0 everywhere (PD); the variance hᵀPh of
      the measured combination within 2 % of float64 (per-step rounding relative to it is
      ~2 u ‖h‖₁ √cond ≈ 7e-3, not accumulating: every update re-measures it); the mean along
      h within 0.1 σ; diag P within 10 %.  The last is the one cumulative effect: the
      rounding of ``H L`` (a cancellation, ~u ‖h‖₁ √P_v) acts as a spurious observation of
      the unobservable direction, shrinking its variance by up to 4 u² ‖h‖₁² P_v / R ≈ 4e-6
      per step (0.4 over 10⁵ steps in the worst case).  Measured: 3.8 % when multiply-adds
      are not fused (this suite compiles with LLVM optimisation off) and 1.2e-5 with the
      default compilation (fused multiply-add makes the cancellation exact).
    """
    rng = np.random.default_rng(5)
    xs = rng.normal(size=2) * np.sqrt(P0_LR) + np.cumsum(rng.normal(size=(T_LR, 2)) * np.sqrt(Q_LR), 0)
    zs = (xs @ H_LR + rng.normal(size=T_LR) * np.sqrt(R_LR))[:, None]
    run_c, run_s = long_runners()
    t0 = time.perf_counter()
    ref = run_s(zs)  # float64 reference
    s32 = run_s(zs.astype(np.float32))
    c32 = run_c(zs.astype(np.float32))
    jax.block_until_ready((ref, s32, c32))
    elapsed = time.perf_counter() - t0

    P_ref = covs_of(ref.chols)
    hph_ref = np.einsum("i,tij,j->t", H_LR, P_ref, H_LR)
    w_ref = np.linalg.eigvalsh(P_ref)
    cond = float(np.max(w_ref[:, 1] / w_ref[:, 0]))
    assert np.all(np.asarray(ref.status) == 0) and cond > 1e8  # the test's premise

    def err_along_h(means):
        return np.abs((np.asarray(means, np.float64) - np.asarray(ref.means)) @ H_LR) / np.sqrt(hph_ref)

    # The covariance form fails.
    P_c = np.asarray(c32.covs, np.float64)
    w_c = np.linalg.eigvalsh(P_c)
    not_psd_c = int(np.sum((np.asarray(c32.status) & errors.NOT_PSD) != 0))
    neg_c = int(np.sum(w_c[:, 0] < 0))
    err_c = float(np.max(err_along_h(c32.means)))
    assert not_psd_c > 0.9 * T_LR
    assert neg_c > 0.9 * T_LR
    assert err_c > 10.0

    # The square-root form stays PD, finite, unflagged, and close to float64.
    L = np.asarray(s32.chols)
    assert L.dtype == np.float32 and np.all(np.isfinite(L))
    assert np.all(np.diagonal(L, 0, 1, 2) > 0)
    assert np.all(np.asarray(s32.status) == 0)
    P_s = covs_of(L)
    hph_s = np.einsum("i,tij,j->t", H_LR, P_s, H_LR)
    rel_hph = float(np.max(np.abs(hph_s - hph_ref) / hph_ref))
    rel_diag = float(np.max(np.abs(np.asarray(s32.cov_diags) - np.asarray(ref.cov_diags))
                            / np.asarray(ref.cov_diags)))
    err_s = float(np.max(err_along_h(s32.means)))
    print(f"\n10^5 float32 steps, condition number up to {cond:.2g} (float64 reference); "
          f"3 runs {elapsed:.1f} s\n  covariance form: NOT_PSD on {not_psd_c} updates, "
          f"negative eigenvalue in {neg_c} stored covariances (min λ {w_c[:, 0].min():.2g}), "
          f"mean error along h up to {err_c:.3g} σ\n  square-root form: no flag, min diag(L) "
          f"{np.diagonal(L, 0, 1, 2).min():.2g}, rel. error of hᵀPh ≤ {rel_hph:.2g}, "
          f"of diag P ≤ {rel_diag:.2g}, mean error along h ≤ {err_s:.2g} σ")
    assert rel_hph < 2e-2
    assert err_s < 0.1
    assert rel_diag < 0.1


# --------------------------------------------------------------------------
# Factors, masks, failures, logdet
# --------------------------------------------------------------------------

def test_factors_roundtrip_and_singular_psd():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(4, 4))
    P = A @ A.T + 0.1 * np.eye(4)
    s = se.from_gaussian(ekf.Gaussian(np.zeros(4), P))
    np.testing.assert_allclose(np.asarray(s.chol), np.linalg.cholesky(P), atol=1e-12)  # diag ≥ 0
    assert_close(se.to_gaussian(s).cov, P, 1e-14)
    # Singular PSD (an unforced state): host and traced paths both give an exact factor.
    Qs = np.diag([0.3, 0.2, 0.0])
    for L in (se.psd_factor(Qs), jax.jit(se.psd_factor)(Qs)):
        L = np.asarray(L)
        assert np.all(np.isfinite(L)) and np.all(np.triu(L, 1) == 0)
        assert_close(L @ L.T, Qs, 1e-14)
    Ps = np.outer([1.0, 2.0, -1.0], [1.0, 2.0, -1.0])  # rank 1, dense
    for L in (se.psd_factor(Ps), jax.jit(se.psd_factor)(Ps)):
        assert_close(np.asarray(L) @ np.asarray(L).T, Ps, 1e-12)
    # Indefinite: NaN, never a silently clipped factor.
    assert np.all(np.isnan(np.asarray(se.psd_factor(np.diag([1.0, -1.0])))))
    assert np.all(np.isnan(np.asarray(jax.jit(se.psd_factor)(np.diag([1.0, -1.0])))))
    # float32 result from float64 input on request.
    assert se.psd_factor(P, np.float32).dtype == np.float32


@functools.cache
def jit_update(gate_callable=False):
    g = ekf.chi2_gate(0.99, 2) if gate_callable else None
    return jax.jit(lambda s, z, R, mask: se.update(s, z, h_rb, R, jnp.asarray(LANDMARKS[0], s.mean.dtype),
                                                   residual=rb.residual, mask=mask, gate=g))


def test_failures_keep_prior_and_flag():
    s = se.from_gaussian(ekf.Gaussian(np.array([0.0, 0.0, 0.1]), 0.1 * np.eye(3)))
    z = np.asarray(rb.observe(jnp.asarray([0.1, 0.0, 0.1]), jnp.asarray(LANDMARKS[0])))
    upd = jit_update()
    ok = np.ones(2, bool)
    # Not PD R on the valid block: NOT_PSD, prior kept, no NaN anywhere.
    post, info = upd(s, z, np.diag([-1.0, 1e-4]), ok)
    assert int(info.status) == errors.NOT_PSD and not bool(info.accepted)
    np.testing.assert_array_equal(np.asarray(post.chol), np.asarray(s.chol))
    np.testing.assert_array_equal(np.asarray(post.mean), np.asarray(s.mean))
    # The same R is harmless where that component is masked out (and its NaN z too).
    post, info = upd(s, np.array([np.nan, z[1]]), np.diag([-1.0, 1e-4]), np.array([False, True]))
    assert int(info.status) == 0 and bool(info.accepted) and np.all(np.isfinite(np.asarray(post.chol)))
    # NaN in a valid component: NON_FINITE, prior kept (same flags as the covariance form).
    post, info = upd(s, np.array([np.nan, z[1]]), R_RB, ok)
    # jitted for speed only (eager, this one update compiled ~100 one-operation programs)
    _, info_c = jax.jit(lambda g, zz: ekf.update(g, zz, h_rb, R_RB, jnp.asarray(LANDMARKS[0]),
                                                 residual=rb.residual))(se.to_gaussian(s), np.array([np.nan, z[1]]))
    assert int(info.status) & errors.NON_FINITE and int(info_c.status) & errors.NON_FINITE
    np.testing.assert_array_equal(np.asarray(post.mean), np.asarray(s.mean))
    # Nothing valid: unchanged, not accepted, no flag, dof 0.
    post, info = upd(s, np.full(2, np.nan), R_RB, np.zeros(2, bool))
    assert int(info.dof) == 0 and int(info.status) == 0 and not bool(info.accepted)
    np.testing.assert_array_equal(np.asarray(post.chol), np.asarray(s.chol))
    # A callable gate rejects a gross outlier.
    post, info = jit_update(True)(s, z + np.array([5.0, 0.0]), R_RB, ok)
    assert int(info.status) == errors.GATED and not bool(info.accepted)


@pytest.mark.skipif("logdet" not in ekf.UpdateInfo._fields, reason="UpdateInfo has no logdet field yet")
def test_logdet_over_valid_block():
    s = se.from_gaussian(ekf.Gaussian(np.array([0.0, 0.0, 0.1]), 0.1 * np.eye(3)))
    z = np.array([3.9, 0.2])
    R = np.array([[0.01, 0.002], [0.002, 0.003]])
    for mask in (np.array([True, True]), np.array([False, True])):
        _, info = jit_update()(s, z, R, mask)
        Sv = np.asarray(info.S)[np.ix_(mask, mask)]
        np.testing.assert_allclose(float(info.logdet), np.linalg.slogdet(Sv)[1], rtol=1e-12)


def test_gradient_equals_covariance_form():
    """grad through the whole square-root scan (tuning Q and R) = grad of the covariance form."""
    us, zs = simulate_cv(7, T=25)

    def loss(mod, th):
        post = mod.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None,
                               jnp.exp(th[0]) * Q_CV, jnp.exp(th[1]) * R_CV)
        return jnp.sum(post.nis) + jnp.sum(jnp.log(post.cov_diags))

    th = jnp.array([0.1, -0.2])
    v_s, g_s = jax.jit(jax.value_and_grad(functools.partial(loss, se)))(th)
    v_c, g_c = jax.jit(jax.value_and_grad(functools.partial(loss, ekf)))(th)
    np.testing.assert_allclose(float(v_s), float(v_c), rtol=1e-10)
    assert np.all(np.isfinite(np.asarray(g_s)))
    np.testing.assert_allclose(np.asarray(g_s), np.asarray(g_c), rtol=1e-8)

    # A singular process noise Q = 0.05 G Gᵀ (rank 2 of 4) given by its (4, 2) square root.
    C0 = np.sqrt(0.05) * G_CV

    def loss_chol(th):
        post = se.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None, None,
                              jnp.exp(th[1]) * R_CV, Q_chol=jnp.exp(th[0] / 2) * C0)
        return jnp.sum(post.nis) + jnp.sum(jnp.log(post.cov_diags))

    def loss_cov(th):
        post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None,
                               jnp.exp(th[0]) * C0 @ C0.T, jnp.exp(th[1]) * R_CV)
        return jnp.sum(post.nis) + jnp.sum(jnp.log(post.cov_diags))

    v_s, g_s = jax.jit(jax.value_and_grad(loss_chol))(th)
    v_c, g_c = jax.jit(jax.value_and_grad(loss_cov))(th)
    np.testing.assert_allclose(float(v_s), float(v_c), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(g_s), np.asarray(g_c), rtol=1e-8)


# --------------------------------------------------------------------------
# Boundary validation and compile-once
# --------------------------------------------------------------------------

def _scan(**over):
    us, zs = simulate_cv(8, T=5)
    kw = {"x0": X0_CV, "P0": P0_CV, "us": us, "zs": zs, "masks": None, "Q": Q_CV, "R": R_CV}
    kw.update(over)
    return se.filter_scan(f_cv, h_pos, kw["x0"], kw["P0"], kw["us"], kw["zs"], kw["masks"],
                          kw["Q"], kw["R"])


@pytest.mark.parametrize("over, name", [
    ({"zs": np.zeros(5)}, "zs"),
    ({"zs": np.zeros((5, 2, 1))}, "zs"),
    ({"Q": -Q_CV}, "Q"),
    ({"Q": np.eye(3)}, "Q"),
    ({"x0": np.zeros((4, 1))}, "x0"),
    ({"x0": np.array([0.0, np.nan, 0.0, 0.0])}, "x0"),
    ({"P0": np.eye(3)}, "P0"),
    ({"P0": np.diag([1.0, 1.0, -1.0, 1.0])}, "P0"),
    ({"R": np.zeros((2, 2))}, "R"),
    ({"R": np.eye(3)}, "R"),
    ({"masks": np.ones((5, 3), bool)}, "masks"),
    ({"us": np.zeros((4, 2))}, "us"),
])
def test_bad_input_raises_input_error_naming_argument(over, name):
    with pytest.raises(InputError, match=rf"^{name}:"):
        _scan(**over)


def test_filter_scan_compiles_once():
    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(x0, P0, us, zs, masks, Q, R, gate):
        return se.filter_scan(f_cv, h_pos, x0, P0, us, zs, masks, Q, R, gate=gate)

    chex.clear_trace_counter()
    us, zs = simulate_cv(9, T=20)
    m = np.ones(zs.shape, bool)
    a = run(X0_CV, P0_CV, us, zs, m, Q_CV, R_CV, 9.0)
    b = run(X0_CV + 1, 2 * P0_CV, us * 2, zs + 1, ~m, 2 * Q_CV, 3 * R_CV, 5.0)
    assert np.all(np.isfinite(np.asarray(a.means))) and np.all(np.isfinite(np.asarray(b.means)))
    assert np.all(np.asarray(b.dof) == 0)


@pytest.mark.parametrize("moving", [True, False], ids=["cv", "f_none"])
def test_per_step_noise_and_a_still_state_equal_numpy(moving):
    """``Q`` (T, n, n) and ``R`` (T, m, m), each step's own, and ``f=None`` (a state that does
    not move: P' = P + Q_t), against the closed-form Kalman filter written here."""
    us, zs = simulate_cv(4, T=20)
    rng = np.random.default_rng(2)
    Qs = Q_CV[None] * rng.uniform(0.5, 2.0, size=(20, 1, 1))
    Rs = R_CV[None] * rng.uniform(0.5, 2.0, size=(20, 1, 1))
    post = se.filter_scan(f_cv if moving else None, h_pos, X0_CV, P0_CV, us, zs, None, Qs, Rs, save_chol=True)
    x, P = X0_CV.astype(float), P0_CV.astype(float)
    F = F_CV if moving else np.eye(4)
    for t in range(20):
        x = F @ x + (G_CV @ us[t] if moving else 0.0)
        P = F @ P @ F.T + Qs[t]
        S = H_CV @ P @ H_CV.T + Rs[t]
        K = np.linalg.solve(S, H_CV @ P).T
        x, P = x + K @ (zs[t] - H_CV @ x), P - K @ S @ K.T
        assert_close(post.means[t], x, 1e-10)
        assert_close(covs_of(post.chols[t]), P, 1e-10)
    assert not np.any(np.asarray(post.status))
    with pytest.raises(InputError, match=r"^Q: one matrix per step needs 20"):
        se.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None, Qs[:19], R_CV)
    with pytest.raises(InputError, match=r"^R: expected shape \(2, 2\) or \(20, 2, 2\)"):
        se.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None, Q_CV, Rs[:19])
