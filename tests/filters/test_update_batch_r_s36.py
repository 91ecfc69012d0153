"""``ekf.update_batch`` in its joint mode with a traced ``R`` holding a negative variance on a used
row: ``NOT_PSD`` and the prior kept, as the sequential mode and ``ekf.update`` (via
``gaussian.negative_variance``).  Before: the joint mode used it with status 0 whenever ``S``
still factored and the posterior variance, ``-1e-9``, was within the finaliser's rounding
tolerance (here the joint ``S = diag(1.1, 1 - 1e-9)``): status 0, accepted, the mean moved."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import errors
from jaxslam.filters import ekf
from jaxslam.filters.gaussian import Gaussian


def _h(x, sel):
    return jnp.array([sel @ x])  # measurement i observes coordinate i: S stays diagonal


PRIOR = Gaussian(jnp.array([0.0, 0.0], jnp.float64), jnp.eye(2, dtype=jnp.float64))  # (x64: conftest)
ZS = jnp.array([[0.3], [-0.2]], jnp.float64)
SEL = jnp.eye(2, dtype=jnp.float64)


def _batch(R, masks=None, sequential=False):
    f = jax.jit(lambda R: ekf.update_batch(PRIOR, ZS, _h, R, SEL, masks=masks, sequential=sequential))
    return f(R)


def test_joint_mode_flags_a_negative_variance_on_a_used_row_and_keeps_the_prior():
    R = jnp.array([[[0.1]], [[-1e-9]]])  # measurement 1's variance is negative
    post, info = _batch(R)
    assert np.asarray(info.status).tolist() == [errors.NOT_PSD, errors.NOT_PSD]  # a joint failure: every used one
    assert np.asarray(info.accepted).tolist() == [False, False]
    np.testing.assert_array_equal(post.mean, PRIOR.mean)
    np.testing.assert_array_equal(post.cov, PRIOR.cov)
    assert float(info.nis[1]) == 0.0  # as ekf.update: its NIS is 0 (never GATED)
    # the sequential mode says NOT_PSD on the same measurement
    _, seq = _batch(R, sequential=True)
    assert int(seq.status[1]) & errors.NOT_PSD


def test_joint_mode_flags_a_shared_negative_variance():
    post, info = _batch(jnp.array([[-1e-9]]))
    assert np.asarray(info.status).tolist() == [errors.NOT_PSD, errors.NOT_PSD]
    np.testing.assert_array_equal(post.mean, PRIOR.mean)


def test_a_negative_variance_on_a_masked_measurement_changes_nothing():
    masks = jnp.array([True, False])
    post_neg, info_neg = _batch(jnp.array([[[0.1]], [[-1e-9]]]), masks=masks)
    post_pos, info_pos = _batch(jnp.array([[[0.1]], [[0.5]]]), masks=masks)
    assert np.asarray(info_neg.status).tolist() == [0, 0]
    assert bool(info_neg.accepted[0])
    for a, b in zip(jax.tree.leaves((post_neg, info_neg)), jax.tree.leaves((post_pos, info_pos))):
        np.testing.assert_array_equal(a, b)  # bit for bit: the unused R is not read
