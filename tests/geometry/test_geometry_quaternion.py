"""Hamilton quaternions against SciPy (scalar last!) and closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxslam.geometry import quaternion as qu
from jaxslam.geometry import euler as eu

qmul_j = jax.jit(qu.qmul)
dcm_j = jax.jit(qu.dcm_from_quat)
fromdcm_j = jax.jit(qu.quat_from_dcm)
exp_j = jax.jit(qu.qexp)
log_j = jax.jit(qu.qlog)
rot_j = jax.jit(qu.qrotate)


def to_scipy(q):
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def from_scipy(r):
    return r.as_quat()[..., [3, 0, 1, 2]]


def canon(q):
    q = np.asarray(q, dtype=float)
    return np.where(q[..., :1] < 0, -q, q)


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def near_pi_rotvecs(rng, n):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    ang = np.pi - 10.0 ** rng.uniform(-9, -2, n)
    return axis * ang[:, None]


def hamilton_np(p, q):
    """Left-multiplication matrix form of the Hamilton product (independent)."""
    p0, p1, p2, p3 = p
    L = np.array([[p0, -p1, -p2, -p3], [p1, p0, -p3, p2], [p2, p3, p0, -p1], [p3, -p2, p1, p0]])
    return L @ q


def test_qmul_hamilton_and_composition():
    rng = np.random.default_rng(0)
    p, q, r = random_quats(rng, 50), random_quats(rng, 50), random_quats(rng, 50)
    pq = np.asarray(qmul_j(p, q))
    np.testing.assert_allclose(pq, np.stack([hamilton_np(a, b) for a, b in zip(p, q)]), atol=1e-15)
    # i j = k, j i = −k (Hamilton)
    ij = np.asarray(qmul_j(np.array([[0.0, 1, 0, 0], [0, 0, 1, 0]]), np.array([[0.0, 0, 1, 0], [0, 1, 0, 0]])))
    np.testing.assert_allclose(ij, [[0, 0, 0, 1], [0, 0, 0, -1]])
    # rotation of p ⊗ q = C(p) C(q), with C from SciPy
    np.testing.assert_allclose(dcm_j(pq), to_scipy(p).as_matrix() @ to_scipy(q).as_matrix(), atol=1e-14)
    # associativity
    np.testing.assert_allclose(qmul_j(qmul_j(p, q), r), qmul_j(p, qmul_j(q, r)), atol=1e-14)
    # broadcasting a single quaternion against a batch
    np.testing.assert_allclose(qmul_j(p[0], q), np.stack([hamilton_np(p[0], b) for b in q]), atol=1e-15)
    # conjugate is the inverse
    np.testing.assert_allclose(jax.jit(lambda p: qu.qmul(p, qu.qconj(p)))(p), np.tile([1.0, 0, 0, 0], (50, 1)), atol=1e-15)


def test_dcm_rotate_and_euler_match_scipy():
    rng = np.random.default_rng(1)
    q = random_quats(rng, 100).reshape(5, 20, 4)
    v = rng.normal(size=(5, 20, 3))
    R = to_scipy(q.reshape(-1, 4))
    np.testing.assert_allclose(dcm_j(q), R.as_matrix().reshape(5, 20, 3, 3), atol=1e-15)
    np.testing.assert_allclose(rot_j(q, v), R.apply(v.reshape(-1, 3)).reshape(5, 20, 3), atol=1e-14)
    run = jax.jit(lambda q: (lambda e: (e, qu.quat_from_euler(e), eu.dcm_from_euler(e)))(qu.euler_from_quat(q)))
    e, qe, Ce = (np.asarray(a) for a in run(q.reshape(-1, 4)))
    np.testing.assert_allclose(e, R.as_euler("ZYX")[:, ::-1], atol=1e-12)
    np.testing.assert_allclose(canon(qe), canon(from_scipy(R)), atol=1e-14)
    # quaternion and Euler DCMs agree (paper 000 eq. 1)
    np.testing.assert_allclose(dcm_j(qe), Ce, atol=1e-14)


def test_quat_from_dcm_all_branches():
    rng = np.random.default_rng(2)
    rv = np.concatenate(
        [
            rng.normal(size=(100, 3)),
            near_pi_rotvecs(rng, 100),  # q0 ≈ 0
            np.pi * np.eye(3),  # exactly π about x, y, z: branches 1, 2, 3
            (np.pi - 1e-7) * np.eye(3),
            np.pi * np.array([[1.0, 1, 0], [0, 1, 1], [1, 1, 1]]) / np.sqrt([[2], [2], [3]]),
            np.zeros((1, 3)),  # identity: branch 0
            1e-12 * rng.normal(size=(3, 3)),
        ]
    )
    R = Rotation.from_rotvec(rv)
    C = R.as_matrix()
    q = np.asarray(fromdcm_j(C))
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    qs = from_scipy(R)
    # compare up to the double cover (q0 = 0 cases may carry either sign)
    err = np.minimum(np.abs(q - qs).max(-1), np.abs(q + qs).max(-1))
    assert err.max() < 1e-14, err.max()
    np.testing.assert_allclose(dcm_j(q), C, atol=1e-14)
    # each Shepperd branch was exercised
    s = np.stack([1 + np.trace(C, axis1=1, axis2=2)] + [1 + 2 * C[:, i, i] - np.trace(C, axis1=1, axis2=2) for i in range(3)], -1)
    assert set(np.argmax(s, -1)) == {0, 1, 2, 3}
    # gradient finite (double-where) at identity and at a π rotation
    g = jax.jit(jax.vmap(jax.jacfwd(qu.quat_from_dcm)))((np.stack([np.eye(3), C[200], C[202]])))
    assert np.all(np.isfinite(g))


def test_exp_log_match_scipy_and_invert():
    rng = np.random.default_rng(3)
    rv = np.concatenate([rng.normal(size=(100, 3)) * 0.9, near_pi_rotvecs(rng, 50),
                         1e-10 * rng.normal(size=(10, 3)), 1e-5 * rng.normal(size=(10, 3)), np.zeros((1, 3))])
    rv = rv[np.linalg.norm(rv, axis=-1) < np.pi]
    q = np.asarray(exp_j(rv))
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(canon(q), canon(from_scipy(Rotation.from_rotvec(rv))), atol=1e-15)
    back = np.asarray(log_j(q))
    np.testing.assert_allclose(back, rv, atol=1e-12)
    np.testing.assert_allclose(log_j(-q), back, atol=1e-12)  # double cover
    # log of arbitrary quaternions = SciPy's shortest rotation vector (angle ≤ π)
    qr = random_quats(rng, 200)
    lr = np.asarray(log_j(qr))
    np.testing.assert_allclose(lr, Rotation.from_quat(qr[:, [1, 2, 3, 0]]).as_rotvec(), atol=1e-12)
    assert np.linalg.norm(lr, axis=-1).max() <= np.pi + 1e-12
    np.testing.assert_allclose(canon(exp_j(lr)), canon(qr), atol=1e-14)
    # qlog ignores the norm
    np.testing.assert_allclose(log_j(3.0 * qr), lr, atol=1e-12)


def test_exp_log_gradients_closed_form_at_identity():
    @jax.jit
    def jacs(r, q):
        return jax.jacfwd(qu.qexp)(r), jax.jacfwd(qu.qlog)(q), jax.jacrev(qu.qlog)(q)

    Jexp, Jlog, Jrev = jacs(np.zeros(3), np.array([1.0, 0, 0, 0]))
    np.testing.assert_allclose(Jexp, np.vstack([np.zeros((1, 3)), 0.5 * np.eye(3)]), atol=1e-15)
    np.testing.assert_allclose(Jlog, np.hstack([np.zeros((3, 1)), 2.0 * np.eye(3)]), atol=1e-15)
    np.testing.assert_allclose(Jrev, Jlog, atol=1e-15)


def _log_np(q):
    w, v = q[0], q[1:]
    n = np.linalg.norm(v)
    return 2.0 * np.arctan2(n, w) / n * v


def _exp_np(r):
    t = np.linalg.norm(r)
    return np.r_[np.cos(t / 2), np.sin(t / 2) / t * r]


def _fd_jac(fun, x, h):
    return np.stack([(fun(x + h * e) - fun(x - h * e)) / (2 * h) for e in np.eye(len(x))], 1)


def test_gradients_near_singular_points_finite_and_correct():
    """Forward and reverse Jacobians vs central differences of NumPy oracles.

    qlog jumps at q0 = 0 (double cover), so the difference step there stays
    below q0 (1e-10 at q0 = 1e-9).
    """
    rng = np.random.default_rng(4)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    qs = np.stack([
        np.r_[1e-9, u * np.sqrt(1 - 1e-18)],  # q0 ≈ 0: rotation ≈ π
        np.r_[1e-3, u * np.sqrt(1 - 1e-6)],
        np.r_[0.999, 0.01, -0.02, 0.03],
        np.r_[1.0, 1e-9 * u],  # near identity (Taylor branch)
        np.r_[1.0 - 1e-12, 3e-7 * u],
    ])
    steps = [1e-10, 1e-5, 1e-6, 1e-7, 1e-7]
    Jf = np.asarray(jax.jit(jax.vmap(jax.jacfwd(qu.qlog)))(qs))
    Jr = np.asarray(jax.jit(jax.vmap(jax.jacrev(qu.qlog)))(qs))
    assert np.all(np.isfinite(Jf)) and np.all(np.isfinite(Jr))
    for q, h, a, b in zip(qs, steps, Jf, Jr):
        ref = _fd_jac(_log_np, q, h)
        np.testing.assert_allclose(a, ref, atol=2e-5 * max(1.0, np.abs(ref).max()))
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    rs = np.stack([1e-6 * u, 1e-3 * u, 2.0 * u, 3.1 * u])
    Ef = np.asarray(jax.jit(jax.vmap(jax.jacfwd(qu.qexp)))(rs))
    Er = np.asarray(jax.jit(jax.vmap(jax.jacrev(qu.qexp)))(rs))
    for r, a, b in zip(rs, Ef, Er):
        np.testing.assert_allclose(a, _fd_jac(_exp_np, r, 1e-7), atol=1e-7)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    # second derivatives at the identity: finite, and closed form for qexp
    hess = jax.jit(lambda q, r: (jax.hessian(lambda q: jnp.sum(qu.qlog(q)))(q),
                                 jax.hessian(lambda r: jnp.sum(qu.qexp(r)))(r)))
    Hl, He = hess(np.array([1.0, 0, 0, 0]), np.zeros(3))
    assert np.all(np.isfinite(Hl))
    np.testing.assert_allclose(He, -0.25 * np.eye(3), atol=1e-15)  # ∂²cos(|r|/2) = −I/4 at 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_preserved(dtype):
    rng = np.random.default_rng(5)
    rv = np.concatenate([rng.normal(size=(20, 3)), near_pi_rotvecs(rng, 5), 1e-6 * rng.normal(size=(5, 3))]).astype(dtype)
    rv = rv[np.linalg.norm(rv.astype(float), axis=-1) < np.pi - 1e-3]

    @jax.jit
    def run(rv):
        q = qu.qexp(rv)
        C = qu.dcm_from_quat(q)
        others = (qu.qmul(q, q), qu.qrotate(q, rv), qu.quat_from_euler(rv), qu.euler_from_quat(q),
                  qu.qconj(q), qu.qnormalize(q), qu.qcanonical(q), C)
        g = jax.grad(lambda r: jnp.sum(qu.qlog(qu.qexp(r))))(jnp.zeros(3, rv.dtype))
        return q, qu.qlog(q), qu.quat_from_dcm(C), others, g

    q, r2, q2, others, g = run(rv)
    assert all(o.dtype == dtype for o in (q, r2, q2, g, *others))
    tol = 2e-6 if dtype == np.float32 else 1e-13
    np.testing.assert_allclose(np.asarray(r2, float), rv.astype(float), atol=tol)
    np.testing.assert_allclose(canon(q2), canon(q), atol=tol)
    np.testing.assert_allclose(g, 1.0, atol=tol)  # qlog ∘ qexp = id near 0


def test_vmap_and_canonical():
    rng = np.random.default_rng(6)
    q = random_quats(rng, 16)

    @jax.jit
    def run(q):
        return (jax.vmap(qu.qlog)(q), jax.vmap(qu.quat_from_dcm)(jax.vmap(qu.dcm_from_quat)(q)),
                qu.qcanonical(q), qu.qnormalize(2.5 * q))

    vlog, vq, c, nq = (np.asarray(a) for a in run(q))
    np.testing.assert_allclose(vlog, log_j(q), atol=1e-15)
    np.testing.assert_allclose(vq, fromdcm_j(dcm_j(q)), atol=1e-15)
    assert np.all(c[:, 0] >= 0)
    np.testing.assert_allclose(np.abs(c), np.abs(q))
    np.testing.assert_allclose(c * np.sign(q[:, :1]), q)
    np.testing.assert_allclose(nq, q, atol=1e-15)


def test_wrongly_shaped_rotations_are_named_not_answered():
    # each used to return a plausible answer (qmul of a (3,) quaternion gave [1, 1, 1, 1],
    # euler_from_dcm of a 2×2 matrix three angles) or fail in a broadcast
    from jaxslam.errors import InputError

    q = np.array([1.0, 0.0, 0.0, 0.0])
    cases = [
        (lambda: qu.qmul(np.ones(3), q), r"^qmul: p expected shape \(\.\.\., 4\), got \(3,\)"),
        (lambda: qu.qmul(q, np.ones(5)), r"^qmul: q expected shape \(\.\.\., 4\), got \(5,\)"),
        (lambda: qu.dcm_from_quat(np.ones(3)), r"^dcm_from_quat: q expected shape"),
        (lambda: qu.euler_from_quat(np.ones(3)), r"^dcm_from_quat: q expected shape"),
        (lambda: qu.qrotate(q, np.ones(2)), r"^qrotate: v expected shape \(\.\.\., 3\)"),
        (lambda: qu.quat_from_dcm(np.eye(2)), r"^quat_from_dcm: C expected shape \(\.\.\., 3, 3\)"),
        (lambda: qu.qexp(np.ones(4)), r"^qexp: rotvec expected shape \(\.\.\., 3\)"),
        (lambda: qu.qlog(np.ones(3)), r"^qlog: q expected shape"),
        (lambda: eu.euler_from_dcm(np.eye(2)), r"^euler_from_dcm: C expected shape \(\.\.\., 3, 3\)"),
        (lambda: eu.dcm_from_euler(np.zeros(2)), r"^dcm_from_euler: euler expected shape \(\.\.\., 3\)"),
        (lambda: eu.euler_rates(np.zeros(3), np.zeros(2)), r"^euler_rates: omega expected shape"),
    ]
    for call, msg in cases:
        with pytest.raises(InputError, match=msg):
            call()
    # batches keep working, and under jit the check is a trace-time shape test
    np.testing.assert_allclose(np.asarray(jax.jit(qu.qmul)(np.tile(q, (5, 1)), q)), np.tile(q, (5, 1)))
