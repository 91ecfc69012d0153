"""Tests for jaxslam.features.lines (paper 004 ch. 4.1: Hesse lines, eq. 4.1, Algorithm 1, matching).

Speed: the jitted extractors are module-level and shared; the acceptance run is one jitted,
vmapped call over all scans.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.features import lines as F
from jaxslam.sensors import laser2d as L

CFG = F.DEFAULT_RANSAC
SPEC = L.URG04LX
_EXTRACT = jax.jit(F.extract_lines, static_argnames="cfg")
_MATCH = jax.jit(F.match_predicted, static_argnames="cfg")
_GUIDED = jax.jit(F.extract_guided, static_argnames="cfg")
_FIT = jax.jit(F.fit_line)
_COV = jax.jit(F.fit_line_cov)

BOX = L.walls_from_polygon([[0.0, 0.0], [4.5, 0.0], [4.5, 3.0], [0.0, 3.0]])


def _wrapdiff(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi)


def _true_lines(walls, pose):
    x, y, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    Rt = np.array([[c, s], [-s, c]])
    return np.array([[float(v) for v in F.line_through(Rt @ (a - [x, y]), Rt @ (b - [x, y]))] for a, b in walls])


def _scan_one(key, pose, walls, q=0.3, dtype=jnp.float64):
    r, v, w = L.scan(key, jnp.asarray(pose, dtype), jnp.asarray(walls, dtype), jnp.ones(len(walls), bool), SPEC,
                     outlier_prob=q)
    p, m = L.scan_points(r, v, SPEC)
    return p, m, w


def test_hesse_flip_and_wrap():
    r, t = F.hesse_normalize(jnp.array([-1.0, 2.0, -0.5, 1.0]), jnp.array([0.3, 3.5, 3.0, -math.pi]))
    np.testing.assert_allclose(np.asarray(r), [1.0, 2.0, 0.5, 1.0])
    np.testing.assert_allclose(np.asarray(t), [0.3 + math.pi - 2 * math.pi, 3.5 - 2 * math.pi,
                                               3.0 + math.pi - 2 * math.pi, math.pi], atol=1e-12)
    # Same set of points before and after.
    p = np.array([1.0 * math.cos(0.3) * -1, -1.0 * math.sin(0.3)])
    assert abs(p @ [math.cos(float(t[0])), math.sin(float(t[0]))] - float(r[0])) < 1e-12
    rr, tt = F.line_through(jnp.array([1.0, 0.0]), jnp.array([1.0, 5.0]))
    assert float(rr) == pytest.approx(1.0) and float(tt) == pytest.approx(0.0, abs=1e-15)
    rr, tt = F.line_through(jnp.array([-2.0, 1.0]), jnp.array([-2.0, -3.0]))
    assert float(rr) == pytest.approx(2.0) and float(tt) == pytest.approx(math.pi)


def test_fit_line_matches_svd_oracle_and_cov_matches_monte_carlo():
    rng = np.random.default_rng(0)
    for _ in range(5):
        P = rng.normal(size=(50, 2)) * [2.0, 0.1] @ np.linalg.qr(rng.normal(size=(2, 2)))[0] + rng.normal(size=2) * 3
        w = rng.uniform(0.2, 2.0, 50)
        c = (w[:, None] * P).sum(0) / w.sum()
        _, _, Vt = np.linalg.svd(np.sqrt(w)[:, None] * (P - c))
        n = Vt[-1]
        rho, th = c @ n, math.atan2(n[1], n[0])
        if rho < 0:
            rho, th = -rho, th + math.pi
        r, t = _FIT(jnp.asarray(P), jnp.asarray(w))
        assert float(r) == pytest.approx(rho, abs=1e-10) and _wrapdiff(t, th) < 1e-10
    # Monte Carlo of the covariance: 30 points over 2 m of the line ρ = 1.5, θ = 0.4.
    rho0, th0, sig = 1.5, 0.4, 0.01
    n0, d0 = np.array([math.cos(th0), math.sin(th0)]), np.array([-math.sin(th0), math.cos(th0)])
    u = np.linspace(0.2, 2.2, 30)
    P0 = rho0 * n0 + u[:, None] * d0
    w = np.ones(30)
    noise = np.random.default_rng(1).normal(scale=sig, size=(20000, 30, 2))
    r, t = jax.jit(jax.vmap(F.fit_line, in_axes=(0, None)))(jnp.asarray(P0 + noise), jnp.asarray(w))
    emp = np.cov(np.stack([np.asarray(r), np.asarray(t)]))
    cov = np.asarray(_COV(jnp.asarray(P0), jnp.asarray(w), sig))
    np.testing.assert_allclose(np.diag(emp), np.diag(cov), rtol=0.05)
    assert emp[0, 1] / math.sqrt(emp[0, 0] * emp[1, 1]) == pytest.approx(
        cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]), abs=0.03)
    # Closed form about the centroid (module docstring), unit weights.
    suu = ((u - u.mean()) ** 2).sum()
    assert cov[1, 1] == pytest.approx(sig**2 / suu, rel=1e-9)
    assert cov[0, 0] == pytest.approx(sig**2 * (1 / 30 + u.mean() ** 2 / suu), rel=1e-9)
    # Endpoints and distances.
    ends = np.asarray(F.segment_endpoints(jnp.asarray(P0), jnp.asarray(w), rho0, th0))
    np.testing.assert_allclose(ends, P0[[0, -1]], atol=1e-12)
    np.testing.assert_allclose(np.asarray(F.point_line_distance(jnp.asarray(P0 + n0 * 0.1), rho0, th0)), 0.1, atol=1e-12)


def test_n_hypotheses_eq_4_1():
    # Hand values: p = 0.99, ε = 0.5, m = 2: log 0.01 / log 0.75 = 16.008 → 17.
    assert F.n_hypotheses(0.99, 0.5, 2) == 17
    # p = 0.99, ε = 0.9, m = 2: log 0.01 / log 0.99 = 458.21 → 459 (the default n_hyp).
    assert F.n_hypotheses(0.99, 0.9, 2) == 459 == CFG.n_hyp
    assert F.n_hypotheses(0.95, 0.3, 3) == 8  # log 0.05 / log(1 − 0.7³) = 7.13 → 8
    for p, e, m in ((0.99, 0.7, 2), (0.999, 0.5, 4), (0.9, 0.2, 20), (0.95, 0.3, 3)):
        expect = math.ceil(math.log(1 - p) / math.log(1 - (1 - e) ** m))
        assert F.n_hypotheses(p, e, m) == expect
    for bad in ((1.0, 0.5, 2), (0.9, 0.0, 2), (0.9, 0.5, 1), (0.9, 0.5, 2.0), (0.9, 0.5, True)):
        with pytest.raises(InputError):
            F.n_hypotheses(*bad)


@pytest.fixture(scope="module")
def room_scan():
    pose = (2.3, 1.4, 0.15)
    p, m, w = _scan_one(jax.random.PRNGKey(7), pose, BOX)
    return p, m, w, _true_lines(BOX, pose)


def test_extraction_deterministic_and_finds_room_walls(room_scan):
    p, m, w, true = room_scan
    a, rem_a = _EXTRACT(jax.random.PRNGKey(3), p, m, CFG)
    b, rem_b = _EXTRACT(jax.random.PRNGKey(3), p, m, CFG)
    for x, y in zip(jax.tree.leaves((a, rem_a)), jax.tree.leaves((b, rem_b))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    valid = np.asarray(a.valid)
    counts = np.bincount(np.asarray(w)[np.asarray(w) >= 0], minlength=4)
    for j in np.flatnonzero(counts >= CFG.min_inliers):
        ok = (np.abs(np.asarray(a.rho) - true[j, 0]) <= 0.02) & (_wrapdiff(a.theta, true[j, 1]) <= math.radians(0.5))
        assert np.any(ok & valid), f"wall {j} not found"
    # Bookkeeping: inlier sets disjoint, removed from remaining, counts consistent.
    inl = np.asarray(a.inliers)
    assert np.all(inl.sum(0) <= 1) and not np.any(inl.any(0) & np.asarray(rem_a))
    np.testing.assert_array_equal(inl.sum(1), np.asarray(a.n_inliers))
    assert np.all(np.asarray(a.n_inliers)[valid] >= CFG.min_inliers)
    assert np.all(np.asarray(a.rho)[valid] >= 0) and np.all(np.asarray(a.rho)[~valid] == 0)
    assert np.all(np.linalg.eigvalsh(np.asarray(a.cov)[valid]) > 0)


def test_all_invalid_scan_gives_no_lines_and_no_nan():
    p = jnp.full((682, 2), jnp.nan)
    lines, rem = _EXTRACT(jax.random.PRNGKey(0), p, jnp.zeros(682, bool), CFG)
    assert not np.any(np.asarray(lines.valid)) and not np.any(np.asarray(rem))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(lines) if x.dtype.kind == "f")
    m, new, rem = _GUIDED(jax.random.PRNGKey(0), p, jnp.ones(682, bool), jnp.array([1.0]), jnp.array([0.0]),
                          jnp.array([True]), CFG, 0.2)
    assert not np.any(np.asarray(m.valid)) and not np.any(np.asarray(new.valid))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves((m, new)) if x.dtype.kind == "f")


def test_float32_extraction(room_scan):
    p, m, _, true = room_scan
    lines, _ = _EXTRACT(jax.random.PRNGKey(3), p.astype(jnp.float32), m, CFG)
    assert lines.rho.dtype == jnp.float32 and lines.cov.dtype == jnp.float32
    assert int(np.sum(np.asarray(lines.valid))) >= 3


def test_match_predicted_finds_present_and_rejects_absent(room_scan):
    p, m, w, true = room_scan
    absent = np.array([[0.8, 2.0]])  # no wall there
    pred = np.concatenate([true + [[0.03, 0.01]], absent])
    mask = np.array([True] * 4 + [True])
    mask[:4][np.bincount(np.asarray(w)[np.asarray(w) >= 0], minlength=4) < CFG.min_inliers] = False
    matched, new, rem = _GUIDED(jax.random.PRNGKey(5), p, m, jnp.asarray(pred[:, 0]), jnp.asarray(pred[:, 1]),
                                jnp.asarray(mask), CFG, 0.2)
    mv = np.asarray(matched.valid)
    np.testing.assert_array_equal(mv, mask & np.array([True] * 4 + [False]))
    for j in np.flatnonzero(mv):
        assert abs(float(matched.rho[j]) - true[j, 0]) <= 0.02
        assert _wrapdiff(matched.theta[j], true[j, 1]) <= math.radians(0.5)
    # The walls were taken by matching: no new line duplicates them.
    for r, t, v in zip(np.asarray(new.rho), np.asarray(new.theta), np.asarray(new.valid)):
        if v:
            assert not np.any((np.abs(true[mask[:4], 0] - r) < 0.05) & (_wrapdiff(true[mask[:4], 1], t) < 0.02))
    inl = np.concatenate([np.asarray(matched.inliers), np.asarray(new.inliers)])
    assert np.all(inl.sum(0) <= 1) and not np.any(inl.any(0) & np.asarray(rem))


def test_unused_prediction_slots_are_empty_and_vmap_agrees(room_scan):
    """An unused slot is skipped (lax.cond) alone and selected away under vmap: both give the
    empty record and leave every point to the later slots."""
    p, m, _, true = room_scan
    pr, pt = jnp.asarray(true[:, 0]), jnp.asarray(true[:, 1])
    masks = jnp.asarray([[True, False, True, False], [False, True, False, True]])
    single = [_MATCH(p, m, pr, pt, mk, CFG, 0.2) for mk in masks]
    batch = jax.jit(jax.vmap(lambda mk: F.match_predicted(p, m, pr, pt, mk, CFG, 0.2)))(masks)
    for b, (lines, rem) in enumerate(single):
        for f in lines._fields:  # floats to rounding (a batched reduction sums in its own order)
            np.testing.assert_allclose(np.asarray(getattr(batch[0], f)[b]),
                                       np.asarray(getattr(lines, f)), rtol=1e-9, atol=1e-15)
        np.testing.assert_array_equal(np.asarray(batch[1][b]), np.asarray(rem))
        off = ~np.asarray(masks[b])
        assert not np.asarray(lines.valid)[off].any() and not np.asarray(lines.inliers)[off].any()
        for f in ("rho", "theta", "cov", "endpoints", "n_inliers"):
            assert not np.asarray(getattr(lines, f))[off].any(), f


def test_bad_config_is_rejected_on_the_host():
    p = jnp.zeros((10, 2))
    with pytest.raises(InputError, match="min_inliers"):
        F.extract_lines(jax.random.PRNGKey(0), p, jnp.ones(10, bool), CFG._replace(min_inliers=1))
    with pytest.raises(InputError, match="threshold"):
        F.extract_lines(jax.random.PRNGKey(0), p, jnp.ones(10, bool), CFG._replace(threshold=-1.0))
    with pytest.raises(InputError, match="points"):
        F.extract_lines(jax.random.PRNGKey(0), jnp.zeros((10, 3)), jnp.ones(10, bool), CFG)


# ----------------------------------------------------------------------------- acceptance
# Long walls, so that the 0.5° tolerance is reachable: a line's θ error is ≈ σ√12/(√N·ℓ) for N
# points over a length ℓ, so a 20-point segment (12 cm at 1 m) cannot be held to 0.5°.  The
# sensor stands in a 4.5 m × 3 m room facing the far wall (yaw within ±20°), 30 % clutter.


def _acceptance(n_scans, seed):
    rng = np.random.default_rng(seed)
    poses = np.column_stack([rng.uniform(2.2, 2.6, n_scans), rng.uniform(1.0, 2.0, n_scans),
                             np.radians(rng.uniform(-20, 20, n_scans))])
    walls = jnp.asarray(BOX)

    def one(k, pose):
        k1, k2 = jax.random.split(k)
        p, m, w = _scan_one(k1, pose, walls)
        lines, _ = F.extract_lines(k2, p, m, CFG)
        return lines.rho, lines.theta, lines.valid, w

    out = jax.jit(jax.vmap(one))(jax.random.split(jax.random.PRNGKey(seed), n_scans), jnp.asarray(poses))
    rho, th, val, w = map(np.asarray, out)
    ok_scans, errs = 0, []
    for i in range(n_scans):
        true = _true_lines(BOX, poses[i])
        counts = np.bincount(w[i][w[i] >= 0], minlength=4)
        good = True
        for j in np.flatnonzero(counts >= CFG.min_inliers):
            dr, dt = np.abs(rho[i] - true[j, 0]), _wrapdiff(th[i], true[j, 1])
            k = np.argmin(np.where(val[i], dr / 0.02 + dt / math.radians(0.5), np.inf))
            errs.append((dr[k], math.degrees(dt[k])))
            good &= bool(val[i, k] and dr[k] <= 0.02 and dt[k] <= math.radians(0.5))
        ok_scans += good
    errs = np.array(errs)
    rate = ok_scans / n_scans
    print(f"\nacceptance {n_scans} scans: success {rate:.4f}; |Δρ| p50/p95/p99/max [mm] "
          f"{np.percentile(errs[:, 0], [50, 95, 99, 100]) * 1e3}; |Δθ| [deg] "
          f"{np.percentile(errs[:, 1], [50, 95, 99, 100])}")
    return rate


@pytest.mark.slow  # the acceptance figure itself (measured 99.9 %); 250 scans in the default suite
def test_acceptance_1000_scans():
    assert _acceptance(1000, 2024) >= 0.99


def test_acceptance_reduced_250_scans():
    # The same check on a quarter of the scans (other seed): at 99.9 % expected, at most 2 misses.
    assert _acceptance(250, 7) >= 0.99


def test_largest_run_and_trim():
    # jitted for speed only (eager, one program per operation and shape); gap and k are static
    largest_run = jax.jit(F.largest_run, static_argnums=1)
    trim_run = jax.jit(F.trim_run, static_argnums=1)
    m = np.zeros(40, bool)
    m[[1, 2, 3]] = True  # run of 3
    m[10:20] = True  # run of 10 (with a 1-beam hole below)
    m[15] = False
    m[30] = True  # stray point
    run = np.asarray(largest_run(jnp.asarray(m), 2))
    expect = np.zeros(40, bool)
    expect[10:20] = True
    expect[15] = False
    np.testing.assert_array_equal(run, expect)
    # max_gap 1 splits at the hole: the run 10-14 (5 beams) beats 16-19 (4).
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(largest_run(jnp.asarray(m), 1))), np.arange(10, 15))
    t = np.asarray(trim_run(jnp.asarray(expect), 2))
    np.testing.assert_array_equal(np.flatnonzero(t), [12, 13, 14, 16, 17])
    assert not np.asarray(largest_run(jnp.zeros(5, bool), 3)).any()
    assert not np.asarray(trim_run(jnp.asarray(expect), 5)).any()
