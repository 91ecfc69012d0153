"""Gradients of a whole FastSLAM run through soft resampling.

Toy planar robot (x, y, yaw) with 2D range-bearing landmarks, written here.
A 20-step run with 64 particles, reparametrised proposal noise
(``pose' = pose + Δ + exp(½ log Q) ⊙ ε`` with ε fixed by the key), exact
Rao-Blackwellised weights and soft resampling (α = 0.5) at every step.  The
gradients of two losses — the negative log marginal likelihood
``−Σ_t log Σ_i w̄_i p(z_t | i)`` and the mean squared position error of the
weighted estimate — with respect to ``log Q`` (3,) and ``log R`` (2,) are
compared with central finite differences.

Why the tolerance is tight (rtol 1e-6): at a fixed key the run is a smooth
function of the parameters except where an ancestor index jumps (the soft
resampler's uniform draws cross a cumulative-weight boundary).  For a step of
1e-6 no index changes (checked: the finite differences at steps 1e-6 and
1e-5 agree to 1e-6), so the pathwise gradient and the central difference
differ only by truncation (O(h²), ~1e-12 relative) and float64 round-off
(~1e-16·|loss|/h ≈ 1e-8 absolute).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.filters import ekf
from jaxslam.filters import fastslam as fs
from jaxslam.linalg import wrap_angle

T, N = 20, 64
LMS = np.array([[2.0, 1.0], [-1.0, 3.0], [4.0, -2.0], [0.5, -3.0]])


def observe(pose, l, params):
    d = l - pose[:2]
    return jnp.stack([jnp.sqrt(d @ d), wrap_angle(jnp.arctan2(d[1], d[0]) - pose[2])])


def inverse(pose, z, params):
    a = z[1] + pose[2]
    return pose[:2] + z[0] * jnp.stack([jnp.cos(a), jnp.sin(a)])


MODEL = fs.LandmarkModel(2, 2, observe, inverse, ekf.angle_residual([False, True]))


def _data():
    rng = np.random.default_rng(0)
    t = np.arange(T + 1) * 0.15
    truth = np.stack([1.5 * np.cos(t) - 1.0, 1.5 * np.sin(t), t + np.pi / 2], axis=1)
    du = np.diff(truth, axis=0) + rng.normal(size=(T, 3)) * [0.02, 0.02, 0.01]
    zs, mask = [], []
    for k in range(T):
        d = LMS - truth[k + 1, :2]
        z = np.stack([np.hypot(d[:, 0], d[:, 1]),
                      np.arctan2(d[:, 1], d[:, 0]) - truth[k + 1, 2]], axis=1)
        z = z + rng.normal(size=z.shape) * [0.05, 0.02]
        m = np.ones(4, bool)
        m[k % 4] = k < 2  # one landmark unseen per step after the first two
        zs.append(np.where(m[:, None], z, np.nan))  # masked entries are NaN
        mask.append(m)
    return truth, du, np.stack(zs), np.stack(mask)


TRUTH, DU, ZS, MASK = _data()


def sample(pose, aux, key, du, sq):
    return pose + du + sq * jax.random.normal(key, (3,), pose.dtype), aux


def losses(theta, key):
    """(negative log marginal likelihood, mean squared position error)."""
    log_q, log_r = theta[:3], theta[3:]
    sq = jnp.exp(0.5 * log_q)
    R = jnp.diag(jnp.exp(log_r))
    p = fs.init(jnp.asarray(TRUTH[0]), N, 4, 2)

    def body(p, x):
        k, du, z, m = x
        k1, k2 = jax.random.split(k)
        p = fs.propagate(p, k1, sample, du, sq)
        p, info = fs.observe_update(p, MODEL, z, jnp.arange(4), m, R)
        p = fs.resample_soft(p, k2, 0.5)
        return p, (info.log_marginal, fs.estimate(p)[0][:2])

    p, (lm, est) = jax.lax.scan(body, p, (jax.random.split(key, T), DU, ZS, MASK))
    nll = -jnp.sum(lm)
    mse = jnp.mean(jnp.sum((est - TRUTH[1:, :2]) ** 2, axis=1))
    return jnp.stack([nll, mse])


THETA0 = np.log(np.array([0.03, 0.03, 0.01, 0.06, 0.025]) ** 2)


@pytest.fixture(scope="module")
def grads():
    """Reverse-mode Jacobian and central differences at two step sizes.

    One compilation: the jitted ``jacrev`` also returns the loss values
    (``has_aux``), and the finite differences reuse it at perturbed inputs.
    """
    key = jax.random.PRNGKey(42)
    fn = jax.jit(jax.jacrev(lambda th: (losses(th, key),) * 2, has_aux=True))

    def value(th):
        return np.asarray(fn(jnp.asarray(th))[1])

    jac, v0 = fn(jnp.asarray(THETA0))
    jac, v0 = np.asarray(jac), np.asarray(v0)
    fd = {}
    for h in (1e-6, 1e-5):
        E = h * np.eye(5)
        fd[h] = np.stack([(value(THETA0 + E[i]) - value(THETA0 - E[i])) / (2 * h)
                          for i in range(5)], axis=1)  # (2 losses, 5 params)
    step = -1e-3 * jac[0] / np.linalg.norm(jac[0])  # downhill for the NLL
    return jac, fd, v0, value(THETA0 + step)


def test_gradients_finite_and_match_finite_differences(grads):
    jac, fd, value, _ = grads
    assert np.all(np.isfinite(value)) and np.all(np.isfinite(jac))
    assert np.all(np.abs(jac) > 1e-6), "every parameter should influence both losses"
    # Smoothness at this key: two step sizes agree (no ancestor index jumped).
    np.testing.assert_allclose(fd[1e-6], fd[1e-5], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(jac, fd[1e-6], rtol=1e-6, atol=1e-6)


def test_nll_gradient_points_downhill(grads):
    """A small step against the NLL gradient lowers the NLL (same key)."""
    _, _, value, moved = grads
    assert moved[0] < value[0]
