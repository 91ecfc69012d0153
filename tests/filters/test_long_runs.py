"""Long runs of the EKF, EKF-SLAM and FastSLAM cores in float32 and float64 (issue 22).

Each run is one jitted loop over ``steps`` (a traced trip count: the default runs and the
10⁵-step ``slow`` runs share one compiled program per filter and dtype).  Every step draws
its own truth and measurement noise from ``fold_in(key, t)``, runs the filter, and folds
the step's diagnostics into a few scalars of the loop carry, so memory does not grow with
the run: no covariance is kept.

Per step:

* asymmetry ``max|P − Pᵀ| / max|P|`` of the stored covariance (not symmetrised);
* relative smallest eigenvalue ``λ_min / λ_max`` of the covariance, computed in float64
  from the stored matrix (so a float32 run is judged on its own rounding, not on a float32
  eigensolver's);
* any non-finite value in a mean, a covariance or a weight;
* the estimation error against the truth (computed in float64; the truth is always
  simulated in float64, only the filter runs in the dtype under test).

Bounds are fixed in advance from the design, not from observed output:

* **Asymmetry = 0, exactly, in both dtypes.**  Every covariance write of the three filters
  ends in ``symmetrize`` ((X + Xᵀ)/2, jaxslam.linalg), whose (i, j) and (j, i) entries are
  the same IEEE sum (addition commutes exactly), or writes a block and its transpose from
  one array (EKF-SLAM prediction and registration).  No positive tolerance would test
  anything: with the final symmetrisation removed, the factored Joseph form
  A − (A Hᵀ) Kᵀ + K R Kᵀ of these runs stays within 0.5-1 eps of symmetric (measured once;
  the rounding does not accumulate), so the only figure that tells the two apart is 0.
* **λ_min ≥ −10·n·eps·λ_max.**  The factored Joseph form is a sum of PSD terms in exact
  arithmetic, and prediction adds a PSD Q; rounding perturbs each entry of P by a few
  eps·‖P‖ per step, which moves an eigenvalue by at most ‖ΔP‖₂ ≤ n·max|ΔP|.  A covariance
  that loses definiteness goes below by the size of the information lost, far beyond.
  (These runs are well conditioned: measured once, even the plain (I − K H) P update keeps
  EKF-SLAM PSD over 10⁵ float32 steps; the check guards against a defect, it does not tell
  update forms apart.)
* **Status word**: no flag at all (jaxslam.errors): no NON_FINITE, NOT_PSD, DEGENERATE,
  CAPACITY_OVERFLOW; nothing is gated (no gate) and every input is finite.
* **Error**: the maximum over the run of the position error < 10 σ_pos, σ_pos the position
  σ of one range-bearing fix at the largest range the geometry allows, max(σ_r, r σ_β).
  The largest of 10⁵ draws of a 2D Gaussian error of σ per axis is ≈ 4.8 σ
  (exp(−k²/2) = 10⁻⁵); 10 leaves a factor 2 for linearisation and for EKF-SLAM's known
  long-run over-confidence, while a diverging filter leaves it far behind.  Heading errors
  alike: 10 (σ_β + σ_pos / d_min), the heading σ of one fix of a landmark at distance d_min.
* **NEES** (the EKF's state, EKF-SLAM's robot pose; the filters are given the true noise
  models): E[NEES] = n for a consistent filter; the mean over ≥ 2·10³ correlated steps
  scatters by < 0.1 n, so the band [0.7 n, 1.4 n] fails only for an inconsistent filter
  (EKF-SLAM's long-run over-confidence would show as a mean above it).  FastSLAM's pose
  spread of 16 particles, often descended from one ancestor, is no covariance to test so.
* **Measurements used**: every EKF update is accepted; the SLAM loops have ≥ 4 landmarks
  within range everywhere (module constants), detected with p = 0.9, so ≥ 2 rows per step
  (per particle) must be used on average: a filter that silently rejects updates and dead-
  reckons fails here before its error grows.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.dynamics import planar
from jaxslam.filters import ekf
from jaxslam.filters import ekf_slam as es
from jaxslam.filters import fastslam as fs
from jaxslam.linalg import symmetrize, wrap_angle
from jaxslam.sensors import range_bearing2d as rb

F64 = jnp.float64
STEPS_DEFAULT = 2000
STEPS_LONG = 100_000
DTYPES = ["float32", "float64"]
ERR_MULT = 10.0  # bound = ERR_MULT × design σ (module docstring)
ASYM_TOL = 0.0  # max|P − Pᵀ| / max|P|, both dtypes (module docstring)
PSD_EPS_PER_DIM = 10.0  # λ_min ≥ −PSD_EPS_PER_DIM · n · eps · λ_max (module docstring)
NEES_BAND = (0.7, 1.4)  # mean NEES / n (module docstring)
MIN_ROWS_PER_STEP = 2  # SLAM measurement rows used per step, on average (module docstring)

STEP_PARAMS = [STEPS_DEFAULT, pytest.param(STEPS_LONG, marks=pytest.mark.slow)]


# ---------------------------------------------------------------------------
# Per-step diagnostics folded into the loop carry
# ---------------------------------------------------------------------------

def _stats0():
    return {"asym": jnp.zeros((), F64), "min_eig": jnp.asarray(np.inf, F64),
            "nonfinite": jnp.zeros((), bool), "status": jnp.zeros((), jnp.int32),
            "pos_err": jnp.zeros((), F64), "head_err": jnp.zeros((), F64),
            "nees": jnp.zeros((), F64), "used": jnp.zeros((), jnp.int32)}


def _cov_stats(P, used=None):
    """(max|P − Pᵀ| / max|P|, λ_min / λ_max) of one stored covariance, in float64.

    ``used`` (n,) bool marks the rows in use (EKF-SLAM: the robot and the active slots);
    the others are exactly zero and would put eigenvalues 0 in the spectrum, so they get
    max|P| on the diagonal instead: the eigenvalues of the used block remain.
    """
    P = P.astype(F64)
    scale = jnp.max(jnp.abs(P))
    asym = jnp.max(jnp.abs(P - P.T)) / scale
    Ps = symmetrize(P)
    if used is not None:
        Ps = Ps + jnp.diag(jnp.where(used, 0.0, scale))
    w = jnp.linalg.eigvalsh(Ps)
    return asym, w[0] / w[-1]


def _fold(s, asym, min_eig, nonfinite, status, used, pos_err, head_err=0.0, nees=0.0):
    """The running maxima / minima / sums of the loop carry after one step."""
    return {"asym": jnp.maximum(s["asym"], asym), "min_eig": jnp.minimum(s["min_eig"], min_eig),
            "nonfinite": s["nonfinite"] | nonfinite, "status": s["status"] | status,
            "pos_err": jnp.maximum(s["pos_err"], pos_err),
            "head_err": jnp.maximum(s["head_err"], head_err), "nees": s["nees"] + nees,
            "used": s["used"] + jnp.asarray(used, jnp.int32)}


def _any_nonfinite(*xs):
    return jnp.any(jnp.stack([jnp.any(~jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(xs)]))


def _to_host(stats, steps):
    out = {k: np.asarray(v).item() for k, v in stats.items()}
    out["nees_mean"] = out.pop("nees") / steps
    return out


def _check_common(out, dtype, n):
    """The bounds every run shares (module docstring); n the covariance size."""
    eps = float(np.finfo(dtype).eps)
    assert not out["nonfinite"], out
    assert out["status"] == errors.OK, (errors.decode(out["status"]), out)
    assert out["asym"] <= ASYM_TOL, out
    assert out["min_eig"] >= -PSD_EPS_PER_DIM * n * eps, out


# ---------------------------------------------------------------------------
# Generic EKF: a damped 2D oscillator seen in range and bearing from the origin
# ---------------------------------------------------------------------------

DT = 0.1
W0, ZETA = 0.5, 0.2  # natural frequency [rad/s] and damping of the target's spring
CENTRE = np.array([12.0, 0.0])  # rest point of the target [m]
Q_ACC = 0.1  # acceleration noise density [m²/s³]: stationary σ_p² = q/(4 ζ ω0³) = 1 m²
SIG_R_EKF, SIG_B_EKF = 0.1, 0.005  # [m], [rad]
# Largest range: centre + 5 stationary σ (10⁵ steps are ~10³ correlation times 1/(ζ ω0) =
# 10 s, whose largest excursion is ≈ 3.5 σ).  The bearing's singular point (the sensor) is
# 12 σ away.
R_MAX_EKF = 12.0 + 5.0
SIGPOS_EKF = max(SIG_R_EKF, R_MAX_EKF * SIG_B_EKF)  # 0.1 m

_A1 = np.array([[1.0, DT], [-W0**2 * DT, 1.0 - 2 * ZETA * W0 * DT]])  # one axis, (p, v)
F_EKF = np.kron(_A1, np.eye(2))  # state (px, py, vx, vy)
B_EKF = np.concatenate([np.zeros(2), W0**2 * DT * CENTRE])
Q_EKF = Q_ACC * np.kron(np.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]]), np.eye(2))
R_EKF = np.diag([SIG_R_EKF**2, SIG_B_EKF**2])
X0_EKF = np.array([12.0, 0.0, 0.0, 0.0])
P0_EKF = np.diag([1.0, 1.0, 0.25, 0.25])
RESID_EKF = ekf.angle_residual([False, True])


def _f_ekf(x, u):
    return jnp.asarray(F_EKF, x.dtype) @ x + jnp.asarray(B_EKF, x.dtype)


def _h_ekf(x):
    p = x[:2]
    return jnp.stack([jnp.sqrt(p @ p), jnp.arctan2(p[1], p[0])])


@functools.partial(jax.jit, static_argnames="dtype")
def _run_ekf(key, steps, dtype):
    dt_ = jnp.dtype(dtype)
    LQ = jnp.asarray(np.linalg.cholesky(Q_EKF), F64)
    LR = jnp.asarray(np.linalg.cholesky(R_EKF), F64)
    Fd, Bd = jnp.asarray(F_EKF, F64), jnp.asarray(B_EKF, F64)
    Q, R = jnp.asarray(Q_EKF, dt_), jnp.asarray(R_EKF, dt_)
    k0, key = jax.random.split(key)
    x_true = jnp.asarray(X0_EKF, F64) + jnp.asarray(np.linalg.cholesky(P0_EKF), F64) @ \
        jax.random.normal(k0, (4,), F64)
    g0 = ekf.Gaussian(jnp.asarray(X0_EKF, dt_), jnp.asarray(P0_EKF, dt_))

    def body(t, c):
        x_true, g, s = c
        kw, kv = jax.random.split(jax.random.fold_in(key, t))
        x_true = Fd @ x_true + Bd + LQ @ jax.random.normal(kw, (4,), F64)
        z = _h_ekf(x_true) + LR @ jax.random.normal(kv, (2,), F64)
        g = ekf.predict(g, _f_ekf, None, Q)
        g, info = ekf.update(g, z.astype(dt_), _h_ekf, R, residual=RESID_EKF)
        asym, lam = _cov_stats(g.cov)
        e = x_true - g.mean.astype(F64)
        nees = e @ jnp.linalg.solve(g.cov.astype(F64), e)
        s = _fold(s, asym, lam, _any_nonfinite(g), info.status, info.accepted,
                  jnp.linalg.norm(e[:2]), nees=nees)
        return x_true, g, s

    _, g, s = jax.lax.fori_loop(0, steps, body, (x_true, g0, _stats0()))
    return g, s


@pytest.mark.parametrize("steps", STEP_PARAMS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_ekf_long_run_stays_symmetric_psd_finite_and_consistent(dtype, steps):
    g, s = _run_ekf(jax.random.PRNGKey(11), steps, dtype)
    assert g.mean.dtype == dtype and g.cov.dtype == dtype  # the run really is in `dtype`
    out = _to_host(s, steps)
    _check_common(out, dtype, 4)
    assert out["used"] == steps, out
    assert out["pos_err"] < ERR_MULT * SIGPOS_EKF, out
    assert NEES_BAND[0] * 4 <= out["nees_mean"] <= NEES_BAND[1] * 4, out


# ---------------------------------------------------------------------------
# Shared planar world of the SLAM runs: loops of radius 4 m among six landmarks
# ---------------------------------------------------------------------------

LMS = np.array([[6.0, 0.0], [0.0, 6.0], [-6.0, 0.0], [0.0, -6.0], [1.5, 1.3], [-1.4, -1.4]])
N_LM = LMS.shape[0]
CAP = 8  # two slots stay free
RADIUS, SPEED = 4.0, 1.0  # loop radius [m], speed [m/s]: one loop = 25 s = 251 steps
# Landmarks seen within MAX_RANGE: each is registered during the first loop; the two inner
# ones (1.98 m from the centre) are always within 6 m of the loop, and of the ring (6 m from
# the centre) at least two are (≤ 4.25 m, at 45° between two of them).
MAX_RANGE = 6.0
P_DETECT = 0.9  # each visible landmark is detected with this probability per step
SIG_R, SIG_B = 0.05, 0.01  # [m], [rad]
SIG_Q = np.array([0.01, 0.01, 0.002])  # additive world-frame pose noise per step [m, m, rad]
R_SLAM = np.diag([SIG_R**2, SIG_B**2])
Q_SLAM = np.diag(SIG_Q**2)
S0 = np.array([RADIUS, 0.0, np.pi / 2])  # on the loop, heading along it
P0_SLAM = np.diag([1e-4, 1e-4, 1e-5])
SIGPOS_SLAM = max(SIG_R, MAX_RANGE * SIG_B)  # 0.06 m
D_MIN = 2.0  # nearest a landmark comes to the loop [m]
HEAD_BOUND = ERR_MULT * (SIG_B + SIGPOS_SLAM / D_MIN)  # 0.4 rad


def _guidance(s):
    """(v, ω) that keeps the true robot on the loop (the filter sees it as a known input)."""
    r = jnp.hypot(s[0], s[1])
    heading = jnp.arctan2(s[1], s[0]) + jnp.pi / 2 + 0.5 * (r - RADIUS)
    return jnp.stack([jnp.asarray(SPEED, F64), SPEED / RADIUS + 1.0 * wrap_angle(heading - s[2])])


def _world_step(key, t, s_true):
    """True pose after step t, the command u, and the step's measurements of every landmark."""
    kq, kz, kd = jax.random.split(jax.random.fold_in(key, t), 3)
    u = _guidance(s_true)
    s_true = planar.unicycle(s_true, u, DT) + jnp.asarray(SIG_Q, F64) * jax.random.normal(kq, (3,), F64)
    s_true = s_true.at[2].set(wrap_angle(s_true[2]))
    lms = jnp.asarray(LMS, F64)
    z = jax.vmap(rb.observe, in_axes=(None, 0))(s_true, lms)
    z = z + jax.random.normal(kz, z.shape, F64) * jnp.asarray([SIG_R, SIG_B], F64)
    z = z.at[:, 1].set(wrap_angle(z[:, 1]))
    seen = (z[:, 0] <= MAX_RANGE) & (jax.random.uniform(kd, (N_LM,), F64) < P_DETECT)
    return s_true, u, z, seen


def _pose_errors(s_est, s_true):
    e = s_true - s_est.astype(F64)
    return jnp.hypot(e[0], e[1]), jnp.abs(wrap_angle(e[2]))


def _initial_truth(key):
    """True start pose, drawn from the filters' prior N(S0, P0); the key of the steps."""
    k0, key = jax.random.split(key)
    s0 = jnp.asarray(S0, F64) + jnp.sqrt(jnp.diag(jnp.asarray(P0_SLAM, F64))) * \
        jax.random.normal(k0, (3,), F64)
    return s0, key


def _map_error(lm_mean, ids, active):
    """Largest position error of the mapped landmarks (float64)."""
    true = jnp.asarray(LMS, F64)[jnp.clip(ids, 0, N_LM - 1)]
    err = jnp.linalg.norm(lm_mean.astype(F64) - true, axis=-1)
    return jnp.max(jnp.where(active, err, 0.0))


# ---------------------------------------------------------------------------
# EKF-SLAM engine
# ---------------------------------------------------------------------------

SLAM_MODEL = es.SlamModel(3, 2, 2, lambda s, u, p: planar.unicycle(s, u, DT), rb.observe,
                          rb.inverse, rb.residual)


@functools.partial(jax.jit, static_argnames=("dtype", "active_only", "joseph"))
def _run_ekf_slam(key, steps, dtype, active_only=False, joseph=True):
    dt_ = jnp.dtype(dtype)
    Q, R = jnp.asarray(Q_SLAM, dt_), jnp.asarray(R_SLAM, dt_)
    ids = jnp.arange(N_LM, dtype=jnp.int32)
    st0 = es.init(jnp.asarray(S0, dt_), jnp.asarray(P0_SLAM, dt_), CAP, 2)

    def body(t, c):
        s_true, st, s = c
        s_true, u, z, seen = _world_step(key, t, s_true)
        st = es.predict(st, SLAM_MODEL, u.astype(dt_), Q, active_only=active_only)
        zd = z.astype(dt_)
        slots, mapped = es.associate_known(st, ids, seen)
        st, info = es.update(st, SLAM_MODEL, zd, slots, mapped, R, active_only=active_only,
                             joseph=joseph)
        st = es.register(st, SLAM_MODEL, zd, ids, seen & ~mapped, R)
        used_rows = jnp.concatenate([jnp.ones((3,), bool), jnp.repeat(st.active, 2)])
        asym, lam = _cov_stats(st.P, used_rows)
        pos, head = _pose_errors(st.x[:3], s_true)
        e = (s_true - st.x[:3].astype(F64)).at[2].set(wrap_angle(s_true[2] - st.x[2].astype(F64)))
        nees = e @ jnp.linalg.solve(st.P[:3, :3].astype(F64), e)
        s = _fold(s, asym, lam, _any_nonfinite(st.x, st.P), st.status, jnp.sum(info.used), pos,
                  head, nees)
        return s_true, st, s

    s_true0, key = _initial_truth(key)
    _, st, s = jax.lax.fori_loop(0, steps, body, (s_true0, st0, _stats0()))
    lm = st.x[3:].reshape(CAP, 2)
    return st, s, _map_error(lm, st.ids, st.active)


@pytest.mark.parametrize("active_only,joseph", [(False, True), (True, True), (True, False)],
                         ids=["whole", "active_only", "active_only-standard"])
@pytest.mark.parametrize("steps", STEP_PARAMS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_ekf_slam_long_run_stays_symmetric_psd_finite_and_bounded(dtype, steps, active_only, joseph):
    # active_only: the tiled correction (sym_rank_update) and strip prediction
    # (robot_cross_update) keep P bitwise symmetric too (each tile/strip written with its mirror).
    # joseph=False: the standard form P − K S Kᵀ (sym_outer_update) is held to the same bounds:
    # on this problem it loses no definiteness the Joseph form keeps (docs/papers.md)
    st, s, map_err = _run_ekf_slam(jax.random.PRNGKey(12), steps, dtype, active_only, joseph)
    assert st.x.dtype == dtype and st.P.dtype == dtype
    out = _to_host(s, steps)
    out["map_err"] = float(map_err)
    _check_common(out, dtype, 3 + 2 * CAP)
    assert int(st.overflow) == 0 and int(np.sum(np.asarray(st.active))) == N_LM, out
    assert out["used"] >= MIN_ROWS_PER_STEP * steps, out
    assert NEES_BAND[0] * 3 <= out["nees_mean"] <= NEES_BAND[1] * 3, out
    assert out["pos_err"] < ERR_MULT * SIGPOS_SLAM, out
    assert out["head_err"] < HEAD_BOUND, out
    assert out["map_err"] < ERR_MULT * SIGPOS_SLAM, out


# ---------------------------------------------------------------------------
# FastSLAM 1.0 core
# ---------------------------------------------------------------------------

N_PARTICLES = 16
FS_MODEL = fs.LandmarkModel(2, 2, rb.observe, rb.inverse, rb.residual)


def _sample(pose, aux, key, u):
    """Proposal = the motion model with the true process noise (additive, world frame)."""
    eps = jax.random.normal(key, (3,), pose.dtype) * jnp.asarray(SIG_Q, pose.dtype)
    nxt = planar.unicycle(pose, u, DT) + eps
    return nxt.at[2].set(wrap_angle(nxt[2])), aux


def _cov2_stats(C, active):
    """(max asymmetry, min λ_min/λ_max) over active 2×2 landmark covariances, float64."""
    C = C.astype(F64)
    a, b, c, d = C[..., 0, 0], C[..., 0, 1], C[..., 1, 0], C[..., 1, 1]
    scale = jnp.maximum(jnp.maximum(jnp.abs(a), jnp.abs(d)), jnp.maximum(jnp.abs(b), jnp.abs(c)))
    scale = jnp.where(active, scale, 1.0)
    asym = jnp.max(jnp.where(active, jnp.abs(b - c) / scale, 0.0))
    m, off = 0.5 * (a + d), 0.5 * (b + c)
    rad = jnp.sqrt((0.5 * (a - d)) ** 2 + off**2)
    lo, hi = m - rad, m + rad
    rel = jnp.where(active, lo / jnp.where(active, hi, 1.0), jnp.inf)
    return asym, jnp.min(rel)


@functools.partial(jax.jit, static_argnames="dtype")
def _run_fastslam(key, steps, dtype):
    dt_ = jnp.dtype(dtype)
    R = jnp.asarray(R_SLAM, dt_)
    ids = jnp.arange(N_LM, dtype=jnp.int32)
    p0 = fs.init(jnp.asarray(S0, dt_), N_PARTICLES, CAP, 2)

    def body(t, c):
        s_true, p, s = c
        s_true, u, z, seen = _world_step(key, t, s_true)
        kf = jax.random.fold_in(jax.random.fold_in(key, t), 1)
        p, info = fs.step(p, kf, _sample, (u.astype(dt_),), FS_MODEL, z.astype(dt_), ids, seen, R)
        mu, cov = fs.estimate(p, (False, False, True))
        asym, lam = _cov2_stats(p.lm_cov, p.active)
        # the pose spread too (0 when every particle descends from one ancestor)
        c64 = cov.astype(F64)
        scale = jnp.max(jnp.abs(c64))
        asym = jnp.maximum(asym, jnp.max(jnp.abs(c64 - c64.T)) / jnp.where(scale > 0, scale, 1.0))
        pos, head = _pose_errors(mu, s_true)
        nf = _any_nonfinite(p.pose, p.lm_mean, p.lm_cov, p.log_w, mu, cov)
        s = _fold(s, asym, lam, nf, p.status | info.status, info.n_used, pos, head)
        return s_true, p, s

    s_true0, key = _initial_truth(key)
    _, p, s = jax.lax.fori_loop(0, steps, body, (s_true0, p0, _stats0()))
    i = jnp.argmax(p.log_w)
    return p, s, _map_error(p.lm_mean[i], p.ids[i], p.active[i])


@pytest.mark.parametrize("steps", STEP_PARAMS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_fastslam_long_run_stays_symmetric_psd_finite_and_bounded(dtype, steps):
    p, s, map_err = _run_fastslam(jax.random.PRNGKey(13), steps, dtype)
    assert p.pose.dtype == dtype and p.lm_cov.dtype == dtype and p.log_w.dtype == dtype
    out = _to_host(s, steps)
    out["map_err"] = float(map_err)
    out["resamples"], out["underflow"] = int(p.resamples), int(p.underflow)
    _check_common(out, dtype, 2)
    assert int(p.overflow) == 0 and np.all(np.sum(np.asarray(p.active), axis=1) == N_LM), out
    assert out["used"] >= MIN_ROWS_PER_STEP * N_PARTICLES * steps, out
    assert out["pos_err"] < ERR_MULT * SIGPOS_SLAM, out
    assert out["head_err"] < HEAD_BOUND, out
    assert out["map_err"] < ERR_MULT * SIGPOS_SLAM, out
