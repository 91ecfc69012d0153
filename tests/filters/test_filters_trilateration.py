"""Least-squares trilateration (paper 003 eq. 22-26).

Oracles: exact geometry (noise-free ranges), ``numpy.linalg.lstsq`` on eq. 26
rebuilt here in NumPy, a finite-difference (first-order) covariance of that
oracle, and hand-made degenerate geometries.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.filters import trilateration as tri

DTYPES = [jnp.float32, jnp.float64]


def _oracle(points, ranges):
    """Eq. 26 (sign-corrected: rows 2 (a_k − a_1)) solved by numpy.linalg.lstsq."""
    a1, d1 = points[0], ranges[0]
    A = 2.0 * (points[1:] - a1)
    b = d1 ** 2 - ranges[1:] ** 2 + np.sum(points[1:] ** 2, axis=1) - a1 @ a1
    return np.linalg.lstsq(A, b, rcond=None)[0]


_JTRI = jax.jit(tri.trilaterate, static_argnames=("min_points",))
_JLINE = jax.jit(tri.trilaterate_line, static_argnames=("min_points",))


@pytest.fixture(scope="module")
def jtri():
    return _JTRI


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("dim", [2, 3])
def test_exact_on_noise_free_ranges(dtype, dim, jtri):
    rng = np.random.default_rng(dim)
    for _ in range(5):
        P = rng.uniform(-4, 4, size=(8, dim))
        x = rng.uniform(-3, 3, size=dim)
        d = np.linalg.norm(P - x, axis=1)
        r = jtri(jnp.asarray(P, dtype), jnp.asarray(d, dtype))
        assert r.position.dtype == dtype
        assert bool(r.ok) and int(r.status) == 0 and int(r.n_used) == 8
        tol = 2e-3 if dtype == jnp.float32 else 1e-10
        np.testing.assert_allclose(np.asarray(r.position), x, atol=tol)
        assert float(r.residual_max) < tol


def test_paper_sign_of_eq26_reflects_the_point():
    # Erratum check: rows 2 (a_1 − a_k) with the paper's b give −x, the point reflected
    # through the origin; the corrected rows give x.
    rng = np.random.default_rng(7)
    P = rng.uniform(-4, 4, size=(6, 2))
    x = np.array([1.3, -0.7])
    d = np.linalg.norm(P - x, axis=1)
    a1 = P[0]
    b = d[0] ** 2 - d[1:] ** 2 + np.sum(P[1:] ** 2, 1) - a1 @ a1
    paper = np.linalg.lstsq(2.0 * (a1 - P[1:]), b, rcond=None)[0]
    np.testing.assert_allclose(paper, -x, atol=1e-12)
    np.testing.assert_allclose(np.asarray(_JTRI(jnp.asarray(P), jnp.asarray(d)).position), x,
                               atol=1e-12)


def test_noisy_matches_numpy_lstsq(jtri):
    rng = np.random.default_rng(11)
    for i in range(20):
        K = (3, 12)[i % 2]  # two shapes: two compilations
        P = rng.uniform(-5, 5, size=(K, 2))
        x = rng.uniform(-3, 3, size=2)
        d = np.linalg.norm(P - x, axis=1) + rng.uniform(-0.2, 0.2, size=K)
        d = np.abs(d) + 1e-3
        r = jtri(jnp.asarray(P), jnp.asarray(d))
        np.testing.assert_allclose(np.asarray(r.position), _oracle(P, d), atol=1e-10, rtol=0)
        # The error with respect to the truth is the oracle's error.
        np.testing.assert_allclose(np.linalg.norm(np.asarray(r.position) - x),
                                   np.linalg.norm(_oracle(P, d) - x), atol=1e-10)


def test_mask_equals_dropping_rows(jtri):
    rng = np.random.default_rng(5)
    P = rng.uniform(-5, 5, size=(12, 2))
    x = np.array([0.5, 1.0])
    d = np.linalg.norm(P - x, axis=1) + rng.normal(0, 0.1, 12)
    mask = np.ones(12, bool)
    mask[[0, 3, 7]] = False  # the first sample too: the reference moves to the first valid
    r = jtri(jnp.asarray(P), jnp.asarray(d), jnp.asarray(mask))
    np.testing.assert_allclose(np.asarray(r.position), _oracle(P[mask], d[mask]), atol=1e-10)
    assert int(r.n_used) == 9 and int(r.status) == 0  # a deliberate mask is not bad input


def test_invalid_ranges_are_dropped_and_flagged(jtri):
    rng = np.random.default_rng(6)
    P = rng.uniform(-5, 5, size=(10, 2))
    x = np.array([-1.0, 0.5])
    d = np.linalg.norm(P - x, axis=1) + rng.normal(0, 0.1, 10)
    bad = d.copy()
    bad[2], bad[5], bad[8] = np.nan, 0.0, -0.3
    r = jtri(jnp.asarray(P), jnp.asarray(bad))
    keep = np.ones(10, bool)
    keep[[2, 5, 8]] = False
    np.testing.assert_allclose(np.asarray(r.position), _oracle(P[keep], d[keep]), atol=1e-10)
    assert int(r.status) & errors.MASKED_INPUT
    assert bool(r.ok)


@pytest.mark.parametrize("dtype", DTYPES)
def test_collinear_and_degenerate_detected(dtype, jtri):
    # Every case has 9 samples (masks, not shapes, vary): one compilation per dtype.
    x = np.array([0.3, 1.7])
    line = np.stack([np.linspace(-3, 3, 9), 0.5 * np.linspace(-3, 3, 9) + 1.0], axis=1)  # collinear
    same = np.tile([[1.0, 1.0]], (9, 1))  # coincident
    two = np.random.default_rng(0).uniform(-3, 3, size=(9, 2))  # general, but only two valid
    near = line.copy()
    near[4, 1] += 1e-3  # 1 mm off a 6 m line
    cases = [(line, np.ones(9, bool), 0.0), (same, np.ones(9, bool), 0.0),
             (two, np.arange(9) < 2, 0.0), (near, np.ones(9, bool), 0.3)]
    for P, m, spread in cases:
        d = np.linalg.norm(P - x, axis=1)
        r = jtri(jnp.asarray(P, dtype), jnp.asarray(d, dtype), jnp.asarray(m), None, None, spread)
        assert not bool(r.ok)
        assert int(r.status) & errors.DEGENERATE
        assert np.all(np.isfinite(np.asarray(r.position)))
    assert float(r.spread) < 0.01  # the nearly collinear case is rejected by the spread requirement


def test_covariance_matches_first_order_propagation():
    rng = np.random.default_rng(9)
    P = rng.uniform(-4, 4, size=(7, 2))
    x = np.array([0.4, -0.8])
    d = np.linalg.norm(P - x, axis=1)
    s2 = 1e-4
    r = _JTRI(jnp.asarray(P), jnp.asarray(d), range_var=s2)
    J = np.zeros((2, 7))
    h = 1e-6
    for k in range(7):
        dp, dm = d.copy(), d.copy()
        dp[k] += h
        dm[k] -= h
        J[:, k] = (_oracle(P, dp) - _oracle(P, dm)) / (2 * h)
    C1 = s2 * J @ J.T  # first order; the module adds the small 2σ⁴ terms
    np.testing.assert_allclose(np.asarray(r.cov), C1, rtol=2e-3, atol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
def test_line_trilateration_noise_free(dtype):
    xs = np.linspace(-3.0, 0.0, 21)
    for L, side in (((-1.5, 2.5), 1.0), ((1.0, -2.0), -1.0), ((-4.0, 0.7), 1.0)):
        d = np.sqrt((xs - L[0]) ** 2 + L[1] ** 2)
        r = _JLINE(jnp.asarray(xs, dtype), jnp.asarray(d, dtype), side=side)
        tol = 2e-3 if dtype == jnp.float32 else 1e-10
        np.testing.assert_allclose(np.asarray(r.position), L, atol=tol)
        assert bool(r.ok)


def test_line_trilateration_noisy_along_line_is_lstsq_and_point_on_line_flagged():
    rng = np.random.default_rng(4)
    xs = np.linspace(-3.0, 0.0, 21)
    d = np.sqrt((xs + 1.5) ** 2 + 2.5 ** 2) + rng.uniform(-0.2, 0.2, 21)
    r = _JLINE(jnp.asarray(xs), jnp.asarray(d))
    A = 2.0 * (xs[1:] - xs[0])[:, None]
    b = d[0] ** 2 - d[1:] ** 2 + xs[1:] ** 2 - xs[0] ** 2
    u = np.linalg.lstsq(A, b, rcond=None)[0][0]
    y = np.sqrt(np.mean(d ** 2 - (u - xs) ** 2))
    np.testing.assert_allclose(np.asarray(r.position), [u, y], atol=1e-10)
    # a point on the line (y² ≤ 0 after noise): flagged, y = 0, never NaN
    r = _JLINE(jnp.asarray(xs), jnp.asarray(np.abs(xs + 1.5) - 0.05).clip(1e-3))
    assert not bool(r.ok) and int(r.status) & errors.DEGENERATE
    assert float(r.position[1]) == 0.0 and np.all(np.isfinite(np.asarray(r.position)))
    # no baseline (the drone did not move)
    r = _JLINE(jnp.zeros(21), jnp.full(21, 2.0))
    assert not bool(r.ok) and np.all(np.isfinite(np.asarray(r.position)))


def test_vmap_over_landmarks_and_no_retrace():
    rng = np.random.default_rng(8)
    P = jnp.asarray(rng.uniform(-4, 4, size=(10, 2)))
    L = rng.uniform(-3, 3, size=(4, 2))
    D = jnp.asarray(np.linalg.norm(np.asarray(P)[:, None] - L[None], axis=-1))
    traces = []

    @jax.jit
    def f(P, D):
        traces.append(1)
        return jax.vmap(lambda d: tri.trilaterate(P, d).position, in_axes=1)(D)

    np.testing.assert_allclose(np.asarray(f(P, D)), L, atol=1e-10)
    f(P + 0.0, D * 1.0)
    assert len(traces) == 1


def test_gradient_matches_numpy_finite_differences_and_is_finite_when_degenerate():
    """The fit's derivative with respect to the known points and the ranges (QR path) equals
    central differences of the NumPy lstsq oracle, also for three points at a right angle,
    where eq. 26's A has equal singular values and an SVD's derivative is NaN (measured with the
    earlier SVD solve); on degenerate inputs (an empty buffer, coincident or collinear points)
    every derivative is finite — a filter differentiates through beacons that are not ready yet."""
    pts = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0], [1.0, 3.0]])
    target = np.array([1.3, 2.1])
    h = 1e-6
    for P in (pts, pts[:3]):  # pts[:3]: A = diag(8, 8)
        r = np.linalg.norm(P - target, axis=1) + np.array([0.01, -0.02, 0.015, 0.0, 0.005])[:len(P)]
        Jp, Jr = jax.jit(jax.jacfwd(lambda pp, rr: tri.trilaterate(pp, rr).position, argnums=(0, 1)))(
            jnp.asarray(P), jnp.asarray(r))  # jitted: one program, not one per operation
        fd_r = np.stack([(_oracle(P, r + h * e) - _oracle(P, r - h * e)) / (2 * h) for e in np.eye(len(r))], 1)
        np.testing.assert_allclose(np.asarray(Jr), fd_r, rtol=1e-6, atol=1e-8)
        for k in range(len(P)):
            for j in range(2):
                E = np.zeros_like(P)
                E[k, j] = h
                fd = (_oracle(P + E, r) - _oracle(P - E, r)) / (2 * h)
                np.testing.assert_allclose(np.asarray(Jp[:, k, j]), fd, rtol=1e-6, atol=1e-8)

    def loss(points, ranges, mask):
        f = tri.trilaterate(points, ranges, mask=mask, range_var=0.04, min_points=3)
        return jnp.sum(f.position) + jnp.sum(f.cov) + f.residual_max

    for points, ranges, mask in ((jnp.zeros((6, 2)), jnp.zeros(6), jnp.zeros(6, bool)),  # empty buffer
                                 (jnp.ones((6, 2)), jnp.full(6, 2.0), jnp.ones(6, bool)),  # one point
                                 (jnp.stack([jnp.arange(6.0), jnp.zeros(6)], 1), jnp.full(6, 3.0),
                                  jnp.ones(6, bool))):  # collinear
        g = jax.jit(jax.grad(loss, argnums=(0, 1)))(points, ranges, mask)
        assert all(np.all(np.isfinite(np.asarray(a))) for a in g)


def test_fewer_points_than_dimensions_and_a_dropped_nan_row():
    """Review of 2026-12-07: K < d (two anchors in 3D, one in 2D) made solve_triangular raise inside
    the fit (ok False with DEGENERATE is what the docstring promises); a masked-off row with a NaN
    position made trilaterate_line's spread NaN, so a good fit came back DEGENERATE.  Oracle for the
    latter: the same fit with the row removed."""
    for pts, r in ((np.array([[0.0, 0, 0], [1, 0, 0]]), np.array([1.0, 1.0])), (np.array([[0.0, 0]]), np.array([1.0]))):
        res = tri.trilaterate(pts, r)
        assert not bool(res.ok) and int(res.status) & errors.DEGENERATE
        assert np.isfinite(np.asarray(res.position)).all()
        jax.jit(tri.trilaterate)(pts, r)  # under jit too
    xs = np.array([0.0, -1, -2, -3, -4])
    r = np.hypot(xs + 1.5, 2.0)
    xs_nan = xs.copy()
    xs_nan[4] = np.nan
    got = tri.trilaterate_line(xs_nan, r, mask=np.array([1, 1, 1, 1, 0], bool))
    want = tri.trilaterate_line(xs[:4], r[:4])
    assert bool(got.ok) and int(got.status) == 0
    np.testing.assert_allclose(np.asarray(got.position), np.asarray(want.position), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(got.position), [-1.5, 2.0], rtol=1e-9)


def test_from_buffer_checks_var_rows_as_a_mask():
    from jaxslam.errors import InputError
    from jaxslam.filters import delayed_init as di

    pts = np.stack([np.linspace(0, 5, 6), np.array([0, 3, 0, 3, 0, 3.0])], 1)
    r = np.linalg.norm(pts - np.array([2.0, 8.0]), axis=1)
    for bad, msg in ((np.full(6, 0.5), "got dtype float64"), (np.full(6, 2), "got the value 2")):
        with pytest.raises(InputError, match=rf"^var_rows: expected a bool mask .*{msg}"):
            di.from_buffer(pts, np.zeros(6), r, np.ones(6, bool), 0.01, var_rows=bad)
    fit, P = di.from_buffer(pts, np.zeros(6), r, np.ones(6, bool), 0.01, var_rows=np.ones(6, int))
    np.testing.assert_allclose(np.asarray(fit.position), [2.0, 8.0], atol=1e-9)
